"""Tracking a stream of frames with the map (``Localizer.track``; docs/design.md, section 1).

A robot's frames arrive in order, each close to the last. With the previous poses as a prior,
a frame needs only the guided pass, started from a predicted pose instead of a first pass's:

    frame pass  (``track.frame_pass``) after a "localized" frame that was not relocalized:
                the frame matched to that frame's keypoints that sit on map points, RANSAC
                and refinement on those points, the guided pass rendered at that pose
                (:func:`frame_step`); kept when "localized" and the guided pass's own pose
                agrees with it (:func:`frame_rejection`), else the steps below
    predict     constant velocity: the relative motion of the last two good poses applied
                once more (scaled to the frame gap on SE(3)); one good pose: that pose
    references  the k reference images with the most map points in view of the predicted
                camera (:func:`reference_scores`), instead of retrieval
    views       (render mode, ``track.reference_views``) their first-pass descriptors
                rendered from their own cameras, given by the host from the stream's
                descriptor cache (rendered once per stream): ``track_step``'s ``views``
    track pass  the guided pass (``stages.guided_pass``) from the predicted pose: those
                images' map points projected with it, described by the views or rendered at
                the prediction (render mode without views), matched within
                ``track.radius_px`` of their projections, the pose refined
    re-match    ``track.refine_passes`` guided passes from the tracked pose on the patches
                the track pass rendered (nothing rendered again), with the config's guided
                radius and inlier threshold: the tight gates of a guided pass
    check       the frame matched to the same candidates without the prediction (every
                query keypoint against every candidate descriptor, as the first pass
                matches; nothing rendered again), RANSAC and refinement: a pose that owes
                nothing to the prediction (:func:`check_pass`); then, with
                ``track.check_guided``, the config's guided pass from that pose (map points
                rendered there), as full localization refines its first pass
    accept      the verdict of the pose confidence is "localized", enough inliers, the
                pose did not jump far from the prediction, and the check pass's pose agrees
                with it (:func:`rejection`); else the check pass's pose if it has enough
                inliers and its verdict is "localized" or (``track.keep_uncertain_check``)
                "uncertain" (:func:`accepted`); else the frame is localized in full
                (retrieval + first pass + guided)

The first frame, a frame after more than ``track.max_gap`` frames without a good pose, and a
frame whose tracking is rejected are localized in full. An unreadable frame, or one with fewer
keypoints than PnP needs inliers (a blank frame), is flagged (``error``) and skipped; the
prior then comes from the last good poses. Everything from the references to the guided
passes is one jitted function with fixed shapes (:func:`track_step`): one compilation for the
whole stream. The prediction, the acceptance and the loop are host code (numpy).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from tqdm import tqdm

from vrs_jax import geometry
from vrs_jax.data.images import read_gray
from vrs_jax.errors import VrsError
from vrs_jax.features.matching import match, planar_sq_distances
from vrs_jax.localize import stages as st
from vrs_jax.localize.confidence import (
    LOCALIZED_AT,
    map_scale,
    one_confidence,
    result_fields,
    weakest_test,
)
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.localize.pnp import ransac_pnp, refine_seed
from vrs_jax.localize.query import Query
from vrs_jax.localize.stages import LocalizeResult
from vrs_jax.maps import Map

Array = Any
UNCERTAIN_BELOW = float(np.nextafter(LOCALIZED_AT, 0.0))  # the largest "uncertain" confidence


# ----------------------------------------------------------------------------- prediction


def se3_log(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Twist (w [3] rotation vector, u [3]) of the rigid motion (R [3, 3], t [3]):
    ``se3_exp(*se3_log(R, t)) == (R, t)``."""
    w = np.asarray(geometry.rot_to_axis_angle(np.asarray(R, np.float64)), np.float64)
    th2 = float(w @ w)
    W = geometry.skew(w)
    if th2 < 1e-12:
        c = 1.0 / 12.0
    else:
        th = np.sqrt(th2)
        c = (1.0 - th * np.sin(th) / (2.0 * (1.0 - np.cos(th)))) / th2
    V_inv = np.eye(3) - 0.5 * W + c * (W @ W)
    return w, V_inv @ np.asarray(t, np.float64)


