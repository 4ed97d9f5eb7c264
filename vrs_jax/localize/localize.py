"""``localize(params, egm, query)``: retrieval, patch rendering, description, matching, PnP.

One jitted function per scene and config (shapes are fixed by the maps and the config, so all
queries of a scene share one compilation) and vmappable over a batch of queries. The stages
are also exposed one by one (each jitted) so that :func:`localize_timed` can report time per
stage; ``localize`` itself fuses them.

Data flow for one query (DESIGN.md section 1)::

    retrieve      top-k reference images by global descriptor          [k]
    patch rays    canonical grids of their 3D-linked keypoints as cones [k, K_max, P, P]
    render        each image's rays with its cluster's NeRF              [k, K_max, P, P, 3]
    describe      the one descriptor path (grey -> gradient histograms)  [k, K_max, D]
    match         query vs each candidate, mutual NN + ratio             [k, Kq]
    lift          matched keypoints -> their EGM 3D points               [k * Kq, 2|3]
    PnP           OpenCV RANSAC seed + optimistix LM refinement          pose
    fallback      a failed query returns the top-1 reference pose, flagged

In ``gt`` mode the render and describe stages are replaced by the baseline map's stored
descriptors of the real reference patches; everything else is shared.
"""

from __future__ import annotations

import functools
import time
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax import geometry
from vrs_jax.egm.map import EGM
from vrs_jax.egm.retrieval import topk
from vrs_jax.errors import VrsError
from vrs_jax.features.descriptor import describe, rgb_to_gray
from vrs_jax.features.matching import match
from vrs_jax.localize import rays as rays_mod
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.localize.pnp import estimate_pose, ransac_pnp, refine_seed
from vrs_jax.localize.query import Query
from vrs_jax.nerf.ilm import ILM
from vrs_jax.nerf.model import Field, render_rays, render_rays_narrow, select_field

Array = Any


@flax.struct.dataclass
class LocalizeResult:
    """Outcome of one query (batched under vmap).

    R, t: [3, 3], [3] world-to-camera pose (the top-1 reference pose when ``fallback``).
    success: [] bool PnP succeeded; fallback: [] bool the pose is the retrieval fallback.
    n_inliers: [] int32; n_matches: [] int32 2D-3D correspondences fed to RANSAC.
    retrieved: [k] int32 reference indices, best first.
    """

    R: Array
    t: Array
    success: Array
    fallback: Array
    n_inliers: Array
    n_matches: Array
    retrieved: Array


# ----------------------------------------------------------------------------- stages


def retrieve(egm: EGM, query: Query, cfg: LocalizeConfig) -> Array:
    """Top-k reference indices [k] int32 by global-descriptor similarity."""
    k = min(cfg.top_k, egm.num_images)
    idx, _ = topk(query.global_desc, egm.global_desc, k)
    return idx


def candidate_rays(egm: EGM, idx: Array, cfg: LocalizeConfig) -> rays_mod.PatchRays:
    """Patch rays of the candidates' 3D-linked keypoints: arrays [k, K_max, P, P, ...]."""
    def one(i):
        return rays_mod.patch_rays(egm.keypoints[i], egm.K[i], egm.R[i], egm.t[i], cfg.patches,
                                   egm.dist[i])
    return jax.vmap(one)(idx)


