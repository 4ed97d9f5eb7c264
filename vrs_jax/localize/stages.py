"""The localization stages, each defined once as a named pure function.

Data flow for one query (docs/design.md, section 1)::

    retrieval   top-k reference images by global descriptor            idx [k]
    render      their 3D-linked keypoints' patches with the NeRF        gray [k, K_max, P, P]
    describe    rendered patches -> descriptors (real mode: the map's)  desc [k, K_max, D]
    matching    query vs each candidate (mutual NN + ratio), lifted to
                3D points, each (query keypoint, 3D point) pair once    uv, X, ok [k * Kq]
    ransac      OpenCV MAGSAC seed                                      R0, t0, inliers
    refinement  optimistix LM on the seed's inliers; fallback to the
                top-1 reference pose when PnP fails, flagged            LocalizeResult
    guided      (cfg.guided_passes > 0) map points projected with the pose, rendered
                from it, matched near their projections, pose refined    LocalizeResult

Every stage is ``fn(map, query, cfg, state) -> dict`` of new state entries; :mod:`run`
chains them fused under one jit (``localize``) or one jit per stage with timing
(``localize_timed``); the figures stop after ``matching``. In real-patch mode the render stage
is skipped and describe reads the map's stored real-patch descriptors.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

from vrs_jax import geometry
from vrs_jax.egm.retrieval import topk
from vrs_jax.errors import VrsError
from vrs_jax.features.descriptor import describe as describe_patches
from vrs_jax.features.matching import guided_match, match, planar_sq_distances
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.localize.pnp import PnPConfig, inlier_mask, ransac_pnp, refine_seed
from vrs_jax.localize.query import Query
from vrs_jax.localize.render import (
    first_occurrence,
    first_pass_keypoints,
    grid_cells,
    longest_tracks,
    render_points_at_pose,
    render_reference,
    spread_tracks,
    track_lengths,
)
from vrs_jax.maps import Map

Array = Any
State = dict[str, Any]


@flax.struct.dataclass
class LocalizeResult:
    """Outcome of one query (batched under vmap).

    R, t: [3, 3], [3] world-to-camera pose (the top-1 reference pose when ``fallback``).
    success: [] bool PnP succeeded; fallback: [] bool the pose is the retrieval fallback.
    n_inliers: [] int32 distinct 2D-3D inliers; n_matches: [] int32 distinct 2D-3D
    correspondences fed to RANSAC. retrieved: [k] int32 reference indices, best first.
    R_first, t_first, n_inliers_first: the first pass's pose and inliers (equal to R, t,
    n_inliers unless a guided pass improved them).
    n_inliers_guided: [] int32 inliers of the last guided pass's refined pose, whether or not
      it was kept (a wrong first pose gathers few of them: the map rendered or projected there
      does not match the query); -1 when no guided pass ran (none configured, or no first
      pose).
    n_rendered, n_rendered_first: [] int32 keypoint patches rendered in all passes and in the
    first (0 in real-patch mode; each patch is P^2 rays).
    n_keypoints: [] int32 keypoints of the query image (0: a blank or featureless image;
      :func:`failure_reason` says why a result has no PnP pose).

    Geometry of the final inliers (:func:`inlier_geometry`; NaN without inliers), for a user
    to judge a pose that ``success`` alone does not: a pose resting on inliers in one corner
    of the image, or on points seen along nearly the same rays from the query and the map,
    has a poorly constrained translation.
    inlier_coverage: [] float32 fraction of the cells of a ``cfg.coverage_grid`` squared grid
      over the query keypoints' bounding box that hold an inlier, among the cells that hold a
      query keypoint (1: inliers wherever the query has features).
    inlier_ray_angle_deg: [] float32 median angle (degrees) at the inliers' 3D points between
      the ray from the estimated query centre and the ray from the reference camera whose
      keypoint was matched (the triangulation angle of the query with the map view).
    inlier_depth_spread: [] float32 (90th - 10th percentile) / median of the inliers' depths
      in the estimated camera (0: all at one depth).
    inlier_centre_std: [] float32 standard deviation of the estimated camera centre along
      its worst-determined direction, in map units, from the Gauss-Newton information of the
      inliers' reprojections at their own residual spread with the focal length known only
      to ``cfg.confidence.focal_std`` (:func:`centre_uncertainty`): large when the inliers
      cannot fix the translation (few, or all at one depth: then moving along the optical
      axis looks like a zoom).
    centre_std_first: [] float32 the same quantity from the first pass's inliers (for a
      tracked frame, the tracking pass's): the matches made without a pose prior. The guided
      passes keep it: a guided pass matches near the projections of the pose it starts from,
      so at a wrong first pose the few near points it adds can be chance matches that agree
      with that pose (measured on the phone walk), while the first pass's inliers say how
      well the pose was fixed before it.
    attempt_shift: [] float32 camera-centre distance (map units) from this pose to the
      farthest PnP pose of the query's other attempts (:mod:`~vrs_jax.localize.retry`: the
      next references by appearance); NaN when it had none (no retry, or no pose there).
      Two attempts on disjoint references that put the camera in different places cannot
      both be right, and nothing in either result says which one is.
    """

    R: Array
    t: Array
    success: Array
    fallback: Array
    n_inliers: Array
    n_matches: Array
    retrieved: Array
    R_first: Array
    t_first: Array
    n_inliers_first: Array
    n_inliers_guided: Array
    n_rendered: Array
    n_rendered_first: Array
    inlier_coverage: Array
    inlier_ray_angle_deg: Array
    inlier_depth_spread: Array
    n_keypoints: Array
    inlier_centre_std: Array
    centre_std_first: Array
    attempt_shift: Array


def failure_reason(r: LocalizeResult, min_inliers: int) -> str | None:
    """Why result ``r`` has no PnP pose (None when it has one), from its counts: no or too
    few query keypoints (a blank or featureless image), no match with the map, or too few
    inliers. ``min_inliers``: the PnP config's (``cfg.pnp.min_inliers``)."""
    if bool(r.success):
        return None
    n_kp, n_m, n_in = int(r.n_keypoints), int(r.n_matches), int(r.n_inliers)
    tail = ": the top-1 reference pose is written"
    if n_kp == 0:
        return "no keypoints in the query image (blank or featureless)" + tail
    if n_kp < min_inliers:
        return (f"{n_kp} keypoints in the query image, fewer than PnP needs inliers "
                f"({min_inliers})" + tail)
    if n_m == 0:
        return f"no match between the query's {n_kp} keypoints and the map" + tail
    return (f"PnP failed: {n_m} matches, {n_in} inliers (PnP needs {min_inliers})" + tail)


