"""The COLMAP SIFT reference localizer: hierarchical structure-based localization, pycolmap only.

The row the accuracy figures are compared against, built the way a plain hloc/COLMAP
localizer is:

Map (:func:`build_sift_map`, reference images with KNOWN poses):
  1. COLMAP SIFT (pycolmap's feature extractor, default SIFT options) on every reference
     image, read exactly as the rest of vrs-jax reads it (``images.read_image`` at
     ``scene.sizes``; RGBA images composited on ``scene.background``), converted to grey by
     COLMAP itself (``Bitmap.clone_as_grey``). Keypoints and descriptors go into a COLMAP
     database together with the scene's cameras (PINHOLE without distortion, OPENCV /
     FULL_OPENCV with it) and trivial rigs/frames.
  2. ``pycolmap.match_exhaustive``: COLMAP's SIFT matcher (ratio 0.8, distance 0.7, cross
     check) and two-view geometric verification of every pair.
  3. ``pycolmap.triangulate_points`` on a reconstruction that holds the known reference
     poses (kept fixed): COLMAP's point triangulator (triangulation, track merging and
     completion, bundle adjustment of the points only).
  Each map image keeps, per keypoint linked to a 3D point, its position, its uint8 SIFT
  descriptor and the index of its 3D point (``keep_unlinked`` keeps the other keypoints
  too, as hloc does).

Query (:func:`localize_sift`):
  1. SIFT on the query (same extractor).
  2. COLMAP's SIFT matching rule (ratio 0.8, distance 0.7, cross check) between the query
     and every map image (exhaustive over the map; fine for the ~100-image scenes of the
     benchmarks), computed with one BLAS product per map image (:func:`match_sift`, the
     same matches as pycolmap's CPU matcher, which is ~100x slower on these sizes; the
     ``matcher="colmap"`` option uses pycolmap's).
  3. Matches to keypoints with a 3D point become 2D-3D correspondences, each (query keypoint,
     3D point) pair once (:func:`unique_correspondences`; one keypoint matched to several 3D
     points keeps one correspondence per point, as hloc does).
  4. ``pycolmap.estimate_and_refine_absolute_pose``: LO-RANSAC (P3P, max error 12 px as
     hloc's default) and non-linear refinement with the query's known intrinsics. Fewer than
     ``min_inliers`` inliers, or no RANSAC model, is a failure: no pose (NaN R, t), which
     ``eval.metrics.pose_errors`` counts as an infinite error.

Imports only vrs_jax.data and vrs_jax.errors (plus pycolmap, numpy).
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path

import numpy as np
import pycolmap
from tqdm.auto import tqdm

from vrs_jax.data.images import read_image
from vrs_jax.data.readers.colmap import colmap_camera, quiet_pycolmap
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError

DESC_DIM = 128


@dataclasses.dataclass(frozen=True)
class SiftReferenceConfig:
    """Every setting of the SIFT reference (defaults: COLMAP's / hloc's)."""

    max_num_features: int = 8192  # COLMAP's default SIFT budget per image
    max_ratio: float = 0.8  # COLMAP SIFT matcher: Lowe's ratio test
    max_distance: float = 0.7  # COLMAP SIFT matcher: max descriptor distance (angle)
    cross_check: bool = True  # COLMAP SIFT matcher: mutual nearest neighbours
    # Query matching: "numpy" (COLMAP's SIFT matching rule on BLAS, the same matches as
    # pycolmap's CPU matcher, ~100x faster) or "colmap" (pycolmap.FeatureMatcher).
    matcher: str = "numpy"
    ransac_max_error_px: float = 12.0  # hloc's default for localization
    min_inliers: int = 12  # fewer RANSAC inliers = failure (as vrs_jax.localize.pnp)
    keep_unlinked: bool = False  # keep map keypoints without a 3D point (hloc matches them)
    num_threads: int = -1  # COLMAP threads (-1: all cores)
    seed: int = 0  # COLMAP's RANSAC / triangulation randomness: repeatable runs

    def __post_init__(self) -> None:
        if self.max_num_features < 1:
            raise VrsError(f"max_num_features must be >= 1, got {self.max_num_features}")
        if not 0.0 < self.max_ratio <= 1.0:
            raise VrsError(f"max_ratio must be in (0, 1], got {self.max_ratio}")
        if self.ransac_max_error_px <= 0:
            raise VrsError(f"ransac_max_error_px must be > 0, got {self.ransac_max_error_px}")
        if self.matcher not in ("numpy", "colmap"):
            raise VrsError(f"matcher must be 'numpy' or 'colmap', got {self.matcher!r}")
        if self.min_inliers < 0:
            raise VrsError(f"min_inliers must be >= 0, got {self.min_inliers}")


@dataclasses.dataclass
class SiftMap:
    """The reference map: per map image its kept keypoints, and the 3D points.

    Attributes:
      names: [M] reference image names.
      K: [M, 3, 3], dist: [M, 5], sizes: [M, 2]: their cameras (as the Scene).
      R: [M, 3, 3], t: [M, 3]: their known world-to-camera poses.
      keypoints: M arrays [n_i, 2] float32 pixel positions (COLMAP convention, as K).
      descriptors: M arrays [n_i, 128] uint8 COLMAP SIFT descriptors.
      point_idx: M arrays [n_i] int32: row of ``points3d`` of each keypoint (-1: none).
      points3d: [P, 3] float64 triangulated points (world).
      stats: build statistics (keypoints extracted, verified pairs, tracks, seconds).
    """

    names: list[str]
    K: np.ndarray
    dist: np.ndarray
    sizes: np.ndarray
    R: np.ndarray
    t: np.ndarray
    keypoints: list[np.ndarray]
    descriptors: list[np.ndarray]
    point_idx: list[np.ndarray]
    points3d: np.ndarray
    stats: dict

    @property
    def num_images(self) -> int:
        return len(self.names)


@dataclasses.dataclass
class SiftResult:
    """One query's outcome.

    Attributes:
      name: query image name.
      R: [3, 3], t: [3] estimated world-to-camera pose (NaN when ``success`` is False).
      success: a RANSAC model with at least ``min_inliers`` inliers.
      n_inliers: RANSAC inliers among the distinct 2D-3D correspondences.
      n_inlier_keypoints: distinct query keypoints among them.
      n_correspondences: distinct (query keypoint, 3D point) pairs.
      n_matches: query-to-map-image matches (all map images, with or without a 3D point).
      n_keypoints: SIFT keypoints of the query.
      timing: seconds of ``read`` (image I/O), ``extract``, ``match`` (matching, lifting,
        de-duplication), ``pose`` (RANSAC + refinement) and ``total``.
    """

    name: str
    R: np.ndarray
    t: np.ndarray
    success: bool
    n_inliers: int
    n_inlier_keypoints: int
    n_correspondences: int
    n_matches: int
    n_keypoints: int
    timing: dict[str, float]


# ----------------------------------------------------------------------------- pycolmap glue


def _extraction_options(cfg: SiftReferenceConfig) -> pycolmap.FeatureExtractionOptions:
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = cfg.num_threads
    opts.sift.max_num_features = cfg.max_num_features
    return opts


def _matching_options(cfg: SiftReferenceConfig) -> pycolmap.FeatureMatchingOptions:
    opts = pycolmap.FeatureMatchingOptions()
    opts.num_threads = cfg.num_threads
    opts.sift.max_ratio = cfg.max_ratio
    opts.sift.max_distance = cfg.max_distance
    opts.sift.cross_check = cfg.cross_check
    return opts


def grey_image(path: str | Path, size, background=None) -> np.ndarray:
    """[H, W] uint8 grey image as COLMAP sees it: ``read_image`` (RGBA composited on
    ``background``, resized to ``size`` = (width, height)) quantised to 8 bits, then
    COLMAP's own grey conversion."""
    rgb = read_image(path, background, tuple(int(s) for s in size))
    u8 = np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(pycolmap.Bitmap.from_array(u8).clone_as_grey().to_array())


