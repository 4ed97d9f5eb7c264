"""From Scene to NeRF rays: pixel convention, near/far priors, normalisation, bad input."""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np
import pytest

from vrs_jax import geometry
from vrs_jax.errors import VrsError
from vrs_jax.nerf import data
from vrs_jax.nerf.toy import make_toy_scene


@pytest.fixture(scope="module")
def toy(tmp_path_factory):
    return make_toy_scene(tmp_path_factory.mktemp("toy"), n_images=4, size=16, query_every=0)


def test_sampled_rays_go_through_their_pixel_centres(toy):
    images = data.load_images(toy, np.ones(3))
    bank = data.build_bank(toy, np.full(4, 2.0), np.full(4, 6.0), images)
    members, counts = data.pad_members(np.ones((1, 4), bool))
    b = jax.jit(data.sample_rays, static_argnums=4)(bank, members[0], counts[0],
                                                     jax.random.key(0), 256)
    b = {k: np.asarray(v) for k, v in b.items()}
    img, (i, j) = b["image"], b["pixel"].T
    assert set(np.unique(img)) <= {0, 1, 2, 3} and len(np.unique(img)) == 4
    # Independent check: the 3D point at depth 3 along each ray projects to (j+.5, i+.5).
    X = b["origins"] + 3.0 * b["directions"]
    for k in range(len(img)):
        n = img[k]
        uv, z = geometry.project(toy.K[n], toy.R[n], toy.t[n], X[k][None].astype(np.float64))
        np.testing.assert_allclose(uv[0], [j[k] + 0.5, i[k] + 0.5], atol=2e-4)
        np.testing.assert_allclose(z[0], 3.0, rtol=1e-5)  # t is the z-depth
        np.testing.assert_allclose(b["rgb"][k], images[n][i[k], j[k]], atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(b["radii"], 2 / math.sqrt(12) / toy.K[0, 0, 0], rtol=1e-6)
    assert np.all(b["near"] == 2.0) and np.all(b["far"] == 6.0)


def test_sampling_respects_cluster_membership(toy):
    images = data.load_images(toy, np.ones(3))
    bank = data.build_bank(toy, np.full(4, 2.0), np.full(4, 6.0), images)
    members, counts = data.pad_members(np.array([[True, False, True, False],
                                                 [False, False, False, True]]))
    np.testing.assert_array_equal(counts, [2, 1])
    np.testing.assert_array_equal(members, [[0, 2], [3, 3]])
    for c, allowed in ((0, {0, 2}), (1, {3})):
        b = data.sample_rays(bank, members[c], counts[c], jax.random.key(c), 64)
        assert set(np.unique(np.asarray(b["image"]))) == allowed


def test_image_rays_pixel_convention():
    K = geometry.intrinsics_matrix(100.0, 100.0, 2.0, 2.0)  # 4 x 4 image, centre (2, 2)
    o, d, r = data.image_rays(K, np.eye(3), np.zeros(3), (4, 4))
    assert o.shape == (16, 3) and d.shape == (16, 3) and r.shape == (16,)
    # Element [0, 0] is at (0.5, 0.5): direction ((0.5 - 2) / 100, (0.5 - 2) / 100, 1).
    np.testing.assert_allclose(d[0], [-0.015, -0.015, 1.0], atol=1e-7)
    np.testing.assert_allclose(d[5], [-0.005, -0.005, 1.0], atol=1e-7)  # element [1, 1]


def test_near_far_from_depths_percentiles_and_margin():
    rng = np.random.default_rng(0)
    d0 = rng.uniform(2, 4, 10_000)
    d1 = np.concatenate([rng.uniform(1, 9, 1000), [0.0, -1.0, np.nan, np.inf]])  # invalid
    near, far = data.near_far_from_depths([d0, d1, np.zeros(0)], (1, 99), 0.2)
    np.testing.assert_allclose(near[0], np.percentile(d0, 1) * 0.8, rtol=1e-5)
    np.testing.assert_allclose(far[0], np.percentile(d0, 99) * 1.2, rtol=1e-5)
    valid1 = d1[np.isfinite(d1) & (d1 > 0)]
    np.testing.assert_allclose(far[1], np.percentile(valid1, 99) * 1.2, rtol=1e-5)
    pooled = np.concatenate([d0, valid1])  # the image without depths gets the pooled bounds
    np.testing.assert_allclose(near[2], np.percentile(pooled, 1) * 0.8, rtol=1e-5)
    with pytest.raises(VrsError, match="no valid depth"):
        data.near_far_from_depths([np.zeros(5), np.full(3, np.nan)])


def test_scene_near_far_priority(toy):
    n, f = data.scene_near_far(toy, 2.0, 6.0)
    assert np.all(n == 2.0) and np.all(f == 6.0)
    # Points on the unit sphere seen from distance 4.03 / 4.27: depths in [3.03, 5.27].
    pts = np.random.default_rng(1).standard_normal((2000, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    n, f = data.scene_near_far(toy, points3d=pts, margin=0.0, percentiles=(0, 100))
    assert np.all((n > 2.95) & (n < 3.3)) and np.all((f > 4.95) & (f < 5.3))
    n2, f2 = data.scene_near_far(toy, near=1.0, points3d=pts)
    assert np.all(n2 == 1.0) and np.all(f2 > 4.0)
    bounded = dataclasses.replace(toy, bounds=np.tile([3.0, 5.0], (4, 1)))
    n, f = data.scene_near_far(bounded, margin=0.1)
    np.testing.assert_allclose(n, 2.7, rtol=1e-6)
    np.testing.assert_allclose(f, 5.5, rtol=1e-6)
    with pytest.raises(VrsError, match="no depth prior"):
        data.scene_near_far(toy)
    with pytest.raises(VrsError, match="near < far"):
        data.scene_near_far(toy, 6.0, 2.0)


def test_normalization_maps_sampled_region_into_pi_box(toy):
    pts = data.frustum_points(toy.K, toy.R, toy.t, toy.sizes, np.full(4, 2.0), np.full(4, 6.0))
    center, scale = data.normalization(pts, math.pi)
    y = (pts - center) * scale
    assert np.max(np.abs(y)) <= math.pi * (1 + 1e-5)
    assert np.max(np.abs(y)) >= math.pi * (1 - 1e-5)  # tight
    with pytest.raises(VrsError, match="degenerate"):
        data.normalization(np.ones((5, 3)))


def test_scene_with_one_image_cannot_be_trained(toy):
    with pytest.raises(VrsError, match="single posed reference image"):
        data.check_scene_for_training(toy.subset([0]))
    only_queries = dataclasses.replace(toy, is_query=np.ones(4, bool))
    with pytest.raises(VrsError, match="no posed reference"):
        data.check_scene_for_training(only_queries)


def test_inner_ball_and_unbounded_ratio():
    """The inner ball holds every camera plus the median content depth; a far bound many
    radii beyond it makes the scene unbounded, a bound near the cameras does not."""
    rng = np.random.default_rng(0)
    cams = rng.normal(0, 1, (20, 3))
    depths = np.full(20, 3.0)
    center, radius = data.inner_ball(cams, depths)
    np.testing.assert_allclose(center, cams.mean(0), rtol=1e-6)
    assert np.all(np.linalg.norm(cams - center, axis=1) <= radius - 3.0 + 1e-6)
    assert data.unbounded_ratio(cams, depths, np.full(20, 4.0)) < 1
    assert data.unbounded_ratio(cams, depths, np.full(20, 500.0)) > data.UNBOUNDED_RATIO
    np.testing.assert_allclose(data.typical_depths(np.full(2, 1.0), np.full(2, 4.0),
                                                   [np.array([5.0, 7.0, np.nan]), np.zeros(0)]),
                               [6.0, 2.0])
    with pytest.raises(VrsError):
        data.inner_ball(np.zeros((3, 3)), np.zeros(3))
