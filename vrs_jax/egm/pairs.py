"""Reference image pairs from the KNOWN poses: frustum overlap and viewing-angle covisibility.

Matching every reference image against every other costs N^2 and produces many false matches
between images that see nothing in common. With known poses, the pairs worth matching can be
read off the geometry (as hloc's ``pairs_from_poses`` and COLMAP's spatial matcher do, but
with the view frustum instead of the camera centre alone):

1. Each image's frustum is sampled: a grid of pixels, each back-projected at a few depths
   spread (log-uniformly) over that image's depth range.
2. The overlap of image i with image j is the fraction of i's samples that project inside j
   (in front of it); the pair score is the mean of both directions.
3. A pair is kept when its score reaches ``min_overlap`` and the angle between the two optical
   axes is at most ``max_angle_deg`` (SIFT-like descriptors stop matching beyond ~60 deg of
   viewpoint change); each image keeps its ``num_neighbors`` best partners, and the union
   of those choices is returned.

The depth range per image comes, in order of preference, from the dataset's bounds (LLFF),
its depth maps (7Scenes, the synthetic scene), its sparse points (COLMAP, NVM), the point
where the optical axes converge (object-centric captures such as NeRF's lego), or as a last
resort from the spread of the camera centres.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from vrs_jax import geometry
from vrs_jax.data.images import read_depth
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError


@dataclasses.dataclass(frozen=True)
class PairsConfig:
    """How reference pairs are chosen from the known poses."""

    # Partners kept per image. hloc uses 20-50 covisible pairs per image for large scenes;
    # 10 keeps matching cost linear in N while leaving every point several observations.
    num_neighbors: int = 10
    # Minimum mean frustum overlap (fraction of samples seen by the other camera). 0.1 keeps
    # pairs that share a tenth of their view: enough for a few dozen SIFT matches.
    min_overlap: float = 0.1
    # Maximum angle between optical axes, degrees: SIFT-like descriptors are invariant to
    # in-plane rotation but not to out-of-plane viewpoint changes much beyond ~60 degrees.
    max_angle_deg: float = 60.0
    # Frustum sampling: grid x grid pixels, each at n_depths depths (log-uniform in range).
    grid: int = 8
    n_depths: int = 6
    # Depth percentiles (of depth maps or sparse points) taken as an image's near/far.
    depth_percentiles: tuple[float, float] = (5.0, 95.0)
    # At most this many depth maps are read to estimate ranges; the others borrow the range
    # of the nearest image (by index) that was read. Trajectories change depth slowly.
    max_depth_reads: int = 200
    # Fixed depth range (near, far) in metres for every image, overriding the estimate.
    depth_range: tuple[float, float] | None = None


def _ranges_from_depth_maps(scene: Scene, pct: tuple[float, float], max_reads: int
                            ) -> np.ndarray | None:
    """[N, 2] near/far from the scene's depth maps (a subset read), or None if unusable."""
    if scene.depth_paths is None or any(p is None for p in scene.depth_paths):
        return None
    n = len(scene)
    read = np.unique(np.linspace(0, n - 1, min(n, max_reads)).round().astype(int))
    got = {}
    for i in read:
        d = read_depth(scene.depth_paths[i], scale=scene.depth_scale)[::4, ::4]
        v = d[d > 0]
        if v.size >= 16:
            got[int(i)] = np.percentile(v, pct)
    if not got:
        return None
    keys = np.array(sorted(got))
    nearest = keys[np.abs(np.arange(n)[:, None] - keys[None, :]).argmin(axis=1)]
    return np.stack([got[int(k)] for k in nearest])


def _ranges_from_points(scene: Scene, pct: tuple[float, float]) -> np.ndarray | None:
    """[N, 2] near/far from the scene's sparse points seen in each image, or None."""
    X = scene.points3d
    if X is None or len(X) < 8:
        return None
    X = np.asarray(X, np.float64)
    out = np.full((len(scene), 2), np.nan)
    for i in range(len(scene)):
        uv, z = geometry.project(scene.K[i], scene.R[i], scene.t[i], X)
        w, h = scene.sizes[i]
        vis = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        if vis.sum() >= 8:
            out[i] = np.percentile(z[vis], pct)
    ok = np.isfinite(out[:, 0])
    if not ok.any():
        return None
    out[~ok] = np.median(out[ok], axis=0)
    return out


