"""hloc query lists with intrinsics (vrs_jax.data.readers.query_list): every supported COLMAP
model projects like pycolmap, bad lines and bad image folders raise VrsError file:line."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest

from vrs_jax import geometry
from vrs_jax.data.readers.query_list import query_scene, read_query_list
from vrs_jax.errors import VrsError

# (model, params) with strong enough distortion that a wrong coefficient slot shows.
CAMERAS = [
    ("SIMPLE_PINHOLE", [420.0, 319.5, 241.0]),
    ("PINHOLE", [410.0, 430.0, 320.0, 239.0]),
    ("SIMPLE_RADIAL", [400.0, 321.0, 238.0, -0.12]),
    ("RADIAL", [405.0, 318.0, 242.0, -0.1, 0.03]),
    ("OPENCV", [400.0, 415.0, 322.0, 236.0, -0.11, 0.02, 0.003, -0.002]),
    ("FULL_OPENCV", [398.0, 402.0, 317.0, 243.0, -0.09, 0.025, -0.001, 0.0025, -0.004,
                     0.0, 0.0, 0.0]),
]


def write_list(path, lines):
    path.write_text("\n".join(lines) + "\n")
    return path


def test_every_model_projects_like_pycolmap(tmp_path):
    lines = [f"q/{m.lower()}.jpg {m} 640 480 " + " ".join(repr(p) for p in params)
             for m, params in CAMERAS]
    entries = read_query_list(write_list(tmp_path / "q.txt", ["# comment", ""] + lines))
    assert [e.name for e in entries] == [f"q/{m.lower()}.jpg" for m, _ in CAMERAS]
    rng = np.random.default_rng(0)
    X = np.concatenate([rng.uniform(-0.6, 0.6, (200, 2)), np.ones((200, 1))], axis=1)
    X *= rng.uniform(1.0, 5.0, (200, 1))  # camera-frame points inside a ~60 deg cone
    for e, (model, params) in zip(entries, CAMERAS, strict=True):
        assert (e.model, e.width, e.height) == (model, 640, 480)
        cam = pycolmap.Camera(model=model, width=640, height=480, params=params)
        ref = np.asarray(cam.img_from_cam(X))
        uv, z = geometry.project(e.K, np.eye(3), np.zeros(3), X, e.dist)
        np.testing.assert_allclose(uv, ref, atol=1e-9, err_msg=model)
        assert np.all(z > 0)


def test_query_scene(tmp_path):
    img = tmp_path / "images"
    (img / "q").mkdir(parents=True)
    cv2.imwrite(str(img / "q" / "a.png"), np.zeros((6, 8, 3), np.uint8))
    cv2.imwrite(str(img / "q" / "b.jpg"), np.zeros((8, 6, 3), np.uint8))
    ql = write_list(tmp_path / "q.txt", ["q/a.png PINHOLE 8 6 10 11 4 3",
                                         "q/b.jpg SIMPLE_RADIAL 6 8 9 3 4 0.01"])
    s = query_scene(ql, img)
    assert s.names == ["q/a.png", "q/b.jpg"] and s.format == "query_list"
    assert s.image_paths == [img / "q" / "a.png", img / "q" / "b.jpg"]
    np.testing.assert_array_equal(s.sizes, [[8, 6], [6, 8]])
    assert not s.has_pose.any() and s.is_query.all()
    np.testing.assert_array_equal(s.K[0], [[10, 0, 4], [0, 11, 3], [0, 0, 1]])
    np.testing.assert_array_equal(s.dist[1], [0.01, 0, 0, 0, 0])
    np.testing.assert_array_equal(s.R, np.tile(np.eye(3), (2, 1, 1)))
    assert len(s.queries()) == 2 and len(s.references()) == 0
    # The image size must be the list's.
    write_list(ql, ["q/a.png PINHOLE 8 6 10 11 4 3", "q/b.jpg SIMPLE_RADIAL 8 6 9 3 4 0.01"])
    with pytest.raises(VrsError, match=r"q\.txt:2: image q/b\.jpg is 6x8 but the list gives 8x6"):
        query_scene(ql, img)
    # A missing listed image is a query that localizing flags (issue 23: every unreadable
    # query is flagged while the others localize); none of them there is an error.
    write_list(ql, ["q/a.png PINHOLE 8 6 10 11 4 3", "q/c.png PINHOLE 8 6 10 11 4 3"])
    assert query_scene(ql, img).names == ["q/a.png", "q/c.png"]
    write_list(ql, ["q/c.png PINHOLE 8 6 10 11 4 3", "q/d.png PINHOLE 8 6 10 11 4 3"])
    with pytest.raises(VrsError, match=r"images/q/c\.png: image of query q/c\.png \(line 1"):
        query_scene(ql, img)
    write_list(ql, ["# nothing"])
    with pytest.raises(VrsError, match="no queries"):
        query_scene(ql, img)


@pytest.mark.parametrize("line, problem", [
    ("q.jpg OPENCV_FISHEYE 640 480 400 400 320 240 0.1 0 0 0",
     "unsupported camera model OPENCV_FISHEYE"),
    ("q.jpg FOV 640 480 400 400 320 240 0.9", "unsupported camera model FOV"),
    ("q.jpg FULL_OPENCV 640 480 400 400 320 240 0.1 0 0 0 0 0.2 0 0",
     "FULL_OPENCV camera with k4, k5, k6 = 0.2, 0, 0: the rational distortion part is not "
     "supported"),
    ("q.jpg OPENCV 640 480 400 400 320 240 0.1", "camera model OPENCV takes 8 parameters, got 5"),
    ("q.jpg PINHOLE 640.5 480 400 400 320 240", "width and height must be positive integers"),
    ("q.jpg PINHOLE 640 0 400 400 320 240", "width and height must be positive integers"),
    ("q.jpg PINHOLE 640 480 400 x 320 240", "malformed query line (camera parameters)"),
    ("q.jpg PINHOLE 640 480", "expected 'name MODEL width height params...'"),
    ("q.jpg PINHOLE 640 480 -400 400 320 240", "non-positive focal length"),
    ("p.jpg PINHOLE 640 480 400 400 320 240", "query p.jpg listed twice (first on line 1)"),
])
def test_bad_lines_name_file_and_line(tmp_path, line, problem):
    ql = write_list(tmp_path / "q.txt", ["p.jpg PINHOLE 640 480 400 400 320 240", line])
    with pytest.raises(VrsError) as ei:
        read_query_list(ql)
    assert str(ei.value).startswith(f"{ql}:2: "), str(ei.value)
    assert problem in str(ei.value), str(ei.value)


def test_byte_order_mark_is_not_part_of_the_first_name(tmp_path):
    """A list saved with a UTF-8 BOM (Windows editors) reads as without one; a missing first
    image is named without it. Results files (evaluate) too."""
    from vrs_jax.eval.results import read_results

    img = tmp_path / "images"
    img.mkdir()
    cv2.imwrite(str(img / "a.png"), np.zeros((6, 8, 3), np.uint8))
    ql = tmp_path / "q.txt"
    ql.write_bytes(b"\xef\xbb\xbfa.png PINHOLE 8 6 10 11 4 3\n")
    assert query_scene(ql, img).names == ["a.png"]
    ql.write_bytes(b"\xef\xbb\xbfc.png PINHOLE 8 6 10 11 4 3\n")
    with pytest.raises(VrsError, match="image of query c.png ") as e:
        query_scene(ql, img)
    assert "\ufeff" not in str(e.value)
    res = tmp_path / "results.txt"
    res.write_bytes(b"\xef\xbb\xbfa.png 1 0 0 0 0 0 0\n")
    assert list(read_results(res)) == ["a.png"]
