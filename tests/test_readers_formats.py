"""Readers for COLMAP, NeRF, LLFF, Aachen and Cambridge: the real samples in ../shared/data
(acceptance checks) and small fixtures with known ground truth written to tmp_path."""

from __future__ import annotations

import json
import warnings

import cv2
import numpy as np
import pycolmap
import pytest
from conftest import SHARED_DATA, shared_path

from vrs_jax import geometry as g
from vrs_jax.data.readers import FORMATS, load_scene
from vrs_jax.data.readers._common import image_size
from vrs_jax.data.readers.nvm import read_nvm

MAUPERTUIS = ("kapture_samples", "samples", "maupertuis", "colmap")
AACHEN = ("kapture_samples", "samples", "Aachen-Day-Night")
FERN = ("llff_fern", "data", "nerf_llff_data", "fern")
LEGO = ("nerf_synthetic_lego_200",)
rng = np.random.default_rng(0)


def test_formats_registry():
    assert FORMATS == ("7scenes", "cambridge", "aachen", "nerf", "llff", "colmap")


# ----------------------------------------------------------------------------- COLMAP


def test_maupertuis_reprojection_against_pycolmap_observations(capsys):
    """Acceptance: the model's points projected with the poses read land on the stored 2D
    observations (pycolmap's own parse of images.txt/points3D.txt is the reference)."""
    root = shared_path(*MAUPERTUIS)
    s = load_scene("colmap", root / "reconstruction")
    assert s.names == ["00.jpg", "01.jpg", "02.jpg", "03.jpg"]
    assert all(p.parent == root / "images" for p in s.image_paths)
    np.testing.assert_array_equal(s.sizes, np.tile([1919, 1079], (4, 1)))
    assert s.points3d.shape == (1039, 3)
    rec = pycolmap.Reconstruction(str(root / "reconstruction"))
    by_name = {im.name: im for im in rec.images.values()}
    meds = []
    for i, name in enumerate(s.names):
        im = by_name[name]
        obs = [p for p in im.points2D if p.has_point3D()]
        xy = np.array([p.xy for p in obs])
        X = np.array([rec.points3D[p.point3D_id].xyz for p in obs])
        uv, z = g.project(s.K[i], s.R[i], s.t[i], X, s.dist[i])
        assert (z > 0).all()
        meds.append(np.median(np.linalg.norm(uv - xy, axis=1)))
    with capsys.disabled():
        print(f"\nmaupertuis median reprojection error per image (px): {np.round(meds, 3)}")
    assert max(meds) < 1.0
    # Poses equal the quaternions/translations written in images.txt (parsed here by hand).
    lines = [ln.split() for ln in (root / "reconstruction" / "images.txt").read_text()
             .splitlines() if ln and not ln.startswith("#")][::2]
    for parts in lines:
        i = s.names.index(parts[9])
        # (6-digit quaternions: pycolmap normalises them in float64 its own way)
        np.testing.assert_allclose(s.R[i], g.quat_to_rot(np.array(parts[1:5], float)),
                                   atol=1e-5)
        np.testing.assert_allclose(s.t[i], np.array(parts[5:8], float), atol=1e-9)


def write_text_model(model_dir, img_dir):
    """A COLMAP text model with one image per supported camera model; returns its params."""
    model_dir.mkdir(parents=True)
    img_dir.mkdir(parents=True, exist_ok=True)
    cams = [("SIMPLE_PINHOLE", [70.0, 31.0, 24.5]),
            ("PINHOLE", [72.0, 69.0, 32.0, 23.0]),
            ("SIMPLE_RADIAL", [75.0, 32.5, 24.0, -0.08]),
            ("RADIAL", [71.0, 30.0, 25.0, 0.05, -0.02]),
            ("OPENCV", [70.0, 73.0, 33.0, 22.0, -0.1, 0.03, 0.002, -0.001])]
    cam_lines, img_lines, poses = [], [], []
    for k, (model, params) in enumerate(cams, start=1):
        cam_lines.append(f"{k} {model} 64 48 " + " ".join(map(str, params)))
        R = g.axis_angle_to_rot(rng.normal(size=3) * 0.2)
        t = rng.normal(size=3)
        q = g.rot_to_quat(R)
        img_lines += [f"{k} {' '.join(map(str, q))} {' '.join(map(str, t))} {k} im{k}.png", ""]
        poses.append((R, t))
        # The image of camera 5 is stored at half the camera's size: K must follow it.
        size = (32, 24) if k == 5 else (64, 48)
        cv2.imwrite(str(img_dir / f"im{k}.png"), np.zeros((size[1], size[0], 3), np.uint8))
    (model_dir / "cameras.txt").write_text("\n".join(cam_lines) + "\n")
    (model_dir / "images.txt").write_text("\n".join(img_lines) + "\n")
    (model_dir / "points3D.txt").write_text("1 0.5 0.2 4.0 255 0 0 0.1\n2 -1 0 5 0 0 0 0.2\n")
    return cams, poses


