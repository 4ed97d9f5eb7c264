"""Absolute pose from 2D-3D correspondences: an OpenCV RANSAC seed, then robust LM refinement.

Both stages run inside ``jax.jit`` (and ``jax.vmap`` over a batch of queries) with fixed
shapes: correspondences are padded to a static ``M`` and carry a boolean mask.

- :func:`ransac_pnp` calls ``cv2.solvePnPRansac`` on the host through ``jax.pure_callback``
  and returns a fixed-size result (pose, inlier mask [M], success flag); it never raises.
- :func:`refine_pose` minimises the robust reprojection cost
  ``0.5 * sum_i w_i * rho(|e_i|^2)`` (Ceres' convention, so the numbers compare with COLMAP's)
  with optimistix' Levenberg-Marquardt over a 6-vector SE(3) tangent update applied on the
  left of the seed pose. Errors come back as results (``throw=False``), and the seed is kept
  whenever the refined cost is not lower, so refinement never worsens the seed's robust cost.
- :func:`estimate_pose` chains the two and returns a :class:`PoseResult`.

Pixel convention. Points and intrinsics follow COLMAP (the centre of the top-left pixel is
(0.5, 0.5)). OpenCV's projection is the same formula ``u = fx * x / z + cx`` -- conventions
differ only in which (u, v) the *pixel array* element [0, 0] sits at, i.e. in how ``cx, cy``
and the keypoints are expressed. Since both the points and ``K`` given here are in COLMAP's
convention, they are handed to OpenCV unchanged: shifting the points by -0.5 would require
shifting ``cx, cy`` by -0.5 too, and the two shifts cancel in the projection. (A +0.5 shift
applies where OpenCV *keypoint detections* enter the project, in features/keypoints.py.)
"""

from __future__ import annotations

import dataclasses
import functools
import warnings
from typing import Any, NamedTuple

import cv2
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from vrs_jax import geometry

Array = Any

# RANSAC methods available through ``PnPConfig.method``.
#   "magsac":   OpenCV's USAC framework with MAGSAC++ scoring, sigma-consensus local
#               optimisation and a MAGSAC final polish, P3P minimal samples.
#   "usac":     USAC with MSAC scoring, inner + iterative LO and a least-squares polish.
#   "sqpnp":    classic cv2 RANSAC (5-point EPnP samples), final fit on the inliers by SQPnP.
METHODS = ("magsac", "usac", "sqpnp")


