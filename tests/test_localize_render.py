"""localize.render: the patch renderer's strided sampling and the guided pass's selection,
against the full renderer on the tests' tiny map."""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np
import pytest

from vrs_jax import localize, maps
from vrs_jax.errors import VrsError
from vrs_jax.localize.render import (
    interpolation_matrix,
    rays_per_patch,
    render_at_pose,
    render_reference,
)


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