def test_colmap_camera_models_match_pycolmap_projection(tmp_path):
    cams, poses = write_text_model(tmp_path / "proj" / "sparse" / "0", tmp_path / "proj" / "images")
    s = load_scene("colmap", tmp_path / "proj")  # finds sparse/0 and ../../images
    assert s.names == [f"im{k}.png" for k in range(1, 6)]
    np.testing.assert_allclose(s.points3d, [[0.5, 0.2, 4.0], [-1, 0, 5]])
    Xc = np.concatenate([rng.uniform(-0.4, 0.4, (50, 2)), np.ones((50, 1))], 1) * \
        rng.uniform(1, 5, (50, 1))
    for k, (model, params) in enumerate(cams):
        R, t = poses[k]
        np.testing.assert_allclose(s.R[k], R, atol=1e-9)
        np.testing.assert_allclose(s.t[k], t, atol=1e-12)
        ref = pycolmap.Camera(model=model, width=64, height=48, params=params).img_from_cam(Xc)
        Xw = g.transform_points(*g.pose_inverse(R, t), Xc)
        uv, _ = g.project(s.K[k], s.R[k], s.t[k], Xw, s.dist[k])
        if model == "OPENCV":  # image at half size: coordinates halve (COLMAP convention)
            ref = ref * 0.5
            np.testing.assert_array_equal(s.sizes[k], [32, 24])
        np.testing.assert_allclose(uv, ref, atol=1e-8, err_msg=model)


def test_colmap_binary_equals_text(tmp_path):
    root = shared_path(*MAUPERTUIS)
    rec = pycolmap.Reconstruction(str(root / "reconstruction"))
    (tmp_path / "bin").mkdir()
    rec.write_binary(str(tmp_path / "bin"))
    assert (tmp_path / "bin" / "images.bin").is_file()
    a = load_scene("colmap", root / "reconstruction")
    b = load_scene("colmap", tmp_path / "bin", images=root / "images", query_every=2)
    assert a.names == b.names
    for f in ("K", "dist", "R", "t", "sizes", "points3d"):
        np.testing.assert_allclose(getattr(b, f), getattr(a, f), err_msg=f)
    np.testing.assert_array_equal(b.is_query, [True, False, True, False])


# ----------------------------------------------------------------------------- NeRF


def test_lego_cameras_on_sphere_looking_at_origin(capsys):
    """Acceptance: every camera centre at radius ~4.03 and its optical axis through the origin;
    the focal follows the 200x200 images."""
    s = load_scene("nerf", shared_path(*LEGO), split="train")
    assert len(s) == 100 and s.names[0] == "train/r_0.png"
    np.testing.assert_array_equal(s.sizes, np.tile([200, 200], (100, 1)))
    meta = json.loads((SHARED_DATA.joinpath(*LEGO) / "transforms_train.json").read_text())
    f = 0.5 * 200 / np.tan(0.5 * meta["camera_angle_x"])
    np.testing.assert_allclose(s.K[:, 0, 0], f)
    np.testing.assert_allclose(s.K[:, :2, 2], 100.0)
    assert s.background == (1.0, 1.0, 1.0)
    r = np.linalg.norm(s.centers, axis=1)
    with capsys.disabled():
        print(f"\nlego camera radius: {r.min():.6f} .. {r.max():.6f}")
    np.testing.assert_allclose(r, 4.0311, atol=1e-3)
    # The origin projects to the principal point, in front of every camera.
    uv, z = g.project(s.K, s.R, s.t, np.zeros((100, 1, 3)))
    np.testing.assert_allclose(uv[:, 0], 100.0, atol=1e-2)
    np.testing.assert_allclose(z[:, 0], r, rtol=1e-6)
    # OpenGL -> OpenCV: the world z axis (Blender's up) points up in the images (v decreases).
    uv_up, _ = g.project(s.K, s.R, s.t, np.tile([[0.0, 0.0, 0.5]], (100, 1, 1)))
    assert (uv_up[:, 0, 1] < 100).all()


