"""Multiresolution hash-grid encoding (Instant-NGP), with footprint-aware level weights.

Written from the description in Mueller, Evans, Schied, Keller, "Instant Neural Graphics
Primitives with a Multiresolution Hash Encoding" (SIGGRAPH 2022), section 3, and the
anti-aliasing of Barron et al., "Zip-NeRF" (ICCV 2023), section 2.

Encoding of a point ``x`` in the unit cube [0, 1]^3:

- L levels with grid resolutions growing geometrically from ``base_res`` to ``max_res``:
  ``N_l = floor(base_res * b^l)``, ``b = exp((ln max_res - ln base_res) / (L - 1))``.
- Level l holds a table of T = 2^log2_T feature vectors of F entries. A level whose
  (N_l + 1)^3 grid vertices fit in T indexes them densely (one entry per vertex, no
  collisions); finer levels hash the integer vertex coordinates
  ``h(i) = (i_x * 1  XOR  i_y * 2654435761  XOR  i_z * 805459861)  mod  T``
  (uint32 arithmetic, the primes of the paper; the first is 1 for cache coherence).
- The level's feature at ``x`` is the trilinear interpolation of its 8 surrounding
  vertices' features; levels are concatenated -> [L * F].

Anti-aliasing (cone rays). A sample is a Gaussian of standard deviation ``sigma`` (the
radial spread of its conical frustum, see :func:`footprint_std`). Following Zip-NeRF, the
grid's features are modelled as i.i.d. zero-mean values per cell; averaging a level's
feature over the Gaussian then keeps (in expectation) only the contribution of the cell the
mean lies in, weighted by the probability that a sample drawn from the Gaussian falls in that
cell. With the mean at the cell centre and per-axis cell width ``c = 1 / N_l``, that
probability along one axis is ``P(|X| < c/2) = erf(c / (2 sqrt(2) sigma)) = erf(c / (sqrt(8)
sigma))`` for X ~ N(0, sigma^2). We use that one-axis factor as the level's weight (as
Zip-NeRF does): it lies in [0, 1], is 1 for a point (sigma -> 0), and falls monotonically as
the footprint grows, so levels finer than the footprint are switched off, just as IPE
switches off the frequencies that the cone cannot resolve. The cone radius therefore keeps
its meaning: a wide patch ray (large keypoint) reads only the coarse levels.

Pure functions of explicit arrays: ``table`` [L, T, F] is a parameter leaf of the field.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax.nerf.mipnerf import conical_frustum_moments

Array = jax.Array

# Instant-NGP's spatial hash primes (the first is 1: neighbouring x stay close in memory).
PRIMES = (1, 2654435761, 805459861)

# The 8 corners of a cell as offsets [8, 3] (x fastest).
CORNERS = np.array([[(c >> 0) & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.uint32)


def level_resolutions(n_levels: int, base_res: int, max_res: int) -> np.ndarray:
    """Grid resolution of each level, [L] int64: floor(base_res * b^l), geometric growth."""
    if n_levels == 1:
        return np.array([base_res], np.int64)
    b = math.exp((math.log(max_res) - math.log(base_res)) / (n_levels - 1))
    return np.floor(base_res * b ** np.arange(n_levels) + 1e-6).astype(np.int64)


def dense_levels(res: np.ndarray, table_size: int) -> np.ndarray:
    """[L] bool: the level's (N + 1)^3 vertices fit in the table (indexed without hashing)."""
    return (res.astype(np.float64) + 1) ** 3 <= table_size


def axis_multipliers(res: np.ndarray, dense: np.ndarray) -> list[np.ndarray]:
    """Per-axis multipliers [L] uint32 of the vertex index (static): a dense level's linear
    index is ``i_x + i_y (N + 1) + i_z (N + 1)^2`` (a sum), a hashed level's ``i_x p_0 XOR
    i_y p_1 XOR i_z p_2`` (the primes); both combine one term per axis."""
    stride = res.astype(np.uint64) + 1
    mults = (np.ones_like(stride), stride, stride * stride)
    return [np.where(dense, m, np.uint64(p)).astype(np.uint32)
            for m, p in zip(mults, PRIMES, strict=True)]


