"""Rendering the reference keypoints' patches with the map's NeRF (render mode).

Each retrieved reference image's 3D-linked keypoints are cast as patch cones
(:func:`vrs_jax.features.rays.patch_rays`, the grid that reads real patches) and rendered with
the NeRF of the image's cluster, either depth-guided (``narrow_samples`` around the
keypoint's 3D point, then ``narrow_fine`` resampled where the surface is) or with the map's
full coarse + fine sampling. With ``probe_grid`` the depth-guided first pass runs on a few
probe rays of each patch only, and every rendered ray draws its resampled pass from their
weights (:func:`render_probed`). Pure and jittable.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax import geometry
from vrs_jax.errors import VrsError
from vrs_jax.features import rays as rays_mod
from vrs_jax.features.descriptor import rgb_to_gray
from vrs_jax.features.patches import PatchConfig
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.maps import Map
from vrs_jax.nerf.mipnerf import stratified_t_vals
from vrs_jax.nerf.model import (
    Field,
    render_rays,
    render_rays_narrow,
    render_rays_resampled,
    select_field,
)

Array = Any


def render_flat(render: Callable[..., dict[str, Array]], rays: tuple[Array, ...],
                n_valid: Array, cfg: LocalizeConfig, keys: tuple[str, ...] = ("rgb",)
                ) -> dict[str, Array]:
    """Render N rays in chunks of ``cfg.render_chunk``, skipping chunks past ``n_valid``.

    ``rays``: per-ray arrays [N, ...] (origins, directions, radii, then the sampler's
    intervals) that ``render(*chunk_arrays)`` turns into a dict of outputs; returns its
    entries ``keys`` [N, ...]. The last chunk is padded with copies of the last ray (valid
    inputs whose outputs are dropped); skipped chunks hold zeros.
    """
    n = rays[0].shape[0]
    chunk = min(cfg.render_chunk, n)
    n_chunks = -(-n // chunk)
    pad = n_chunks * chunk - n

    def padded(x):
        x = jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)])
        return x.reshape((n_chunks, chunk) + x.shape[1:])

    xs = (jnp.arange(n_chunks) * chunk,) + tuple(padded(x) for x in rays)
    blank = jax.eval_shape(lambda a: render(*a), tuple(x[0] for x in xs[1:]))

    def render_chunk(args):
        start, chunk_rays = args[0], args[1:]

        def go(_):
            out = render(*chunk_rays)
            return {k: out[k] for k in keys}

        def skip(_):
            return {k: jnp.zeros(blank[k].shape, blank[k].dtype) for k in keys}

        return jax.lax.cond(start < n_valid, go, skip, None)

    out = jax.lax.map(render_chunk, xs)
    return {k: v.reshape((n_chunks * chunk,) + v.shape[2:])[:n] for k, v in out.items()}


def sampler(field: Field, nerf_cfg, cfg: LocalizeConfig) -> Callable[..., dict[str, Array]]:
    """The config's ray renderer ``fn(o, d, r, near, far) -> dict``: depth-guided
    ``narrow_samples`` + ``narrow_fine`` inside [near, far], or the map's full coarse +
    fine sampling."""
    if cfg.depth_guided:
        return lambda o, d, r, n, f: render_rays_narrow(field, o, d, r, n, f, None, nerf_cfg,
                                                        cfg.narrow_samples, cfg.narrow_fine)
    return lambda o, d, r, n, f: render_rays(field, o, d, r, n, f, None, nerf_cfg)


def render_probed(field: Field, kp: Array, K: Array, R: Array, t: Array, dist: Array | None,
                  depth: Array, n_kp: Array, patches: PatchConfig, nerf_cfg,
                  cfg: LocalizeConfig) -> Array:
    """Colours [Kp, S, S, 3] of the patches' rendered rays (S = :func:`render_side` per
    side), their samples placed by a few probe rays per patch.

    ``probe_grid`` x ``probe_grid`` rays spread over each patch (both ends of every row and
    column: its corners for 2) take the depth-guided first pass, ``narrow_samples`` evenly
    spaced around the keypoint's point depth (``depth`` [Kp]); every ray of the patch shares
    that window. Their weights, interpolated bilinearly over the patch, are the proposal
    from which each rendered ray draws its ``narrow_fine`` samples (mip-NeRF's fine level,
    with the coarse level of the neighbouring probes instead of its own: the rays of one
    patch are a few pixels apart and cross the same surface). kp: [Kp, 4] keypoints of the
    camera (K, R, t, dist); n_kp: the valid keypoints, a prefix of the rows.
    """
    g, side = cfg.probe_grid, render_side(patches, cfg)
    flat = lambda x: x.reshape((-1,) + x.shape[3:])  # noqa: E731
    probe = rays_mod.patch_rays(kp, K, R, t, patches, dist, g)  # [Kp, g, g, ...]
    near, far = rays_mod.narrow_interval(depth, cfg.depth_margin, probe.radii.shape)
    coarse = lambda o, d, r, n, f: render_rays_narrow(  # noqa: E731
        field, o, d, r, n, f, None, nerf_cfg, cfg.narrow_samples)
    # chunks of as many patches as the rendered rays' chunks hold: a chunk of probes past
    # the last valid keypoint is skipped as the rendered rays' are
    per_chunk = max(1, cfg.render_chunk // (side * side)) * g * g
    out = render_flat(coarse, (flat(probe.origins), flat(probe.directions), flat(probe.radii),
                               flat(near), flat(far)), n_kp * g * g,
                      dataclasses.replace(cfg, render_chunk=per_chunk),
                      keys=("weights",))
    kp_n = depth.shape[0]
    weights = out["weights"].reshape(kp_n, g, g, -1)  # zeros where a chunk was skipped
    # the probes' intervals, one window a patch (computed, not read back: a skipped chunk's
    # zeros would make empty intervals)
    t_vals = stratified_t_vals(None, near[:, 0, 0], far[:, 0, 0], cfg.narrow_samples, False)
    W = jnp.asarray(resample_matrix(g, side))  # [S, g]
    w_rays = jnp.einsum("ia,kabs,jb->kijs", W, weights, W)  # [Kp, S, S, N]
    rays = rays_mod.patch_rays(kp, K, R, t, patches, dist, side)
    t_rays = jnp.broadcast_to(t_vals[:, None, None], (kp_n, side, side, t_vals.shape[-1]))
    fine = lambda o, d, r, t, w: render_rays_resampled(  # noqa: E731
        field, o, d, r, t, w, None, nerf_cfg, cfg.narrow_fine)
    rgb = render_flat(fine, (flat(rays.origins), flat(rays.directions), flat(rays.radii),
                             flat(t_rays), flat(w_rays)), n_kp * side * side, cfg)["rgb"]
    return rgb.reshape(kp_n, side, side, 3)


def render_side(patches: PatchConfig, cfg: LocalizeConfig) -> int:
    """Rays per patch row and column that render mode renders: ``cfg.render_grid``, or the
    patch size P (0: every sample)."""
    return cfg.render_grid or patches.size


def render_keypoints(field: Field, kp: Array, mask: Array, depth: Array, K: Array, R: Array,
                     t: Array, dist: Array | None, near: Array, far: Array,
                     patches: PatchConfig, nerf_cfg, cfg: LocalizeConfig) -> Array:
    """Rendered grey patches [Kp, P, P] of keypoints seen by one camera, with one field.

    S x S rays spread over each patch (:func:`render_side`) are rendered and, when S < P,
    interpolated bilinearly onto the P x P grid.

    Args:
      kp: [Kp, 4] keypoints (x, y, scale, angle) in that camera; mask: [Kp] bool valid rows
        (a prefix: rendering stops after the last valid one); depth: [Kp] z-depth of each
        keypoint's 3D point (the depth-guided interval); K, R, t, dist: the camera;
      near, far: the full sampler's ray interval, [] or per keypoint [Kp].
    """
    P, side = patches.size, render_side(patches, cfg)
    check_grids(patches, cfg)
    n_kp = jnp.sum(mask)
    if cfg.probe_grid > 0:
        rgb = render_probed(field, kp, K, R, t, dist, depth, n_kp, patches, nerf_cfg, cfg)
    else:
        pr = rays_mod.patch_rays(kp, K, R, t, patches, dist, side)
        shape = (kp.shape[0], side, side)
        if cfg.depth_guided:
            near_r, far_r = rays_mod.narrow_interval(depth, cfg.depth_margin, shape)
        else:  # one interval for all rows ([]) or one per row ([Kp])
            near_r = jnp.broadcast_to(jnp.asarray(near)[..., None, None], shape)
            far_r = jnp.broadcast_to(jnp.asarray(far)[..., None, None], shape)
        render = sampler(field, nerf_cfg, cfg)
        if patches.mode == "literal":
            # overlapping axis-aligned patches share whole pixels: render each distinct
            # one once
            pixels, inverse, count = rays_mod.unique_literal_pixels(pr.positions, mask)
            o, d = geometry.pixel_rays(K, R, t, pixels, dist)
            r = jnp.broadcast_to(pr.radii[0, 0, 0], pixels.shape[:1])
            idx = inverse.reshape(-1)
            near_p = jnp.zeros(pixels.shape[:1]).at[idx].set(near_r.reshape(-1))
            far_p = jnp.ones(pixels.shape[:1]).at[idx].set(far_r.reshape(-1))
            rgb_u = render_flat(render, (o, d, r, near_p, far_p), count, cfg)["rgb"]
            rgb = rgb_u[idx].reshape(shape + (3,))
        else:
            flat = lambda x: x.reshape((-1,) + x.shape[3:])  # noqa: E731
            rgb = render_flat(render, (flat(pr.origins), flat(pr.directions), flat(pr.radii),
                                       flat(near_r), flat(far_r)), n_kp * side * side,
                              cfg)["rgb"]
            rgb = rgb.reshape(shape + (3,))
    gray = rgb_to_gray(rgb)
    if side < P:
        W = jnp.asarray(resample_matrix(side, P))  # [P, S]
        gray = jnp.einsum("ia,kab,jb->kij", W, gray, W)
    return gray


def check_grids(patches: PatchConfig, cfg: LocalizeConfig) -> None:
    """VrsError unless the config's render and probe grids fit the patch (static): fewer
    rays than samples per side, or probes, need canonical patches (literal patches are
    whole pixels), at most P per side; probes need the depth-guided sampler (they search
    around the keypoint's 3D point)."""
    P, g, side = patches.size, cfg.probe_grid, cfg.render_grid
    if side > P or (0 < side < P and patches.mode == "literal"):
        raise VrsError(f"render_grid {side} needs canonical patches and at most P = {P} rays "
                       f"per side (mode {patches.mode})")
    if g > 0:
        if patches.mode == "literal" or g > P:
            raise VrsError(f"probe_grid {g} needs canonical patches and at most P = {P} "
                           f"probes per side (mode {patches.mode})")
        if not cfg.depth_guided or cfg.narrow_fine < 1:
            raise VrsError("probe_grid needs depth_guided sampling with narrow_fine >= 1 "
                           "(the probes search around the keypoint's 3D point, every ray "
                           "resamples from them)")


def resample_matrix(n_from: int, n_to: int) -> np.ndarray:
    """[n_to, n_from] float32: linear interpolation from n_from evenly spaced samples of a
    segment (both ends included) onto n_to evenly spaced samples of the same segment; a
    target that falls on a source sample copies it."""
    pos = np.arange(n_to) * ((n_from - 1) / max(n_to - 1, 1))  # in source samples
    i0 = np.minimum(np.floor(pos + 1e-9).astype(int), max(n_from - 2, 0))
    frac = np.clip(pos - i0, 0.0, 1.0) if n_from > 1 else np.zeros(n_to)
    W = np.zeros((n_to, n_from), np.float32)
    W[np.arange(n_to), i0] = 1.0 - frac
    if n_from > 1:
        W[np.arange(n_to), i0 + 1] += frac
    return W


def track_lengths(m: Map) -> Array:
    """[N] int32: how many reference images' keypoints each map point links."""
    pid, ok = m.egm.point_idx, m.egm.kp_mask & (m.egm.point_idx >= 0)
    return jnp.zeros(m.egm.points3d.shape[0], jnp.int32).at[jnp.maximum(pid, 0)].add(
        ok.astype(jnp.int32))


def longest_tracks(keep: Array, pid: Array, track: Array, budget: int) -> Array:
    """[..., C] bool: at most ``budget`` of the ``keep`` [..., C] entries along the last
    axis, those whose map points (``pid`` [..., C], -1 none) have the longest tracks
    (``track`` [N]); ties in their order."""
    score = jnp.where(keep & (pid >= 0), track[jnp.maximum(pid, 0)], -1)
    order = jnp.argsort(-score, axis=-1, stable=True)
    rank = jnp.argsort(order, axis=-1, stable=True)
    return keep & (rank < budget)


def grid_cells(points2d: Array, mask: Array, uv: Array, grid: int) -> Array:
    """[N] int32 cell (row-major) of each point uv [N, 2] on a ``grid`` x ``grid`` grid over
    the bounding box of the valid query keypoints (points2d [Kq, 2], mask [Kq]); points
    outside the box fall in the border cells."""
    big = jnp.float32(1e30)
    lo = jnp.min(jnp.where(mask[:, None], points2d, big), axis=0)
    hi = jnp.max(jnp.where(mask[:, None], points2d, -big), axis=0)
    span = jnp.maximum(hi - lo, 1e-6)
    cxy = jnp.clip(jnp.floor((uv - lo) / span * grid), 0, grid - 1).astype(jnp.int32)
    return cxy[:, 1] * grid + cxy[:, 0]


def spread_tracks(keep: Array, pid: Array, track: Array, cell: Array, budget: int) -> Array:
    """[C] bool: at most ``budget`` of the ``keep`` [C] entries, spread over image cells
    (``cell`` [C] int32): every cell's longest-track point (map point ``pid`` [C], -1 none;
    ``track`` [N] lengths) first, then every cell's second, and so on; within a round the
    longest tracks first, ties in their order."""
    n = keep.shape[0]
    score = jnp.where(keep & (pid >= 0), track[jnp.maximum(pid, 0)], -1)
    by_cell = jnp.lexsort((-score, cell))  # cell by cell, longest tracks first
    c = cell[by_cell]
    pos = jnp.arange(n)
    starts = jnp.concatenate([jnp.ones(1, bool), c[1:] != c[:-1]])
    first = jax.lax.cummax(jnp.where(starts, pos, 0))  # each run's first position
    rank = jnp.zeros(n, jnp.int32).at[by_cell].set(pos - first)
    rank = jnp.where(score >= 0, rank, n)
    order = jnp.lexsort((-score, rank))  # round by round
    return keep & (score >= 0) & (jnp.argsort(order, stable=True) < budget)


def first_pass_keypoints(m: Map, idx: Array, cfg: LocalizeConfig) -> Array:
    """[..., K_max] bool: the keypoints of reference images ``idx`` [...] that the first
    pass renders (render mode) and matches: every valid one, or with
    ``cfg.first_pass_keypoints`` > 0 that many per image, those of the longest tracks first
    (3D points seen in the most reference images: the best triangulated, the likeliest in
    view of a query), ties in the map's keypoint order. With ``cfg.first_pass_unique_points``
    and a list of candidates (idx [k]), a keypoint whose 3D point an earlier candidate's
    selection holds is dropped (:func:`unique_points`): each point rendered once a pass."""
    mask = m.egm.kp_mask[idx]
    pid = m.egm.point_idx[idx]
    budget = cfg.first_pass_keypoints
    if 0 < budget < mask.shape[-1] and cfg.first_pass_spread_grid > 0:
        g, track = cfg.first_pass_spread_grid, track_lengths(m)

        def spread(msk, p, uv):  # one image's keypoints [K_max]
            return spread_tracks(msk, p, track, grid_cells(uv, msk, uv, g), budget)

        uv = m.egm.keypoints[idx][..., :2]
        flat = lambda x: x.reshape((-1,) + x.shape[mask.ndim - 1:])  # noqa: E731
        mask = jax.vmap(spread)(flat(mask), flat(pid), flat(uv)).reshape(mask.shape)
    elif 0 < budget < mask.shape[-1]:
        mask = longest_tracks(mask, pid, track_lengths(m), budget)
    if cfg.first_pass_unique_points and mask.ndim == 2:
        mask = unique_points(mask, pid)
    return mask


def first_occurrence(ok: Array, *keys: Array) -> Array:
    """[M] bool: the ``ok`` entries whose key (one value of each ``keys`` array [M] int) no
    earlier ``ok`` entry has: each key kept once, at its first valid position."""
    order = jnp.lexsort((jnp.arange(ok.shape[0]), *keys[::-1], ~ok))  # valid first, by key
    ok_s = ok[order]
    same = ok_s[:-1]
    for k in keys:
        k_s = k[order]
        same = same & (k_s[1:] == k_s[:-1])
    same = jnp.concatenate([jnp.zeros(1, bool), same])
    return jnp.zeros_like(ok).at[order].set(ok_s & ~same)


def unique_points(mask: Array, pid: Array) -> Array:
    """[k, K] bool: ``mask`` [k, K] without the entries whose map point (``pid`` [k, K],
    -1 none) an earlier entry holds, candidates in order, slots in order within one."""
    linked = mask & (pid >= 0)  # keypoints without a point are never duplicates
    once = first_occurrence(linked.reshape(-1), pid.reshape(-1)).reshape(mask.shape)
    return once | (mask & ~linked)


def render_rows(field: Field, kp: Array, keep: Array, depth: Array, K: Array, R: Array,
                t: Array, dist: Array | None, near: Array, far: Array, patches: PatchConfig,
                nerf_cfg, cfg: LocalizeConfig) -> Array:
    """:func:`render_keypoints` of the rows ``keep`` [Kp] bool only, wherever they are:
    they are rendered first (the renderer stops after the last kept one) and put back in
    place; other rows are zeros. -> [Kp, P, P]."""
    order = jnp.argsort(~keep, stable=True)
    kp = jnp.where(keep[:, None], kp, jnp.array([0.0, 0.0, 1.0, 0.0], kp.dtype))
    gray = render_keypoints(field, kp[order], keep[order], jnp.where(keep, depth, 1.0)[order],
                            K, R, t, dist, near, far, patches, nerf_cfg, cfg)
    return jnp.zeros_like(gray).at[order].set(jnp.where(keep[order, None, None], gray, 0.0))


def render_reference(m: Map, i: Array, patches: PatchConfig, cfg: LocalizeConfig,
                     keep: Array | None = None) -> Array:
    """Rendered grey patches [K_max, P, P] of reference image ``i``'s keypoints ``keep``
    [K_max] bool (default its own first-pass keypoints, :func:`first_pass_keypoints`;
    zeros elsewhere) with its cluster's NeRF."""
    egm, ilm = m.egm, m.ilm
    field = select_field(ilm.fields, ilm.image_cluster[i])
    z = rays_mod.keypoint_depths(egm.points3d, egm.point_idx[i], egm.R[i], egm.t[i])
    args = (egm.K[i], egm.R[i], egm.t[i], egm.dist[i], ilm.near[i], ilm.far[i], patches,
            ilm.config, cfg)
    if keep is None and cfg.first_pass_keypoints <= 0:  # every valid one: a prefix
        return render_keypoints(field, egm.keypoints[i], egm.kp_mask[i], z, *args)
    keep = first_pass_keypoints(m, i, cfg) if keep is None else keep
    return render_rows(field, egm.keypoints[i], keep, z, *args)


def render_at_pose(m: Map, i: Array, K: Array, R: Array, t: Array, patches: PatchConfig,
                   cfg: LocalizeConfig, keep: Array | None = None
                   ) -> tuple[Array, Array, Array]:
    """Reference image ``i``'s map keypoints rendered from another (pinhole) viewpoint.

    Each keypoint is moved into the camera (K [3, 3], R [3, 3], t [3]) through its 3D point
    (:func:`vrs_jax.features.rays.transfer_keypoints`) and its patch rendered there with the
    image's cluster NeRF: what that camera would see around the point, in the keypoint's
    transferred frame. ``keep`` [K_max] bool (None: all) selects the keypoints to render.
    Returns grey patches [K_max, P, P] (zeros where not rendered), the moved keypoints
    [K_max, 4] and their validity [K_max] (kept, linked to a 3D point in front of the
    camera): only valid keypoints are rendered.
    """
    egm, ilm = m.egm, m.ilm
    field = select_field(ilm.fields, ilm.image_cluster[i])
    pid = egm.point_idx[i]
    X = egm.points3d[jnp.maximum(pid, 0)]
    kp, z = rays_mod.transfer_keypoints(egm.keypoints[i], X, egm.K[i], egm.R[i], egm.t[i],
                                        egm.dist[i], K, R, t)
    valid = egm.kp_mask[i] & (pid >= 0) & (z > 1e-6)
    if keep is not None:
        valid = valid & keep
    kp = jnp.where(valid[:, None], kp, jnp.array([0.0, 0.0, 1.0, 0.0], kp.dtype))
    gray = render_rows(field, kp, valid, z, K, R, t, None, ilm.near[i], ilm.far[i], patches,
                       ilm.config, cfg)
    return gray, kp, valid


def render_points_at_pose(m: Map, img: Array, slot: Array, keep: Array, K: Array, R: Array,
                          t: Array, patches: PatchConfig, cfg: LocalizeConfig
                          ) -> tuple[Array, Array]:
    """:func:`render_at_pose` for a flat list of B map keypoints of several reference images
    at once: keypoint ``slot`` [B] of reference image ``img`` [B] where ``keep`` [B], moved
    into the camera (K, R, t) and rendered with its image's cluster NeRF. The kept rows of
    all images share one chunked render per cluster (rows of other clusters skipped), so a
    pass that renders a few keypoints of each of k images pays for its keypoints, not for k
    padded renders. Returns grey patches [B, P, P] (zeros where not rendered) and the
    validity [B] (kept, linked to a 3D point in front of the camera)."""
    egm, ilm = m.egm, m.ilm
    pid = egm.point_idx[img, slot]
    X = egm.points3d[jnp.maximum(pid, 0)]

    def move(kp, x, i):
        k, z = rays_mod.transfer_keypoints(kp[None], x[None], egm.K[i], egm.R[i], egm.t[i],
                                           egm.dist[i], K, R, t)
        return k[0], z[0]

    kp, z = jax.vmap(move)(egm.keypoints[img, slot], X, img)
    valid = keep & egm.kp_mask[img, slot] & (pid >= 0) & (z > 1e-6)
    kp = jnp.where(valid[:, None], kp, jnp.array([0.0, 0.0, 1.0, 0.0], kp.dtype))
    cluster = ilm.image_cluster[img]

    def one_cluster(c):
        return render_rows(select_field(ilm.fields, c), kp, valid & (cluster == c), z, K, R,
                           t, None, ilm.near[img], ilm.far[img], patches, ilm.config, cfg)

    n_clusters = jax.tree.leaves(ilm.fields)[0].shape[0]
    if n_clusters == 1:
        gray = one_cluster(jnp.int32(0))
    else:  # each row is rendered by its own cluster's pass; the others hold zeros there
        gray = jnp.sum(jax.lax.map(one_cluster, jnp.arange(n_clusters)), axis=0)
    return gray, valid


def rays_per_query(m: Map, cfg: LocalizeConfig) -> float:
    """Patch rays a query renders at most (valid keypoints of k reference images x P^2, once
    more per guided pass that renders); an early exit and the guided pass's selection render
    fewer: ``LocalizeResult.n_rendered`` counts them per query."""
    if cfg.source != "render":
        return 0.0
    per_image = np.asarray(m.egm.kp_mask).sum(axis=1).mean() * rays_per_patch(m, cfg)
    guided = cfg.guided_render and cfg.source in cfg.guided_sources
    passes = 1 + (cfg.guided_passes if guided else 0)
    return float(passes * min(cfg.top_k, m.egm.num_images) * per_image)


def rays_per_patch(m: Map, cfg: LocalizeConfig) -> int:
    """Rays rendered per keypoint patch: P^2, or render_grid^2."""
    return render_side(cfg.patches or m.config.features.patches, cfg) ** 2


def nerf_evals_per_ray(m: Map, cfg: LocalizeConfig) -> float:
    """MLP evaluations per rendered patch ray (depth-guided: narrow + resampled, or with
    probes their narrow pass shared out over the patch's rays plus the resampled pass;
    full: coarse + fine): evaluations per patch = this x :func:`rays_per_patch`."""
    if cfg.depth_guided and cfg.probe_grid > 0:
        probes = cfg.probe_grid ** 2 * cfg.narrow_samples
        return probes / rays_per_patch(m, cfg) + cfg.narrow_fine
    if cfg.depth_guided:
        return float(cfg.narrow_samples + cfg.narrow_fine)
    c = m.config.nerf
    return float(c.num_samples_coarse + (c.num_levels - 1) * c.num_samples_fine)


def full_image_evals(m: Map, retrieved: np.ndarray) -> int:
    """MLP evaluations to render the reference images ``retrieved`` [k] in full with the map's
    coarse + fine sampling (every pixel one ray): the cost patch rendering is compared with."""
    c = m.config.nerf
    per_ray = c.num_samples_coarse + (c.num_levels - 1) * c.num_samples_fine
    sizes = np.asarray(m.egm.sizes, np.int64)[np.asarray(retrieved)]
    return int(np.prod(sizes, axis=-1).sum() * per_ray)