def _render_flat(field: Field, o: Array, d: Array, r: Array, near: Array, far: Array,
                 n_valid: Array, ilm_cfg, cfg: LocalizeConfig) -> Array:
    """Render N rays [N, ...] in chunks, skipping chunks past ``n_valid`` -> rgb [N, 3]."""
    n = o.shape[0]
    chunk = min(cfg.render_chunk, n)
    n_chunks = -(-n // chunk)
    pad = n_chunks * chunk - n

    def padded(x, fill=0.0):
        return jnp.concatenate([x, jnp.full((pad,) + x.shape[1:], fill, x.dtype)]).reshape(
            (n_chunks, chunk) + x.shape[1:])

    # padded rays: a harmless unit direction with a valid interval
    d_p = padded(d, 1.0)
    xs = (jnp.arange(n_chunks) * chunk, padded(o), d_p, padded(r, 1e-3), padded(near, 1.0),
          padded(far, 2.0))

    def render_chunk(args):
        start, oc, dc, rc, nc, fc = args

        def go(_):
            if cfg.depth_guided:
                out = render_rays_narrow(field, oc, dc, rc, nc, fc, None, ilm_cfg,
                                         cfg.narrow_samples)
            else:
                out = render_rays(field, oc, dc, rc, nc, fc, None, ilm_cfg)
            return out["rgb"]

        return jax.lax.cond(start < n_valid, go, lambda _: jnp.zeros((chunk, 3), oc.dtype), None)

    rgb = jax.lax.map(render_chunk, xs)
    return rgb.reshape(n_chunks * chunk, 3)[:n]


def render_candidate(ilm: ILM, egm: EGM, i: Array, cfg: LocalizeConfig) -> Array:
    """Rendered grey patches [K_max, P, P] of reference image ``i`` with its cluster's NeRF."""
    P = cfg.patches.size
    kp, mask = egm.keypoints[i], egm.kp_mask[i]
    field = select_field(ilm.fields, egm.cluster[i])
    pr = rays_mod.patch_rays(kp, egm.K[i], egm.R[i], egm.t[i], cfg.patches, egm.dist[i])
    kmax = kp.shape[0]
    shape = (kmax, P, P)
    if cfg.depth_guided:
        z = rays_mod.keypoint_depths(egm.points3d, egm.point_idx[i], egm.R[i], egm.t[i])
        near, far = rays_mod.narrow_interval(z, cfg.depth_margin, shape)
    else:
        near = jnp.broadcast_to(ilm.near[i], shape)
        far = jnp.broadcast_to(ilm.far[i], shape)
    n_kp = jnp.sum(mask)
    if cfg.patches.mode == "literal":
        # overlapping axis-aligned patches share whole pixels: render each distinct one once
        pixels, inverse, count = rays_mod.unique_literal_pixels(pr.positions, mask)
        o, d = geometry.pixel_rays(egm.K[i], egm.R[i], egm.t[i], pixels, egm.dist[i])
        r = jnp.broadcast_to(pr.radii[0, 0, 0], pixels.shape[:1])
        near_p = jnp.zeros(pixels.shape[:1]).at[inverse.reshape(-1)].set(near.reshape(-1))
        far_p = jnp.ones(pixels.shape[:1]).at[inverse.reshape(-1)].set(far.reshape(-1))
        rgb_u = _render_flat(field, o, d, r, near_p, far_p, count, ilm.config, cfg)
        rgb = rgb_u[inverse.reshape(-1)].reshape(shape + (3,))
    else:
        flat = lambda x: x.reshape((-1,) + x.shape[3:])  # noqa: E731
        rgb = _render_flat(field, flat(pr.origins), flat(pr.directions), flat(pr.radii),
                           flat(near), flat(far), n_kp * P * P, ilm.config, cfg)
        rgb = rgb.reshape(shape + (3,))
    return rgb_to_gray(rgb)


def reference_descriptors(ilm: ILM | None, egm: EGM, idx: Array, cfg: LocalizeConfig
                          ) -> tuple[Array, Array]:
    """Descriptors [k, K_max, D] and mask [k, K_max] of the candidates' keypoints."""
    mask = egm.kp_mask[idx]
    if cfg.mode == "gt":
        if egm.local_desc is None:
            raise VrsError("gt mode needs the baseline map (built with --baseline)")
        return egm.local_desc[idx], mask
    if ilm is None:
        raise VrsError("render mode needs the NeRF map (ILM)")
    gray = jax.lax.map(lambda i: render_candidate(ilm, egm, i, cfg), idx)
    return describe(gray, cfg.descriptor), mask


def match_candidates(query: Query, desc: Array, mask: Array, cfg: LocalizeConfig
                     ) -> tuple[Array, Array]:
    """Match the query to each candidate: indices [k, Kq] into K_max and validity [k, Kq]."""
    def one(d, m):
        j, valid, _ = match(query.desc, query.mask, d, m, cfg.ratio, cfg.mutual)
        return j, valid
    return jax.vmap(one)(desc, mask)


def lift(query: Query, egm: EGM, idx: Array, j: Array, valid: Array
         ) -> tuple[Array, Array, Array]:
    """2D-3D correspondences [k * Kq, 2], [k * Kq, 3] and mask [k * Kq] from the matches."""
    pid = jnp.take_along_axis(egm.point_idx[idx], j, axis=1)  # [k, Kq]
    ok = valid & (pid >= 0)
    X = egm.points3d[jnp.maximum(pid, 0)]  # [k, Kq, 3]
    uv = jnp.broadcast_to(query.points2d[None], X.shape[:2] + (2,))
    return uv.reshape(-1, 2), X.reshape(-1, 3), ok.reshape(-1)


def finish(egm: EGM, idx: Array, pose, n_matches: Array) -> LocalizeResult:
    """Apply the fallback: a failed PnP returns the top-1 reference pose, flagged."""
    ok = pose.success
    R = jnp.where(ok, pose.R, egm.R[idx[0]])
    t = jnp.where(ok, pose.t, egm.t[idx[0]])
    return LocalizeResult(R=R, t=t, success=ok, fallback=~ok, n_inliers=pose.n_inliers,
                          n_matches=n_matches.astype(jnp.int32), retrieved=idx)


def _localize(params: ILM | None, egm: EGM, query: Query, cfg: LocalizeConfig
              ) -> LocalizeResult:
    idx = retrieve(egm, query, cfg)
    desc, mask = reference_descriptors(params, egm, idx, cfg)
    j, valid = match_candidates(query, desc, mask, cfg)
    uv, X, ok = lift(query, egm, idx, j, valid)
    pose = estimate_pose(uv, X, ok, query.K, cfg.pnp)
    return finish(egm, idx, pose, jnp.sum(ok))


localize = jax.jit(_localize, static_argnames=("cfg",))
localize.__doc__ = """Localize one query: ``localize(params, egm, query, cfg=cfg)``.

Args:
  params: the ILM (stacked per-cluster NeRFs), or None in ``gt`` mode.
  egm: the explicit geometric map (the baseline map in ``gt`` mode).
  query: a prepared :class:`~vrs_jax.localize.query.Query`.
  cfg: LocalizeConfig (static).
Returns:
  LocalizeResult. Compiled once per (map shapes, cfg); ``jax.vmap`` over stacked queries
  localizes a batch.
"""


def make_localizer(cfg: LocalizeConfig):
    """``localize`` with the config bound: a jitted ``fn(params, egm, query)``."""
    return jax.jit(functools.partial(_localize, cfg=cfg))


# ----------------------------------------------------------------------------- timing


@functools.partial(jax.jit, static_argnames=("cfg",))
def _stage_rays(egm, idx, cfg):
    return candidate_rays(egm, idx, cfg)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _stage_render(ilm, egm, idx, cfg):
    return jax.lax.map(lambda i: render_candidate(ilm, egm, i, cfg), idx)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _stage_describe(gray, cfg):
    return describe(gray, cfg.descriptor)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _stage_retrieve(egm, query, cfg):
    return retrieve(egm, query, cfg)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _stage_match(query, egm, idx, desc, mask, cfg):
    j, valid = match_candidates(query, desc, mask, cfg)
    return lift(query, egm, idx, j, valid)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _stage_ransac(uv, X, ok, K, cfg):
    return ransac_pnp(uv, X, ok, K, cfg.pnp)


@functools.partial(jax.jit, static_argnames=("cfg",))
def _stage_refine(R0, t0, uv, X, inl, ok_seed, ok, K, egm, idx, cfg):
    pose = refine_seed(R0, t0, inl, ok_seed, uv, X, ok, K, cfg.pnp)
    return finish(egm, idx, pose, jnp.sum(ok))


STAGES = ("retrieval", "rays", "render", "describe", "matching", "ransac", "refinement")


def _timed(fn, *args, **kw):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn(*args, **kw))
    return out, time.perf_counter() - t0