def inlier_geometry(points2d: Array, mask: Array, grid: int, R: Array, t: Array, X: Array,
                    ref_centers: Array, inliers: Array) -> tuple[Array, Array, Array]:
    """(inlier_coverage, inlier_ray_angle_deg, inlier_depth_spread) [] float32 of a pose's
    inliers (see :class:`LocalizeResult`; NaN without inliers), with fixed shapes and masks.

    Args:
      points2d: [Kq, 2] query keypoints; mask: [Kq] bool; grid: cells per side (static).
      R, t: the pose; X: [M, 3] the correspondences' 3D points; ref_centers: [M, 3] the
      centre of the reference camera whose keypoint each correspondence matched;
      inliers: [M] bool. The 2D side of correspondence i is query keypoint ``i % Kq`` (both
      passes lay their correspondences out so).
    """
    kq = points2d.shape[0]
    cell = grid_cells(points2d, mask, points2d, grid)  # [Kq]
    has_kp = jnp.zeros(grid * grid, bool).at[cell].max(mask)
    inl_q = jnp.zeros(kq, bool).at[jnp.arange(inliers.shape[0]) % kq].max(inliers)
    has_inl = jnp.zeros(grid * grid, bool).at[cell].max(inl_q & mask)
    any_inl = jnp.any(inliers)
    coverage = jnp.where(any_inl, jnp.sum(has_inl & has_kp) / jnp.maximum(jnp.sum(has_kp), 1),
                         jnp.nan)
    a, b = X - geometry.camera_center(R, t), X - ref_centers
    cos = jnp.sum(a * b, -1) / jnp.maximum(jnp.linalg.norm(a, axis=-1)
                                           * jnp.linalg.norm(b, axis=-1), 1e-12)
    ang = jnp.degrees(jnp.arccos(jnp.clip(cos, -1.0, 1.0)))
    angle = jnp.nanmedian(jnp.where(inliers, ang, jnp.nan))
    z = X @ R[2] + t[2]
    p10, p50, p90 = jnp.nanpercentile(jnp.where(inliers, z, jnp.nan), jnp.array([10, 50, 90]))
    spread = (p90 - p10) / jnp.where(jnp.abs(p50) > 0, jnp.abs(p50), jnp.nan)
    f32 = lambda v: jnp.asarray(v, jnp.float32)  # noqa: E731
    return f32(coverage), f32(angle), f32(spread)