@dataclasses.dataclass(frozen=True)
class PnPConfig:
    """RANSAC seed and robust refinement settings (one source of truth; hashable, so static
    under jit).

    Choices measured on synthetic problems (640x480, f = 525, 1 px noise, 400 points at
    1-5 m, 10 problems each): at 50% outliers every method finds the same inliers; at 80% the
    classic 5-point EPnP RANSAC (``sqpnp``) takes ~0.5 s per problem and at 90% fails on 8 of
    10 within 10k iterations, while USAC's 3-point P3P sampling succeeds on all of them in
    5-40 ms. MAGSAC++ scoring marginalises over the noise scale, so it depends least on the
    threshold (Barath et al., CVPR 2020); its pose matched the other USAC variants here.
    """

    # MAGSAC++ (USAC, P3P samples): robust at high outlier ratios, fast, threshold-tolerant.
    method: str = "magsac"
    # Inlier threshold in pixels (MAGSAC: the upper bound of the noise scale it marginalises
    # over). 6 px at ~640 px image width: well above 1-2 px keypoint noise and the small
    # misalignment of NeRF-rendered patches, small enough that a random outlier lands inside it
    # with probability ~ pi 6^2 / (640 * 480) ~ 4e-4.
    threshold_px: float = 6.0
    # RANSAC iteration cap: 10k P3P samples find a 3-point all-inlier sample with 99.99%
    # confidence down to ~10% inliers; the adaptive stopping criterion exits far earlier on
    # easy problems (measured on 1000 points: 4-8 ms at 50% outliers, ~40 ms at 90%).
    max_iterations: int = 10000
    # Confidence of the adaptive stopping criterion (as pycolmap's default 0.9999).
    confidence: float = 0.9999
    # Fewer valid correspondences than this -> no RANSAC call, success False. P3P needs 3
    # points plus at least one to disambiguate; 6 gives the 5-point EPnP of "sqpnp" room.
    min_points: int = 6
    # A pose supported by fewer inliers is reported as a failure (then localize falls back to
    # the top-1 reference pose): a wrong pose from an outlier sample gathers a few chance
    # inliers (its own sample points and whatever falls within the threshold); 12 makes such
    # a pose unlikely at the few hundred matches per query we expect.
    min_inliers: int = 12
    # Seed of OpenCV's RANSAC generator: fixed, so the callback is a pure function.
    seed: int = 0

    # Robust loss of the refinement: "cauchy" (as COLMAP's absolute pose refinement) or
    # "huber". Cauchy is redescending-like: residual outliers that slip under the RANSAC
    # threshold get weight ~ c^2 / e^2 and barely move the pose.
    loss: str = "cauchy"
    # Loss scale c in pixels: 1 px (COLMAP's default loss_function_scale), the order of the
    # keypoint noise; errors above c are progressively down-weighted.
    loss_scale_px: float = 1.0
    # Levenberg-Marquardt steps: from a RANSAC seed the cost stops decreasing after ~8 steps;
    # in float32 the following steps are rejected on round-off of the cost until the trust
    # region collapses and the tolerance test passes (25-30 steps in all, ~10 ms for 1000
    # points on CPU). 50 is a safe cap that keeps the while-loop bounded under jit/vmap;
    # hitting it only sets ``converged`` False: the best accepted iterate is still used.
    max_steps: int = 50
    # LM tolerances (optimistix' Cauchy criterion: |step| < atol + rtol |y| on the tangent
    # update AND |change of each residual| < atol + rtol |r|, in pixels). The update's
    # translation is in units of the mean point depth, so 1e-6 means ~1 um at 1 m and ~1e-6 rad;
    # 1e-5 px is above the float32 round-off of the projected residuals.
    rtol: float = 1e-6
    atol: float = 1e-5

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"PnPConfig.method must be one of {METHODS}, not {self.method!r}")
        if self.loss not in ("cauchy", "huber"):
            raise ValueError(f"PnPConfig.loss must be 'cauchy' or 'huber', not {self.loss!r}")
        if self.min_points < 4:
            raise ValueError("PnPConfig.min_points must be at least 4")


CONFIGS: dict[str, PnPConfig] = {
    # The defaults above, used for every reported number.
    "paper": PnPConfig(),
    # Fewer RANSAC iterations and LM steps for quick CPU runs (tests, --quick demos); only
    # matters at very high outlier ratios.
    "cpu-small": PnPConfig(max_iterations=2000, max_steps=30),
}


def get_config(name: str) -> PnPConfig:
    """Named PnP configuration (``paper`` or ``cpu-small``)."""
    if name not in CONFIGS:
        raise KeyError(f"unknown PnP config {name!r}; choose from {sorted(CONFIGS)}")
    return CONFIGS[name]


# ----------------------------------------------------------------------------- RANSAC seed


def _usac_params(cfg: PnPConfig) -> cv2.UsacParams:
    p = cv2.UsacParams()
    p.threshold = float(cfg.threshold_px)
    p.confidence = float(cfg.confidence)
    p.maxIterations = int(cfg.max_iterations)
    p.randomGeneratorState = int(cfg.seed)
    p.isParallel = False  # deterministic, and the host CPU is shared with JAX
    p.sampler = cv2.SAMPLING_UNIFORM
    if cfg.method == "magsac":
        p.score = cv2.SCORE_METHOD_MAGSAC
        p.loMethod = cv2.LOCAL_OPTIM_SIGMA
        p.final_polisher = cv2.MAGSAC
    else:
        p.score = cv2.SCORE_METHOD_MSAC
        p.loMethod = cv2.LOCAL_OPTIM_INNER_AND_ITER_LO
        p.final_polisher = cv2.LSQ_POLISHER
    return p


