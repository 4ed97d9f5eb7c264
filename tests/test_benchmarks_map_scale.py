"""The map-size scale series (benchmarks/map_scale.py, via ``benchmarks.map_size --series``)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from benchmarks import map_scale, map_size
from vrs_jax import maps
from vrs_jax.errors import VrsError
from vrs_jax.nerf import ilm as ilm_lib


@pytest.fixture(scope="module")
def series(tmp_path_factory):
    """The series on 1, 2 and 3 rooms at 64x48, 6 references per room, test config, EGM
    only (~30 s on 2 idle cores)."""
    d = tmp_path_factory.mktemp("series")
    out = d / "series.json"
    png = d / "series.png"
    argv = ["--series", "1,2,3", "--series-size", "64x48", "--series-refs", "6",
            "--series-queries", "1", "--series-real", "", "--config", "test", "--work",
            str(d / "work"), "--json", str(out), "--plot", str(png), "--quiet"]
    assert map_size.main(argv) == 0
    return json.loads(out.read_text()), png


def test_series_bytes_are_the_files_on_disk(series):
    doc, png = series
    rows = doc["series"]["rows"]
    assert [r["scene"] for r in rows] == ["rooms1", "rooms2", "rooms3"]
    assert [r["images"] for r in rows] == [6, 12, 18]
    assert png.is_file() and png.stat().st_size > 10_000
    for r in rows:
        assert set(r["vrs"]) == {"one", "paper", "per_room"}
        assert r["vrs"]["per_room"]["clusters"] == r["rooms"]
        for v in r["vrs"].values():
            folder = Path(v["folder"])
            on_disk = {n: (folder / n).stat().st_size for n in ("map.json", "egm.npz",
                                                                  "ilm.npz")}
            assert v["files"] == on_disk
            assert v["metadata"] == on_disk["map.json"]
            assert v["egm"] == on_disk["egm.npz"]
            # the EGM saved again after a load: its int8 global descriptors' per-row scales
            # may move by one float32 ulp (a re-quantisation), a few bytes at most
            assert abs(v["egm"] - r["egm"]) <= 16
            assert v["ilm"] == on_disk["ilm.npz"]
            assert v["total"] == sum(on_disk.values())
            assert v["ratio_float16"] == pytest.approx(r["descriptor_maps"]["float16"]
                                                       / v["total"])
            # an untrained map is measured, never loaded as a map
            with pytest.raises(VrsError, match="never trained"):
                maps.load_map(folder)
        # descriptor maps of the same EGM, counted by map_size's one rule
        egm_dir = Path(r["egm_dir"])
        b = maps.map_bytes(egm_dir)
        assert r["descriptor_maps"] == map_size.descriptor_maps(b, r["kept_keypoints"], 128)
        assert r["descriptor_maps"]["float16"] == sum(
            (egm_dir / n).stat().st_size for n in ("map.json", "egm.npz", "descriptors.npz"))
        assert sum(r["egm_parts"].values()) == r["egm"]
    # more clusters, more NeRF bytes, the same EGM
    r3 = rows[2]["vrs"]
    assert r3["per_room"]["ilm"] > r3["one"]["ilm"]
    per = (r3["per_room"]["ilm"] - r3["one"]["ilm"]) / 2
    assert rows[1]["vrs"]["per_room"]["ilm"] - rows[1]["vrs"]["one"]["ilm"] == pytest.approx(
        per, rel=1e-3)


def test_fit_error_is_computed_from_the_measured_points(series):
    doc, _ = series
    rows, fit = doc["series"]["rows"], doc["series"]["fit"]
    assert fit["scenes"] == [r["scene"] for r in rows]
    for r, e in zip(rows, fit["errors"], strict=True):
        pred = (fit["c_bytes"] + fit["a_bytes_per_image"] * r["images"]
                + fit["b_bytes_per_keypoint"] * r["kept_keypoints"])
        assert e == pytest.approx(pred / r["egm"] - 1.0, abs=1e-9)
    assert fit["max_abs_error"] == pytest.approx(max(abs(e) for e in fit["errors"]))
    large = {(r["scene"], r["config"]): r for r in doc["series"]["large"]}
    assert all(r["label"] == "fit" for r in large.values())
    assert large[("7scenes chess", "test")]["images"] == 4000


def _row(i, n, k, scale=1.0):
    parts = {"poses+intrinsics": 50 * n, "global descriptors": 1000 + 250 * n,
             "keypoints": 3 * k, "links": 2 * k, "points3d": 2 * k, "container": 4000}
    parts = {p: v * scale for p, v in parts.items()}
    return {"scene": f"s{i}", "images": n, "kept_keypoints": k, "egm_parts": parts,
            "egm": sum(parts.values())}


def test_fit_recovers_a_linear_law_and_reports_a_misfit():
    sizes = [(10, 2000), (40, 7000), (160, 30000), (640, 110000)]
    rows = [_row(i, n, k) for i, (n, k) in enumerate(sizes)]
    fit = map_scale.fit_egm(rows)
    assert fit["c_bytes"] == pytest.approx(5000, rel=1e-6)
    assert fit["a_bytes_per_image"] == pytest.approx(300, rel=1e-6)
    assert fit["b_bytes_per_keypoint"] == pytest.approx(7, rel=1e-6)
    assert fit["max_abs_error"] < 1e-9 and abs(fit["holdout"]["error"]) < 1e-9
    rows[-1] = _row(3, *sizes[-1], scale=1.5)  # the largest point off the law: both see it
    bad = map_scale.fit_egm(rows)
    assert bad["max_abs_error"] > 0.01
    assert bad["holdout"]["scene"] == "s3" and bad["holdout"]["error"] == pytest.approx(
        1 / 1.5 - 1, rel=1e-6)
    with pytest.raises(VrsError):
        map_scale.fit_egm(rows[:2])


def test_untrained_ilm_has_the_trained_shapes():
    cfg = dataclasses.replace(maps.get_config("test").nerf, n_clusters=2)
    names = tuple(f"im{i}.png" for i in range(5))
    centers = np.array([[0, 0, 0], [0.1, 0, 0], [0.2, 0, 0], [5, 0, 0], [5.1, 0, 0]], float)
    ilm = ilm_lib.untrained(cfg, names, centers)
    back = ilm_lib.from_bytes(ilm_lib.to_bytes(ilm, float16=True), Path("x"))
    assert back.n_clusters == 2 and back.image_names == names
    assert sorted(np.asarray(back.image_cluster).tolist()) == [0, 0, 0, 1, 1]
    assert np.asarray(back.membership).shape == (2, 5)


def test_cluster_counts():
    assert map_scale.cluster_counts(16, 1) == {"one": 1, "paper": 1, "per_room": 1}
    assert map_scale.cluster_counts(1024, 64) == {"one": 1, "paper": 4, "per_room": 64}
    assert map_scale.cluster_counts(271, None) == {"one": 1, "paper": 1}


def test_real_series_scene_carries_its_split(tmp_path):
    """The phone walk's series point: its reader options are the split (every 10th frame a
    query), whether its EGM folder is given or built from the data (a SceneSpec built with
    positional fields once read a missing attribute here and the series crashed after its
    synthetic scenes)."""
    from benchmarks import common

    args = map_size.build_parser().parse_args(
        ["--series", "", "--series-real", "phone_walk", "--series-egm",
         f"phone_walk={tmp_path / 'egm'}", "--work", str(tmp_path / "work")])
    (given,) = map_scale.series_scenes(args, log=lambda s: None)
    assert given.given and given.scene is None and given.source_options == {"query_every": 10}
    root = common.default_data_root() / "phone_walk"
    if not root.exists():
        pytest.skip(f"phone walk data not found at {root}")
    args = map_size.build_parser().parse_args(
        ["--series", "", "--series-real", "phone_walk", "--work", str(tmp_path / "work")])
    (built,) = map_scale.series_scenes(args, log=lambda s: None)
    assert not built.given and built.source_options == {"query_every": 10}
    n = len(built.scene)
    assert n > 250 and int(np.sum(~np.asarray(built.scene.is_query, bool))) < n