def test_lego_query_every_and_downscale():
    s = load_scene("nerf", shared_path(*LEGO), query_every=8, downscale=2)
    assert s.is_query.sum() == 13  # 100 frames by name: r_0, r_1, r_10, r_11, ...
    names_sorted = sorted(s.names)
    assert [names_sorted[k] for k in range(0, 100, 8)] == sorted(np.array(s.names)[s.is_query])
    np.testing.assert_array_equal(s.sizes[0], [100, 100])
    full = load_scene("nerf", shared_path(*LEGO))
    np.testing.assert_allclose(s.K, g.scale_intrinsics(full.K, 0.5))


def make_rgba(path, w, h):
    img = np.zeros((h, w, 4), np.uint8)
    img[..., 3] = 128
    cv2.imwrite(str(path), img)


def test_instant_ngp_style_scaling_per_frame_and_missing(tmp_path):
    (tmp_path / "images").mkdir()
    poses_cv = []
    frames = []
    for k in range(4):
        R = g.axis_angle_to_rot(rng.normal(size=3))
        c = rng.normal(size=3)
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R.T, c  # OpenCV camera-to-world
        poses_cv.append((R, c))
        gl = M * np.array([1, -1, -1, 1])  # the same camera in OpenGL axes
        fr = {"file_path": f"images/{k:04d}", "transform_matrix": gl.tolist()}
        if k == 1:
            fr.update(fl_x=300.0, fl_y=310.0, cx=190.0, cy=150.0)
        frames.append(fr)
        if k != 3:  # frame 3's image is missing
            make_rgba(tmp_path / "images" / f"{k:04d}.png", 80, 60)  # half of w x h
    meta = {"fl_x": 200.0, "fl_y": 210.0, "cx": 161.0, "cy": 119.0, "w": 160, "h": 120,
            "k1": 0.1, "k2": -0.01, "p1": 0.001, "p2": 0.002, "frames": frames}
    (tmp_path / "transforms.json").write_text(json.dumps(meta))
    with pytest.warns(UserWarning, match=r"missing.*images/0003"):
        s = load_scene("nerf", tmp_path, background=(0.0, 0.5, 1.0))
    assert s.names == ["images/0000.png", "images/0001.png", "images/0002.png"]
    assert s.background == (0.0, 0.5, 1.0)
    np.testing.assert_allclose(s.K[0], [[100, 0, 80.5], [0, 105, 59.5], [0, 0, 1]])
    np.testing.assert_allclose(s.K[1], [[150, 0, 95], [0, 155, 75], [0, 0, 1]])
    np.testing.assert_allclose(s.dist[0], [0.1, -0.01, 0.001, 0.002, 0.0])
    for k in range(3):
        np.testing.assert_allclose(s.R[k], poses_cv[k][0], atol=1e-12)
        np.testing.assert_allclose(s.centers[k], poses_cv[k][1], atol=1e-12)


