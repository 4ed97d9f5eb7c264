"""The mapping pipeline end to end: synthetic scene, lego, 7Scenes stairs, CLI, bad input."""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pycolmap
import pytest
from conftest import shared_path

from vrs_jax import geometry as g
from vrs_jax.data.depth import sample_inverse_depth
from vrs_jax.data.images import read_depth, read_gray, write_image
from vrs_jax.data.readers import load_scene
from vrs_jax.egm import build as B
from vrs_jax.egm import map as M
from vrs_jax.egm import retrieval as RT
from vrs_jax.errors import VrsError
from vrs_jax.features import extract as F

STAIRS = ("kapture_samples", "samples", "7scenes", "microsoft", "stairs")


def _depth_rel_errors(scene, egm, depth_K=None, max_rel=0.05):
    """|z_map - z_sensor| / z_sensor at every EGM link, sensor depth read through depth_K."""
    img, slot, pts = M.observations(egm)
    X = np.asarray(egm.points3d, np.float64)[pts]
    out = []
    for i in np.unique(img):
        sel = img == i
        Xc = X[sel] @ scene.R[i].T + scene.t[i]
        Kd = scene.K[i] if depth_K is None else depth_K[i]
        uv = Xc[:, :2] / Xc[:, 2:] @ Kd[:2, :2].T + Kd[:2, 2]
        z, ok = sample_inverse_depth(read_depth(scene.depth_paths[i], scene.depth_scale), uv,
                                     max_rel)
        out.append(np.abs(z[ok] - Xc[ok, 2]) / z[ok])
    return np.concatenate(out)


@pytest.fixture(scope="module")
def synthetic(small_synthetic_scene):
    scene = load_scene("7scenes", small_synthetic_scene)
    cfg = B.get_config("cpu-small")
    egm, stats = B.build_egm(scene, cfg, progress=False)
    return scene, egm, stats


def test_synthetic_reprojection_and_depths(synthetic):
    scene, egm, stats = synthetic
    refs = scene.references()
    assert egm.names == tuple(refs.names)
    assert egm.num_points > 500 and stats["images_without_points"] == 0
    # reprojection error with the TRUE poses (the dataset's, not the map's float32 copy)
    err = M.reprojection_errors(egm, refs.R, refs.t)
    assert np.median(err) < 1.0
    assert stats["median_reprojection_error_px"] == pytest.approx(np.median(err), abs=1e-3)
    # triangulated depths agree with the rendered depth maps
    rel = _depth_rel_errors(refs, egm)
    assert len(rel) > 0.8 * len(err)
    assert np.median(rel) < 0.01
    assert stats["mean_track_length"] >= 2.0
    # every point is linked, and its track is what the links say
    img, _, pts = M.observations(egm)
    assert set(pts) == set(range(egm.num_points))


def test_synthetic_baseline_descriptors_are_the_describe_path(synthetic):
    scene, egm, _ = synthetic
    refs = scene.references()
    i = 3
    c = int(np.asarray(egm.kp_mask[i]).sum())
    gray = read_gray(refs.image_paths[i])
    fc = B.get_config("cpu-small").features
    d = np.asarray(F.describe_keypoints_jit(gray, egm.keypoints[i, :c], fc.patches,
                                            fc.descriptor))
    np.testing.assert_allclose(np.asarray(egm.local_desc[i, :c]), d, atol=1e-4)


def test_synthetic_map_keeps_real_descriptors_apart(synthetic):
    _, egm, stats = synthetic
    assert egm.local_desc is not None
    assert "local_desc" not in M.to_arrays(egm)  # stored apart from the EGM's arrays
    assert str(stats["points"]) in B.format_stats(stats)


def test_synthetic_retrieval_recall(synthetic):
    scene, egm, _ = synthetic
    refs, queries = scene.references(), scene.queries()
    fc = B.get_config("cpu-small").features
    descs = [F.extract_features(read_gray(p), fc)[1] for p in queries.image_paths]
    gq = RT.global_descriptors(descs, None, egm.vocab)
    idx, _ = RT.topk(gq, egm.global_desc, 5)
    hit = []
    for a in range(len(queries)):
        r = np.asarray(idx[a])
        dt = np.linalg.norm(refs.centers[r] - queries.centers[a], axis=1)
        dr = np.degrees(g.rotation_angle(refs.R[r] @ queries.R[a].T))
        hit.append(np.any((dt < 0.5) & (dr < 30)))
    assert np.mean(hit) >= 0.9


def test_lego_reprojection():
    root = shared_path("nerf_synthetic_lego_200")
    scene = load_scene("nerf", root).subset(np.arange(30))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a few lego views see no 3D point with 30 views
        egm, stats = B.build_egm(scene, B.get_config("test"), progress=False)
    assert egm.num_points > 100
    assert np.median(M.reprojection_errors(egm, scene.R, scene.t)) < 1.0
    assert stats["depth_range_source"] in ("bounds", "axes")


