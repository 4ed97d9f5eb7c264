"""Smoke tests of the benchmarks on the tiny synthetic map: JSON keys, finite, consistent data."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from benchmarks import ablation, common, figures, localize, map_size, render
from vrs_jax import maps
from vrs_jax.features.patches import PatchConfig, extract_patches, patch_grid

ENV_KEYS = {"benchmark", "time_utc", "command", "machine", "device", "versions", "code", "args"}


@pytest.fixture(scope="module")
def base(tiny_map, tmp_path_factory):
    """Arguments shared by the benchmark runs: the tiny map, a shared work folder."""
    work = tmp_path_factory.mktemp("bench_work")
    return ["--map", f"synthetic={tiny_map}", "--work", str(work), "--max-queries", "2",
            "--quiet"]


@pytest.fixture(scope="module")
def loaded(tiny_map):
    return maps.load_map(tiny_map)


@pytest.fixture(scope="module")
def localize_json(base, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_json") / "localize.json"
    assert localize.main(base + ["--scenes", "synthetic", "--json", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def localize_doc(localize_json):
    return json.loads(localize_json.read_text())


def _finite(*xs):
    return all(x is not None and math.isfinite(float(x)) for x in xs)


def test_localize_benchmark_json(localize_doc, loaded):
    doc = localize_doc
    assert ENV_KEYS <= set(doc) and doc["benchmark"] == "localize"
    assert doc["versions"]["jax"] and doc["machine"]["cpu_count"] >= 1
    assert [r["mode"] for r in doc["rows"]] == ["render", "real", "sift"]
    for r in doc["rows"]:  # every recall with its bootstrap interval around it
        for key, value in r["recall_relative"].items():
            lo, hi = r["recall_relative_interval"][key]
            assert lo <= value <= hi
        lo, hi = r["recall_interval"]["5cm_5deg"]
        assert lo <= r["recall"]["5cm_5deg"] <= hi
    egm = loaded.egm
    sift = doc["rows"][2]
    assert sift["n_queries"] == 2 and sift["map_bytes"]["total"] > 0
    for r in doc["rows"][:2]:
        assert r["n_queries"] == 2 and len(r["per_query"]["t_err_m"]) == 2
        assert set(r["recall"]) >= {"5cm_5deg", "2cm_2deg", "25cm_2deg"}
        assert all(0.0 <= v <= 1.0 for v in r["recall"].values())
        assert _finite(r["localize_s_per_query"]) and r["localize_s_per_query"] > 0
        assert all(_finite(r["timing_s"][k]) for k in ("retrieval", "matching", "ransac"))
        cfg = r["localize_config"]
        if r["mode"] == "render":  # depth-guided
            # rays per query = mean patches rendered x P^2 (the test config renders every
            # sample of the k retrieved images' valid keypoints: no early exit, no guided pass)
            rendered = np.asarray(r["per_query"]["rendered"])
            top = np.sort(np.asarray(egm.kp_mask).sum(1))[::-1][:cfg["top_k"]].sum()
            assert np.all((rendered > 0) & (rendered <= top))
            expect = rendered.mean() * r["patch_size"] ** 2
            assert r["rays_per_query"] == pytest.approx(expect)
            assert 0 < r["nerf_evals_per_query"] < r["full_image_evals_per_query"]
            assert r["nerf_evals_per_query"] == pytest.approx(
                expect * (cfg["narrow_samples"] + cfg["narrow_fine"]))
            assert r["nerf_evals_per_query_median"] == pytest.approx(
                np.median(rendered) * r["patch_size"] ** 2
                * (cfg["narrow_samples"] + cfg["narrow_fine"]))
            assert r["timing_s"]["render"] > 0
        elif r["mode"] == "real":
            assert r["rays_per_query"] == 0 and r["timing_s"]["render"] == 0
            assert r["map_bytes"]["total"] > r["map_bytes"]["descriptors"] > 0
            assert r["map_bytes"]["ilm"] == 0
    # the baseline localizes the easy synthetic queries (real patches)
    assert _finite(doc["rows"][1]["median_t_cm"]) and doc["rows"][1]["median_t_cm"] < 5
    assert doc["maps"]["synthetic"]["n_queries_used"] == 2
    from vrs_jax.localize.confidence import VERDICTS

    for r in doc["rows"][:2]:  # each query's verdict and the evidence it was read from
        pq = r["per_query"]
        assert all(v in VERDICTS for v in pq["verdict"]) and len(pq["verdict"]) == 2
        for k in ("confidence", "inlier_ratio", "coverage", "pass_shift", "pass_rotation",
                  "guided_ratio", "n_inliers"):
            assert len(pq[k]) == 2, k
        for v, c, ok in zip(pq["verdict"], pq["confidence"], pq["success"], strict=True):
            assert (v == "localized") == (c >= 0.5) and (v == "failed") == (not ok)


def test_guided_runs_report_their_first_pass(base, tmp_path):
    """A config with a guided pass: the run's summary carries the first pass's poses,
    errors and inliers (no guided time), and localize rows get a "pass 1" twin."""
    from benchmarks import common

    args = localize.build_parser().parse_args(base + ["--scenes", "synthetic"])
    ctx = common.prepare_scene("synthetic", args, log=lambda s: None)
    cfg = common.localize_cfg(ctx, "real", guided_passes=1)
    s = common.localize_run(ctx, cfg, tmp_path, progress=False, log=lambda s: None)
    first = s["first_pass"]
    assert first["timing_s"]["guided"] == 0 and s["timing_s"]["guided"] > 0
    assert len(first["per_query"]["t_err_m"]) == len(s["per_query"]["t_err_m"]) == 2
    for a, b in zip(first["per_query"]["inliers"], s["per_query"]["inliers"], strict=True):
        assert b >= a  # the guided pass is kept only with at least as many inliers
    again = common.localize_run(ctx, cfg, tmp_path, progress=False, log=lambda s: None)
    assert again["reused"] and again["first_pass"]["per_query"] == first["per_query"]


def test_repeated_runs_report_the_median_time_of_each_stage(base, tmp_path, capsys):
    """--repeat 3: a row's stage times are the medians of its three runs (kept in the row),
    its accuracy the first run's, and the runs gave the same poses (real patches: the render
    rows take the same path, and the benchmark's other test covers their keys)."""
    out = tmp_path / "rep.json"
    assert localize.main(base + ["--scenes", "synthetic", "--modes", "real",
                                 "--repeat", "3", "--json", str(out)]) == 0
    assert "every run gave the same poses" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert [r["mode"] for r in doc["rows"]] == ["real"]
    for r in doc["rows"]:
        rep = r["repeats"]
        assert rep["n"] == 3 and rep["same_poses"] and len(rep["timing_s"]) == 3
        for k in ("matching", "ransac", "query_preparation"):
            assert r["timing_s"][k] == pytest.approx(
                float(np.median([t[k] for t in rep["timing_s"]])))
        assert r["localize_s_per_query"] == pytest.approx(
            sum(r["timing_s"][k] or 0.0 for k in localize.STAGES))
        assert len(rep["localize_s_per_query"]) == 3
    assert localize.main(base + ["--scenes", "synthetic", "--repeat", "0", "--json",
                                 str(tmp_path / "x.json")]) == 2


