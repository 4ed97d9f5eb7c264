"""COLMAP export of the EGM (vrs_jax.egm.colmap): camera model choice, and a round trip
through pycolmap and through our own COLMAP reader."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest
from test_egm_map import _toy

from vrs_jax import geometry as g
from vrs_jax.data.readers import colmap as colmap_reader
from vrs_jax.data.readers.colmap import colmap_camera
from vrs_jax.egm.colmap import export_colmap


@pytest.mark.parametrize("dist, model", [
    (np.zeros(5), "PINHOLE"),
    (np.array([-0.2, 0.05, 1e-3, 2e-3, 0.0]), "OPENCV"),
    (np.array([-0.2, 0.0, 0.0, 0.0, 0.0]), "OPENCV"),
    (np.array([-0.2, 0.05, 1e-3, 2e-3, 0.01]), "FULL_OPENCV"),
    (np.array([0.0, 0.0, 0.0, 0.0, 0.01]), "FULL_OPENCV"),
])
def test_colmap_camera_simplest_exact_model(dist, model):
    K = g.intrinsics_matrix(300.0, 310.0, 160.5, 120.5)
    X = np.random.default_rng(0).uniform([-1, -1, 2], [1, 1, 4], (30, 3))
    cam = colmap_camera(K, dist, (320, 240), 1)
    assert cam.model.name == model
    ours, _ = g.project(K, np.eye(3), np.zeros(3), X, dist)
    np.testing.assert_allclose(cam.img_from_cam(X), ours, atol=1e-9)
    # and our reader maps the written model back to exactly the same K and dist
    K2, d2 = colmap_reader.camera_to_K_dist(cam.model.name, cam.params)
    np.testing.assert_array_equal(K2, K)
    np.testing.assert_array_equal(d2, dist)


@pytest.mark.parametrize("text", [True, False])
def test_export_round_trip_pycolmap_and_our_reader(tmp_path, text):
    egm = _toy()  # images 0 (no distortion), 1 (k3 = 0), 2 (k3 != 0): all three models
    model_dir = export_colmap(egm, tmp_path / "model", text=text)
    assert (model_dir / ("cameras.txt" if text else "cameras.bin")).is_file()
    images = tmp_path / "images"
    for name in egm.names:  # our reader checks the images' sizes against the cameras
        (images / name).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(images / name), np.zeros((240, 320, 3), np.uint8))
    scene = colmap_reader.load(model_dir, images=images)
    rec = pycolmap.Reconstruction(str(model_dir))

    assert scene.names == list(egm.names)
    assert rec.num_images() == rec.num_reg_images() == egm.num_images
    by_name = {im.name: im for im in rec.images.values()}
    models = []
    for i, name in enumerate(egm.names):
        im = by_name[name]
        cam = rec.camera(im.camera_id)
        models.append(cam.model.name)
        pose = im.cam_from_world()
        # our reader == pycolmap, exactly
        np.testing.assert_array_equal(scene.R[i], pose.rotation.matrix())
        np.testing.assert_array_equal(scene.t[i], pose.translation)
        K, dist = colmap_reader.camera_to_K_dist(cam.model.name, cam.params)
        np.testing.assert_array_equal(scene.K[i], K)
        np.testing.assert_array_equal(scene.dist[i], dist)
        np.testing.assert_array_equal(scene.K[i], cam.calibration_matrix())
        # both == the map (the rotation is re-orthonormalised from float32 on export)
        np.testing.assert_allclose(scene.R[i], egm.R[i], atol=1e-6)
        np.testing.assert_allclose(scene.t[i], egm.t[i], atol=1e-6)
        np.testing.assert_array_equal(scene.K[i], np.asarray(egm.K[i], np.float64))
        np.testing.assert_array_equal(scene.dist[i], np.asarray(egm.dist[i], np.float64))
        np.testing.assert_array_equal(scene.sizes[i], egm.sizes[i])
        # 2D points and their 3D points
        c = int(np.asarray(egm.kp_mask[i]).sum())
        assert im.num_points2D() == c and im.num_points3D == c
        X = np.asarray(egm.points3d, np.float64)
        for k, p2 in enumerate(im.points2D):
            np.testing.assert_array_equal(p2.xy, np.asarray(egm.keypoints[i, k, :2], np.float64))
            np.testing.assert_array_equal(rec.point3D(p2.point3D_id).xyz,
                                          X[int(egm.point_idx[i, k])])
    assert models == ["PINHOLE", "OPENCV", "FULL_OPENCV"]
    # points: our reader (sorted by id) == pycolmap == the map's linked points, in map order
    used = np.unique(np.asarray(egm.point_idx)[np.asarray(egm.kp_mask)])
    assert rec.num_points3D() == len(used)
    pts = np.stack([rec.points3D[k].xyz for k in sorted(rec.points3D)])
    np.testing.assert_array_equal(scene.points3d, pts)
    np.testing.assert_array_equal(pts, np.asarray(egm.points3d, np.float64)[used])
    # the exported model reprojects like the map (cameras incl. distortion survived)
    assert rec.compute_mean_reprojection_error() < 1e-2
