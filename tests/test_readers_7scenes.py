"""7-Scenes reader and the depth-consistency check, on the real stairs sample and on tiny
analytic scenes (a tilted plane seen by two cameras, written in the 7-Scenes layout)."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
from conftest import shared_path

from vrs_jax import geometry as g
from vrs_jax.data.depth import depth_reprojection_errors, sample_inverse_depth
from vrs_jax.data.images import write_depth
from vrs_jax.data.readers import load_scene

STAIRS = ("kapture_samples", "samples", "7scenes", "microsoft", "stairs")


def stairs():
    return load_scene("7scenes", shared_path(*STAIRS))


def test_stairs_layout_split_and_intrinsics():
    s = stairs()
    assert len(s) == 12 and s.format == "7scenes"
    # TrainSplit = sequence2, sequence3; TestSplit = sequence1, sequence4 (CRLF files).
    ref = {n.split("/")[0] for n in s.references().names}
    qry = {n.split("/")[0] for n in s.queries().names}
    assert ref == {"seq-02", "seq-03"} and qry == {"seq-01", "seq-04"}
    assert "seq-01/frame-000000.color.jpg" in s.names
    np.testing.assert_array_equal(s.sizes, np.tile([640, 480], (12, 1)))
    np.testing.assert_allclose(s.K[0], [[525, 0, 320], [0, 525, 240], [0, 0, 1]])
    np.testing.assert_allclose(s.depth_K[0], [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    assert s.depth_scale == 0.001 and all(p is not None and p.is_file() for p in s.depth_paths)
    # Pose file is camera-to-world: the reader's camera centre is its last column.
    i = s.names.index("seq-01/frame-000000.color.jpg")
    np.testing.assert_allclose(s.centers[i], [-1.4903377, -0.49737796, -0.054694783], atol=1e-6)
    np.testing.assert_allclose(s.R[i] @ s.R[i].T, np.eye(3), atol=1e-12)


def test_stairs_depth_consistency_within_sequences(capsys):
    """Acceptance: frame 0's depth seen from frame 2 of the same sequence, median < 3 cm."""
    s = stairs()
    lines = []
    for seq in ("seq-01", "seq-02", "seq-03", "seq-04"):
        i = s.names.index(f"{seq}/frame-000000.color.jpg")
        j = s.names.index(f"{seq}/frame-000002.color.jpg")
        e = depth_reprojection_errors(s, i, j, stride=4)
        base = np.linalg.norm(s.centers[i] - s.centers[j])
        lines.append(f"{seq} 0->2: median {np.median(e) * 100:.2f} cm over {e.size} px "
                     f"(baseline {base * 100:.1f} cm)")
        assert e.size > 5000
        assert np.median(e) < 0.03
    with capsys.disabled():
        print("\n" + "\n".join(lines))


def test_stairs_depth_consistency_across_sequences_and_negative_controls(capsys):
    """Wide-baseline pairs (about 45 degrees apart) make the check sensitive: the right
    conventions agree within 3 cm, wrong ones (pose not inverted, RGB focal for depth) fail."""
    s = stairs()
    pairs = [("seq-03/frame-000000.color.jpg", "seq-01/frame-000000.color.jpg"),
             ("seq-02/frame-000000.color.jpg", "seq-04/frame-000000.color.jpg")]
    Rw, tw = g.pose_inverse(s.R, s.t)
    wrong = {"pose not inverted": dataclasses.replace(s, R=Rw, t=tw),
             "depth with f=525": dataclasses.replace(s, depth_K=s.K)}
    out = []
    for a, b in pairs:
        i, j = s.names.index(a), s.names.index(b)
        _, angle = g.pose_errors(s.R[i], s.t[i], s.R[j], s.t[j])
        assert angle > 30
        med = np.median(depth_reprojection_errors(s, i, j, stride=4))
        out.append(f"{a} -> {b}: median {med * 100:.2f} cm (rotation {angle:.0f} deg)")
        assert med < 0.03
        for what, sc in wrong.items():
            e = depth_reprojection_errors(sc, i, j, stride=4)
            out.append(f"  {what}: median {np.median(e) * 100:.1f} cm")
            assert e.size == 0 or np.median(e) > 0.04
    with capsys.disabled():
        print("\n" + "\n".join(out))


def test_pgt_poses_override(tmp_path):
    root = shared_path(*STAIRS)
    base = load_scene("7scenes", root)
    i = base.names.index("seq-03/frame-000001.color.jpg")
    R = g.axis_angle_to_rot(np.array([0.1, -0.2, 0.3]))
    t = np.array([0.5, -1.0, 2.0])
    q = g.rot_to_quat(R)
    pgt = tmp_path / "pgt.txt"
    # Names in published pseudo-GT files end in .color.png; the sample's frames are .jpg.
    pgt.write_text("# name qw qx qy qz tx ty tz f\n"
                   f"seq-03/frame-000001.color.png {' '.join(map(str, q))} "
                   f"{' '.join(map(str, t))} 530.5\n"
                   "seq-99/frame-000000.color.png 1 0 0 0 0 0 0 500\n")
    with pytest.warns(UserWarning, match="11 of 12 images have no pseudo-ground-truth"):
        s = load_scene("7scenes", root, pgt=pgt)
    np.testing.assert_allclose(s.R[i], R, atol=1e-12)
    np.testing.assert_allclose(s.t[i], t)
    np.testing.assert_allclose(s.K[i], [[530.5, 0, 320], [0, 530.5, 240], [0, 0, 1]])
    others = np.arange(len(s)) != i
    np.testing.assert_array_equal(s.R[others], base.R[others])
    np.testing.assert_array_equal(s.K[others], base.K[others])