def ransac_pnp_host(points2d: np.ndarray, points3d: np.ndarray, mask: np.ndarray,
                    K: np.ndarray, cfg: PnPConfig
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """One RANSAC PnP problem on the host (numpy in, numpy out; never raises).

    Args:
      points2d: [M, 2] pixel coordinates (COLMAP convention, like ``K``).
      points3d: [M, 3] world points.
      mask: [M] bool, valid correspondences.
      K: [3, 3] intrinsics.
    Returns:
      R [3, 3], t [3] (world-to-camera; identity/zero on failure), inliers [M] bool, success.
    """
    M = points2d.shape[0]
    R_fail, t_fail, inl_fail = np.eye(3), np.zeros(3), np.zeros(M, dtype=bool)
    p2 = np.asarray(points2d, dtype=np.float64).reshape(M, 2)
    p3 = np.asarray(points3d, dtype=np.float64).reshape(M, 3)
    K = np.asarray(K, dtype=np.float64).reshape(3, 3)
    valid = np.array(mask, dtype=bool).reshape(M)  # a copy: callback inputs are read-only
    valid &= np.isfinite(p2).all(-1) & np.isfinite(p3).all(-1)
    idx = np.flatnonzero(valid)
    if idx.size < cfg.min_points or not np.isfinite(K).all():
        return R_fail, t_fail, inl_fail, False
    obj = np.ascontiguousarray(p3[idx])
    img = np.ascontiguousarray(p2[idx])
    try:
        if cfg.method == "sqpnp":
            ok, rvec, tvec, inl = cv2.solvePnPRansac(
                obj, img, K, None, iterationsCount=int(cfg.max_iterations),
                reprojectionError=float(cfg.threshold_px), confidence=float(cfg.confidence),
                flags=cv2.SOLVEPNP_SQPNP)
        else:
            ok, _, rvec, tvec, inl = cv2.solvePnPRansac(obj, img, K.copy(), None,
                                                        params=_usac_params(cfg))
    except cv2.error:
        return R_fail, t_fail, inl_fail, False
    if not ok or rvec is None or tvec is None or inl is None:
        return R_fail, t_fail, inl_fail, False
    R = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3))[0]
    t = np.asarray(tvec, dtype=np.float64).reshape(3)
    if not (np.isfinite(R).all() and np.isfinite(t).all()):
        return R_fail, t_fail, inl_fail, False
    inliers = np.zeros(M, dtype=bool)
    inliers[idx[np.asarray(inl, dtype=np.int64).reshape(-1)]] = True
    if inliers.sum() < cfg.min_inliers:
        return R_fail, t_fail, inl_fail, False
    return R, t, inliers, True


def _ransac_batched_host(points2d, points3d, mask, K, *, cfg: PnPConfig, dtype):
    """pure_callback body: any leading batch axes (``vmap_method="broadcast_all"``)."""
    points2d, points3d = np.asarray(points2d), np.asarray(points3d)
    mask, K = np.asarray(mask), np.asarray(K)
    batch = points2d.shape[:-2]
    M = points2d.shape[-2]
    R = np.zeros(batch + (3, 3), dtype=dtype)
    t = np.zeros(batch + (3,), dtype=dtype)
    inl = np.zeros(batch + (M,), dtype=bool)
    ok = np.zeros(batch, dtype=bool)
    for i in np.ndindex(*batch):
        try:
            R[i], t[i], inl[i], ok[i] = ransac_pnp_host(points2d[i], points3d[i], mask[i], K[i],
                                                        cfg)
        except Exception as e:  # raising inside pure_callback is undefined behaviour
            warnings.warn(f"RANSAC PnP failed on the host: {e!r}", RuntimeWarning, stacklevel=1)
            R[i], t[i], inl[i], ok[i] = np.eye(3), 0.0, False, False
    return R, t, inl, ok


def ransac_pnp(points2d: Array, points3d: Array, mask: Array, K: Array, cfg: PnPConfig
               ) -> tuple[Array, Array, Array, Array]:
    """RANSAC PnP seed through OpenCV, callable inside jit and vmap.

    Args:
      points2d: [M, 2] pixel coordinates (COLMAP convention, like ``K``).
      points3d: [M, 3] world points.
      mask: [M] bool, valid correspondences (padding is False).
      K: [3, 3] intrinsics.
      cfg: PnPConfig (static).
    Returns:
      R [3, 3], t [3] world-to-camera (identity and zero on failure), inliers [M] bool,
      success [] bool. Fewer than ``cfg.min_points`` valid correspondences, fewer than
      ``cfg.min_inliers`` inliers or an OpenCV failure give success False, never an exception.
    """
    points2d = jnp.asarray(points2d)
    dtype = jnp.result_type(points2d.dtype, jnp.float32)
    M = points2d.shape[-2]
    shapes = (jax.ShapeDtypeStruct((3, 3), dtype), jax.ShapeDtypeStruct((3,), dtype),
              jax.ShapeDtypeStruct((M,), jnp.bool_), jax.ShapeDtypeStruct((), jnp.bool_))
    host = functools.partial(_ransac_batched_host, cfg=cfg, dtype=np.dtype(dtype))
    # broadcast_all: under vmap the callback receives the whole batch at once (one host
    # round trip per batch instead of one per query) with every input tiled to the batch, so
    # the host body just loops over the leading axes.
    return jax.pure_callback(host, shapes, points2d, jnp.asarray(points3d), jnp.asarray(mask),
                             jnp.asarray(K), vmap_method="broadcast_all")


