"""Bad input to the readers: every case raises VrsError naming the file (and line)."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest
from conftest import shared_path

from vrs_jax.data.depth import depth_reprojection_errors
from vrs_jax.data.images import read_image
from vrs_jax.data.readers import FORMATS, load_scene
from vrs_jax.errors import VrsError

POSE = "1 0 0 0.5\r\n0 1 0 0\r\n0 0 1 0\r\n0 0 0 1\r\n"


def seven(root, n=2, pose=POSE):
    """Minimal 7-Scenes folder: seq-01 with n frames, split files."""
    (root / "seq-01").mkdir(parents=True)
    for k in range(n):
        cv2.imwrite(str(root / "seq-01" / f"frame-{k:06d}.color.png"), np.zeros((6, 8, 3),
                                                                               np.uint8))
        (root / "seq-01" / f"frame-{k:06d}.pose.txt").write_text(pose)
    (root / "TrainSplit.txt").write_text("sequence1\n")
    (root / "TestSplit.txt").write_text("")
    return root


def raises(match_path, *args, line=None, problem=None, **kw):
    with pytest.raises(VrsError) as ei:
        load_scene(*args, **kw)
    msg = str(ei.value)
    where = str(match_path) + (f":{line}:" if line is not None else "")
    assert where in msg, msg
    if problem is not None:
        assert problem in msg, msg
    assert "\n" not in msg
    return msg


def test_unknown_format_and_option(tmp_path):
    with pytest.raises(VrsError, match="unknown dataset format 'sevenscenes'.*7scenes"):
        load_scene("sevenscenes", tmp_path)
    seven(tmp_path)
    raises(tmp_path, "7scenes", tmp_path, problem="unknown option(s) focal", focal=500)
    raises(tmp_path, "7scenes", tmp_path, problem="downscale", downscale=0)
    raises(tmp_path, "7scenes", tmp_path, problem="query_every", query_every=-1)


@pytest.mark.parametrize("fmt", FORMATS)
def test_missing_folder(tmp_path, fmt):
    missing = tmp_path / "nope"
    raises(missing, fmt, missing, problem="not found")


def test_7scenes_malformed_pose_lines(tmp_path):
    root = seven(tmp_path / "a")
    pose = root / "seq-01" / "frame-000001.pose.txt"
    pose.write_text("1 0 0 0.5\n0 1 x 0\n0 0 1 0\n0 0 0 1\n")
    raises(pose, "7scenes", root, line=2, problem="malformed pose row")
    pose.write_text("1 0 0 0.5\n0 1 0 0\n0 0 1\n0 0 0 1\n")
    raises(pose, "7scenes", root, line=3, problem="expected 4 numbers, got 3")
    pose.write_text("1 0 0 0.5\n0 1 0 0\n0 0 1 0\n")
    raises(pose, "7scenes", root, problem="4 rows")
    pose.write_text("2 0 0 0.5\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    raises(pose, "7scenes", root, problem="not a rotation")
    pose.unlink()
    raises(pose, "7scenes", root, problem="pose file not found")


def test_7scenes_split_pgt_and_sequences(tmp_path):
    root = seven(tmp_path / "a")
    (root / "TestSplit.txt").write_text("sequence2\n")
    raises(root / "seq-02", "7scenes", root, problem="not found")
    (root / "TestSplit.txt").write_text("seq two\n")
    raises(root / "TestSplit.txt", "7scenes", root, line=1, problem="malformed split line")
    (root / "TestSplit.txt").write_text("")
    pgt = tmp_path / "pgt.txt"
    pgt.write_text("seq-01/frame-000000.color.png 1 0 0 0 0 0 0 525\n"
                   "seq-01/frame-000001.color.png 1 0 0 0 0 0 525\n")
    raises(pgt, "7scenes", root, line=2, problem="malformed pose line", pgt=pgt)
    pgt.write_text("seq-01/frame-000000.color.png 1 0 0 0 0 0 0 nan\n")
    raises(pgt, "7scenes", root, line=1, problem="malformed pose line", pgt=pgt)
    (root / "intrinsics.txt").write_text("500 500 4 3\n")
    raises(root / "intrinsics.txt", "7scenes", root, line=1, problem="fx fy cx cy width height")


def test_unreadable_images(tmp_path):
    root = seven(tmp_path / "a")
    bad = root / "seq-01" / "frame-000001.color.png"
    bad.write_text("this is not a PNG")
    raises(bad, "7scenes", root, problem="unreadable image")
    with pytest.raises(VrsError, match="unreadable image"):
        read_image(bad)
    ok, buf = cv2.imencode(".jpg", np.zeros((6, 8, 3), np.uint8))
    bad.unlink()
    truncated = root / "seq-01" / "frame-000001.color.jpg"
    truncated.write_bytes(buf.tobytes()[:20])  # JPEG header cut before the frame header
    raises(truncated, "7scenes", root, problem="unreadable image")


def test_cambridge_errors(tmp_path):
    root = tmp_path / "c"
    (root / "seq1").mkdir(parents=True)
    cv2.imwrite(str(root / "seq1" / "f1.png"), np.zeros((6, 8, 3), np.uint8))
    head = "Visual Landmark Dataset V1\nImageFile, Camera Position [X Y Z W P Q R]\n\n"
    split = root / "dataset_train.txt"
    split.write_text(head + "seq1/f1.png 1 2 3 1 0 0\n")
    raises(split, "cambridge", root, line=4, problem="expected 'name X Y Z W P Q R'")
    split.write_text(head + "seq1/f1.png 1 2 3 1 0 0 zero\n")
    raises(split, "cambridge", root, line=4, problem="malformed pose line")
    split.write_text(head + "seq1/f1.png 1 2 3 1 0 0 0\n")
    raises(root / "reconstruction.nvm", "cambridge", root, problem="NVM model not found")
    nvm = root / "reconstruction.nvm"
    nvm.write_text("NVM_V3\n\n1\nseq1/f1.jpg 1600 1 0 0\n")
    raises(nvm, "cambridge", root, line=4, problem="malformed NVM camera line")
    nvm.write_text("NVM_V3\n\n1\nseq1/f2.jpg 1600 1 0 0 0 1 2 3 0 0\n")
    raises(nvm, "cambridge", root, problem="no camera in the NVM model")
    nvm.write_text("NVM_V2\n")
    raises(nvm, "cambridge", root, line=1, problem="not an NVM_V3 file")
    nvm.write_text("NVM_V3_R9T\n\n0\n")
    raises(nvm, "cambridge", root, line=1, problem="not supported")
    nvm.write_text("NVM_V3\n\n1\nseq1/f1.jpg 1600 1 0 0 0 1 2 3 0 0\n\n1\n1 2 3 4 5 6 1 7 0 1 2\n")
    raises(nvm, "cambridge", root, line=7, problem="camera index out of range")
    split.write_text(head + "seq1/missing.png 1 2 3 1 0 0 0\n")
    raises(root / "seq1" / "missing.png", "cambridge", root, problem="not found", focal=500.0)


def test_aachen_errors(tmp_path):
    src = shared_path("kapture_samples", "samples", "Aachen-Day-Night")
    root = tmp_path / "aachen"
    shutil.copytree(src, root)
    ql = root / "queries" / "day_time_queries_with_intrinsics.txt"
    lines = ql.read_text().splitlines()
    lines[2] = lines[2].replace("SIMPLE_RADIAL", "OPENCV_FISHEYE")
    ql.write_text("\n".join(lines) + "\n")
    raises(ql, "aachen", root, line=3, problem="unsupported camera model OPENCV_FISHEYE")
    lines[2] = "query/day/x.jpg SIMPLE_RADIAL 1024 768 977 512 oops 0.04"
    ql.write_text("\n".join(lines) + "\n")
    raises(ql, "aachen", root, line=3, problem="malformed query line")
    db = root / "images_upright" / "db" / "4446.jpg"
    db.unlink()
    raises(db, "aachen", root, problem="not found", queries=[])


def test_colmap_errors(tmp_path):
    fern_model = shared_path("llff_fern", "data", "nerf_llff_data", "fern", "sparse", "0")
    raises(fern_model, "colmap", fern_model, problem="images.bin / images.txt missing")
    root = tmp_path / "m"
    root.mkdir()
    (root / "cameras.txt").write_text("1 FULL_OPENCV 8 6 5 5 4 3 0 0 0 0 0 0.1 0 0\n")
    (root / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n\n")
    (root / "points3D.txt").write_text("")
    (tmp_path / "images").mkdir()
    cv2.imwrite(str(tmp_path / "images" / "a.png"), np.zeros((6, 8, 3), np.uint8))
    raises(root, "colmap", root, problem="FULL_OPENCV camera with k4, k5, k6 = 0.1, 0, 0")
    (root / "cameras.txt").write_text("1 OPENCV_FISHEYE 8 6 5 5 4 3 0 0 0 0\n")
    raises(root, "colmap", root, problem="unsupported camera model OPENCV_FISHEYE")
    (root / "cameras.txt").write_text("1 PINHOLE 8 6 5 5 4 3\n")
    raises(tmp_path / "elsewhere", "colmap", root, problem="images folder not found",
           images=tmp_path / "elsewhere")
    (root / "cameras.txt").write_text("1 PINHOLE 8 6 5 x 4 3\n")
    raises(root / "cameras.txt", "colmap", root, line=1,
           problem="malformed camera line: expected numbers")
    raises(tmp_path / "images", "colmap", tmp_path / "images", problem="no COLMAP model")


def test_nerf_errors(tmp_path):
    tf = tmp_path / "transforms.json"
    tf.write_text('{"camera_angle_x": 0.7,\n "frames": [\n {"file_path": "a"},,]}')
    raises(tf, "nerf", tmp_path, line=3, problem="malformed JSON")
    eye = np.eye(4).tolist()
    tf.write_text(json.dumps({"camera_angle_x": 0.7,
                              "frames": [{"file_path": "a", "transform_matrix": eye}]}))
    with pytest.warns(UserWarning, match="missing"):
        raises(tf, "nerf", tmp_path, problem="no frame with an existing image file")
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((6, 8, 3), np.uint8))
    tf.write_text(json.dumps({"frames": [{"file_path": "a", "transform_matrix": eye}]}))
    raises(tf, "nerf", tmp_path, problem="no intrinsics")
    tf.write_text(json.dumps({"camera_angle_x": 0.7,
                              "frames": [{"file_path": "a", "transform_matrix": [[1, 0]]}]}))
    raises(tf, "nerf", tmp_path, problem="transform_matrix must be")
    tf.write_text(json.dumps({"fl_x": 5, "camera_model": "OPENCV_FISHEYE",
                              "frames": [{"file_path": "a", "transform_matrix": eye}]}))
    raises(tf, "nerf", tmp_path, problem="unsupported camera_model")
    raises(tmp_path / "transforms_val.json", "nerf", tmp_path, split="val", problem="not found")


def test_llff_errors(tmp_path):
    src = shared_path("llff_fern", "data", "nerf_llff_data", "fern")
    root = tmp_path / "fern"
    (root / "images_8").mkdir(parents=True)
    for p in sorted((src / "images_8").iterdir())[:19]:
        shutil.copy(p, root / "images_8" / p.name)
    raises(root / "poses_bounds.npy", "llff", root, problem="not found")
    shutil.copy(src / "poses_bounds.npy", root / "poses_bounds.npy")
    raises(root / "images_8", "llff", root, problem="19 images but 20 rows")
    raises(root / "images_4", "llff", root, factor=4, problem="not found")
    np.save(root / "poses_bounds.npy", np.zeros((19, 15)))
    raises(root / "poses_bounds.npy", "llff", root, problem="[N, 17]")
    (root / "poses_bounds.npy").write_text("garbage")
    raises(root / "poses_bounds.npy", "llff", root, problem="unreadable .npy")


def test_depth_check_without_depth(tmp_path):
    root = seven(tmp_path / "a")
    s = load_scene("7scenes", root)
    with pytest.raises(VrsError, match="has no depth map"):
        depth_reprojection_errors(s, 0, 1)


@pytest.mark.parametrize("fmt", ["llff", "nerf"])
def test_an_unreadable_query_image_is_flagged_later_not_fatal_here(fmt, tmp_path):
    """A query image that exists but is not an image (empty here) gives a scene: the reader
    takes its size from the dataset (or the other images) and reading it at localization is
    what flags it, so the other queries are localized; an unreadable map image still stops."""
    from vrs_jax import geometry as g
    from vrs_jax.data.images import read_gray

    n, rng = 4, np.random.default_rng(0)
    folder = tmp_path / ("images" if fmt == "llff" else "train")
    folder.mkdir()
    rows, frames = [], []
    for k in range(n):
        cv2.imwrite(str(folder / f"IMG_{k}.png"), np.full((30, 40, 3), 100, np.uint8))
        R, c = g.axis_angle_to_rot(rng.normal(size=3)), rng.normal(size=3)
        x, y, z = R
        rows.append(np.concatenate([np.stack([y, x, -z, c, [30, 40, 35.0]], 1).ravel(),
                                    [1.0, 10.0]]))
        M = np.eye(4)
        M[2, 3] = 4.0
        frames.append({"file_path": f"./train/IMG_{k}", "transform_matrix": M.tolist()})
    np.save(tmp_path / "poses_bounds.npy", np.stack(rows))
    (tmp_path / "transforms_train.json").write_text(
        json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    s = load_scene(fmt, tmp_path, query_every=2)
    q = int(np.flatnonzero(s.is_query)[0])
    s.image_paths[q].write_bytes(b"")
    again = load_scene(fmt, tmp_path, query_every=2)
    np.testing.assert_array_equal(again.sizes, s.sizes)
    with pytest.raises(VrsError, match="IMG_"):
        read_gray(again.image_paths[q])
    ref = int(np.flatnonzero(~s.is_query)[0])
    s.image_paths[ref].write_bytes(b"")
    with pytest.raises(VrsError, match=s.image_paths[ref].name):
        load_scene(fmt, tmp_path, query_every=2)
