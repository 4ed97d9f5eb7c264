"""Evaluation: metrics (vrs_jax.eval.metrics), results files (vrs_jax.eval.results) and the
``experiments.evaluate`` CLI end to end on tiny hand-made 7Scenes-layout folders."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from vrs_jax import geometry
from vrs_jax.cli import evaluate
from vrs_jax.errors import VrsError
from vrs_jax.eval import metrics
from vrs_jax.eval.results import read_results, write_results

RECALL_KEYS = ["1cm_1deg", "2cm_2deg", "3cm_3deg", "5cm_5deg", "10cm_5deg", "25cm_2deg",
               "50cm_5deg", "500cm_10deg"]


def rot_z(deg: float) -> np.ndarray:
    return geometry.axis_angle_to_rot(np.array([0.0, 0.0, np.radians(deg)]))


def perturbed(R: np.ndarray, t: np.ndarray, shift: np.ndarray, deg: float):
    """A pose whose centre is moved by ``shift`` (m) and whose rotation differs by ``deg``."""
    R2 = geometry.axis_angle_to_rot(np.array([0.3, -0.5, 0.8]) / np.linalg.norm(
        [0.3, -0.5, 0.8]) * np.radians(deg)) @ R
    c2 = geometry.camera_center(R, t) + shift
    return R2, -R2 @ c2


# ----------------------------------------------------------------------------- metrics


def test_pose_errors_hand_computed_and_missing_is_hlocs_inf_180():
    R_gt = np.stack([np.eye(3), rot_z(30), rot_z(-10), np.eye(3)])
    t_gt = np.array([[0, 0, 1.0], [1, 2, 3], [0, 0, 0], [5, 5, 5]])
    est = [perturbed(R_gt[0], t_gt[0], np.array([0.03, 0.04, 0.0]), 0.0),   # 5 cm, 0 deg
           perturbed(R_gt[1], t_gt[1], np.zeros(3), 7.0),                  # 0 cm, 7 deg
           perturbed(R_gt[2], t_gt[2], np.array([0, 0, -2.0]), 3.0),       # 2 m, 3 deg
           (np.full((3, 3), np.nan), np.zeros(3))]                         # not finite
    R_est = np.stack([e[0] for e in est])
    t_est = np.stack([e[1] for e in est])
    dt, dr = metrics.pose_errors(R_est, t_est, R_gt, t_gt)
    np.testing.assert_allclose(dt[:3], [0.05, 0.0, 2.0], atol=1e-12)
    np.testing.assert_allclose(dr[:3], [0.0, 7.0, 3.0], atol=1e-5)
    assert np.isinf(dt[3]) and dr[3] == 180.0
    dt, dr = metrics.pose_errors(R_est, t_est, R_gt, t_gt, has_estimate=[True, False, True, True])
    assert np.isinf(dt[1]) and dr[1] == 180.0 and dt[0] == pytest.approx(0.05)


def test_pose_errors_match_hlocs_formula():
    """hloc: e_t = ||-R_gt^T t_gt + R^T t||, e_R = deg |arccos(clip((tr(R_gt^T R) - 1) / 2))|,
    written out per query here as hloc's loop does."""
    rng = np.random.default_rng(3)
    R_gt = np.stack([geometry.axis_angle_to_rot(v) for v in rng.normal(size=(6, 3))])
    R_est = np.stack([geometry.axis_angle_to_rot(v) for v in rng.normal(size=(6, 3))])
    t_gt, t_est = rng.normal(size=(6, 3)), rng.normal(size=(6, 3))
    dt, dr = metrics.pose_errors(R_est, t_est, R_gt, t_gt)
    for i in range(6):
        e_t = np.linalg.norm(-R_gt[i].T @ t_gt[i] + R_est[i].T @ t_est[i])
        cos = np.clip((np.trace(R_gt[i].T @ R_est[i]) - 1) / 2, -1.0, 1.0)
        assert dt[i] == pytest.approx(e_t, rel=1e-14)
        assert dr[i] == pytest.approx(np.rad2deg(abs(np.arccos(cos))), rel=1e-12)


