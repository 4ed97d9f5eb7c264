"""VLAD retrieval in JAX against numpy references."""

from __future__ import annotations

import numpy as np
import pytest

from vrs_jax.egm import retrieval as RT
from vrs_jax.errors import VrsError
from vrs_jax.kmeans import kmeans


def _unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _vlad_numpy(desc, centers, power=0.5):
    """Reference VLAD: residual sums, intra-norm, signed power, L2."""
    a = np.argmin(((desc[:, None] - centers[None]) ** 2).sum(-1), axis=1)
    v = np.zeros_like(centers, dtype=np.float64)
    for k in range(len(centers)):
        if np.any(a == k):
            v[k] = (desc[a == k] - centers[k]).sum(0)
    n = np.linalg.norm(v, axis=1, keepdims=True)
    v = np.where(n > 0, v / np.maximum(n, 1e-12), 0)
    v = np.sign(v) * np.abs(v) ** power
    v = v.ravel()
    return v / np.linalg.norm(v)


def test_vocabulary_is_the_shared_kmeans_of_the_descriptors():
    rng = np.random.default_rng(0)
    true = rng.normal(size=(6, 8)) * 5
    descs = [np.concatenate([c + 0.1 * rng.normal(size=(20, 8)) for c in true]).astype(
        np.float32) for _ in range(3)]
    vocab = RT.learn_vocabulary(descs, RT.RetrievalConfig(n_words=6, kmeans_iters=10))
    c = kmeans(np.concatenate(descs), 6, iters=10, seed=0)
    np.testing.assert_array_equal(np.asarray(vocab.centers), c)
    assert np.all(np.linalg.norm(true[:, None] - c[None], axis=-1).min(1) < 0.1)


def test_vlad_matches_numpy_and_ignores_padding():
    rng = np.random.default_rng(2)
    centers = _unit(rng.normal(size=(8, 16))).astype(np.float32)
    desc = _unit(rng.normal(size=(50, 16))).astype(np.float32)
    v = np.asarray(RT.vlad(desc, np.ones(50, bool), centers))
    np.testing.assert_allclose(v, _vlad_numpy(desc, centers), atol=1e-5)
    assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-5)
    # padding rows (garbage) masked out change nothing
    padded = np.concatenate([desc, rng.normal(size=(14, 16)).astype(np.float32)])
    mask = np.arange(64) < 50
    np.testing.assert_allclose(RT.vlad(padded, mask, centers), v, atol=1e-6)
    # no valid descriptor: the zero vector, not NaN
    z = np.asarray(RT.vlad(desc, np.zeros(50, bool), centers))
    assert np.all(z == 0)


def test_global_descriptor_shared_helper_and_topk():
    rng = np.random.default_rng(3)
    descs = [_unit(rng.normal(size=(n, 16))).astype(np.float32) for n in (30, 45, 0, 60)]
    vocab = RT.learn_vocabulary(descs, RT.RetrievalConfig(n_words=4, kmeans_iters=5))
    assert vocab.dim == 64
    G = RT.global_descriptors(descs, None, vocab)
    for i, d in enumerate(descs):
        np.testing.assert_allclose(RT.global_descriptor(d, None, vocab), G[i], atol=1e-6)
    assert np.all(G[2] == 0)
    # a query equal to image 3's descriptors retrieves image 3 first
    q = RT.global_descriptor(descs[3], None, vocab)
    idx, scores = RT.topk(q, G, 2)
    assert int(idx[0]) == 3 and float(scores[0]) == pytest.approx(1.0, abs=1e-5)
    # batched top-k equals numpy's sort; the mask removes entries
    Q = rng.normal(size=(5, 64)).astype(np.float32)
    idx, scores = RT.topk(Q, G, 3)
    ref = np.argsort(-(Q @ G.T), axis=1, kind="stable")[:, :3]
    np.testing.assert_array_equal(np.asarray(idx), ref)
    idx, _ = RT.topk(Q, G, 3, db_mask=np.array([True, False, True, True]))
    assert 1 not in np.asarray(idx)


def test_pca_whitening_gives_identity_covariance():
    rng = np.random.default_rng(4)
    v = rng.normal(size=(40, 10)) @ rng.normal(size=(10, 10))
    mean, proj = RT.pca_whitening(v, 6, eps=0.0)
    y = (v - mean) @ proj
    np.testing.assert_allclose(np.cov(y.T), np.eye(6), atol=1e-4)
    descs = [_unit(rng.normal(size=(30, 8))).astype(np.float32) for _ in range(10)]
    vocab = RT.learn_vocabulary(descs, RT.RetrievalConfig(n_words=4, pca_dim=5))
    G = RT.global_descriptors(descs, None, vocab)
    assert G.shape == (10, 5) and np.allclose(np.linalg.norm(G, axis=1), 1, atol=1e-5)


def test_vocabulary_errors():
    with pytest.raises(VrsError, match="no reference image has keypoints"):
        RT.learn_vocabulary([np.zeros((0, 8))], RT.RetrievalConfig(n_words=2))
    with pytest.raises(VrsError, match="visual words"):
        RT.learn_vocabulary([np.ones((3, 8))], RT.RetrievalConfig(n_words=4))
    with pytest.raises(VrsError, match="at least 2 reference images"):
        RT.learn_vocabulary([np.random.default_rng(0).normal(size=(10, 8))],
                            RT.RetrievalConfig(n_words=2, pca_dim=4))


def test_local_whitening_before_vlad_matches_numpy():
    """local_dim: the local descriptors are PCA-whitened (identity covariance over the
    training descriptors) before the words are learned and VLAD is taken; a query's global
    descriptor is the numpy VLAD of its whitened descriptors on those words."""
    rng = np.random.default_rng(5)
    mix = rng.normal(size=(16, 16))
    descs = [_unit(rng.normal(size=(n, 16)) @ mix).astype(np.float32) for n in (40, 55, 30)]
    vocab = RT.learn_vocabulary(descs, RT.RetrievalConfig(n_words=4, kmeans_iters=5,
                                                          local_dim=6, whiten_eps=0.0))
    assert vocab.input_dim == 16 and np.asarray(vocab.centers).shape == (4, 6)
    assert vocab.dim == 24
    allx = np.concatenate(descs).astype(np.float64)
    mean, proj = np.asarray(vocab.local_mean), np.asarray(vocab.local_proj)
    np.testing.assert_allclose(mean, allx.mean(0), atol=1e-6)
    np.testing.assert_allclose(np.cov(((allx - mean) @ proj).T), np.eye(6), atol=1e-3)
    q = _unit(rng.normal(size=(25, 16)) @ mix).astype(np.float32)
    ref = _vlad_numpy((q - mean) @ proj, np.asarray(vocab.centers, np.float64))
    np.testing.assert_allclose(RT.global_descriptor(q, None, vocab), ref, atol=1e-4)
    with pytest.raises(VrsError, match="exceeds"):
        RT.learn_vocabulary(descs, RT.RetrievalConfig(n_words=4, local_dim=17))
    with pytest.raises(VrsError, match="local_dim"):
        RT.RetrievalConfig(local_dim=0)


def test_a_config_written_before_local_dim_means_raw_descriptors():
    """Maps written before RetrievalConfig.local_dim existed read as without it."""
    from vrs_jax import configio

    d = configio.to_dict(RT.RetrievalConfig(n_words=8))
    del d["local_dim"]
    assert configio.from_dict(RT.RetrievalConfig, d) == RT.RetrievalConfig(n_words=8)
