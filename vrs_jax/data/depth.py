"""Depth-map consistency between two posed frames (a check of poses, intrinsics and depth).

Frame i's depth is back-projected with its depth intrinsics and pose, moved into frame j's
camera and projected there; the predicted depth is compared with frame j's depth map at that
pixel. Frame j's depth is sampled by bilinear interpolation of inverse depth (exact on planes,
since 1/z is affine in the pixel coordinates of a plane) over the 4 neighbours, all of which
must be valid and agree within 5 %, so depth edges are not blended.
"""

from __future__ import annotations

import numpy as np

from vrs_jax import geometry
from vrs_jax.data.images import read_depth
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError


def _depth_K(scene: Scene, i: int) -> np.ndarray:
    return np.asarray(scene.depth_K[i] if scene.depth_K is not None else scene.K[i])


def _load(scene: Scene, i: int) -> np.ndarray:
    if scene.depth_paths is None or scene.depth_paths[i] is None:
        raise VrsError(f"image {scene.names[i]} has no depth map", scene.root)
    if not scene.has_pose[i]:
        raise VrsError(f"image {scene.names[i]} has no pose", scene.root)
    return read_depth(scene.depth_paths[i], scale=scene.depth_scale)


def sample_inverse_depth(depth: np.ndarray, uv: np.ndarray, max_rel: float = 0.05
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Bilinear depth lookup at pixel coordinates (COLMAP convention).

    Args:
      depth: [H, W] metres, 0 = invalid.
      uv: [M, 2] pixel coordinates (pixel (r, c) centre at (c + 0.5, r + 0.5)).
      max_rel: the 4 neighbours must be within this relative spread (no blending across edges).
    Returns:
      z [M] interpolated depth (metres; 0 where invalid), valid [M] bool.
    """
    H, W = depth.shape
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < W) & (y0 + 1 < H) & np.isfinite(x + y)
    x0, y0 = np.where(inside, x0, 0), np.where(inside, y0, 0)
    ax, ay = x - x0, y - y0
    n = np.stack([depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]])
    valid = inside & np.all(n > 0, axis=0)
    lo, hi = n.min(axis=0), n.max(axis=0)
    valid &= hi <= lo * (1 + max_rel)
    inv = 1.0 / np.where(n > 0, n, 1.0)
    wts = np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay])
    inv_z = np.sum(wts * inv, axis=0)
    return np.where(valid, 1.0 / inv_z, 0.0), valid


def depth_reprojection_errors(scene: Scene, i: int, j: int, stride: int = 4) -> np.ndarray:
    """Per-pixel depth disagreement of frame i's depth seen from frame j, in metres.

    Args:
      scene: a Scene with depth_paths (and depth_K; K is used when it is None) and poses.
      i, j: frame indices; stride: take every ``stride``-th pixel of frame i in each axis.
    Returns:
      [M] float64 ``|z_pred - z_j|``: z_pred is the depth in camera j of frame i's
      back-projected pixel, z_j frame j's (interpolated) depth where it projects; only pixels
      valid in both depth maps, in front of camera j and inside its depth image are returned.
    """
    di, dj = _load(scene, i), _load(scene, j)
    H, W = di.shape
    grid = geometry.pixel_grid(W, H)[::stride, ::stride].reshape(-1, 2)
    rows = ((grid[:, 1] - 0.5).astype(np.int64), (grid[:, 0] - 0.5).astype(np.int64))
    z = di[rows].astype(np.float64)
    ok = z > 0
    grid, z = grid[ok], z[ok]
    Xc = geometry.unproject(_depth_K(scene, i), grid) * z[:, None]  # camera i, [M, 3]
    Xw = geometry.transform_points(*geometry.pose_inverse(scene.R[i], scene.t[i]), Xc)
    uv, zj = geometry.project(_depth_K(scene, j), scene.R[j], scene.t[j], Xw)
    front = zj > 1e-6
    z_obs, valid = sample_inverse_depth(dj.astype(np.float64), np.where(front[:, None], uv, -1))
    valid &= front
    return np.abs(zj[valid] - z_obs[valid])