def test_float32_rotation_error_is_the_results_files_error(tmp_path):
    # A solver's float32 rotation, off-orthonormal by ~1e-7: the arccos formula alone turned
    # that into ~0.02 deg, so localize's summary and evaluate on its results.txt disagreed
    # (0.0275 vs 0.0244 deg median).
    rng = np.random.default_rng(3)
    R_gt = np.stack([geometry.axis_angle_to_rot(rng.normal(size=3)) for _ in range(20)])
    t_gt = rng.normal(size=(20, 3))
    R32 = (R_gt @ geometry.axis_angle_to_rot(np.array([0.0, 0.0, 1e-4]))).astype(np.float32)
    _, dr = metrics.pose_errors(R32, t_gt, R_gt, t_gt)
    np.testing.assert_allclose(dr, np.degrees(1e-4), atol=1e-4)
    names = [f"q{i}.png" for i in range(20)]
    back = read_results(write_results(tmp_path / "r.txt", names, R32, t_gt))
    _, dr_file = metrics.pose_errors(np.stack([back[n][0] for n in names]), t_gt, R_gt, t_gt)
    np.testing.assert_allclose(dr, dr_file, rtol=0, atol=1e-9)


def test_hand_made_evaluation_strict_thresholds_and_missing_query():
    """Five queries; answers worked out by hand with hloc's rules (strict <, missing query =
    (inf m, 180 deg), medians over all queries).

    q0: 0 cm, 0 deg      -> within every threshold
    q1: 3 cm, 1 deg      -> exactly on 3 cm: not in 3cm/3deg; in 5/5, 10/5, 25/2, 50/5, 5m/10
    q2: 4 cm, 3 deg      -> exactly on 3 deg: not in 3/3; in 5/5, 10/5, 50/5, 5m/10 (not 25/2)
    q3: 30 cm, 6 deg     -> only 5m/10deg
    q4: missing          -> nothing
    Sorted t (cm): 0, 3, 4, 30, inf -> median 4; sorted R: 0, 1, 3, 6, 180 -> median 3.
    """
    R_gt = np.stack([rot_z(10.0 * i) for i in range(5)])
    t_gt = np.array([[0.0, 0, 2], [1, 0, 2], [0, 1, 2], [1, 1, 2], [2, 2, 2]])
    # Exact error values first (ties on the thresholds must be exact floats), then the same
    # errors made from poses (equal up to rounding, so only checked away from the ties).
    t_err = np.array([0.0, 0.03, 0.04, 0.30, 0.0])
    R_err = np.array([0.0, 1.0, 3.0, 6.0, 0.0])
    t_err_h, R_err_h = t_err.copy(), R_err.copy()
    t_err_h[4], R_err_h[4] = np.inf, 180.0
    # The metrics functions on the exact error values.
    rec = metrics.recall(t_err_h, R_err_h)
    assert rec == {"1cm_1deg": 0.2, "2cm_2deg": 0.2, "3cm_3deg": 0.2, "5cm_5deg": 0.6,
                   "10cm_5deg": 0.6, "25cm_2deg": 0.4, "50cm_5deg": 0.6, "500cm_10deg": 0.8}
    s = metrics.summarize(t_err_h, R_err_h)
    assert s["n_queries"] == 5 and s["n_failed"] == 1
    assert s["median_t_cm"] == pytest.approx(4.0) and s["median_R_deg"] == 3.0
    # The same from poses (errors within float rounding of the hand values, away from ties).
    est = [perturbed(R_gt[i], t_gt[i], np.array([t_err[i], 0.0, 0.0]), R_err[i])
           for i in range(5)]
    dt, dr = metrics.pose_errors(np.stack([e[0] for e in est]), np.stack([e[1] for e in est]),
                                 R_gt, t_gt, has_estimate=[True, True, True, True, False])
    np.testing.assert_allclose(dt[:4], t_err[:4], atol=1e-12)
    np.testing.assert_allclose(dr[:4], R_err[:4], atol=1e-5)
    assert np.isinf(dt[4]) and dr[4] == 180.0
    s2 = metrics.summarize(dt, dr)
    assert s2["median_t_cm"] == pytest.approx(4.0) and s2["median_R_deg"] == pytest.approx(3.0)
    assert s2["recall"]["5cm_5deg"] == 0.6 and s2["recall"]["500cm_10deg"] == 0.8


