"""The JAX descriptor: numpy loop reference, exact symmetries, normalisation, jit/vmap, and the
acceptance test: descriptors of keypoints of an image warped by known similarities find their
originals as nearest neighbours (and unrelated keypoints do not)."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import shared_path

from vrs_jax.errors import VrsError
from vrs_jax.features.descriptor import DescriptorConfig, describe, rgb_to_gray
from vrs_jax.features.extract import (
    FeatureConfig,
    describe_keypoints_jit,
    extract_features,
    get_config,
)
from vrs_jax.features.keypoints import KeypointConfig, detect
from vrs_jax.features.matching import match_jit
from vrs_jax.features.patches import PATCH_SIZES, PatchConfig, grid_inside, patch_grid


def _texture(n: int = 160, seed: int = 0) -> np.ndarray:
    """Multi-scale blurred noise in [0, 1], weighted towards coarse blobs (larger keypoints)."""
    rng = np.random.default_rng(seed)
    img = np.zeros((n, n), np.float32)
    for s in (1, 2, 4, 8):
        img += cv2.GaussianBlur(rng.standard_normal((n, n)).astype(np.float32), (0, 0),
                                s) * s ** 1.5
    return (img - img.min()) / (img.max() - img.min())


def _describe_ref(patch: np.ndarray, cfg: DescriptorConfig) -> np.ndarray:
    """Loop-by-loop numpy reference of the histogram (explicit trilinear voting)."""
    P = patch.shape[0]
    n, nb = cfg.n_cells, cfg.n_bins
    gy, gx = np.gradient(patch.astype(np.float64))
    hist = np.zeros((n, n, nb))
    for i in range(P):
        for j in range(P):
            m = np.hypot(gx[i, j], gy[i, j])
            u, v = (j - (P - 1) / 2) / P, (i - (P - 1) / 2) / P
            m *= np.exp(-(u * u + v * v) / (2 * cfg.gauss_sigma ** 2))
            cy, cx = (i + 0.5) * n / P - 0.5, (j + 0.5) * n / P - 0.5
            o = np.arctan2(gy[i, j], gx[i, j]) / (2 * np.pi) * nb
            o0 = int(np.floor(o))
            for dy in (0, 1):
                for dx in (0, 1):
                    for do in (0, 1):
                        by, bx = int(np.floor(cy)) + dy, int(np.floor(cx)) + dx
                        if not (0 <= by < n and 0 <= bx < n):
                            continue
                        w = ((1 - abs(cy - by)) * (1 - abs(cx - bx))
                             * (1 - abs(o - (o0 + do))))
                        hist[by, bx, (o0 + do) % nb] += m * w
    h = hist.reshape(-1) + cfg.eps
    h = np.minimum(h / np.linalg.norm(h), cfg.clip)
    h = np.sqrt(h / h.sum())
    return h / np.linalg.norm(h)


@pytest.mark.parametrize("P, cfg", [(9, DescriptorConfig()), (15, DescriptorConfig()),
                                    (11, DescriptorConfig(n_cells=3, n_bins=6))])
def test_matches_numpy_loop_reference(P, cfg):
    """Every patch of a batch with two leading axes (the cell products run over all patches
    at once) against the loop reference."""
    rng = np.random.default_rng(P)
    patches = cv2.GaussianBlur(rng.uniform(0, 1, (6 * P, P)).astype(np.float32), (0, 0), 1.0)
    patches = patches.reshape(2, 3, P, P)
    got = np.asarray(describe(patches, cfg))
    assert got.shape == (2, 3, cfg.dim)
    for a in range(2):
        for k in range(3):
            np.testing.assert_allclose(got[a, k], _describe_ref(patches[a, k], cfg), atol=2e-5)


@pytest.mark.parametrize("P", PATCH_SIZES)
def test_shape_norm_and_determinism(P):
    p = np.random.default_rng(0).uniform(0, 1, (2, 3, P, P)).astype(np.float32)
    d = np.asarray(describe(p))
    assert d.shape == (2, 3, 128) and d.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-5)
    assert np.all(d >= 0)
    np.testing.assert_array_equal(d, np.asarray(describe(p)))


def test_rot90_permutes_cells_and_shifts_bins_exactly():
    """np.rot90 turns the patch by 90 deg: q(u, v) = p(-v, u), so gradients turn by -90 deg
    (2 of 8 bins) and cell (cy, cx) of q is cell (cx, n-1-cy) of p."""
    P = 15
    p = cv2.GaussianBlur(np.random.default_rng(1).uniform(0, 1, (P, P)).astype(np.float32),
                         (0, 0), 1.0)
    dp = np.asarray(describe(p)).reshape(4, 4, 8)
    dq = np.asarray(describe(np.ascontiguousarray(np.rot90(p)))).reshape(4, 4, 8)
    want = np.empty_like(dp)
    for cy in range(4):
        for cx in range(4):
            want[cy, cx] = np.roll(dp[cx, 3 - cy], -2)  # want[b] = dp[b + 2]
    np.testing.assert_allclose(dq, want, atol=1e-5)


def test_invariant_to_affine_intensity():
    p = np.random.default_rng(2).uniform(0, 1, (4, 13, 13)).astype(np.float32)
    np.testing.assert_allclose(np.asarray(describe(0.3 * p + 0.2)), np.asarray(describe(p)),
                               atol=1e-5)


def test_flat_patch_gives_uniform_unit_vector():
    d = np.asarray(describe(np.full((2, 11, 11), 0.7, np.float32)))
    np.testing.assert_allclose(d, 1 / np.sqrt(128), atol=1e-6)


def test_jit_vmap_and_config_variants():
    p = np.random.default_rng(3).uniform(0, 1, (5, 15, 15)).astype(np.float32)
    eager = np.asarray(describe(p))
    np.testing.assert_allclose(np.asarray(jax.vmap(describe)(p)), eager, atol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.jit(jax.vmap(describe))(jnp.asarray(p))), eager,
                               atol=1e-6)
    plain = np.asarray(describe(p, DescriptorConfig(root=False, clip=None)))
    np.testing.assert_allclose(np.linalg.norm(plain, axis=-1), 1.0, atol=1e-5)
    small = DescriptorConfig(n_cells=2, n_bins=6)
    assert describe(p, small).shape == (5, small.dim) == (5, 24)


def test_rgb_to_gray_matches_opencv():
    rgb = np.random.default_rng(4).uniform(0, 1, (3, 7, 7, 3)).astype(np.float32)
    ref = np.stack([cv2.cvtColor(x, cv2.COLOR_RGB2GRAY) for x in rgb])
    np.testing.assert_allclose(np.asarray(rgb_to_gray(rgb)), ref, atol=1e-5)


def test_bad_patches_raise():
    with pytest.raises(VrsError):
        describe(np.zeros((3, 15, 13), np.float32))
    with pytest.raises(VrsError):
        DescriptorConfig(n_bins=1)


# ----------------------------------------------------------------------------- acceptance

# (rotation on screen in degrees, scale) as cv2.getRotationMatrix2D takes them
WARPS = [(0, 1.0), (30, 1.0), (90, 1.0), (180, 1.0), (-135, 0.7), (45, 0.5), (120, 0.5),
         (0, 2.0), (60, 2.0), (180, 2.0), (15, 1.4)]


def _warp(img, deg, s, canvas):
    """Similarity about the image centre into a fixed canvas. Shrinking is pre-filtered
    (a camera at lower resolution integrates; warpAffine alone would alias)."""
    h, w = img.shape
    M = cv2.getRotationMatrix2D((w / 2 - 0.5, h / 2 - 0.5), deg, s)
    M[:, 2] += np.array([canvas[0] - w, canvas[1] - h]) / 2
    src = cv2.GaussianBlur(img, (0, 0), 0.5 * np.sqrt(1 / s ** 2 - 1)) if s < 1 else img
    out = cv2.warpAffine(src, M, canvas, flags=cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REFLECT_101)
    return out, M


def _map_kp(kp, M):
    """Keypoints through an OpenCV 2x3 similarity (OpenCV pixels: shift by 0.5 around it)."""
    A, t = M[:, :2], M[:, 2]
    xy = (kp[:, :2] - 0.5) @ A.T + t + 0.5
    s = np.sqrt(abs(np.linalg.det(A)))
    phi = np.arctan2(A[1, 0], A[0, 0])  # rotation in pixel axes (= -deg)
    return np.concatenate([xy, kp[:, 2:3] * s, kp[:, 3:4] + phi], 1).astype(np.float32)


def _measure(img, other, warps, canvas, noise=0.0, kmax=256, seed=0):
    """Per warp: (nearest-neighbour fraction, count, fraction whose true partner is closer
    than every keypoint of an unrelated image, fraction matched (mutual + ratio) to the
    unrelated image). Keypoints whose patch leaves either image, or whose warped scale is
    under 1 px, are skipped. noise perturbs the mapped keypoints (position by noise * scale,
    log-scale and angle by noise) to mimic detector error."""
    pcfg, dcfg = PatchConfig(), DescriptorConfig()
    kp = detect(img, KeypointConfig(max_keypoints=kmax))
    pad = np.zeros((kmax, 4), np.float32)
    pad[:, 2] = 1.0

    def desc(im, k):
        p = pad.copy()
        p[:len(k)] = k
        out = describe_keypoints_jit(jnp.asarray(im), jnp.asarray(p), pcfg, dcfg)
        return np.asarray(out)[:len(k)]

    d0, k_other = desc(img, kp), detect(other, KeypointConfig(max_keypoints=kmax))
    d_other = desc(other, k_other)
    rng = np.random.default_rng(seed)
    res = {}
    for deg, s in warps:
        wimg, M = _warp(img, deg, s, canvas)
        kw = _map_kp(kp, M)
        ok = (np.asarray(grid_inside(patch_grid(kp, pcfg)[0], img.shape[1], img.shape[0]))
              & np.asarray(grid_inside(patch_grid(kw, pcfg)[0], *canvas)) & (kw[:, 2] >= 1.0))
        if noise:
            kw[:, :2] += rng.normal(0, noise, (len(kw), 2)) * kw[:, 2:3]
            kw[:, 2] *= np.exp(rng.normal(0, noise, len(kw)))
            kw[:, 3] += rng.normal(0, noise, len(kw))
        dw = desc(wimg, kw)
        D = _dist(dw[ok], d0[ok])
        nn = float(np.mean(D.argmin(1) == np.arange(len(D))))
        closer = float(np.mean(np.diag(D) < _dist(dw[ok], d_other).min(1)))
        # fixed shapes with a mask: one compiled program for every warp
        _, v, _ = match_jit(dw, ok, d_other, np.ones(len(d_other), bool))
        res[(deg, s)] = (nn, int(ok.sum()), closer, float(np.sum(np.asarray(v)) / ok.sum()))
    return res


def _dist(a, b):
    """Euclidean distances [Na, Nb] in float64 numpy (independent of matching.py)."""
    a, b = a.astype(np.float64), b.astype(np.float64)
    return np.sqrt(np.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None] - 2 * a @ b.T, 0))


def _report(name, res):
    print(f"\n{name}: warp (deg, scale): NN fraction [n], true closer than unrelated, "
          "matched to unrelated")
    for k, (nn, n, closer, unrel) in res.items():
        print(f"  {k}: {nn:.3f} [{n}]  {closer:.3f}  {unrel:.3f}")


@pytest.fixture(scope="module")
def procedural_results():
    img, other = _texture(160, 0), _texture(160, 1)
    exact = _measure(img, other, WARPS, (288, 288))
    noisy = _measure(img, other, WARPS, (288, 288), noise=0.1)
    _report("procedural, exact keypoint mapping", exact)
    _report("procedural, keypoints perturbed (0.1 scale px, 10% scale, 0.1 rad)", noisy)
    return exact, noisy


def test_warped_keypoints_find_their_originals_procedural(procedural_results):
    exact, noisy = procedural_results
    for (nn, n, closer, _), (nn2, _, closer2, _) in zip(exact.values(), noisy.values(),
                                                            strict=True):
        assert n >= 20  # enough keypoints that a fraction means something
        assert nn >= 0.9 and closer >= 0.9  # measured 1.00 for every warp
        assert nn2 >= 0.8 and closer2 >= 0.8  # measured >= 0.95 with perturbed keypoints


def test_unrelated_keypoints_do_not_match_procedural(procedural_results):
    exact, _ = procedural_results
    for _, _, _, unrel in exact.values():
        assert unrel <= 0.1  # mutual NN + ratio 0.8 against an unrelated texture: measured ~0


def test_warped_keypoints_find_their_originals_real_photo():
    root = shared_path("kapture_samples", "samples", "maupertuis", "colmap", "images")
    fern = shared_path("llff_fern", "data", "nerf_llff_data", "fern", "images_8")
    from vrs_jax.data.images import read_gray
    # the photos' own aspect ratios (reading checks them), then both cropped to 240x136
    img = read_gray(root / "00.jpg", size=(240, 135))
    img = np.concatenate([img, img[-1:]], axis=0)
    other = read_gray(fern / "IMG_4026.png", size=(240, 180))[22:158]  # an unrelated scene
    warps = [(30, 1.0), (180, 1.0), (-135, 0.7), (45, 0.5), (60, 2.0)]
    res = _measure(img, other, warps, (352, 352), noise=0.1)
    _report("maupertuis 00.jpg (240x136) vs unrelated fern, keypoints perturbed", res)
    for nn, n, closer, unrel in res.values():
        assert n >= 15 and nn >= 0.85 and closer >= 0.85 and unrel <= 0.1


# ----------------------------------------------------------------------------- extract.py


def test_extract_features_equals_its_parts():
    img = _texture(96, 2)
    cfg = get_config("test")
    kp, desc = extract_features(img, cfg)
    assert kp.shape[0] > 10 and desc.shape == (kp.shape[0], 128)
    direct = describe_keypoints_jit(jnp.asarray(img), jnp.asarray(kp), cfg.patches,
                                    cfg.descriptor)
    np.testing.assert_allclose(desc, np.asarray(direct), atol=1e-5)
    kp2, desc2 = extract_features(img, cfg.keypoints, cfg.patches, cfg.descriptor)
    np.testing.assert_array_equal(kp2, kp)
    np.testing.assert_allclose(desc2, desc, atol=1e-6)


def test_extract_features_blank_image():
    kp, desc = extract_features(np.zeros((40, 50), np.float32), get_config("test"))
    assert kp.shape == (0, 4) and desc.shape == (0, 128)


def test_named_configs():
    assert get_config("paper") == FeatureConfig()
    assert get_config("aachen").patches.size == 31
    assert get_config("literal").patches.mode == "literal"
    with pytest.raises(VrsError):
        get_config("nope")