@pytest.fixture(scope="module")
def stairs():
    return load_scene("7scenes", shared_path(*STAIRS))


def test_stairs_references_only_triangulate_nothing(stairs):
    """The 6 stairs references are 3 + 3 consecutive frames (baselines of ~5 mm, seq-02 and
    seq-03 78 deg apart): nothing reaches 1.5 deg of triangulation angle -> a clear error."""
    with pytest.raises(VrsError, match="triangulation produced no 3D points"):
        B.build_egm(stairs, B.get_config("cpu-small"), progress=False)


def test_stairs_all_frames_depths_agree_with_sensor(stairs):
    """All 12 low-quality JPEG frames as references: seq-04's 2-5 cm baselines give a few
    dozen points. The depth camera is not registered to the colour camera (f = 585 vs 525),
    so points are projected into the depth image with depth_K; the tolerance (median relative
    difference under 10%, measured ~5%) covers the RGB-depth misregistration and the
    2-degree triangulation angles."""
    scene = dataclasses.replace(stairs, is_query=np.zeros(len(stairs), bool))
    with pytest.warns(UserWarning, match="no 3D point in the map"):  # seq-02/03: no baseline
        egm, stats = B.build_egm(scene, B.get_config("paper"), progress=False)
    assert egm.num_points >= 8
    rel = _depth_rel_errors(scene, egm, scene.depth_K, max_rel=0.1)
    assert len(rel) >= 10
    assert np.median(rel) < 0.10
    assert stats["median_reprojection_error_px"] < 2.0


# ----------------------------------------------------------------------------- bad input


def test_blank_reference_image_warns_and_builds(small_synthetic_scene, tmp_path):
    scene = load_scene("7scenes", small_synthetic_scene)
    blank = tmp_path / "blank.png"
    w, h = scene.sizes[0]
    write_image(blank, np.full((h, w, 3), 0.5, np.float32))
    refs = scene.references().subset(np.arange(8))
    paths = list(refs.image_paths)
    paths[2] = blank
    refs = dataclasses.replace(refs, image_paths=paths)
    with pytest.warns(UserWarning) as record:
        egm, stats = B.build_egm(refs, B.get_config("test"), progress=False)
    msgs = [str(r.message) for r in record]
    assert any("1 reference images have no keypoints" in m and "seq-01/frame-000002" in m
               for m in msgs)
    assert any("have no 3D point in the map" in m for m in msgs)
    assert int(np.asarray(egm.kp_mask[2]).sum()) == 0
    assert egm.num_points > 0 and stats["images_without_points"] >= 1


def test_unposed_and_empty_scenes_raise(small_synthetic_scene):
    scene = load_scene("7scenes", small_synthetic_scene)
    with pytest.raises(VrsError, match="no reference image has a pose"):
        B.build_egm(dataclasses.replace(scene, has_pose=np.zeros(len(scene), bool)),
                    B.get_config("test"), progress=False)
    with pytest.raises(VrsError, match="no reference images"):
        B.build_egm(dataclasses.replace(scene, is_query=np.ones(len(scene), bool)),
                    B.get_config("test"), progress=False)
    with pytest.raises(VrsError, match="unknown EGM config"):
        B.get_config("nope")


# ----------------------------------------------------------------------------- CLI


def test_cli_build_skip_protect_export(small_synthetic_scene, tmp_path, capsys):
    from vrs_jax import maps
    from vrs_jax.cli.build_egm import main

    out, col = tmp_path / "map", tmp_path / "colmap"
    args = ["--format", "7scenes", "--root", str(small_synthetic_scene), "--out", str(out),
            "--config", "test", "--quiet"]
    assert main(args + ["--export-colmap", str(col)]) == 0
    assert json.loads((out / "run.json").read_text())["config"]["config"]["name"] == "test"
    m = maps.load_map(out, require_ilm=False)
    assert m.ilm is None and m.has_descriptors and m.config == maps.get_config("test")
    assert maps.read_stats(out)["egm"]["points"] == m.egm.num_points
    rec = pycolmap.Reconstruction(col)
    assert rec.num_points3D() == m.egm.num_points and rec.num_reg_images() == m.egm.num_images
    mtime = (out / "egm.npz").stat().st_mtime_ns
    capsys.readouterr()
    # same settings: skipped
    assert main(args) == 0
    assert "skipping" in capsys.readouterr().err  # a log line (vrs_jax logger, stderr)
    assert (out / "egm.npz").stat().st_mtime_ns == mtime
    # different settings: refused, map untouched
    assert main(args[:-3] + ["--config", "cpu-small", "--quiet"]) == 2
    assert "other settings" in capsys.readouterr().err
    assert (out / "egm.npz").stat().st_mtime_ns == mtime
    # bad input: one line, exit 2
    assert main(["--format", "7scenes", "--root", str(tmp_path / "none"), "--out",
                 str(tmp_path / "m2"), "--config", "test", "--quiet"]) == 2
    assert capsys.readouterr().err.startswith("error: ")
