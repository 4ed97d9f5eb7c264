"""Matches between reference pairs, verified and triangulated with the KNOWN poses (pycolmap).

Pipeline (all host-side; the JAX matcher runs on fixed, padded shapes):

1. :func:`match_pairs` -- mutual nearest neighbours with Lowe's ratio test
   (:func:`vrs_jax.features.matching.match`) for every pair from :mod:`vrs_jax.egm.pairs`.
2. :func:`verify_matches` -- geometric verification against the known relative pose: the
   Sampson distance of each match to its epipolar line, in pixels. With poses given there is
   nothing to estimate (no RANSAC on F or E), and the known geometry rejects outliers better
   than an estimated one would.
3. :func:`triangulate_known_poses` -- COLMAP's point triangulator, driven through pycolmap: a
   ``Reconstruction`` with the known cameras and poses, a ``CorrespondenceGraph`` of the
   verified matches, and ``IncrementalTriangulator`` building tracks (transitive
   correspondences), triangulating them (LO-RANSAC over the track's views), completing and
   merging tracks; then ``ObservationManager`` filters by reprojection error, triangulation
   angle and track length. Everything pycolmap receives is validated here first, so that bad
   input raises :class:`~vrs_jax.errors.VrsError` instead of aborting inside COLMAP.
"""

from __future__ import annotations

import dataclasses
import warnings

import jax.numpy as jnp
import numpy as np
import pycolmap

from vrs_jax import geometry
from vrs_jax.data.readers.colmap import colmap_camera, quiet_pycolmap
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError
from vrs_jax.features.matching import match_jit
from vrs_jax.padding import padded_size


@dataclasses.dataclass(frozen=True)
class TriangulationConfig:
    """Matching, verification, triangulation and filtering thresholds."""

    # Lowe's ratio with the mutual check (features.matching's default 0.8): verification by
    # the known epipolar geometry removes most of what a permissive ratio lets through.
    ratio: float = 0.8
    mutual: bool = True
    # Epipolar (Sampson) distance in pixels for a match to count as verified. SIFT keypoints
    # are accurate to ~0.5 px; 2 px leaves room for dataset pose noise (7Scenes' KinectFusion
    # poses are off by a few pixels) while rejecting almost all wrong matches away from the
    # epipolar line.
    max_epipolar_px: float = 2.0
    # A pair with fewer verified matches is dropped: a handful of matches that happen to lie
    # near their epipolar lines is more likely chance than overlap (COLMAP uses 15 inliers).
    min_pair_matches: int = 10
    # COLMAP triangulator options (IncrementalTriangulatorOptions); the angle errors are the
    # maximum angular reprojection errors in degrees for creating / continuing a track (COLMAP's
    # defaults, 2 deg), and the merge/complete limits are in pixels (COLMAP's 4 px).
    create_max_angle_error: float = 2.0
    continue_max_angle_error: float = 2.0
    merge_max_reproj_error: float = 4.0
    complete_max_reproj_error: float = 4.0
    # Final filters. Reprojection error in pixels: 2 px keeps ~all correct points at SIFT
    # accuracy (the acceptance target is a median below 1 px). Triangulation angle: COLMAP's
    # 1.5 deg; below it depth is poorly constrained. Track length 2 keeps two-view points,
    # which sparse scenes (a few references per place) need; raise it for dense captures.
    max_reproj_error: float = 2.0
    min_tri_angle_deg: float = 1.5
    min_track_length: int = 2
    # Plausible depths: when each image's depth range (near, far) is known (from bounds,
    # depth maps or sparse points, see pairs.estimate_depth_ranges), a point whose depth in
    # any observing image lies outside [near / depth_margin, far * depth_margin] is dropped.
    # It catches the "stationary" false matches of tiny baselines (JPEG block artefacts at
    # the same pixel in consecutive frames triangulate a few mm in front of the camera).
    # None disables the check.
    depth_margin: float | None = 3.0
    # Seed of COLMAP's LO-RANSAC in the triangulator (repeatable maps).
    seed: int = 0