# ----------------------------------------------------------------------------- refinement


class RefineInfo(NamedTuple):
    """Diagnostics of :func:`refine_pose` (all scalars)."""

    cost_seed: Array  # robust cost 0.5 * sum w rho(|e|^2) at the seed, pixels^2
    cost: Array  # robust cost of the returned pose (<= cost_seed)
    improved: Array  # bool: the LM solution was kept (its cost is lower than the seed's)
    converged: Array  # bool: optimistix reported success (not max_steps or a failure)
    steps: Array  # int: LM steps taken


def robust_rho(s: Array, loss: str, scale: float) -> Array:
    """Robust loss of squared residual norms ``s`` [...] (Ceres' definitions), same shape.

    cauchy: ``c^2 log(1 + s / c^2)``; huber: ``s`` for ``s <= c^2``, else ``2 c sqrt(s) - c^2``.
    """
    return s * _rho_over_s(s, loss, scale)


def _rho_over_s(s: Array, loss: str, scale: float) -> Array:
    """``rho(s) / s``, smooth at s = 0 (-> 1), for the robustified residuals."""
    c2 = scale * scale
    u = s / c2
    small = u < 1e-4
    u_safe = jnp.where(small, 1.0, u)
    if loss == "cauchy":
        return jnp.where(small, 1.0 - u / 2 + u * u / 3, jnp.log1p(u_safe) / u_safe)
    return jnp.where(u <= 1.0, 1.0, 2.0 / jnp.sqrt(jnp.where(u <= 1.0, 1.0, u)) - 1.0 / u_safe)


def _camera_points(R: Array, t: Array, X: Array) -> Array:
    return X @ R.T + t


def _reprojection(K: Array, Xc: Array, valid: Array) -> tuple[Array, Array]:
    """Project camera-frame points [M, 3] -> uv [M, 2], z [M]; invalid points get (0, 0, 1)."""
    Xc = jnp.where(valid[:, None], Xc, jnp.asarray([0.0, 0.0, 1.0], Xc.dtype))
    z = Xc[:, 2]
    zs = jnp.where(jnp.abs(z) < 1e-9, 1e-9, z)
    xn = Xc[:, :2] / zs[:, None]
    return xn @ K[:2, :2].T + K[:2, 2], z


def _robust_residuals(delta: Array, args, *, loss: str, loss_scale: float) -> Array:
    """LM residuals [M, 2] of a tangent update ``delta = (w, v)`` applied on the left.

    The camera-frame points of the seed ``Xc0`` move to ``exp(w) Xc0 + scale * v``; each 2D
    error ``e`` is multiplied by ``sqrt(weight * rho(|e|^2) / |e|^2)`` so that
    ``0.5 * sum |r|^2`` is exactly the robust cost.
    """
    Xc0, uv, w, valid, K, depth_scale = args
    dR = geometry.axis_angle_to_rot(delta[:3])
    Xc = Xc0 @ dR.T + depth_scale * delta[3:]
    proj, _ = _reprojection(K, Xc, valid)
    e = jnp.where(valid[:, None], proj - uv, 0.0)
    s = jnp.sum(e * e, axis=-1)
    # sqrt(w) separately: d sqrt(x)/dx is infinite at 0, and rho/s > 0 keeps this one finite.
    f = jnp.sqrt(w) * jnp.sqrt(_rho_over_s(s, loss, loss_scale))
    return e * f[:, None]


