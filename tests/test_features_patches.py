"""Canonical patches: grid geometry and similarity equivariance, bilinear sampling against
cv2.remap and a numpy reference, literal mode, blur levels against cv2.GaussianBlur and
against aliasing, jit/vmap."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vrs_jax.errors import VrsError
from vrs_jax.features.patches import (
    PATCH_SIZES,
    PatchConfig,
    blur_stack,
    extract_patches,
    fft_size,
    gaussian_blur_stack,
    grid_inside,
    level_of,
    patch_grid,
    sample_patches,
)


def _random_kp(rng, n, lo=20.0, hi=60.0):
    return np.stack([rng.uniform(lo, hi, n), rng.uniform(lo, hi, n), rng.uniform(0.3, 4.0, n),
                     rng.uniform(-np.pi, np.pi, n)], 1).astype(np.float32)


def _image(h=64, w=80, seed=0):
    rng = np.random.default_rng(seed)
    return rng.uniform(0, 1, (h, w)).astype(np.float32)


def _bilinear_ref(img, x, y):
    """Plain numpy bilinear read, element [i, j] at (j + 0.5, i + 0.5), clamped borders."""
    h, w = img.shape
    u, v = np.asarray(x, np.float64) - 0.5, np.asarray(y, np.float64) - 0.5
    j0, i0 = np.floor(u).astype(int), np.floor(v).astype(int)
    fu, fv = u - j0, v - i0
    out = 0.0
    for di, wi in ((0, 1 - fv), (1, fv)):
        for dj, wj in ((0, 1 - fu), (1, fu)):
            out = out + wi * wj * img[np.clip(i0 + di, 0, h - 1), np.clip(j0 + dj, 0, w - 1)]
    return out


# ----------------------------------------------------------------------------- grid


@pytest.mark.parametrize("P", PATCH_SIZES)
def test_grid_geometry(P):
    cfg = PatchConfig(size=P)
    kp = np.array([[30.3, 17.9, 2.5, 0.7]], np.float32)
    pos, foot = patch_grid(kp, cfg)
    pos, foot = np.asarray(pos[0]), float(foot[0])
    assert pos.shape == (P, P, 2)
    c = (P - 1) // 2
    np.testing.assert_allclose(pos[c, c], kp[0, :2], atol=1e-5)  # centre on the keypoint
    np.testing.assert_allclose(foot, 12.0 * 2.5 / P, rtol=1e-6)  # 12 * scale support
    a = 0.7
    # columns step along the keypoint direction, rows along it turned +90 deg (pixel axes)
    np.testing.assert_allclose(pos[c, c + 1] - pos[c, c], foot * np.array([np.cos(a), np.sin(a)]),
                               atol=1e-5)
    np.testing.assert_allclose(pos[c + 1, c] - pos[c, c], foot * np.array([-np.sin(a), np.cos(a)]),
                               atol=1e-5)
    # the patch covers a square of side window = P * spacing = 12 * scale
    np.testing.assert_allclose(np.linalg.norm(pos[c, -1] - pos[c, 0]) + foot, 30.0, rtol=1e-5)


def test_grid_equivariant_under_similarity():
    """grid(T kp) == T grid(kp) for p' = s R(phi) p + t, kp' = (p', s * scale, angle + phi)."""
    rng = np.random.default_rng(1)
    cfg = PatchConfig(size=15)
    for _ in range(5):
        kp = _random_kp(rng, 7)
        s, phi, t = rng.uniform(0.5, 2.0), rng.uniform(-np.pi, np.pi), rng.uniform(-30, 30, 2)
        A = s * np.array([[np.cos(phi), -np.sin(phi)], [np.sin(phi), np.cos(phi)]])
        kp2 = np.concatenate([kp[:, :2] @ A.T + t, kp[:, 2:3] * s, kp[:, 3:4] + phi], 1)
        pos, foot = patch_grid(kp, cfg)
        pos2, foot2 = patch_grid(kp2.astype(np.float32), cfg)
        np.testing.assert_allclose(np.asarray(pos2), np.asarray(pos) @ A.T + t, atol=2e-4)
        np.testing.assert_allclose(np.asarray(foot2), s * np.asarray(foot), rtol=1e-5)


def test_grid_of_cv2_rotation_matrix():
    """The same with OpenCV's own matrix (getRotationMatrix2D, OpenCV pixel convention):
    its rotation by +deg on screen is phi = -radians(deg) in pixel axes."""
    deg, s = 37.0, 1.3
    M = cv2.getRotationMatrix2D((40.0, 30.0), deg, s)
    kp = np.array([[25.2, 33.7, 2.0, 0.4]], np.float32)
    cfg = PatchConfig(size=11)
    A, t = M[:, :2], M[:, 2]
    xy = (kp[:, :2] - 0.5) @ A.T + t + 0.5
    kp2 = np.array([[xy[0, 0], xy[0, 1], 2.0 * s, 0.4 - np.deg2rad(deg)]], np.float32)
    pos = np.asarray(patch_grid(kp, cfg)[0]).reshape(-1, 2)
    want = (pos - 0.5) @ A.T + t + 0.5
    np.testing.assert_allclose(np.asarray(patch_grid(kp2, cfg)[0]).reshape(-1, 2), want,
                               atol=2e-4)


def test_literal_grid_and_batch_shapes():
    cfg = PatchConfig(size=9, mode="literal")
    kp = np.array([[[10.2, 20.9, 5.0, 1.0], [3.5, 4.0, 0.1, -2.0]]], np.float32)  # [1, 2, 4]
    pos, foot = patch_grid(kp, cfg)
    assert pos.shape == (1, 2, 9, 9, 2) and foot.shape == (1, 2)
    np.testing.assert_array_equal(np.asarray(foot), 1.0)
    np.testing.assert_array_equal(np.asarray(pos[0, 0, 4, 4]), [10.5, 20.5])
    np.testing.assert_array_equal(np.asarray(pos[0, 0, 0, 0]), [6.5, 16.5])
    np.testing.assert_array_equal(np.asarray(pos[0, 1, 4, 4]), [3.5, 4.5])


def test_grid_inside():
    cfg = PatchConfig(size=15)
    kp = np.array([[40, 30, 1.0, 0.0], [40, 30, 1.0, 0.785], [3, 30, 1.0, 0.0]], np.float32)
    # outer samples 7 * 0.8 = 5.6 px from the centre; rotated 45 deg, the corner is 7.9 px away
    np.testing.assert_array_equal(np.asarray(grid_inside(patch_grid(kp, cfg)[0], 80, 37)),
                                  [True, False, False])


# ----------------------------------------------------------------------------- sampling


def test_level0_sampling_matches_numpy_and_cv2_remap():
    img = cv2.GaussianBlur(_image(), (0, 0), 1.0)  # smooth: remap's 1/32 px weights suffice
    rng = np.random.default_rng(2)
    kp = _random_kp(rng, 12, 5.0, 60.0)
    kp[:, 2] = rng.uniform(0.2, 1.2, 12)  # spacing 0.16 .. 0.96 px < 1: level 0
    cfg = PatchConfig(size=15)
    assert float(jnp.max(level_of(cfg.spacing * kp[:, 2], cfg))) == 0.0
    got = np.asarray(extract_patches(img, kp, cfg))
    pos = np.asarray(patch_grid(kp, cfg)[0])
    np.testing.assert_allclose(got, _bilinear_ref(img, pos[..., 0], pos[..., 1]), atol=1e-5)
    mx = (pos[..., 0] - 0.5).reshape(-1, 1).astype(np.float32)  # COLMAP -> OpenCV pixels
    my = (pos[..., 1] - 0.5).reshape(-1, 1).astype(np.float32)
    ref = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    np.testing.assert_allclose(got.reshape(-1), ref.reshape(-1), atol=3e-3)


def test_unblurred_stack_reads_raw_image_at_any_spacing():
    img = _image()
    cfg = PatchConfig(size=13, n_levels=1)  # one level: no anti-aliasing
    kp = _random_kp(np.random.default_rng(3), 9)
    got = np.asarray(extract_patches(img, kp, cfg))
    pos = np.asarray(patch_grid(kp, cfg)[0])
    np.testing.assert_allclose(got, _bilinear_ref(img, pos[..., 0], pos[..., 1]), atol=1e-5)


def test_literal_mode_reads_exact_pixels():
    img = _image()
    cfg = PatchConfig(size=11, mode="literal")
    kp = np.array([[20.0, 30.0, 9.0, 1.0], [20.99, 30.01, 0.5, -1.0], [40.5, 12.7, 3.0, 2.0]],
                  np.float32)
    got = np.asarray(extract_patches(img, kp, cfg))
    for k, (x, y, _, _) in enumerate(kp):
        i, j = int(np.floor(y)), int(np.floor(x))
        np.testing.assert_array_equal(got[k], img[i - 5:i + 6, j - 5:j + 6])


@pytest.mark.parametrize("hw", [(48, 56), (47, 61)])  # padded FFT sizes filled: one axis, both
def test_blur_stack_matches_cv2_gaussian_blur(hw):
    img = _image(*hw, seed=4)
    sigmas = (0.0, 0.5, 1.3, 3.0, 6.0)
    got = np.asarray(gaussian_blur_stack(img, sigmas))
    np.testing.assert_array_equal(got[0], img)
    for s, g in zip(sigmas[1:], got[1:], strict=True):
        k = 2 * int(np.ceil(4 * s)) + 1
        ref = cv2.GaussianBlur(img, (k, k), s, borderType=cv2.BORDER_REFLECT_101)
        np.testing.assert_allclose(g, ref, atol=2e-5)


def test_fft_size_is_the_smallest_5_smooth_size_at_least_n():
    def smooth(m):
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        return m == 1

    for n in range(1, 700):
        got = fft_size(n)
        assert got >= n and smooth(got) and not any(smooth(m) for m in range(n, got))
    assert fft_size(398) == 400 and fft_size(608) == 625


def test_level_sigmas_and_levels():
    cfg = PatchConfig()
    sig = cfg.level_sigmas()
    assert len(sig) == cfg.n_levels and sig[0] == 0.0
    # level l serves spacing 2^(l/2): total blur 0.5 * spacing, given 0.5 px already there
    np.testing.assert_allclose(sig[2], np.sqrt(1.0 ** 2 - 0.25), rtol=1e-9)  # spacing 2
    np.testing.assert_allclose(sig[6], np.sqrt(4.0 ** 2 - 0.25), rtol=1e-9)  # spacing 8
    np.testing.assert_allclose(np.asarray(level_of(jnp.array([0.3, 1.0, 2.0, 8.0, 1e4]), cfg)),
                               [0, 0, 2, 6, cfg.n_levels - 1], atol=1e-6)
    assert PatchConfig(mode="literal").level_sigmas() == (0.0,)


def test_large_keypoints_read_a_blurred_level():
    """A 1-pixel checkerboard is pure high frequency: a keypoint whose samples are 8 px apart
    must see it blurred to its mean (low variance), not aliased; a small keypoint resolves it."""
    n = 96
    board = ((np.arange(n)[:, None] + np.arange(n)[None, :]) % 2).astype(np.float32)
    big = np.array([[48.0, 48.0, 10.0, 0.3]], np.float32)  # spacing 8 px, grid rotated
    small = np.array([[48.0, 48.0, 0.5, 0.0]], np.float32)  # spacing 0.4 px: level 0
    cfg, raw = PatchConfig(size=15), PatchConfig(size=15, n_levels=1)
    assert float(level_of(cfg.spacing * big[:, 2], cfg)[0]) == pytest.approx(6.0)
    v_big = float(np.var(extract_patches(board, big, cfg)))
    v_alias = float(np.var(extract_patches(board, big, raw)))
    v_small = float(np.var(extract_patches(board, small, cfg)))
    assert v_big < 1e-3 and v_alias > 0.02 and v_small > 0.02
    np.testing.assert_allclose(np.mean(extract_patches(board, big, cfg)), 0.5, atol=0.01)


def test_jit_and_vmap():
    img = _image()
    kp = _random_kp(np.random.default_rng(5), 6)
    cfg = PatchConfig(size=9)
    eager = np.asarray(extract_patches(img, kp, cfg))
    jitted = jax.jit(extract_patches, static_argnames="cfg")(img, kp, cfg)
    np.testing.assert_allclose(np.asarray(jitted), eager, atol=1e-5)
    imgs = np.stack([img, img[::-1].copy()])
    kps = np.stack([kp, kp[::-1]])
    batched = jax.jit(jax.vmap(lambda i, k: extract_patches(i, k, cfg)))(imgs, kps)
    np.testing.assert_allclose(np.asarray(batched[0]), eager, atol=1e-5)
    np.testing.assert_allclose(np.asarray(batched[1]),
                               np.asarray(extract_patches(imgs[1], kps[1], cfg)), atol=1e-5)
    stack = blur_stack(img, cfg)
    vm = jax.vmap(lambda k: sample_patches(stack, k, cfg))(kp[:, None])  # [6, 1, P, P]
    np.testing.assert_allclose(np.asarray(vm[:, 0]), eager, atol=1e-5)
    pos, foot = jax.jit(patch_grid, static_argnames="cfg")(kp, cfg)
    assert pos.shape == (6, 9, 9, 2) and foot.shape == (6,)


@pytest.mark.parametrize("kw", [dict(size=12), dict(mode="affine"), dict(n_levels=0),
                                dict(spacing_per_scale=0.0)])
def test_bad_config_raises(kw):
    with pytest.raises(VrsError):
        PatchConfig(**kw)


def test_colour_image_raises():
    with pytest.raises(VrsError):
        extract_patches(np.zeros((8, 8, 3), np.float32), np.zeros((1, 4), np.float32))


def test_explicit_spacing_per_scale():
    cfg = PatchConfig(size=31, spacing_per_scale=0.8)
    _, foot = patch_grid(np.array([[0, 0, 2.0, 0]], np.float32), cfg)
    assert float(foot[0]) == pytest.approx(1.6) and cfg.spacing == 0.8
