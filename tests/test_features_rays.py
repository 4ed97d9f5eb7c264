"""Patch rays against independent references: projection, numpy unique, radii."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax import geometry as g
from vrs_jax.features import rays
from vrs_jax.features.patches import PatchConfig, patch_grid

rng = np.random.default_rng(3)


def _camera():
    K = g.intrinsics_matrix(300.0, 310.0, 160.0, 120.0)
    R = g.axis_angle_to_rot(np.array([0.1, -0.2, 0.05]))
    t = np.array([0.2, -0.1, 1.5])
    return K, R, t


def test_patch_rays_project_back_onto_their_samples():
    K, R, t = _camera()
    kp = np.stack([rng.uniform(20, 300, 6), rng.uniform(20, 220, 6), rng.uniform(1, 6, 6),
                   rng.uniform(-np.pi, np.pi, 6)], -1).astype(np.float32)
    cfg = PatchConfig(size=9)
    pr = rays.patch_rays(jnp.asarray(kp), *(jnp.asarray(a, jnp.float32) for a in (K, R, t)), cfg)
    depth = rng.uniform(1, 4, size=pr.radii.shape)
    X = np.asarray(pr.origins) + depth[..., None] * np.asarray(pr.directions)
    uv, z = g.project(K, R, t, X.reshape(-1, 3).astype(np.float64))
    pos, _ = patch_grid(kp, cfg)
    np.testing.assert_allclose(uv.reshape(pos.shape), pos, atol=2e-3)
    np.testing.assert_allclose(z.reshape(depth.shape), depth, rtol=1e-4)


def test_radii_match_sample_spacing():
    K, R, t = _camera()
    kp = jnp.asarray([[100.0, 80.0, 4.0, 0.3]])
    cfg = PatchConfig(size=15)
    pr = rays.patch_rays(kp, *(jnp.asarray(a, jnp.float32) for a in (K, R, t)), cfg)
    # neighbouring directions (unit camera depth) are spacing / f apart; mip-NeRF's radius is
    # that width times 2 / sqrt(12)
    d = np.asarray(pr.directions)[0]
    step = np.linalg.norm(d[7, 8] - d[7, 7])
    np.testing.assert_allclose(float(pr.radii[0, 0, 0]), step * 2 / np.sqrt(12), rtol=2e-2)


def test_keypoint_depths_and_narrow_interval():
    K, R, t = _camera()
    X = rng.uniform(-1, 1, size=(5, 3))
    z = rays.keypoint_depths(jnp.asarray(X), jnp.asarray([4, 0, 2]), jnp.asarray(R),
                             jnp.asarray(t))
    np.testing.assert_allclose(z, (X[[4, 0, 2]] @ R.T + t)[:, 2], rtol=1e-5)
    near, far = rays.narrow_interval(z, 0.2, (3, 5, 5))
    assert near.shape == (3, 5, 5)
    np.testing.assert_allclose(far[:, 0, 0] / near[:, 0, 0], 1.2 / 0.8, rtol=1e-5)


def test_unique_literal_pixels_against_numpy():
    cfg = PatchConfig(size=9, mode="literal")
    kp = np.stack([rng.uniform(-3, 40, 12), rng.uniform(0, 30, 12), np.ones(12),
                   np.zeros(12)], -1).astype(np.float32)
    mask = np.ones(12, bool)
    mask[[3, 7]] = False
    pos, _ = patch_grid(kp, cfg)
    pixels, inverse, count = jax.jit(rays.unique_literal_pixels)(jnp.asarray(pos),
                                                                 jnp.asarray(mask))
    valid_pos = np.asarray(pos)[mask].reshape(-1, 2)
    ref = np.unique(np.floor(valid_pos).astype(int), axis=0)
    assert int(count) == len(ref) < mask.sum() * 81  # overlapping patches share pixels
    got = np.asarray(pixels)[: int(count)]
    np.testing.assert_array_equal(np.sort(np.floor(got).astype(int), axis=0),
                                  np.sort(ref, axis=0))
    # every sample of a valid keypoint reads back its own pixel
    back = np.asarray(pixels)[np.asarray(inverse)]
    np.testing.assert_allclose(back[mask], np.asarray(pos)[mask], atol=1e-6)
