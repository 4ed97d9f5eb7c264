"""The Mip-NeRF MLP (flax.linen) and cone-ray rendering with explicit parameter pytrees.

A :class:`Field` is one cluster's renderable NeRF: MLP parameters plus the scene
normalisation of that cluster and its background colour. Rays come in WORLD coordinates;
``render_rays`` normalises them inside (``x' = (x - center) * scale``), so callers never
see the normalised frame. The ILM stacks Fields on a leading cluster axis; select one with
:func:`select_field` (works under jit with a traced index) or vmap over it.
"""

from __future__ import annotations

import functools
from typing import Any

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from vrs_jax.nerf import hashgrid, mipnerf
from vrs_jax.nerf.config import NerfConfig

Array = jax.Array


class Linear(nn.Module):
    """The parameters of a Dense layer, kernel [d_in, features] (Glorot uniform) and bias
    [features] (zeros), created as ``nn.Dense`` creates them (same names, order and
    initialisation) for layers that the MLP composes before applying."""

    features: int

    @nn.compact
    def __call__(self, d_in: int) -> tuple[Array, Array]:
        kernel = self.param("kernel", jax.nn.initializers.glorot_uniform(),
                            (d_in, self.features), jnp.float32)
        bias = self.param("bias", jax.nn.initializers.zeros, (self.features,), jnp.float32)
        return kernel, bias


class MipMLP(nn.Module):
    """Mip-NeRF's MLP: trunk on IPE features -> density; bottleneck + view head -> colour.

    The view head's first layer is split (``W [b; v] = W_b b + W_v v``) so the view
    encoding is multiplied once per ray instead of once per sample: the same function as
    mip-NeRF's concatenation, fewer FLOPs.
    """

    net_depth: int
    net_width: int
    skip_layer: int
    net_depth_condition: int
    net_width_condition: int
    use_viewdirs: bool

    @nn.compact
    def __call__(self, x: Array, view: Array | None) -> tuple[Array, Array]:
        """x: [R, S, Dx] IPE features; view: [R, Dv] view encoding -> raw rgb [R, S, 3],
        raw density [R, S]."""
        dense = functools.partial(nn.Dense, kernel_init=jax.nn.initializers.glorot_uniform())
        # Flatten [R, S, D] -> [R*S, D]: plain 2-D GEMMs (a 3-D dot_general's weight gradient
        # contracts two axes, which XLA:CPU runs markedly slower).
        n_rays, n_samples = x.shape[:2]
        x = x.reshape(n_rays * n_samples, x.shape[-1])
        inputs = x
        for i in range(self.net_depth):
            x = nn.relu(dense(self.net_width, name=f"trunk_{i}")(x))
            if self.skip_layer > 0 and i % self.skip_layer == 0 and i > 0:
                x = jnp.concatenate([x, inputs], axis=-1)
        raw_density = dense(1, name="density")(x)[..., 0].reshape(n_rays, n_samples)
        if self.use_viewdirs:
            # mip-NeRF's bottleneck has no activation: it and the view head's first layer are
            # one affine map, applied as one product (half the colour path's products)
            kb, bb = Linear(self.net_width, name="bottleneck")(x.shape[-1])
            kv, bv = Linear(self.net_width_condition, name="view_0")(self.net_width)
            h = x @ (kb @ kv) + (bb @ kv + bv)
            h_view = dense(self.net_width_condition, use_bias=False, name="view_0_dir")(view)
            h = h.reshape(n_rays, n_samples, -1) + h_view[:, None, :]
            x = nn.relu(h.reshape(n_rays * n_samples, -1))
            for i in range(1, self.net_depth_condition):
                x = nn.relu(dense(self.net_width_condition, name=f"view_{i}")(x))
        raw_rgb = dense(3, name="rgb")(x).reshape(n_rays, n_samples, 3)
        return raw_rgb, raw_density


def make_mlp(cfg: NerfConfig) -> MipMLP:
    return MipMLP(cfg.net_depth, cfg.net_width, cfg.skip_layer, cfg.net_depth_condition,
                  cfg.net_width_condition, cfg.use_viewdirs)


# Parameter-tree key of the hash-grid table [L, T, F] (next to the MLP's layers).
HASH_TABLE = "hash_table"


def feature_dims(cfg: NerfConfig) -> tuple[int, int]:
    """(position feature size: IPE or hash grid, view encoding size)."""
    if cfg.encoding == "hashgrid":
        dx = cfg.hash_levels * cfg.hash_features
    else:
        dx = 6 * (cfg.max_deg_point - cfg.min_deg_point)
    return dx, 3 * (1 + 2 * cfg.deg_view)