def centre_uncertainty(points2d: Array, K: Array, R: Array, t: Array, X: Array,
                       inliers: Array, focal_std: float) -> Array:
    """[] float32 standard deviation of the camera centre, worst direction, in map units,
    implied by a pose's inliers with the focal length known only to a relative standard
    deviation ``focal_std`` (NaN with fewer than 5 inliers).

    Linearised PnP with a zoom: each inlier's projection u(R, c, f) of its 3D point X
    (camera centre c, x_cam = R (X - c), focal lengths scaled by e^z) has the 2 x 7 Jacobian
    [dpi/dx_cam [-[x_cam]x, -R], u - (cx, cy)] in (rotation, centre, z); with a residual
    spread sigma (the inliers' reprojection RMS, unbiased over 2n - 7 degrees of freedom, at
    least 0.25 px) and the prior z ~ N(0, focal_std^2) the covariance is
    sigma^2 (sum J^T J + sigma^2 / focal_std^2 e_z e_z^T)^-1 and the centre's block gives the
    largest standard deviation. Points far away fix the rotation but hardly the centre; and
    points all at one depth cannot tell a step along the optical axis from a zoom, which a
    query's intrinsics (a phone's focus and stabilisation, a K from another frame) and the
    map's far points (depth from small triangulation angles) both leave open: only points
    at several depths fix that step. Measured on the phone walk's render-mode first passes
    (``docs/figures/localize_walk_fox_scan24.json``): with the focal length fixed the wrong
    poses (7-31% of the scale off along the optical axis) had 1.1-3.7% of the scale, less
    than many right poses; with it free 6.5-22%, with the 0.3% prior 4.7-8.7%. Fully free,
    it also made the right poses of an object seen from 0.6 m (DTU scan24, calibrated) look
    undetermined (2-10%), hence the prior (``ConfidenceConfig.focal_std``).

    Args:
      points2d: [Kq, 2] query keypoints; the 2D side of correspondence i is ``i % Kq``.
      K: [3, 3]; R, t: the pose; X: [M, 3] the correspondences' 3D points; inliers: [M].
    """
    kq = points2d.shape[0]
    uv = points2d[jnp.arange(X.shape[0]) % kq]
    xc = X @ R.T + t  # [M, 3]
    z = jnp.maximum(xc[:, 2], 1e-6)
    fx, fy = K[0, 0], K[1, 1]
    zero = jnp.zeros_like(z)
    dpi = jnp.stack([jnp.stack([fx / z, zero, -fx * xc[:, 0] / z ** 2], -1),
                     jnp.stack([zero, fy / z, -fy * xc[:, 1] / z ** 2], -1)], 1)  # [M, 2, 3]
    x, y, w = xc[:, 0], xc[:, 1], xc[:, 2]
    skew = jnp.stack([jnp.stack([zero, -w, y], -1), jnp.stack([w, zero, -x], -1),
                      jnp.stack([-y, x, zero], -1)], 1)  # [x_cam]x [M, 3, 3]
    proj = (xc[:, :2] / z[:, None]) * jnp.stack([fx, fy]) + K[:2, 2]
    J = jnp.concatenate([jnp.einsum("mab,mbc->mac", dpi, jnp.concatenate(
        [-skew, -jnp.broadcast_to(R, skew.shape)], -1)),
        (proj - K[:2, 2])[:, :, None]], -1)  # [M, 2, 7]: rotation, centre, log focal
    wt = (inliers & (xc[:, 2] > 1e-6)).astype(jnp.float32)
    n = jnp.sum(wt)
    sse = jnp.sum(wt * jnp.sum((proj - uv) ** 2, -1))
    sigma2 = jnp.maximum(sse / jnp.maximum(2.0 * n - 7.0, 1.0), 0.25 ** 2)
    info = jnp.einsum("m,mai,maj->ij", wt, J, J)
    info = info.at[6, 6].add(sigma2 / jnp.float32(focal_std) ** 2)  # the focal-length prior
    scale = jnp.sqrt(jnp.maximum(jnp.diagonal(info), 1e-12))  # equilibrate before inverting
    cov = jnp.linalg.inv(info / scale[:, None] / scale[None, :]) / scale[:, None] / scale[None, :]
    ev = jnp.linalg.eigvalsh(0.5 * (cov[3:6, 3:6] + cov[3:6, 3:6].T))
    std = jnp.sqrt(sigma2 * jnp.maximum(ev[-1], 0.0))
    return jnp.where(n >= 5, std, jnp.nan).astype(jnp.float32)