def robust_cost(R: Array, t: Array, points2d: Array, points3d: Array, weights: Array, K: Array,
                cfg: PnPConfig) -> Array:
    """Robust reprojection cost ``0.5 * sum_i w_i rho(|e_i|^2)`` [] (pixels^2) of a pose.

    Points with weight 0 contribute nothing (and may hold any finite or non-finite padding).
    """
    R, t, uv, X, w, K = _as_float(R, t, points2d, points3d, weights, K)
    valid = (w > 0) & jnp.all(jnp.isfinite(X), -1) & jnp.all(jnp.isfinite(uv), -1)
    w = jnp.where(valid, w, 0.0)
    proj, _ = _reprojection(K, _camera_points(R, t, jnp.where(valid[:, None], X, 0.0)), valid)
    e = jnp.where(valid[:, None], proj - jnp.where(valid[:, None], uv, 0.0), 0.0)
    return 0.5 * jnp.sum(w * robust_rho(jnp.sum(e * e, -1), cfg.loss, cfg.loss_scale_px))


def _as_float(*arrays):
    dtype = jnp.result_type(*[jnp.asarray(a).dtype for a in arrays], jnp.float32)
    return tuple(jnp.asarray(a, dtype=dtype) for a in arrays)


def refine_pose(R: Array, t: Array, points2d: Array, points3d: Array, weights: Array, K: Array,
                cfg: PnPConfig) -> tuple[Array, Array, RefineInfo]:
    """Levenberg-Marquardt refinement of a robust reprojection error (jittable, vmappable).

    Args:
      R, t: [3, 3], [3] seed pose, world-to-camera.
      points2d: [M, 2] pixel coordinates; points3d: [M, 3] world points.
      weights: [M] non-negative weights (0 for masked / outlier correspondences; the
        RANSAC inlier mask as float is the usual choice).
      K: [3, 3] intrinsics.
      cfg: PnPConfig (static).
    Returns:
      R [3, 3], t [3] refined pose -- the seed itself when LM did not lower the robust cost --
      and a :class:`RefineInfo`.
    """
    R, t, uv, X, w, K = _as_float(R, t, points2d, points3d, weights, K)
    if uv.shape[0] == 0:  # static: no correspondences at all, nothing to refine
        zero = jnp.zeros((), R.dtype)
        return R, t, RefineInfo(cost_seed=zero, cost=zero, improved=jnp.array(False),
                                converged=jnp.array(True), steps=jnp.array(0, jnp.int32))
    valid = (w > 0) & jnp.all(jnp.isfinite(X), -1) & jnp.all(jnp.isfinite(uv), -1)
    w = jnp.where(valid, w, 0.0)
    uv = jnp.where(valid[:, None], uv, 0.0)
    Xc0 = _camera_points(R, t, jnp.where(valid[:, None], X, 0.0))
    # Translation update in units of the mean point depth: both halves of the tangent vector
    # are then dimensionless (radians ~ metres / depth), which balances LM's damping and makes
    # one tolerance fit both.
    n_valid = jnp.maximum(jnp.sum(valid), 1)
    depth_scale = jnp.sum(jnp.where(valid, jnp.abs(Xc0[:, 2]), 0.0)) / n_valid
    depth_scale = jnp.where(depth_scale > 0, depth_scale, 1.0)
    args = (Xc0, uv, w, valid, K, depth_scale)
    fn = functools.partial(_robust_residuals, loss=cfg.loss, loss_scale=float(cfg.loss_scale_px))
    # The damped 6 x 6 normal equations by Cholesky, not optimistix' default QR of the
    # [2M + 6, 6] system: six unknowns in tangent units balanced by depth_scale keep them
    # well conditioned, and XLA on CPU runs a program that holds LAPACK's QR (geqrf) markedly
    # slower around it (the guided stage, patch rendering included: 115 ms instead of
    # 180 ms per query on two cores).
    solver = optx.LevenbergMarquardt(rtol=cfg.rtol, atol=cfg.atol,
                                     linear_solver=lx.Normal(lx.Cholesky()))
    delta0 = jnp.zeros(6, dtype=R.dtype)
    sol = optx.least_squares(fn, solver, delta0, args=args,
                             max_steps=cfg.max_steps, throw=False)
    delta = sol.value

    def cost_of(d):
        r = fn(d, args)
        return 0.5 * jnp.sum(r * r)

    cost_seed, cost_new = cost_of(delta0), cost_of(delta)
    improved = jnp.isfinite(cost_new) & jnp.all(jnp.isfinite(delta)) & (cost_new < cost_seed)
    dR = geometry.axis_angle_to_rot(jnp.where(improved, delta[:3], 0.0))
    R_new = dR @ R
    t_new = dR @ t + depth_scale * jnp.where(improved, delta[3:], 0.0)
    R_out = jnp.where(improved, R_new, R)
    t_out = jnp.where(improved, t_new, t)
    info = RefineInfo(cost_seed=cost_seed, cost=jnp.where(improved, cost_new, cost_seed),
                      improved=improved, converged=sol.result == optx.RESULTS.successful,
                      steps=jnp.asarray(sol.stats["num_steps"], jnp.int32))
    return R_out, t_out, info


