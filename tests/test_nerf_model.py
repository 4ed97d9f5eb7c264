"""The MLP and ray rendering: shapes, world-frame invariance, cluster selection, loss."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vrs_jax.errors import VrsError
from vrs_jax.nerf import model
from vrs_jax.nerf.config import get_config, parse_overrides

CFG = get_config("test")
# One compiled renderer for the whole module (64 rays everywhere): compiling dominates.
_render = jax.jit(model.render_rays, static_argnums=(7, 8))


def _rays(n=64, seed=0):
    rng = np.random.default_rng(seed)
    o = rng.normal(0, 0.3, (n, 3)) + np.array([0.0, 0.0, -4.0])
    d = np.concatenate([rng.normal(0, 0.2, (n, 2)), np.ones((n, 1))], 1)
    f = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    return f(o), f(d), f(np.full(n, 0.004)), f(np.full(n, 2.0)), f(np.full(n, 6.0))


def _field(seed=0, center=(0.0, 0.0, 0.0), scale=0.8, bg=(1.0, 1.0, 1.0)):
    params = model.init_params(jax.random.key(seed), CFG)
    return model.Field(params, jnp.asarray(center, jnp.float32), jnp.float32(scale),
                       jnp.asarray(bg, jnp.float32))


def test_render_rays_shapes_and_ranges():
    o, d, r, n, f = _rays()
    out = _render(_field(), o, d, r, n, f, jax.random.key(1), CFG, True)
    assert out["rgb"].shape == (64, 3) and out["depth"].shape == (64,)
    assert out["acc"].shape == (64,)
    assert np.all((np.asarray(out["acc"]) >= 0) & (np.asarray(out["acc"]) <= 1 + 1e-5))
    assert np.all((np.asarray(out["depth"]) >= 2.0 - 1e-4) & (np.asarray(out["depth"]) <= 6.0))
    levels = jax.jit(model.render_levels, static_argnums=(7, 8))(
        _field(), o, d, r, n, f, jax.random.key(1), CFG, True)
    assert len(levels) == 2
    assert levels[0]["weights"].shape == (64, CFG.num_samples_coarse)
    assert levels[1]["t_vals"].shape == (64, CFG.num_samples_fine + 1)


def test_rendering_is_invariant_to_a_similarity_of_the_world_frame():
    # World B = (world A - a) * k. Rays, radii and the normalisation move with it, so the
    # rendering (and the t-depths) must be identical: radii scale with the world.
    o, d, r, n, f = _rays()
    a, k = np.array([1.0, -2.0, 0.5]), 3.0
    field_a = _field(center=(0.1, 0.2, -0.3), scale=0.8)
    field_b = model.Field(field_a.params, (field_a.center - a) * k, field_a.scale / k,
                          field_a.background)
    key = jax.random.key(0)
    out_a = _render(field_a, o, d, r, n, f, key, CFG, False)
    out_b = _render(field_b, (o - a) * k, d * k, r * k, n, f, key, CFG, False)
    for key in ("rgb", "depth", "acc"):
        np.testing.assert_allclose(out_a[key], out_b[key], rtol=2e-4, atol=2e-5)


def test_radius_changes_the_rendering():
    o, d, r, n, f = _rays()
    key = jax.random.key(0)
    a = _render(_field(), o, d, r, n, f, key, CFG, False)["rgb"]
    b = _render(_field(), o, d, r * 50, n, f, key, CFG, False)["rgb"]
    assert float(jnp.max(jnp.abs(a - b))) > 1e-4


def test_select_field_picks_the_cluster():
    stacked = jax.tree.map(lambda *x: jnp.stack(x), _field(0), _field(1, scale=0.5))
    o, d, r, n, f = _rays()
    key = jax.random.key(0)
    for c in (0, 1):
        ref = _render(_field(c, scale=0.8 if c == 0 else 0.5), o, d, r, n, f, key, CFG, False)
        got = _render(model.select_field(stacked, c), o, d, r, n, f, key, CFG, False)
        np.testing.assert_allclose(got["rgb"], ref["rgb"], atol=1e-6)


def test_stacked_init_gives_independent_clusters():
    p = jax.jit(model.init_stacked_params, static_argnums=(1, 2))(jax.random.key(0), CFG, 3)
    k = p["trunk_0"]["kernel"]
    assert k.shape[0] == 3 and not np.allclose(k[0], k[1])
    assert model.count_params(p) == 3 * model.count_params(model.init_params(jax.random.key(0),
                                                                             CFG))


def test_narrow_interval_renderer():
    o, d, r, _, _ = _rays(32)
    near, far = jnp.full(32, 3.8), jnp.full(32, 4.2)
    out = jax.jit(model.render_rays_narrow, static_argnums=(7, 8))(
        _field(), o, d, r, near, far, None, CFG, 8)
    assert out["rgb"].shape == (32, 3)
    assert np.all((np.asarray(out["depth"]) >= 3.8 - 1e-5) & (np.asarray(out["depth"]) <= 4.2))


def test_narrow_coarse_to_fine_is_the_full_renderer_on_the_same_interval():
    # With the ray's own [near, far] and the config's sample counts, the narrow renderer's
    # two passes are exactly mip-NeRF's coarse and fine levels (independent path:
    # render_levels), and its resampled depths stay inside the interval.
    cfg = CFG
    assert not cfg.lindisp and cfg.num_levels == 2
    o, d, r, near, far = _rays(32)
    f = _field()
    full = model.render_rays(f, o, d, r, near, far, None, cfg)
    narrow = model.render_rays_narrow(f, o, d, r, near, far, None, cfg,
                                      cfg.num_samples_coarse, cfg.num_samples_fine)
    np.testing.assert_allclose(np.asarray(narrow["rgb"]), np.asarray(full["rgb"]), atol=1e-5)
    one = model.render_rays_narrow(f, o, d, r, near, far, None, cfg, cfg.num_samples_coarse)
    assert not np.allclose(np.asarray(one["rgb"]), np.asarray(full["rgb"]), atol=1e-4)


def test_loss_is_point_one_coarse_plus_fine():
    coarse = {"rgb": jnp.zeros((4, 3))}
    fine = {"rgb": jnp.full((4, 3), 0.5)}
    target = jnp.ones((4, 3))
    loss, mse = model.nerf_loss([coarse, fine], target, CFG)
    np.testing.assert_allclose(float(mse), 0.25)
    np.testing.assert_allclose(float(loss), 0.25 + 0.1 * 1.0)


def test_window_mass_against_numpy_overlaps():
    rng = np.random.default_rng(0)
    t = np.sort(rng.uniform(1.0, 9.0, (5, 9)), axis=-1)
    w = rng.uniform(0.0, 0.2, (5, 8))
    lo, hi = rng.uniform(1.0, 5.0, 5), rng.uniform(5.0, 9.0, 5)
    want = [sum(w[r, i] * max(0.0, min(t[r, i + 1], hi[r]) - max(t[r, i], lo[r]))
                / (t[r, i + 1] - t[r, i]) for i in range(8)) for r in range(5)]
    got = model.window_mass(jnp.asarray(t), jnp.asarray(w), jnp.asarray(lo), jnp.asarray(hi))
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5)


def test_depth_loss_counts_the_weight_outside_the_window_of_rays_with_depth():
    t = jnp.broadcast_to(jnp.linspace(0.0, 10.0, 11), (3, 11))
    w = jnp.zeros((3, 10)).at[:, 4].set(1.0)  # all weight in [4, 5]
    level = {"t_vals": t, "weights": w}
    # ray 0: window [3.6, 5.4] holds it all; ray 1: window [8, 12] none; ray 2: no depth
    depth = jnp.array([4.5, 10.0, 0.0])
    np.testing.assert_allclose(float(model.depth_loss([level], depth, 0.2)), 0.5, rtol=1e-6)
    np.testing.assert_allclose(float(model.depth_loss([level, level], depth[:1], 0.2)), 0.0,
                               atol=1e-7)
    assert float(model.depth_loss([level], jnp.zeros(3), 0.2)) == 0.0


def test_window_loss_of_an_empty_field_is_the_background_error_of_rays_with_depth():
    """With no density anywhere every window render is the background colour, so the loss
    is the colour MSE of the background against the targets, over the rays with a depth."""
    cfg = get_config("test", density_bias=-200.0, window_samples=8, window_fine=4)
    o, d, r, _, _ = _rays(8)
    bg = (0.2, 0.5, 0.9)
    field = _field(bg=bg)
    rng = np.random.default_rng(3)
    target = rng.uniform(0.0, 1.0, (8, 3)).astype(np.float32)
    depth = np.array([3.0, 4.0, 0.0, 5.0, 0.0, 3.5, 4.5, 2.5], np.float32)
    got = float(model.window_loss(field, o, d, r, jnp.asarray(target), jnp.asarray(depth),
                                  jax.random.key(0), cfg))
    has = depth > 0
    want = np.mean((np.asarray(bg, np.float32)[None] - target[has]) ** 2)
    np.testing.assert_allclose(got, want, rtol=1e-5)
    assert float(model.window_loss(field, o, d, r, jnp.asarray(target), jnp.zeros(8),
                                   jax.random.key(0), cfg)) == 0.0


@pytest.mark.parametrize("viewdirs", [False, True])
def test_flop_count_matches_xla_cost_analysis(viewdirs):
    # with view directions: the bottleneck and view_0 are one product (counted so), the
    # per-ray direction layer and the per-call kernel product are the few % left over
    cfg = get_config("test", use_viewdirs=viewdirs)
    params = model.init_params(jax.random.key(0), cfg)
    dx, dv = model.feature_dims(cfg)
    x, v = jnp.zeros((64, 8, dx)), jnp.zeros((64, dv))
    fn = jax.jit(lambda p, x, v: model.make_mlp(cfg).apply({"params": p}, x, v))
    cost = fn.lower(params, x, v).compile().cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    if not cost or "flops" not in cost:
        pytest.skip("backend reports no cost analysis")
    dots = model.mlp_flops_per_sample(cfg) * 64 * 8
    assert dots <= cost["flops"] <= 1.2 * dots  # + bias adds and relus


def test_config_overrides_and_errors():
    cfg = get_config("cpu-small", **parse_overrides(["n_clusters=3", "lindisp=true",
                                                     "near_far_percentiles=2,98"]))
    assert cfg.n_clusters == 3 and cfg.lindisp and cfg.near_far_percentiles == (2.0, 98.0)
    with pytest.raises(VrsError, match="unknown NeRF config"):
        get_config("huge")
    with pytest.raises(VrsError, match="unknown NeRF config field"):
        parse_overrides(["widht=3"])
    with pytest.raises(VrsError, match="bad value"):
        parse_overrides(["net_width=wide"])
    paper = get_config("paper")
    assert (paper.net_depth, paper.net_width, paper.skip_layer) == (8, 256, 4)
    assert (paper.num_samples_coarse, paper.num_samples_fine, paper.batch_size) == (128, 128,
                                                                                      1024)


def test_contracted_field_reads_far_points_inside_its_cube():
    """With contraction, the encoded positions of points from the inner ball to 1e4 ball
    radii stay inside the cube, the inner ball is unchanged, and footprints shrink with the
    contraction (hash-grid level weights rise towards the far field's coarser cells)."""
    import dataclasses

    cfg = dataclasses.replace(get_config("test"), contraction=True)
    r = model.inner_radius(cfg.norm_radius)
    x = jnp.asarray([[0.3, 0.0, 0.0], [r * 0.99, 0, 0], [r * 10, 0, 0], [0, 0, r * 1e4]],
                    jnp.float32)
    c, s = model.contract_gaussians(x, cfg.norm_radius)
    np.testing.assert_allclose(c[:2], x[:2], rtol=1e-6)
    assert float(jnp.max(jnp.abs(c))) <= cfg.norm_radius
    np.testing.assert_allclose(np.linalg.norm(c[2]), r * (2 - 0.1), rtol=1e-5)
    assert s[0] == 1.0 and 0 < s[3] < s[2] < 1.0
    o, d, rr, n, f = _rays()
    out = _render(_field(), o, d, rr, n, jnp.full_like(f, 1e3), jax.random.key(1), cfg, True)
    assert np.all(np.isfinite(np.asarray(out["rgb"]))) and np.all(np.isfinite(out["depth"]))


def test_contraction_spends_half_the_coarse_samples_inside_the_ball():
    import dataclasses

    cfg = dataclasses.replace(get_config("test"), contraction=True)
    field = _field(scale=0.5)
    o = jnp.zeros((4, 3), jnp.float32)
    d = jnp.asarray(np.tile([0.0, 0.0, 1.0], (4, 1)), jnp.float32)
    levels = model.render_levels(field, o, d, jnp.full(4, 1e-3), jnp.full(4, 0.1),
                                 jnp.full(4, 1e4), jax.random.key(0), cfg, False)
    t = np.asarray(levels[0]["t_vals"][0])
    pivot = model.inner_radius(cfg.norm_radius) / 0.5  # world units: ball radius / scale
    inside = np.mean(t < pivot)
    assert 0.4 <= inside <= 0.6 and t[-1] > 100 * pivot
