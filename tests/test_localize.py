"""localize(params, egm, query): end to end on a tiny map, compile-once, batching, failures."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from vrs_jax import geometry, pipeline
from vrs_jax.data.images import read_gray
from vrs_jax.data.readers import load_scene
from vrs_jax.errors import VrsError
from vrs_jax.localize.localize import localize
from vrs_jax.localize.query import prepare_query, stack_queries


@pytest.fixture(scope="module")
def loaded(tiny_map, small_synthetic_scene):
    m = pipeline.load_map(tiny_map)
    queries = load_scene("7scenes", small_synthetic_scene).queries()
    return m, queries


def _query(m, queries, i, cfg):
    size = tuple(int(s) for s in queries.sizes[i])
    return prepare_query(read_gray(queries.image_paths[i], size=size), queries.K[i],
                         queries.dist[i], m.egm.vocab, cfg)


def test_gt_mode_localizes_the_synthetic_queries(loaded, tiny_map):
    m, queries = loaded
    cfg = pipeline.localize_config(m.pcfg, m.egm_cfg, "gt")
    results, info = pipeline.localize_queries(m, queries, cfg, progress=False)
    s = pipeline.summarize(queries, results, info, m, cfg, tiny_map)
    assert s["n_queries"] == len(queries)
    assert s["recall"]["5cm_5deg"] >= 0.75, s
    assert s["map_bytes"]["total"] == s["map_bytes"]["egm"] > 0
    assert set(s["timing_s"]) >= {"retrieval", "matching", "ransac", "refinement"}


def test_render_mode_runs_and_compiles_once(loaded):
    m, queries = loaded
    cfg = pipeline.localize_config(m.pcfg, m.egm_cfg, "render")
    egm = m.egm.without_local_descriptors()
    before = localize._cache_size()
    outs = [localize(m.ilm, egm, _query(m, queries, i, cfg), cfg=cfg) for i in range(3)]
    assert localize._cache_size() == before + 1  # one compilation for all queries
    for r in outs:
        assert np.all(np.isfinite(np.asarray(r.R))) and np.all(np.isfinite(np.asarray(r.t)))
        assert bool(r.success) != bool(r.fallback)
        assert int(r.n_matches) >= int(r.n_inliers)


def test_vmap_over_queries_matches_single_calls(loaded):
    m, queries = loaded
    cfg = pipeline.localize_config(m.pcfg, m.egm_cfg, "gt")
    qs = [_query(m, queries, i, cfg) for i in range(2)]
    single = [localize(None, m.egm, q, cfg=cfg) for q in qs]
    batched = jax.vmap(lambda q: localize(None, m.egm, q, cfg=cfg))(stack_queries(qs))
    for i, r in enumerate(single):
        np.testing.assert_array_equal(np.asarray(batched.retrieved[i]), np.asarray(r.retrieved))
        np.testing.assert_allclose(np.asarray(batched.t[i]), np.asarray(r.t), atol=1e-3)


def test_query_without_keypoints_falls_back_to_top1_reference(loaded):
    m, queries = loaded
    cfg = pipeline.localize_config(m.pcfg, m.egm_cfg, "render")
    blank = np.full((int(queries.sizes[0, 1]), int(queries.sizes[0, 0])), 0.5, np.float32)
    q = prepare_query(blank, queries.K[0], None, m.egm.vocab, cfg)
    assert not np.asarray(q.mask).any()
    r = localize(m.ilm, m.egm.without_local_descriptors(), q, cfg=cfg)
    assert bool(r.fallback) and not bool(r.success) and int(r.n_matches) == 0
    top1 = int(r.retrieved[0])
    np.testing.assert_allclose(np.asarray(r.R), np.asarray(m.egm.R[top1]))
    np.testing.assert_allclose(np.asarray(r.t), np.asarray(m.egm.t[top1]))


def test_localize_cli_writes_results_and_summary(tiny_map, small_synthetic_scene, tmp_path):
    from experiments import localize as cli
    from vrs_jax.eval.results import read_results

    out = tmp_path / "loc"
    rc = cli.main(["--map", str(tiny_map), "--format", "7scenes", "--root",
                   str(small_synthetic_scene), "--out", str(out), "--mode", "gt", "--quiet"])
    assert rc == 0
    res = read_results(out / "results.txt")
    queries = load_scene("7scenes", small_synthetic_scene).queries()
    assert sorted(res) == sorted(queries.names)
    s = json.loads((out / "summary.json").read_text())
    for key in ("n_queries", "median_t_cm", "median_R_deg", "recall", "map_bytes", "timing_s",
                "rays_per_query", "nerf_evals_per_query", "mode", "config"):
        assert key in s
    assert set(s["recall"]) == {"1cm_1deg", "2cm_2deg", "3cm_3deg", "5cm_5deg", "10cm_5deg",
                                "25cm_2deg", "50cm_5deg", "500cm_10deg"}
    assert set(s["map_bytes"]) == {"egm", "ilm", "total"}
    # the written poses are the localized ones: errors agree with the summary's median
    dt = [geometry.pose_errors(*res[n], queries.R[i], queries.t[i])[0]
          for i, n in enumerate(queries.names)]
    assert np.median(dt) * 100 == pytest.approx(s["median_t_cm"], rel=1e-3, abs=1e-3)


def test_missing_and_wrong_version_maps_give_one_line_errors(tiny_map, tmp_path, capsys):
    from experiments import localize as cli

    with pytest.raises(VrsError, match="map folder not found"):
        pipeline.load_map(tmp_path / "nope")
    bad = tmp_path / "bad"
    bad.mkdir()
    meta = json.loads((tiny_map / "map.json").read_text())
    meta["format_version"] = 999
    (bad / "map.json").write_text(json.dumps(meta))
    with pytest.raises(VrsError, match="format version 999"):
        pipeline.load_map(bad)
    rc = cli.main(["--map", str(bad), "--format", "7scenes", "--root", str(tmp_path),
                   "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "format version 999" in err[0]
