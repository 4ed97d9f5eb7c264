"""The mapping pipeline: reference images with known poses -> EGM (+ real-patch descriptors).

    features (SIFT keypoints, canonical patches, JAX descriptor)      vrs_jax.features
    -> covisible pairs from the known poses                           egm.pairs
    -> matches, verified by the known epipolar geometry               egm.triangulate
    -> 3D points triangulated with the known poses (pycolmap)         egm.triangulate
    -> per image the keypoints with a 3D point, chosen by track length and spread
    -> VLAD vocabulary and global descriptors                         egm.retrieval
    -> EGM, with the real-patch descriptors of the kept keypoints

The real-patch descriptors (the paper's "15x15 (GT)" row, the hierarchical baseline) are the
very descriptors computed for matching here, by the same ``extract_patches -> describe`` path
the rendered patches take; a map stores them apart from its EGM (:mod:`vrs_jax.maps`), so the
VRS map's size never includes them.
"""

from __future__ import annotations

import dataclasses
import time
import warnings

import numpy as np
from tqdm.auto import tqdm

from vrs_jax.data.images import read_gray
from vrs_jax.data.scene import Scene
from vrs_jax.egm import map as egm_map
from vrs_jax.egm.map import EGM, make_egm
from vrs_jax.egm.pairs import PairsConfig, estimate_depth_ranges, reference_pairs
from vrs_jax.egm.retrieval import RetrievalConfig, global_descriptors, learn_vocabulary
from vrs_jax.egm.triangulate import (
    Triangulation,
    TriangulationConfig,
    match_pairs,
    subset_points,
    triangulate_known_poses,
)
from vrs_jax.errors import VrsError
from vrs_jax.features import extract as feat
from vrs_jax.features.keypoints import grid_round_robin


@dataclasses.dataclass(frozen=True)
class EGMConfig:
    """Everything that defines how a map is built (single source of truth)."""

    name: str = "paper"
    # Detector / patch / descriptor (features.extract's named configs).
    features: feat.FeatureConfig = feat.get_config("paper")
    pairs: PairsConfig = PairsConfig()
    triangulation: TriangulationConfig = TriangulationConfig()
    retrieval: RetrievalConfig = RetrievalConfig()
    # Keypoints kept per image in the EGM (those with a 3D point, best first). Half the
    # detection budget: about the number of triangulated keypoints per image in practice,
    # and what the localizer renders per retrieved image (K_max * P^2 rays).
    k_max: int = 1024
    # Spread of the kept keypoints: round-robin over (columns, rows) cells, longest tracks
    # first within a cell, so that a textured corner does not take the whole budget (PnP is
    # better conditioned with points spread over the image).
    selection_grid: tuple[int, int] = (8, 8)


CONFIGS: dict[str, EGMConfig] = {
    "paper": EGMConfig(),
    # Laptop CPU: 1024 keypoints per image detected, 256 kept; VLAD of 32 visual words over
    # the descriptors PCA-whitened to 32-D (1024-D, 1 KB per image as int8, the size of the
    # 8 raw 128-D words before): the global descriptors, which both the VRS and the baseline
    # map carry, stay below the keypoints in size. On the phone walk's held-out leg the raw
    # 8 words retrieved, for 12 of 50 frames, no reference seeing half the points of the
    # best one (GT covisibility; 7 with 16 raw words, 5 with these); real patches there went
    # from 32% / 52% to 38% / 58% within 1% / 2%, rendered ones from 12% / 30% to 20% / 36%
    # (README, "Retrieval on whitened descriptors"). The small scenes find a covisible
    # reference either way, but about one retrieved reference in five changes there, and
    # lego and fern each lost queries at the 1% threshold in render mode (same section).
    "cpu-small": EGMConfig(name="cpu-small", features=feat.get_config("cpu-small"),
                           k_max=256, retrieval=RetrievalConfig(n_words=32, local_dim=32)),
    # Unit tests: tiny budgets, small patches, a small vocabulary.
    "test": EGMConfig(name="test", features=feat.get_config("test"), k_max=64,
                      pairs=PairsConfig(num_neighbors=6),
                      retrieval=RetrievalConfig(n_words=8, kmeans_iters=10)),
}


