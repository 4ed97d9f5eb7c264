"""The embedded synthetic scene: determinism, 7Scenes layout, exact depth and poses, keypoints."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from vrs_jax import geometry
from vrs_jax.cli import make_synthetic
from vrs_jax.data import synthetic as sy
from vrs_jax.data.depth import depth_reprojection_errors
from vrs_jax.data.images import read_depth
from vrs_jax.data.readers import load_scene
from vrs_jax.errors import VrsError

CFG = sy.get_config("test")


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    return sy.generate(tmp_path_factory.mktemp("syn") / "room", CFG)


@pytest.fixture(scope="module")
def scene(scene_dir):
    return load_scene("7scenes", scene_dir)


def _tree_bytes(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*"))
            if p.is_file()}


# ----------------------------------------------------------------------------- files


def test_deterministic_for_a_seed(scene_dir, tmp_path):
    again = sy.generate(tmp_path / "again", CFG)
    a, b = _tree_bytes(scene_dir), _tree_bytes(again)
    assert a.keys() == b.keys()
    assert all(a[k] == b[k] for k in a), [k for k in a if a[k] != b[k]]
    # Another seed gives another scene.
    other = sy.generate(tmp_path / "other", dataclasses.replace(CFG, seed=CFG.seed + 1))
    c = _tree_bytes(other)
    assert c["seq-01/frame-000000.color.png"] != a["seq-01/frame-000000.color.png"]


def test_layout_and_file_formats(scene_dir):
    assert (scene_dir / "TrainSplit.txt").read_text() == "sequence1\n"
    assert (scene_dir / "TestSplit.txt").read_text() == "sequence2\n"
    assert "synthetic" in (scene_dir / "README.txt").read_text()
    fx, fy, cx, cy, w, h = (float(v) for v in (scene_dir / "intrinsics.txt").read_text().split())
    K = sy.intrinsics(CFG)
    assert (fx, fy, cx, cy, w, h) == (K[0, 0], K[1, 1], CFG.width / 2, CFG.height / 2,
                                      CFG.width, CFG.height)
    # 7Scenes RGB focal ratio (525 px at 640 px).
    assert fx == pytest.approx(525.0 * CFG.width / 640.0, rel=1e-9)
    for seq, n in (("seq-01", CFG.n_reference), ("seq-02", CFG.n_query)):
        names = sorted(p.name for p in (scene_dir / seq).iterdir())
        assert names == sorted(f"frame-{i:06d}.{kind}" for i in range(n)
                               for kind in ("color.png", "depth.png", "pose.txt"))
        for i in range(n):
            stem = scene_dir / seq / f"frame-{i:06d}"
            rgb = cv2.imread(f"{stem}.color.png", cv2.IMREAD_UNCHANGED)
            assert rgb.dtype == np.uint8 and rgb.shape == (CFG.height, CFG.width, 3)
            assert rgb.std() > 20  # textured, not flat
            d = cv2.imread(f"{stem}.depth.png", cv2.IMREAD_UNCHANGED)
            assert d.dtype == np.uint16 and d.shape == (CFG.height, CFG.width)
            assert d.min() > 300 and d.max() < 8000  # mm: closed room, no invalid pixels
            M = np.loadtxt(f"{stem}.pose.txt")
            assert M.shape == (4, 4) and np.array_equal(M[3], [0, 0, 0, 1])
            assert np.allclose(M[:3, :3] @ M[:3, :3].T, np.eye(3), atol=1e-12)
            assert np.linalg.det(M[:3, :3]) == pytest.approx(1.0, abs=1e-12)


def test_loads_back_through_the_7scenes_reader(scene):
    layout = sy.build_layout(CFG)
    n_r, n_q = CFG.n_reference, CFG.n_query
    assert len(scene) == n_r + n_q
    assert scene.names[0] == "seq-01/frame-000000.color.png"
    assert scene.names[n_r] == "seq-02/frame-000000.color.png"
    assert np.array_equal(scene.is_query, np.r_[np.zeros(n_r, bool), np.ones(n_q, bool)])
    assert np.allclose(scene.K, sy.intrinsics(CFG), rtol=0, atol=1e-12)
    assert np.allclose(scene.depth_K, scene.K, rtol=0, atol=1e-12)
    assert np.array_equal(scene.sizes, np.tile([CFG.width, CFG.height], (n_r + n_q, 1)))
    c2w = np.concatenate([layout.c2w_ref, layout.c2w_query])
    R, t = geometry.pose_from_c2w(c2w)
    assert np.allclose(scene.R, R, atol=1e-12) and np.allclose(scene.t, t, atol=1e-12)


def test_depth_reprojects_to_under_1mm(scene):
    layout = sy.build_layout(CFG)
    n_r = CFG.n_reference
    # Consecutive references, and each query against its nearest reference.
    cr, cq = layout.c2w_ref[:, :3, 3], layout.c2w_query[:, :3, 3]
    pairs = [(0, 1), (3, 4)] + [(n_r + q, int(np.linalg.norm(cr - cq[q], axis=1).argmin()))
                                for q in range(CFG.n_query)]
    for i, j in pairs:
        err = depth_reprojection_errors(scene, i, j, stride=1)
        assert len(err) > 0.2 * CFG.width * CFG.height, (i, j, len(err))
        assert np.median(err) < 1e-3, (i, j, np.median(err))
        assert np.percentile(err, 90) < 3e-3, (i, j)


def _scene_sdf(layout: sy.Layout, X: np.ndarray) -> np.ndarray:
    """Distance [N] of points X [N, 3] to the nearest surface (room planes or box faces)."""
    d = np.minimum(X - layout.room_min, layout.room_max - X).min(axis=1)
    for box in layout.boxes:
        c, s = math.cos(box.yaw), math.sin(box.yaw)
        rel = X - box.center
        local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1],
                          rel[:, 2]], -1)
        q = np.abs(local) - box.half
        sdf = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
        d = np.minimum(d, np.abs(sdf))
    return d


def _backproject(scene, i: int) -> np.ndarray:
    """World points [H, W, 3] of every pixel of frame i (its depth, K and pose as read)."""
    depth = read_depth(scene.depth_paths[i]).astype(np.float64)
    h, w = depth.shape
    rays = geometry.unproject(scene.depth_K[i], geometry.pixel_grid(w, h).reshape(-1, 2))
    Xc = rays * depth.reshape(-1, 1)
    Rc, tc = geometry.pose_inverse(scene.R[i], scene.t[i])
    return geometry.transform_points(Rc, tc, Xc).reshape(h, w, 3)


def test_every_depth_pixel_lies_on_the_known_geometry(scene):
    layout = sy.build_layout(CFG)
    for i in range(len(scene)):
        X = _backproject(scene, i).reshape(-1, 3)
        # Rounding to millimetres moves a point at most 0.5 mm * |ray| < 0.7 mm.
        assert _scene_sdf(layout, X).max() < 1e-3, i


def _on_box(box: sy.Box, X: np.ndarray, tol: float = 3e-3) -> np.ndarray:
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    rel = X - box.center
    local = np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1],
                      rel[..., 2]], -1)
    return np.all(np.abs(local) <= box.half + tol, axis=-1)


def test_box_silhouette_edges_fall_between_the_predicted_pixels(scene):
    """Poses and the pixel convention are exact: a box's vertical silhouette edge, projected
    with the pose read back, lies between the two pixel centres where the depth map changes
    from the box to the background (a half-pixel error would misplace about half the rows)."""
    layout = sy.build_layout(CFG)
    checked = 0
    for i in range(len(scene)):
        K, R, t = scene.K[i], scene.R[i], scene.t[i]
        cam = geometry.camera_center(R, t)
        X = _backproject(scene, i)
        h, w = X.shape[:2]
        for box in layout.boxes:
            rot = sy._rot_z(box.yaw)
            for sx, sy_ in ((-1, -1), (-1, 1), (1, -1), (1, 1)):
                corner = box.center + rot @ (box.half * [sx, sy_, -1])  # on the floor
                n1, n2 = rot[:, 0] * sx, rot[:, 1] * sy_  # normals of the faces at the edge
                if np.sign(n1 @ (cam - corner)) == np.sign(n2 @ (cam - corner)):
                    continue  # not a silhouette from this camera
                inward = (box.center - corner) * [1, 1, 0]
                inward *= 0.01 / np.linalg.norm(inward)
                # The edge is corner + z e_z; in the camera A + z B.
                A, B = R @ corner + t, R[:, 2]
                for r in range(h):
                    yn = (r + 0.5 - K[1, 2]) / K[1, 1]  # this row's pixel-centre height
                    z = (A[1] - yn * A[2]) / (yn * B[2] - B[1])
                    if not 0.03 < z < 2 * box.half[2] - 0.03 or A[2] + z * B[2] < 0.1:
                        continue
                    P = corner + [0, 0, z]
                    (u_e, v_e), (u_in, _) = geometry.project(K, R, t, np.stack([P, P + inward]))[0]
                    assert v_e == pytest.approx(r + 0.5, abs=1e-9)
                    j0 = int(math.floor(u_e - 0.5))  # pixel centres j0 + 0.5 <= u_e < j0 + 1.5
                    if j0 < 0 or j0 + 1 >= w:
                        continue
                    jb, jo = (j0, j0 + 1) if u_in < u_e else (j0 + 1, j0)
                    on_b, on_o = _on_box(box, X[r, jb]), _on_box(box, X[r, jo])
                    if not (on_b or on_o):
                        continue  # the edge is hidden here (another box in front)
                    assert on_b and not on_o, (i, r, u_e, jb, jo)
                    checked += 1
    assert checked >= 100, checked


def test_trajectories_are_smooth_and_queries_near_references():
    layout = sy.build_layout(sy.SyntheticConfig())
    c = layout.c2w_ref[:, :3, 3]
    step = np.linalg.norm(np.roll(c, -1, 0) - c, axis=1)
    rel = np.swapaxes(layout.c2w_ref[:, :3, :3], -1, -2) @ np.roll(layout.c2w_ref[:, :3, :3],
                                                                    -1, 0)
    ang = np.degrees(geometry.rotation_angle(rel))
    assert step.max() < 0.25 and ang.max() < 15.0  # a smooth closed loop
    assert 1.2 < c[:, 2].min() and c[:, 2].max() < 1.7  # hand-held heights
    dist, rot = sy.query_offsets_to_references(layout)
    assert len(dist) == 20 and (dist > 0.02).all() and (dist < 0.35).all()
    assert (rot < 15.0).all() and np.median(rot) > 1.0
    # Cameras keep clear of the boxes and the walls.
    for X in (layout.c2w_ref[:, :3, 3], layout.c2w_query[:, :3, 3]):
        assert (X[:, :2] > layout.room_min[:2] + 0.5).all()
        assert (X[:, :2] < layout.room_max[:2] - 0.5).all()
        for box in layout.boxes:
            d = sy._point_box_distance(X[:, :2], box.center, box.half, box.yaw)
            assert d.min() > 0.3


def test_default_frames_have_plenty_of_sift_keypoints():
    cfg = sy.SyntheticConfig()
    world = sy.build_world(cfg)
    sift = cv2.SIFT_create()
    for c2w in (world.layout.c2w_ref[0], world.layout.c2w_ref[33], world.layout.c2w_query[7]):
        rgb, depth = sy.render_frame(world, world.layout.K, c2w, cfg.width, cfg.height,
                                     cfg.supersample)
        assert rgb.shape == (240, 320, 3) and depth.shape == (240, 320)
        grey = cv2.cvtColor(np.round(rgb * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)
        kps = sift.detect(grey, None)
        assert len(kps) > 300, len(kps)
        # Keypoints spread over the image, not clustered in one place.
        xy = np.array([k.pt for k in kps])
        hist, _, _ = np.histogram2d(xy[:, 0], xy[:, 1], bins=(4, 3), range=[[0, 320], [0, 240]])
        assert (hist > 5).sum() >= 10


def test_render_is_anti_aliased_and_textures_vary():
    cfg = CFG
    world = sy.build_world(cfg)
    c2w = world.layout.c2w_ref[2]
    rgb, depth = {}, {}
    for S in (1, 2, 6):
        rgb[S], depth[S] = sy.render_frame(world, world.layout.K, c2w, cfg.width, cfg.height, S)
    assert np.array_equal(depth[1], depth[2])  # depth is the pixel-centre ray, whatever S
    # Supersampling converges to the pixel-box-filtered image (6x6 as reference): the 2x2
    # default is already close, and much closer than one sample per pixel (aliased).
    err1, err2 = (float(np.abs(rgb[S] - rgb[6]).mean()) for S in (1, 2))
    assert err2 < 0.03 and err2 < 0.6 * err1, (err1, err2)
    # No two faces share a texture (non-repeating), and textures are not flat.
    tex = [p[0] for p in world.textures]
    means = np.array([t.mean(axis=(0, 1)) for t in tex])
    assert len(np.unique(np.round(means, 4), axis=0)) == len(tex)
    assert min(float(t.std()) for t in tex) > 0.05


# ----------------------------------------------------------------------------- re-runs


def test_rerun_skips_and_resumes(tmp_path):
    cfg = dataclasses.replace(CFG, n_reference=3, n_query=1)
    out = sy.generate(tmp_path / "s", cfg)
    before = _tree_bytes(out)
    assert sy.is_generated(out, cfg)
    color = out / "seq-01" / "frame-000001.color.png"
    mtime = color.stat().st_mtime_ns
    sy.generate(out, cfg)  # complete: nothing rewritten
    assert color.stat().st_mtime_ns == mtime
    # Interrupted run: a frame missing -> resumed, and the result is the same bytes.
    (out / "seq-01" / "frame-000001.pose.txt").unlink()
    color.unlink()
    assert not sy.is_generated(out, cfg)
    sy.generate(out, cfg)
    assert _tree_bytes(out) == before
    # overwrite regenerates everything.
    sy.generate(out, cfg, overwrite=True)
    assert color.stat().st_mtime_ns != mtime and _tree_bytes(out) == before


def test_refuses_foreign_or_different_folders(tmp_path):
    cfg = dataclasses.replace(CFG, n_reference=2, n_query=0)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "precious.txt").write_text("keep me")
    for overwrite in (False, True):
        with pytest.raises(VrsError, match="holds no synthetic scene"):
            sy.generate(foreign, cfg, overwrite=overwrite)
    assert (foreign / "precious.txt").read_text() == "keep me"
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(VrsError, match="not a folder"):
        sy.generate(a_file, cfg)
    out = sy.generate(tmp_path / "s", cfg)
    other = dataclasses.replace(cfg, seed=7)
    with pytest.raises(VrsError, match="another configuration"):
        sy.generate(out, other)
    sy.generate(out, other, overwrite=True)
    assert sy.is_generated(out, other) and not sy.is_generated(out, cfg)
    (out / sy.MARKER).write_text("{not json")
    with pytest.raises(VrsError, match="malformed synthetic scene marker"):
        sy.generate(out, other)


def test_bad_config_raises():
    with pytest.raises(VrsError, match="too small"):
        sy.SyntheticConfig(width=4, height=4)
    with pytest.raises(VrsError, match="reference"):
        sy.SyntheticConfig(n_reference=1)
    with pytest.raises(VrsError, match="could not place"):
        sy.build_layout(dataclasses.replace(CFG, box_footprint_range=(3.0, 3.5)))
    with pytest.raises(VrsError, match="unknown synthetic config"):
        sy.get_config("nope")


def test_cli(tmp_path, capsys):
    out = tmp_path / "cli"
    args = ["--out", str(out), "--size", "64x48", "--n-ref", "2", "--n-query", "1"]
    assert make_synthetic.main(args) == 0
    assert (out / "seq-02" / "frame-000000.color.png").is_file()
    assert "64 48" in (out / "intrinsics.txt").read_text()
    assert make_synthetic.main(args) == 0
    assert "nothing to do" in capsys.readouterr().out
    assert make_synthetic.main(args[:2] + ["--seed", "3"]) == 2
    assert "another configuration" in capsys.readouterr().err
    for bad in ("64", "64x", "0x48", "axb"):
        with pytest.raises(SystemExit) as e:
            make_synthetic.main(["--out", str(out), "--size", bad])
        assert e.value.code == 2
        assert "invalid size" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        make_synthetic.main(["--out", str(out), "--n-ref", "1"])
    assert "must be >= 2" in capsys.readouterr().err


# ----------------------------------------------------------------------------- several rooms

# The test room with 3 references and 1 query as the generator made it before the multi-room
# extension (commit 11fae83; made with `snapshot` below and np.savez_compressed). Pixels are
# compared with a tolerance, not a hash: the ray caster's float arithmetic (numpy's SIMD
# paths, libm) differs between CPUs, which can move a pixel by one grey level or, on an edge,
# onto the other surface.
SINGLE_ROOM_REFERENCE = Path(__file__).parent / "data" / "single_room_before_rooms.npz"


def snapshot(root: Path) -> dict[str, np.ndarray]:
    """Every file of a generated scene as an array: decoded PNG pixels, numeric text as
    float64 (poses, intrinsics), any other file as its bytes (uint8)."""
    out = {}
    for p in sorted(root.rglob("*")):
        if not p.is_file():
            continue
        name = str(p.relative_to(root))
        if p.suffix == ".png":
            out[name] = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        elif name.endswith(".pose.txt") or name == "intrinsics.txt":
            out[name] = np.loadtxt(p, dtype=np.float64)
        else:
            out[name] = np.frombuffer(p.read_bytes(), np.uint8)
    return out


def assert_scene_close(got: dict, want: dict) -> None:
    """Same files, shapes and bytes; numbers to 1e-9; pixels as two CPUs' renders agree:
    at most 0.5% of an image's pixels more than one level (1 mm of depth) apart, and those
    only on edges (mean absolute difference under 0.2 levels)."""
    assert sorted(got) == sorted(want)
    for name, w in want.items():
        g = got[name]
        assert g.shape == w.shape and g.dtype == w.dtype, name
        if name.endswith(".png"):
            d = np.abs(g.astype(np.int64) - w.astype(np.int64))
            assert np.mean(d > 1) <= 0.005 and d.mean() < 0.2, (name, np.mean(d > 1), d.mean())
        elif g.dtype == np.float64:
            np.testing.assert_allclose(g, w, rtol=0, atol=1e-9, err_msg=name)
        elif name.endswith(".json"):
            assert _json_leaves(json.loads(g.tobytes())) == pytest.approx(
                _json_leaves(json.loads(w.tobytes()))), name
        else:
            assert g.tobytes() == w.tobytes(), name


def _json_leaves(obj, key: str = "") -> dict:
    """A parsed JSON document as {"a/b/0": leaf}, so numbers compare with pytest.approx."""
    if isinstance(obj, dict):
        items = obj.items()
    elif isinstance(obj, list):
        items = enumerate(obj)
    else:
        return {key: obj}
    return {k: v for i, x in items for k, v in _json_leaves(x, f"{key}/{i}").items()}


def test_single_room_is_unchanged_by_the_room_extension(tmp_path):
    cfg = dataclasses.replace(CFG, n_reference=3, n_query=1)
    out = sy.generate(tmp_path / "one", cfg)
    with np.load(SINGLE_ROOM_REFERENCE) as ref:
        assert_scene_close(snapshot(out), dict(ref))
    assert "n_rooms" not in (out / "synthetic.json").read_text()


def test_scene_comparison_catches_a_changed_pixel_block_and_pose(tmp_path):
    cfg = dataclasses.replace(CFG, n_reference=3, n_query=1)
    base = snapshot(sy.generate(tmp_path / "one", cfg))
    img = "seq-01/frame-000000.color.png"
    moved = dict(base, **{img: base[img].copy()})
    moved[img][:8, :8] = 255 - moved[img][:8, :8]  # 64 of 6,912 pixels: 0.9%
    with pytest.raises(AssertionError):
        assert_scene_close(moved, base)
    pose = "seq-01/frame-000000.pose.txt"
    with pytest.raises(AssertionError):
        assert_scene_close(dict(base, **{pose: base[pose] + 1e-6}), base)


ROOMS = sy.get_config("rooms4")


def test_rooms4_layout_rooms_walls_and_cameras():
    lay = sy.build_layout(ROOMS)
    n_ref, n_q = ROOMS.room_frames()
    assert n_ref == [20, 15, 15, 15] and n_q == [5, 4, 4, 4]
    assert len(lay.c2w_ref) == ROOMS.total_reference == 65
    assert len(lay.c2w_query) == ROOMS.total_query == 17
    np.testing.assert_allclose(lay.room_x, [-9.25, -1.25, 2.25, 5.75, 9.25])
    np.testing.assert_allclose(lay.room_max - lay.room_min, [18.5, 4.0, 2.6])
    # every camera lies inside its own room, at least 0.5 m from its walls
    for c2w, room in ((lay.c2w_ref, lay.ref_room), (lay.c2w_query, lay.query_room)):
        x = c2w[:, 0, 3]
        assert np.all(x > lay.room_x[room] + 0.5) and np.all(x < lay.room_x[room + 1] - 0.5)
    # partition walls: the last 6 boxes, floor to ceiling at the inner boundaries with a 1 m door
    walls = lay.boxes[-6:]
    for b in walls:
        assert b.half[2] * 2 == pytest.approx(2.6) and b.yaw == 0.0
        assert np.min(np.abs(b.center[0] - lay.room_x[1:-1])) < 1e-9
    gaps = sorted(b.center[1] - b.half[1] for b in walls if b.center[1] > 0)
    assert gaps == pytest.approx([0.5] * 3)  # doorway from y = -0.5 to 0.5
    # furniture boxes stay in one room, clear of the walls
    for b in lay.boxes[:-6]:
        fp = sy._box_footprint(b.center, b.half, b.yaw)[:, 0]
        r = np.searchsorted(lay.room_x, b.center[0]) - 1
        assert fp.min() > lay.room_x[r] + 0.03 and fp.max() < lay.room_x[r + 1] - 0.03
    # a ray from room 0's centre along +x, above the boxes (<= 1.2 m), passes the three
    # doorways and hits the end wall (face 1: the room's +x plane); 1.5 m beside the doorway
    # it hits the first partition wall
    assert max(b.center[2] + b.half[2] for b in lay.boxes[:-6]) <= 1.2
    t, face = sy.cast_rays(lay, np.array([lay.room_centers()[0], 0.0, 1.5]),
                           np.array([[1.0, 0.0, 0.0]]))
    assert face[0] == 1 and t[0] == pytest.approx(lay.room_x[-1] - lay.room_centers()[0])
    t, face = sy.cast_rays(lay, np.array([lay.room_centers()[0], 1.5, 1.5]),
                           np.array([[1.0, 0.0, 0.0]]))
    assert face[0] >= 6 and t[0] == pytest.approx(lay.room_x[1] - 0.06 - lay.room_centers()[0])


def test_rooms4_cameras_form_four_separable_clusters():
    """K-means (any seed) finds the four rooms; a uniform grid of four cells cuts two of
    them: the scene the cluster benchmark compares the two on."""
    from vrs_jax.nerf import clusters

    lay = sy.build_layout(ROOMS)
    x = lay.c2w_ref[:, :3, 3]
    room = lay.ref_room
    # well separated: the closest cameras of two rooms are farther apart than 2x the largest
    # distance of a camera to its own room's mean
    spread = max(np.linalg.norm(x[room == r] - x[room == r].mean(0), axis=1).max()
                 for r in range(4))
    gap = min(np.linalg.norm(x[room == a][:, None] - x[room == b][None], axis=-1).min()
              for a in range(4) for b in range(a + 1, 4))
    assert gap > 1.5 and gap > 0.9 * spread, (gap, spread)
    for seed in range(4):
        cl = clusters.cluster_cameras(x, 4, seed=seed)
        table = np.zeros((4, 4), int)
        np.add.at(table, (room, cl.primary), 1)
        assert (np.count_nonzero(table, axis=1) == 1).all(), table  # one cluster per room
    grid = clusters.cluster_cameras(x, 4, method="grid")
    table = np.zeros((4, 4), int)
    np.add.at(table, (room, grid.primary), 1)
    assert (np.count_nonzero(table, axis=1) > 1).sum() == 2, table


def test_rooms_config_record_and_validation(tmp_path):
    assert sy.config_dict(ROOMS)["n_rooms"] == 4
    assert "door_width" not in sy.config_dict(CFG)
    with pytest.raises(VrsError, match="room_widths"):
        sy.SyntheticConfig(n_rooms=3, room_widths=(5.0, 5.0))
    with pytest.raises(VrsError, match="2.6 m wide"):
        sy.SyntheticConfig(n_rooms=2, room_widths=(5.0, 2.0))
    with pytest.raises(VrsError, match="door width"):
        sy.SyntheticConfig(n_rooms=2, door_width=5.0)
    # three equal rooms, tiny: frames render and read back through the 7Scenes reader
    cfg = dataclasses.replace(CFG, width=32, height=24, n_reference=4, n_query=1, n_rooms=3,
                              texels_per_m=16.0, supersample=1)
    out = sy.generate(tmp_path / "three", cfg)
    scene = load_scene("7scenes", out)
    assert len(scene.references()) == 12 and len(scene.queries()) == 3
    assert "3 procedurally textured rooms" in (out / "README.txt").read_text()


def test_cli_rooms(tmp_path, capsys):
    out = tmp_path / "rooms"
    args = ["--out", str(out), "--config", "rooms4", "--rooms", "2", "--size", "32x24",
            "--n-ref", "4", "--n-query", "1"]
    assert make_synthetic.main(args) == 0
    assert "2 rooms" in capsys.readouterr().out
    cfg = make_synthetic.config_of(make_synthetic.build_parser().parse_args(args))
    assert cfg.n_rooms == 2 and cfg.room_widths == (8.0, 3.5)
    assert sy.is_generated(out, cfg)


def test_query_arc_makes_an_ordered_stream_and_keeps_the_references():
    base = dataclasses.replace(CFG, n_reference=6, n_query=5)
    stream = dataclasses.replace(base, query_arc=0.05)
    a, b = sy.build_layout(base), sy.build_layout(stream)
    np.testing.assert_array_equal(a.c2w_ref, b.c2w_ref)  # same room, same references
    assert [bx.center.tolist() for bx in a.boxes] == [bx.center.tolist() for bx in b.boxes]
    steps = np.linalg.norm(np.diff(b.c2w_query[:, :3, 3], axis=0), axis=1)
    assert steps.max() < 0.15 and steps.max() < 1.5 * steps.min()  # short, even steps
    spread = np.linalg.norm(np.diff(a.c2w_query[:, :3, 3], axis=0), axis=1)
    assert spread.min() > steps.max()  # the default queries are spread over the loop
    assert "query_arc" not in json.dumps(sy.config_dict(base))
    assert sy.config_dict(stream)["query_arc"] == 0.05
    with pytest.raises(VrsError, match="query_arc"):
        dataclasses.replace(base, query_arc=1.5)