def test_seed_spread_over_hand_made_errors():
    """The recall of each seed, its range and mean, computed by hand: scale 2 m, so 1% is
    2 cm; seed 0 gets one of two queries within 1% / 1 deg, seed 1 both, seed 2 none (a
    failure reads inf / 180 deg)."""
    inf = float("inf")
    runs = [{"per_query": {"t_err_m": t, "R_err_deg": r}} for t, r in (
        ([0.01, 0.03], [0.5, 0.5]), ([0.01, 0.019], [0.5, 0.9]), ([inf, 0.05], [180.0, 1.5]))]
    sp = localize.seed_spread(runs, 2.0)
    assert sp["n"] == 3
    assert sp["recall_relative"]["1pct_1deg"] == [0.5, 1.0, 0.0]
    assert sp["recall_relative"]["2pct_2deg"] == [1.0, 1.0, 0.0]
    assert (sp["min"]["1pct_1deg"], sp["max"]["1pct_1deg"]) == (0.0, 1.0)
    assert sp["mean"]["1pct_1deg"] == pytest.approx(0.5)
    assert sp["median_t_rel"][:2] == pytest.approx([0.01, 0.00725])
    cfg = localize.with_seed(__import__("vrs_jax").localize.get_config("cpu-small"), 7)
    assert cfg.pnp.seed == 7 and cfg.pnp.threshold_px == 6.0