def hash_levels(cfg: NerfConfig) -> tuple[np.ndarray, np.ndarray]:
    """Static per-level resolutions [L] and dense flags [L] of the hash grid."""
    res = hashgrid.level_resolutions(cfg.hash_levels, cfg.hash_base_res, cfg.hash_max_res)
    return res, hashgrid.dense_levels(res, 1 << cfg.hash_log2_table)


def init_params(key: Array, cfg: NerfConfig) -> Any:
    """Parameter pytree of one cluster: the MLP's layers (+ ``hash_table`` [L, T, F])."""
    dx, dv = feature_dims(cfg)
    k_mlp, k_grid = jax.random.split(key)
    if cfg.encoding != "hashgrid":
        k_mlp = key  # IPE fields keep their historical initialisation
    params = make_mlp(cfg).init(k_mlp, jnp.zeros((1, 1, dx)), jnp.zeros((1, dv)))["params"]
    if cfg.encoding == "hashgrid":
        params = dict(params)
        params[HASH_TABLE] = hashgrid.init_table(k_grid, cfg.hash_levels,
                                                 1 << cfg.hash_log2_table, cfg.hash_features,
                                                 cfg.hash_init_scale)
    return params


def init_stacked_params(key: Array, cfg: NerfConfig, n_clusters: int) -> Any:
    """Parameters of ``n_clusters`` independent MLPs stacked on a leading axis [C, ...]."""
    return jax.vmap(lambda k: init_params(k, cfg))(jax.random.split(key, n_clusters))


def count_params(params: Any) -> int:
    return int(sum(x.size for x in jax.tree.leaves(params)))


def mlp_flops_per_sample(cfg: NerfConfig) -> int:
    """Multiply-adds x 2 of one MLP evaluation (forward) as :class:`MipMLP` computes it: the
    bottleneck and the view head's first layer as one product, the view direction's part of
    that layer (per ray) and the product of their kernels (per call) left out."""
    dx, _ = feature_dims(cfg)
    w = cfg.net_width
    macs, d_in = 0, dx
    for i in range(cfg.net_depth):
        macs += d_in * w
        d_in = w + (dx if cfg.skip_layer > 0 and i % cfg.skip_layer == 0 and i > 0 else 0)
    macs += d_in  # density
    if cfg.use_viewdirs:
        macs += d_in * cfg.net_width_condition  # bottleneck and view_0: one affine map
        macs += (cfg.net_depth_condition - 1) * cfg.net_width_condition ** 2
        macs += cfg.net_width_condition * 3
    else:
        macs += d_in * 3
    return 2 * macs


@struct.dataclass
class Field:
    """One cluster's NeRF (or C of them with every leaf stacked on a leading axis).

    params: MLP parameter pytree.
    center: [3] world point mapped to the origin of the normalised frame.
    scale: [] normalised units per world unit.
    background: [3] colour composited behind the content (white: Blender scenes).
    """

    params: Any
    center: Array
    scale: Array
    background: Array


def select_field(fields: Field, c: Array | int) -> Field:
    """Cluster ``c``'s Field from a stacked Field (``c`` may be traced)."""
    return jax.tree.map(lambda x: jnp.take(x, c, axis=0), fields)


def normalize_rays(field: Field, origins: Array, directions: Array, radii: Array
                   ) -> tuple[Array, Array, Array]:
    """World rays -> normalised frame. t is unchanged: o' + t d' = (o + t d - c) s.

    origins, directions: [..., 3]; radii: [...] -> same shapes.
    """
    s = field.scale
    return (origins - field.center) * s, directions * s, radii * s


def position_features(params: Any, cfg: NerfConfig, means: Array, covs: Array,
                      t_vals: Array, radii: Array) -> Array:
    """Encoded sample positions [R, S, Dx] (normalised frame).

    means, covs: [R, S, 3] frustum Gaussians; t_vals: [R, S + 1]; radii: [R] cone radius at
    t = 1. IPE reads the Gaussians; the hash grid reads the means mapped to the unit cube and
    weights its levels by the frustum's radial std (hashgrid.footprint_std). With
    ``cfg.contraction`` the Gaussians are first contracted (:func:`contract_gaussians`).
    """
    scale = None
    if cfg.contraction:
        means, scale = contract_gaussians(means, cfg.norm_radius)
    if cfg.encoding != "hashgrid":
        if scale is not None:
            covs = covs * scale[..., None] ** 2
        return mipnerf.integrated_pos_enc(means, covs, cfg.min_deg_point, cfg.max_deg_point)
    n_rays, n_samples = means.shape[:2]
    half = 2.0 * cfg.norm_radius  # the cube [-norm_radius, norm_radius]^3 -> [0, 1]^3
    x = (means.reshape(-1, 3) + cfg.norm_radius) / half
    sigma = None
    if cfg.hash_antialias:
        sigma = hashgrid.footprint_std(t_vals, radii)
        if scale is not None:
            sigma = sigma * scale
        sigma = sigma.reshape(-1) / half
    res, dense = hash_levels(cfg)
    feats = hashgrid.encode(params[HASH_TABLE], x, sigma, res, dense)
    return feats.reshape(n_rays, n_samples, -1)


