"""RANSAC seed + robust LM refinement (vrs_jax.localize.pnp).

Geometry of the synthetic problems (the acceptance test's): 640x480 pinhole camera, f = 525,
c = (320, 240) -- the 7Scenes RGB camera -- 1000 correspondences whose true points lie at
depths uniform in [0.5, 3] m (indoor, 7Scenes-like), image points uniform over the frame,
1 px Gaussian noise on the inliers, 50% of the correspondences replaced by uniform outliers.

Why this geometry: the Cramer-Rao bound of the camera centre from 500 inliers at 0.5-3 m is
0.27 mm RMS (rotation 0.012 deg), so "under 1 mm / 0.05 deg" is a ~4-sigma claim any
efficient estimator should meet. With a sparser geometry (400 points at 1-5 m, i.e.
200 inliers) the bound itself is 1.2 mm RMS (0.029 deg): no estimator can meet 1 mm there
reliably, so that geometry would make the test fail for a correct implementation.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vrs_jax import geometry
from vrs_jax.localize import pnp

W, H, F = 640, 480, 525.0
K64 = np.array([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1.0]])
CFG = pnp.PnPConfig()

_estimate = jax.jit(pnp.estimate_pose, static_argnames="cfg")
_refine = jax.jit(pnp.refine_pose, static_argnames="cfg")


def make_problem(seed: int, n: int = 1000, outliers: float = 0.5, noise: float = 1.0,
                 dmin: float = 0.5, dmax: float = 3.0):
    """Random pose and correspondences. Returns uv [n,2], X [n,3], R, t, is_inlier [n]."""
    rng = np.random.default_rng(seed)
    R = geometry.axis_angle_to_rot(rng.normal(size=3) * 0.5)
    t = -R @ rng.normal(size=3)
    uv_true = np.stack([rng.uniform(0, W, n), rng.uniform(0, H, n)], -1)
    depth = rng.uniform(dmin, dmax, n)
    Xc = geometry.unproject(K64, uv_true) * depth[:, None]
    X = (Xc - t) @ R  # camera -> world: R^T (Xc - t)
    uv = uv_true + rng.normal(size=uv_true.shape) * noise
    n_out = int(round(n * outliers))
    out = rng.permutation(n)[:n_out]
    uv[out] = np.stack([rng.uniform(0, W, n_out), rng.uniform(0, H, n_out)], -1)
    inl = np.ones(n, dtype=bool)
    inl[out] = False
    return uv, X, R, t, inl


def f32(*arrays):
    return tuple(np.asarray(a, dtype=np.float32) for a in arrays)


def errors(R, t, R_gt, t_gt):
    dt, dr = geometry.pose_errors(np.asarray(R, np.float64), np.asarray(t, np.float64), R_gt, t_gt)
    return float(dt), float(dr)


def np_robust_cost(R, t, uv, X, w, K, c=1.0):
    """Independent float64 reference of 0.5 * sum w * c^2 log(1 + |e|^2 / c^2)."""
    R, t, uv, X, w = (np.asarray(a, np.float64) for a in (R, t, uv, X, w))
    keep = w > 0
    proj, _ = geometry.project(np.asarray(K, np.float64), R, t, X[keep])
    s = np.sum((proj - uv[keep]) ** 2, -1)
    return 0.5 * np.sum(w[keep] * c * c * np.log1p(s / (c * c)))


# ----------------------------------------------------------------------------- acceptance


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_recovers_pose_with_half_outliers(seed):
    uv, X, R, t, inl = make_problem(seed)
    res = _estimate(*f32(uv, X), np.ones(len(uv), bool), *f32(K64), cfg=CFG)
    assert bool(res.success)
    dt, dr = errors(res.R, res.t, R, t)
    assert dt < 1e-3 and dr < 0.05, (dt, dr)
    # The inliers found are the true ones (up to the odd outlier landing within 6 px).
    found = np.asarray(res.inliers)
    assert np.sum(found & ~inl) <= 3 and np.sum(inl & ~found) <= 3
    assert int(res.n_inliers) == found.sum()
    assert float(res.cost) <= float(res.cost_seed)


def test_refinement_improves_on_the_seed_on_average():
    """The LM stage is not a no-op: over a few problems it reduces the pose error."""
    gains = []
    for seed in range(3):
        uv, X, R, t, _ = make_problem(seed)
        mask = np.ones(len(uv), bool)
        R0, t0, inl0, ok = pnp.ransac_pnp(*f32(uv, X), mask, *f32(K64), CFG)
        assert bool(ok)
        R1, t1, info = _refine(R0, t0, *f32(uv, X), np.asarray(inl0, np.float32), *f32(K64),
                               cfg=CFG)
        assert bool(info.improved) and float(info.cost) < float(info.cost_seed)
        gains.append(errors(R0, t0, R, t)[0] - errors(R1, t1, R, t)[0])
    assert np.mean(gains) > 0


def test_refine_seed_on_a_few_rows_matches_every_row():
    """refine_seed with max_rows at least the seed's inliers gives the pose of all M slots
    (the other slots weigh 0); with fewer rows than inliers the first ones still refine the
    pose near the truth, to another pose than all of them, and the recount always uses every
    slot."""
    uv, X, R, t, _ = make_problem(4, n=1200, outliers=0.7)
    mask = np.ones(len(uv), bool)
    R0, t0, inl0, ok = pnp.ransac_pnp(*f32(uv, X), mask, *f32(K64), CFG)
    n_inl = int(np.sum(inl0))
    assert bool(ok) and 100 < n_inl < 600
    seed = jax.jit(pnp.refine_seed, static_argnames=("cfg", "max_rows"))
    args = (R0, t0, inl0, ok, *f32(uv, X), mask, *f32(K64))
    full = seed(*args, cfg=CFG)
    few = seed(*args, cfg=CFG, max_rows=600)
    np.testing.assert_allclose(np.asarray(few.R), np.asarray(full.R), atol=2e-5)
    np.testing.assert_allclose(np.asarray(few.t), np.asarray(full.t), atol=2e-5)
    np.testing.assert_array_equal(np.asarray(few.inliers), np.asarray(full.inliers))
    part = seed(*args, cfg=CFG, max_rows=n_inl // 2)
    assert bool(part.success) and errors(part.R, part.t, R, t)[0] < 2e-3
    # half the inliers give another pose (~2e-3 away here): max_rows does cut the rows
    assert np.max(np.abs(np.asarray(part.t) - np.asarray(full.t))) > 1e-4
    assert abs(int(part.n_inliers) - int(full.n_inliers)) <= 3
    assert np.asarray(part.inliers).shape == (len(uv),)


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), rot_deg=st.floats(0.0, 3.0), trans_m=st.floats(0.0, 0.1),
       outliers=st.sampled_from([0.0, 0.3, 0.6]))
def test_refinement_never_worsens_the_seed_cost(seed, rot_deg, trans_m, outliers):
    """Property: from any seed (perturbed truth, inliers or not), cost never goes up, and the
    reported costs are the robust cost of the returned poses (checked against numpy)."""
    uv, X, R, t, _ = make_problem(seed, n=300, outliers=outliers)
    rng = np.random.default_rng(seed + 1)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R0 = geometry.axis_angle_to_rot(axis * np.radians(rot_deg)) @ R
    t0 = t + rng.normal(size=3) * trans_m
    w = rng.uniform(0, 2, len(uv)) * (rng.uniform(size=len(uv)) < 0.8)  # some zero weights
    R1, t1, info = _refine(*f32(R0, t0, uv, X, w, K64), cfg=CFG)
    assert float(info.cost) <= float(info.cost_seed)
    ref_seed = np_robust_cost(R0, t0, uv, X, w, K64)
    ref_new = np_robust_cost(R1, t1, uv, X, w, K64)
    assert float(info.cost_seed) == pytest.approx(ref_seed, rel=1e-4)
    assert float(info.cost) == pytest.approx(ref_new, rel=1e-4)
    assert ref_new <= ref_seed * (1 + 1e-5)
    if not bool(info.improved):
        np.testing.assert_array_equal(np.asarray(R1), np.float32(R0))
        np.testing.assert_array_equal(np.asarray(t1), np.float32(t0))


def float32_basin(cost: float, n_inliers: int, n_terms: int) -> float:
    """Radius in radians of the flat region around a float32 optimum of the robust cost.

    LM accepts a step whenever the float32 cost goes down, and near the optimum that test is
    decided by round-off: a sum of ``n_terms`` float32 terms carries an error of about
    eps * cost * sqrt(n_terms), and a rotation by d radians raises the cost by about
    0.5 * n_inliers * F^2 * d^2 (each inlier moves by F * d pixels, weight ~1 below the 1 px
    Cauchy scale). Steps inside the radius where the two are equal are accepted or rejected
    by chance, so a second refinement may wander that far without being wrong.
    """
    eps = float(np.finfo(np.float32).eps)
    return float(np.sqrt(2 * eps * np.sqrt(n_terms) * cost / (n_inliers * F ** 2)))


@pytest.mark.parametrize("seed", [0, 3])
def test_refining_the_optimum_again_keeps_it(seed):
    uv, X, R, t, inl = make_problem(seed, n=300)
    R1, t1, _ = _refine(*f32(R, t, uv, X, inl, K64), cfg=CFG)
    R2, t2, info = _refine(R1, t1, *f32(uv, X, inl, K64), cfg=CFG)
    assert float(info.cost) <= float(info.cost_seed)
    dt, dr = errors(R2, t2, np.asarray(R1, np.float64), np.asarray(t1, np.float64))
    # Measured (one machine): 0.3-6.7 um and 1.6e-5 - 1.5e-4 deg for seeds 0-5, against a basin
    # of ~1.5e-4 deg (2.6e-6 rad). A rotation inside the basin trades against a translation
    # of d * depth (the pixel motion of the one nearly cancels the other's), depth <= 3 m.
    # Three basins is still 1/50 of the Cramer-Rao spread (0.02 deg) of this geometry.
    basin = float32_basin(np_robust_cost(R1, t1, uv, X, inl, K64), int(inl.sum()), len(uv))
    assert dr < 3 * np.degrees(basin), (dr, np.degrees(basin))
    assert dt < 3 * basin * 3.0, (dt, basin)


@pytest.mark.parametrize("seed", [0, 1])
def test_agrees_with_pycolmap(seed):
    uv, X, R, t, _ = make_problem(seed)
    camera = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[F, F, W / 2, H / 2])
    est = pycolmap.AbsolutePoseEstimationOptions()
    est.ransac.max_error = CFG.threshold_px
    ref = pycolmap.AbsolutePoseRefinementOptions()  # Cauchy loss, scale 1 px: as CFG
    assert ref.loss_function_scale == CFG.loss_scale_px and CFG.loss == "cauchy"
    out = pycolmap.estimate_and_refine_absolute_pose(uv, X, camera, est, ref)
    Rp, tp = out["cam_from_world"].rotation.matrix(), out["cam_from_world"].translation
    res = _estimate(*f32(uv, X), np.ones(len(uv), bool), *f32(K64), cfg=CFG)
    # Measured: 3-13 um and 0.3-1.3 arcsec apart (both 0.2-0.8 mm from the truth).
    dt, dr = errors(res.R, res.t, Rp, tp)
    assert dt < 5e-5 and dr < 2e-3, (dt, dr)
    # On pycolmap's own inlier set our optimum is at least as low in the shared robust cost.
    w = np.asarray(out["inlier_mask"], np.float64).reshape(-1)
    R1, t1, _ = _refine(*f32(Rp, tp, uv, X, w, K64), cfg=CFG)
    assert np_robust_cost(R1, t1, uv, X, w, K64) <= np_robust_cost(Rp, tp, uv, X, w, K64) * (
        1 + 1e-6)


# ----------------------------------------------------------------------------- jit / vmap


def test_vmap_over_a_batch_of_three():
    probs = [make_problem(s) for s in (4, 5)]
    uv = np.stack([p[0] for p in probs] + [probs[0][0]]).astype(np.float32)
    X = np.stack([p[1] for p in probs] + [probs[0][1]]).astype(np.float32)
    mask = np.ones(uv.shape[:2], bool)
    mask[2] = False  # the third problem has every correspondence masked out
    Ks = np.broadcast_to(K64, (3, 3, 3)).astype(np.float32)
    batched = jax.jit(jax.vmap(pnp.estimate_pose, in_axes=(0, 0, 0, 0, None)),
                      static_argnums=4)(uv, X, mask, Ks, CFG)
    np.testing.assert_array_equal(np.asarray(batched.success), [True, True, False])
    for i in range(2):
        single = _estimate(uv[i], X[i], mask[i], Ks[i], cfg=CFG)
        np.testing.assert_allclose(np.asarray(batched.R[i]), np.asarray(single.R), atol=1e-5)
        np.testing.assert_allclose(np.asarray(batched.t[i]), np.asarray(single.t), atol=1e-5)
        assert int(batched.n_inliers[i]) == int(single.n_inliers)
        dt, dr = errors(batched.R[i], batched.t[i], probs[i][2], probs[i][3])
        assert dt < 1e-3 and dr < 0.05
    np.testing.assert_array_equal(np.asarray(batched.R[2]), np.eye(3))
    assert int(batched.n_inliers[2]) == 0


def test_ransac_seed_under_jit_and_vmap_with_unbatched_K():
    uv, X, R, t, _ = make_problem(6, n=100, outliers=0.3)
    uvb = np.stack([uv, uv]).astype(np.float32)
    Xb = np.stack([X, X]).astype(np.float32)
    fn = jax.jit(jax.vmap(lambda a, b, m, k: pnp.ransac_pnp(a, b, m, k, CFG),
                          in_axes=(0, 0, 0, None)))
    Rb, tb, inl, ok = fn(uvb, Xb, np.ones((2, 100), bool), K64.astype(np.float32))
    assert Rb.shape == (2, 3, 3) and inl.shape == (2, 100) and ok.shape == (2,)
    assert bool(ok.all())
    dt, dr = errors(Rb[1], tb[1], R, t)
    assert dt < 0.02 and dr < 0.5


# ----------------------------------------------------------------------------- conventions


def test_no_pixel_shift_noise_free():
    """Noise-free points in COLMAP's convention give the exact pose: a 0.5 px shift between
    the points and K would bias it by ~1.5 mm at these depths."""
    uv, X, R, t, _ = make_problem(7, n=300, outliers=0.0, noise=0.0)
    res = _estimate(*f32(uv, X), np.ones(300, bool), *f32(K64), cfg=CFG)
    assert bool(res.success) and int(res.n_inliers) == 300
    dt, dr = errors(res.R, res.t, R, t)
    assert dt < 2e-5 and dr < 1e-3, (dt, dr)


def test_masked_padding_is_ignored_even_if_nan():
    """Padding rows (mask False) holding NaN/inf or zeros give bit-identical results."""
    uv, X, R, t, _ = make_problem(8, n=260, outliers=0.3)
    pad = 40
    mask = np.r_[np.ones(260, bool), np.zeros(pad, bool)]
    a = _estimate(*f32(np.concatenate([uv, np.full((pad, 2), np.nan)]),
                       np.concatenate([X, np.full((pad, 3), np.inf)])), mask, *f32(K64), cfg=CFG)
    b = _estimate(*f32(np.concatenate([uv, np.zeros((pad, 2))]),
                       np.concatenate([X, np.zeros((pad, 3))])), mask, *f32(K64), cfg=CFG)
    assert bool(a.success) and bool(b.success)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert not np.asarray(a.inliers)[260:].any()
    assert np.isfinite(float(a.cost))
    dt, dr = errors(a.R, a.t, R, t)
    assert dt < 3e-3 and dr < 0.1


@pytest.mark.parametrize("method", ["usac", "sqpnp"])
def test_other_ransac_methods(method):
    """The alternative seeds (host side; refinement is the same code for all)."""
    uv, X, R, t, inl = make_problem(9, n=300, outliers=0.5)
    cfg = dataclasses.replace(CFG, method=method)
    R0, t0, found, ok = pnp.ransac_pnp_host(uv, X, np.ones(300, bool), K64, cfg)
    assert ok
    assert np.sum(found != inl) <= 3
    dt, dr = errors(R0, t0, R, t)
    assert dt < 5e-3 and dr < 0.2


def test_huber_loss_refinement():
    uv, X, R, t, inl = make_problem(10, n=300, outliers=0.0)
    cfg = dataclasses.replace(CFG, loss="huber", loss_scale_px=2.0)
    R0 = geometry.axis_angle_to_rot(np.array([0.01, -0.02, 0.005])) @ R
    R1, t1, info = _refine(*f32(R0, t + 0.02, uv, X, inl, K64), cfg=cfg)
    assert bool(info.improved) and bool(info.converged)
    dt, dr = errors(R1, t1, R, t)
    assert dt < 2e-3 and dr < 0.05


def test_robust_rho_closed_forms():
    s = jnp.asarray([0.0, 1e-9, 0.25, 1.0, 4.0, 100.0])
    c = 2.0
    cauchy = np.asarray(pnp.robust_rho(s, "cauchy", c))
    np.testing.assert_allclose(cauchy, c * c * np.log1p(np.asarray(s) / (c * c)), rtol=1e-5,
                               atol=1e-12)
    huber = np.asarray(pnp.robust_rho(s, "huber", c))
    sn = np.asarray(s, np.float64)
    np.testing.assert_allclose(huber, np.where(sn <= c * c, sn, 2 * c * np.sqrt(sn) - c * c),
                               rtol=1e-5, atol=1e-12)


# ----------------------------------------------------------------------------- degenerate


@pytest.mark.parametrize("case", ["empty", "three", "all_masked", "identical_3d", "random_2d"])
def test_degenerate_inputs_fail_cleanly(case):
    uv, X, _, _, _ = make_problem(11, n=300, outliers=0.0)
    mask = np.ones(300, bool)
    if case == "empty":
        uv, X, mask = uv[:0], X[:0], mask[:0]
    elif case == "three":
        uv, X, mask = uv[:3], X[:3], mask[:3]
    elif case == "all_masked":
        mask[:] = False
    elif case == "identical_3d":
        X = np.repeat(X[:1], 300, axis=0)
    elif case == "random_2d":
        uv = np.random.default_rng(0).uniform(0, 480, size=(300, 2))
    res = _estimate(*f32(uv, X), mask, *f32(K64), cfg=CFG)
    assert not bool(res.success)
    np.testing.assert_array_equal(np.asarray(res.R), np.eye(3))
    np.testing.assert_array_equal(np.asarray(res.t), np.zeros(3))
    assert int(res.n_inliers) == 0 and not np.asarray(res.inliers).any()
    R, t, inl, ok = pnp.ransac_pnp_host(uv, X, mask, K64, CFG)
    assert not ok and not inl.any()


def test_config_validation_and_names():
    assert pnp.get_config("paper") == pnp.PnPConfig()
    assert pnp.get_config("cpu-small").max_iterations < pnp.PnPConfig().max_iterations
    with pytest.raises(KeyError):
        pnp.get_config("nope")
    with pytest.raises(ValueError):
        pnp.PnPConfig(method="ransac")
    with pytest.raises(ValueError):
        pnp.PnPConfig(loss="l2")
    hash(pnp.PnPConfig())  # static under jit
