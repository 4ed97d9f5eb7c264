"""Keypoint-patch training rays: same cones as the localizer, targets = the real patches."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax import geometry
from vrs_jax.data.images import read_image
from vrs_jax.data.readers import load_scene
from vrs_jax.features.keypoints import KeypointConfig, detect
from vrs_jax.features.patches import PatchConfig, extract_patches, patch_grid
from vrs_jax.nerf import data as data_lib
from vrs_jax.nerf.patch_pool import patch_pool


def _refs_with_keypoints(root, k=24):
    refs = load_scene("7scenes", root).references().subset(np.arange(3))
    kps, masks = [], []
    for i in range(len(refs)):
        img = read_image(refs.image_paths[i])
        kp = detect(img.mean(-1), KeypointConfig(max_keypoints=k))
        pad = np.zeros((k, 4), np.float32)
        pad[:, 2] = 1
        pad[: len(kp)] = kp
        m = np.zeros(k, bool)
        m[: len(kp)] = True
        kps.append(pad)
        masks.append(m)
    return refs, np.stack(kps), np.stack(masks)


def test_pool_rays_and_targets_match_the_real_patches(small_synthetic_scene):
    refs, kps, masks = _refs_with_keypoints(small_synthetic_scene)
    cfg = PatchConfig(size=9)
    near, far = np.full(3, 0.1), np.full(3, 8.0)
    pool = patch_pool(refs, kps, masks, cfg, near, far, max_rays=10**7)
    assert set(pool) == {"origins", "directions", "radii", "near", "far", "rgb", "depth",
                         "image"}
    assert not pool["depth"].any()  # no depths given
    # image 0's rays: project back onto its patch grid, and carry the real patch colours
    sel = pool["image"] == 0
    pos, _ = patch_grid(kps[0][masks[0]], cfg)
    pos = np.asarray(pos).reshape(-1, 2)
    X = pool["origins"][sel] + 2.0 * pool["directions"][sel]
    uv, _ = geometry.project(refs.K[0], refs.R[0], refs.t[0], X.astype(np.float64))
    img = read_image(refs.image_paths[0])
    h, w = img.shape[:2]
    inside = (pos[:, 0] >= 0) & (pos[:, 0] <= w) & (pos[:, 1] >= 0) & (pos[:, 1] <= h)
    np.testing.assert_allclose(uv, pos[inside], atol=1e-2)
    ref = np.stack([np.asarray(extract_patches(jnp.asarray(img[..., c]),
                                               jnp.asarray(kps[0][masks[0]]), cfg))
                    for c in range(3)], -1).reshape(-1, 3)[inside]
    np.testing.assert_allclose(pool["rgb"][sel], np.clip(ref, 0, 1), atol=1e-5)
    # the cap subsamples
    small = patch_pool(refs, kps, masks, cfg, near, far, max_rays=200)
    assert 100 < len(small["image"]) < 300


def test_sample_rays_draws_the_pool_fraction(small_synthetic_scene):
    refs, kps, masks = _refs_with_keypoints(small_synthetic_scene)
    cfg = PatchConfig(size=9)
    near, far = np.full(3, 0.1), np.full(3, 8.0)
    pool = patch_pool(refs, kps, masks, cfg, near, far, max_rays=10**7)
    images = data_lib.load_images(refs)
    bank = data_lib.build_bank(refs, near, far, images, pool, pool_fraction=0.5)
    members = jnp.arange(3, dtype=jnp.int32)
    b = jax.jit(data_lib.sample_rays, static_argnums=4)(bank, members, jnp.int32(3),
                                                        jax.random.key(0), 64)
    # the second half are pixel rays (pixel radius), the first half pool rays (patch radii)
    np.testing.assert_allclose(np.asarray(b["radii"])[32:], data_lib.pixel_radii(refs.K)[0],
                               rtol=1e-5)
    # each pool ray's colour is the pool target of that very ray
    o = np.asarray(b["origins"])[:32]
    d = np.asarray(b["directions"])[:32]
    for k in range(32):
        hit = np.flatnonzero(np.all(np.isclose(pool["directions"], d[k], atol=1e-6), axis=1)
                             & np.all(np.isclose(pool["origins"], o[k], atol=1e-6), axis=1))
        assert hit.size >= 1  # the first half comes from the keypoint patches
        assert np.isclose(pool["radii"][hit[0]], np.asarray(b["radii"])[k])
        np.testing.assert_allclose(np.asarray(b["rgb"])[k], pool["rgb"][hit[0]], atol=1e-6)


def test_pool_carries_each_keypoints_depth_to_its_samples(small_synthetic_scene):
    refs, kps, masks = _refs_with_keypoints(small_synthetic_scene)
    cfg = PatchConfig(size=9)
    near, far = np.full(3, 0.1), np.full(3, 8.0)
    depths = np.where(masks, 1.0 + np.arange(masks.shape[1])[None, :], 0.0)
    depths[1, 0] = -1.0  # a keypoint without a 3D point: no depth (0)
    pool = patch_pool(refs, kps, masks, cfg, near, far, max_rays=10**7, depths=depths)
    pos, _ = patch_grid(kps[0][masks[0]], cfg)
    pos = np.asarray(pos).reshape(-1, 2)
    img = read_image(refs.image_paths[0])
    h, w = img.shape[:2]
    inside = (pos[:, 0] >= 0) & (pos[:, 0] <= w) & (pos[:, 1] >= 0) & (pos[:, 1] <= h)
    want = np.repeat(depths[0][masks[0]], 81)[inside]
    np.testing.assert_array_equal(pool["depth"][pool["image"] == 0], want)
    assert np.all(pool["depth"][pool["image"] == 1][:81] == 0.0)
    # the bank hands them to the pool rays of a batch, and 0 to pixel rays
    images = data_lib.load_images(refs)
    bank = data_lib.build_bank(refs, near, far, images, pool, pool_fraction=0.5)
    b = data_lib.sample_rays(bank, jnp.arange(3, dtype=jnp.int32), jnp.int32(3),
                             jax.random.key(1), 64)
    d, o = np.asarray(b["directions"])[:32], np.asarray(b["origins"])[:32]
    for k in range(32):
        hit = np.flatnonzero(np.all(np.isclose(pool["directions"], d[k], atol=1e-6), axis=1)
                             & np.all(np.isclose(pool["origins"], o[k], atol=1e-6), axis=1))
        assert float(b["depth"][k]) in set(pool["depth"][hit].tolist())
    assert not np.asarray(b["depth"])[32:].any()