def reference_centers(m: Map, ref: Array) -> Array:
    """[..., 3] camera centres of reference images ``ref`` [...] int."""
    return geometry.camera_center(m.egm.R[ref], m.egm.t[ref])


def check(m: Map, cfg: LocalizeConfig) -> None:
    """Raise VrsError if the map cannot serve this config (static: checked at trace time)."""
    if cfg.source == "render" and m.ilm is None:
        raise VrsError("render mode needs the map's NeRF; this map has none trained yet")
    if cfg.source == "real" and not m.has_descriptors:
        raise VrsError("real-patch mode needs the map's real-patch descriptors "
                       "(descriptors.npz); load the map with descriptors=True")


def retrieval(m: Map, q: Query, cfg: LocalizeConfig, s: State) -> State:
    """Reference indices [k] int32 by global-descriptor similarity: ranks
    ``cfg.retrieval_offset`` .. + top_k - 1 (k = top_k, or the references left after the
    offset; at least the last one)."""
    n = m.egm.num_images
    off = min(cfg.retrieval_offset, n - 1)
    idx, _ = topk(q.global_desc, m.egm.global_desc, min(off + cfg.top_k, n))
    return {"idx": idx[off:]}


def render(m: Map, q: Query, cfg: LocalizeConfig, s: State) -> State:
    """Rendered grey patches [k, K_max, P, P] of the retrieved images' map keypoints,
    ``rendered`` [k] bool (the candidates rendered: all of them unless an early exit) and
    ``n_rendered`` [] int32 (patches rendered). An early exit also returns what describe and
    matching would make of them (``desc``, ``desc_mask``, ``match_j``, ``match_valid``): it
    described and matched each candidate as it was rendered."""
    patches = cfg.patches or m.config.features.patches
    idx = s["idx"]
    keep = first_pass_keypoints(m, idx, cfg)  # [k, K_max]

    def one(c):
        return render_reference(m, idx[c], patches, cfg, keep[c])

    k = idx.shape[0]
    if cfg.early_exit_inliers <= 0 or k == 1:
        out = {"gray": jax.lax.map(one, jnp.arange(k)), "rendered": jnp.ones(k, bool)}
    else:
        out = early_exit_render(m, q, cfg, idx, keep, one)
    n = jnp.sum(keep & out["rendered"][:, None]).astype(jnp.int32)
    return {**out, "n_rendered": n}


def early_exit_render(m: Map, q: Query, cfg: LocalizeConfig, idx: Array, keep: Array,
                      one: Callable[[Array], Array]) -> State:
    """Render the candidates idx [k] best first (``one(c)``: candidate c's patches; keep
    [k, K_max] its rows), describing and matching each one as it is rendered, and stop once
    the correspondences so far give a RANSAC seed with ``cfg.early_exit_inliers`` inliers.
    Returns gray [k, K_max, P, P], desc [k, K_max, D], match_j / match_valid [k, Kq] (zeros
    where not rendered), desc_mask [k, K_max] and rendered [k] bool."""
    k = idx.shape[0]
    dcfg = m.config.features.descriptor

    def work(c):
        g = one(c)
        d = describe_patches(g[None], dcfg)[0]
        j, valid = match_candidates(q, cfg, d[None], keep[c][None])
        return g, d, j[0], valid[0]

    blank = jax.eval_shape(work, jnp.int32(0))

    def step(carry, c):
        made, rendered, done = carry
        new = jax.lax.cond(done, lambda: jax.tree.map(lambda b: jnp.zeros(b.shape, b.dtype),
                                                      blank), lambda: work(c))
        made = jax.tree.map(lambda a, x: a.at[c].set(x), made, new)
        rendered = rendered.at[c].set(~done)

        def confident():
            st = lift_matches(m, q, idx, made[2], made[3] & rendered[:, None])
            st.update(ransac(m, q, cfg, st))
            return st["ok_seed"] & (jnp.sum(st["inl0"] & st["ok"]) >= cfg.early_exit_inliers)

        # the last candidate needs no decision
        done = jax.lax.cond(done | (c == k - 1), lambda: done, confident)
        return (made, rendered, done), None

    init = (jax.tree.map(lambda b: jnp.zeros((k,) + b.shape, b.dtype), blank),
            jnp.zeros(k, bool), jnp.bool_(False))
    ((gray, desc, j, valid), rendered, _), _ = jax.lax.scan(step, init, jnp.arange(k))
    return {"gray": gray, "rendered": rendered, "desc": desc,
            "desc_mask": keep & rendered[:, None], "match_j": j, "match_valid": valid}


