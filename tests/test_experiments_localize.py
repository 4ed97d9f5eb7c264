"""experiments.localize with --images/--queries (an hloc query list), and the run record
(run.json) every experiment writes."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from vrs_jax import maps
from vrs_jax.cli import evaluate as evaluate_cli
from vrs_jax.cli import localize as cli
from vrs_jax.cli import make_synthetic
from vrs_jax.data.readers import load_scene
from vrs_jax.errors import VrsError
from vrs_jax.eval.results import read_results
from vrs_jax.runrecord import RECORD_FORMAT


def _query_list(path, scene, idx):
    """Two lines: PINHOLE for the first query, SIMPLE_RADIAL (k1 = 0) for the second."""
    lines = ["# image_name MODEL width height params"]
    for j, i in enumerate(idx):
        K = scene.K[i]
        w, h = (int(s) for s in scene.sizes[i])
        if j % 2 == 0:
            params = [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
            model = "PINHOLE"
        else:
            assert K[0, 0] == pytest.approx(K[1, 1])
            params = [K[0, 0], K[0, 2], K[1, 2], 0.0]
            model = "SIMPLE_RADIAL"
        lines.append(f"{scene.names[i]} {model} {w} {h} " + " ".join(f"{p:.10g}" for p in params))
    path.write_text("\n".join(lines) + "\n")
    return path


def _record(folder):
    rec = json.loads((folder / "run.json").read_text())
    assert rec["format"] == RECORD_FORMAT
    return rec


def test_localize_query_list_and_run_records(tiny_map, small_synthetic_scene, tmp_path):
    queries = load_scene("7scenes", small_synthetic_scene).queries()
    qlist = _query_list(tmp_path / "queries_with_intrinsics.txt", queries, [3, 0])
    out = tmp_path / "run"
    rc = cli.main(["--map", str(tiny_map), "--images", str(small_synthetic_scene), "--queries",
                   str(qlist), "--out", str(out), "--config", "test", "--mode", "real",
                   "--quiet", "--no-timing"])
    assert rc == 0
    names = [queries.names[3], queries.names[0]]
    res = read_results(out / "results.txt")
    assert list(res) == names  # exactly the list's names, in its order
    s = json.loads((out / "summary.json").read_text())
    assert s["recall"] is None and s["n_with_ground_truth"] == 0 and s["n_queries"] == 2
    # no guided pass here: the inlier ratio is RANSAC's over all matches, which the
    # thresholds (measured with one) may call uncertain; a PnP pose is never failed
    assert s["n_localized"] + s["n_uncertain"] == 2 and s["n_failed"] == 0
    assert [p["name"] for p in s["per_query"]] == names
    for p in s["per_query"]:
        assert set(p) == {"name", "success", "fallback", "inliers", "matches", "error",
                          "inlier_coverage", "inlier_ray_angle_deg", "inlier_depth_spread",
                          "inlier_centre_std", "centre_std_first", "attempt_shift", "confidence",
                          "verdict"}
        assert p["success"] and p["error"] is None and p["inliers"] >= 10
        assert p["verdict"] in ("localized", "uncertain") and 0 < p["confidence"] <= 1
        assert 0 < p["inlier_coverage"] <= 1 and p["inlier_ray_angle_deg"] > 0
    rec = _record(out)
    assert rec["config"]["config"]["source"] == "real"
    assert rec["config"]["args"]["queries"] == str(qlist) and rec["argv"][-1] == "--no-timing"

    # the poses are those of the dataset (the list's intrinsics are the scene's)
    ev = tmp_path / "eval"
    ev.mkdir()
    assert evaluate_cli.main(["--results", str(out / "results.txt"), "--format", "7scenes",
                              "--root", str(small_synthetic_scene), "--json",
                              str(ev / "eval.json")]) == 0
    doc = json.loads((ev / "eval.json").read_text())
    assert all(doc["per_query"][n]["t_cm"] < 5 for n in names)  # the others: no result
    assert _record(ev)["config"]["args"]["fmt"] == "7scenes"


def test_localize_query_list_refusals(tiny_map, small_synthetic_scene, tmp_path, capsys):
    m = maps.load_map(tiny_map, descriptors=False)
    scene = load_scene("7scenes", small_synthetic_scene)
    ref = int(np.flatnonzero(~scene.is_query)[0])
    assert scene.names[ref] in m.names
    qlist = _query_list(tmp_path / "q.txt", scene, [ref])
    base = ["--map", str(tiny_map), "--out", str(tmp_path / "o"), "--quiet"]
    assert cli.main(base + ["--images", str(small_synthetic_scene), "--queries",
                            str(qlist)]) == 2
    assert "map images" in capsys.readouterr().err
    assert cli.main(base + ["--images", str(small_synthetic_scene), "--queries", str(qlist),
                            "--format", "7scenes", "--root", str(small_synthetic_scene)]) == 2
    assert "exclusive" in capsys.readouterr().err
    assert cli.main(base + ["--queries", str(qlist)]) == 2
    assert "--images" in capsys.readouterr().err
    # the same name in another folder is another photo: not refused
    one = scene.subset(np.array([ref]))
    other = dataclasses.replace(one, root=tmp_path, image_paths=[tmp_path / scene.names[ref]])
    cli.refuse_map_images(m, other)
    with pytest.raises(VrsError, match="map images"):
        cli.refuse_map_images(m, one)


def test_make_synthetic_writes_run_record(tmp_path):
    out = tmp_path / "scene"
    assert make_synthetic.main(["--out", str(out), "--size", "32x24", "--n-ref", "2",
                                "--n-query", "1"]) == 0
    rec = _record(out)
    assert rec["config"]["config"]["width"] == 32 and rec["config"]["args"]["n_ref"] == 2
    assert rec["timings_s"]["total"] > 0


def test_photos_to_map_to_results_in_two_commands(tmp_path):
    """README: a folder of unposed photos -> a map (SfM, EGM, NeRF) -> localized held-out
    photos, with the map's own SfM frame reused by localize."""
    from conftest import shared_path

    from vrs_jax import maps
    from vrs_jax.cli import localize as loc_cli
    from vrs_jax.cli import train as train_cli
    from vrs_jax.eval.results import read_results

    photos = shared_path("hloc_sacre_coeur", "datasets", "sacre_coeur", "mapping")
    out = tmp_path / "map"
    assert train_cli.main(["--format", "images", "--root", str(photos), "--query-every", "5",
                           "--out", str(out), "--config", "test", "--steps", "20",
                           "--quiet"]) == 0
    m = maps.load_map(out, descriptors=False)
    assert m.source.format == "images" and len(m.source.query_names) == 2
    assert loc_cli.main(["--map", str(out), "--out", str(tmp_path / "loc"), "--config", "test",
                         "--mode", "real", "--quiet"]) == 0
    res = read_results(tmp_path / "loc" / "results.txt")
    assert sorted(res) == sorted(m.source.query_names)
    assert not (tmp_path / "loc" / "sfm").exists()  # the map's SfM was reused


