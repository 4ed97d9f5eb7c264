"""The shared k-means: frozen reference of the camera clustering it replaced, blobs, seeding."""

from __future__ import annotations

import numpy as np
import pytest

from vrs_jax import kmeans as KM
from vrs_jax.errors import VrsError


def _old_kmeans(points, k, seed=0, iters=100):
    """Frozen copy of vrs_jax.nerf.clusters.kmeans before the k-means was shared (the
    reference: the camera clustering must not change)."""
    points = np.asarray(points, dtype=np.float64)
    rng = np.random.default_rng(seed)
    n = len(points)
    centers = [points[rng.integers(n)]]
    d2 = np.sum((points - centers[0]) ** 2, axis=1)
    for _ in range(1, k):
        total = d2.sum()
        idx = int(rng.integers(n)) if total <= 0 else int(rng.choice(n, p=d2 / total))
        centers.append(points[idx])
        d2 = np.minimum(d2, np.sum((points - points[idx]) ** 2, axis=1))
    centers = np.stack(centers)
    labels = np.zeros(len(points), dtype=np.int64)
    for it in range(iters):
        d2 = np.sum((points[:, None, :] - centers[None]) ** 2, axis=-1)
        new_labels = np.argmin(d2, axis=1)
        if it > 0 and np.array_equal(new_labels, labels):
            break
        labels = new_labels
        for j in range(k):
            sel = labels == j
            if sel.any():
                centers[j] = points[sel].mean(axis=0)
    return centers, labels


def _blobs(seed=0, n=30):
    rng = np.random.default_rng(seed)
    centres = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 1.0]])
    pts = np.concatenate([c + 0.5 * rng.standard_normal((n, 3)) for c in centres])
    return pts, np.repeat(np.arange(3), n), centres


@pytest.mark.parametrize("seed", range(6))
def test_bit_identical_to_the_former_camera_kmeans(seed):
    rng = np.random.default_rng(100 + seed)
    cams = [rng.uniform(-5, 5, (200, 3)),  # a room of camera centres
            np.cumsum(rng.normal(size=(300, 3)), axis=0),  # a trajectory
            np.repeat(rng.normal(size=(4, 3)), 5, axis=0),  # repeated positions
            _blobs(seed)[0]]
    for x in cams:
        for k in (1, 2, 4, 7):
            for iters in (1, 3, 100):
                c, lab = KM.kmeans(x, k, seed=seed, iters=iters)
                c0, lab0 = _old_kmeans(x, k, seed=seed, iters=iters)
                np.testing.assert_array_equal(lab, lab0)
                np.testing.assert_array_equal(c, c0)


def test_block_distances_equal_one_block():
    rng = np.random.default_rng(1)
    x, c = rng.normal(size=(1000, 16)), rng.normal(size=(5, 16))
    full = np.sum((x[:, None] - c[None]) ** 2, axis=-1)
    old = KM._BLOCK_ELEMENTS
    try:
        KM._BLOCK_ELEMENTS = 7 * 5 * 16  # blocks of 7 rows, the last one partial
        np.testing.assert_array_equal(KM.sq_dists(x, c), full)
    finally:
        KM._BLOCK_ELEMENTS = old
    np.testing.assert_array_equal(KM.sq_dists(x, c), full)


def test_recovers_separated_blobs_deterministically():
    pts, truth, centres = _blobs()
    c1, l1 = KM.kmeans(pts, 3, seed=5)
    c2, l2 = KM.kmeans(pts, 3, seed=5)
    np.testing.assert_array_equal(l1, l2)
    np.testing.assert_array_equal(c1, c2)
    for k in range(3):  # the truth up to a relabelling, centres near the blob centres
        assert len(np.unique(l1[truth == k])) == 1
        assert np.min(np.linalg.norm(c1 - centres[k], axis=1)) < 0.3


def test_recovers_clusters_in_descriptor_dimensions():
    rng = np.random.default_rng(0)
    true = rng.normal(size=(6, 128)) * 5
    x = np.concatenate([c + 0.1 * rng.normal(size=(100, 128)) for c in true]).astype(np.float32)
    c, labels = KM.kmeans(x, 6, iters=10, seed=0)
    # the mean of 100 samples of N(0, 0.1^2 I_128) is ~0.11 from the true centre
    assert np.all(np.linalg.norm(true[:, None] - c[None], axis=-1).min(1) < 0.2)
    # one Lloyd step more changes nothing: centres are the means of their members
    ref = np.stack([x[labels == j].astype(np.float64).mean(0) for j in range(6)])
    np.testing.assert_allclose(c, ref, rtol=0, atol=1e-12)


def test_kmeans_pp_seeds_spread_out_and_distinct():
    pts, _, _ = _blobs()
    seeds = KM.kmeans_pp_init(pts, 3, np.random.default_rng(0))
    d = np.linalg.norm(seeds[:, None] - seeds[None], axis=-1)
    assert np.min(d[np.triu_indices(3, 1)]) > 5.0  # one seed per blob
    x = np.repeat(np.eye(4), 10, axis=0)  # 4 distinct points, 10 copies each
    assert len({tuple(r) for r in KM.kmeans_pp_init(x, 4, np.random.default_rng(0))}) == 4


def test_bad_input_is_one_line():
    with pytest.raises(VrsError, match="points \\[N, D\\]"):
        KM.kmeans(np.zeros((0, 3)), 1)
    with pytest.raises(VrsError, match="cannot make 4 clusters from 3 points"):
        KM.kmeans(np.zeros((3, 2)), 4)


def test_matrix_product_distances_agree_with_exact_ones():
    rng = np.random.default_rng(2)
    x, c = rng.normal(size=(400, 128)), rng.normal(size=(16, 128))
    np.testing.assert_allclose(KM.sq_dists(x, c, exact=False), KM.sq_dists(x, c),
                               rtol=1e-12, atol=1e-10)
    np.testing.assert_array_equal(KM.sq_dists(x, x[:3], exact=False)[np.arange(3), np.arange(3)]
                                  >= 0, True)
    # the same clustering of well-separated data either way
    true = rng.normal(size=(5, 128)) * 5
    pts = np.concatenate([t + 0.1 * rng.normal(size=(50, 128)) for t in true])
    _, la = KM.kmeans(pts, 5, seed=3, exact=False)
    _, lb = KM.kmeans(pts, 5, seed=3)
    np.testing.assert_array_equal(la, lb)