def _ranges_from_axes(centers: np.ndarray, axes: np.ndarray) -> np.ndarray | None:
    """[N, 2] near/far around the point the optical axes converge to, or None.

    The point p minimising the summed squared distance to all axes solves
    sum(I - a a^T) p = sum(I - a a^T) c. For an object-centric capture it is the object
    centre; for a forward-facing or trajectory capture the system is ill-conditioned or p
    lies behind the cameras, and None is returned.
    """
    P = np.eye(3)[None] - axes[:, :, None] * axes[:, None, :]
    A = P.sum(0)
    ev = np.linalg.eigvalsh(A / len(axes))
    if ev[0] < 0.05:
        return None
    p = np.linalg.solve(A, np.einsum("nij,nj->i", P, centers))
    d = np.einsum("ni,ni->n", p[None] - centers, axes)
    if np.mean(d > 0) < 0.9:
        return None
    d = np.maximum(d, np.median(d[d > 0]) * 0.1)
    return np.stack([0.5 * d, 1.5 * d], axis=1)


def estimate_depth_ranges(scene: Scene, cfg: PairsConfig = PairsConfig()
                          ) -> tuple[np.ndarray, str]:
    """Depth range of every image of ``scene`` (see the module docstring for the sources).

    Returns:
      ranges: [N, 2] (near, far) in metres.
      source: where they came from: "config", "bounds", "depth", "points", "axes" or
        "extent" (the last one is a guess from the camera layout, not a measurement).
    """
    n = len(scene)
    if cfg.depth_range is not None:
        return np.tile(np.asarray(cfg.depth_range, np.float64), (n, 1)), "config"
    source = "bounds"
    r = None if scene.bounds is None else np.asarray(scene.bounds, np.float64).reshape(n, 2)
    if r is None:
        source = "depth"
        r = _ranges_from_depth_maps(scene, cfg.depth_percentiles, cfg.max_depth_reads)
    if r is None:
        source = "points"
        r = _ranges_from_points(scene, cfg.depth_percentiles)
    centers = scene.centers
    if r is None:
        source = "axes"
        r = _ranges_from_axes(centers, scene.R[:, 2, :])
    if r is None:
        source = "extent"
        extent = np.linalg.norm(centers.max(0) - centers.min(0)) if n > 1 else 1.0
        extent = max(float(extent), 1e-3)
        r = np.tile([0.5 * extent, 2.0 * extent], (n, 1))
    r = np.array(r, np.float64)
    r[:, 0] = np.maximum(r[:, 0], 1e-3)
    r[:, 1] = np.maximum(r[:, 1], r[:, 0] * 1.01)
    return r, source


def frustum_samples(K: np.ndarray, R: np.ndarray, t: np.ndarray, sizes: np.ndarray,
                    ranges: np.ndarray, grid: int, n_depths: int) -> np.ndarray:
    """World points sampling each view frustum.

    Args:
      K: [N, 3, 3]; R: [N, 3, 3]; t: [N, 3]; sizes: [N, 2] (w, h); ranges: [N, 2] near/far.
    Returns:
      [N, grid * grid * n_depths, 3] world points (pixel grid cell centres x depths).
    """
    n = len(K)
    f = (np.arange(grid) + 0.5) / grid
    gu, gv = np.meshgrid(f, f, indexing="xy")
    uv = np.stack([gu.ravel(), gv.ravel()], -1)[None] * sizes[:, None, :]  # [N, G, 2]
    rays = geometry.unproject(K, uv)  # [N, G, 3], z = 1
    s = (np.arange(n_depths) + 0.5) / n_depths
    near, far = ranges[:, :1], ranges[:, 1:]
    depths = near * (far / near) ** s[None]  # [N, D] log-uniform
    Xc = rays[:, :, None, :] * depths[:, None, :, None]  # [N, G, D, 3]
    Rt, tt = geometry.pose_inverse(R, t)
    return geometry.transform_points(Rt, tt, Xc.reshape(n, -1, 3))


