"""Patch rays: the canonical grid of a reference keypoint cast as cone rays of its camera.

The same :func:`vrs_jax.features.patches.patch_grid` that reads real patches gives the sample
positions, so a rendered patch and a real patch describe the same piece of the scene
(docs/design.md, section 2). Each sample becomes one mip-NeRF cone whose radius matches the sample
spacing (:func:`vrs_jax.geometry.cone_radius`, the same definition NeRF training uses for
pixels). This module sits below both ``nerf`` (keypoint-patch training rays) and ``localize``.

Pure functions; vmap over images and keypoints is free.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax.numpy as jnp

from vrs_jax import geometry
from vrs_jax.features.patches import PatchConfig, patch_grid

Array = Any

class PatchRays(NamedTuple):
    """Cone rays of K patches of P x P samples (all world frame).

    origins: [K, P, P, 3]; directions: [K, P, P, 3] with unit camera depth (t = z-depth);
    radii: [K, P, P] cone radius at t = 1; positions: [K, P, P, 2] pixel coordinates.
    """

    origins: Array
    directions: Array
    radii: Array
    positions: Array


def patch_rays(kp: Array, K: Array, R: Array, t: Array, patch_cfg: PatchConfig,
               dist: Array | None = None, side: int | None = None) -> PatchRays:
    """Cone rays for the patches of keypoints of one reference camera.

    Args:
      kp: [Kp, 4] keypoints (x, y, scale, angle), COLMAP pixel convention.
      K: [3, 3] intrinsics; R, t: [3, 3], [3] world-to-camera pose.
      patch_cfg: patch geometry (the same config that reads real patches).
      dist: optional [5] OpenCV distortion of the reference camera.
      side: S rays per patch row and column spread over the patch (canonical patches; see
        :func:`patch_grid`), each with the full grid's cone radius; None: the P x P grid.
    Returns:
      PatchRays with arrays [Kp, P, P, ...] (or [Kp, S, S, ...]).
    """
    pos, foot = patch_grid(kp, patch_cfg, side)  # [Kp, S, S, 2], [Kp]
    kshape = pos.shape[:-1]
    flat = pos.reshape(-1, 2)
    o, d = geometry.pixel_rays(K, R, t, flat, dist)
    radius = geometry.cone_radius(K, foot)  # [Kp]
    radii = jnp.broadcast_to(radius[:, None, None], kshape)
    return PatchRays(o.reshape(*kshape, 3), d.reshape(*kshape, 3), radii, pos)


def keypoint_depths(points3d: Array, point_idx: Array, R: Array, t: Array) -> Array:
    """z-depth [Kp] in one camera of the 3D points linked to its keypoints (point_idx [Kp]).

    Padding entries (index -1) read point 0; callers mask them.
    """
    X = jnp.take(points3d, jnp.maximum(point_idx, 0), axis=0)
    return geometry.transform_points(R, t, X)[..., 2]


def narrow_interval(depth: Array, margin: float, shape: tuple[int, ...]) -> tuple[Array, Array]:
    """Depth-guided [near, far] per ray around the keypoint's point depth.

    Args:
      depth: [Kp] z-depth of each keypoint's 3D point.
      margin: relative half-width of the interval (0.15: +-15% of the depth).
      shape: the ray grid shape [Kp, P, P] to broadcast to.
    Returns:
      near, far: arrays of ``shape``.
    """
    d = jnp.maximum(depth, 1e-3)[:, None, None]
    near = jnp.broadcast_to(d * (1.0 - margin), shape)
    far = jnp.broadcast_to(d * (1.0 + margin), shape)
    return near, far


# Literal-mode pixel ids: (y + PAD) * LIN_W + (x + PAD) fits int32 for images up to
# ~31k x ~64k pixels, and keeps samples that fall outside the image (negative coordinates).
_PAD = 1024
_LIN_W = 1 << 15


def unique_literal_pixels(positions: Array, mask: Array) -> tuple[Array, Array, Array]:
    """Paper-literal mode: the distinct whole pixels of overlapping axis-aligned patches.

    Overlapping patches of one image share pixels; each distinct pixel needs one ray only.
    With fixed shapes, the distinct set is padded to the total sample count; renderers skip
    the padding (see ``count``).

    Args:
      positions: [Kp, P, P, 2] pixel-centre coordinates (literal grid: half-integers).
      mask: [Kp] valid keypoints.
    Returns:
      pixels: [Kp * P * P, 2] pixel-centre coordinates of the distinct pixels, valid ones
        first (sorted), then padding,
      inverse: [Kp, P, P] index of each sample into ``pixels``,
      count: [] number of distinct pixels of valid keypoints (the rays actually needed).
    """
    kshape = positions.shape[:-1]
    n = math.prod(kshape)
    ij = jnp.floor(positions).astype(jnp.int32) + _PAD
    lin = ij[..., 1] * _LIN_W + ij[..., 0]
    big = jnp.iinfo(jnp.int32).max  # padding id for masked keypoints: sorts last
    lin = jnp.where(mask[:, None, None], lin, big).reshape(-1)
    uniq, inverse = jnp.unique(lin, size=n, fill_value=big, return_inverse=True)
    count = jnp.sum(uniq < big)
    xy = jnp.stack([uniq % _LIN_W, uniq // _LIN_W], -1) - _PAD
    pixels = xy.astype(jnp.float32) + 0.5
    return pixels, inverse.reshape(kshape), count



def transfer_keypoints(kp: Array, X: Array, K_ref: Array, R_ref: Array, t_ref: Array,
                       dist_ref: Array | None, K: Array, R: Array, t: Array
                       ) -> tuple[Array, Array]:
    """Keypoints of a reference view moved into another view through their 3D points.

    A keypoint's frame (centre, scale, orientation) is the image of a small fronto-parallel
    disc at its 3D point. In the other (pinhole) camera the centre is the point's projection,
    the scale shrinks with depth and focal length (s f / z_ref -> s' f' / z), and the
    orientation is that of the projected direction: the point one scale along the keypoint's
    orientation, lifted to the 3D point's depth in the reference and projected.

    Args:
      kp: [Kp, 4] reference keypoints (x, y, scale, angle); X: [Kp, 3] their 3D points.
      K_ref, R_ref, t_ref, dist_ref: the reference camera ([3, 3], [3, 3], [3], [5] or None).
      K, R, t: the target pinhole camera (world-to-camera).
    Returns:
      kp_new: [Kp, 4] keypoints in the target view; z: [Kp] depth of X in the target view
      (<= 0: behind it; callers mask those).
    """
    uv, z = geometry.project(K, R, t, X)
    z_ref = (X @ R_ref.T + t_ref)[:, 2]
    ang = kp[:, 3]
    tip = kp[:, :2] + kp[:, 2:3] * jnp.stack([jnp.cos(ang), jnp.sin(ang)], -1)
    tip_cam = geometry.unproject(K_ref, tip, dist_ref) * z_ref[:, None]
    tip_world = (tip_cam - t_ref) @ R_ref  # R^T (x - t) for row vectors
    uv_tip, _ = geometry.project(K, R, t, tip_world)
    f_ref = 0.5 * (K_ref[0, 0] + K_ref[1, 1])
    f = 0.5 * (K[0, 0] + K[1, 1])
    scale = kp[:, 2] * (f / f_ref) * z_ref / jnp.maximum(z, 1e-6)
    dv = uv_tip - uv
    angle = jnp.arctan2(dv[:, 1], dv[:, 0])
    return jnp.concatenate([uv, scale[:, None], angle[:, None]], -1), z
