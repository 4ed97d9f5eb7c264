"""localize.render: the patch renderer's strided sampling and the guided pass's selection,
against the full renderer on the tests' tiny map."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vrs_jax import localize, maps
from vrs_jax.errors import VrsError
from vrs_jax.features.rays import keypoint_depths, narrow_interval, patch_rays
from vrs_jax.localize.render import (
    interpolate_depth,
    interpolation_matrix,
    nerf_evals_per_ray,
    probe_surface,
    rays_per_patch,
    render_at_pose,
    render_reference,
)
from vrs_jax.nerf.model import render_rays_narrow, select_field


@pytest.fixture(scope="module")
def tiny(tiny_map):
    return maps.load_map(tiny_map)


@pytest.mark.parametrize("n,stride", [(8, 2), (5, 2), (3, 7), (4, 1)])
def test_interpolation_matrix_is_exact_on_linear_ramps(n, stride):
    W = interpolation_matrix(n, stride)
    assert W.shape == ((n - 1) * stride + 1, n)
    np.testing.assert_allclose(W.sum(1), 1.0, atol=1e-6)
    np.testing.assert_allclose(W[::stride], np.eye(n), atol=1e-6)  # kept samples unchanged
    ramp = 3.0 + 0.5 * np.arange(n)
    fine = 3.0 + 0.5 * np.arange((n - 1) * stride + 1) / stride
    np.testing.assert_allclose(W @ ramp, fine, atol=1e-5)


def test_strided_render_keeps_its_samples_and_approximates_the_rest(tiny):
    cfg1 = localize.get_config("test")
    cfg2 = dataclasses.replace(cfg1, render_stride=2)
    patches = tiny.config.features.patches
    full = np.asarray(render_reference(tiny, jnp.int32(0), patches, cfg1))
    half = np.asarray(render_reference(tiny, jnp.int32(0), patches, cfg2))
    mask = np.asarray(tiny.egm.kp_mask[0])
    full, half = full[mask], half[mask]
    np.testing.assert_allclose(half[:, ::2, ::2], full[:, ::2, ::2], atol=2e-4)
    mse = np.mean((half - full) ** 2)
    assert 10 * np.log10(1.0 / mse) > 25.0  # the interpolated samples are close
    assert rays_per_patch(tiny, cfg2) == ((patches.size - 1) // 2 + 1) ** 2
    bad = next(s for s in (3, 4, 5) if (patches.size - 1) % s)
    with pytest.raises(VrsError, match="render_stride"):
        render_reference(tiny, jnp.int32(0), patches, dataclasses.replace(cfg1, render_stride=bad))


def test_render_at_pose_renders_only_the_kept_keypoints(tiny):
    cfg = localize.get_config("test")
    patches = tiny.config.features.patches
    K, R, t = tiny.egm.K[1], tiny.egm.R[1], tiny.egm.t[1]
    g_all, kp_all, v_all = render_at_pose(tiny, jnp.int32(0), K, R, t, patches, cfg)
    rng = np.random.default_rng(0)
    keep = rng.random(tiny.egm.kp_mask.shape[1]) < 0.5
    g, kp, v = render_at_pose(tiny, jnp.int32(0), K, R, t, patches, cfg, jnp.asarray(keep))
    v, v_all = np.asarray(v), np.asarray(v_all)
    np.testing.assert_array_equal(v, v_all & keep)
    assert v.sum() > 0
    np.testing.assert_allclose(np.asarray(g)[v], np.asarray(g_all)[v], atol=2e-4)
    assert np.all(np.asarray(g)[~v] == 0)


@pytest.mark.parametrize("seed", range(5))
def test_interpolate_depth_is_exact_on_a_plane(seed):
    """Inverse-depth interpolation of a few probes recovers the depth of every sample of a
    patch grid on a plane (closed form: z = c / (n . K^-1 [u, v, 1]))."""
    rng = np.random.default_rng(seed)
    K = np.array([[rng.uniform(200, 500), 0, 160], [0, rng.uniform(200, 500), 120],
                  [0, 0, 1]])
    n = np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), 1.0])  # oblique plane
    c = rng.uniform(1.0, 5.0)
    P, step = 9, 4
    origin, a, b = rng.uniform(100, 200, 2), rng.normal(0, 3, 2), rng.normal(0, 3, 2)
    ij = np.stack(np.meshgrid(np.arange(P), np.arange(P), indexing="ij"), -1)
    uv = origin + ij[..., :1] * a + ij[..., 1:] * b  # an affine (rotated, scaled) grid
    rays = np.concatenate([uv, np.ones((P, P, 1))], -1) @ np.linalg.inv(K).T
    z = c / (rays @ n)
    assert np.all(z > 0)
    got = np.asarray(interpolate_depth(jnp.asarray(z[None, ::step, ::step], jnp.float32),
                                       step))[0]
    np.testing.assert_allclose(got, z, rtol=1e-5)


def test_probes_place_the_surface_samples(tiny):
    """probe_surface renders the probe rays of the full patch grid with the narrow search
    and returns their depth there; every rendered ray's interval is centred on it."""
    cfg = dataclasses.replace(localize.get_config("test"), probe_grid=3)
    patches = tiny.config.features.patches
    i = int(np.argmax(np.asarray(tiny.egm.kp_mask).sum(1)))
    egm, ilm = tiny.egm, tiny.ilm
    field = select_field(ilm.fields, ilm.image_cluster[i])
    pr = patch_rays(egm.keypoints[i], egm.K[i], egm.R[i], egm.t[i], patches, egm.dist[i])
    z = keypoint_depths(egm.points3d, egm.point_idx[i], egm.R[i], egm.t[i])
    n_kp = jnp.sum(egm.kp_mask[i])
    surf = np.asarray(probe_surface(field, pr, z, n_kp, 3, ilm.config, cfg))
    step = (patches.size - 1) // 2
    probe = jax.tree.map(lambda x: x[:, ::step, ::step].reshape((-1,) + x.shape[3:]), pr)
    near, far = narrow_interval(z, cfg.depth_margin, (z.shape[0], 3, 3))
    ref = render_rays_narrow(field, probe.origins, probe.directions, probe.radii,
                             near.reshape(-1), far.reshape(-1), None, ilm.config,
                             cfg.narrow_samples, cfg.narrow_fine)
    mask = np.asarray(egm.kp_mask[i])
    hit = np.asarray(ref["acc"]).reshape(-1, 3, 3) > 0.5
    want = np.where(hit, np.asarray(ref["depth"]).reshape(-1, 3, 3),
                    np.asarray(z)[:, None, None])
    np.testing.assert_allclose(surf[:, ::step, ::step][mask], want[mask], rtol=1e-4)
    assert hit[mask].mean() > 0.5  # the tiny field does have surfaces there
    gray = np.asarray(render_reference(tiny, jnp.int32(i), patches, cfg))[mask]
    assert np.all(np.isfinite(gray)) and gray.std() > 0.01


def test_probe_evaluations_and_grids_are_checked(tiny):
    cfg = localize.get_config("test")
    patches = tiny.config.features.patches  # P = 9
    c = dataclasses.replace(cfg, probe_grid=3, surface_samples=6)
    per_patch = 9 * (cfg.narrow_samples + cfg.narrow_fine) + patches.size ** 2 * 6
    assert nerf_evals_per_ray(tiny, c) * rays_per_patch(tiny, c) == pytest.approx(per_patch)
    with pytest.raises(VrsError, match="probe_grid"):
        render_reference(tiny, jnp.int32(0), patches, dataclasses.replace(cfg, probe_grid=4))
    with pytest.raises(VrsError, match="probe_grid"):
        render_reference(tiny, jnp.int32(0), patches,
                         dataclasses.replace(cfg, probe_grid=3, depth_guided=False))
    for bad in ({"probe_grid": 1}, {"surface_samples": 0}, {"surface_margin": 0.0}):
        with pytest.raises(VrsError):
            localize.get_config("test", **bad)
