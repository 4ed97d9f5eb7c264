"""Camera geometry as small pure functions, for numpy and jax arrays alike.

Conventions (docs/design.md, section 3), fixed once for the whole project:

- A pose is world-to-camera ``(R, t)``: ``x_cam = R @ x_world + t`` (COLMAP's convention).
- Camera axes are OpenCV's: x right, y down, z forward.
- Quaternions are ``(w, x, y, z)``, Hamilton, as COLMAP stores them.
- Pixel coordinates follow COLMAP: the centre of the top-left pixel is ``(0.5, 0.5)``; an
  image array element ``img[i, j]`` sits at ``(u, v) = (j + 0.5, i + 0.5)``. Intrinsics are
  expressed in that convention, so a ray for pixel coordinate ``(u, v)`` has direction
  ``K^-1 [u, v, 1]``.
- Distortion is OpenCV's radial/tangential model, coefficients ``(k1, k2, p1, p2, k3)``.
- Units are metres and radians; reports convert to centimetres and degrees.

Every function dispatches on its inputs: numpy in, numpy out (float64 kept); a jax array in,
jax out (traceable under jit/vmap). Shapes use ``...`` for arbitrary leading batch axes.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax.errors import VrsError

Array = Any

# Focal lengths below this many pixels are refused: a field of view of nearly 180 degrees for
# any image, i.e. a K in other units (normalised coordinates, metres) or a typo.
MIN_FOCAL_PX = 1.0
# Distortion lengths taken: OpenCV's (k1, k2, p1, p2) and (k1, k2, p1, p2, k3); 4 is padded.
DIST_LENGTHS = (4, 5)


def _xp(*arrays: Array):
    """The array module matching the inputs: jnp if any is a jax array or tracer."""
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


# ----------------------------------------------------------------------------- rotations


def quat_to_rot(q: Array) -> Array:
    """Unit quaternion ``(w, x, y, z)`` [..., 4] -> rotation matrix [..., 3, 3].

    The quaternion is normalised first, so slightly off-unit inputs from files are fine.
    """
    xp = _xp(q)
    q = q / xp.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return xp.stack([xp.stack(r, axis=-1) for r in rows], axis=-2)


def rot_to_quat(R: Array) -> Array:
    """Rotation matrix [..., 3, 3] -> unit quaternion ``(w, x, y, z)`` [..., 4] with w >= 0.

    Shepperd's method: of the four candidate formulas the one with the largest pivot is
    used, so the result is accurate for every rotation (including 180 degrees).
    """
    xp = _xp(R)
    m00, m11, m22 = R[..., 0, 0], R[..., 1, 1], R[..., 2, 2]
    tr = m00 + m11 + m22
    # Four candidates, each well conditioned where its pivot is large.
    cands = xp.stack(
        [
            xp.stack([1 + tr, R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                      R[..., 1, 0] - R[..., 0, 1]], axis=-1),
            xp.stack([R[..., 2, 1] - R[..., 1, 2], 1 + m00 - m11 - m22,
                      R[..., 0, 1] + R[..., 1, 0], R[..., 0, 2] + R[..., 2, 0]], axis=-1),
            xp.stack([R[..., 0, 2] - R[..., 2, 0], R[..., 0, 1] + R[..., 1, 0],
                      1 - m00 + m11 - m22, R[..., 1, 2] + R[..., 2, 1]], axis=-1),
            xp.stack([R[..., 1, 0] - R[..., 0, 1], R[..., 0, 2] + R[..., 2, 0],
                      R[..., 1, 2] + R[..., 2, 1], 1 - m00 - m11 + m22], axis=-1),
        ],
        axis=-2,
    )  # [..., 4 candidates, 4]
    pivots = xp.stack([1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
                      axis=-1)
    best = xp.argmax(pivots, axis=-1)
    q = xp.take_along_axis(cands, best[..., None, None] * xp.ones((1, 4), dtype=best.dtype),
                           axis=-2)[..., 0, :]
    q = q / xp.linalg.norm(q, axis=-1, keepdims=True)
    return q * xp.where(q[..., :1] < 0, -1.0, 1.0)


def skew(v: Array) -> Array:
    """Vector [..., 3] -> cross-product matrix [..., 3, 3] with ``skew(a) @ b = a x b``."""
    xp = _xp(v)
    z = xp.zeros_like(v[..., 0])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return xp.stack(
        [xp.stack([z, -w, y], -1), xp.stack([w, z, -x], -1), xp.stack([-y, x, z], -1)], -2
    )


def axis_angle_to_rot(w: Array) -> Array:
    """Rodrigues: rotation vector [..., 3] (axis * angle, radians) -> rotation [..., 3, 3].

    Uses the Taylor expansion near zero so that it is smooth (and differentiable) at w = 0.
    """
    xp = _xp(w)
    theta2 = xp.sum(w * w, axis=-1)[..., None, None]
    small = theta2 < 1e-8
    safe = xp.where(small, 1.0, theta2)
    theta = xp.sqrt(safe)
    a = xp.where(small, 1 - theta2 / 6, xp.sin(theta) / theta)
    b = xp.where(small, 0.5 - theta2 / 24, (1 - xp.cos(theta)) / safe)
    W = skew(w)
    eye = xp.broadcast_to(xp.eye(3, dtype=W.dtype), W.shape)
    return eye + a * W + b * (W @ W)


def rot_to_axis_angle(R: Array) -> Array:
    """Rotation [..., 3, 3] -> rotation vector [..., 3] (via the quaternion; exact near pi)."""
    xp = _xp(R)
    q = rot_to_quat(R)
    s = xp.linalg.norm(q[..., 1:], axis=-1)
    angle = 2 * xp.arctan2(s, q[..., 0])
    scale = xp.where(s < 1e-12, 2.0, angle / xp.where(s < 1e-12, 1.0, s))
    return q[..., 1:] * scale[..., None]


def rotation_angle(R: Array) -> Array:
    """Rotation angle in radians [...] of rotation matrices [..., 3, 3], robust near 0 and pi."""
    xp = _xp(R)
    cos = (R[..., 0, 0] + R[..., 1, 1] + R[..., 2, 2] - 1) / 2
    # arccos loses precision near 0; use the skew part for the sine.
    sin = 0.5 * xp.linalg.norm(
        xp.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0],
                  R[..., 1, 0] - R[..., 0, 1]], axis=-1), axis=-1)
    return xp.arctan2(sin, xp.clip(cos, -1.0, 1.0))


# ----------------------------------------------------------------------------- poses


def pose_inverse(R: Array, t: Array) -> tuple[Array, Array]:
    """Invert a rigid transform: (R [..., 3, 3], t [..., 3]) -> (R^T, -R^T t)."""
    xp = _xp(R, t)
    Rt = xp.swapaxes(R, -1, -2)
    return Rt, -(Rt @ t[..., None])[..., 0]


def pose_compose(R1: Array, t1: Array, R2: Array, t2: Array) -> tuple[Array, Array]:
    """Compose rigid transforms: apply (R2, t2) first, then (R1, t1). [..., 3, 3], [..., 3]."""
    return R1 @ R2, (R1 @ t2[..., None])[..., 0] + t1


def transform_points(R: Array, t: Array, X: Array) -> Array:
    """Apply (R [..., 3, 3], t [..., 3]) to points X [..., M, 3] -> [..., M, 3]."""
    xp = _xp(R, t, X)
    return X @ xp.swapaxes(R, -1, -2) + t[..., None, :]


def camera_center(R: Array, t: Array) -> Array:
    """Camera centre in world coordinates [..., 3] of a world-to-camera pose: c = -R^T t."""
    xp = _xp(R, t)
    return -(xp.swapaxes(R, -1, -2) @ t[..., None])[..., 0]


def pose_from_c2w(c2w: Array) -> tuple[Array, Array]:
    """Camera-to-world matrix [..., 3|4, 4] (OpenCV axes) -> world-to-camera (R, t)."""
    return pose_inverse(c2w[..., :3, :3], c2w[..., :3, 3])


def opengl_to_opencv_c2w(c2w: Array) -> Array:
    """Camera-to-world in OpenGL axes (x right, y up, -z forward) -> OpenCV axes. [..., 3|4, 4].

    Flipping the camera's y and z axes is a right-multiplication by diag(1, -1, -1, 1).
    """
    xp = _xp(c2w)
    flip = xp.asarray([1.0, -1.0, -1.0, 1.0], dtype=c2w.dtype)
    return c2w * flip[: c2w.shape[-1]]


# ----------------------------------------------------------------------------- cameras


def intrinsics_matrix(fx: Array, fy: Array, cx: Array, cy: Array) -> Array:
    """Pinhole intrinsics [..., 3, 3] from focal lengths and principal point (all [...])."""
    xp = _xp(fx, fy, cx, cy)
    fx, fy, cx, cy = (xp.asarray(v, dtype=float) for v in (fx, fy, cx, cy))
    z, o = xp.zeros_like(fx), xp.ones_like(fx)
    return xp.stack(
        [xp.stack([fx, z, cx], -1), xp.stack([z, fy, cy], -1), xp.stack([z, z, o], -1)], -2
    )


def _numbers(x: Any, what: str, name: str) -> np.ndarray:
    """``x`` as a float64 array, or VrsError naming ``what`` (ragged lists, strings,
    complex numbers are not numbers here)."""
    try:
        a = np.asarray(x)
    except ValueError:
        a = None
    if a is None or a.dtype == object or not (np.issubdtype(a.dtype, np.integer)
                                              or np.issubdtype(a.dtype, np.floating)):
        kind = "a ragged nested list" if a is None or a.dtype == object else f"dtype {a.dtype}"
        raise VrsError(f"{name}: {what} must be real numbers, got {kind}")
    return a.astype(np.float64)


def check_camera(K: Any, dist: Any = None, name: str = "image"
                 ) -> tuple[np.ndarray, np.ndarray | None]:
    """Validate a query camera: ``K`` [3, 3] (finite, last row [0, 0, 1], focal lengths of at
    least :data:`MIN_FOCAL_PX`) and ``dist`` (None, or finite with a length in
    :data:`DIST_LENGTHS`). Returns (K float64 [3, 3], dist float64 [5] or None); VrsError
    naming ``name`` and the argument otherwise. The image size is checked against K by
    :func:`vrs_jax.data.images.check_intrinsics`."""
    K = _numbers(K, "K", name)
    if K.shape != (3, 3):
        raise VrsError(f"{name}: K must be a [3, 3] matrix, got shape {K.shape}")
    if not np.all(np.isfinite(K)):
        raise VrsError(f"{name}: K has non-finite entries (NaN or inf): {K.tolist()}")
    if np.any(K[2] != (0.0, 0.0, 1.0)):
        raise VrsError(f"{name}: K's last row must be [0, 0, 1], got {K[2].tolist()}")
    fx, fy = K[0, 0], K[1, 1]
    if fx <= 0 or fy <= 0:
        raise VrsError(f"{name}: focal lengths must be positive, got fx={fx:g} fy={fy:g}")
    if min(fx, fy) < MIN_FOCAL_PX:
        raise VrsError(f"{name}: focal lengths fx={fx:g} fy={fy:g} are below "
                       f"{MIN_FOCAL_PX:g} pixel: K must be in pixels")
    if dist is None:
        return K, None
    d = _numbers(dist, "dist", name)
    if d.ndim != 1 or d.size not in DIST_LENGTHS:
        raise VrsError(f"{name}: dist must be (k1, k2, p1, p2[, k3]): "
                       f"{' or '.join(map(str, DIST_LENGTHS))} numbers, got shape {d.shape}")
    if not np.all(np.isfinite(d)):
        raise VrsError(f"{name}: dist has non-finite entries (NaN or inf): {d.tolist()}")
    return K, np.pad(d, (0, 5 - d.size))


def scale_intrinsics(K: Array, sx: float, sy: float | None = None) -> Array:
    """Intrinsics for an image resized by (sx, sy), in COLMAP's pixel convention. [..., 3, 3].

    With pixel centres at half-integers, resizing maps u -> sx * u exactly, so both the focal
    length and the principal point scale (no half-pixel shift, unlike OpenCV's convention).
    """
    xp = _xp(K)
    sy = sx if sy is None else sy
    S = xp.asarray([[sx, 0, 0], [0, sy, 0], [0, 0, 1]], dtype=K.dtype)
    return S @ K


def distort(xn: Array, dist: Array) -> Array:
    """Apply OpenCV radial/tangential distortion to normalised coordinates.

    Args:
      xn: [..., 2] normalised image coordinates (x/z, y/z).
      dist: [..., 5] ``(k1, k2, p1, p2, k3)``; broadcast against xn's leading axes.
    Returns:
      [..., 2] distorted normalised coordinates.
    """
    xp = _xp(xn, dist)
    x, y = xn[..., 0], xn[..., 1]
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
    dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xp.stack([x * radial + dx, y * radial + dy], axis=-1)


def undistort_normalized(xd: Array, dist: Array, iterations: int = 20) -> Array:
    """Invert :func:`distort` by fixed-point iteration (as OpenCV's undistortPoints does).

    Args:
      xd: [..., 2] distorted normalised coordinates.
      dist: [..., 5] distortion coefficients.
      iterations: fixed number of iterations (a static shape for jit).
    Returns:
      [..., 2] undistorted normalised coordinates.
    """
    xp = _xp(xd, dist)
    x = xd
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    for _ in range(iterations):
        u, v = x[..., 0], x[..., 1]
        r2 = u * u + v * v
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2
        dx = 2 * p1 * u * v + p2 * (r2 + 2 * u * u)
        dy = p1 * (r2 + 2 * v * v) + 2 * p2 * u * v
        x = xp.stack([(xd[..., 0] - dx) / radial, (xd[..., 1] - dy) / radial], axis=-1)
    return x


def project(K: Array, R: Array, t: Array, X: Array, dist: Array | None = None
            ) -> tuple[Array, Array]:
    """Project world points into a camera.

    Args:
      K: [..., 3, 3] intrinsics (COLMAP pixel convention).
      R, t: [..., 3, 3], [..., 3] world-to-camera pose.
      X: [..., M, 3] world points.
      dist: optional [..., 5] OpenCV distortion coefficients.
    Returns:
      uv: [..., M, 2] pixel coordinates; z: [..., M] depth along the optical axis
      (points with z <= 0 are behind the camera; their uv is not meaningful).
    """
    xp = _xp(K, R, t, X)
    Xc = transform_points(R, t, X)
    z = Xc[..., 2]
    zs = xp.where(xp.abs(z) < 1e-12, 1e-12, z)
    xn = Xc[..., :2] / zs[..., None]
    if dist is not None:
        xn = distort(xn, dist[..., None, :])
    uv = xn @ xp.swapaxes(K[..., :2, :2], -1, -2) + K[..., None, :2, 2]
    return uv, z


def unproject(K: Array, uv: Array, dist: Array | None = None) -> Array:
    """Pixel coordinates [..., M, 2] -> camera-frame ray directions [..., M, 3] with z = 1.

    This is ``K^-1 [u, v, 1]`` (then undistorted when ``dist`` [..., 5] is given).
    """
    xp = _xp(K, uv)
    Kinv = xp.linalg.inv(K)
    xn = uv @ xp.swapaxes(Kinv[..., :2, :2], -1, -2) + Kinv[..., None, :2, 2]
    if dist is not None:
        xn = undistort_normalized(xn, dist[..., None, :])
    return xp.concatenate([xn, xp.ones_like(xn[..., :1])], axis=-1)


def pixel_rays(K: Array, R: Array, t: Array, uv: Array, dist: Array | None = None
               ) -> tuple[Array, Array]:
    """World-frame rays through pixel coordinates.

    Args:
      K: [..., 3, 3]; R, t: [..., 3, 3], [..., 3] world-to-camera; uv: [..., M, 2].
    Returns:
      origins [..., M, 3] (the camera centre), directions [..., M, 3] (not normalised: their
      z component in the camera frame is 1, so ``origin + d * direction`` is the point at
      depth d along the optical axis).
    """
    xp = _xp(K, R, t, uv)
    d_cam = unproject(K, uv, dist)
    d_world = d_cam @ R  # R^T d for row vectors
    o = xp.broadcast_to(camera_center(R, t)[..., None, :], d_world.shape)
    return o, d_world


# mip-NeRF: a square pixel of side w has the second moment of a disc of radius w * 2/sqrt(12).
PIXEL_TO_RADIUS = 2.0 / float(np.sqrt(12.0))


def cone_radius(K: Array, spacing: Array = 1.0) -> Array:
    """Mip-NeRF cone radius at unit depth of rays ``spacing`` pixels apart (the one definition).

    Directions are scaled to unit camera depth (``K^-1 [u, v, 1]``), so a spacing of ``s`` pixels
    is ``s / f`` on the z = 1 plane, with ``f = sqrt(fx fy)`` (the focal length of a pixel of
    the same area). Args: K [..., 3, 3]; spacing [...] pixels. Returns [...].
    """
    xp = _xp(K, spacing)
    return spacing * PIXEL_TO_RADIUS / xp.sqrt(K[..., 0, 0] * K[..., 1, 1])


def pixel_grid(width: int, height: int) -> np.ndarray:
    """Pixel-centre coordinates of a whole image [H, W, 2] in COLMAP's convention."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([u, v], axis=-1)


# ----------------------------------------------------------------------------- errors


def pose_errors(R_est: Array, t_est: Array, R_gt: Array, t_gt: Array) -> tuple[Array, Array]:
    """Localization errors between world-to-camera poses.

    Returns:
      translation error [...] in metres (distance between camera centres) and rotation error
      [...] in degrees (angle of R_est R_gt^T).
    """
    xp = _xp(R_est, t_est, R_gt, t_gt)
    dc = xp.linalg.norm(camera_center(R_est, t_est) - camera_center(R_gt, t_gt), axis=-1)
    dR = R_est @ xp.swapaxes(R_gt, -1, -2)
    return dc, xp.degrees(rotation_angle(dR))
