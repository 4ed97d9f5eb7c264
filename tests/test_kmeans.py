"""The shared k-means (JAX): separated clusters, a Lloyd step against numpy, seeding."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vrs_jax import kmeans as KM
from vrs_jax.errors import VrsError


def test_recovers_separated_clusters_deterministically():
    rng = np.random.default_rng(0)
    true = rng.normal(size=(6, 8)) * 5
    x = np.concatenate([c + 0.1 * rng.normal(size=(100, 8)) for c in true])
    c = KM.kmeans(x, 6, iters=10, seed=0)
    assert c.shape == (6, 8) and c.dtype == np.float32
    d = np.linalg.norm(true[:, None] - c[None], axis=-1)
    assert np.all(d.min(1) < 0.1)  # every true centre found
    np.testing.assert_array_equal(c, KM.kmeans(x, 6, iters=10, seed=0))


def test_recovers_camera_blobs_far_from_the_origin_when_centred():
    rng = np.random.default_rng(1)
    blobs = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 1.0]])
    x = np.concatenate([b + 0.5 * rng.standard_normal((30, 3)) for b in blobs])
    offset = np.array([4.0e5, -3.0e5, 50.0])  # UTM-like world coordinates
    c = KM.kmeans(x + offset - (x + offset).mean(0), 3, iters=100, seed=5)
    c = c + (x + offset).mean(0)
    for b in blobs:
        assert np.min(np.linalg.norm(c - offset - b, axis=1)) < 0.3


def test_sq_dists_and_lloyd_step_match_numpy():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(300, 4)).astype(np.float32)
    c0 = x[:5].copy()
    d2 = ((x[:, None] - c0[None]) ** 2).sum(-1)
    np.testing.assert_allclose(np.asarray(KM.sq_dists(jnp.asarray(x), jnp.asarray(c0))), d2,
                               atol=1e-5)
    c = np.asarray(KM.lloyd(jnp.asarray(x), jnp.asarray(c0), 1))
    a = np.argmin(d2, axis=1)
    ref = np.stack([x[a == k].mean(0) for k in range(5)])
    np.testing.assert_allclose(c, ref, atol=1e-5)


def test_kmeans_pp_picks_distinct_points_and_spreads_out():
    x = np.repeat(np.eye(4, dtype=np.float32), 10, axis=0)  # 4 distinct points, 10 copies each
    c = np.asarray(KM.kmeans_pp_init(jax.random.PRNGKey(0), jnp.asarray(x), 4))
    assert len({tuple(r) for r in c}) == 4
    rng = np.random.default_rng(0)
    blobs = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 1.0]])
    pts = np.concatenate([b + 0.5 * rng.standard_normal((30, 3)) for b in blobs])
    seeds = np.asarray(KM.kmeans_pp_init(jax.random.PRNGKey(0), jnp.asarray(pts, jnp.float32),
                                         3))
    d = np.linalg.norm(seeds[:, None] - seeds[None], axis=-1)
    assert np.min(d[np.triu_indices(3, 1)]) > 5.0  # one seed per blob


def test_bad_input_is_one_line():
    with pytest.raises(VrsError, match="non-empty \\[M, D\\]"):
        KM.kmeans(np.zeros((0, 3)), 1)
    with pytest.raises(VrsError, match="cannot make 4 clusters from 3 points"):
        KM.kmeans(np.zeros((3, 2)), 4)
