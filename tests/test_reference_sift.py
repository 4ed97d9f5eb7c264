"""The COLMAP SIFT reference localizer (vrs_jax.reference.sift) and its benchmark CLI."""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pycolmap
import pytest

from tests.conftest import shared_path
from vrs_jax import geometry
from vrs_jax.data.readers import load_scene
from vrs_jax.errors import VrsError
from vrs_jax.eval import metrics
from vrs_jax.reference import sift


@pytest.fixture(scope="module")
def scene(small_synthetic_scene):
    return load_scene("7scenes", small_synthetic_scene)


@pytest.fixture(scope="module")
def sift_map(scene, tmp_path_factory):
    return sift.build_sift_map(scene, tmp_path_factory.mktemp("sift_map"), progress=False)


# ----------------------------------------------------------------------------- pure functions


def test_unique_correspondences_removes_duplicate_pairs_only():
    q = np.array([3, 1, 3, 1, 2, 3, 2, 1])
    p = np.array([7, 5, 7, 5, 9, 8, 9, 6])
    uq, up = sift.unique_correspondences(q, p)
    pairs = list(zip(uq.tolist(), up.tolist(), strict=True))
    assert pairs == sorted(set(zip(q.tolist(), p.tolist(), strict=True)))
    assert len(pairs) == 5  # (1,5) (1,6) (2,9) (3,7) (3,8): keypoint 3 keeps both its points
    # Order of the input does not matter; empty input gives empty output.
    perm = np.random.default_rng(0).permutation(len(q))
    uq2, up2 = sift.unique_correspondences(q[perm], p[perm])
    assert np.array_equal(uq, uq2) and np.array_equal(up, up2)
    e = sift.unique_correspondences(np.zeros(0, int), np.zeros(0, int))
    assert e[0].shape == (0,) and e[1].shape == (0,)
    with pytest.raises(ValueError):
        sift.unique_correspondences(np.zeros(3, int), np.zeros(2, int))


def test_match_sift_equals_pycolmap_matcher(scene):
    """The BLAS matcher gives exactly the matches of pycolmap's CPU SIFT matcher."""
    ext = pycolmap.FeatureExtractor.create(pycolmap.FeatureExtractionOptions(),
                                           pycolmap.Device.cpu)
    descs = [sift._extract(ext, sift.grey_image(scene.image_paths[i], scene.sizes[i]))[1]
             for i in (0, 1, 5)]
    matcher = pycolmap.FeatureMatcher.create(pycolmap.FeatureMatchingOptions(),
                                             pycolmap.Device.cpu)
    total = 0
    for a, b in ((0, 1), (0, 2), (1, 0)):
        ref = np.asarray(matcher.match(None, sift._descriptors(descs[a]), None,
                                       sift._descriptors(descs[b])), np.int64)
        ours = sift.match_sift(descs[a], descs[b])
        assert set(map(tuple, ours.tolist())) == set(map(tuple, ref.tolist()))
        total += len(ref)
    assert total > 50
    # A lone candidate (its second best counts as 90 degrees away), no cross check.
    opts = pycolmap.FeatureMatchingOptions()
    opts.sift.cross_check = False
    one_way = pycolmap.FeatureMatcher.create(opts, pycolmap.Device.cpu)
    lone = np.asarray(one_way.match(None, sift._descriptors(descs[0]), None,
                                    sift._descriptors(descs[1][:1])), np.int64)
    ours = sift.match_sift(descs[0], descs[1][:1], cross_check=False)
    assert len(lone) > 0 and set(map(tuple, ours.tolist())) == set(map(tuple, lone.tolist()))
    # Without cross check: a superset, each first index once.
    one_way = sift.match_sift(descs[0], descs[1], cross_check=False)
    assert len(np.unique(one_way[:, 0])) == len(one_way) >= len(sift.match_sift(descs[0],
                                                                                 descs[1]))


def test_config_validation():
    with pytest.raises(VrsError, match="matcher"):
        sift.SiftReferenceConfig(matcher="flann")
    with pytest.raises(VrsError, match="ransac"):
        sift.SiftReferenceConfig(ransac_max_error_px=0)


def test_colmap_camera_models():
    K = np.array([[100.0, 0, 50], [0, 110, 40], [0, 0, 1]])
    assert sift.colmap_camera(K, np.zeros(5), (100, 80), 1).model.name == "PINHOLE"
    cam = sift.colmap_camera(K, np.array([0.1, -0.01, 0.001, 0.002, 0.0]), (100, 80), 1)
    assert cam.model.name == "OPENCV"
    # The COLMAP camera distorts as the project's OpenCV model does.
    xn = np.array([[0.2, -0.1], [-0.3, 0.25]])
    uv, _ = geometry.project(K, np.eye(3), np.zeros(3), np.c_[xn, np.ones(2)],
                          dist=np.array([0.1, -0.01, 0.001, 0.002, 0.0]))
    assert np.allclose(cam.img_from_cam(np.c_[xn, np.ones(2)]), uv, atol=1e-6)
    cam = sift.colmap_camera(K, np.array([0.1, 0, 0, 0, 0.01]), (100, 80), 1)
    assert cam.model.name == "FULL_OPENCV"


# ----------------------------------------------------------------------------- map and query


