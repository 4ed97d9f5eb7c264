"""Incremental SfM with pycolmap for image sets without poses."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
from conftest import shared_path

from vrs_jax import geometry as g
from vrs_jax.data.images import write_image
from vrs_jax.egm import sfm
from vrs_jax.errors import VrsError

SACRE_COEUR = ("hloc_sacre_coeur", "datasets", "sacre_coeur", "mapping")


@pytest.mark.slow
def test_sacre_coeur_registers_at_least_8_of_10(tmp_path):
    root = shared_path(*SACRE_COEUR)
    scene = sfm.scene_from_images(root, tmp_path / "sfm")
    assert len(scene) == 10
    assert scene.has_pose.sum() >= 8
    assert len(scene.points3d) > 500
    # the poses are consistent with the points: most points are in front of the cameras
    # that registered, and project inside their images
    for i in np.flatnonzero(scene.has_pose):
        uv, z = g.project(scene.K[i], scene.R[i], scene.t[i], scene.points3d, scene.dist[i])
        w, h = scene.sizes[i]
        seen = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        assert seen.mean() > 0.2
    # the finished model is reused, not recomputed
    mtime = (tmp_path / "sfm" / "model").stat().st_mtime_ns
    again = sfm.scene_from_images(root, tmp_path / "sfm")
    np.testing.assert_allclose(again.R, scene.R, atol=1e-6)
    assert (tmp_path / "sfm" / "model").stat().st_mtime_ns == mtime


def test_scene_from_reconstruction_converts_cameras(tmp_path):
    rec = pycolmap.Reconstruction()
    models = {
        "SIMPLE_RADIAL": [300.0, 160.0, 120.0, -0.05],
        "RADIAL": [310.0, 161.0, 119.0, -0.05, 0.01],
        "OPENCV": [300.0, 305.0, 160.0, 121.0, -0.05, 0.01, 1e-3, -1e-3],
        "PINHOLE": [300.0, 305.0, 160.0, 121.0],
    }
    X = np.random.default_rng(0).uniform([-1, -1, 3], [1, 1, 5], (20, 3))
    for i, (model, params) in enumerate(models.items()):
        cam = pycolmap.Camera(model=model, width=320, height=240, params=params,
                              camera_id=i + 1)
        rec.add_camera_with_trivial_rig(cam)
        R = g.axis_angle_to_rot(np.array([0.0, 0.1 * i, 0.0]))
        t = np.array([0.1 * i, 0.0, 0.0])
        im = pycolmap.Image(name=f"{i}.jpg", keypoints=np.zeros((0, 2)), camera_id=i + 1,
                            image_id=i + 1)
        rec.add_image_with_trivial_frame(im, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
    write_image(tmp_path / "x.jpg", np.zeros((10, 12, 3), np.float32))  # not registered
    with pytest.warns(UserWarning, match="did not register 1 of 5"):
        scene = sfm.scene_from_reconstruction(rec, tmp_path,
                                              [f"{i}.jpg" for i in range(4)] + ["x.jpg"])
    assert scene.has_pose.tolist() == [True] * 4 + [False]
    assert scene.sizes[4].tolist() == [12, 10]
    for i, model in enumerate(models):
        cam = rec.camera(i + 1)
        ours, _ = g.project(scene.K[i], np.eye(3), np.zeros(3), X, scene.dist[i])
        np.testing.assert_allclose(cam.img_from_cam(X), ours, atol=1e-6, err_msg=model)
        im = rec.image(i + 1)
        np.testing.assert_allclose(scene.R[i], im.cam_from_world().rotation.matrix(),
                                   atol=1e-12)


def test_bad_image_folders(tmp_path):
    with pytest.raises(VrsError, match="image folder not found"):
        sfm.scene_from_images(tmp_path / "missing", tmp_path / "work")
    (tmp_path / "empty").mkdir()
    with pytest.raises(VrsError, match="no images"):
        sfm.scene_from_images(tmp_path / "empty", tmp_path / "work")
    with pytest.raises(VrsError, match="image not found"):
        sfm.run_sfm(tmp_path / "empty", tmp_path / "work", ["a.jpg"])


def test_blank_images_register_nothing(tmp_path):
    """Two featureless images: COLMAP finds no pair; a VrsError, not a crash."""
    for k in range(2):
        write_image(tmp_path / "img" / f"{k}.png", np.full((60, 80, 3), 0.5, np.float32))
    with pytest.raises(VrsError, match="registered no images"):
        sfm.run_sfm(tmp_path / "img", tmp_path / "work")