def test_nerf_splits_give_queries(tmp_path):
    (tmp_path / "train").mkdir()
    (tmp_path / "test").mkdir()
    for split, n in (("train", 3), ("test", 2)):
        frames = []
        for k in range(n):
            make_rgba(tmp_path / split / f"r_{k}.png", 8, 8)
            M = np.eye(4)
            M[2, 3] = 4.0
            frames.append({"file_path": f"./{split}/r_{k}", "transform_matrix": M.tolist()})
        (tmp_path / f"transforms_{split}.json").write_text(
            json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    s = load_scene("nerf", tmp_path)
    assert len(s) == 5 and s.is_query.sum() == 2
    assert all(n.startswith("test/") for n in np.array(s.names)[s.is_query])
    s = load_scene("nerf", tmp_path, split="test")
    assert len(s) == 2 and s.is_query.all()


# ----------------------------------------------------------------------------- LLFF


def test_fern_poses_bounds_and_focal(capsys):
    """Acceptance: 20 poses, focal scaled to images_8, the sparse points seen by each camera lie
    inside its near/far bounds (LLFF derives them from those points' depths)."""
    root = shared_path(*FERN)
    s = load_scene("llff", root)
    assert len(s) == 20 and s.names[0] == "IMG_4026.png"
    assert all(p.parent.name == "images_8" for p in s.image_paths)
    np.testing.assert_array_equal(s.sizes, np.tile([504, 378], (20, 1)))
    pb = np.load(root / "poses_bounds.npy")
    np.testing.assert_allclose(s.K[:, 0, 0], pb[:, 14] / 8)
    np.testing.assert_allclose(s.K[0, 0, 0], 407.57, atol=0.01)
    np.testing.assert_allclose(s.K[:, :2, 2], np.tile([252.0, 189.0], (20, 1)))
    assert s.bounds.shape == (20, 2) and (s.bounds[:, 0] > 0).all()
    assert (s.bounds[:, 0] < s.bounds[:, 1]).all()
    # Camera centres are the 4th column of the LLFF matrices.
    np.testing.assert_allclose(s.centers, pb[:, :15].reshape(20, 3, 5)[:, :, 3], atol=1e-9)
    fractions = []
    for i in range(20):
        uv, z = g.project(s.K[i], s.R[i], s.t[i], s.points3d)
        w, h = s.sizes[i]
        seen = (z > 0) & (uv[:, 0] > 0) & (uv[:, 1] > 0) & (uv[:, 0] < w) & (uv[:, 1] < h)
        assert seen.mean() > 0.9  # forward-facing: nearly every point is in view
        zs = z[seen]
        fractions.append(np.mean((zs >= s.bounds[i, 0] * 0.95) & (zs <= s.bounds[i, 1] * 1.05)))
    with capsys.disabled():
        print(f"\nfern: fraction of in-view sparse points within [0.95 near, 1.05 far]: "
              f"min {min(fractions):.4f}")
    assert min(fractions) > 0.98


def test_llff_axes_factor_and_query_every(tmp_path):
    """LLFF matrices built from known OpenCV poses: columns [down, right, back] = [y, x, -z]."""
    n, H, W, f = 5, 240, 320, 300.0
    rows, gt = [], []
    for _ in range(n):
        R = g.axis_angle_to_rot(rng.normal(size=3))  # world-to-camera
        c = rng.normal(size=3)
        x, y, z = R  # camera axes in world coordinates (rows of R)
        M = np.stack([y, x, -z, c, [H, W, f]], axis=1)  # [3, 5]
        rows.append(np.concatenate([M.ravel(), [1.0, 10.0]]))
        gt.append((R, c))
    np.save(tmp_path / "poses_bounds.npy", np.stack(rows))
    for folder, size in (("images_4", (80, 60)), ("images_8", (40, 30))):
        (tmp_path / folder).mkdir()
        for k in range(n):
            cv2.imwrite(str(tmp_path / folder / f"IMG_{k}.JPG"), np.zeros(size[::-1] + (3,),
                                                                        np.uint8))
    s = load_scene("llff", tmp_path, query_every=2)  # smallest factor present: 4
    assert s.image_paths[0].parent.name == "images_4" and s.points3d is None
    np.testing.assert_allclose(s.K[0], [[75, 0, 40], [0, 75, 30], [0, 0, 1]])
    for k, (R, c) in enumerate(gt):
        np.testing.assert_allclose(s.R[k], R, atol=1e-12)
        np.testing.assert_allclose(s.centers[k], c, atol=1e-12)
    np.testing.assert_array_equal(s.is_query, [True, False, True, False, True])
    np.testing.assert_allclose(s.bounds, np.tile([1.0, 10.0], (n, 1)))
    s8 = load_scene("llff", tmp_path, factor=8)
    np.testing.assert_allclose(s8.K[0], [[37.5, 0, 20], [0, 37.5, 15], [0, 0, 1]])


# ----------------------------------------------------------------------------- Aachen


def test_aachen_database_and_queries():
    root = shared_path(*AACHEN)
    s = load_scene("aachen", root)
    ref, qry = s.references(), s.queries()
    assert ref.names == ["db/1045.jpg", "db/4446.jpg", "db/1135.jpg"] and ref.has_pose.all()
    assert len(qry) == 4 and not qry.has_pose.any()
    i = s.names.index("query/day/milestone/2011-12-17_14-50-43_241.jpg")
    np.testing.assert_allclose(s.K[i], [[971.838, 0, 384], [0, 971.838, 512], [0, 0, 1]])
    np.testing.assert_allclose(s.dist[i], [-0.00177789, 0, 0, 0, 0])
    np.testing.assert_array_equal(s.sizes[i], [768, 1024])
    # NVM: focal at the stored size, principal point at the centre, k1 = -radial, t = -R c.
    np.testing.assert_allclose(s.K[0], [[1084.59, 0, 800], [0, 1084.59, 533.5], [0, 0, 1]])
    np.testing.assert_allclose(s.dist[:3, 0], [-0.0810989, -0.086426, -0.0794687])
    np.testing.assert_allclose(s.centers[0], [738.038, -6.17486, -41.8371], atol=1e-9)
    np.testing.assert_allclose(s.R[0], g.quat_to_rot(np.array(
        [-0.0305504, -0.212047, 0.12058, 0.969311])), atol=1e-12)
    assert s.points3d.shape == (5, 3)
    # kapture's conversion of the same data is an independent reference for t.
    np.testing.assert_allclose(s.t[0], [652.833568325199, 84.70595670766824, 336.3358355014467],
                               rtol=1e-5)
    # Original-size option: focal scaled by actual / original.
    s2 = load_scene("aachen", root, queries=[], nvm_max_side=3200, read_points=False,
                    query_every=2)
    assert len(s2) == 3 and s2.points3d is None
    np.testing.assert_allclose(s2.K[0, 0, 0], 1084.59 / 2)
    # Held-out database images (by name: 1045, 1135, 4446 -> every 2nd) keep their pose.
    assert s2.queries().names == ["db/1045.jpg", "db/4446.jpg"] and s2.has_pose.all()


def test_nvm_parser_tracks():
    m = read_nvm(shared_path(*AACHEN) / "3D-models" / "aachen_cvpr2018_db.nvm")
    assert m.names == ["db/1045.jpg", "db/4446.jpg", "db/1135.jpg"]
    assert m.points.shape == (5, 3) and len(m.obs_point) == 4 + 4 + 3 + 3 + 13
    np.testing.assert_array_equal(m.obs_image[:4], [1, 0, 0, 0])
    np.testing.assert_allclose(m.obs_uv[0], [980.898, 247.696])


# ----------------------------------------------------------------------------- Cambridge


def write_cambridge(root, n=4, size=(96, 54)):
    """Cambridge-like scene: split files, NVM with .jpg names for .png images (1920x1080
    focals), one garbage pose. Returns ground truth [(R, c)] and focals."""
    (root / "seq1").mkdir(parents=True)
    gt, cams = [], []
    focals = 1600 + 20 * np.arange(n)
    for k in range(n):
        R = g.axis_angle_to_rot(rng.normal(size=3))
        c = rng.normal(size=3) * 10
        gt.append((R, c))
        q = pycolmap.Rotation3d(R).quat  # x y z w: an independent quaternion
        qw = [q[3], q[0], q[1], q[2]]
        cv2.imwrite(str(root / "seq1" / f"frame{k:05d}.png"),
                    np.zeros((size[1], size[0], 3), np.uint8))
        cams.append(f"seq1/frame{k:05d}.jpg {focals[k]} {' '.join(map(str, qw))} "
                    f"{' '.join(map(str, c))} {0.01 * k} 0")
    lines = [f"seq1/frame{k:05d}.png {' '.join(map(str, gt[k][1]))} "
             f"{' '.join(map(str, g.rot_to_quat(gt[k][0])))}" for k in range(n)]
    header = "Visual Landmark Dataset V1\nImageFile, Camera Position [X Y Z W P Q R]\n\n"
    (root / "dataset_train.txt").write_text(header + "\n".join(lines[:-1]) + "\n")
    cv2.imwrite(str(root / "seq1" / "frame99999.png"), np.zeros((54, 96, 3), np.uint8))
    bad = "seq1/frame99999.png 1e5 2e5 3 1 0 0 0"
    (root / "dataset_test.txt").write_text(header + lines[-1] + "\n" + bad + "\n")
    (root / "reconstruction.nvm").write_text(
        "NVM_V3\n\n" + f"{n}\n" + "\n".join(cams) + "\n\n1\n1 2 3 255 0 0 1 0 7 10.5 -3.0\n\n0\n")
    return gt, focals


def test_cambridge_split_nvm_intrinsics_and_dropped_pose(tmp_path):
    gt, focals = write_cambridge(tmp_path)
    with pytest.warns(UserWarning, match=r"dropped \(1\): seq1/frame99999.png"):
        s = load_scene("cambridge", tmp_path)
    assert s.names == [f"seq1/frame{k:05d}.png" for k in range(4)]
    np.testing.assert_array_equal(s.is_query, [False, False, False, True])
    for k, (R, c) in enumerate(gt):
        np.testing.assert_allclose(s.R[k], R, atol=1e-12)
        np.testing.assert_allclose(s.t[k], -R @ c, atol=1e-9)
        f = focals[k] * 96 / 1920  # NVM focal at 1920x1080 scaled to the 96x54 images
        np.testing.assert_allclose(s.K[k], [[f, 0, 48], [0, f, 27], [0, 0, 1]])
        np.testing.assert_allclose(s.dist[k, 0], -0.01 * k)
    np.testing.assert_allclose(s.points3d, [[1, 2, 3]])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s2 = load_scene("cambridge", tmp_path, focal=70.0)
    np.testing.assert_allclose(s2.K[:, 0, 0], 70.0)
    # Intrinsics from a COLMAP model of 192x108 frames (twice the images), .jpg names.
    model = tmp_path / "colmap"
    model.mkdir()
    (model / "cameras.txt").write_text("".join(
        f"{k + 1} SIMPLE_RADIAL 192 108 {150 + k} 96 54 {0.01 * k}\n" for k in range(4)))
    (model / "images.txt").write_text("".join(
        f"{k + 1} 1 0 0 0 0 0 0 {k + 1} seq1/frame{k:05d}.jpg\n\n" for k in range(4)))
    (model / "points3D.txt").write_text("")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s3 = load_scene("cambridge", tmp_path, colmap=model)
    np.testing.assert_allclose(s3.K[:, 0, 0], (150 + np.arange(4)) / 2)
    np.testing.assert_allclose(s3.K[:, :2, 2], np.tile([48.0, 27.0], (4, 1)))
    np.testing.assert_allclose(s3.dist[:, 0], 0.01 * np.arange(4))
    np.testing.assert_allclose(s3.R, s.R)  # poses still come from the split files


# ----------------------------------------------------------------------------- image sizes


def test_header_image_size_matches_decoding(tmp_path):
    files = []
    for ext in ("jpg", "png"):
        files += sorted(SHARED_DATA.glob(f"**/*.{ext}"))[:40]
    img = rng.integers(0, 255, (37, 53, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "p.jpg"), img, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])
    cv2.imwrite(str(tmp_path / "b.jpg"), img)
    cv2.imwrite(str(tmp_path / "d.png"), np.zeros((37, 53), np.uint16))
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((37, 53, 4), np.uint8))
    cv2.imwrite(str(tmp_path / "x.bmp"), img)
    files += sorted(tmp_path.iterdir())
    for f in files:
        ref = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
        assert image_size(f) == (ref.shape[1], ref.shape[0]), f


def test_query_range_holds_out_a_stretch_in_name_order():
    """query_range A:B makes the A-th..(B-1)-th images by name queries, on top of query_every;
    out-of-range or malformed ranges are one VrsError."""
    from vrs_jax.errors import VrsError

    root = shared_path(*LEGO)
    base = load_scene("nerf", root, query_every=8)
    s = load_scene("nerf", root, query_every=8, query_range="3:9")
    order = np.argsort(np.asarray(s.names, dtype=object), kind="stable")
    expect = base.is_query.copy()
    expect[order[3:9]] = True
    np.testing.assert_array_equal(s.is_query, expect)
    for bad in ("9:3", "0:100000", "x:4", "5"):
        with pytest.raises(VrsError, match="query_range"):
            load_scene("nerf", root, query_range=bad)
    with pytest.raises(VrsError, match="no reference"):
        load_scene("nerf", root, query_range=f"0:{len(base)}")