def get_config(name: str) -> EGMConfig:
    """Named EGMConfig; VrsError listing the names for an unknown one."""
    if name not in CONFIGS:
        raise VrsError(f"unknown EGM config {name!r}; choose from {sorted(CONFIGS)}")
    return CONFIGS[name]


# ----------------------------------------------------------------------------- stages


def extract_reference_features(scene: Scene, cfg: feat.FeatureConfig, progress: bool = True
                               ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Keypoints [K_i, 4] and descriptors [K_i, D] of every image (warns for empty images)."""
    kps, descs, empty = [], [], []
    for i in tqdm(range(len(scene)), desc="features", unit="img", disable=not progress):
        # RGBA images (NeRF synthetic) are composited on the scene's background, as the
        # NeRF sees them; grey = the descriptor's luma, as for rendered patches
        gray = read_gray(scene.image_paths[i], size=tuple(int(s) for s in scene.sizes[i]),
                         background=scene.background)
        kp, d = feat.extract_features(gray, cfg)
        kps.append(kp)
        descs.append(d)
        if len(kp) == 0:
            empty.append(scene.names[i])
    if empty:
        warnings.warn(f"{len(empty)} reference images have no keypoints (blank or "
                      f"textureless?): {', '.join(empty[:5])}" + (" ..." if len(empty) > 5 else ""),
                      stacklevel=2)
    return kps, descs


def select_keypoints(kp: np.ndarray, point_of_kp: np.ndarray, track_len: np.ndarray,
                     errors: np.ndarray, size, k_max: int, grid: tuple[int, int]) -> np.ndarray:
    """Indices of the keypoints an image keeps in the EGM, best first.

    Args:
      kp: [K, 4] keypoints; point_of_kp: [K] point index or -1; track_len, errors: [M] per
      point; size: (w, h); k_max: budget; grid: (columns, rows) for spreading.
    Returns:
      [k <= k_max] int64 indices into kp: keypoints with a 3D point, ranked by (rank of the
      keypoint within its grid cell, longer track, smaller error) -- every cell gives its
      best keypoint before any gives its second.
    """
    cand = np.flatnonzero(point_of_kp >= 0)
    if len(cand) == 0:
        return cand
    p = point_of_kp[cand]
    order = cand[np.lexsort((errors[p], -track_len[p]))]  # best first
    pri = grid_round_robin(kp[order, :2], float(size[0]), float(size[1]), grid)
    return order[pri[:k_max]]


def _assemble(scene: Scene, kps, descs, tri: Triangulation, cfg: EGMConfig):
    """Per-image kept keypoints, point links and real-patch descriptors; points
    that no kept keypoint links are dropped."""
    sel = [select_keypoints(kps[i], tri.point_of_kp[i], tri.track_lengths, tri.errors,
                            scene.sizes[i], cfg.k_max, cfg.selection_grid)
           for i in range(len(scene))]
    used = np.zeros(tri.num_points, bool)
    for i, s in enumerate(sel):
        used[tri.point_of_kp[i][s]] = True
    tri = subset_points(tri, used)  # reindexes point_of_kp
    kp_rows = [kps[i][s] for i, s in enumerate(sel)]
    pi_rows = [tri.point_of_kp[i][s] for i, s in enumerate(sel)]
    ld_rows = [descs[i][s] for i, s in enumerate(sel)]
    return tri, kp_rows, pi_rows, ld_rows


def build_egm(scene: Scene, cfg: EGMConfig = EGMConfig(), progress: bool = True,
              verbose: bool = False) -> tuple[EGM, dict]:
    """Build the EGM of a scene's reference images (their poses are taken as known).

    Args:
      scene: a Scene; its reference images (``~is_query``) with poses are mapped.
      cfg: :class:`EGMConfig`.
      progress: tqdm progress bars.
      verbose: keep COLMAP's log lines.
    Returns:
      (egm, stats): the EGM with its real-patch descriptors (``local_desc``); stats holds
      counts, mean track length, median reprojection error and timings.
    Raises:
      VrsError if no reference image has a pose, or no 3D point survives.
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    refs = scene.references()
    if len(refs) == 0:
        raise VrsError("the scene has no reference images", scene.root)
    if not refs.has_pose.all():
        missing = int((~refs.has_pose).sum())
        if missing == len(refs):
            raise VrsError("no reference image has a pose; build poses with SfM first "
                           "(vrs_jax.egm.sfm, or --format images)", scene.root)
        warnings.warn(f"{missing} reference images have no pose and are left out of the map",
                      stacklevel=2)
        refs = refs.subset(refs.has_pose)

    t0 = time.perf_counter()
    kps, descs = extract_reference_features(refs, cfg.features, progress)
    timings["features_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ranges, range_source = estimate_depth_ranges(refs, cfg.pairs)
    pairs, _ = reference_pairs(refs, cfg.pairs, ranges)
    timings["pairs_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    with tqdm(total=len(pairs), desc="matching", unit="pair", disable=not progress) as bar:
        matches, mstats = match_pairs(refs, kps, descs, pairs, cfg.triangulation, bar.update)
    timings["matching_s"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an empty result is reported below, as an error
        tri = triangulate_known_poses(
            refs, kps, matches, cfg.triangulation,
            depth_ranges=None if range_source == "extent" else ranges, verbose=verbose)
    timings["triangulation_s"] = time.perf_counter() - t0
    if tri.num_points == 0:
        raise VrsError(f"triangulation produced no 3D points from {len(refs)} reference images "
                       f"({len(pairs)} pairs, {mstats['verified_matches']} verified matches): "
                       "too little overlap or baseline between the references", scene.root)

    t0 = time.perf_counter()
    tri, kp_rows, pi_rows, ld_rows = _assemble(refs, kps, descs, tri, cfg)
    vocab = learn_vocabulary(descs, cfg.retrieval)
    gdesc = global_descriptors(descs, None, vocab)
    egm = make_egm(tri.points3d, refs.R, refs.t, refs.K, refs.dist, refs.sizes, kp_rows,
                   pi_rows, gdesc, vocab, refs.names, k_max=cfg.k_max, local_desc=ld_rows)
    timings["assembly_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start

    err = egm_map.reprojection_errors(egm)
    counts = np.asarray(egm.kp_mask).sum(1)
    no_points = [refs.names[i] for i in np.flatnonzero(counts == 0)]
    if no_points:
        warnings.warn(f"{len(no_points)} reference images have no 3D point in the map: "
                      + ", ".join(no_points[:5]) + (" ..." if len(no_points) > 5 else ""),
                      stacklevel=2)
    stats = {
        "config": cfg.name,
        "reference_images": len(refs),
        "images_without_points": len(no_points),
        "points": egm.num_points,
        # observations per point kept in the EGM (<= the triangulated track when K_max cuts)
        "mean_track_length": float(np.mean(np.bincount(
            np.asarray(egm.point_idx)[np.asarray(egm.kp_mask)], minlength=egm.num_points))),
        "mean_track_length_triangulated": float(np.mean(tri.track_lengths)),
        "median_reprojection_error_px": float(np.median(err)),
        "keypoints_per_image_mean": float(counts.mean()),
        "keypoints_detected_per_image_mean": float(np.mean([len(k) for k in kps])),
        "depth_range_source": range_source,
        **mstats,
        "points_triangulated": int(tri.stats.get("points_pycolmap", tri.num_points)),
        "points_outside_depth_range": int(tri.stats.get("points_outside_depth_range", 0)),
        "timings": timings,
    }
    return egm, stats


def format_stats(stats: dict) -> str:
    """A few human-readable lines of build statistics."""
    lines = [
        f"EGM (config {stats['config']}): "
        f"{stats['reference_images']} images, {stats['points']} points, mean track length "
        f"{stats['mean_track_length']:.2f}, median reprojection error "
        f"{stats['median_reprojection_error_px']:.3f} px, "
        f"{stats['keypoints_per_image_mean']:.0f} keypoints/image",
        "time: " + ", ".join(f"{k[:-2]} {v:.1f}s" for k, v in stats["timings"].items()),
    ]
    return "\n".join(lines)