def corner_indices(cell: list[Array], res: np.ndarray, dense: np.ndarray, table_size: int
                   ) -> Array:
    """Flat table indices of the 8 vertices of each point's cell.

    Args:
      cell: per axis [N, L] uint32, the cell's lower vertex coordinate (0..N_l - 1).
      res: [L] resolutions; dense: [L] bool (see :func:`dense_levels`); table_size: T, a
        power of two.
    Returns:
      [N, L, 8] int32 indices into the flattened [L * T, F] table (level l's entries at
      l * T + [0, T)), corners in :data:`CORNERS` order.
    """
    mults = axis_multipliers(res, dense)
    # one term per axis and vertex side: 6 products instead of 24 per level
    terms = [[(c + jnp.uint32(side)) * jnp.asarray(m) for side in (0, 1)]
             for c, m in zip(cell, mults, strict=True)]
    is_dense = jnp.asarray(dense)
    offset = jnp.asarray(np.arange(len(res), dtype=np.int32) * table_size)
    out = []
    for cx, cy, cz in CORNERS:
        a, b, c = terms[0][cx], terms[1][cy], terms[2][cz]
        h = jnp.where(is_dense, a + b + c, a ^ b ^ c) & jnp.uint32(table_size - 1)
        out.append(h.astype(jnp.int32) + offset)
    return jnp.stack(out, axis=-1)


def cell_corners(x: Array, res: np.ndarray, dense: np.ndarray, table_size: int
                 ) -> tuple[Array, tuple[Array, ...]]:
    """The 8 table entries around each point on each level and their trilinear weights.

    Args:
      x: [N, 3] points in [0, 1]^3 (clipped); res: [L] resolutions; dense: [L] bool
        (static numpy arrays); table_size: T.
    Returns:
      idx [N, L, 8] int32 into the flattened [L * T, F] table (:func:`corner_indices`) and
      the weights, one [N, L] array per corner in :data:`CORNERS` order (summing to 1).
    """
    res_f = jnp.asarray(res, x.dtype)
    # per axis [N, L] arrays: a trailing axis of 3 (or 8 x 3 corners) left XLA CPU unable
    # to vectorise the index arithmetic (the encoding ran 2x slower, the same values)
    pos = [jnp.clip(x[:, a], 0.0, 1.0)[:, None] * res_f for a in range(3)]
    # cell index in 0..N-1 (x = 1 falls in the last cell with fraction 1)
    i0 = [jnp.clip(jnp.floor(p), 0.0, res_f - 1.0) for p in pos]
    frac = [p - i for p, i in zip(pos, i0, strict=True)]  # in [0, 1]
    idx = corner_indices([i.astype(jnp.uint32) for i in i0], res, dense, table_size)
    side = [(1.0 - f, f) for f in frac]  # per axis [N, L] each
    return idx, tuple(side[0][cx] * side[1][cy] * side[2][cz] for cx, cy, cz in CORNERS)


@jax.custom_vjp
def weighted_gather(flat: Array, idx: Array, weights: tuple[Array, ...]) -> Array:
    """sum_c weights[c] [N, L, None] * flat[idx[:, :, c]]: [N, L, F] (flat [L * T, F], idx
    [N, L, 8] in range, weights 8 x [N, L]).

    Forward: one gather from the flattened table (indices are in range by construction, so
    no bounds handling: on CPU the default fill mode made it ~3x slower), then the weighted
    sum written out per corner (as a reduction over the corner axis XLA CPU made the sum a
    tiny batched matrix product and the weights a select-reduce: together 40% of the
    encoding's time). Backward (custom): the table's cotangent is one scatter-add of
    weights x cotangent laid out [N, L, 8, F]. Autodiff of the per-corner sum built that
    array as the sum of 8 padded slices, recomputing every corner's weight for every element
    (the transposed gather: more than half of ``cpu-small``'s training step on CPU).
    """
    vals = flat.at[idx].get(mode="promise_in_bounds")  # [N, L, 8, F]
    out = 0.0
    for c, w in enumerate(weights):
        out = out + w[..., None] * vals[:, :, c, :]
    return out


