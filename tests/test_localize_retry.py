"""Retries of doubtful queries (vrs_jax.localize.retry): the retrieval offset against a numpy
ranking, the number of attempts against a count of the references left, which attempt is
kept (hand-made results), and localize_scene retrying on the tiny map."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest

from vrs_jax import localize, maps
from vrs_jax.data.readers import load_scene
from vrs_jax.geometry import camera_center
from vrs_jax.localize import stages as st
from vrs_jax.localize.batch import localize_scene
from vrs_jax.localize.confidence import ConfidenceConfig, map_scale, one_confidence
from vrs_jax.localize.retry import attempt_config, attempt_shift, attempts, localize_with_retries
from vrs_jax.localize.track import start_result


def _stub_map(n: int, desc: np.ndarray | None = None):
    return SimpleNamespace(egm=SimpleNamespace(num_images=n, global_desc=desc))


def test_retrieval_offset_takes_the_next_ranks():
    rng = np.random.default_rng(0)
    n, g = 12, 16
    db = rng.normal(size=(n, g)).astype(np.float32)
    db /= np.linalg.norm(db, axis=1, keepdims=True)
    q = rng.normal(size=g).astype(np.float32)
    order = np.argsort(-(db @ q), kind="stable")  # best first
    m = _stub_map(n, db)
    for off in (0, 3, 5, 10, 11, 15):
        cfg = localize.get_config("test", top_k=5, retrieval_offset=off)
        idx = np.asarray(st.retrieval(m, SimpleNamespace(global_desc=q), cfg, {})["idx"])
        start = min(off, n - 1)
        np.testing.assert_array_equal(idx, order[start:start + 5], err_msg=f"offset {off}")


def test_attempts_count_the_references_left():
    for n in range(1, 14):
        for k in range(1, 7):
            for off in range(n):
                for retries in range(5):
                    cfg = localize.get_config("test", top_k=k, retrieval_offset=off,
                                              retries=retries)
                    want = 1 + sum(off + a * k < n for a in range(1, retries + 1))
                    assert attempts(_stub_map(n), cfg) == want, (n, k, off, retries)
    cfg = localize.get_config("test", top_k=5, retries=2)
    assert attempt_config(cfg, 0) is cfg
    assert attempt_config(cfg, 2).retrieval_offset == 10 and attempt_config(cfg, 2).retries == 0


def _result(n_inliers: int, rendered: int, success: bool = True, centre=(0.0, 0.0, -1.0)):
    """A result at one pose (identity rotation, camera centre ``centre``) with ``n_inliers``
    of 100 matches (coverage 0.6; both passes at that pose): localized from 30 inliers with
    the default thresholds."""
    q = SimpleNamespace(mask=np.ones(50, bool))
    t = -np.asarray(centre, np.float64)  # c = -R^T t with R = I
    r = start_result(q, np.arange(2, dtype=np.int32), np.eye(3), t)
    return r.replace(success=np.bool_(success), fallback=np.bool_(not success),
                     n_inliers=np.int32(n_inliers), n_matches=np.int32(100),
                     n_inliers_first=np.int32(n_inliers), n_rendered=np.int32(rendered),
                     inlier_coverage=np.float32(0.6))


@pytest.mark.parametrize("outcomes, retries, want_calls, want_kept", [
    # uncertain, failed, localized: stop there, keep the localized one
    ([(20, 10, True), (0, 7, False), (80, 5, True), (90, 3, True)], 3, [0, 5, 10], 2),
    # never localized: every attempt made, the most confident kept (the first)
    ([(20, 10, True), (0, 7, False), (12, 5, True)], 3, [0, 5, 10], 0),
    # localized at once: no retry
    ([(80, 10, True), (90, 7, True)], 3, [0], 0),
    # no retries configured
    ([(20, 10, True), (90, 7, True)], 0, [0], 0),
])
def test_retries_keep_the_most_confident_and_stop_once_localized(outcomes, retries,
                                                                  want_calls, want_kept):
    # the hand-made outcomes' verdicts: localized from 30 inliers, failed without a pose
    for n, rendered, ok in outcomes:
        want = "failed" if not ok else "localized" if n >= 30 else "uncertain"
        assert one_confidence(_result(n, rendered, ok), 1.0)[1] == want
    cfg = localize.get_config("test", top_k=5, retries=retries)
    calls = []

    def once(c):
        calls.append(c.retrieval_offset)
        assert c is cfg or c.retries == 0
        return _result(*outcomes[c.retrieval_offset // 5])

    r, kept = localize_with_retries(_stub_map(5 * len(outcomes)), None, cfg, once, scale=1.0)
    assert calls == want_calls and kept == want_kept
    assert int(r.n_inliers) == outcomes[want_kept][0]
    assert int(r.n_rendered) == sum(outcomes[c // 5][1] for c in calls)  # every attempt's


def test_attempt_shift_is_the_distance_to_the_farthest_other_pose():
    kept = _result(80, 1, centre=(1.0, 2.0, 3.0))
    others = [_result(20, 1, centre=(1.0, 2.0, 4.0)), _result(0, 1, False, centre=(9, 9, 9)),
              _result(25, 1, centre=(4.0, 6.0, 3.0))]
    assert attempt_shift(kept, others) == pytest.approx(5.0, abs=1e-5)  # 3-4-5; no failed one
    assert np.isnan(attempt_shift(kept, others[1:2]))  # no other PnP pose: unknown
    assert np.isnan(attempt_shift(kept, []))


@pytest.mark.parametrize("first_centre, first_ok, want_verdict", [
    ((0.0, 0.0, -1.0 + 0.04), True, "localized"),  # attempts agree within 4% of the scale
    ((0.0, 0.0, -1.0 + 0.06), True, "uncertain"),  # 6% apart: not both right
    ((5.0, 0.0, 0.0), False, "localized"),  # the first attempt had no pose: nothing to check
])
def test_a_kept_retry_whose_attempts_disagree_is_uncertain(first_centre, first_ok,
                                                           want_verdict):
    """A doubtful first attempt, then a confident retry: the retry is kept, and its verdict
    is localized only if the two poses agree within max_attempt_shift (5% of the scale)."""
    outcomes = [_result(20, 10, first_ok, first_centre), _result(80, 5)]
    cfg = localize.get_config("test", top_k=5, retries=1)
    r, kept = localize_with_retries(_stub_map(10), None, cfg,
                                    lambda c: outcomes[c.retrieval_offset // 5], scale=1.0)
    assert kept == 1 and int(r.n_inliers) == 80
    want_shift = np.linalg.norm(np.subtract(first_centre, (0.0, 0.0, -1.0)))
    if first_ok:
        assert float(r.attempt_shift) == pytest.approx(want_shift, abs=1e-5)
    else:
        assert np.isnan(float(r.attempt_shift))
    assert one_confidence(r, 1.0)[1] == want_verdict
    assert ConfidenceConfig().max_attempt_shift == 0.05


@pytest.fixture(scope="module")
def loaded(tiny_map, small_synthetic_scene):
    return maps.load_map(tiny_map), load_scene("7scenes", small_synthetic_scene).queries()


def test_localize_scene_retries_doubtful_queries_with_the_next_references(loaded):
    """With an inlier threshold no pose reaches, every query is doubtful: each is tried again
    with the next top_k references (the tiny map has 24), and the pose kept is that of the
    more confident attempt, the same as localizing with that attempt's references directly."""
    m, queries = loaded
    strict = ConfidenceConfig(min_inliers=10_000)
    cfg = localize.get_config("test", source="real", retries=1, confidence=strict)
    results, info = localize_scene(m, queries, cfg, progress=False, timed=False)
    assert set(info["retried"]) == set(queries.names)
    assert all(v["attempts"] == 2 for v in info["retried"].values())
    one = dataclasses.replace(cfg, retries=0)
    direct = {a: localize_scene(m, queries, attempt_config(one, a), progress=False,
                                timed=False)[0] for a in (0, 1)}
    scale = map_scale(m)
    for i, name in enumerate(queries.names):
        c0, c1 = (one_confidence(direct[a][i], scale, strict)[0] for a in (0, 1))
        a = info["retried"][name]["kept"]
        assert a == (1 if c1 > c0 else 0), (name, c0, c1)  # the more confident, first on ties
        np.testing.assert_allclose(results[i].t, direct[a][i].t, atol=1e-5)
        np.testing.assert_array_equal(results[i].retrieved, direct[a][i].retrieved)
        other = direct[1 - a][i]  # the attempt not kept: its pose's distance, or none
        want = (np.linalg.norm(camera_center(results[i].R, results[i].t)
                               - camera_center(other.R, other.t))
                if bool(other.success) and not bool(other.fallback) else np.nan)
        np.testing.assert_allclose(float(results[i].attempt_shift), want, atol=1e-4)
        assert not set(np.asarray(direct[0][i].retrieved).tolist()) & set(
            np.asarray(direct[1][i].retrieved).tolist())  # the next references, not the same
    _, info0 = localize_scene(m, queries, one, progress=False, timed=False)
    assert info0["retried"] == {}  # retries off: one attempt each, nothing recorded
