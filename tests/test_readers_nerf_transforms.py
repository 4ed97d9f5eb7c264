"""nerfstudio transforms.json split lists and masks (vrs_jax.data.readers.nerf_transforms) on
tiny generated folders."""

from __future__ import annotations

import json
import warnings

import cv2
import numpy as np
import pytest

from vrs_jax.data.readers import nerf_transforms
from vrs_jax.errors import VrsError


def make_folder(root, n=6, **top):
    """n frames images/f{k}.png (8x6), file_path with extension, plus top-level keys."""
    (root / "images").mkdir(parents=True)
    frames = []
    for k in range(n):
        cv2.imwrite(str(root / "images" / f"f{k}.png"), np.zeros((6, 8, 3), np.uint8))
        M = np.eye(4)
        M[0, 3] = 0.1 * k
        frames.append({"file_path": f"images/f{k}.png", "transform_matrix": M.tolist()})
    meta = {"fl_x": 10.0, "fl_y": 10.0, "cx": 4.0, "cy": 3.0, "frames": frames, **top}
    (root / "transforms.json").write_text(json.dumps(meta))
    return meta


def load_quiet(root, **kw):
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        s = nerf_transforms.load(root, **kw)
    return s, [str(w.message) for w in rec]


def test_split_lists_choose_queries(tmp_path):
    # names in the lists: plain, with ./, and without the extension
    make_folder(tmp_path, train_filenames=["images/f0.png", "./images/f1.png", "images/f2",
                                           "images/f3.png"],
                val_filenames=["images/f4.png"], test_filenames=["./images/f5"])
    s, warns = load_quiet(tmp_path)
    assert warns == []
    assert s.names == [f"images/f{k}.png" for k in range(6)]
    np.testing.assert_array_equal(s.is_query, [False] * 4 + [True] * 2)
    assert s.has_pose.all()


def test_frames_in_no_list_are_skipped_when_a_train_list_exists(tmp_path):
    make_folder(tmp_path, train_filenames=["images/f0.png", "images/f1.png"],
                test_filenames=["images/f5.png"])
    s, warns = load_quiet(tmp_path)
    assert s.names == ["images/f0.png", "images/f1.png", "images/f5.png"]
    np.testing.assert_array_equal(s.is_query, [False, False, True])
    assert len(warns) == 1 and "in none of train/val/test_filenames, skipped (3)" in warns[0]


def test_without_train_list_the_rest_are_references(tmp_path):
    make_folder(tmp_path, val_filenames=["images/f2.png"])
    s, warns = load_quiet(tmp_path)
    assert warns == [] and len(s) == 6
    np.testing.assert_array_equal(np.flatnonzero(s.is_query), [2])


def test_query_every_wins_over_lists_with_a_warning(tmp_path):
    make_folder(tmp_path, train_filenames=["images/f0.png"], test_filenames=["images/f5.png"])
    s, warns = load_quiet(tmp_path, query_every=2)
    assert len(s) == 6
    np.testing.assert_array_equal(np.flatnonzero(s.is_query), [0, 2, 4])  # by name
    assert len(warns) == 1 and "query_every=2 given" in warns[0] and "ignored" in warns[0]


def test_no_lists_keeps_the_old_behaviour(tmp_path):
    make_folder(tmp_path)
    s, warns = load_quiet(tmp_path)
    assert warns == [] and not s.is_query.any() and len(s) == 6
    s, _ = load_quiet(tmp_path, query_every=3)
    np.testing.assert_array_equal(np.flatnonzero(s.is_query), [0, 3])


@pytest.mark.parametrize("lists, problem", [
    ({"test_filenames": ["images/f9.png"]},
     "test_filenames names 1 file(s) that no frame has as file_path: images/f9.png"),
    ({"train_filenames": ["images/f1.png"], "val_filenames": ["images/f1.png"]},
     "frame images/f1.png is in train_filenames and in a val/test list"),
    ({"val_filenames": "images/f1.png"}, "'val_filenames' must be a list of file paths"),
])
def test_bad_lists(tmp_path, lists, problem):
    make_folder(tmp_path, **lists)
    with pytest.raises(VrsError) as ei:
        nerf_transforms.load(tmp_path)
    assert str(ei.value) == f"{tmp_path / 'transforms.json'}: {problem}"


@pytest.mark.parametrize("where", ["frame", "top"])
def test_masks_warn_once(tmp_path, where):
    if where == "top":
        make_folder(tmp_path, mask_path="masks/all.png")
    else:
        meta = make_folder(tmp_path)
        for k, fr in enumerate(meta["frames"]):
            fr["mask_path"] = f"masks/f{k}.png"
        (tmp_path / "transforms.json").write_text(json.dumps(meta))
    s, warns = load_quiet(tmp_path)
    assert len(s) == 6
    assert len(warns) == 1 and "mask_path given, but vrs-jax does not use masks" in warns[0]