def covisibility(K: np.ndarray, R: np.ndarray, t: np.ndarray, sizes: np.ndarray,
                 ranges: np.ndarray, grid: int = 8, n_depths: int = 6) -> np.ndarray:
    """[N, N] frustum overlap score in [0, 1] (symmetric, zero diagonal); see module doc."""
    n = len(K)
    X = frustum_samples(K, R, t, sizes, ranges, grid, n_depths)  # [N, S, 3]
    chunk = max(1, int(2e6 // (n * X.shape[1])))  # bounds the [c, N, S, 3] temporaries
    frac = np.zeros((n, n))
    for a in range(0, n, chunk):
        Xa = X[a:a + chunk]  # [c, S, 3]
        # project every sample of images a..a+c into every camera j: [c, N, S]
        Xc = np.einsum("nij,csj->cnsi", R, Xa) + t[None, :, None, :]
        z = Xc[..., 2]
        uvw = np.einsum("nij,cnsj->cnsi", K, Xc)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = uvw[..., 0] / z
            v = uvw[..., 1] / z
        w = sizes[None, :, None, 0]
        h = sizes[None, :, None, 1]
        inside = (z > 1e-6) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
        frac[a:a + chunk] = inside.mean(-1)
    score = 0.5 * (frac + frac.T)
    np.fill_diagonal(score, 0.0)
    return score


def viewing_angles(R: np.ndarray) -> np.ndarray:
    """[N, N] angle in radians between the optical axes (world z of each camera)."""
    axes = R[:, 2, :]
    return np.arccos(np.clip(axes @ axes.T, -1.0, 1.0))


def select_pairs(score: np.ndarray, angles: np.ndarray, num_neighbors: int,
                 min_overlap: float, max_angle: float) -> np.ndarray:
    """Union of each image's top-N partners: [P, 2] int (i < j), sorted, unique."""
    n = len(score)
    ok = (score >= min_overlap) & (angles <= max_angle)
    np.fill_diagonal(ok, False)
    s = np.where(ok, score, -np.inf)
    k = min(num_neighbors, max(n - 1, 0))
    if k == 0:
        return np.zeros((0, 2), np.int64)
    top = np.argsort(-s, axis=1, kind="stable")[:, :k]  # [N, k]
    i = np.repeat(np.arange(n), k)
    j = top.ravel()
    keep = np.isfinite(s[i, j])
    i, j = i[keep], j[keep]
    pairs = np.unique(np.stack([np.minimum(i, j), np.maximum(i, j)], 1), axis=0)
    return pairs.reshape(-1, 2).astype(np.int64)


def reference_pairs(scene: Scene, cfg: PairsConfig = PairsConfig(),
                    ranges: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Covisible pairs among the images of ``scene`` (all must have poses).

    Args:
      scene: posed images.
      cfg: pair selection settings.
      ranges: [N, 2] depth ranges (default: :func:`estimate_depth_ranges`).

    Returns:
      pairs: [P, 2] int64 indices into ``scene`` with i < j.
      score: [N, N] float overlap scores (for diagnostics).
    Raises:
      VrsError if an image has no pose.
    """
    if len(scene) and not np.all(scene.has_pose):
        bad = [n for n, ok in zip(scene.names, scene.has_pose, strict=True) if not ok]
        raise VrsError(f"reference pairs need poses; {len(bad)} images have none "
                       f"(first: {bad[0]}); run SfM first", scene.root)
    if len(scene) < 2:
        return np.zeros((0, 2), np.int64), np.zeros((len(scene), len(scene)))
    if ranges is None:
        ranges, _ = estimate_depth_ranges(scene, cfg)
    score = covisibility(scene.K, scene.R, scene.t, np.asarray(scene.sizes, np.float64),
                         ranges, cfg.grid, cfg.n_depths)
    pairs = select_pairs(score, viewing_angles(scene.R), cfg.num_neighbors, cfg.min_overlap,
                         np.deg2rad(cfg.max_angle_deg))
    return pairs, score