def localize_timed(params: ILM | None, egm: EGM, query: Query, cfg: LocalizeConfig
                   ) -> tuple[LocalizeResult, dict[str, float]]:
    """The same computation as :func:`localize`, stage by stage, with wall time per stage.

    Returns the result and ``{stage: seconds}`` for the stages in :data:`STAGES` (``rays``,
    ``render`` and ``describe`` are 0 in gt mode). The first call of each stage includes its
    compilation; callers time a warm-up query first.
    """
    times = dict.fromkeys(STAGES, 0.0)
    idx, times["retrieval"] = _timed(_stage_retrieve, egm, query, cfg=cfg)
    if cfg.mode == "gt":
        desc, mask = reference_descriptors(None, egm, idx, cfg)
    else:
        _, times["rays"] = _timed(_stage_rays, egm, idx, cfg=cfg)
        gray, times["render"] = _timed(_stage_render, params, egm, idx, cfg=cfg)
        desc, times["describe"] = _timed(_stage_describe, gray, cfg=cfg)
        mask = egm.kp_mask[idx]
    (uv, X, ok), times["matching"] = _timed(_stage_match, query, egm, idx, desc, mask, cfg=cfg)
    (R0, t0, inl, ok_seed), times["ransac"] = _timed(_stage_ransac, uv, X, ok, query.K, cfg=cfg)
    res, times["refinement"] = _timed(_stage_refine, R0, t0, uv, X, inl, ok_seed, ok, query.K,
                                      egm, idx, cfg=cfg)
    return res, times


def rays_per_query(egm: EGM, cfg: LocalizeConfig) -> float:
    """Mean patch rays rendered per query (valid keypoints of k reference images x P^2)."""
    if cfg.mode == "gt":
        return 0.0
    per_image = np.asarray(egm.kp_mask).sum(axis=1).mean() * cfg.patches.size ** 2
    return float(min(cfg.top_k, egm.num_images) * per_image)


def nerf_evals_per_ray(ilm: ILM, cfg: LocalizeConfig) -> int:
    """MLP evaluations per rendered ray (narrow: one pass; full: coarse + fine samples)."""
    if cfg.depth_guided:
        return cfg.narrow_samples
    c = ilm.config
    return c.num_samples_coarse + (c.num_levels - 1) * c.num_samples_fine