def describe(m: Map, q: Query, cfg: LocalizeConfig, s: State) -> State:
    """Descriptors [k, K_max, D] and mask [k, K_max] of the candidates' keypoints (without
    the candidates an early exit left unrendered; an early exit described them already:
    nothing new)."""
    if "match_valid" in s:
        return {}
    idx = s["idx"]
    mask = first_pass_keypoints(m, idx, cfg) if cfg.source == "render" else m.egm.kp_mask[idx]
    if cfg.source == "real":
        desc = m.egm.local_desc[idx]
    else:
        desc = describe_patches(s["gray"], m.config.features.descriptor)
        if "rendered" in s:
            mask = mask & s["rendered"][:, None]
    return {"desc": desc, "desc_mask": mask}


def match_candidates(q: Query, cfg: LocalizeConfig, desc: Array, desc_mask: Array
                     ) -> tuple[Array, Array]:
    """The query matched to each candidate's descriptors desc [k, K_max, D] (mask
    [k, K_max]; mutual nearest neighbour and ratio test): matched slot j [k, Kq] and valid
    [k, Kq] bool."""
    def one(d, dm):
        j, valid, _ = match(q.desc, q.mask, d, dm, cfg.ratio, cfg.mutual)
        return j, valid

    return jax.vmap(one)(desc, desc_mask)


def lift_matches(m: Map, q: Query, idx: Array, j: Array, valid: Array) -> State:
    """Per-candidate matches (j, valid [k, Kq] of the references idx [k]) lifted to
    distinct 2D-3D correspondences: uv [k * Kq, 2], X [k * Kq, 3], ok [k * Kq] (each (query
    keypoint, 3D point) pair once), and j."""
    pid = jnp.take_along_axis(m.egm.point_idx[idx], j, axis=1)  # [k, Kq]
    ok = valid & (pid >= 0)
    X = m.egm.points3d[jnp.maximum(pid, 0)]  # [k, Kq, 3]
    uv = jnp.broadcast_to(q.points2d[None], X.shape[:2] + (2,))
    qi = jnp.broadcast_to(jnp.arange(j.shape[1])[None], j.shape)
    ok = first_occurrence(ok.reshape(-1), qi.reshape(-1), pid.reshape(-1))
    return {"j": j, "uv": uv.reshape(-1, 2), "X": X.reshape(-1, 3), "ok": ok}


def matching(m: Map, q: Query, cfg: LocalizeConfig, s: State) -> State:
    """Match the query to each candidate and lift to distinct 2D-3D correspondences:
    j [k, Kq] matched keypoint slot per candidate, uv [k * Kq, 2], X [k * Kq, 3],
    ok [k * Kq] (each (query keypoint, 3D point) pair once). An early exit's render matched
    its candidates already (``match_j``, ``match_valid``): those are lifted."""
    if "match_valid" in s:
        j, valid = s["match_j"], s["match_valid"]
    else:
        j, valid = match_candidates(q, cfg, s["desc"], s["desc_mask"])
    return lift_matches(m, q, s["idx"], j, valid)


def ransac(m: Map, q: Query, cfg: LocalizeConfig, s: State) -> State:
    """OpenCV RANSAC seed: R0 [3, 3], t0 [3], seed inliers [M], ok_seed []."""
    R0, t0, inl, ok = ransac_pnp(s["uv"], s["X"], s["ok"], q.K, cfg.pnp)
    return {"R0": R0, "t0": t0, "inl0": inl, "ok_seed": ok}


