"""Matching: against a brute-force numpy reference with masks; mutual and ratio behaviour;
degenerate sizes; jit."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vrs_jax.features import matching
from vrs_jax.features.matching import match, match_jit, pairwise_distances, planar_sq_distances


def _ref(dq, mq, dr, mr, ratio, mutual, max_dist=None):
    """Loop-by-loop reference in float64."""
    nq = len(dq)
    idx = np.zeros(nq, np.int64)
    valid = np.zeros(nq, bool)
    dist = np.full(nq, np.inf)
    D = np.linalg.norm(dq[:, None].astype(np.float64) - dr[None].astype(np.float64), axis=-1)
    for q in range(nq):
        if not mq[q]:
            continue
        cand = [(D[q, r], r) for r in range(len(dr)) if mr[r]]
        if not cand:
            continue
        cand.sort()
        d1, r1 = cand[0]
        idx[q], dist[q], ok = r1, d1, True
        if ratio is not None and len(cand) > 1:
            ok &= d1 < ratio * cand[1][0]
        if mutual:
            back = min((D[qq, r1], qq) for qq in range(nq) if mq[qq])[1]
            ok &= back == q
        if max_dist is not None:
            ok &= d1 <= max_dist
        valid[q] = ok
    return idx, valid, dist


def _data(rng, nq, nr, d=16, p_mask=0.2):
    dq = rng.normal(size=(nq, d)).astype(np.float32)
    dr = rng.normal(size=(nr, d)).astype(np.float32)
    # plant near-duplicates so that many queries have a clear match
    k = min(nq, nr) // 2
    dr[:k] = dq[:k] + 0.1 * rng.normal(size=(k, d)).astype(np.float32)
    return dq, rng.random(nq) > p_mask, dr, rng.random(nr) > p_mask


@pytest.mark.parametrize("ratio,mutual,max_dist", [(0.8, True, None), (0.8, False, None),
                                                   (None, True, None), (None, False, None),
                                                   (0.95, True, 3.0)])
def test_against_bruteforce_reference(ratio, mutual, max_dist):
    rng = np.random.default_rng(0)
    for nq, nr in [(30, 40), (25, 7), (5, 3)]:
        dq, mq, dr, mr = _data(rng, nq, nr)
        idx, valid, dist = match_jit(dq, mq, dr, mr, ratio, mutual, max_dist)
        ridx, rvalid, rdist = _ref(dq, mq, dr, mr, ratio, mutual, max_dist)
        assert idx.dtype == np.int32 and valid.dtype == bool and idx.shape == (nq,)
        np.testing.assert_array_equal(np.asarray(valid), rvalid)
        has = np.isfinite(rdist)
        np.testing.assert_array_equal(np.asarray(idx)[has], ridx[has])
        np.testing.assert_allclose(np.asarray(dist), rdist, rtol=1e-4, atol=1e-4)
        assert not np.any(np.asarray(valid) & ~mq), "masked queries never match"
        assert np.all(mr[np.asarray(idx)[np.asarray(valid)]]), "masked references never chosen"


def test_mutual_check_keeps_only_the_closer_query():
    dr = np.array([[0.0, 0.0], [10.0, 0.0]], np.float32)
    dq = np.array([[0.1, 0.0], [0.5, 0.0]], np.float32)  # both nearest to r0; q0 closer
    ones = np.ones(2, bool)
    idx, valid, _ = match(dq, ones, dr, ones, ratio=None, mutual=True)
    np.testing.assert_array_equal(np.asarray(idx), [0, 0])
    np.testing.assert_array_equal(np.asarray(valid), [True, False])
    _, valid, _ = match(dq, ones, dr, ones, ratio=None, mutual=False)
    np.testing.assert_array_equal(np.asarray(valid), [True, True])
    # masking q0 out makes q1 the mutual partner of r0
    _, valid, _ = match(dq, np.array([False, True]), dr, ones, ratio=None, mutual=True)
    np.testing.assert_array_equal(np.asarray(valid), [False, True])


def test_ratio_test_rejects_ambiguous_matches():
    dr = np.array([[0.0, 0.0], [2.0, 0.0], [0.0, 50.0]], np.float32)
    dq = np.array([[0.9, 0.0], [0.0, 49.0]], np.float32)  # q0: d1 0.9, d2 1.1 -> ambiguous
    m = np.ones(3, bool)
    _, valid, dist = match(dq, m[:2], dr, m, ratio=0.8, mutual=False)
    np.testing.assert_array_equal(np.asarray(valid), [False, True])
    np.testing.assert_allclose(np.asarray(dist), [0.9, 1.0], atol=1e-5)
    _, valid, _ = match(dq, m[:2], dr, m, ratio=0.9, mutual=False)  # 0.9 < 0.9*1.1 = 0.99
    np.testing.assert_array_equal(np.asarray(valid), [True, True])
    # masking the distractor r1 removes the ambiguity
    _, valid, _ = match(dq, m[:2], dr, np.array([True, False, True]), ratio=0.8, mutual=False)
    np.testing.assert_array_equal(np.asarray(valid), [True, True])


def test_degenerate_sizes():
    dq = np.random.default_rng(1).normal(size=(4, 8)).astype(np.float32)
    mq = np.ones(4, bool)
    # one reference: no second neighbour, ratio test off, mutual decides
    idx, valid, dist = match_jit(dq, mq, dq[:1], np.ones(1, bool), 0.8)
    np.testing.assert_array_equal(np.asarray(idx), 0)
    np.testing.assert_array_equal(np.asarray(valid), [True, False, False, False])
    assert np.isfinite(np.asarray(dist)).all()
    # no reference
    idx, valid, dist = match(dq, mq, np.zeros((0, 8), np.float32), np.zeros(0, bool))
    assert idx.shape == (4,) and not np.asarray(valid).any() and np.isinf(np.asarray(dist)).all()
    # all references masked
    idx, valid, dist = match_jit(dq, mq, dq, np.zeros(4, bool), 0.8)
    assert not np.asarray(valid).any() and np.isinf(np.asarray(dist)).all()
    # no query
    idx, valid, dist = match(np.zeros((0, 8), np.float32), np.zeros(0, bool), dq, mq)
    assert idx.shape == valid.shape == dist.shape == (0,)


def test_traced_ratio_under_jit_and_vmap():
    rng = np.random.default_rng(2)
    dq, mq, dr, mr = _data(rng, 12, 15)
    f = jax.jit(lambda r: match(dq, mq, dr, mr, r, True))
    for r in (0.6, 0.8, 0.95):
        np.testing.assert_array_equal(np.asarray(f(r)[1]), _ref(dq, mq, dr, mr, r, True)[1])
    # vmap over a batch of query sets (e.g. several queries against one rendered set)
    dqs = np.stack([dq, dq[::-1]])
    mqs = np.stack([mq, mq[::-1]])
    idx, valid, _ = jax.vmap(lambda a, b: match(a, b, dr, mr, 0.8, True))(dqs, mqs)
    np.testing.assert_array_equal(np.asarray(valid[1]), _ref(dqs[1], mqs[1], dr, mr, 0.8, True)[1])


def test_pairwise_distances():
    rng = np.random.default_rng(3)
    a, b = rng.normal(size=(5, 7)), rng.normal(size=(6, 7))
    ref = np.linalg.norm(a[:, None] - b[None], axis=-1)
    np.testing.assert_allclose(np.asarray(pairwise_distances(a, b)), ref, rtol=1e-5)
    # self-distances: float32 cancellation leaves sqrt(eps * 2 |a|^2) ~ 1e-3 for |a|^2 ~ 7
    assert float(np.asarray(pairwise_distances(a, a)).diagonal().max()) < 4e-3


def test_planar_sq_distances():
    rng = np.random.default_rng(4)
    a, b = rng.uniform(0, 640, size=(9, 2)), rng.uniform(0, 640, size=(11, 2))
    ref = np.sum((a[:, None] - b[None]) ** 2, axis=-1)
    got = np.asarray(jax.jit(planar_sq_distances)(a, b))
    assert got.shape == (9, 11)
    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-2)
    assert np.asarray(planar_sq_distances(a, a)).diagonal().max() == 0.0


def test_first_argmin_is_numpys_argmin():
    """Ties to the lowest index, slices of +inf (masked rows) give 0, both axes, under jit;
    a NaN still gives a valid index."""
    rng = np.random.default_rng(6)
    x = rng.integers(0, 4, size=(37, 23)).astype(np.float32)  # many ties
    x[rng.uniform(size=x.shape) < 0.3] = np.inf
    x[5] = np.inf
    x[:, 7] = np.inf
    f = jax.jit(matching.first_argmin, static_argnames="axis")
    for axis in (0, 1, -1):
        got = np.asarray(f(x, axis=axis))
        assert got.dtype == np.int32
        np.testing.assert_array_equal(got, np.argmin(x, axis=axis))
    y = x.copy()
    y[3, 4] = np.nan
    assert 0 <= int(matching.first_argmin(y, 1)[3]) < y.shape[1]


def _guided_reference(uv_q, dq, mq, uv_r, dr, mr, gr, radius, ratio):
    """Brute-force numpy reference of guided_match."""
    nq, nr = len(uv_q), len(uv_r)
    D = np.full((nq, nr), np.inf)
    for a in range(nq):
        for b in range(nr):
            if mq[a] and mr[b] and np.sum((uv_q[a] - uv_r[b]) ** 2) < radius ** 2:
                D[a, b] = np.linalg.norm(dq[a] - dr[b])
    valid = np.zeros(nq, bool)
    idx = np.zeros(nq, int)
    for a in range(nq):
        if not np.isfinite(D[a]).any():
            continue
        b = int(np.argmin(D[a]))
        rivals = [D[a, c] for c in range(nr) if gr[c] != gr[b]]
        d2 = min(rivals) if rivals else np.inf
        ok = D[a, b] < ratio * d2 or np.isinf(d2)
        ok &= int(np.argmin(D[:, b])) == a
        valid[a], idx[a] = ok, b
    return idx, valid


def test_guided_match_against_brute_force():
    rng = np.random.default_rng(3)
    nq, nr = 60, 40
    uv_q = rng.uniform(0, 100, (nq, 2))
    uv_r = rng.uniform(0, 100, (nr, 2))
    dq = rng.normal(size=(nq, 16))
    dq /= np.linalg.norm(dq, axis=1, keepdims=True)
    dr = rng.normal(size=(nr, 16))
    dr /= np.linalg.norm(dr, axis=1, keepdims=True)
    # ten true pairs: close in the image and in descriptor space
    uv_r[:10] = uv_q[:10] + rng.normal(0, 1.0, (10, 2))
    dr[:10] = dq[:10] + rng.normal(0, 0.05, (10, 16))
    gr = np.arange(nr) % 30  # a few references share a group (the same 3D point)
    mq = rng.uniform(size=nq) > 0.1
    mr = rng.uniform(size=nr) > 0.1
    idx, valid, _ = matching.guided_match(uv_q, dq, mq, uv_r, dr, mr, jnp.asarray(gr), 12.0, 0.9)
    ridx, rvalid = _guided_reference(uv_q, dq, mq, uv_r, dr, mr, gr, 12.0, 0.9)
    np.testing.assert_array_equal(np.asarray(valid), rvalid)
    np.testing.assert_array_equal(np.asarray(idx)[rvalid], ridx[rvalid])
    true = np.flatnonzero(mq[:10] & mr[:10])
    assert np.all(np.asarray(valid)[true]) and np.all(np.asarray(idx)[true] == true)
    # nothing outside the radius is ever chosen
    far = np.sum((uv_q - uv_r[np.asarray(idx)]) ** 2, 1) >= 144
    assert not np.any(np.asarray(valid) & far)