def test_map_uses_the_known_poses(scene, sift_map):
    refs = scene.references()
    assert sift_map.names == list(refs.names)
    assert np.allclose(sift_map.R, refs.R) and np.allclose(sift_map.t, refs.t)
    st = sift_map.stats
    assert st["n_points3d"] > 300 and st["n_verified_pairs"] > 20
    # Every kept keypoint has a 3D point that reprojects onto it with the known pose.
    errs = []
    for i in range(sift_map.num_images):
        idx = sift_map.point_idx[i]
        assert np.all(idx >= 0) and len(idx) == len(sift_map.keypoints[i])
        assert sift_map.descriptors[i].dtype == np.uint8
        assert sift_map.descriptors[i].shape == (len(idx), 128)
        uv, _ = geometry.project(refs.K[i], refs.R[i], refs.t[i], sift_map.points3d[idx])
        errs.append(np.linalg.norm(uv - sift_map.keypoints[i], axis=1))
    errs = np.concatenate(errs)
    assert np.median(errs) < 0.5 and np.max(errs) < 4.5  # COLMAP's merge/complete bound: 4 px


def test_map_bytes(sift_map):
    b = sift.sift_map_bytes(sift_map)
    n_kp = sum(len(k) for k in sift_map.keypoints)
    assert b["n_keypoints"] == n_kp and b["descriptors"] == 128 * n_kp
    assert b["points3d"] == 12 * len(sift_map.points3d)
    assert b["total"] == sum(b[k] for k in ("descriptors", "keypoints", "point_ids",
                                            "points3d", "poses", "cameras"))


def test_localizes_the_synthetic_queries(scene, sift_map):
    queries = scene.queries()
    res = sift.localize_sift(sift_map, queries, progress=False)
    R, t, ok = sift.result_arrays(res)
    assert ok.all(), [r.name for r in res if not r.success]
    dt, dr = metrics.pose_errors(R, t, queries.R, queries.t)
    assert np.max(dt) < 0.03 and np.max(dr) < 0.5, (dt, dr)
    for r in res:
        assert r.name in queries.names
        assert 12 <= r.n_inliers <= r.n_correspondences <= r.n_matches
        assert r.n_inlier_keypoints <= r.n_inliers
        assert set(r.timing) == {"read", "extract", "match", "pose", "total"}


def test_blank_query_fails_without_exception(scene, sift_map, tmp_path):
    queries = scene.queries().subset([0])
    blank = tmp_path / "blank.png"
    w, h = (int(s) for s in queries.sizes[0])
    cv2.imwrite(str(blank), np.full((h, w, 3), 128, np.uint8))
    queries = dataclasses.replace(queries, image_paths=[blank])
    (r,) = sift.localize_sift(sift_map, queries, progress=False)
    assert not r.success and r.n_keypoints == 0 and r.n_inliers == 0
    assert np.all(np.isnan(r.R)) and np.all(np.isnan(r.t))
    dt, dr = metrics.pose_errors(r.R[None], r.t[None], queries.R, queries.t)
    assert np.isinf(dt[0]) and dr[0] == 180.0  # hloc: a missing pose is inf m, 180 deg


def test_too_few_references_is_a_vrs_error(scene, tmp_path):
    one = scene.subset([0])
    with pytest.raises(VrsError, match="at least 2"):
        sift.build_sift_map(one, tmp_path, progress=False)


# ----------------------------------------------------------------------------- CLI


def test_cli_writes_the_row(small_synthetic_scene, tmp_path, capsys):
    from benchmarks import localize, sift_reference

    out = tmp_path / "sift.json"
    rc = sift_reference.main(["--format", "7scenes", "--root", str(small_synthetic_scene),
                              "--work", str(tmp_path / "work"), "--json", str(out),
                              "--max-queries", "3", "--quiet"])
    assert rc == 0
    doc = json.loads(out.read_text())
    (row,) = doc["rows"]
    assert row["mode"] == "sift" and row["n_queries"] == 3 and row["n_failed"] == 0
    assert row["recall"]["5cm_5deg"] == 1.0 and row["recall_relative"]["5pct_5deg"] == 1.0
    assert row["scene_scale"] > 0.5  # the room's camera loop: ~1 m radius
    # The keys benchmarks.localize's rows share mean the same thing there.
    shared = {"scene", "mode", "n_queries", "median_t_cm", "median_R_deg", "recall",
              "n_success", "n_fallback", "median_inliers", "timing_s",
              "localize_s_per_query", "map_bytes", "per_query", "measured_at"}
    assert shared <= set(row)
    assert set(row["recall"]) == set(localize.RECALL_KEYS)
    assert "COLMAP SIFT reference" in capsys.readouterr().out


def test_cli_bad_root_is_one_line(tmp_path, capsys):
    from benchmarks import sift_reference

    rc = sift_reference.main(["--format", "7scenes", "--root", str(tmp_path / "nope")])
    assert rc == 2
    assert capsys.readouterr().err.startswith("error: ")


# ----------------------------------------------------------------------------- real data


def test_dtu_scan24_acceptance(tmp_path):
    """Real photographs: every 10th view a query, all within 1% of the scene scale / 1 deg."""
    root = shared_path("dtu_scan24")
    scene = load_scene("nerf", root, query_every=10)
    cfg = sift.SiftReferenceConfig(max_num_features=2048)
    m = sift.build_sift_map(scene, tmp_path, cfg, progress=False)
    queries = scene.queries()
    R, t, ok = sift.result_arrays(sift.localize_sift(m, queries, cfg, progress=False))
    dt, dr = metrics.pose_errors(R, t, queries.R, queries.t, has_estimate=ok)
    scale = metrics.scene_scale(scene.centers)
    rec = metrics.relative_recall(dt, dr, scale)
    assert rec["1pct_1deg"] == 1.0, (dt / scale, dr)