def refinement(m: Map, q: Query, cfg: LocalizeConfig, s: State) -> State:
    """LM refinement of the seed, then the fallback to the top-1 reference pose; also the
    final inlier mask [k * Kq]."""
    # the LM on at most Kq of the k * Kq slots: the seed's inliers (each query keypoint
    # matches one 3D point per candidate, so more than Kq inliers needs keypoints matched to
    # several points)
    pose = refine_seed(s["R0"], s["t0"], s["inl0"], s["ok_seed"], s["uv"], s["X"], s["ok"],
                       q.K, cfg.pnp, max_rows=q.points2d.shape[0])
    top = s["idx"][0]
    ok = pose.success
    R = jnp.where(ok, pose.R, m.egm.R[top])
    t = jnp.where(ok, pose.t, m.egm.t[top])
    kq = q.points2d.shape[0]
    ref = s["idx"][jnp.arange(s["X"].shape[0]) // kq]
    cov, ang, spread = inlier_geometry(q.points2d, q.mask, cfg.coverage_grid, R, t, s["X"],
                                       reference_centers(m, ref), pose.inliers)
    std = centre_uncertainty(q.points2d, q.K, R, t, s["X"], pose.inliers,
                             cfg.confidence.focal_std)
    res = LocalizeResult(R=R, t=t, success=ok, fallback=~ok, n_inliers=pose.n_inliers,
                         n_matches=jnp.sum(s["ok"]).astype(jnp.int32), retrieved=s["idx"],
                         R_first=R, t_first=t, n_inliers_first=pose.n_inliers,
                         n_inliers_guided=jnp.int32(-1),
                         n_rendered=s.get("n_rendered", jnp.int32(0)),
                         n_rendered_first=s.get("n_rendered", jnp.int32(0)),
                         inlier_coverage=cov, inlier_ray_angle_deg=ang,
                         inlier_depth_spread=spread,
                         n_keypoints=jnp.sum(q.mask).astype(jnp.int32),
                         inlier_centre_std=std, centre_std_first=std,
                         attempt_shift=jnp.float32(jnp.nan))
    return {"result": res, "inliers": pose.inliers}


def near_any(uv: Array, uv_q: Array, mask_q: Array, radius: float) -> Array:
    """[N] bool: some valid query keypoint (uv_q [Nq, 2], mask_q [Nq]) lies within
    ``radius`` pixels of uv [N, 2]."""
    d2 = planar_sq_distances(uv, uv_q)
    return jnp.any((d2 < jnp.float32(radius) ** 2) & mask_q[None, :], axis=1)


def guided_pnp(cfg: LocalizeConfig) -> PnPConfig:
    """The refinement settings of a guided pass: the config's, with the guided pass's own
    inlier threshold when ``cfg.guided_threshold_px`` is set."""
    if cfg.guided_threshold_px is None:
        return cfg.pnp
    return dataclasses.replace(cfg.pnp, threshold_px=cfg.guided_threshold_px)


def guided_pass(m: Map, q: Query, cfg: LocalizeConfig, s: State, res: LocalizeResult
                ) -> tuple[LocalizeResult, Array]:
    """One guided pass from ``res``'s pose (a no-op unless it succeeded): candidates are the
    retrieved images' keypoints with 3D points [k * K_max]; returns the refined result when
    it has at least as many inliers, else ``res``, and the pass's inliers [Kq] bool (query
    keypoints whose guided match is an inlier of the refined pose; all False when the pass
    was not kept).

    Render mode renders only what the guided matching can use: each 3D point once (in the
    first retrieved image that sees it) and only where its projection has a query keypoint
    within ``guided_radius``."""
    res, inl, _ = guided_pass_described(m, q, cfg, s, res)
    return res, inl


def guided_pass_described(m: Map, q: Query, cfg: LocalizeConfig, s: State,
                          res: LocalizeResult) -> tuple[LocalizeResult, Array, tuple]:
    """:func:`guided_pass`, also returning the candidates' descriptors it matched
    (desc [k * K_max, D], mask [k * K_max]; mask all False when the pass did not run), so
    that a further pass can re-match them from the refined pose without rendering
    (:func:`guided_rematch`)."""
    idx = s["idx"]
    pid = m.egm.point_idx[idx].reshape(-1)  # [C]

    def run(_):
        desc, mask, n_new = guided_descriptors(m, q, cfg, s, res)
        out, inl = guided_refine(m, q, cfg, idx, res, desc, mask, n_new)
        return out, inl, (desc, mask)

    def skip(_):
        d = s["desc"].reshape(pid.shape[0], -1) if "desc" in s else jnp.zeros(
            (pid.shape[0], q.desc.shape[-1]), q.desc.dtype)
        return res, jnp.zeros(q.mask.shape, bool), (d, jnp.zeros(pid.shape, bool))

    return jax.lax.cond(res.success, run, skip, None)


def guided_descriptors(m: Map, q: Query, cfg: LocalizeConfig, s: State,
                       res: LocalizeResult) -> tuple[Array, Array, Array]:
    """The guided pass's candidate descriptors at ``res``'s pose: desc [C, D], mask [C]
    (C = k * K_max) and the patches rendered [] int32 (render mode with ``guided_render``:
    rendered from the pose, each 3D point once and only near a query keypoint; else the
    first pass's descriptors in ``s``)."""
    idx = s["idx"]
    pid = m.egm.point_idx[idx].reshape(-1)  # [C]
    X = m.egm.points3d[jnp.maximum(pid, 0)]  # [C, 3]
    uv_r, z = geometry.project(q.K, res.R, res.t, X)
    cand = m.egm.kp_mask[idx].reshape(-1) & (pid >= 0) & (z > 1e-6)
    n_new = jnp.int32(0)
    if cfg.source == "render" and cfg.guided_render:
        patches = cfg.patches or m.config.features.patches
        keep = (first_occurrence(cand, pid)
                & near_any(uv_r, q.points2d, q.mask, cfg.guided_radius))
        reused = jnp.zeros_like(cand)
        if cfg.guided_reuse_inliers and "inliers" in s:
            reused = first_pass_inlier_slots(m, s).reshape(-1) & cand
            seen = jnp.zeros(m.egm.points3d.shape[0], bool).at[jnp.maximum(pid, 0)].max(reused)
            keep = keep & ~seen[jnp.maximum(pid, 0)]
        n_cand = keep.shape[0]
        budget = n_cand
        if cfg.guided_keypoints > 0:
            if cfg.guided_spread_grid > 0:
                cell = grid_cells(q.points2d, q.mask, uv_r, cfg.guided_spread_grid)
                keep = spread_tracks(keep, pid, track_lengths(m), cell, cfg.guided_keypoints)
            else:
                keep = longest_tracks(keep, pid, track_lengths(m), cfg.guided_keypoints)
            budget = min(cfg.guided_keypoints, n_cand)
        # the kept candidates (at most the budget) first, as one flat list of rows
        rows = jnp.argsort(~keep, stable=True)[:budget]
        k_max = m.egm.point_idx.shape[1]
        gray, valid = render_points_at_pose(m, idx[rows // k_max], rows % k_max, keep[rows],
                                            q.K, res.R, res.t, patches, cfg)
        d_rows = describe_patches(gray, m.config.features.descriptor)  # [B, D]
        desc = jnp.zeros((n_cand, d_rows.shape[-1]), d_rows.dtype).at[rows].set(
            jnp.where(valid[:, None], d_rows, 0.0))
        mask = jnp.zeros(n_cand, bool).at[rows].set(valid)
        n_new = jnp.sum(mask).astype(jnp.int32)
        if cfg.guided_reuse_inliers and "inliers" in s:
            first = s["desc"].reshape(desc.shape)
            desc = jnp.where(reused[:, None], first, desc)
            mask = mask | reused
    else:
        desc, mask = s["desc"], s["desc_mask"].reshape(-1)
    return desc.reshape(pid.shape[0], -1), mask & cand, n_new


def first_pass_inlier_slots(m: Map, s: State) -> Array:
    """[k, K_max] bool: the candidates' keypoint slots that the first pass matched to an
    inlier of its refined pose (``s["j"]`` [k, Kq] matched slots, ``s["inliers"]``
    [k * Kq])."""
    j = s["j"]
    k, kq = j.shape
    inl = s["inliers"].reshape(k, kq)
    rows = jnp.broadcast_to(jnp.arange(k)[:, None], j.shape)
    return jnp.zeros((k, m.egm.point_idx.shape[1]), bool).at[rows, j].max(inl)


def guided_refine(m: Map, q: Query, cfg: LocalizeConfig, idx: Array, res: LocalizeResult,
                  desc: Array, mask: Array, n_new: Array) -> tuple[LocalizeResult, Array]:
    """Match the query keypoints to the candidates (desc [C, D], mask [C]) predicted within
    ``cfg.guided_radius`` px of their projections at ``res``'s pose, refine the pose on
    those matches and keep it if it has at least as many inliers as ``res``. Returns the
    result (``n_new`` patches added to ``n_rendered``) and the kept inliers [Kq]."""
    pid = m.egm.point_idx[idx].reshape(-1)  # [C]
    X = m.egm.points3d[jnp.maximum(pid, 0)]  # [C, 3]
    uv_r, z = geometry.project(q.K, res.R, res.t, X)
    mask = mask & (z > 1e-6)
    j, ok, _ = guided_match(q.points2d, q.desc, q.mask, uv_r, desc, mask, pid,
                            cfg.guided_radius, cfg.guided_ratio)
    Xq = X[j]
    pnp = guided_pnp(cfg)
    inl0 = inlier_mask(res.R, res.t, q.points2d, Xq, ok, q.K, pnp.threshold_px)
    pose = refine_seed(res.R, res.t, inl0, res.success, q.points2d, Xq, ok, q.K, pnp)
    better = pose.success & (pose.n_inliers >= res.n_inliers)
    pick = lambda a, b: jnp.where(better, a, b)  # noqa: E731
    k_max = m.egm.point_idx.shape[1]
    geo = inlier_geometry(q.points2d, q.mask, cfg.coverage_grid, pose.R, pose.t, Xq,
                          reference_centers(m, idx[j // k_max]), pose.inliers)
    return res.replace(R=pick(pose.R, res.R), t=pick(pose.t, res.t),
                       n_inliers=pick(pose.n_inliers, res.n_inliers),
                       n_inliers_guided=pose.n_inliers.astype(jnp.int32),
                       n_matches=pick(jnp.sum(ok).astype(jnp.int32), res.n_matches),
                       n_rendered=res.n_rendered + n_new,
                       inlier_coverage=pick(geo[0], res.inlier_coverage),
                       inlier_ray_angle_deg=pick(geo[1], res.inlier_ray_angle_deg),
                       inlier_depth_spread=pick(geo[2], res.inlier_depth_spread),
                       inlier_centre_std=pick(centre_uncertainty(
                           q.points2d, q.K, pose.R, pose.t, Xq, pose.inliers,
                           cfg.confidence.focal_std),
                           res.inlier_centre_std)
                       ), pose.inliers & better


def guided_rematch(m: Map, q: Query, cfg: LocalizeConfig, idx: Array, res: LocalizeResult,
                   desc: Array, mask: Array) -> tuple[LocalizeResult, Array]:
    """A guided pass from ``res``'s pose on descriptors already at hand (desc [C, D], mask
    [C], e.g. a previous pass's: :func:`guided_pass_described`), rendering nothing; a no-op
    unless ``res`` succeeded."""
    none = jnp.zeros(q.mask.shape, bool)
    return jax.lax.cond(
        res.success,
        lambda _: guided_refine(m, q, cfg, idx, res, desc, mask, jnp.int32(0)),
        lambda _: (res, none), None)


def guided(m: Map, q: Query, cfg: LocalizeConfig, s: State) -> State:
    """``cfg.guided_passes`` guided passes on the refined result (the first pass's inlier
    mask stays in ``inliers``); ``guided_inliers`` [Kq] bool: the query keypoints that are
    inliers of the last kept guided pass (all False when none was kept)."""
    res = s["result"]
    kept = jnp.zeros(q.mask.shape, bool)
    for _ in range(cfg.guided_passes):
        res, inl, (desc, mask) = guided_pass_described(m, q, cfg, s, res)
        kept = jnp.where(jnp.any(inl), inl, kept)
    # the last guided pass's descriptors again, nothing rendered
    for _ in range(cfg.guided_rematch_passes if cfg.guided_passes else 0):
        res, inl = guided_rematch(m, q, cfg, s["idx"], res, desc, mask)
        kept = jnp.where(jnp.any(inl), inl, kept)
    return {"result": res, "guided_inliers": kept}


Stage = Callable[[Map, Query, LocalizeConfig, State], State]
STAGES: tuple[tuple[str, Stage], ...] = (
    ("retrieval", retrieval), ("render", render), ("describe", describe),
    ("matching", matching), ("ransac", ransac), ("refinement", refinement),
    ("guided", guided))
STAGE_NAMES = tuple(name for name, _ in STAGES)


def stages_for(cfg: LocalizeConfig) -> tuple[tuple[str, Stage], ...]:
    """The stages a config runs (real-patch mode renders nothing; guided only with passes)."""
    return tuple((n, f) for n, f in STAGES if not (n == "render" and cfg.source == "real")
                 and not (n == "guided" and not guided_on(cfg)))


def guided_on(cfg: LocalizeConfig) -> bool:
    """Whether the config makes guided passes for its source."""
    return cfg.guided_passes > 0 and cfg.source in cfg.guided_sources