# ----------------------------------------------------------------------------- both


class PoseResult(NamedTuple):
    """Output of :func:`estimate_pose` (a pytree of arrays; batched under vmap)."""

    R: Array  # [3, 3] world-to-camera rotation (identity when success is False)
    t: Array  # [3] world-to-camera translation (zeros when success is False)
    inliers: Array  # [M] bool: reprojection error < threshold at the final pose
    n_inliers: Array  # [] int32
    success: Array  # [] bool
    cost: Array  # [] robust cost of the final pose over the RANSAC inliers (pixels^2)
    cost_seed: Array  # [] robust cost of the RANSAC seed over the same points


def inlier_mask(R: Array, t: Array, points2d: Array, points3d: Array, mask: Array, K: Array,
                threshold_px: float) -> Array:
    """[M] bool: valid, in front of the camera, and reprojection error below the threshold."""
    R, t, uv, X, K = _as_float(R, t, points2d, points3d, K)
    valid = mask & jnp.all(jnp.isfinite(X), -1) & jnp.all(jnp.isfinite(uv), -1)
    Xc = _camera_points(R, t, jnp.where(valid[:, None], X, 0.0))
    proj, z = _reprojection(K, Xc, valid)
    err2 = jnp.sum((proj - jnp.where(valid[:, None], uv, 0.0)) ** 2, -1)
    return valid & (z > 0) & (err2 < threshold_px * threshold_px)


def estimate_pose(points2d: Array, points3d: Array, mask: Array, K: Array, cfg: PnPConfig
                  ) -> PoseResult:
    """RANSAC seed + robust LM refinement on the seed's inliers; jittable and vmappable.

    Args:
      points2d: [M, 2] pixel coordinates (COLMAP convention); points3d: [M, 3] world points;
      mask: [M] bool valid correspondences; K: [3, 3]; cfg: PnPConfig (static).
    Returns:
      PoseResult. On failure (too few points or inliers, OpenCV failure) the pose is the
      identity, ``success`` is False and nothing raises.
    """
    mask = jnp.asarray(mask, dtype=bool)
    R0, t0, inl0, ok = ransac_pnp(points2d, points3d, mask, K, cfg)
    return refine_seed(R0, t0, inl0, ok, points2d, points3d, mask, K, cfg)


def refine_seed(R0: Array, t0: Array, inl0: Array, ok: Array, points2d: Array, points3d: Array,
                mask: Array, K: Array, cfg: PnPConfig, max_rows: int | None = None
                ) -> PoseResult:
    """The second half of :func:`estimate_pose`: refine a RANSAC seed on its inliers [M],
    recount inliers at the refined pose and flag success (also used to time the stages
    separately).

    ``max_rows`` (static): the LM sees only that many slots, the seed's inliers first in slot
    order, instead of all M (the other slots weigh 0 and cost the same work each step); with
    more inliers than that the first ``max_rows`` refine the pose. The recount uses all M."""
    uv, X, w = points2d, points3d, inl0.astype(R0.dtype)
    if max_rows is not None and max_rows < points2d.shape[0]:
        rows = jnp.argsort(~inl0, stable=True)[:max_rows]
        uv, X, w = uv[rows], X[rows], w[rows]
    R, t, info = refine_pose(R0, t0, uv, X, w, K, cfg)
    inliers = inlier_mask(R, t, points2d, points3d, mask, K, cfg.threshold_px) & ok
    n_inl = jnp.sum(inliers).astype(jnp.int32)
    success = ok & (n_inl >= cfg.min_inliers) & jnp.all(jnp.isfinite(R)) & jnp.all(
        jnp.isfinite(t))
    R = jnp.where(success, R, jnp.eye(3, dtype=R.dtype))
    t = jnp.where(success, t, 0.0)
    return PoseResult(R=R, t=t, inliers=inliers & success, n_inliers=jnp.where(success, n_inl, 0),
                      success=success, cost=info.cost, cost_seed=info.cost_seed)