# ----------------------------------------------------------------- analytic plane scene

PLANE_N = np.array([0.2, -0.3, 1.0]) / np.linalg.norm([0.2, -0.3, 1.0])
PLANE_D = 3.0  # plane {X : n . X = d}


def plane_depth(K, R, t, w, h):
    """z-depth [h, w] of the plane seen by camera (K, R, t), from the ray intersection."""
    uv = g.pixel_grid(w, h).reshape(-1, 2)
    o, d = g.pixel_rays(K, R, t, uv)
    lam = (PLANE_D - o @ PLANE_N) / (d @ PLANE_N)  # d has camera z = 1: lam is z-depth
    return lam.reshape(h, w)


def write_plane_scene(root, size=(64, 48), intr_size=(128, 96)):
    """Two frames of a tilted plane in the 7-Scenes layout, intrinsics.txt at 2x size."""
    w, h = size
    fx, fy, cx, cy = 100.0, 104.0, 64.0, 48.0
    (root / "seq-01").mkdir(parents=True)
    K = g.scale_intrinsics(g.intrinsics_matrix(fx, fy, cx, cy), w / intr_size[0],
                           h / intr_size[1])
    poses = [(g.axis_angle_to_rot(np.array([0.02, 0.05, 0.0])), np.array([0.1, 0.0, 0.0])),
             (g.axis_angle_to_rot(np.array([-0.05, -0.1, 0.03])), np.array([-0.3, 0.1, 0.2]))]
    rng = np.random.default_rng(0)
    for k, (R, t) in enumerate(poses):
        stem = root / "seq-01" / f"frame-{k:06d}"
        cv2.imwrite(f"{stem}.color.png", rng.integers(0, 255, (h, w, 3), dtype=np.uint8))
        write_depth(f"{stem}.depth.png", plane_depth(K, R, t, w, h))
        Rc, c = g.pose_inverse(R, t)
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = Rc, c
        # 7-Scenes style: tabs, scientific notation, CRLF line endings.
        rows = ["\t".join(f"{v: .9e}" for v in row) + "\t" for row in M]
        (root / "seq-01" / f"frame-{k:06d}.pose.txt").write_bytes(
            ("\r\n".join(rows) + "\r\n").encode())
    (root / "intrinsics.txt").write_text(f"{fx} {fy} {cx} {cy} {intr_size[0]} {intr_size[1]}\n")
    return K, poses


def test_intrinsics_txt_registered_depth_and_submillimetre_consistency(tmp_path):
    K, poses = write_plane_scene(tmp_path)
    s = load_scene("7scenes", tmp_path, query_every=2)
    assert s.names == ["seq-01/frame-000000.color.png", "seq-01/frame-000001.color.png"]
    np.testing.assert_array_equal(s.is_query, [True, False])  # no split files: every 2nd
    np.testing.assert_allclose(s.K[0], K, atol=1e-12)  # scaled from 128x96 to 64x48
    np.testing.assert_allclose(s.depth_K, s.K)
    for k, (R, t) in enumerate(poses):
        np.testing.assert_allclose(s.R[k], R, atol=1e-8)
        np.testing.assert_allclose(s.t[k], t, atol=1e-8)
    e = depth_reprojection_errors(s, 0, 1, stride=1)
    assert e.size > 0.5 * 64 * 48
    assert np.median(e) < 0.001  # only the millimetre quantisation of the PNGs remains
    # Negative control: 1 cm off in the pose is seen.
    moved = dataclasses.replace(s, t=s.t + np.array([[0, 0, 0], [0, 0, 0.01]]))
    assert np.median(depth_reprojection_errors(moved, 0, 1, stride=1)) > 0.005


def test_sample_inverse_depth_is_exact_on_planes_and_refuses_edges():
    K = g.intrinsics_matrix(50.0, 50.0, 20.0, 15.0)
    R, t = np.eye(3), np.zeros(3)
    d = plane_depth(K, R, t, 40, 30)
    uv = np.random.default_rng(1).uniform([1, 1], [39, 29], size=(200, 2))
    z, ok = sample_inverse_depth(d, uv)
    assert ok.all()
    np.testing.assert_allclose(z, plane_depth_at(K, R, t, uv), rtol=1e-10)
    d2 = d.copy()
    d2[:, 20:] *= 2.0  # a depth edge between columns 19 and 20
    z, ok = sample_inverse_depth(d2, np.array([[20.0, 10.5], [10.0, 10.5], [0.2, 3.0]]))
    np.testing.assert_array_equal(ok, [False, True, False])  # across the edge; off-image


def plane_depth_at(K, R, t, uv):
    o, d = g.pixel_rays(K, R, t, uv)
    return (PLANE_D - o @ PLANE_N) / (d @ PLANE_N)


def test_pose_file_without_image_is_skipped_with_a_warning(tmp_path):
    """A missing pose is an error; a pose file with no colour image is skipped, and a warning
    names it."""
    from vrs_jax.errors import VrsError

    write_plane_scene(tmp_path)
    orphan = tmp_path / "seq-01" / "frame-000007.pose.txt"
    orphan.write_bytes((tmp_path / "seq-01" / "frame-000000.pose.txt").read_bytes())
    with pytest.warns(UserWarning, match="pose files without") as rec:
        s = load_scene("7scenes", tmp_path, query_every=2)
    assert len(s) == 2
    assert any(str(orphan) in str(w.message) for w in rec)
    orphan.unlink()
    (tmp_path / "seq-01" / "frame-000001.pose.txt").unlink()
    with pytest.raises(VrsError, match="pose file not found"):
        load_scene("7scenes", tmp_path, query_every=2)