def inner_radius(norm_radius: float) -> float:
    """Radius of a contracted field's inner ball in the normalised frame: half the cube's,
    so that the contracted space (twice the ball) fills the cube [-norm_radius, +]^3."""
    return 0.5 * norm_radius


def contract_gaussians(means: Array, norm_radius: float) -> tuple[Array, Array]:
    """Sample Gaussians of the normalised frame pushed through the scene contraction.

    The inner ball (radius :func:`inner_radius`) is kept, the rest of space is contracted
    into the ball of twice its radius (mipnerf.contract). means: [..., 3] -> contracted
    means [..., 3] (inside [-norm_radius, norm_radius]^3) and the contraction's isotropic
    length scale [...] by which every standard deviation shrinks there.
    """
    r = inner_radius(norm_radius)
    u = means / r
    return mipnerf.contract(u) * r, mipnerf.contraction_scale(u)


def sample_pivot(cfg: NerfConfig, directions: Array) -> Array | None:
    """Per-ray pivot of the piecewise sample spacing (contracted fields), None otherwise:
    the t at which a ray from the ball's centre would leave the inner ball.
    directions: [R, 3] normalised frame -> [R]."""
    if not cfg.contraction:
        return None
    return inner_radius(cfg.norm_radius) / jnp.linalg.norm(directions, axis=-1)


def _mlp_params(params: Any) -> Any:
    return {k: v for k, v in params.items() if k != HASH_TABLE}


def _eval_mlp(params: Any, cfg: NerfConfig, means: Array, covs: Array, t_vals: Array,
              radii: Array, view_enc: Array, key: Array | None, randomized: bool
              ) -> tuple[Array, Array]:
    """Encoding + MLP + activations: means/covs [R, S, 3], t_vals [R, S + 1], radii [R],
    view_enc [R, Dv] -> rgb [R, S, 3], density [R, S]."""
    feats = position_features(params, cfg, means, covs, t_vals, radii)
    raw_rgb, raw_density = make_mlp(cfg).apply({"params": _mlp_params(params)}, feats,
                                               view_enc)
    if randomized and cfg.density_noise > 0 and key is not None:
        raw_density = raw_density + cfg.density_noise * jax.random.normal(
            key, raw_density.shape, raw_density.dtype)
    rgb = jax.nn.sigmoid(raw_rgb) * (1 + 2 * cfg.rgb_padding) - cfg.rgb_padding
    density = jax.nn.softplus(raw_density + cfg.density_bias)
    return rgb, density


def _view_encoding(cfg: NerfConfig, directions: Array) -> Array:
    viewdirs = directions / jnp.linalg.norm(directions, axis=-1, keepdims=True)
    return mipnerf.pos_enc(viewdirs, 0, cfg.deg_view, append_identity=True)


def render_levels(field: Field, origins: Array, directions: Array, radii: Array, near: Array,
                  far: Array, key: Array, cfg: NerfConfig, randomized: bool
                  ) -> list[dict[str, Array]]:
    """Coarse-to-fine rendering of world-frame cone rays with ONE cluster's Field.

    Args:
      origins, directions: [R, 3] world frame (directions not necessarily unit).
      radii: [R] cone radius at t = 1 (world units); near, far: [R] in t units.
      key: PRNG key (stratification, resampling and density noise when randomized).
    Returns:
      one dict per level (coarse first) with rgb [R, 3], depth [R], acc [R],
      weights [R, S], t_vals [R, S + 1].
    """
    o, d, r = normalize_rays(field, origins, directions, radii)
    view_enc = _view_encoding(cfg, d)
    keys = jax.random.split(key, 4)
    t_vals, (means, covs) = mipnerf.sample_along_rays(
        keys[0], o, d, r, near, far, cfg.num_samples_coarse, randomized, cfg.lindisp,
        sample_pivot(cfg, d))
    out = []
    for level in range(cfg.num_levels):
        if level > 0:
            t_vals, (means, covs) = mipnerf.resample_along_rays(
                keys[1], o, d, r, t_vals, out[-1]["weights"], cfg.num_samples_fine,
                randomized, cfg.resample_padding)
        rgb, density = _eval_mlp(field.params, cfg, means, covs, t_vals, r, view_enc,
                                 keys[2 + level], randomized)
        res = mipnerf.volumetric_rendering(rgb, density, t_vals, d, field.background)
        res["t_vals"] = t_vals
        out.append(res)
    return out


