"""Mip-NeRF math as small pure functions (Barron et al., ICCV 2021).

Every function is jittable and works on arbitrary leading batch axes written ``...``;
``S`` is the number of samples (intervals) along a ray. Rays are cones: a ray is
``x(t) = o + t d`` with ``d`` NOT normalised, and its cone radius at parameter ``t`` is
``t * r`` (``r``: "radius at unit distance along d", mip-NeRF's ``base_radius``; for a
pixel of width ``dx`` in normalised image coordinates ``r = dx * 2 / sqrt(12)``). Sample
intervals are given by their ``S + 1`` endpoints ``t_vals`` along ``d``.

The functions implement, in order of use:
  sample_along_rays  -> stratified interval endpoints in [near, far]
  cast_rays          -> conical frustum of each interval as a Gaussian (mean, diagonal cov)
  integrated_pos_enc -> expected sin/cos features of that Gaussian
  pos_enc            -> plain positional encoding of view directions
  volumetric_rendering -> weights, colour, depth, opacity, background compositing
  resample_along_rays  -> hierarchical samples from blurred coarse weights
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

Array = jax.Array


# ----------------------------------------------------------------------------- cones


def conical_frustum_moments(t0: Array, t1: Array, base_radius: Array
                            ) -> tuple[Array, Array, Array]:
    """Mean and variances of a conical frustum, mip-NeRF's numerically stable form.

    The frustum is the part of the cone between parameters t0 and t1; points are uniform
    in its volume. With ``mu = (t0 + t1) / 2`` and ``hw = (t1 - t0) / 2`` (eq. 7 of the
    paper) the moments are written so that no catastrophic cancellation occurs for thin
    intervals (``hw << mu``), unlike the raw ratios of ``t^5 - t^3`` polynomials.

    Args:
      t0, t1: [...] interval endpoints along d (0 <= t0 < t1).
      base_radius: [...] cone radius at t = 1 (broadcastable to t0).
    Returns:
      t_mean [...]: mean of t; t_var [...]: variance of t (in t units);
      r_var [...]: variance of the offset perpendicular to the axis, per perpendicular
      direction, in world units squared.
    """
    mu = (t0 + t1) / 2
    hw = (t1 - t0) / 2
    denom = 3 * mu**2 + hw**2
    t_mean = mu + (2 * mu * hw**2) / denom
    t_var = hw**2 / 3 - (4 / 15) * (hw**4 * (12 * mu**2 - hw**2)) / denom**2
    r_var = base_radius**2 * (mu**2 / 4 + (5 / 12) * hw**2 - (4 / 15) * hw**4 / denom)
    return t_mean, t_var, r_var


def lift_gaussian(d: Array, t_mean: Array, t_var: Array, r_var: Array) -> tuple[Array, Array]:
    """Lift the 1D moments along a ray into a 3D Gaussian with diagonal covariance.

    Cov = t_var d d^T + r_var (I - d d^T / |d|^2); only its diagonal is kept (the
    diagonal IPE of mip-NeRF needs no more).

    Args:
      d: [..., 3] ray directions (any norm > 0).
      t_mean, t_var, r_var: [..., S].
    Returns:
      mean [..., S, 3] (relative to the ray origin), cov_diag [..., S, 3].
    """
    mean = d[..., None, :] * t_mean[..., None]
    d_mag_sq = jnp.maximum(1e-10, jnp.sum(d**2, axis=-1, keepdims=True))
    d_outer_diag = d**2
    null_outer_diag = 1 - d_outer_diag / d_mag_sq
    cov_diag = (t_var[..., None] * d_outer_diag[..., None, :]
                + r_var[..., None] * null_outer_diag[..., None, :])
    return mean, cov_diag


def cast_rays(t_vals: Array, origins: Array, directions: Array, radii: Array
              ) -> tuple[Array, Array]:
    """Gaussians of the conical frustums between consecutive ``t_vals``.

    Args:
      t_vals: [..., S + 1] sorted interval endpoints.
      origins, directions: [..., 3].
      radii: [...] cone radius at t = 1.
    Returns:
      means [..., S, 3] (world positions), cov_diag [..., S, 3].
    """
    t0, t1 = t_vals[..., :-1], t_vals[..., 1:]
    t_mean, t_var, r_var = conical_frustum_moments(t0, t1, radii[..., None])
    mean, cov = lift_gaussian(directions, t_mean, t_var, r_var)
    return mean + origins[..., None, :], cov


# ----------------------------------------------------------------------------- sampling


def piecewise_spacing(t: Array, pivot: Array) -> Array:
    """Linear-then-disparity spacing g(t): t / p below the pivot p, 2 - p / t beyond it.

    Continuous with a continuous slope at p, monotone, and g -> 2 as t -> inf: samples even
    in g are even in distance up to p and even in disparity beyond (the 1D form of the scene
    contraction). t, pivot: [...] (> 0) -> [...].
    """
    return jnp.where(t < pivot, t / pivot, 2.0 - pivot / jnp.maximum(t, 1e-10))


def piecewise_spacing_inv(g: Array, pivot: Array) -> Array:
    """Inverse of :func:`piecewise_spacing` for g in [0, 2): [...] -> t [...]."""
    return jnp.where(g < 1.0, g * pivot, pivot / jnp.maximum(2.0 - g, 1e-10))


def stratified_t_vals(key: Array, near: Array, far: Array, num_samples: int,
                      randomized: bool, lindisp: bool = False,
                      pivot: Array | None = None) -> Array:
    """Interval endpoints in [near, far], one random point per stratum when randomized.

    Args:
      key: PRNG key (unused when not randomized).
      near, far: [...] per-ray bounds (0 < near < far when lindisp).
      num_samples: number of intervals S (static).
      randomized: jitter each endpoint uniformly inside its stratum (training);
        otherwise evenly spaced endpoints (evaluation).
      lindisp: space the endpoints evenly in disparity 1/t instead of in t.
      pivot: [...] or None: space the endpoints evenly in :func:`piecewise_spacing` with
        this pivot (linear up to it, disparity beyond; the contracted scene's sampling);
        wins over lindisp.
    Returns:
      t_vals [..., S + 1], sorted, t_vals[..., 0] >= near, t_vals[..., -1] <= far.
    """
    s = jnp.linspace(0.0, 1.0, num_samples + 1, dtype=near.dtype)
    near_, far_ = near[..., None], far[..., None]
    if pivot is not None:
        p = jnp.broadcast_to(pivot, near.shape)[..., None]
        g0, g1 = piecewise_spacing(near_, p), piecewise_spacing(far_, p)
        g = g0 * (1.0 - s) + g1 * s
        if randomized:  # one uniform point per stratum of g, ends kept
            mids = 0.5 * (g[..., 1:] + g[..., :-1])
            upper = jnp.concatenate([mids, g[..., -1:]], axis=-1)
            lower = jnp.concatenate([g[..., :1], mids], axis=-1)
            g = lower + (upper - lower) * jax.random.uniform(key, g.shape, dtype=g.dtype)
        t_vals = piecewise_spacing_inv(g, p)
        return jnp.clip(jax.lax.cummax(t_vals, axis=t_vals.ndim - 1), near_, far_)
    if lindisp:
        t_vals = 1.0 / (1.0 / near_ * (1.0 - s) + 1.0 / far_ * s)
    else:
        t_vals = near_ * (1.0 - s) + far_ * s
    if randomized:
        mids = 0.5 * (t_vals[..., 1:] + t_vals[..., :-1])
        upper = jnp.concatenate([mids, t_vals[..., -1:]], axis=-1)
        lower = jnp.concatenate([t_vals[..., :1], mids], axis=-1)
        u = jax.random.uniform(key, t_vals.shape, dtype=t_vals.dtype)
        t_vals = lower + (upper - lower) * u
    return t_vals


def sample_along_rays(key: Array, origins: Array, directions: Array, radii: Array,
                      near: Array, far: Array, num_samples: int, randomized: bool,
                      lindisp: bool = False, pivot: Array | None = None
                      ) -> tuple[Array, tuple[Array, Array]]:
    """Stratified samples along cone rays.

    Args:
      origins, directions: [..., 3]; radii, near, far: [...]; pivot: see
        :func:`stratified_t_vals`.
    Returns:
      t_vals [..., S + 1] and the frustum Gaussians (means [..., S, 3], cov_diag [..., S, 3]).
    """
    t_vals = stratified_t_vals(key, near, far, num_samples, randomized, lindisp, pivot)
    return t_vals, cast_rays(t_vals, origins, directions, radii)


def sorted_piecewise_constant_pdf(key: Array, bins: Array, weights: Array, num_samples: int,
                                  randomized: bool) -> Array:
    """Inverse-transform samples of the piecewise-constant density given by ``weights``.

    Args:
      bins: [..., S + 1] sorted bin edges.
      weights: [..., S] non-negative bin weights (need not sum to 1).
      num_samples: number of samples N (static).
      randomized: stratified random u (one per 1/N stratum); else evenly spaced u.
    Returns:
      samples [..., N], sorted, inside [bins[..., 0], bins[..., -1]].
    """
    eps = 1e-5
    weight_sum = jnp.sum(weights, axis=-1, keepdims=True)
    padding = jnp.maximum(0.0, eps - weight_sum)  # all-zero weights -> uniform
    weights = weights + padding / weights.shape[-1]
    weight_sum = weight_sum + padding
    pdf = weights / weight_sum
    cdf = jnp.minimum(1.0, jnp.cumsum(pdf[..., :-1], axis=-1))
    shape = cdf.shape[:-1]
    cdf = jnp.concatenate([jnp.zeros(shape + (1,), cdf.dtype), cdf,
                           jnp.ones(shape + (1,), cdf.dtype)], axis=-1)  # [..., S + 1]
    if randomized:
        step = 1.0 / num_samples
        u = jnp.arange(num_samples, dtype=cdf.dtype) * step
        u = u + jax.random.uniform(key, shape + (num_samples,), dtype=cdf.dtype,
                                   maxval=step - eps)
        u = jnp.minimum(u, 1.0 - eps)
    else:
        u = jnp.broadcast_to(jnp.linspace(0.0, 1.0 - eps, num_samples, dtype=cdf.dtype),
                             shape + (num_samples,))
    # For each u, the last cdf entry <= u: comparisons against all S + 1 edges (S is small,
    # and this vectorises far better on CPU/GPU than a per-ray binary search).
    above = jnp.sum(u[..., None, :] >= cdf[..., :, None], axis=-2)  # [..., N] in 1..S+1
    i0 = jnp.clip(above - 1, 0, cdf.shape[-1] - 1)
    i1 = jnp.clip(above, 0, cdf.shape[-1] - 1)
    cdf0 = jnp.take_along_axis(cdf, i0, axis=-1)
    cdf1 = jnp.take_along_axis(cdf, i1, axis=-1)
    b0 = jnp.take_along_axis(bins, i0, axis=-1)
    b1 = jnp.take_along_axis(bins, i1, axis=-1)
    denom = cdf1 - cdf0
    frac = jnp.where(denom > 0, (u - cdf0) / jnp.where(denom > 0, denom, 1.0), 0.0)
    samples = b0 + jnp.clip(frac, 0.0, 1.0) * (b1 - b0)
    # Monotone by construction; the running max removes last-ulp rounding inversions.
    return jax.lax.cummax(samples, axis=samples.ndim - 1)


def blur_weights(weights: Array, resample_padding: float) -> Array:
    """Mip-NeRF's 2-tap max filter then 2-tap blur of the coarse weights, plus padding.

    Args:
      weights: [..., S].
    Returns:
      [..., S] smoothed weights (the max/blur widens every peak to its neighbours so the
      fine samples also cover the intervals next to a surface; the padding keeps some
      samples everywhere).
    """
    w_pad = jnp.concatenate([weights[..., :1], weights, weights[..., -1:]], axis=-1)
    w_max = jnp.maximum(w_pad[..., :-1], w_pad[..., 1:])
    w_blur = 0.5 * (w_max[..., :-1] + w_max[..., 1:])
    return w_blur + resample_padding


def resample_along_rays(key: Array, origins: Array, directions: Array, radii: Array,
                        t_vals: Array, weights: Array, num_samples: int, randomized: bool,
                        resample_padding: float = 0.01
                        ) -> tuple[Array, tuple[Array, Array]]:
    """Hierarchical sampling: new intervals drawn from the blurred coarse weights.

    As in mip-NeRF the fine level uses only the resampled intervals (no union with the
    coarse ones), and no gradient flows into the sample positions.

    Args:
      origins, directions: [..., 3]; radii: [...].
      t_vals: [..., S + 1] coarse endpoints; weights: [..., S] coarse weights.
      num_samples: number of fine intervals N (N + 1 endpoints are drawn).
    Returns:
      new t_vals [..., N + 1] (sorted, inside [t_vals[0], t_vals[-1]]) and their
      Gaussians (means [..., N, 3], cov_diag [..., N, 3]).
    """
    w = blur_weights(weights, resample_padding)
    new_t = sorted_piecewise_constant_pdf(key, t_vals, w, num_samples + 1, randomized)
    new_t = jax.lax.stop_gradient(new_t)
    return new_t, cast_rays(new_t, origins, directions, radii)


# ----------------------------------------------------------------------------- contraction


def contract(x: Array) -> Array:
    """mip-NeRF 360's scene contraction: x inside the unit ball, (2 - 1/|x|) x / |x| beyond.

    Maps all of space into the ball of radius 2 (continuous, with a continuous Jacobian at
    |x| = 1). x: [..., 3] -> [..., 3].
    """
    n = jnp.sqrt(jnp.maximum(jnp.sum(x * x, axis=-1, keepdims=True), 1e-20))
    return jnp.where(n <= 1.0, x, (2.0 - 1.0 / n) * x / n)


def contraction_scale(x: Array) -> Array:
    """Isotropic length scale of the contraction's Jacobian at x: det(J)^(1/3).

    Beyond the unit ball J has the radial eigenvalue 1/|x|^2 and twice the tangential one
    (2 - 1/|x|)/|x|; inside it is the identity (1). A Gaussian of standard deviation sigma
    at x becomes one of about sigma * contraction_scale(x) (Zip-NeRF's isotropic
    approximation of mip-NeRF 360's linearised covariance). x: [..., 3] -> [...].
    """
    n = jnp.sqrt(jnp.maximum(jnp.sum(x * x, axis=-1), 1e-20))
    outer = jnp.cbrt((1.0 / n**2) * ((2.0 - 1.0 / n) / n) ** 2)
    return jnp.where(n <= 1.0, 1.0, outer)


# ----------------------------------------------------------------------------- encodings


def fast_sin(x: Array) -> Array:
    """sin(x) in float32 to ~2e-7 absolute, as plain vectorisable arithmetic.

    Cody-Waite reduction to [-pi, pi] (2 pi split in two constants, so k * 2pi is exact for
    |k| < 2^16), the reflection sin(r) = sin(+-pi - r) to [-pi/2, pi/2], then the Taylor
    polynomial to degree 11 (truncation error < 6e-8 there). XLA:CPU's own sin costs ~15x
    more and the encodings evaluate ~10^7 of them per training step, so this matters on CPU;
    the features only need the accuracy of their float32 arguments (ulp(2^9 pi) ~ 1e-4).
    """
    two_pi_hi = 6.28125  # exactly representable with few mantissa bits
    two_pi_lo = 2 * 3.141592653589793 - 6.28125
    k = jnp.round(x * (1 / (2 * 3.141592653589793)))
    r = x - k * two_pi_hi - k * two_pi_lo
    half_pi, pi = 0.5 * 3.141592653589793, 3.141592653589793
    r = jnp.where(r > half_pi, pi - r, jnp.where(r < -half_pi, -pi - r, r))
    r2 = r * r
    return r * (1 + r2 * (-1 / 6 + r2 * (1 / 120 + r2 * (-1 / 5040 + r2 * (
        1 / 362880 + r2 * (-1 / 39916800))))))


def expected_sin(x: Array, x_var: Array) -> Array:
    """E[sin(X)] for X ~ N(x, x_var): exp(-x_var / 2) sin(x). Shapes broadcast."""
    return jnp.exp(-0.5 * x_var) * fast_sin(x)


def integrated_pos_enc(mean: Array, cov_diag: Array, min_deg: int, max_deg: int) -> Array:
    """Integrated positional encoding (mip-NeRF eq. 14) with diagonal covariance.

    Features are E[sin(2^l x_i)] and E[cos(2^l x_i)] for l in [min_deg, max_deg) under
    the Gaussian: high frequencies are attenuated in proportion to the footprint.

    Args:
      mean, cov_diag: [..., 3] (coordinates already normalised to about [-pi, pi]).
    Returns:
      [..., 2 * 3 * (max_deg - min_deg)] features: [sin block, cos block], each ordered
      degree-major then axis (l0: x, y, z; l1: x, y, z; ...).
    """
    # [y, y + pi/2] = mean @ [basis, basis] + offsets with basis [3, 3L] = [2^l I]_l: one
    # matrix product instead of broadcasts, reshapes and a concatenation (3-4x faster on
    # CPU; exact, as the basis holds powers of two).
    basis = np.concatenate([2.0**deg * np.eye(3) for deg in range(min_deg, max_deg)], axis=1)
    basis2 = jnp.asarray(np.concatenate([basis, basis], axis=1), mean.dtype)  # [3, 6L]
    offset = jnp.asarray(np.repeat([0.0, 0.5 * np.pi], basis.shape[1]), mean.dtype)
    y = jnp.matmul(mean, basis2, precision="highest") + offset
    y_var = jnp.matmul(cov_diag, basis2**2, precision="highest")
    return expected_sin(y, y_var)


def pos_enc(x: Array, min_deg: int, max_deg: int, append_identity: bool = True) -> Array:
    """Plain positional encoding [x, sin(2^l x), cos(2^l x)] for view directions.

    Args:
      x: [..., D].
    Returns:
      [..., D * (append_identity + 2 * (max_deg - min_deg))].
    """
    scales = 2.0 ** jnp.arange(min_deg, max_deg, dtype=x.dtype)
    xb = jnp.reshape(x[..., None, :] * scales[:, None], x.shape[:-1] + (-1,))
    four = fast_sin(jnp.concatenate([xb, xb + 0.5 * jnp.pi], axis=-1))
    return jnp.concatenate([x, four], axis=-1) if append_identity else four


# ----------------------------------------------------------------------------- rendering


def volumetric_rendering(rgb: Array, density: Array, t_vals: Array, directions: Array,
                         background: Array) -> dict[str, Array]:
    """Alpha compositing of samples along rays (NeRF eq. 3, mip-NeRF's interval form).

    Args:
      rgb: [..., S, 3] colours in [0, 1]; density: [..., S] non-negative.
      t_vals: [..., S + 1] interval endpoints; directions: [..., 3] (the length of an
        interval is (t1 - t0) |d|).
      background: [3] (or [..., 3]) colour seen where the ray's opacity is below one
        (white for Blender scenes, black -- i.e. no compositing -- otherwise).
    Returns:
      dict with rgb [..., 3], depth [..., ] (expected t of the visible content, in t units
      along d; t_vals[0] where nothing is hit), acc [...] (opacity), weights [..., S].
    """
    t_mids = 0.5 * (t_vals[..., :-1] + t_vals[..., 1:])
    t_dists = t_vals[..., 1:] - t_vals[..., :-1]
    delta = t_dists * jnp.linalg.norm(directions[..., None, :], axis=-1)
    density_delta = density * delta
    alpha = 1.0 - jnp.exp(-density_delta)
    trans = jnp.exp(-jnp.concatenate(
        [jnp.zeros_like(density_delta[..., :1]),
         jnp.cumsum(density_delta[..., :-1], axis=-1)], axis=-1))
    weights = alpha * trans
    acc = jnp.sum(weights, axis=-1)
    comp_rgb = jnp.sum(weights[..., None] * rgb, axis=-2)
    comp_rgb = comp_rgb + (1.0 - acc[..., None]) * background
    safe_acc = jnp.where(acc > 1e-10, acc, 1.0)
    depth = jnp.where(acc > 1e-10, jnp.sum(weights * t_mids, axis=-1) / safe_acc,
                      t_vals[..., 0])
    depth = jnp.clip(depth, t_vals[..., 0], t_vals[..., -1])
    return {"rgb": comp_rgb, "depth": depth, "acc": acc, "weights": weights}