@dataclasses.dataclass
class Triangulation:
    """3D points with their tracks (host structure; the EGM is built from it).

    Attributes:
      points3d: [M, 3] float64 world points.
      errors: [M] float64 mean reprojection error (pixels) over the track.
      track_lengths: [M] int64 number of observations.
      tri_angles: [M] float64 largest triangulation angle (radians) between the track's views.
      obs_image: [O] int64 image index (into the scene given) of every observation.
      obs_kp: [O] int64 keypoint index in that image.
      obs_point: [O] int64 point index.
      obs_errors: [O] float64 reprojection error of every observation (pixels).
      point_of_kp: [N] arrays [K_i] int64: point index of each keypoint, -1 if none.
      stats: counters (pairs, raw and verified matches, ...).
    """

    points3d: np.ndarray
    errors: np.ndarray
    track_lengths: np.ndarray
    tri_angles: np.ndarray
    obs_image: np.ndarray
    obs_kp: np.ndarray
    obs_point: np.ndarray
    obs_errors: np.ndarray
    point_of_kp: list[np.ndarray]
    stats: dict

    @property
    def num_points(self) -> int:
        return len(self.points3d)


# ----------------------------------------------------------------------------- matching


def _pad(desc: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """[K, D] -> ([n, D] zero-padded, [n] mask)."""
    k, d = desc.shape
    out = np.zeros((n, d), np.float32)
    out[:k] = desc[:n]
    mask = np.zeros(n, bool)
    mask[:min(k, n)] = True
    return out, mask


def match_pair(desc_i: np.ndarray, desc_j: np.ndarray, cfg: TriangulationConfig,
               pad: int | None = None) -> np.ndarray:
    """Mutual-NN + ratio matches of two images: [m, 2] int64 (keypoint in i, keypoint in j).

    Descriptors are padded to ``pad`` rows (default: a power of two) so that the jitted
    matcher compiles once per padded size.
    """
    if len(desc_i) == 0 or len(desc_j) == 0:
        return np.zeros((0, 2), np.int64)
    n = pad or padded_size(max(len(desc_i), len(desc_j)))
    di, mi = _pad(desc_i, n)
    dj, mj = _pad(desc_j, n)
    idx, valid, _ = match_jit(jnp.asarray(di), jnp.asarray(mi), jnp.asarray(dj),
                              jnp.asarray(mj), cfg.ratio, mutual=cfg.mutual)
    idx, valid = np.asarray(idx), np.asarray(valid)
    q = np.flatnonzero(valid)
    return np.stack([q, idx[q]], axis=1).astype(np.int64)


def sampson_errors(uv1: np.ndarray, uv2: np.ndarray, K1, dist1, R1, t1, K2, dist2, R2, t2
                   ) -> np.ndarray:
    """Sampson distance (pixels) of correspondences to the known epipolar geometry.

    Args:
      uv1, uv2: [M, 2] pixel coordinates in images 1 and 2. K: [3, 3], dist: [5] or None,
      R, t: world-to-camera poses.
    Returns:
      [M] first-order distance to the epipolar constraint, computed in normalised
      (undistorted) coordinates with E = [t]x R of camera 2 relative to camera 1, then scaled
      to pixels by the mean focal length of the two cameras.
    """
    x1 = geometry.unproject(np.asarray(K1, np.float64), np.asarray(uv1, np.float64), dist1)
    x2 = geometry.unproject(np.asarray(K2, np.float64), np.asarray(uv2, np.float64), dist2)
    R = R2 @ R1.T
    t = t2 - R @ t1
    nt = np.linalg.norm(t)
    if nt < 1e-12:  # same centre: no epipolar geometry, every match is consistent
        return np.zeros(len(x1))
    E = geometry.skew(t / nt) @ R
    Ex1 = x1 @ E.T
    Etx2 = x2 @ E
    num = np.einsum("mi,mi->m", x2, Ex1)
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    d = np.abs(num) / np.sqrt(np.maximum(den, 1e-30))
    f = 0.25 * (K1[0, 0] + K1[1, 1] + K2[0, 0] + K2[1, 1])
    return d * f


def verify_matches(scene: Scene, i: int, j: int, kp_i: np.ndarray, kp_j: np.ndarray,
                   matches: np.ndarray, cfg: TriangulationConfig) -> np.ndarray:
    """Matches of pair (i, j) consistent with the known relative pose: [m', 2]."""
    if len(matches) == 0:
        return matches
    e = sampson_errors(kp_i[matches[:, 0], :2], kp_j[matches[:, 1], :2],
                       scene.K[i], scene.dist[i], scene.R[i], scene.t[i],
                       scene.K[j], scene.dist[j], scene.R[j], scene.t[j])
    return matches[e <= cfg.max_epipolar_px]


def match_pairs(scene: Scene, keypoints: list[np.ndarray], descriptors: list[np.ndarray],
                pairs: np.ndarray, cfg: TriangulationConfig, progress=None
                ) -> tuple[dict[tuple[int, int], np.ndarray], dict]:
    """Match and verify every pair.

    Args:
      scene: the images (with poses) that ``keypoints``/``descriptors`` belong to.
      keypoints: [N] arrays [K_i, >=2]; descriptors: [N] arrays [K_i, D].
      pairs: [P, 2] image index pairs.
      progress: optional callable advanced by one per pair (e.g. ``tqdm.update``).
    Returns:
      matches: {(i, j): [m, 2] int64} verified matches (pairs with fewer than
        ``cfg.min_pair_matches`` dropped); stats: counters.
    """
    pad = padded_size(max([len(d) for d in descriptors] + [0]))
    out: dict[tuple[int, int], np.ndarray] = {}
    n_raw = n_ver = n_empty = 0
    for i, j in np.asarray(pairs, np.int64).reshape(-1, 2):
        i, j = int(i), int(j)
        m = match_pair(descriptors[i], descriptors[j], cfg, pad)
        n_raw += len(m)
        v = verify_matches(scene, i, j, keypoints[i], keypoints[j], m, cfg)
        if len(v) >= cfg.min_pair_matches:
            out[(i, j)] = v
            n_ver += len(v)
        else:
            n_empty += 1
        if progress is not None:
            progress(1)
    stats = dict(pairs=int(len(pairs)), pairs_kept=len(out), pairs_dropped=n_empty,
                 raw_matches=n_raw, verified_matches=n_ver)
    return out, stats


# ----------------------------------------------------------------------------- pycolmap


def check_cameras(scene: Scene) -> None:
    """VrsError naming the first image whose pose or intrinsics pycolmap would choke on."""
    for i, name in enumerate(scene.names):
        where = scene.image_paths[i] if scene.image_paths else name
        K, R, t = scene.K[i], scene.R[i], scene.t[i]
        if not (np.all(np.isfinite(K)) and np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
            raise VrsError("pose or intrinsics contain NaN/inf", where)
        if K[0, 0] <= 0 or K[1, 1] <= 0 or abs(K[0, 1]) > 1e-9 * K[0, 0]:
            raise VrsError(f"intrinsics need positive focal lengths and no skew, got {K.tolist()}",
                           where)
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-5 or np.linalg.det(R) < 0:
            raise VrsError("pose rotation is not a rotation matrix", where)
        if np.any(np.asarray(scene.sizes[i]) <= 0):
            raise VrsError(f"image size must be positive, got {scene.sizes[i]}", where)


def build_reconstruction(scene: Scene, points2d: list[np.ndarray]) -> pycolmap.Reconstruction:
    """A pycolmap Reconstruction with the known cameras/poses and 2D points, no 3D points.

    Image i of the scene gets camera, rig, frame and image id i + 1.
    """
    check_cameras(scene)
    rec = pycolmap.Reconstruction()
    for i, name in enumerate(scene.names):
        rec.add_camera_with_trivial_rig(colmap_camera(scene.K[i], scene.dist[i],
                                                      scene.sizes[i], i + 1))
        xy = np.asarray(points2d[i], np.float64).reshape(-1, 2)
        image = pycolmap.Image(name=name, keypoints=xy, camera_id=i + 1, image_id=i + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(scene.R[i], np.float64)),
                                np.asarray(scene.t[i], np.float64))
        rec.add_image_with_trivial_frame(image, pose)
    return rec


def _check_inputs(scene: Scene, keypoints: list[np.ndarray],
                  matches: dict[tuple[int, int], np.ndarray]) -> None:
    n = len(scene)
    if len(keypoints) != n:
        raise VrsError(f"{len(keypoints)} keypoint arrays for {n} images")
    for i, kp in enumerate(keypoints):
        if len(kp) and not np.all(np.isfinite(kp[:, :2])):
            raise VrsError("keypoints contain NaN/inf", scene.image_paths[i])
    seen = set()
    for (i, j), m in matches.items():
        if not (0 <= i < n and 0 <= j < n) or i == j:
            raise VrsError(f"bad image pair ({i}, {j}) for {n} images")
        if (min(i, j), max(i, j)) in seen:
            raise VrsError(f"image pair ({i}, {j}) given twice (also as ({j}, {i}))")
        seen.add((min(i, j), max(i, j)))
        m = np.asarray(m)
        if m.ndim != 2 or m.shape[1] != 2:
            raise VrsError(f"matches of pair ({i}, {j}) must be [m, 2], got {m.shape}")
        if len(m) and (m.min() < 0 or m[:, 0].max() >= len(keypoints[i])
                       or m[:, 1].max() >= len(keypoints[j])):
            raise VrsError(f"matches of pair ({scene.names[i]}, {scene.names[j]}) index "
                           "keypoints that do not exist")


def _empty(n_images: int, keypoints: list[np.ndarray], stats: dict) -> Triangulation:
    z = np.zeros(0, np.int64)
    return Triangulation(np.zeros((0, 3)), np.zeros(0), z, np.zeros(0), z, z, z, np.zeros(0),
                         [np.full(len(k), -1, np.int64) for k in keypoints], stats)


def triangulate_known_poses(scene: Scene, keypoints: list[np.ndarray],
                            matches: dict[tuple[int, int], np.ndarray],
                            cfg: TriangulationConfig = TriangulationConfig(),
                            depth_ranges: np.ndarray | None = None,
                            verbose: bool = False) -> Triangulation:
    """3D points from verified matches and the scene's known poses (COLMAP's triangulator).

    Args:
      scene: N images with poses, intrinsics and sizes.
      keypoints: [N] arrays [K_i, >=2] (x, y first, COLMAP pixel convention).
      matches: {(i, j): [m, 2]} verified keypoint matches.
      cfg: thresholds.
      depth_ranges: optional [N, 2] plausible (near, far) depth per image (see
        ``cfg.depth_margin``).
      verbose: keep COLMAP's log lines.
    Returns:
      A :class:`Triangulation`; with no points (no matches, or all filtered) an empty one and
      a warning -- the caller decides whether that is an error.
    Raises:
      VrsError for inconsistent input (bad indices, NaN, non-rotations).
    """
    _check_inputs(scene, keypoints, matches)
    n = len(scene)
    stats = dict(input_matches=int(sum(len(m) for m in matches.values())))
    if stats["input_matches"] == 0:
        warnings.warn(f"triangulation: no verified matches among {n} images "
                      f"({scene.root}); no 3D points", stacklevel=2)
        return _empty(n, keypoints, stats)
    rec = build_reconstruction(scene, [np.asarray(k)[:, :2] for k in keypoints])
    try:
        _run_triangulator(rec, keypoints, matches, cfg, verbose)
    except (RuntimeError, ValueError) as e:  # a COLMAP check that our validation missed
        raise VrsError(f"pycolmap triangulation failed: {e}", scene.root) from e
    out = _collect(scene, keypoints, rec, stats)
    stats["points_pycolmap"] = out.num_points
    if depth_ranges is not None and cfg.depth_margin is not None and out.num_points:
        out = _filter_depth(scene, out, np.asarray(depth_ranges, np.float64), cfg.depth_margin)
    stats["points"] = out.num_points
    if out.num_points == 0:
        warnings.warn(f"triangulation: {stats['input_matches']} matches among {n} images "
                      f"({scene.root}) gave no 3D point that passed the filters", stacklevel=2)
    return out


def _run_triangulator(rec: pycolmap.Reconstruction, keypoints: list[np.ndarray],
                      matches: dict[tuple[int, int], np.ndarray], cfg: TriangulationConfig,
                      verbose: bool) -> None:
    """COLMAP's point triangulator on ``rec`` (modified in place): correspondence graph of the
    matches, triangulation image by image, track completion and merging, then filtering."""
    graph = pycolmap.CorrespondenceGraph()
    for i in range(len(keypoints)):
        graph.add_image(i + 1, len(keypoints[i]))
    for (i, j), m in matches.items():
        if len(m):
            tvg = pycolmap.TwoViewGeometry(
                inlier_matches=np.ascontiguousarray(m, np.uint32),
                config=pycolmap.TwoViewGeometryConfiguration.CALIBRATED)
            graph.add_two_view_geometry(i + 1, j + 1, tvg)
    graph.finalize()
    opts = pycolmap.IncrementalTriangulatorOptions(
        ignore_two_view_tracks=False,
        create_max_angle_error=cfg.create_max_angle_error,
        continue_max_angle_error=cfg.continue_max_angle_error,
        merge_max_reproj_error=cfg.merge_max_reproj_error,
        complete_max_reproj_error=cfg.complete_max_reproj_error,
        min_angle=cfg.min_tri_angle_deg,
        random_seed=cfg.seed)
    with quiet_pycolmap(verbose):
        obs = pycolmap.ObservationManager(rec, graph)
        tri = pycolmap.IncrementalTriangulator(graph, rec, obs)
        for i in range(len(keypoints)):
            if graph.num_correspondences_for_image(i + 1) > 0:
                tri.triangulate_image(opts, i + 1)
        tri.complete_all_tracks(opts)
        tri.merge_all_tracks(opts)
        obs.filter_all_points3D(cfg.max_reproj_error, cfg.min_tri_angle_deg)
        obs.filter_points3D_with_short_tracks(cfg.min_track_length)


def _collect(scene: Scene, keypoints: list[np.ndarray], rec: pycolmap.Reconstruction,
             stats: dict) -> Triangulation:
    """Points, tracks and our own reprojection errors out of the pycolmap reconstruction."""
    ids = sorted(rec.point3D_ids())
    if not ids:
        return _empty(len(scene), keypoints, stats)
    # pycolmap's points and tracks are objects: one pass reads them (the only per-observation
    # Python here); everything after works on the flat observation arrays.
    points = [rec.points3D[p] for p in ids]
    X = np.array([p.xyz for p in points], np.float64).reshape(-1, 3)
    tracks = [p.track.elements for p in points]
    obs_image = np.fromiter((el.image_id for els in tracks for el in els), np.int64) - 1
    obs_kp = np.fromiter((el.point2D_idx for els in tracks for el in els), np.int64)
    obs_point = np.repeat(np.arange(len(ids), dtype=np.int64), [len(e) for e in tracks])
    # Reprojection errors with our own projection (an independent check of pycolmap's).
    # One vectorised projection per observing image (loop over images, not observations).
    obs_err = np.zeros(len(obs_image))
    for i in np.unique(obs_image):
        sel = obs_image == i
        uv, _ = geometry.project(scene.K[i], scene.R[i], scene.t[i], X[obs_point[sel]],
                                 scene.dist[i])
        obs_err[sel] = np.linalg.norm(uv - keypoints[i][obs_kp[sel], :2], axis=-1)
    lengths = [len(k) for k in keypoints]
    flat = np.full(sum(lengths), -1, np.int64)  # point of every keypoint of every image
    flat[np.cumsum([0, *lengths])[obs_image] + obs_kp] = obs_point
    point_of_kp = _split(flat, lengths)
    m = len(X)
    track_len = np.bincount(obs_point, minlength=m)
    errors = np.bincount(obs_point, weights=obs_err, minlength=m) / np.maximum(track_len, 1)
    tri_angles = _max_tri_angles(scene.centers[obs_image], X[obs_point], obs_point, m)
    return Triangulation(X, errors, track_len.astype(np.int64), tri_angles, obs_image, obs_kp,
                         obs_point, obs_err, point_of_kp, stats)


def _concat(rows: list[np.ndarray]) -> np.ndarray:
    """Per-image int arrays [K_i] -> [sum K_i] int64."""
    return np.concatenate([np.asarray(r, np.int64).reshape(-1) for r in rows]
                          + [np.zeros(0, np.int64)])


def _split(flat: np.ndarray, lengths: list[int]) -> list[np.ndarray]:
    """Inverse of :func:`_concat`: [sum K_i] -> [N] arrays [K_i] (copies)."""
    return [a.copy() for a in np.split(flat, np.cumsum(lengths)[:-1])] if lengths else []


def subset_points(tr: Triangulation, keep: np.ndarray) -> Triangulation:
    """The triangulation restricted to the points where ``keep`` [M] is True (reindexed)."""
    keep = np.asarray(keep, bool)
    new_index = np.cumsum(keep) - 1
    sel = keep[tr.obs_point]
    flat = _concat(tr.point_of_kp)
    ok = flat >= 0
    ok[ok] = keep[flat[ok]]
    flat = np.where(ok, flat, -1)
    flat[ok] = new_index[flat[ok]]
    point_of_kp = _split(flat, [len(p) for p in tr.point_of_kp])
    return Triangulation(tr.points3d[keep], tr.errors[keep], tr.track_lengths[keep],
                         tr.tri_angles[keep], tr.obs_image[sel], tr.obs_kp[sel],
                         new_index[tr.obs_point[sel]], tr.obs_errors[sel], point_of_kp,
                         tr.stats)


def _filter_depth(scene: Scene, tr: Triangulation, ranges: np.ndarray, margin: float
                  ) -> Triangulation:
    """Drop points outside [near / margin, far * margin] in any image that observes them."""
    X = tr.points3d[tr.obs_point]
    R, t = scene.R[tr.obs_image], scene.t[tr.obs_image]
    z = np.einsum("oj,oj->o", R[:, 2, :], X) + t[:, 2]
    r = ranges[tr.obs_image]
    bad = (z < r[:, 0] / margin) | (z > r[:, 1] * margin)
    keep = np.bincount(tr.obs_point[bad], minlength=tr.num_points) == 0
    tr.stats["points_outside_depth_range"] = int((~keep).sum())
    return subset_points(tr, keep)


def _max_tri_angles(centers: np.ndarray, X_obs: np.ndarray, obs_point: np.ndarray, m: int
                    ) -> np.ndarray:
    """[m] largest angle between viewing rays of each point (over all observation pairs).

    Computed in one vectorised pass over the pairs of observations of the same point
    (tracks are short: a few to a few dozen observations).
    """
    rays = X_obs - centers
    rays /= np.maximum(np.linalg.norm(rays, axis=-1, keepdims=True), 1e-12)
    order = np.argsort(obs_point, kind="stable")
    rays, pts = rays[order], obs_point[order]
    out = np.zeros(m)
    start = np.searchsorted(pts, np.arange(m))
    count = np.bincount(pts, minlength=m)
    max_len = int(count.max()) if m else 0
    for a in range(max_len):  # loop over track positions, not over points
        for b in range(a + 1, max_len):
            ok = count > b
            ia, ib = start[ok] + a, start[ok] + b
            ang = np.arccos(np.clip(np.einsum("ki,ki->k", rays[ia], rays[ib]), -1.0, 1.0))
            out[ok] = np.maximum(out[ok], ang)
    return out