def render_rays(field: Field, origins: Array, directions: Array, radii: Array, near: Array,
                far: Array, key: Array | None, cfg: NerfConfig, randomized: bool = False
                ) -> dict[str, Array]:
    """Render world-frame cone rays with one cluster's Field (the finest level).

    Args:
      field: one cluster's Field (see :func:`select_field`).
      origins, directions: [R, 3]; radii, near, far: [R] (see :func:`render_levels`).
      key: PRNG key, or None for deterministic rendering (randomized must be False).
    Returns:
      dict(rgb [R, 3], depth [R] (t units along ``directions``), acc [R]).
    """
    if key is None:
        key = jax.random.key(0)
    res = render_levels(field, origins, directions, radii, near, far, key, cfg, randomized)[-1]
    return {"rgb": res["rgb"], "depth": res["depth"], "acc": res["acc"]}


def render_rays_narrow(field: Field, origins: Array, directions: Array, radii: Array,
                       near: Array, far: Array, key: Array | None, cfg: NerfConfig,
                       num_samples: int, num_fine: int = 0,
                       randomized: bool = False) -> dict[str, Array]:
    """Depth-guided rendering inside a narrow interval [near, far].

    For patch rays whose surface depth is known (the EGM point of the keypoint), samples
    around that depth replace the full coarse + fine sampling: ``num_samples`` evenly spaced
    samples in the interval, then (``num_fine`` > 0) ``num_fine`` samples resampled from
    their weights inside the same interval (:func:`render_rays_resampled`), as mip-NeRF's
    fine level does over the whole ray. The MLP is the shared one, so both passes are
    ordinary mip-NeRF levels; the resampled pass puts its frustums where the field's
    surface is, which is what the MLP learned to colour (measured on dtu_scan24: 16 + 8
    samples give the keypoint patches 1.1 dB and 9 points of own-keypoint rate more than 16
    samples in one pass, see ``benchmarks.fidelity``).

    Args:
      origins, directions: [R, 3] world frame; radii, near, far: [R].
      num_samples: samples of the first pass (static), e.g. 16.
      num_fine: samples of the resampled pass (static); 0 renders the first pass only.
    Returns:
      dict(rgb [R, 3], depth [R], acc [R]) of the last pass, and the first pass's
      t_vals [R, S + 1] and weights [R, S] (the proposal a resampled pass draws from); the
      background fills what the interval misses.
    """
    if key is None:
        key = jax.random.key(0)
    keys = jax.random.split(key, 4)
    t_vals = mipnerf.stratified_t_vals(keys[0], near, far, num_samples, randomized)
    res = render_rays_at(field, origins, directions, radii, t_vals, keys[1], cfg, randomized)
    first = {"t_vals": t_vals, "weights": res["weights"]}
    if num_fine > 0:
        res = render_rays_resampled(field, origins, directions, radii, t_vals, res["weights"],
                                    keys[2], cfg, num_fine, randomized)
    return {"rgb": res["rgb"], "depth": res["depth"], "acc": res["acc"], **first}


def render_rays_at(field: Field, origins: Array, directions: Array, radii: Array,
                   t_vals: Array, key: Array | None, cfg: NerfConfig,
                   randomized: bool = False) -> dict[str, Array]:
    """One level at given intervals: the frustums between the sorted ``t_vals`` [R, S + 1]
    evaluated and composited. origins, directions: [R, 3] world frame; radii: [R].
    Returns dict(rgb [R, 3], depth [R], acc [R], weights [R, S])."""
    if key is None:
        key = jax.random.key(0)
    o, d, r = normalize_rays(field, origins, directions, radii)
    means, covs = mipnerf.cast_rays(t_vals, o, d, r)
    rgb, density = _eval_mlp(field.params, cfg, means, covs, t_vals, r, _view_encoding(cfg, d),
                             key, randomized)
    return mipnerf.volumetric_rendering(rgb, density, t_vals, d, field.background)