def _extract(extractor, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """SIFT of a grey image: keypoints [n, 4] float32 (x, y, scale, orientation), descriptors
    [n, 128] uint8."""
    kp, desc = extractor.extract_from_uint8_array(grey)
    kpm = np.asarray(pycolmap.keypoints_to_matrix(kp), np.float32).reshape(-1, 4)
    return kpm, np.asarray(desc.data, np.uint8).reshape(-1, DESC_DIM)


def _descriptors(d: np.ndarray) -> pycolmap.FeatureDescriptors:
    return pycolmap.FeatureDescriptors(pycolmap.FeatureExtractorType.SIFT,
                                       np.ascontiguousarray(d, np.uint8).reshape(-1, DESC_DIM))


def _check_references(refs: Scene) -> None:
    if len(refs) < 2:
        raise VrsError(f"the SIFT reference map needs at least 2 reference images, got "
                       f"{len(refs)}", refs.root)
    for i in range(len(refs)):
        where = refs.image_paths[i]
        if not refs.has_pose[i]:
            raise VrsError("reference image without a pose", where)
        K, R, t = refs.K[i], refs.R[i], refs.t[i]
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise VrsError("pose or intrinsics contain NaN/inf", where)
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-5 or np.linalg.det(R) < 0:
            raise VrsError("pose rotation is not a rotation matrix", where)


# ----------------------------------------------------------------------------- map


def build_sift_map(scene: Scene, work_dir: str | Path,
                   cfg: SiftReferenceConfig = SiftReferenceConfig(), progress: bool = True,
                   verbose: bool = False) -> SiftMap:
    """Build the SIFT reference map of the scene's reference images (``~scene.is_query``).

    Args:
      scene: the scene; its query images are left out.
      work_dir: folder for COLMAP's database and the triangulated model (replaced).
      cfg: :class:`SiftReferenceConfig`.
      progress: tqdm bar over the images; verbose: keep COLMAP's log lines.
    Raises:
      VrsError: fewer than 2 references, a reference without a valid pose, an unreadable
        image, or COLMAP failing on the input.
    """
    refs = scene.subset(~np.asarray(scene.is_query, bool))
    _check_references(refs)
    work = Path(work_dir)
    db_path, model_dir = work / "database.db", work / "model"
    if db_path.exists():
        db_path.unlink()
    if model_dir.exists():
        shutil.rmtree(model_dir)
    model_dir.mkdir(parents=True)
    t_start = time.perf_counter()
    n = len(refs)
    with quiet_pycolmap(verbose, errors_only=True):
        pycolmap.set_random_seed(cfg.seed)
        extractor = pycolmap.FeatureExtractor.create(_extraction_options(cfg),
                                                     pycolmap.Device.cpu)
        rec = pycolmap.Reconstruction()
        all_kp, all_desc = [], []
        db = pycolmap.Database.open(db_path)
        try:
            for i in tqdm(range(n), desc="sift map", unit="img", disable=not progress):
                cam = colmap_camera(refs.K[i], refs.dist[i], refs.sizes[i], i + 1)
                kp, desc = _extract(extractor, grey_image(refs.image_paths[i], refs.sizes[i],
                                                          refs.background))
                rec.add_camera_with_trivial_rig(cam)
                image = pycolmap.Image(name=refs.names[i], keypoints=kp[:, :2].astype(np.float64),
                                       camera_id=i + 1, image_id=i + 1)
                pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(refs.R[i], np.float64)),
                                        np.asarray(refs.t[i], np.float64))
                rec.add_image_with_trivial_frame(image, pose)
                db.write_camera(cam, use_camera_id=True)
                db.write_rig(rec.rigs[i + 1], use_rig_id=True)
                db.write_frame(rec.frames[i + 1], use_frame_id=True)
                db.write_image(pycolmap.Image(name=refs.names[i], camera_id=i + 1,
                                              image_id=i + 1), use_image_id=True)
                db.write_keypoints(i + 1, kp)
                db.write_descriptors(i + 1, _descriptors(desc))
                all_kp.append(kp)
                all_desc.append(desc)
        finally:
            db.close()
        t_extract = time.perf_counter()
        verification = pycolmap.TwoViewGeometryOptions()
        verification.ransac.random_seed = cfg.seed
        try:
            pycolmap.match_exhaustive(db_path, matching_options=_matching_options(cfg),
                                      verification_options=verification,
                                      device=pycolmap.Device.cpu)
        except (RuntimeError, ValueError) as e:
            raise VrsError(f"pycolmap matching failed: {e}", db_path) from e
        db = pycolmap.Database.open(db_path)
        n_pairs, n_inlier_matches = db.num_verified_image_pairs(), db.num_inlier_matches()
        db.close()
        t_match = time.perf_counter()
        options = pycolmap.IncrementalPipelineOptions()
        options.num_threads = cfg.num_threads
        options.random_seed = cfg.seed
        options.triangulation.random_seed = cfg.seed
        options.extract_colors = False
        try:
            out = pycolmap.triangulate_points(rec, db_path, work, model_dir, options=options)
        except (RuntimeError, ValueError) as e:
            raise VrsError(f"pycolmap triangulation failed: {e}", db_path) from e
    t_tri = time.perf_counter()

    ids = np.asarray(sorted(out.points3D.keys()), np.int64)
    points3d = (np.stack([out.points3D[int(p)].xyz for p in ids]) if len(ids)
                else np.zeros((0, 3)))
    keypoints, descriptors, point_idx = [], [], []
    for i in range(n):
        image = out.images[i + 1]
        link = np.full(len(all_kp[i]), -1, np.int32)
        obs = np.asarray(image.get_observation_point2D_idxs(), np.int64)
        if len(obs):
            pid = np.asarray([image.points2D[int(k)].point3D_id for k in obs], np.int64)
            link[obs] = np.searchsorted(ids, pid).astype(np.int32)
        keep = np.ones(len(link), bool) if cfg.keep_unlinked else link >= 0
        keypoints.append(np.ascontiguousarray(all_kp[i][keep, :2]))
        descriptors.append(np.ascontiguousarray(all_desc[i][keep]))
        point_idx.append(link[keep])
    n_obs = sum(int((p >= 0).sum()) for p in point_idx)
    stats = {"n_images": n, "n_keypoints_extracted": int(sum(len(k) for k in all_kp)),
             "n_keypoints_kept": int(sum(len(k) for k in keypoints)),
             "n_observations": n_obs, "n_points3d": int(len(ids)),
             "mean_track_length": n_obs / max(len(ids), 1),
             "n_verified_pairs": int(n_pairs), "n_inlier_matches": int(n_inlier_matches),
             "extract_s": t_extract - t_start, "match_s": t_match - t_extract,
             "triangulate_s": t_tri - t_match, "total_s": t_tri - t_start}
    return SiftMap(list(refs.names), np.asarray(refs.K, np.float64),
                   np.asarray(refs.dist, np.float64), np.asarray(refs.sizes),
                   np.asarray(refs.R, np.float64), np.asarray(refs.t, np.float64),
                   keypoints, descriptors, point_idx, points3d, stats)