def se3_exp(w: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid motion (R [3, 3], t [3]) of the twist (w [3], u [3])."""
    w = np.asarray(w, np.float64)
    th2 = float(w @ w)
    W = geometry.skew(w)
    if th2 < 1e-12:
        a, b = 0.5, 1.0 / 6.0
    else:
        th = np.sqrt(th2)
        a, b = (1.0 - np.cos(th)) / th2, (th - np.sin(th)) / (th2 * th)
    V = np.eye(3) + a * W + b * (W @ W)
    return np.asarray(geometry.axis_angle_to_rot(w), np.float64), V @ np.asarray(u, np.float64)


def relative_motion(R0: np.ndarray, t0: np.ndarray, R1: np.ndarray, t1: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The motion D [3, 3], [3] from world-to-camera pose 0 to pose 1: ``P1 = D P0``
    (camera 0's coordinates to camera 1's)."""
    R0, t0, R1, t1 = (np.asarray(a, np.float64) for a in (R0, t0, R1, t1))
    dR = R1 @ R0.T
    return dR, t1 - dR @ t0


def predict_pose(history: Sequence[tuple[int, np.ndarray, np.ndarray]], frame: int,
                 max_gap: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The constant-velocity pose prior of frame ``frame`` (world-to-camera R [3, 3], t [3],
    float64) from the last good poses ``history`` [(frame index, R, t), ...] (oldest first).

    None without a good pose, or when the last one is more than ``max_gap`` frames back. One
    good pose (or two more than ``max_gap`` frames apart): that pose. Two: their relative
    motion D over their frame gap n, applied for the gap g to this frame, ``D^(g/n) P_last``
    on SE(3) (D itself for consecutive frames).
    """
    if not history:
        return None
    f1, R1, t1 = history[-1]
    gap = frame - f1
    if gap < 1 or gap > max_gap:
        return None
    R1, t1 = np.asarray(R1, np.float64), np.asarray(t1, np.float64)
    if len(history) < 2 or f1 - history[-2][0] > max_gap:
        return R1, t1
    f0, R0, t0 = history[-2]
    w, u = se3_log(*relative_motion(R0, t0, R1, t1))
    s = gap / float(f1 - f0)
    dR, dt = se3_exp(s * w, s * u)
    return dR @ R1, dR @ t1 + dt


def jump(R: np.ndarray, t: np.ndarray, R_pred: np.ndarray, t_pred: np.ndarray
         ) -> tuple[float, float]:
    """(camera-centre distance, rotation angle in degrees) of a pose from its prediction."""
    f = lambda a: np.asarray(a, np.float64)  # noqa: E731
    dt, dr = geometry.pose_errors(f(R), f(t), f(R_pred), f(t_pred))
    return float(dt), float(dr)


# ----------------------------------------------------------------------------- tracking step


def reference_scores(m: Map, K: Array, R: Array, t: Array, size: Array,
                     max_ray_angle_deg: float) -> Array:
    """[N] int32 per reference image: its map points in view of the camera (K [3, 3], R, t;
    ``size`` [2] width, height in pixels): linked keypoints whose 3D point projects inside
    the image, in front of the camera, with the rays from the reference and from the camera
    meeting at the point within ``max_ray_angle_deg``."""
    egm = m.egm
    pid = egm.point_idx  # [N, K_max]
    X = egm.points3d[jnp.maximum(pid, 0)]  # [N, K_max, 3]
    uv, z = geometry.project(K, R, t, X.reshape(-1, 3))
    uv, z = uv.reshape(pid.shape + (2,)), z.reshape(pid.shape)
    inside = ((z > 1e-6) & (uv[..., 0] >= 0) & (uv[..., 1] >= 0)
              & (uv[..., 0] <= size[0]) & (uv[..., 1] <= size[1]))
    a = X - geometry.camera_center(R, t)
    b = X - st.reference_centers(m, jnp.arange(egm.num_images))[:, None, :]
    cos = jnp.sum(a * b, -1) / jnp.maximum(jnp.linalg.norm(a, axis=-1)
                                           * jnp.linalg.norm(b, axis=-1), 1e-12)
    ok = egm.kp_mask & (pid >= 0) & inside & (cos >= jnp.cos(jnp.radians(max_ray_angle_deg)))
    return jnp.sum(ok, axis=1).astype(jnp.int32)


def nearest_references(m: Map, K: Array, R: Array, t: Array, size: Array, k: int,
                       max_ray_angle_deg: float) -> Array:
    """[k] int32 reference indices, most map points in view first (:func:`reference_scores`;
    ties to the nearest camera centre)."""
    score = reference_scores(m, K, R, t, size, max_ray_angle_deg).astype(jnp.float32)
    d = jnp.linalg.norm(st.reference_centers(m, jnp.arange(m.egm.num_images))
                        - geometry.camera_center(R, t), axis=-1)
    score = score + 0.5 * (1.0 - d / jnp.maximum(jnp.max(d), 1e-12))  # < 1: ties only
    return jax.lax.top_k(score, k)[1].astype(jnp.int32)


def start_result(q: Query, idx: Array, R: Array, t: Array) -> LocalizeResult:
    """The predicted pose as a result the guided pass can start from (success, no inliers)."""
    i32, nan = jnp.int32(0), jnp.float32(jnp.nan)
    R, t = jnp.asarray(R, jnp.float32), jnp.asarray(t, jnp.float32)
    return LocalizeResult(R=R, t=t, success=jnp.bool_(True), fallback=jnp.bool_(False),
                          n_inliers=i32, n_matches=i32, retrieved=idx, R_first=R, t_first=t,
                          n_inliers_first=i32, n_inliers_guided=jnp.int32(-1), n_rendered=i32,
                          n_rendered_first=i32, inlier_coverage=nan, inlier_ray_angle_deg=nan,
                          inlier_depth_spread=nan, n_keypoints=jnp.sum(q.mask).astype(jnp.int32),
                          inlier_centre_std=nan, centre_std_first=nan, attempt_shift=nan)


def track_pass_config(cfg: LocalizeConfig) -> LocalizeConfig:
    """The guided-pass settings of the tracking pass: ``cfg`` with the tracking radius and
    inlier threshold."""
    return dataclasses.replace(cfg, guided_radius=cfg.track.radius_px,
                               guided_threshold_px=cfg.track.threshold_px,
                               guided_keypoints=cfg.track.keypoints or cfg.guided_keypoints)


class TrackStep(NamedTuple):
    """A tracking step's output: ``result`` the tracked pose (the tracking pass and its
    re-matching passes); ``check`` the check pass's pose (:func:`check_pass`)."""

    result: LocalizeResult
    check: LocalizeResult


def check_pass(m: Map, q: Query, cfg: LocalizeConfig, idx: Array, desc: Array, mask: Array
               ) -> LocalizeResult:
    """The frame's pose from the tracking pass's candidates without the prediction: every
    query keypoint matched to every candidate descriptor (desc [k * K_max, D], mask
    [k * K_max] of the references ``idx`` [k]; the first pass's matching, ratio test and
    mutual check), then the first pass's RANSAC seed and refinement. The tracking pass
    matches only near the projections of the predicted pose, so a wrong prediction can
    gather consistent inliers of its own that keep the pose where the prediction put it
    (the phone walk's held-out leg: 5 tracked poses 10-24% of the scale off); these matches
    do not depend on it. Then ``track.refine_passes`` re-matching passes from that pose, as
    the tracked pose has. The prediction still chose the references (and, in render mode,
    the viewpoint and the points rendered): within the descriptors' invariance the pose is
    the frame's own, as a full localization's first pass is on retrieved references."""
    k, k_max = idx.shape[0], m.egm.point_idx.shape[1]
    s: st.State = {"idx": idx, "desc": desc.reshape(k, k_max, -1),
                   "desc_mask": mask.reshape(k, k_max)}
    for stage in (st.matching, st.ransac, st.refinement):
        s.update(stage(m, q, cfg, s))
    res = s["result"]
    for _ in range(cfg.track.refine_passes):  # as the tracked pose: the guided gates
        res, _ = st.guided_rematch(m, q, cfg, idx, res, desc, mask)
    return res


def step_k(m: Map, cfg: LocalizeConfig) -> int:
    """References a tracking step uses: ``track.top_k`` or the config's top_k."""
    return min(cfg.track.top_k or cfg.top_k, m.egm.num_images)


def step_references(m: Map, q: Query, R_pred: Array, t_pred: Array, size: Array,
                    cfg: LocalizeConfig) -> Array:
    """[k] int32: the references of a tracking step at the predicted pose
    (:func:`nearest_references`, k = :func:`step_k`)."""
    return nearest_references(m, q.K, R_pred, t_pred, size, step_k(m, cfg),
                              cfg.track.max_ray_angle_deg)


def _track_step(m: Map, q: Query, R_pred: Array, t_pred: Array, size: Array,
                cfg: LocalizeConfig, views: tuple[Array, Array, Array] | None = None
                ) -> TrackStep:
    st.check(m, cfg)
    pass_cfg = cfg
    if views is not None:  # the references' own-view descriptors, given (cached by the host)
        idx, desc0, mask0 = views
        s: st.State = {"idx": idx, "desc": desc0, "desc_mask": mask0}
        pass_cfg = dataclasses.replace(cfg, guided_render=False)  # the passes read s["desc"]
    else:
        idx = step_references(m, q, R_pred, t_pred, size, cfg)
        s = {"idx": idx}
    if views is None and (cfg.source == "real" or not cfg.guided_render):
        if cfg.source == "render":  # the passes read s["desc"]
            s.update(st.render(m, q, dataclasses.replace(cfg, early_exit_inliers=0), s))
        s.update(st.describe(m, q, cfg, s))
    res = start_result(q, idx, R_pred, t_pred).replace(
        n_rendered=s.get("n_rendered", jnp.int32(0)))
    res, inl, (desc, mask) = st.guided_pass_described(m, q, track_pass_config(pass_cfg), s,
                                                      res)
    ok = jnp.any(inl)  # the refined pose was kept (success with inliers)
    res = res.replace(success=ok, fallback=~ok, R_first=res.R, t_first=res.t,
                      n_inliers_first=res.n_inliers, n_inliers_guided=jnp.int32(-1),
                      centre_std_first=jnp.where(ok, res.inlier_centre_std, jnp.nan),
                      n_rendered_first=res.n_rendered)
    for _ in range(cfg.track.refine_passes):  # the same patches, the guided pass's gates
        res, _ = st.guided_rematch(m, q, cfg, idx, res, desc, mask)
    if cfg.track.max_disagreement <= 0:  # not checked: no check pass
        return TrackStep(res, res)
    chk = check_pass(m, q, cfg, idx, desc, mask)
    if cfg.track.check_guided:  # a full localization's guided pass, from the check's pose
        chk, _, _ = st.guided_pass_described(m, q, cfg, s, chk)
    return TrackStep(res, chk.replace(n_rendered=res.n_rendered_first + chk.n_rendered,
                                      n_rendered_first=res.n_rendered_first))


_track_jit = jax.jit(_track_step, static_argnames=("cfg",))
step_references_jit = jax.jit(step_references, static_argnames=("cfg",))


def track_step(m: Map, q: Query, R_pred: Array, t_pred: Array, size: Array,
               cfg: LocalizeConfig, views: tuple[Any, Any, Any] | None = None) -> TrackStep:
    """One tracking step (jitted; cfg static; one compilation per map and config).

    Args:
      m: the map; q: the frame's Query; R_pred [3, 3], t_pred [3]: the predicted
        world-to-camera pose; size: [2] the frame's width and height in pixels.
      views: render mode with ``track.reference_views``: (idx [k] int32 the references of
        :func:`nearest_references`, desc [k, K_max, D] their first-pass descriptors rendered from
        their own cameras, mask [k, K_max]); the tracking and check passes match the frame
        to these (nothing rendered at the prediction), the check pose's guided pass renders
        at that pose. None: the references' points rendered at the predicted pose.
    Returns:
      TrackStep: ``result`` with ``retrieved`` the references used
      (:func:`nearest_references`); R_first, t_first, n_inliers_first the tracking pass's
      pose; R, t, n_inliers after the re-matching passes (``n_inliers_guided`` the last
      one's); success False (and the predicted pose) when the tracking pass found no pose.
      ``check``: the check pass's result (:func:`check_pass`; success False without a pose).
    """
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    if views is not None:
        views = (jnp.asarray(views[0], jnp.int32), f32(views[1]), jnp.asarray(views[2], bool))
    return _track_jit(m, q, f32(R_pred), f32(t_pred), f32(size), cfg, views)


track_step._cache_size = _track_jit._cache_size  # compilations so far (tests)


# ----------------------------------------------------------------------------- frame pass


def frame_points(m: Map, q: Query, R: Array, t: Array, idx: Array, radius_px: float
                 ) -> Array:
    """[Kq] int32 per query keypoint the map point it sits on at the pose (R [3, 3], t [3])
    or -1: the map points of the references ``idx`` [k] projected with the pose, each query
    keypoint paired with the nearest projection within ``radius_px`` when that keypoint is
    also the projection's nearest (mutual nearest neighbours)."""
    pid = m.egm.point_idx[idx].reshape(-1)  # [C]
    X = m.egm.points3d[jnp.maximum(pid, 0)]
    uv, z = geometry.project(q.K, R, t, X)
    valid = m.egm.kp_mask[idx].reshape(-1) & (pid >= 0) & (z > 1e-6)
    d2 = planar_sq_distances(q.points2d, uv)  # [Kq, C]
    d2 = jnp.where(q.mask[:, None] & valid[None, :], d2, jnp.inf)
    c = jnp.argmin(d2, axis=1)  # [Kq]
    kq = jnp.arange(d2.shape[0])
    ok = (d2[kq, c] < jnp.float32(radius_px) ** 2) & (jnp.argmin(d2, axis=0)[c] == kq)
    return jnp.where(ok, pid[c], -1).astype(jnp.int32)


def frame_match(m: Map, q: Query, cfg: LocalizeConfig, prev_desc: Array, prev_pid: Array
                ) -> tuple[Array, Array, Array]:
    """The frame matched to the previous frame's keypoints on map points (prev_desc
    [Kp, D], prev_pid [Kp], -1: none; mutual nearest neighbour and ratio test) and lifted to
    2D-3D: uv [Kq, 2], X [Kq, 3], ok [Kq]."""
    j, valid, _ = match(q.desc, q.mask, prev_desc, prev_pid >= 0, cfg.ratio, cfg.mutual)
    pid = prev_pid[j]
    return q.points2d, m.egm.points3d[jnp.maximum(pid, 0)], valid & (pid >= 0)


def frame_seed(q: Query, cfg: LocalizeConfig, X: Array, ok: Array, centre: Array,
               idx: Array, pose) -> LocalizeResult:
    """The frame pass's own pose as a result (``pose`` a PoseResult from the matches ok
    [Kq] of the query keypoints to an anchor frame's map points X [Kq, 3]), with its inlier
    geometry (the anchor's camera ``centre`` [3] as the reference of every correspondence)
    and centre uncertainty; ``idx`` [k] the references it reports. ``n_inliers_first`` is
    at most the guided pass's render budget (``guided_keypoints``, render mode): the
    confidence compares the guided pass's inliers with it, and that pass can confirm no
    more points than it renders (the first pass of a full localization has about as many
    inliers as the budget; a frame pass on a close frame can have several times more)."""
    centres = jnp.broadcast_to(centre, X.shape)
    cov, ang, spread = st.inlier_geometry(q.points2d, q.mask, cfg.coverage_grid, pose.R,
                                          pose.t, X, centres, pose.inliers)
    std = st.centre_uncertainty(q.points2d, q.K, pose.R, pose.t, X, pose.inliers,
                                cfg.confidence.focal_std)
    n_first = pose.n_inliers
    if cfg.source == "render" and cfg.guided_render and cfg.guided_keypoints > 0:
        n_first = jnp.minimum(n_first, cfg.guided_keypoints)
    return start_result(q, idx, pose.R, pose.t).replace(
        success=pose.success, fallback=~pose.success, n_inliers=pose.n_inliers,
        n_matches=jnp.sum(ok).astype(jnp.int32), n_inliers_first=n_first,
        inlier_coverage=cov, inlier_ray_angle_deg=ang, inlier_depth_spread=spread,
        inlier_centre_std=std, centre_std_first=std)


class FrameStep(NamedTuple):
    """A frame pass's output (:func:`frame_step`): ``result`` the pose kept; ``pid`` [Kq]
    int32 the frame's keypoints on map points at it (-1: none; all -1 without a pose);
    ``R_guided`` [3, 3], ``t_guided`` [3] the guided pass's own pose from the frame pass's
    (``result.R_first``), whether kept or not, and ``guided_ok`` [] bool whether it found
    one: the map seen from the frame pass's pose, evidence the anchor frame did not give."""

    result: LocalizeResult
    pid: Array
    R_guided: Array
    t_guided: Array
    guided_ok: Array


def _frame_step(m: Map, q: Query, anchor: tuple[Array, Array, Array], size: Array,
                cfg: LocalizeConfig) -> FrameStep:
    st.check(m, cfg)
    uv, X, ok = frame_match(m, q, cfg, anchor[0], anchor[1])
    R0, t0, inl0, ok0 = ransac_pnp(uv, X, ok, q.K, cfg.pnp)
    pose = refine_seed(R0, t0, inl0, ok0, uv, X, ok, q.K, cfg.pnp)
    idx = step_references(m, q, pose.R, pose.t, size, cfg)
    s: st.State = {"idx": idx}
    if cfg.source == "real" or not cfg.guided_render:  # the passes read s["desc"]
        if cfg.source == "render":
            s.update(st.render(m, q, dataclasses.replace(cfg, early_exit_inliers=0), s))
        s.update(st.describe(m, q, cfg, s))
    # the guided pass from the frame pass's pose (its own pose whatever its inliers: no
    # inliers to beat), kept if it has as many inliers as the frame pass (as a full
    # localization's guided pass replaces its first pass's pose)
    seed = frame_seed(q, cfg, X, ok, anchor[2], idx, pose)
    g, inl, (desc, mask) = st.guided_pass_described(m, q, cfg, s,
                                                     seed.replace(n_inliers=jnp.int32(0)))
    g_ok = jnp.any(inl)
    res = jax.tree.map(lambda a, b: jnp.where(g_ok & (g.n_inliers >= seed.n_inliers), a, b),
                       g.replace(n_inliers_first=seed.n_inliers_first), seed.replace(
                           n_inliers_guided=g.n_inliers_guided,
                           n_rendered=g.n_rendered))
    for _ in range(cfg.track.refine_passes):
        res, _ = st.guided_rematch(m, q, cfg, idx, res, desc, mask)
    pid = frame_points(m, q, res.R, res.t, idx, cfg.track.associate_px)
    return FrameStep(res, jnp.where(res.success, pid, -1), g.R, g.t, g_ok)


_frame_jit = jax.jit(_frame_step, static_argnames=("cfg",))
frame_points_jit = jax.jit(frame_points, static_argnames=("radius_px",))


def frame_step(m: Map, q: Query, anchor: tuple[Any, Any, Any], size: Array,
               cfg: LocalizeConfig) -> FrameStep:
    """The frame pass (jitted; cfg static): the frame matched to an anchor frame's keypoints
    on map points, RANSAC and refinement on those points (the pose owes nothing to the
    prediction), then the guided pass rendered at that pose from the
    :func:`nearest_references` of that pose (kept with at least as many inliers), and
    ``track.refine_passes`` re-matching passes.

    Args:
      anchor: (desc [Kp, D] the anchor frame's keypoint descriptors, pid [Kp] int32 their
        map points, -1: none (:func:`frame_points` at its pose), centre [3] its camera
        centre).
    Returns:
      :class:`FrameStep`: ``result`` with ``R_first``, ``t_first``, ``n_inliers_first``,
      ``centre_std_first`` the frame pass's own (success False without a pose); ``pid``
      the frame's keypoints on map points at the pose kept (the next frame's anchor); the
      guided pass's own pose.
    """
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    anchor = (f32(anchor[0]), jnp.asarray(anchor[1], jnp.int32), f32(anchor[2]))
    return _frame_jit(m, q, anchor, f32(size), cfg)


frame_step._cache_size = _frame_jit._cache_size  # compilations so far (tests)


# ----------------------------------------------------------------------------- acceptance


def appearance_agrees(m: Map, q: Query, used: np.ndarray, cfg: LocalizeConfig) -> bool:
    """Whether the references a tracking pass used (``used`` [k] int, those nearest its
    predicted pose) share at least ``cfg.track.min_retrieval_overlap`` images with the
    query's own top_k by global descriptor (the first pass's retrieval: what the frame looks
    like, independent of any pose)."""
    need = cfg.track.min_retrieval_overlap
    if need <= 0:
        return True
    idx = np.asarray(st.retrieval(m, q, cfg, {})["idx"])
    return len(set(idx.tolist()) & set(np.asarray(used).tolist())) >= need


def frame_rejection(fr: FrameStep, verdict: str, scale: float, cfg: LocalizeConfig,
                    weakest: str | None = None) -> str | None:
    """Why a frame pass's pose is not kept (None: kept): no pose, :func:`pose_rejection`
    (a "localized" verdict, ``weakest`` naming its lowest test otherwise; min_inliers), a
    guided pass that found no pose from the frame pass's, or one farther from it than
    ``track.frame_disagreement`` / ``frame_disagreement_deg`` (the frame pass inherits its
    anchor's error; the map rendered at its pose does not)."""
    tc = cfg.track
    if not bool(fr.result.success):
        return "the frame pass found no pose"
    reason = pose_rejection(fr.result, verdict, cfg, weakest=weakest)
    if reason is not None:
        return reason
    if not bool(fr.guided_ok):
        return "the guided pass found no pose from the frame pass's"
    dt, dr = jump(fr.result.R_first, fr.result.t_first, fr.R_guided, fr.t_guided)
    if tc.frame_disagreement > 0 and (dt > tc.frame_disagreement * scale
                                      or dr > tc.frame_disagreement_deg):
        return (f"the guided pass's pose is {dt / scale:.3f} of the scene scale and "
                f"{dr:.1f} deg from the frame pass's")
    return None


def pose_rejection(r: LocalizeResult, verdict: str, cfg: LocalizeConfig,
                   agrees: bool = True, weakest: str | None = None,
                   verdicts: tuple[str, ...] = ("localized",)) -> str | None:
    """Why a pose of a tracking step is not kept on its own merits (None: kept): no pose, a
    verdict not in ``verdicts`` (naming the confidence's ``weakest`` test when given),
    fewer than ``track.min_inliers`` inliers, or references that the frame's appearance
    does not retrieve (``agrees`` False: :func:`appearance_agrees`)."""
    tc = cfg.track
    if not bool(r.success):
        return "the tracking pass found no pose"
    if verdict not in verdicts:
        return f"confidence verdict {verdict}" + (
            f" (weakest test: {weakest})" if weakest else "")
    if int(r.n_inliers) < tc.min_inliers:
        return f"{int(r.n_inliers)} inliers, fewer than {tc.min_inliers}"
    if not agrees:
        return (f"fewer than {tc.min_retrieval_overlap} of the map images nearest the tracked "
                "pose are among those the frame's appearance retrieves")
    return None


def rejection(r: LocalizeResult, verdict: str, R_pred: np.ndarray, t_pred: np.ndarray,
              scale: float, cfg: LocalizeConfig, agrees: bool = True,
              check: LocalizeResult | None = None, weakest: str | None = None) -> str | None:
    """Why a tracked pose is not kept (None: kept): :func:`pose_rejection`, a jump from the
    prediction beyond ``track.max_jump`` (fraction of the scene ``scale``) or
    ``track.max_jump_deg``, or a check pass (``check``, :func:`check_pass`; None: not
    checked) without a pose or farther from the tracked pose than ``track.max_disagreement``
    or ``track.max_disagreement_deg``."""
    tc = cfg.track
    reason = pose_rejection(r, verdict, cfg, agrees, weakest)
    if reason is not None:
        return reason
    dt, dr = jump(r.R, r.t, R_pred, t_pred)
    if dt > tc.max_jump * scale or dr > tc.max_jump_deg:
        return (f"jumped {dt / scale:.3f} of the scene scale and {dr:.1f} deg from the "
                "prediction")
    if check is not None and tc.max_disagreement > 0:
        if not bool(check.success):
            return "the check pass (matches made without the prediction) found no pose"
        dt, dr = jump(r.R, r.t, check.R, check.t)
        if dt > tc.max_disagreement * scale or dr > tc.max_disagreement_deg:
            return (f"the check pass's pose (matches made without the prediction) is "
                    f"{dt / scale:.3f} of the scene scale and {dr:.1f} deg away")
    return None


# ----------------------------------------------------------------------------- the stream


@dataclasses.dataclass
class TrackResult:
    """One frame of a tracked stream: the :class:`LocalizeResult` fields (numpy) and

    name: the frame's name; tracked: the pose is the tracking step's (else a full
    localization, or none); attempted: a prediction existed and the tracking step ran;
    rejected: why the tracking pass's pose was not kept (None if kept or not attempted);
    by_check: the pose kept is the check pass's (:func:`check_pass`; the tracking pass's
    was rejected, ``rejected`` says why), tracked all the same (no full localization);
    by_frame: the pose kept is the frame pass's (:func:`frame_step`: matched to the previous
    good frame; the tracking step did not run); frame_rejected: why the frame pass's pose
    was not kept (None if kept or not run: :func:`frame_rejection`);
    unconfirmed: the tracked pose passed every test but the check pass, which found no pose
    at all, and the frame's full localization was not "localized" either: the tracked pose
    is kept, its verdict "uncertain" (confidence capped below the localized threshold);
    confidence, verdict: the pose confidence (localize.confidence) of the pose returned;
    latency_s: wall seconds of the frame (reading, preparation, tracking and any full
    localization); n_rendered: every patch rendered for the frame, by the attempts not kept
    too (a rejected frame pass or tracking step before a full localization); R_pred,
    t_pred: the prediction (None without one); error: why the frame has no result
    (unreadable, blank), else None.
    """

    name: str
    R: np.ndarray
    t: np.ndarray
    success: bool
    fallback: bool
    n_inliers: int
    n_matches: int
    retrieved: np.ndarray
    R_first: np.ndarray
    t_first: np.ndarray
    n_inliers_first: int
    n_inliers_guided: int
    n_rendered: int
    n_rendered_first: int
    inlier_coverage: float
    inlier_ray_angle_deg: float
    inlier_depth_spread: float
    n_keypoints: int
    inlier_centre_std: float = float("nan")
    centre_std_first: float = float("nan")
    attempt_shift: float = float("nan")
    tracked: bool = False
    by_check: bool = False
    by_frame: bool = False
    frame_rejected: str | None = None
    unconfirmed: bool = False
    attempted: bool = False
    rejected: str | None = None
    confidence: float = 0.0
    verdict: str = "failed"
    latency_s: float = 0.0
    R_pred: np.ndarray | None = None
    t_pred: np.ndarray | None = None
    error: str | None = None

    @property
    def relocalized(self) -> bool:
        """A tracking attempt was rejected and the frame localized in full."""
        return self.attempted and not self.tracked and self.error is None

    def localize_result(self) -> LocalizeResult | None:
        """The frame's LocalizeResult (numpy), or None for a flagged frame."""
        if self.error is not None:
            return None
        return LocalizeResult(**{f.name: getattr(self, f.name)
                                 for f in dataclasses.fields(LocalizeResult)})


def as_track_result(name: str, r: LocalizeResult, **extra) -> TrackResult:
    """A LocalizeResult (numpy or device values) with the tracking fields ``extra``."""
    r = jax.device_get(r)
    vals = {f.name: np.asarray(getattr(r, f.name)) for f in dataclasses.fields(LocalizeResult)}
    for k, v in vals.items():
        if v.ndim == 0:
            vals[k] = v.item()
    return TrackResult(name=name, **vals, **extra)


def flagged(name: str, error: str, k: int, latency_s: float, n_keypoints: int = 0
            ) -> TrackResult:
    """A frame with no result (unreadable, or blank): success False, verdict failed."""
    nan = float("nan")
    return TrackResult(name=name, R=np.eye(3), t=np.zeros(3), success=False, fallback=False,
                       n_inliers=0, n_matches=0, retrieved=np.full(k, -1, np.int32),
                       R_first=np.eye(3), t_first=np.zeros(3), n_inliers_first=0,
                       n_inliers_guided=-1, n_rendered=0, n_rendered_first=0,
                       inlier_coverage=nan, inlier_ray_angle_deg=nan, inlier_depth_spread=nan,
                       n_keypoints=n_keypoints, latency_s=latency_s, error=error)


def stream_inputs(frames: Sequence[Any], K: Any, dist: Any = None
                  ) -> tuple[list[Any], list[np.ndarray], list[np.ndarray | None]]:
    """(frames, K per frame [3, 3], dist per frame or None) of a stream: one K [3, 3] for
    all frames or one per frame [N, 3, 3]; dist None, one [4]/[5] for all or one per frame
    [N, 5]. VrsError naming the argument otherwise (a frame's own K and dist are checked
    with it)."""
    if isinstance(frames, (str, Path, np.ndarray)) or not isinstance(frames, Sequence):
        raise VrsError("track: frames must be a list of image paths or arrays, got "
                       f"{type(frames).__name__}")
    n = len(frames)
    if n == 0:
        raise VrsError("track: no frames")

    def per_frame(x, ndim, what):
        if isinstance(x, (list, tuple)) and len(x) and (x[0] is None
                                                          or np.ndim(x[0]) == ndim):
            if len(x) != n:  # one per frame (None: no distortion)
                raise VrsError(f"track: {n} frames but {len(x)} {what}")
            return [None if v is None else np.asarray(v, np.float64) for v in x]
        a = np.asarray(x, np.float64)
        if a.ndim == ndim:
            return [a] * n
        if a.ndim == ndim + 1:
            if len(a) != n:
                raise VrsError(f"track: {n} frames but {len(a)} {what}")
            return list(a)
        raise VrsError(f"track: {what} must be one or one per frame, got shape {a.shape}")

    try:
        Ks = per_frame(K, 2, "K")
        dists = [None] * n if dist is None else per_frame(dist, 1, "distortions")
    except (TypeError, ValueError) as e:
        raise VrsError(f"track: K and dist must be numbers ({e})") from None
    if any(k_.shape != (3, 3) for k_ in Ks):
        raise VrsError(f"track: K must be [3, 3] (or [N, 3, 3]), got {Ks[0].shape}")
    return list(frames), Ks, dists


def frame_image(frame: Any, size: Any = None) -> np.ndarray:
    """A frame as an array: read from its file (VrsError naming it; at ``size`` (w, h) when
    given), or the array itself."""
    if isinstance(frame, (str, Path)):
        return read_gray(frame, size=None if size is None else tuple(int(v) for v in size))
    return np.asarray(frame)


def track_frames(m: Map, cfg: LocalizeConfig, frames: Sequence[Any], K: Any, dist: Any,
                 prepare: Callable[..., Query], full: Callable[[Query], LocalizeResult],
                 names: Sequence[str] | None = None, progress: bool = False,
                 step: Callable[..., TrackStep] = track_step,
                 sizes: Sequence[Any] | None = None,
                 views: Callable[..., tuple] | None = None,
                 frame: Callable[..., tuple] = frame_step) -> list[TrackResult]:
    """Track a stream: per frame a :class:`TrackResult`, in order (module docstring).

    Args:
      m, cfg: the map and the query-time config (``cfg.track``: the tracking settings).
      frames: image paths or arrays, in stream order; K, dist: see :func:`stream_inputs`.
      prepare: ``prepare(image, K, dist, name) -> Query`` (VrsError for a bad frame);
        full: ``full(query) -> LocalizeResult``, the full localization (``Localizer``'s,
        with its descriptor cache).
      names: per frame (default: the path, or "frame i").
      progress: a progress bar.
      sizes: per frame the (width, height) a frame file is read at (a dataset read with
        ``--downscale``, whose K belong to the scaled images); None: the file's own size.
      views: render mode with ``track.reference_views``: ``views(q, R_pred, t_pred, size,
        cfg) -> (idx, desc, mask, n_rendered)``, the step's references, their own-view
        first-pass descriptors and the patches rendered to get them (``Localizer``'s, from
        its descriptor cache); None: rendered at the prediction.
      frame: the frame pass (``track.frame_pass``; :func:`frame_step`).
    """
    frames, Ks, dists = stream_inputs(frames, K, dist)
    if names is not None and len(names) != len(frames):
        raise VrsError(f"track: {len(frames)} frames but {len(names)} names")
    if sizes is not None and len(sizes) != len(frames):
        raise VrsError(f"track: {len(frames)} frames but {len(sizes)} sizes")
    tc = cfg.track
    scale = map_scale(m)
    k = min(cfg.top_k, m.egm.num_images)
    history: list[tuple[int, np.ndarray, np.ndarray]] = []
    prev = None  # the last frame's (descriptors [Kq, D], map point per keypoint [Kq], camera
    # centre [3]) if its verdict was "localized" and it was not relocalized: the frame
    # pass's anchor
    out: list[TrackResult] = []
    bar = tqdm(range(len(frames)), desc=f"track ({cfg.source})", unit="frame",
               disable=not progress)
    for i in bar:
        t0 = time.perf_counter()
        f = frames[i]
        name = names[i] if names is not None else (str(f) if isinstance(f, (str, Path))
                                                   else f"frame {i}")
        try:
            gray = frame_image(f, None if sizes is None else sizes[i])
            q = prepare(gray, Ks[i], dists[i], name)
        except VrsError as e:
            out.append(flagged(name, str(e), k, time.perf_counter() - t0))
            continue
        n_kp = int(np.sum(np.asarray(q.mask)))
        if n_kp < cfg.pnp.min_inliers:
            out.append(flagged(name, f"{name}: {n_kp} keypoints, fewer than PnP needs inliers "
                               f"({cfg.pnp.min_inliers}): a blank or featureless frame", k,
                               time.perf_counter() - t0, n_kp))
            continue
        pred = predict_pose(history, i, tc.max_gap)
        extra: dict[str, Any] = {"attempted": pred is not None}
        pid = None  # the frame's keypoints on map points, from the frame pass
        size = np.array([gray.shape[1], gray.shape[0]], np.float32)
        rendered = 0  # patches rendered for the frame, by every attempt (kept or not)
        if pred is not None and tc.frame_pass and prev is not None:
            fr = jax.device_get(frame(m, q, prev, size, cfg))
            r, pid = fr.result, fr.pid
            rendered += int(r.n_rendered)
            conf, verdict = confidence_of(r, scale, cfg)
            why = frame_rejection(fr, verdict, scale, cfg, weakest_of(r, scale, cfg))
            if why is None:
                extra.update(R_pred=pred[0], t_pred=pred[1], tracked=True, by_frame=True)
            else:
                extra.update(frame_rejected=why)
                pid = None
        if pred is not None and not extra.get("tracked"):
            extra.update(R_pred=pred[0], t_pred=pred[1])
            own = (views(q, pred[0], pred[1], size, cfg) if views is not None
                   and cfg.source == "render" and tc.reference_views else None)
            out_step = jax.device_get(step(m, q, pred[0], pred[1], size, cfg,
                                           None if own is None else own[:3]))
            if own is not None:  # the references' patches rendered for this frame (misses)
                out_step = TrackStep(*(r.replace(n_rendered=r.n_rendered + own[3])
                                       for r in out_step))
            rendered += int(out_step.check.n_rendered)  # the step's own (check: its total)
            r, conf, verdict, kept = accepted(m, q, cfg, out_step, pred, scale)
            extra.update(kept)
        if not extra.get("tracked"):
            tracked = (r, conf) if extra.get("unconfirmed") else None
            r = jax.device_get(full(q))
            rendered += int(r.n_rendered)
            conf, verdict = confidence_of(r, scale, cfg)
            if tracked is not None and verdict != "localized":
                # the full localization did no better: the unconfirmed tracked pose, uncertain
                r, conf, verdict = tracked[0], min(tracked[1], UNCERTAIN_BELOW), "uncertain"
                extra.update(tracked=True)
            else:
                extra.update(unconfirmed=False)
        r = r.replace(n_rendered=rendered)
        res = as_track_result(name, r, confidence=conf, verdict=verdict,
                              latency_s=time.perf_counter() - t0, **extra)
        history = updated_history(history, i, res, scale, cfg)
        # a "localized" pose anchors the next frame's frame pass, which inherits its error:
        # not a relocalized one (its tracking was rejected; the stream did not confirm it)
        if (tc.frame_pass and res.success and res.verdict == "localized"
                and not res.relocalized):
            if pid is None:  # the pose's keypoints on map points, at its references
                pid = frame_points_jit(m, q, jnp.asarray(res.R, jnp.float32),
                                       jnp.asarray(res.t, jnp.float32),
                                       jnp.asarray(res.retrieved, jnp.int32), tc.associate_px)
            prev = (q.desc, pid, geometry.camera_center(res.R, res.t))
        elif tc.frame_pass:
            prev = None
        out.append(res)
    return out


def accepted(m: Map, q: Query, cfg: LocalizeConfig, out: TrackStep,
             pred: tuple[np.ndarray, np.ndarray], scale: float
             ) -> tuple[LocalizeResult, float, str, dict[str, Any]]:
    """The pose a tracking step keeps (host code): (result, confidence, verdict, fields)
    with fields ``tracked``, ``by_check``, ``rejected`` and ``unconfirmed``
    (:class:`TrackResult`). The tracked pose if :func:`rejection` finds nothing against it;
    else the check pass's if ``track.keep_check`` and it passes :func:`pose_rejection`
    (with an "uncertain" verdict too if ``track.keep_uncertain_check``; the retrieval
    overlap only if ``track.check_needs_overlap``);
    else ``tracked`` False (the frame is to be localized in full), with ``unconfirmed``
    True when only the check failed, by finding no pose (then the tracked pose, reported
    uncertain, is kept if the full localization is not "localized" either)."""
    tc = cfg.track
    r, check = out
    conf, verdict = confidence_of(r, scale, cfg)
    agrees = appearance_agrees(m, q, r.retrieved, cfg)
    weakest = weakest_of(r, scale, cfg) if verdict != "localized" else None
    reason = rejection(r, verdict, pred[0], pred[1], scale, cfg, agrees, check, weakest)
    if reason is None:
        return r, conf, verdict, {"tracked": True}
    if tc.keep_check and tc.max_disagreement > 0:
        c_conf, c_verdict = confidence_of(check, scale, cfg)
        keep = ("localized", "uncertain") if tc.keep_uncertain_check else ("localized",)
        c_agrees = agrees or not tc.check_needs_overlap
        if pose_rejection(check, c_verdict, cfg, c_agrees, verdicts=keep) is None:
            return check, c_conf, c_verdict, {"tracked": True, "by_check": True,
                                              "rejected": reason}
    # only unconfirmed: the check pass found no pose to agree or disagree with
    unconfirmed = (tc.max_disagreement > 0 and not bool(check.success)
                   and rejection(r, verdict, pred[0], pred[1], scale, cfg, agrees) is None)
    return r, conf, verdict, {"tracked": False, "rejected": reason,
                              "unconfirmed": unconfirmed}


def weakest_of(r: LocalizeResult, scale: float, cfg: LocalizeConfig) -> str:
    """The lowest-scoring test of one result's confidence (localize.confidence.weakest_test;
    "pnp" where it has no pose)."""
    return str(weakest_test(result_fields([r]), scale, cfg.confidence)[0])


def confidence_of(r: LocalizeResult, scale: float, cfg: LocalizeConfig) -> tuple[float, str]:
    """(confidence, verdict) of one result (localize.confidence)."""
    return one_confidence(r, scale, cfg.confidence)


def updated_history(history: list[tuple[int, np.ndarray, np.ndarray]], i: int,
                    res: TrackResult, scale: float, cfg: LocalizeConfig
                    ) -> list[tuple[int, np.ndarray, np.ndarray]]:
    """The last two good poses after frame ``i``: its pose is added when it is a PnP pose
    whose verdict is in ``track.prior_verdicts``. A full localization, or a check pass's pose
    kept by tracking (both made without the prediction), that lands farther from the
    prediction than the jump limits re-anchors the history (the stream jumped:
    dropped frames, or the camera was moved): the new pose, preceded by a virtual pose one
    frame before it that keeps the motion per frame of the old history (the camera most
    likely kept moving as it did; zero motion with one good pose)."""
    tc = cfg.track
    if not res.success or res.verdict not in tc.prior_verdicts:
        return history
    R, t = np.asarray(res.R, np.float64), np.asarray(res.t, np.float64)
    entry = (i, R, t)
    if (not res.tracked or res.by_check or res.by_frame) and res.R_pred is not None:
        dt, dr = jump(R, t, res.R_pred, res.t_pred)
        if dt > tc.max_jump * scale or dr > tc.max_jump_deg:
            if len(history) < 2:
                return [entry]
            (f0, R0, t0), (f1, R1, t1) = history[-2:]
            w, u = se3_log(*relative_motion(R0, t0, R1, t1))
            n = float(f1 - f0)
            dR, dt_ = se3_exp(-w / n, -u / n)  # one frame of the old motion, backwards
            return [(i - 1, dR @ R, dR @ t + dt_), entry]
    return (history + [entry])[-2:]