def test_seeds_rerun_the_rows_with_other_ransac_seeds(base, tmp_path, capsys):
    """--seeds 2: each row keeps its seed-0 accuracy and carries both seeds' recall, the
    first equal to the row's own; the table is printed; --seeds 0 is refused."""
    out = tmp_path / "seeds.json"
    assert localize.main(base + ["--scenes", "synthetic", "--modes", "real", "--seeds", "2",
                                 "--json", str(out)]) == 0
    assert "Recall over RANSAC seeds" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    for r in doc["rows"]:
        sp = r["seeds"]
        assert sp["n"] == 2 and len(sp["per_query"]) == 2
        assert sp["per_query"][0]["t_err_m"] == r["per_query"]["t_err_m"]
        for k in localize.SEED_KEYS:
            assert sp["recall_relative"][k][0] == r["recall_relative"][k]
            assert sp["min"][k] <= sp["mean"][k] <= sp["max"][k]
    assert localize.main(base + ["--scenes", "synthetic", "--seeds", "0", "--json",
                                 str(tmp_path / "x.json")]) == 2


def test_ablation_reuses_the_localize_runs(base, localize_doc, tmp_path):
    # (other patch sizes run the same code path as the localize benchmark's fresh runs; the
    # render benchmark test covers a P other than the map's)
    out = tmp_path / "ablation.json"
    assert ablation.main(base + ["--scenes", "synthetic", "--sizes", "9",
                                 "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    rows = {r["method"]: r for r in doc["rows"]}
    assert list(rows) == ["render 9x9", "real 9x9 (GT)"]
    # the map's P (9 in the test config) and real rows are the localize benchmark's runs
    assert rows["render 9x9"]["reused"] and rows["real 9x9 (GT)"]["reused"]
    loc = {r["mode"]: r for r in localize_doc["rows"]}
    for method, mode in (("render 9x9", "render"), ("real 9x9 (GT)", "real")):
        assert rows[method]["record"] == loc[mode]["record"]
        assert rows[method]["recall"] == loc[mode]["recall"]
        assert rows[method]["rays_per_query"] == loc[mode]["rays_per_query"]
    assert rows["render 9x9"]["render_s_per_query"] > 0
    assert rows["real 9x9 (GT)"]["render_s_per_query"] == 0


def test_map_size_parts_add_up(base, tiny_map, tmp_path):
    out = tmp_path / "map_size.json"
    assert map_size.main(base + ["--scenes", "synthetic", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    s = doc["sizes"]["synthetic"]
    d = tiny_map
    size = lambda n: (d / n).stat().st_size  # noqa: E731
    assert s["vrs"] == size("map.json") + size("egm.npz") + size("ilm.npz")
    assert s["descriptor_maps"]["float16"] == (size("map.json") + size("egm.npz")
                                               + size("descriptors.npz"))
    base_b = size("map.json") + size("egm.npz")
    dim = s["desc_dim"]
    assert s["descriptor_maps"]["uint8"] == base_b + s["n_keypoints"] * dim
    assert s["descriptor_maps"]["float32"] == base_b + 4 * s["n_keypoints"] * dim
    assert sum(s["egm_parts"].values()) == s["egm"]
    assert s["ratio"]["uint8"] == pytest.approx(s["descriptor_maps"]["uint8"] / s["vrs"])
    cfgs = {r["config"]: r for r in doc["nerf_configs"]}
    assert cfgs["paper"]["bytes_per_cluster"] == 2 * cfgs["paper"]["params"]  # float16
    # cpu-small's hash tables as int8 (a byte per entry, a float32 scale per level), its MLP
    # float16: fewer bytes than float16 throughout would take
    hg = cfgs["cpu-small"]
    assert hg["params"] < hg["bytes_per_cluster"] < 2 * hg["params"]
    assert min(cfgs["paper"]["params"], hg["params"]) > cfgs["test"]["params"]


def test_render_benchmark_counts(base, loaded, tmp_path):
    out = tmp_path / "render.json"
    assert render.main(base + ["--sizes", "11", "--samplers", "dg", "--sweep-keypoints", "8",
                               "--repeats", "1", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    s = doc["scenes"]["synthetic"]
    c = s["query_vs_full"]
    egm = loaded.egm
    idx = np.asarray(c["retrieved"])
    valid = np.asarray(egm.kp_mask)[idx].sum(1)
    P = c["patch_size"]
    assert c["valid_keypoints"] == valid.tolist()
    assert c["patch_rays"] == int(valid.sum()) * P * P
    assert c["full_image_pixels"] == int(np.prod(np.asarray(egm.sizes)[idx], axis=1).sum())
    assert c["fewer_rays_factor"] == pytest.approx(c["full_image_pixels"] / c["patch_rays"])
    assert 0 < c["literal_distinct_pixels"] <= c["patch_rays"]
    rows = {r["method"]: r for r in c["rows"]}
    dg, cf = rows["patches, depth-guided"], rows["patches, coarse+fine"]
    full = rows["full images, coarse+fine"]
    cfg = loaded.config.nerf
    assert cf["nerf_evals_per_ray"] == full["nerf_evals_per_ray"] == (
        cfg.num_samples_coarse + cfg.num_samples_fine)
    assert dg["nerf_evals"] == dg["rays"] * dg["nerf_evals_per_ray"]
    assert all(_finite(r["seconds"]) and r["seconds"] > 0 for r in c["rows"])
    assert len(s["sweep"]) == 1  # P = 11 (the map's is 9), depth-guided
    for r in s["sweep"]:
        assert r["patches_timed"] == min(8, int(valid[0]))
        assert r["patch_size"] == 11 and r["depth_guided"]
        assert r["rays_per_query"] == pytest.approx(
            s["localize_config"]["top_k"] * np.asarray(egm.kp_mask).sum(1).mean() * 121)
        assert _finite(r["ms_per_patch"], r["rays_per_s"]) and r["ms_per_patch"] > 0
        assert r["nerf_evals_per_s"] == pytest.approx(r["rays_per_s"] * r["nerf_evals_per_ray"])


def test_figures_written(base, localize_json, localize_doc, tmp_path):
    out = tmp_path / "fig"
    assert figures.main(base + ["--out", str(out), "--cluster-scenes", "synthetic",
                                "--views", "1", "--match-modes", "render,real",
                                "--localize-json", str(localize_json)]) == 0
    doc = json.loads((out / "figures.json").read_text())
    names = sorted(p.split("/")[-1] for p in doc["figures"])
    assert names == ["clusters_synthetic.png", "cumulative_errors.png",
                     "matches_synthetic.png", "matches_synthetic_real.png",
                     "render_vs_real_synthetic.png", "timing.png"]
    # the curves and the bars are the localize run's numbers
    rows = {r["mode"]: r for r in localize_doc["rows"]}
    for mode in ("render", "real", "sift"):
        got = doc["info"]["curves"][f"synthetic/{mode}"]
        assert got["n_queries"] == rows[mode]["n_queries"] == 2
        assert doc["info"]["timing"][f"synthetic / {mode}"]["total_s"] == pytest.approx(
            sum(v for v in rows[mode]["timing_s"].values() if v is not None))
    for p in doc["figures"]:
        img = cv2.imread(p)
        assert img is not None and img.shape[0] > 200 and img.shape[1] > 400
        assert img.std() > 10  # not blank
    info = doc["info"]
    assert info["matches_synthetic_real"]["inliers"] >= 12  # the baseline matches this query
    assert sum(info["clusters_synthetic"]["kmeans_counts"]) == 24
    assert sum(info["clusters_synthetic"]["grid_counts"]) == 24
    assert _finite(info["render_synthetic"]["views"][0]["psnr"])


def test_paste_patches_puts_literal_patches_back_exactly():
    rng = np.random.default_rng(0)
    img = rng.random((40, 50)).astype(np.float32)
    kp = np.array([[10.3, 12.7, 2.0, 0.3], [30.9, 20.1, 1.5, -1.0]], np.float32)
    cfg = PatchConfig(size=9, mode="literal")
    patches = np.asarray(extract_patches(img, kp, cfg))
    pos, _ = patch_grid(kp, cfg)
    out = figures.paste_patches(np.zeros((40, 50, 3), np.float32), patches, pos,
                                np.arange(2))
    for k in range(2):
        x0, y0 = (np.floor(pos[k, 0, 0]).astype(int))
        np.testing.assert_allclose(out[y0:y0 + 9, x0:x0 + 9, 0], img[y0:y0 + 9, x0:x0 + 9],
                                   atol=1e-5)
    assert out[0, 0, 0] == 0.0  # outside every patch: untouched


def test_paste_patches_follows_rotated_canonical_grid():
    # a smooth image: canonical patches read back and pasted land on the same values
    yy, xx = np.mgrid[0:60, 0:80].astype(np.float32)
    img = 0.5 + 0.4 * np.sin(xx / 9.0) * np.cos(yy / 7.0)
    kp = np.array([[40.0, 30.0, 1.5, 0.7]], np.float32)
    cfg = PatchConfig(size=15)
    patches = np.asarray(extract_patches(img, kp, cfg))
    pos, _ = patch_grid(kp, cfg)
    out = figures.paste_patches(np.full((60, 80, 3), -1.0, np.float32), patches, pos,
                                np.arange(1))
    cover = out[..., 0] >= 0
    assert cover.sum() > 100
    assert np.abs(out[..., 0][cover] - img[cover]).mean() < 0.03


def test_grid_and_top_view():
    assert figures.grid_shape(4, 1.0) == (2, 2)
    assert figures.grid_shape(6, 2.0) == (3, 2)
    assert figures.grid_shape(5, 1.0) in ((5, 1), (1, 5))
    rng = np.random.default_rng(1)
    xy = rng.random((50, 2)) * [4.0, 2.0]
    labels, (nx, ny), edges = figures.grid_clusters(xy, 8)
    assert (nx, ny) == (4, 2) and labels.min() >= 0 and labels.max() < 8
    assert np.bincount(labels, minlength=8).sum() == 50
    # top view of cameras on a horizontal ellipse drops the vertical axis
    a = np.linspace(0, 2 * np.pi, 30, endpoint=False)
    centers = np.stack([2 * np.cos(a), np.sin(a), 1.5 + 0.01 * np.sin(3 * a)], -1)
    tv = figures.top_view(centers)
    assert np.ptp(tv[:, 0]) == pytest.approx(4.0, rel=0.02)
    assert np.ptp(tv[:, 1]) == pytest.approx(2.0, rel=0.02)


def test_bad_arguments_and_missing_data(tmp_path, capsys):
    # --json in tmp_path: the default (outputs/benchmarks/NAME.json under the working folder)
    # may exist from a user's run, and an existing output is refused first
    js = lambda name: ["--json", str(tmp_path / f"{name}.json")]  # noqa: E731
    assert localize.main(["--scenes", "nosuch", "--work", str(tmp_path), *js("l")]) == 2
    assert "unknown scene" in capsys.readouterr().err
    assert map_size.main(["--map", "nowhere", "--work", str(tmp_path), *js("m")]) == 2
    assert ablation.main(["--sizes", "10", "--work", str(tmp_path), *js("a")]) == 2
    out = tmp_path / "ms.json"
    assert map_size.main(["--scenes", "fern", "--data-root", str(tmp_path / "none"),
                          "--work", str(tmp_path), "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["sizes"] == {} and doc["skipped"][0]["scene"] == "fern"
    assert "scaling" not in doc  # large scenes: measured by --series (test_benchmarks_map_scale)
    assert map_size.main(["--series", "1,x", "--work", str(tmp_path)]) == 2


def test_given_map_reads_its_images_from_data_root_when_given(tmp_path, monkeypatch):
    """--map with --data-root reads the scene's folder there (a map built on another copy of
    the data); without it the recorded folder, then the default data root; else one error."""
    import argparse

    from vrs_jax.errors import VrsError

    recorded = tmp_path / "built_here" / "instant_ngp_fox"
    other = tmp_path / "copy"
    (other / "instant_ngp_fox").mkdir(parents=True)
    default = tmp_path / "default"
    (default / "instant_ngp_fox").mkdir(parents=True)
    monkeypatch.setenv("VRS_SHARED_DATA", str(default))
    ns = lambda root: argparse.Namespace(data_root=root)  # noqa: E731
    quiet = lambda s: None  # noqa: E731
    got = common.given_map_root("fox", recorded, ns(str(other)), tmp_path, quiet)
    assert got == other / "instant_ngp_fox"
    assert common.given_map_root("fox", recorded, ns(None), tmp_path, quiet) == (
        default / "instant_ngp_fox")
    recorded.mkdir(parents=True)
    assert common.given_map_root("fox", recorded, ns(None), tmp_path, quiet) == recorded
    with pytest.raises(VrsError, match="--data-root"):
        common.given_map_root("fox", tmp_path / "gone", ns(str(tmp_path / "none")),
                              tmp_path, quiet)


def test_table_and_number_formatting():
    t = common.table(["a", "b"], [["x", "1"], ["long name", "22"]], title="T")
    lines = t.splitlines()
    assert lines[0] == "T" and len({len(x) for x in lines[1:]}) == 1
    assert common.fmt(None) == "-" and common.fmt(math.inf) == "inf"
    assert common.fmt(1234) == "1,234" and common.fmt(1.23456, 3) == "1.235"
    assert common.pct(0.5) == "50.0%"
    assert common.evenly_spaced(20, 3).tolist() == [0, 10, 19]
    assert common.evenly_spaced(5, None).tolist() == list(range(5))


def test_localize_overrides_are_typed_and_checked():
    from vrs_jax.errors import VrsError

    got = common.localize_overrides(["top_k=3", "guided_radius=8", "guided_threshold_px=none",
                                     "depth-guided=false"])
    assert got == {"top_k": 3, "guided_radius": 8.0, "guided_threshold_px": None,
                   "depth_guided": False}
    assert common.localize_overrides(["guided_threshold_px=2.5"]) == {"guided_threshold_px": 2.5}
    assert common.localize_overrides(["guided_sources=render+real"]) == {
        "guided_sources": ("render", "real")}
    for bad in ("source=real", "nosuch=1", "top_k", "top_k=three"):
        with pytest.raises(VrsError):
            common.localize_overrides([bad])


def test_environment_is_the_run_record_environment_plus_extras():
    from vrs_jax import runrecord

    env = common.environment()
    assert set(env) == {"time_utc", "machine", "device", "versions", "code", "env"}
    assert set(env["versions"]) == set(runrecord.versions()) | {"matplotlib"}
    assert env["code"]["vrs_jax_source_sha256"] == common.source_hash()
    assert env["code"]["commit"] == runrecord.git_info()["commit"]


def test_stream_benchmark_cold_and_warm(base, tmp_path):
    from benchmarks import stream

    out = tmp_path / "stream.json"
    assert stream.main(base + ["--scenes", "synthetic", "--cache-mb", "5",
                               "--json", str(out)]) == 0
    rows = json.loads(out.read_text())["rows"]
    kinds = [(r["method"], r["pass"]) for r in rows]
    assert kinds == [("real", "-"), ("render, no cache", "-"), ("render, cache", "cold"),
                     ("render, cache", "warm")]
    warm = rows[-1]
    assert warm["warm_hits"] > 0 and warm["cache"]["bytes"] <= warm["cache"]["budget_bytes"]
    assert all(_finite(r["median_s_per_query"]) for r in rows)


def test_fidelity_benchmark_on_the_tiny_map(tiny_map, loaded, tmp_path):
    from benchmarks import fidelity

    out = tmp_path / "fidelity.json"
    assert fidelity.main(["--map", str(tiny_map), "--views", "3", "--json", str(out),
                          "--quiet"]) == 0
    doc = json.loads(out.read_text())
    r = doc["result"]
    assert r["ilm_bytes"] > r["ilm_bytes_float16"] > 0
    for prec in ("float32", "float16"):
        f = r[prec]
        assert f["views"] == 3 and _finite(f["patch_psnr_db"], f["patch_psnr_median_db"])
        assert 0.0 <= f["own_keypoint_rate"] <= 1.0
        assert 0 <= f["correct_matches_per_view"] <= f["matches_per_view"] \
            <= f["keypoints_per_view"]
        assert 0.0 <= f["surface_in_window_rate"] <= 1.0
        assert f["surface_depth_ratio_median"] > 0
        by = f["own_keypoint_rate_by_depth"]
        n = [by[b]["keypoints"] for b in ("near", "mid", "far")]
        assert sum(n) == round(3 * f["keypoints_per_view"]) and f["scene_scale"] > 0
        # the bins' rates recombine to the overall rate
        assert sum(by[b]["rate"] * by[b]["keypoints"] for b in by if by[b]["keypoints"]) \
            == pytest.approx(f["own_keypoint_rate"] * sum(n))
        win = f["surface_in_window_rate_by_depth"]
        assert sum(win[b]["keypoints"] for b in win) == sum(n)
    # the real patches are read and described as the baseline map's descriptors were: the
    # same up to the map's storage (keypoints quantised to 1/32 px, angle to pi/256, scale to
    # 1/256 of its log range; a patch read elsewhere differs by ~0.3 somewhere)
    assert r["float32"]["real_desc_vs_baseline_max_abs"] < 0.08
    mean_valid = np.asarray(loaded.egm.kp_mask).sum(1)
    assert r["float32"]["keypoints_per_view"] == pytest.approx(
        mean_valid[np.unique(np.round(np.linspace(0, len(mean_valid) - 1, 3))
                                      .astype(int))].mean())


def test_fidelity_rate_by_depth_bins_in_scene_scale_units():
    from benchmarks.fidelity import rate_by_depth

    own = np.array([True, False, True, True, False, False])
    depth = np.array([0.5, 1.5, 2.5, 7.9, 8.0, 100.0])  # scale 2: 0.25, .75 | 1.25, 3.95 | 4, 50
    by = rate_by_depth(own, depth, 2.0)
    assert by["near"] == {"rate": 0.5, "keypoints": 2}
    assert by["mid"] == {"rate": 1.0, "keypoints": 2}
    assert by["far"] == {"rate": 0.0, "keypoints": 2}
    assert rate_by_depth(own[:1], depth[:1], 2.0)["far"] == {"rate": None, "keypoints": 0}


def test_track_benchmark_json_and_plot(tiny_map, stream_scene, tmp_path):
    from benchmarks import track

    out, png = tmp_path / "track.json", tmp_path / "track.png"
    assert track.main(["--map", str(tiny_map), "--format", "7scenes", "--root",
                       str(stream_scene), "--config", "test", "--modes",
                       "track,full,cached", "--track", "cache_mb=5", "--max-frames", "5",
                       "--jump-at", "2", "--jump-len", "1", "--json",
                       str(out), "--plot", str(png), "--work", str(tmp_path), "--quiet"]) == 0
    doc = json.loads(out.read_text())
    assert doc["benchmark"] == "track" and ENV_KEYS <= set(doc)
    rows = {r["run"]: r for r in doc["rows"]}
    assert set(rows) == {"track", "full", "cached", "track, jump"}
    # the cached run's poses are the uncached ones (float16 descriptors), and it renders less
    full, cached = doc["runs"]["full"], doc["runs"]["cached"]
    np.testing.assert_allclose(cached["t_err"], full["t_err"], atol=5e-3)
    assert sum(cached["rendered"]) < sum(full["rendered"])
    assert rows["track"]["n_frames"] == 5 and rows["track, jump"]["n_frames"] == 4
    assert rows["track"]["n_tracked"] + rows["track"]["n_relocalized"] + rows["track"][
        "n_full_no_prior"] == 5
    assert 0 <= rows["track"]["n_by_check"] <= rows["track"]["n_tracked"]
    assert rows["track"]["n_wrong_localized"] == 0  # the synthetic stream: none > 5% off
    assert _finite(rows["full"]["median_latency_s"], rows["track"]["median_latency_s"])
    assert doc["jump"]["dropped"] == [2, 3] and doc["jump"]["first_frame_after_gap"] == 3
    assert cv2.imread(str(png)) is not None


def test_confidence_benchmark_on_scene_maps(tiny_map, tmp_path):
    """benchmarks.confidence on benchmark-scene maps (here the tiny map under two scene
    names, real mode, no rooms): own queries labelled by their error, every pose of the
    other "scene"'s queries labelled wrong; --from-json re-evaluates to the same counts."""
    from benchmarks import confidence

    out = tmp_path / "conf.json"
    argv = ["--seeds", "--scenes", "synthetic,fern", "--map", f"synthetic={tiny_map}",
            "--map", f"fern={tiny_map}", "--modes", "real", "--max-queries", "3",
            "--cross-queries", "2", "--loose-min-inliers", "0", "--json", str(out)]
    assert confidence.main(argv) == 0
    doc = json.loads(out.read_text())
    rows = doc["rows"]
    assert len(rows) == 2 * (3 + 2)
    cross = [r for r in rows if r["map"] != r["queries"]]
    assert len(cross) == 4 and all(r["label"] == "wrong" for r in cross)
    assert {confidence.set_key(r) for r in rows} == {
        f"{s} real {w}" for s in ("synthetic", "fern") for w in ("own", "cross")}
    table, verdicts = confidence.reevaluate(rows, confidence.ConfidenceConfig())
    assert list(verdicts) == [r["verdict"] for r in rows]
    assert table == doc["table"]
