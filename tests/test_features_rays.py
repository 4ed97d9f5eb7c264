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


def _look(yaw, t):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]], np.float64), np.asarray(t, np.float64)


def test_transfer_keypoints_into_the_same_camera_is_the_identity():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    R, t = _look(0.2, [0.1, -0.2, 0.3])
    rng = np.random.default_rng(0)
    uv = rng.uniform([50, 50], [590, 430], (20, 2))
    z = rng.uniform(2, 6, 20)
    Xc = np.concatenate([(uv - K[:2, 2]) / 500.0, np.ones((20, 1))], 1) * z[:, None]
    X = (Xc - t) @ R
    kp = np.concatenate([uv, rng.uniform(1, 5, (20, 1)), rng.uniform(-3, 3, (20, 1))], 1)
    out, zz = rays.transfer_keypoints(jnp.asarray(kp, jnp.float32), jnp.asarray(X, jnp.float32),
                                      K, R, t, None, K, R, t)
    np.testing.assert_allclose(np.asarray(zz), z, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(out[:, :3]), kp[:, :3], rtol=1e-4, atol=1e-3)
    d = np.angle(np.exp(1j * (np.asarray(out[:, 3]) - kp[:, 3])))
    np.testing.assert_allclose(d, 0.0, atol=1e-3)


def test_transfer_keypoints_follows_depth_and_roll():
    # independent reference: a camera moved back along its axis by the point's depth sees
    # the keypoint at half the scale; a camera rolled by r about its axis sees the
    # orientation turned by -r (cv2.projectPoints of the keypoint's tip for the angle)
    import cv2

    K = np.array([[400.0, 0, 200], [0, 400, 150], [0, 0, 1]])
    X = np.array([[0.3, -0.2, 4.0]])
    uv = (X[:, :2] / X[:, 2:] * 400 + K[:2, 2])
    kp = np.array([[uv[0, 0], uv[0, 1], 3.0, 0.7]])
    I, z0 = np.eye(3), np.zeros(3)
    out, z = rays.transfer_keypoints(kp, X, K, I, z0, None, K, I, np.array([-0.3, 0.2, 4.0]))
    np.testing.assert_allclose(float(z[0]), 8.0, rtol=1e-5)
    np.testing.assert_allclose(float(out[0, 2]), 1.5, rtol=1e-4)
    np.testing.assert_allclose(np.asarray(out[0, :2]), K[:2, 2], atol=1e-3)
    roll = 0.4
    Rr = cv2.Rodrigues(np.array([0.0, 0.0, roll]))[0]
    out, _ = rays.transfer_keypoints(kp, X, K, I, z0, None, K, Rr, z0)
    tip = np.array([[kp[0, 0] + 3 * np.cos(0.7), kp[0, 1] + 3 * np.sin(0.7)]])
    tip3 = np.concatenate([(tip - K[:2, 2]) / 400.0, [[1.0]]], 1) * 4.0
    pts, _ = cv2.projectPoints(np.concatenate([X, tip3]), cv2.Rodrigues(Rr)[0], z0, K, None)
    pts = pts[:, 0]
    want = np.arctan2(pts[1, 1] - pts[0, 1], pts[1, 0] - pts[0, 0])
    np.testing.assert_allclose(np.asarray(out[0, :2]), pts[0], atol=1e-3)
    np.testing.assert_allclose(float(out[0, 3]), want, atol=1e-4)
    np.testing.assert_allclose(float(np.angle(np.exp(1j * (out[0, 3] - 0.7)))), roll, atol=1e-4)