def sift_map_bytes(sift_map: SiftMap) -> dict[str, int]:
    """Bytes of the map as the field stores it (raw arrays, no container overhead).

    Per kept keypoint: its uint8 SIFT descriptor (128 B), its position (2 float32) and its
    3D point index (int32); per 3D point its position (3 float32); per map image its pose
    (quaternion + translation, 7 float32) and camera (its COLMAP parameters, float32).
    Returns those parts, ``total``, and ``n_keypoints`` / ``n_points3d`` for reference.
    """
    n_kp = int(sum(len(k) for k in sift_map.keypoints))
    cam_params = sum(len(colmap_camera(k, d, s, 1).params)
                     for k, d, s in zip(sift_map.K, sift_map.dist, sift_map.sizes, strict=True))
    parts = {"descriptors": n_kp * DESC_DIM, "keypoints": n_kp * 2 * 4,
             "point_ids": n_kp * 4, "points3d": int(len(sift_map.points3d)) * 3 * 4,
             "poses": sift_map.num_images * 7 * 4, "cameras": int(cam_params) * 4}
    return {**parts, "total": int(sum(parts.values())), "n_keypoints": n_kp,
            "n_points3d": int(len(sift_map.points3d))}


# ----------------------------------------------------------------------------- query


def unique_correspondences(query_idx: np.ndarray, point_idx: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """Each (query keypoint, 3D point) pair once, sorted by keypoint then point.

    Args:
      query_idx: [N] int query keypoint of each lifted match.
      point_idx: [N] int 3D point of each lifted match.
    Returns:
      (query_idx [M], point_idx [M]) int64, M <= N distinct pairs. A keypoint matched to
      several 3D points keeps one pair per point.
    """
    q = np.asarray(query_idx, np.int64).reshape(-1)
    p = np.asarray(point_idx, np.int64).reshape(-1)
    if q.shape != p.shape:
        raise ValueError(f"query_idx {q.shape} and point_idx {p.shape} differ")
    pairs = np.unique(np.stack([q, p], axis=1), axis=0) if len(q) else np.zeros((0, 2),
                                                                                   np.int64)
    return pairs[:, 0], pairs[:, 1]


def _one_way(sim: np.ndarray, axis: int, max_ratio: float, max_distance: float
             ) -> np.ndarray:
    """Best match along ``axis`` of ``sim`` [n1, n2] (cosines) for each index of the other
    axis, passing COLMAP's distance and ratio tests on angles; -1 where none.

    As COLMAP's brute-force matcher, the second best similarity is at least 0 (a lone
    candidate's second best is at 90 deg) and a tie with the best fails the ratio test.
    """
    other = 1 - axis
    if sim.shape[axis] == 0:
        return np.full(sim.shape[other], -1, np.int64)
    best = np.argmax(sim, axis=axis)
    idx = np.arange(sim.shape[other])
    at = (idx, best) if axis == 1 else (best, idx)
    b1 = sim[at]
    masked = sim.copy()
    masked[at] = -np.inf
    b2 = np.maximum(masked.max(axis=axis), 0.0)
    a1, a2 = np.arccos(np.clip(b1, -1.0, 1.0)), np.arccos(np.clip(b2, -1.0, 1.0))
    return np.where((a1 <= max_distance) & (a1 < max_ratio * a2), best, -1)


def match_sift(desc1: np.ndarray, desc2: np.ndarray, max_ratio: float = 0.8,
               max_distance: float = 0.7, cross_check: bool = True) -> np.ndarray:
    """COLMAP's SIFT matching rule (its brute-force CPU matcher) with one BLAS product.

    Descriptors are COLMAP's uint8 SIFT (unit vectors times 512). A pair (i, j) matches when
    j is i's nearest neighbour with angle <= ``max_distance`` (radians) and angle <
    ``max_ratio`` x the second nearest's; with ``cross_check``, also i is j's.

    Args:
      desc1: [n1, 128] uint8 (or those values as float32); desc2: [n2, 128] likewise.
    Returns:
      [K, 2] int64 (row in desc1, row in desc2), sorted by the first.
    """
    a = np.asarray(desc1, np.float32).reshape(-1, DESC_DIM)
    b = np.asarray(desc2, np.float32).reshape(-1, DESC_DIM)
    sim = (a @ b.T) * np.float32(1.0 / 512.0**2)
    m12 = _one_way(sim, 1, max_ratio, max_distance)
    i = np.flatnonzero(m12 >= 0)
    if cross_check and len(i):
        m21 = _one_way(sim, 0, max_ratio, max_distance)
        i = i[m21[m12[i]] == i]
    return np.stack([i, m12[i]], axis=1).astype(np.int64)


def _failed(name: str, timing: dict, **counts) -> SiftResult:
    nan = np.full((3, 3), np.nan), np.full(3, np.nan)
    base = dict(n_inliers=0, n_inlier_keypoints=0, n_correspondences=0, n_matches=0,
                n_keypoints=0)
    base.update(counts)
    return SiftResult(name, nan[0], nan[1], False, timing=timing, **base)


class _Localizer:
    """pycolmap objects shared by the queries: extractor, matcher, the map's descriptors."""

    def __init__(self, sift_map: SiftMap, cfg: SiftReferenceConfig):
        self.map, self.cfg = sift_map, cfg
        self.extractor = pycolmap.FeatureExtractor.create(_extraction_options(cfg),
                                                          pycolmap.Device.cpu)
        self.matcher = pycolmap.FeatureMatcher.create(_matching_options(cfg),
                                                      pycolmap.Device.cpu)
        self.map_desc = ([_descriptors(d) for d in sift_map.descriptors]
                         if cfg.matcher == "colmap" else None)
        self.map_float = [np.asarray(d, np.float32) for d in sift_map.descriptors]
        self.est = pycolmap.AbsolutePoseEstimationOptions()
        self.est.ransac.max_error = cfg.ransac_max_error_px
        self.est.ransac.random_seed = cfg.seed
        self.ref = pycolmap.AbsolutePoseRefinementOptions()

    def __call__(self, name: str, grey: np.ndarray, K: np.ndarray, dist: np.ndarray,
                 size, read_s: float = 0.0) -> SiftResult:
        """Localize one [H, W] uint8 grey query image with intrinsics K [3, 3], dist [5]."""
        t0 = time.perf_counter()
        kp, desc = _extract(self.extractor, np.ascontiguousarray(grey, np.uint8))
        t1 = time.perf_counter()
        qd = _descriptors(desc) if self.cfg.matcher == "colmap" else None
        q_all, p_all, n_matches = [], [], 0
        if len(kp):
            q_float = np.asarray(desc, np.float32)
            for j, md in enumerate(self.map_float):
                if not len(md):
                    continue
                if qd is None:
                    m = match_sift(q_float, md, self.cfg.max_ratio, self.cfg.max_distance,
                                   self.cfg.cross_check)
                else:
                    m = np.asarray(self.matcher.match(None, qd, None, self.map_desc[j]),
                                   np.int64).reshape(-1, 2)
                n_matches += len(m)
                pid = self.map.point_idx[j][m[:, 1]]
                q_all.append(m[pid >= 0, 0])
                p_all.append(pid[pid >= 0])
        q_idx, p_idx = unique_correspondences(
            np.concatenate(q_all) if q_all else np.zeros(0, np.int64),
            np.concatenate(p_all) if p_all else np.zeros(0, np.int64))
        t2 = time.perf_counter()
        ret = None
        if len(q_idx) >= 4:
            ret = pycolmap.estimate_and_refine_absolute_pose(
                kp[q_idx, :2].astype(np.float64), self.map.points3d[p_idx],
                colmap_camera(K, dist, size, 1), self.est, self.ref)
        t3 = time.perf_counter()
        timing = {"read": read_s, "extract": t1 - t0, "match": t2 - t1, "pose": t3 - t2}
        timing["total"] = float(sum(timing.values()))
        counts = dict(n_correspondences=int(len(q_idx)), n_matches=int(n_matches),
                      n_keypoints=int(len(kp)))
        if ret is None:
            return _failed(name, timing, **counts)
        mask = np.asarray(ret["inlier_mask"], bool)
        n_inl = int(mask.sum())
        n_inl_kp = int(len(np.unique(q_idx[mask])))
        pose = ret["cam_from_world"]
        R = np.asarray(pose.rotation.matrix(), np.float64)
        t = np.asarray(pose.translation, np.float64)
        ok = n_inl >= self.cfg.min_inliers and np.all(np.isfinite(R)) and np.all(np.isfinite(t))
        if not ok:
            return _failed(name, timing, n_inliers=n_inl, n_inlier_keypoints=n_inl_kp, **counts)
        return SiftResult(name, R, t, True, n_inl, n_inl_kp, timing=timing, **counts)


def localize_sift(sift_map: SiftMap, queries: Scene,
                  cfg: SiftReferenceConfig = SiftReferenceConfig(), progress: bool = True,
                  verbose: bool = False) -> list[SiftResult]:
    """Localize every image of ``queries`` (e.g. ``scene.queries()``) against the map.

    Images are read as the map's were (``scene.sizes``, RGBA on ``scene.background``) with
    their own intrinsics. Returns one :class:`SiftResult` per image, in order; a query that
    cannot be localized is a failure (success False, NaN pose), never an exception.
    """
    with quiet_pycolmap(verbose, errors_only=True):
        pycolmap.set_random_seed(cfg.seed)
        loc = _Localizer(sift_map, cfg)
        out = []
        for i in tqdm(range(len(queries)), desc="sift localize", unit="query",
                      disable=not progress):
            t0 = time.perf_counter()
            grey = grey_image(queries.image_paths[i], queries.sizes[i], queries.background)
            out.append(loc(queries.names[i], grey, queries.K[i], queries.dist[i],
                           queries.sizes[i], read_s=time.perf_counter() - t0))
    return out


def result_arrays(results: list[SiftResult]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R [N, 3, 3], t [N, 3], success [N] bool) of a list of results (NaN where failed)."""
    if not results:
        return np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros(0, bool)
    return (np.stack([r.R for r in results]), np.stack([r.t for r in results]),
            np.asarray([r.success for r in results], bool))