def test_recall_strict_bounds_and_keys():
    t = np.array([0.01, 0.05, 0.05, 0.3, np.inf])
    r = np.array([1.0, 5.0, 5.1, 1.0, 180.0])
    rec = metrics.recall(t, r)
    assert list(rec) == RECALL_KEYS
    # q0 (1 cm, 1 deg) is on the 1/1 bound: out there, in from 2/2 on; q1 is on 5 cm and 5 deg.
    assert rec == {"1cm_1deg": 0.0, "2cm_2deg": 0.2, "3cm_3deg": 0.2, "5cm_5deg": 0.2,
                   "10cm_5deg": 0.2, "25cm_2deg": 0.2, "50cm_5deg": 0.4, "500cm_10deg": 0.8}
    assert metrics.recall(np.zeros(0), np.zeros(0)) == dict.fromkeys(RECALL_KEYS, 0.0)


def test_scene_scale_and_relative_recall():
    # Cameras on a circle of radius 2 (any centre): every distance to the centroid is 2.
    a = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    c = np.c_[2 * np.cos(a), 2 * np.sin(a), np.zeros_like(a)] + [10.0, -3.0, 1.0]
    assert metrics.scene_scale(c) == pytest.approx(2.0)
    # Median, not mean: one far camera does not move it.
    line = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0], [100, 0, 0]])
    d = np.abs(line[:, 0] - line[:, 0].mean())
    assert metrics.scene_scale(line) == pytest.approx(np.median(d))
    assert math.isnan(metrics.scene_scale(np.zeros((0, 3))))
    # 1% of a 2 m scene is 2 cm: strict, like hloc's recall (an error on the bound fails).
    rec = metrics.relative_recall(np.array([0.0199, 0.02, 0.05, 0.03, np.inf]),
                                  np.array([0.5, 0.5, 4.9, 5.0, 180.0]), 2.0)
    assert rec == {"1pct_1deg": 0.2, "2pct_2deg": 0.4, "5pct_5deg": 0.6}


def test_summary_medians_with_failures():
    s = metrics.summarize(np.array([0.02, 0.04, np.inf]), np.array([1.0, 3.0, np.inf]))
    assert s["n_queries"] == 3 and s["n_failed"] == 1
    assert s["median_t_cm"] == pytest.approx(4.0) and s["median_R_deg"] == pytest.approx(3.0)
    assert s["recall"]["5cm_5deg"] == pytest.approx(2 / 3)
    s = metrics.summarize(np.array([0.02, np.inf, np.inf]), np.array([1.0, np.inf, np.inf]))
    assert math.isinf(s["median_t_cm"]) and math.isinf(s["median_R_deg"])
    doc = metrics.json_ready(s)
    assert doc["median_t_cm"] is None
    json.dumps(doc, allow_nan=False)  # strict JSON
    table = metrics.format_table(s)
    assert "inf" in table and "recall @ 5 cm, 5 deg (%)" in table


def test_cumulative_curve():
    x, y = metrics.cumulative_curve(np.array([0.5, np.inf, 0.1, 0.3]))
    np.testing.assert_allclose(x, [0.0, 0.1, 0.3, 0.5])
    np.testing.assert_allclose(y, [0.0, 0.25, 0.5, 0.75])
    x, y = metrics.cumulative_curve(np.array([0.5, np.inf, 0.1, 0.3]), max_error=0.35)
    np.testing.assert_allclose(x, [0.0, 0.1, 0.3, 0.35])
    np.testing.assert_allclose(y, [0.0, 0.25, 0.5, 0.5])
    assert np.all(np.diff(y) >= 0) and y[-1] <= 1


