"""Mip-NeRF math against independent references (Monte Carlo, exact rationals, closed forms)."""

from __future__ import annotations

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vrs_jax.nerf import mipnerf


def _frustum_samples(rng, o, d, t0, t1, r, n):
    """Points uniform in the volume of the conical frustum between t0 and t1 (numpy)."""
    # The cross-section at t is a disk of radius t * r, so the density of t is ~ t^2.
    u = rng.random(n)
    t = np.cbrt(t0**3 + u * (t1**3 - t0**3))
    rho = t * r * np.sqrt(rng.random(n))
    phi = 2 * np.pi * rng.random(n)
    dn = d / np.linalg.norm(d)
    a = np.cross(dn, [1.0, 0.0, 0.0] if abs(dn[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(dn, a)
    return (o + t[:, None] * d + rho[:, None] * (np.cos(phi)[:, None] * a
                                                  + np.sin(phi)[:, None] * b))


@pytest.mark.parametrize("case", [
    # origin, direction (any norm), t0, t1, radius at t = 1
    ((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 1.0, 2.0, 0.05),
    ((0.3, -1.0, 2.0), (0.4, -0.7, 1.3), 0.5, 3.0, 0.2),
    ((1.0, 2.0, 3.0), (2.0, 1.0, -0.5), 2.0, 2.3, 0.5),
    ((0.0, 0.0, 0.0), (0.0, 0.6, 0.8), 0.01, 4.0, 0.1),
])
def test_frustum_gaussian_matches_monte_carlo(case):
    o, d, t0, t1, r = case
    o, d = np.asarray(o), np.asarray(d)
    rng = np.random.default_rng(0)
    pts = _frustum_samples(rng, o, d, t0, t1, r, 400_000)
    mc_mean, mc_var = pts.mean(0), pts.var(0)
    mean, cov = mipnerf.cast_rays(jnp.asarray([[t0, t1]], jnp.float32),
                                  jnp.asarray(o[None], jnp.float32),
                                  jnp.asarray(d[None], jnp.float32), jnp.asarray([r], jnp.float32))
    mean, cov = np.asarray(mean[0, 0]), np.asarray(cov[0, 0])
    se_mean = np.sqrt(mc_var / len(pts))
    assert np.all(np.abs(mean - mc_mean) < 5 * se_mean + 1e-5), (mean, mc_mean)
    np.testing.assert_allclose(cov, mc_var, rtol=0.02, atol=1e-7)


def _exact_moments(t0: Fraction, t1: Fraction, r: Fraction):
    """Moments of t (density ~ t^2 on [t0, t1]) and the radial variance, exactly."""
    m3 = t1**3 - t0**3
    mean = Fraction(3, 4) * (t1**4 - t0**4) / m3
    e2 = Fraction(3, 5) * (t1**5 - t0**5) / m3
    return mean, e2 - mean**2, r**2 * e2 / 4


@pytest.mark.parametrize("t0,width", [(1.0, 0.5), (100.0, 0.01), (1000.0, 0.001), (3.0, 1e-4)])
def test_frustum_moments_stable_in_float32(t0, width):
    # Thin, distant intervals: the textbook ratios (t1^5 - t0^5) / (t1^3 - t0^3) cancel
    # catastrophically in float32; the stable form must still match exact rationals.
    t1 = np.float32(t0) + np.float32(width)
    f0, f1 = Fraction(float(np.float32(t0))), Fraction(float(t1))
    mean_x, var_x, rvar_x = _exact_moments(f0, f1, Fraction(1, 10))
    mean, var, rvar = mipnerf.conical_frustum_moments(jnp.float32(t0), jnp.float32(t1),
                                                      jnp.float32(0.1))
    assert abs(float(mean) - float(mean_x)) <= 2e-7 * float(mean_x)
    assert abs(float(var) - float(var_x)) <= 1e-3 * float(var_x)
    assert abs(float(rvar) - float(rvar_x)) <= 1e-5 * float(rvar_x)


def test_ipe_matches_monte_carlo_expectation():
    rng = np.random.default_rng(1)
    mean = rng.uniform(-3, 3, size=(4, 3))
    var = rng.uniform(0, 0.05, size=(4, 3)) ** 2 * np.array([1.0, 10.0, 100.0])
    feats = np.asarray(mipnerf.integrated_pos_enc(jnp.asarray(mean, jnp.float32),
                                                  jnp.asarray(var, jnp.float32), 0, 5))
    n = 200_000
    x = mean[:, None, :] + np.sqrt(var)[:, None, :] * rng.standard_normal((4, n, 3))
    for deg in range(5):
        s = np.mean(np.sin(2.0**deg * x), axis=1)  # [4, 3]
        c = np.mean(np.cos(2.0**deg * x), axis=1)
        np.testing.assert_allclose(feats[:, 3 * deg: 3 * deg + 3], s, atol=0.01)
        np.testing.assert_allclose(feats[:, 15 + 3 * deg: 15 + 3 * deg + 3], c, atol=0.01)


def test_ipe_zero_variance_is_positional_encoding():
    x = jnp.asarray(np.random.default_rng(2).uniform(-3, 3, (10, 3)), jnp.float32)
    a = mipnerf.integrated_pos_enc(x, jnp.zeros_like(x), 0, 4)
    b = mipnerf.pos_enc(x, 0, 4, append_identity=False)
    np.testing.assert_allclose(a, b, atol=1e-5)
    # High frequencies of a wide Gaussian are switched off.
    wide = mipnerf.integrated_pos_enc(x, jnp.ones_like(x), 0, 4)
    assert float(jnp.max(jnp.abs(wide[:, 9:12]))) < 1e-10 + np.exp(-0.5 * 64)


@given(st.floats(-3000, 3000, allow_nan=False, width=32))
@settings(max_examples=200, deadline=None)
def test_fast_sin_matches_numpy(x):
    got = float(mipnerf.fast_sin(jnp.float32(x)))
    assert abs(got - np.sin(np.float64(np.float32(x)))) < 3e-7 + 1e-7 * abs(x) * 1e-3


def test_fast_sin_array():
    x = np.linspace(-700.0, 700.0, 100_001, dtype=np.float32)
    np.testing.assert_allclose(np.asarray(mipnerf.fast_sin(jnp.asarray(x))),
                               np.sin(x.astype(np.float64)), atol=3e-7)


@pytest.mark.parametrize("dnorm", [1.0, 2.5])
def test_volume_rendering_constant_density_closed_form(dnorm):
    rng = np.random.default_rng(3)
    sigma, near, far = 0.7, 2.0, 6.0
    t = np.sort(rng.uniform(near, far, 63))
    t_vals = np.concatenate([[near], t, [far]])[None]  # irregular intervals
    d = np.array([[0.0, 0.6, 0.8]]) * dnorm
    s = t_vals.shape[1] - 1
    rgb = rng.uniform(0, 1, (1, s, 3))
    bg = np.array([0.2, 0.5, 1.0])
    out = mipnerf.volumetric_rendering(jnp.asarray(rgb, jnp.float32),
                                       jnp.full((1, s), sigma, jnp.float32),
                                       jnp.asarray(t_vals, jnp.float32),
                                       jnp.asarray(d, jnp.float32), jnp.asarray(bg, jnp.float32))
    k = sigma * dnorm  # density per unit t
    w = np.exp(-k * (t_vals[0, :-1] - near)) * (1 - np.exp(-k * np.diff(t_vals[0])))
    np.testing.assert_allclose(np.asarray(out["weights"][0]), w, rtol=1e-4, atol=1e-6)
    acc = 1 - np.exp(-k * (far - near))
    np.testing.assert_allclose(float(out["acc"][0]), acc, rtol=1e-5)
    np.testing.assert_allclose(np.asarray(out["rgb"][0]), (w[:, None] * rgb[0]).sum(0)
                               + (1 - acc) * bg, rtol=1e-4)


def test_volume_rendering_depth_of_constant_density():
    # Continuous expectation of the termination depth for constant density, normalised by
    # the opacity: near + 1/k - L exp(-kL) / (1 - exp(-kL)).
    k, near, far = 0.9, 1.0, 5.0
    t_vals = jnp.linspace(near, far, 4001)[None]
    out = mipnerf.volumetric_rendering(jnp.ones((1, 4000, 3)), jnp.full((1, 4000), k),
                                       t_vals, jnp.asarray([[0.0, 0.0, 1.0]]), jnp.zeros(3))
    L = far - near
    expect = near + 1 / k - L * np.exp(-k * L) / (1 - np.exp(-k * L))
    np.testing.assert_allclose(float(out["depth"][0]), expect, atol=2e-3)


def test_empty_ray_gives_background_and_near_depth():
    out = mipnerf.volumetric_rendering(jnp.ones((2, 8, 3)), jnp.zeros((2, 8)),
                                       jnp.tile(jnp.linspace(2, 6, 9), (2, 1)),
                                       jnp.ones((2, 3)), jnp.asarray([1.0, 1.0, 1.0]))
    np.testing.assert_allclose(out["rgb"], 1.0)
    np.testing.assert_allclose(out["acc"], 0.0)
    np.testing.assert_allclose(out["depth"], 2.0)


@pytest.mark.parametrize("randomized,lindisp", [(False, False), (True, False), (True, True)])
def test_stratified_samples_sorted_inside_bounds(randomized, lindisp):
    near = jnp.asarray([0.5, 2.0, 10.0])
    far = jnp.asarray([1.0, 6.0, 100.0])
    t = np.asarray(mipnerf.stratified_t_vals(jax.random.key(0), near, far, 32, randomized,
                                             lindisp))
    assert t.shape == (3, 33)
    assert np.all(np.diff(t, axis=-1) >= 0)
    assert np.all(t >= np.asarray(near)[:, None] - 1e-5)
    assert np.all(t <= np.asarray(far)[:, None] * (1 + 1e-6))


_resample = jax.jit(mipnerf.resample_along_rays, static_argnums=(6, 7))


@given(st.lists(st.floats(0.0, 10.0, allow_nan=False), min_size=32, max_size=32),
       st.integers(0, 2**31 - 1), st.booleans())
@settings(max_examples=60, deadline=None)
def test_resampling_sorted_inside_near_far(weights, seed, randomized):
    s = len(weights)
    rng = np.random.default_rng(seed)
    near, far = rng.uniform(0.1, 2.0), rng.uniform(2.5, 8.0)
    t_vals = np.sort(np.concatenate([[near, far], rng.uniform(near, far, s - 1)]))[None]
    w = np.asarray(weights, np.float32)[None]
    if seed % 5 == 0:
        w = np.zeros_like(w)  # no content at all: falls back to uniform
    new_t, (means, covs) = _resample(
        jax.random.key(seed), jnp.zeros((1, 3)), jnp.asarray([[0.0, 0.0, 1.0]]),
        jnp.asarray([0.01]), jnp.asarray(t_vals, jnp.float32), jnp.asarray(w), 24, randomized)
    new_t = np.asarray(new_t)
    assert new_t.shape == (1, 25) and means.shape == (1, 24, 3) and covs.shape == (1, 24, 3)
    assert np.all(np.diff(new_t) >= 0)
    assert new_t.min() >= np.float32(near) - 1e-5 and new_t.max() <= np.float32(far) + 1e-5


def test_inverse_transform_sampling_follows_the_pdf():
    bins = jnp.asarray([[0.0, 1.0, 2.0, 4.0, 5.0]])
    w = jnp.asarray([[1.0, 0.0, 6.0, 3.0]])
    n = 10_000
    samples = np.asarray(mipnerf.sorted_piecewise_constant_pdf(jax.random.key(0), bins, w, n,
                                                               randomized=True))[0]
    frac = np.histogram(samples, bins=np.asarray(bins[0]))[0] / n
    np.testing.assert_allclose(frac, [0.1, 0.0, 0.6, 0.3], atol=2e-3)
    # Inside a bin the density is uniform.
    inner = samples[(samples > 2.0) & (samples < 4.0)]
    assert abs(np.mean(inner) - 3.0) < 0.02


def test_blur_weights_widens_peaks():
    w = jnp.asarray([[0.0, 0.0, 1.0, 0.0, 0.0]])
    np.testing.assert_allclose(mipnerf.blur_weights(w, 0.0), [[0.0, 0.5, 1.0, 0.5, 0.0]])
    np.testing.assert_allclose(mipnerf.blur_weights(w, 0.01)[0, 0], 0.01)


# ----------------------------------------------------------------------------- contraction


@settings(max_examples=40, deadline=None)
@given(st.floats(0.05, 50.0), st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1))
def test_contraction_scale_is_the_cube_root_of_the_jacobian_determinant(r, a, b, c):
    """contraction_scale(x)^3 equals |det J| of contract at x, J by autodiff; the map stays
    inside the ball of radius 2 and is the identity inside the unit ball."""
    v = np.array([a, b, c]) + 1e-3
    x = jnp.asarray(r * v / np.linalg.norm(v), jnp.float32)
    J = np.asarray(jax.jacfwd(mipnerf.contract)(x), np.float64)
    s = float(mipnerf.contraction_scale(x))
    np.testing.assert_allclose(s**3, abs(np.linalg.det(J)), rtol=2e-4, atol=1e-9)
    y = np.asarray(mipnerf.contract(x))
    assert np.linalg.norm(y) < 2.0 + 1e-6
    if r <= 1.0:
        np.testing.assert_allclose(y, np.asarray(x), rtol=1e-6)
        assert s == 1.0
    else:  # radial direction kept, radius 2 - 1/|x|
        np.testing.assert_allclose(np.linalg.norm(y), 2 - 1 / r, rtol=1e-5)
        np.testing.assert_allclose(y / np.linalg.norm(y), np.asarray(x) / r, atol=1e-5)


def test_contraction_is_continuous_at_the_unit_sphere():
    u = jnp.asarray(np.random.default_rng(0).normal(size=(50, 3)), jnp.float32)
    u = u / jnp.linalg.norm(u, axis=-1, keepdims=True)
    inside, outside = mipnerf.contract(u * (1 - 1e-4)), mipnerf.contract(u * (1 + 1e-4))
    np.testing.assert_allclose(inside, outside, atol=3e-4)
    np.testing.assert_allclose(mipnerf.contraction_scale(u * (1 + 1e-4)), 1.0, atol=1e-3)


def test_piecewise_spacing_inverse_and_samples():
    """g is inverted exactly; samples with a pivot lie in [near, far], sorted, evenly spaced
    in g (linear in t below the pivot, in disparity beyond), stratified when randomized."""
    p = jnp.float32(2.0)
    t = jnp.asarray([0.1, 0.5, 1.9, 2.0, 2.5, 10.0, 1e4], jnp.float32)
    # float32: g = 2 - p / t keeps ~ulp(2) / (p / t) relative precision in t (6e-4 at 1e4)
    np.testing.assert_allclose(mipnerf.piecewise_spacing_inv(mipnerf.piecewise_spacing(t, p), p),
                               t, rtol=1e-3)
    near, far = jnp.full((4,), 0.5), jnp.full((4,), 400.0)
    tv = mipnerf.stratified_t_vals(jax.random.key(0), near, far, 16, False, pivot=jnp.full(4, 2.0))
    g = np.asarray(mipnerf.piecewise_spacing(tv, 2.0))
    np.testing.assert_allclose(np.diff(g, axis=-1), np.diff(g, axis=-1)[:, :1] + 0 * g[:, 1:],
                               rtol=1e-4)
    np.testing.assert_allclose(tv[:, 0], 0.5, rtol=1e-6)
    np.testing.assert_allclose(tv[:, -1], 400.0, rtol=1e-5)
    below = np.asarray(tv[0]) < 2.0
    assert 6 <= below.sum() <= 9  # about half the samples inside the pivot
    tr = np.asarray(mipnerf.stratified_t_vals(jax.random.key(1), near, far, 16, True,
                                              pivot=jnp.full(4, 2.0)))
    assert np.all(np.diff(tr, axis=-1) >= 0) and tr.min() >= 0.5 and tr.max() <= 400.0 + 1e-3
    gr = np.asarray(mipnerf.piecewise_spacing(jnp.asarray(tr), 2.0))
    edges = np.linspace(g[0, 0], g[0, -1], 17)  # each jittered endpoint in its stratum
    half = np.concatenate([[edges[0]], 0.5 * (edges[1:] + edges[:-1]), [edges[-1]]])
    assert np.all(gr[:, 1:-1] >= half[1:-2] - 1e-5) and np.all(gr[:, 1:-1] <= half[2:-1] + 1e-5)