def _weighted_gather_fwd(flat, idx, weights):
    return weighted_gather(flat, idx, weights), (flat, idx, weights)


def _weighted_gather_bwd(saved, ct):
    flat, idx, weights = saved
    upd = jnp.stack(weights, axis=-1)[..., None] * ct[:, :, None, :]  # [N, L, 8, F]
    d_flat = jnp.zeros_like(flat).at[idx].add(upd, mode="promise_in_bounds")
    # the weights' cotangents (the points' gradient; XLA drops them when nothing uses it)
    vals = flat.at[idx].get(mode="promise_in_bounds")
    d_weights = tuple(jnp.sum(vals[:, :, c, :] * ct, axis=-1) for c in range(len(weights)))
    return d_flat, None, d_weights


weighted_gather.defvjp(_weighted_gather_fwd, _weighted_gather_bwd)


def interpolate(table: Array, x: Array, res: np.ndarray, dense: np.ndarray) -> Array:
    """Per-level trilinear interpolation of the tables at points in the unit cube.

    Args:
      table: [L, T, F] features; x: [N, 3] points in [0, 1]^3 (clipped);
      res: [L] resolutions; dense: [L] bool (static numpy arrays).
    Returns:
      [N, L, F] interpolated features (differentiable in ``table`` and ``x``).
    """
    n_levels, table_size, _ = table.shape
    idx, weights = cell_corners(x, res, dense, table_size)
    return weighted_gather(table.reshape(n_levels * table_size, -1), idx, weights)


def level_weights(sigma: Array, res: np.ndarray) -> Array:
    """Zip-NeRF level weights erf(c_l / (sqrt(8) sigma)), c_l = 1 / N_l (unit-cube units).

    Args:
      sigma: [N] footprint standard deviation in unit-cube units (>= 0; 0: a point).
      res: [L] resolutions.
    Returns:
      [N, L] weights in [0, 1], non-increasing in sigma, non-increasing in N_l.
    """
    cell = 1.0 / jnp.asarray(res, sigma.dtype)
    # sigma = 0 -> erf(+inf) = 1; the tiny floor keeps the division finite (and its gradient)
    return jax.scipy.special.erf(cell[None, :] / (math.sqrt(8.0) * jnp.maximum(
        sigma[:, None], 1e-12)))


def encode(table: Array, x: Array, sigma: Array | None, res: np.ndarray, dense: np.ndarray
           ) -> Array:
    """Hash-grid features of points: [N, L * F].

    Args:
      table: [L, T, F]; x: [N, 3] in [0, 1]^3; sigma: [N] footprint std (unit-cube units),
        or None for no anti-aliasing (every level weight 1).
      res, dense: static per-level resolutions and dense flags.
    """
    feats = interpolate(table, x, res, dense)
    if sigma is not None:
        feats = feats * level_weights(sigma, res)[..., None]
    return feats.reshape(x.shape[0], -1)


def footprint_std(t_vals: Array, radii: Array) -> Array:
    """Radial standard deviation of each conical-frustum sample (mip-NeRF's r_var).

    Args:
      t_vals: [R, S + 1] interval endpoints; radii: [R] cone radius at t = 1 (same frame).
    Returns:
      [R, S] sqrt of the per-axis perpendicular variance ~ radius(t) / 2.
    """
    _, _, r_var = conical_frustum_moments(t_vals[..., :-1], t_vals[..., 1:], radii[..., None])
    return jnp.sqrt(jnp.maximum(r_var, 0.0))


def init_table(key: Array, n_levels: int, table_size: int, n_features: int,
               scale: float = 1e-4) -> Array:
    """Instant-NGP initialisation: uniform in [-scale, scale], [L, T, F] float32."""
    return jax.random.uniform(key, (n_levels, table_size, n_features), jnp.float32,
                              -scale, scale)