def test_localize_sequence_tracks_the_stream(tiny_map, stream_scene, tmp_path):
    """--sequence: the queries in name order tracked; results.txt as for single images, each
    query's summary says whether it was tracked, with its confidence and latency."""
    out = tmp_path / "seq"
    assert cli.main(["--map", str(tiny_map), "--format", "7scenes", "--root",
                     str(stream_scene), "--sequence", "--config", "test", "--out", str(out),
                     "--quiet"]) == 0
    names = list(read_results(out / "results.txt"))
    assert names == sorted(load_scene("7scenes", stream_scene).queries().names)
    s = json.loads((out / "summary.json").read_text())
    pq = s["per_query"]
    assert not pq[0]["tracked"] and sum(p["tracked"] for p in pq) >= len(pq) - 3
    assert all(p["latency_s"] > 0 and 0 <= p["confidence"] <= 1 for p in pq)
    assert s["tracking"]["n_tracked"] == sum(p["tracked"] for p in pq)
    assert s["tracking"]["n_by_check"] == sum(p["by_check"] for p in pq)
    assert s["tracking"]["n_by_frame"] == sum(p["by_frame"] for p in pq)
    assert s["tracking"]["descriptor_cache"] is None  # the test config keeps no stream cache
    assert s["recall"]["5cm_5deg"] >= 0.75
    assert cli.main(["--map", str(tiny_map), "--format", "7scenes", "--root",
                     str(stream_scene), "--sequence", "--report", "--config", "test", "--out",
                     str(tmp_path / "r"), "--quiet"]) == 2  # one line: not with --sequence