def render_rays_resampled(field: Field, origins: Array, directions: Array, radii: Array,
                          t_vals: Array, weights: Array, key: Array | None, cfg: NerfConfig,
                          num_fine: int, randomized: bool = False) -> dict[str, Array]:
    """One resampled (fine) level: ``num_fine`` samples drawn from a proposal, the
    piecewise-constant ``weights`` [R, S] over the intervals ``t_vals`` [R, S + 1] (a
    coarse pass of these rays, or of nearby rays: the patch probes of localization), then
    evaluated and composited. origins, directions: [R, 3] world frame; radii: [R].
    Returns dict(rgb [R, 3], depth [R], acc [R])."""
    if key is None:
        key = jax.random.key(0)
    o, d, r = normalize_rays(field, origins, directions, radii)
    keys = jax.random.split(key, 2)
    t_new, (means, covs) = mipnerf.resample_along_rays(
        keys[0], o, d, r, t_vals, weights, num_fine, randomized, cfg.resample_padding)
    rgb, density = _eval_mlp(field.params, cfg, means, covs, t_new, r, _view_encoding(cfg, d),
                             keys[1], randomized)
    res = mipnerf.volumetric_rendering(rgb, density, t_new, d, field.background)
    return {"rgb": res["rgb"], "depth": res["depth"], "acc": res["acc"]}


def window_mass(t_vals: Array, weights: Array, lo: Array, hi: Array) -> Array:
    """Rendering weight inside [lo, hi] per ray: each interval's weight times the fraction of
    the interval inside the window. t_vals [R, S + 1], weights [R, S], lo, hi [R] -> [R]."""
    t0, t1 = t_vals[..., :-1], t_vals[..., 1:]
    inside = jnp.clip(jnp.minimum(t1, hi[..., None]) - jnp.maximum(t0, lo[..., None]), 0.0)
    frac = inside / jnp.maximum(t1 - t0, 1e-10)
    return jnp.sum(weights * frac, axis=-1)


def depth_loss(levels: list[dict[str, Array]], depth: Array, margin: float) -> Array:
    """Mean weight outside the window +-margin around ``depth`` [R] (t units; <= 0: no
    depth, not counted), over the rays with a depth and over the levels -> []."""
    has = (depth > 0).astype(jnp.float32)
    lo, hi = depth * (1.0 - margin), depth * (1.0 + margin)
    out = [jnp.sum((1.0 - window_mass(res["t_vals"], res["weights"], lo, hi)) * has)
           for res in levels]
    return sum(out) / (len(levels) * jnp.maximum(jnp.sum(has), 1.0))


def window_loss(field: Field, origins: Array, directions: Array, radii: Array, rgb: Array,
                depth: Array, key: Array, cfg: NerfConfig) -> Array:
    """Colour MSE of rays rendered as the localizer renders them -> [].

    The rays with a point depth (``depth`` [R] > 0, t units) are rendered only inside
    +-``cfg.depth_loss_margin`` around it (:func:`render_rays_narrow`, ``cfg.window_samples``
    then ``cfg.window_fine``, randomized) and compared with ``rgb`` [R, 3]; rays without a
    depth count for nothing (0 when none has one). origins, directions: [R, 3]; radii: [R].
    """
    has = depth > 0
    d = jnp.where(has, depth, 1.0)
    m = cfg.depth_loss_margin
    res = render_rays_narrow(field, origins, directions, radii, d * (1.0 - m), d * (1.0 + m),
                             key, cfg, cfg.window_samples, cfg.window_fine, randomized=True)
    se = jnp.mean((res["rgb"] - rgb) ** 2, axis=-1)
    w = has.astype(se.dtype)
    return jnp.sum(se * w) / jnp.maximum(jnp.sum(w), 1.0)


def nerf_loss(levels: list[dict[str, Array]], rgb_target: Array, cfg: NerfConfig,
              mask: Array | None = None) -> tuple[Array, Array]:
    """Mip-NeRF loss: coarse_loss_mult x MSE(coarse) + MSE(fine).

    Args:
      levels: output of :func:`render_levels`; rgb_target: [R, 3];
      mask: optional [R] ray weights (1 valid, 0 padding).
    Returns:
      (loss [], fine-level MSE [] for PSNR).
    """
    mses = []
    for res in levels:
        se = jnp.mean((res["rgb"] - rgb_target) ** 2, axis=-1)
        if mask is None:
            mses.append(jnp.mean(se))
        else:
            mses.append(jnp.sum(se * mask) / jnp.maximum(jnp.sum(mask), 1.0))
    loss = mses[-1] + cfg.coarse_loss_mult * sum(mses[:-1])
    return loss, mses[-1]


def mse_to_psnr(mse: Array) -> Array:
    return -10.0 * jnp.log10(mse)