def test_json_ready_converts_numpy():
    doc = metrics.json_ready({"a": np.float32(1.5), "b": np.array([1, 2]), "c": np.bool_(True),
                              "d": [np.nan, np.int64(3)], 4: "x"})
    assert doc == {"a": 1.5, "b": [1, 2], "c": True, "d": [None, 3], "4": "x"}


# ----------------------------------------------------------------------------- results files


def random_poses(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    R = geometry.axis_angle_to_rot(rng.normal(size=(n, 3)))
    return R, rng.normal(size=(n, 3)) * 10


def test_results_round_trip(tmp_path):
    names = ["seq-03/frame-000000.color.png", "seq-03/frame-000001.color.png", "db/x.jpg"]
    R, t = random_poses(3)
    path = write_results(tmp_path / "results.txt", names, R, t)
    got = read_results(path)
    assert list(got) == names
    for i, n in enumerate(names):
        np.testing.assert_allclose(got[n][0], R[i], atol=1e-14)
        np.testing.assert_array_equal(got[n][1], t[i])
    first = path.read_text().splitlines()[0].split()
    assert first[0] == names[0] and len(first) == 8
    np.testing.assert_allclose(geometry.quat_to_rot(np.array(first[1:5], float)), R[0],
                               atol=1e-14)
    assert float(first[1]) >= 0  # w >= 0, as hloc writes
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results.txt"]  # no temp files
    # Overwriting replaces the file.
    write_results(path, names[:1], R[:1], t[:1])
    assert list(read_results(path)) == names[:1]


def test_results_basename_option(tmp_path):
    R, t = random_poses(2)
    p = write_results(tmp_path / "r.txt", ["query/day/a.jpg", "query/night/b.jpg"], R, t,
                      basename=True)
    assert list(read_results(p)) == ["a.jpg", "b.jpg"]
    with pytest.raises(VrsError, match="two queries would be written as 'a.jpg'"):
        write_results(tmp_path / "s.txt", ["day/a.jpg", "night/a.jpg"], R, t, basename=True)
    with pytest.raises(VrsError, match="whitespace"):
        write_results(tmp_path / "s.txt", ["a b.jpg", "c.jpg"], R, t)
    with pytest.raises(VrsError, match="output folder not found"):
        write_results(tmp_path / "nope" / "s.txt", ["a.jpg", "c.jpg"], R, t)
    assert not (tmp_path / "s.txt").exists()


def test_results_skip_comments_and_blank_lines(tmp_path):
    p = tmp_path / "r.txt"
    p.write_text("# hloc results\n\nq.jpg 1 0 0 0 1 2 3\n  \n")
    got = read_results(p)
    np.testing.assert_array_equal(got["q.jpg"][0], np.eye(3))
    np.testing.assert_array_equal(got["q.jpg"][1], [1, 2, 3])


@pytest.mark.parametrize("bad, problem", [
    ("q.jpg 1 0 0 0 1 2", "expected 8 fields"),
    ("q.jpg 1 0 0 0 1 2 3 4", "expected 8 fields"),
    ("q.jpg 1 0 0 0 1 2 x", "'x' is not a number"),
    ("q.jpg nan 0 0 0 1 2 3", "must be finite"),
    ("q.jpg 1 0 0 0 1 inf 3", "must be finite"),
    ("q.jpg 0 0 0 0 1 2 3", "quaternion is zero"),
    ("a.jpg 1 0 0 0 1 2 3", "appears twice (first on line 2)"),
])
def test_malformed_results_name_file_and_line(tmp_path, bad, problem):
    p = tmp_path / "results.txt"
    p.write_text("# header\na.jpg 1 0 0 0 0 0 0\n" + bad + "\n")
    with pytest.raises(VrsError) as e:
        read_results(p)
    assert str(e.value).startswith(f"{p}:3: ")
    assert problem in str(e.value)


def test_missing_or_binary_results_file(tmp_path):
    with pytest.raises(VrsError, match="results file not found"):
        read_results(tmp_path / "none.txt")
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(VrsError, match="not a text file"):
        read_results(tmp_path / "bin.txt")


# ----------------------------------------------------------------------------- CLI


def write_7scenes(root: Path, frames: dict[str, int], split: bool = True, seed: int = 0):
    """A tiny 7Scenes-layout folder: {seq-XX: n frames}, 8x6 PNGs, camera-to-world poses.

    Returns {name: (R, t)} world-to-camera ground truth."""
    rng = np.random.default_rng(seed)
    gt = {}
    for seq, n in frames.items():
        (root / seq).mkdir(parents=True)
        for i in range(n):
            stem = root / seq / f"frame-{i:06d}"
            cv2.imwrite(str(stem) + ".color.png", np.zeros((6, 8, 3), np.uint8))
            R = geometry.axis_angle_to_rot(rng.normal(size=3))
            t = rng.normal(size=3)
            c2w = np.eye(4)
            c2w[:3, :3], c2w[:3, 3] = geometry.pose_inverse(R, t)
            np.savetxt(str(stem) + ".pose.txt", c2w)
            gt[f"{seq}/frame-{i:06d}.color.png"] = (R, t)
    if split:
        (root / "TrainSplit.txt").write_text("sequence1\n")
        (root / "TestSplit.txt").write_text("sequence2\n")
    return gt


def test_evaluate_cli_end_to_end(tmp_path, capsys):
    root = tmp_path / "scene"
    gt = write_7scenes(root, {"seq-01": 2, "seq-02": 3})
    q = [f"seq-02/frame-{i:06d}.color.png" for i in range(3)]
    R1, t1 = perturbed(*gt[q[1]], np.array([0.0, 0.03, 0.0]), 1.5)  # 3 cm, 1.5 deg
    names = [q[0], q[1], "seq-09/frame-000000.color.png", "seq-01/frame-000000.color.png"]
    R = np.stack([gt[q[0]][0], R1, np.eye(3), np.eye(3)])
    t = np.stack([gt[q[0]][1], t1, np.zeros(3), np.zeros(3)])
    res = write_results(tmp_path / "results.txt", names, R, t)
    out_json = tmp_path / "eval.json"
    rc = evaluate.main(["--results", str(res), "--format", "7scenes", "--root", str(root),
                        "--json", str(out_json)])
    cap = capsys.readouterr()
    assert rc == 0
    assert "1 of 3 queries have no result" in cap.err and q[2] in cap.err
    assert "name no image of the dataset" in cap.err and "seq-09" in cap.err
    assert "reference (not query) images" in cap.err
    assert "recall @ 5 cm, 5 deg (%)" in cap.out and "66.7" in cap.out
    doc = json.loads(out_json.read_text())
    assert list(doc["recall"]) == RECALL_KEYS
    assert doc["n_queries"] == 3 and doc["n_failed"] == 1 and doc["n_missing"] == 1
    assert doc["missing"] == [q[2]]
    assert doc["median_t_cm"] == pytest.approx(3.0, abs=1e-6)
    assert doc["median_R_deg"] == pytest.approx(1.5, abs=1e-5)
    assert doc["recall"]["1cm_1deg"] == pytest.approx(1 / 3)
    assert doc["recall"]["2cm_2deg"] == pytest.approx(1 / 3)
    assert doc["recall"]["5cm_5deg"] == pytest.approx(2 / 3)
    assert doc["recall"]["25cm_2deg"] == pytest.approx(2 / 3)
    assert doc["per_query"][q[2]] == {"t_cm": None, "R_deg": 180.0}
    assert doc["per_query"][q[0]]["t_cm"] == pytest.approx(0.0, abs=1e-9)


def test_evaluate_cli_query_every_and_basenames(tmp_path, capsys):
    """Options reach the reader (--query-every), and bare file names match unique queries."""
    root = tmp_path / "scene"
    gt = write_7scenes(root, {"seq-01": 4}, split=False)
    queries = ["seq-01/frame-000000.color.png", "seq-01/frame-000002.color.png"]
    R = np.stack([gt[n][0] for n in queries])
    t = np.stack([gt[n][1] for n in queries])
    res = write_results(tmp_path / "r.txt", queries, R, t, basename=True)
    rc = evaluate.main(["--results", str(res), "--format", "7scenes", "--root", str(root),
                        "--query-every", "2", "--json", str(tmp_path / "e.json")])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    doc = json.loads((tmp_path / "e.json").read_text())
    assert doc["n_queries"] == 2 and doc["n_missing"] == 0 and doc["unknown"] == []
    assert doc["recall"]["1cm_1deg"] == 1.0 and doc["options"] == {"query_every": 2}
    # Without the split option the dataset has no queries: a one-line error, exit 2.
    rc = evaluate.main(["--results", str(res), "--format", "7scenes", "--root", str(root)])
    cap = capsys.readouterr()
    assert rc == 2 and cap.err.startswith("error: ") and "--query-every" in cap.err
    assert cap.err.count("\n") == 1


def test_evaluate_cli_bad_inputs(tmp_path, capsys):
    root = tmp_path / "scene"
    write_7scenes(root, {"seq-01": 1, "seq-02": 1})
    bad = tmp_path / "bad.txt"
    bad.write_text("seq-02/frame-000000.color.png 1 0 0\n")
    for argv, expect in [
        (["--results", str(tmp_path / "none.txt")], "results file not found"),
        (["--results", str(bad)], f"{bad}:1: expected 8 fields"),
    ]:
        rc = evaluate.main(argv + ["--format", "7scenes", "--root", str(root)])
        cap = capsys.readouterr()
        assert rc == 2 and cap.err.startswith("error: ") and expect in cap.err, cap.err
    good = write_results(tmp_path / "ok.txt", ["seq-02/frame-000000.color.png"], np.eye(3)[None],
                         np.zeros((1, 3)))
    for argv, expect in [
        (["--opt", "novalue"], "--opt expects KEY=VALUE"),
        (["--opt", "bogus=1"], "unknown option"),
        (["--json", str(tmp_path / "nope" / "e.json")], "output folder not found"),
    ]:
        rc = evaluate.main(["--results", str(good), "--format", "7scenes", "--root", str(root)]
                           + argv)
        cap = capsys.readouterr()
        assert rc == 2 and expect in cap.err, cap.err
    rc = evaluate.main(["--results", str(good), "--format", "nosuch", "--root", str(root)])
    assert rc == 2 and "nosuch" in capsys.readouterr().err


def test_parse_opts_types():
    assert evaluate.parse_opts(["a=1", "b=2.5", "c=true", "d-e=x/y"]) == {
        "a": 1, "b": 2.5, "c": True, "d_e": "x/y"}


def test_recall_interval_bootstrap():
    """All recalled: [1, 1]; 2 of 4: an interval around 0.5 that a single query can move
    (reaching 0.25 and 0.75), narrower for 2 of 4 repeated 25 times; deterministic."""
    th = {"x": (0.05, 5.0)}
    ok = np.full(4, 0.01)
    assert metrics.recall_interval(ok, ok, th) == {"x": (1.0, 1.0)}
    half = np.array([0.01, 0.01, 1.0, 1.0])
    lo, hi = metrics.recall_interval(half, np.zeros(4), th)["x"]
    assert lo <= 0.25 and hi >= 0.75
    many = np.tile(half, 25)
    lo2, hi2 = metrics.recall_interval(many, np.zeros(100), th)["x"]
    assert lo < lo2 < 0.5 < hi2 < hi
    assert metrics.recall_interval(half, np.zeros(4), th) == metrics.recall_interval(
        half, np.zeros(4), th)
    assert metrics.recall_interval(np.zeros(0), np.zeros(0), th) == {"x": (0.0, 0.0)}
