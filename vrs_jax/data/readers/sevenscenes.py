"""Microsoft 7-Scenes, raw layout (also what ``vrs_jax.data.synthetic`` writes).

Layout of a scene folder ``root``::

    root/seq-XX/frame-XXXXXX.color.png   (or .color.jpg)
    root/seq-XX/frame-XXXXXX.depth.png   uint16 millimetres, 65535 = invalid
    root/seq-XX/frame-XXXXXX.pose.txt    4x4 camera-to-world (metres), CRLF line ends allowed
    root/TrainSplit.txt, root/TestSplit.txt   lines ``sequence1`` -> seq-01
    root/intrinsics.txt (optional)       ``fx fy cx cy width height`` (synthetic scenes)

Conventions converted here: the pose files are camera-to-world and are inverted to
world-to-camera. Without ``intrinsics.txt`` the RGB camera is f = 525, c = (320, 240) at
640x480 and the (unregistered) depth camera is f = 585, c = (320, 240) at 640x480, both scaled
to the actual image sizes; the pose is used for both cameras, as the dataset's tools do (the
offset between the Kinect's RGB and depth sensors is not modelled). With ``intrinsics.txt``
the depth is registered to the colour image and ``depth_K`` equals ``K`` (scaled to the depth
image size).
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from vrs_jax import geometry
from vrs_jax.data.readers import _common as C
from vrs_jax.errors import VrsError, require_dir

RGB_F, DEPTH_F, CX, CY, W0, H0 = 525.0, 585.0, 320.0, 240.0, 640, 480
DEPTH_SCALE = 0.001  # metres per unit of the depth PNGs (millimetres)

_FRAME = re.compile(r"^frame-(\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)
_POSE = re.compile(r"^frame-(\d+)\.pose\.txt$", re.IGNORECASE)
_SEQ = re.compile(r"^seq-?(\d+)$", re.IGNORECASE)
_SPLIT = re.compile(r"^sequence-?(\d+)$", re.IGNORECASE)


def read_pose_file(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A 7-Scenes ``pose.txt`` (4x4 camera-to-world) -> world-to-camera (R [3, 3], t [3]).

    Raises VrsError naming the file and line for a malformed matrix.
    """
    lines = C.text_lines(path, "pose file")
    if len(lines) != 4:
        raise VrsError(f"pose file must have 4 rows of 4 numbers, found {len(lines)} rows",
                       path, lines[-1][0] if lines else None)
    rows = []
    for lineno, text in lines:
        v = C.parse_floats(text.split(), path, lineno, "pose row")
        if v.size != 4:
            raise VrsError(f"malformed pose row: expected 4 numbers, got {v.size}", path, lineno)
        rows.append(v)
    M = np.stack(rows)
    if not np.all(np.isfinite(M)):
        raise VrsError("pose has non-finite entries", path)
    if np.abs(M[3] - [0, 0, 0, 1]).max() > 1e-6:
        raise VrsError("last pose row must be 0 0 0 1", path, lines[3][0])
    Rc2w = C.rotation_from_matrix(M[:3, :3], path)
    return geometry.pose_inverse(Rc2w, M[:3, 3])


def read_split(path: Path) -> list[str]:
    """``TrainSplit.txt``/``TestSplit.txt`` -> sequence folder names (``sequence1`` -> seq-01)."""
    out = []
    for lineno, text in C.text_lines(path, "split file"):
        m = _SPLIT.match(text)
        if not m:
            raise VrsError(f"malformed split line {text!r}: expected 'sequenceN'", path, lineno)
        out.append(f"seq-{int(m.group(1)):02d}")
    return out


def read_intrinsics_txt(path: Path) -> tuple[np.ndarray, tuple[int, int]]:
    """``intrinsics.txt`` (``fx fy cx cy width height``) -> (K [3, 3], (width, height))."""
    lines = C.text_lines(path, "intrinsics file")
    if not lines:
        raise VrsError("empty intrinsics file", path)
    lineno, text = lines[0]
    v = C.parse_floats(text.split(), path, lineno, "intrinsics line")
    if v.size != 6 or not all(C.finite_positive(x) for x in v):
        raise VrsError("intrinsics line must be 'fx fy cx cy width height' (positive numbers)",
                       path, lineno)
    return C.pinhole(*v[:4]), (int(round(v[4])), int(round(v[5])))


def read_pgt(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray, float, int]]:
    """SfM pseudo ground truth ``name qw qx qy qz tx ty tz f`` (world-to-camera).

    Returns name -> (R [3, 3], t [3], focal, line number).
    """
    out = {}
    for lineno, text in C.text_lines(path, "pose file"):
        if text.startswith("#"):
            continue
        parts = text.split()
        if len(parts) != 9:
            raise VrsError(f"malformed pose line: expected 'name qw qx qy qz tx ty tz f', got "
                           f"{len(parts)} fields", path, lineno)
        v = C.parse_floats(parts[1:], path, lineno, "pose line")
        if not np.all(np.isfinite(v)) or np.linalg.norm(v[:4]) < 1e-6 or v[7] <= 0:
            raise VrsError("malformed pose line: non-finite values, zero quaternion or focal <= 0",
                           path, lineno)
        out[parts[0]] = (geometry.quat_to_rot(v[:4]), v[4:7], float(v[7]), lineno)
    return out


def orphan_poses(folder: Path, frames: set[str]) -> list[str]:
    """The ``frame-XXXXXX.pose.txt`` files of a sequence folder whose frame number is not in
    ``frames`` (no colour image), as paths, sorted."""
    return sorted(str(p) for p in folder.iterdir()
                  if (m := _POSE.match(p.name)) and m.group(1) not in frames)


def _strip_ext(name: str) -> str:
    """``seq-01/frame-000000.color.png`` -> ``seq-01/frame-000000`` (matching pgt names)."""
    return re.sub(r"\.color\.(png|jpg|jpeg)$", "", name, flags=re.IGNORECASE)


def load(root: str | Path, *, pgt: str | Path | None = None, query_every: int = 0,
         sequences: list[str] | None = None):
    """Read a 7-Scenes scene folder.

    Args:
      root: the scene folder (holding ``seq-XX/`` and the split files).
      pgt: optional SfM pseudo-ground-truth pose file (``name qw qx qy qz tx ty tz f``, one
        line per image, world-to-camera, ``f`` the focal length at 640x480 with
        c = (320, 240)); the listed images get these poses and focal lengths instead of the
        D-SLAM ones. Names match with or without the ``.color.png`` suffix, and ``.png``
        names match ``.jpg`` frames.
      query_every: without split files, hold out every N-th frame (by name) as a query.
      sequences: restrict to these ``seq-XX`` folders (default: those in the split files, or
        every ``seq-*`` folder when there are none).
    Returns:
      Scene with names like ``seq-01/frame-000000.color.png`` (relative to ``root``), depth
      paths, ``depth_K`` and ``depth_scale`` = 0.001; the TestSplit sequences are queries.
    """
    root = require_dir(root, "7-Scenes scene folder")
    train_f, test_f = root / "TrainSplit.txt", root / "TestSplit.txt"
    has_split = train_f.is_file() and test_f.is_file()
    if has_split:
        train, test = read_split(train_f), read_split(test_f)
        seqs = [(s, False) for s in train] + [(s, True) for s in test]
        for s, _ in seqs:
            require_dir(root / s, f"sequence folder (listed in {train_f.name}/{test_f.name})")
    else:
        seqs = [(p.name, False) for p in sorted(root.iterdir())
                if p.is_dir() and _SEQ.match(p.name)]
    if sequences is not None:
        want = set(sequences)
        seqs = [(s, q) for s, q in seqs if s in want]
    if not seqs:
        raise VrsError("no seq-XX folders found", root)

    names, paths, depth_paths, Rs, ts, is_query = [], [], [], [], [], []
    orphans: list[str] = []
    for seq, query in seqs:
        frames = sorted((m.group(1), p) for p in (root / seq).iterdir()
                        if (m := _FRAME.match(p.name)) and p.is_file())
        if not frames:
            raise VrsError("no frame-XXXXXX.color.png/.jpg images", root / seq)
        lost = orphan_poses(root / seq, {idx for idx, _ in frames})
        if query and has_split:
            # a test frame whose image is gone stays a query (its pose is the ground truth):
            # localizing it flags it ("image not found") and it counts as a failure
            idxs = [_POSE.match(Path(o).name).group(1) for o in lost]
            frames = sorted(frames + [(i, root / seq / f"frame-{i}.color.png") for i in idxs])
        else:
            orphans += lost
        for idx, img in frames:
            pose_f = img.with_name(f"frame-{idx}.pose.txt")
            R, t = read_pose_file(pose_f)
            depth_f = img.with_name(f"frame-{idx}.depth.png")
            names.append(f"{seq}/{img.name}")
            paths.append(img)
            depth_paths.append(depth_f if depth_f.is_file() else None)
            Rs.append(R)
            ts.append(t)
            is_query.append(query)
    # a missing pose is an error (read_pose_file); a pose without its image is skipped, said
    C.warn_list("7-Scenes pose files without a frame-XXXXXX.color image, skipped", orphans)
    n = len(names)
    R, t = np.stack(Rs), np.stack(ts)
    is_query = np.asarray(is_query)
    if not has_split:
        is_query = C.query_mask(names, query_every)
    # an unreadable query image is flagged when it is localized, not here
    sizes = C.image_sizes(paths, tolerate=is_query)

    # Depth images: 7-Scenes' are all 640x480; read the header of the first one per sequence
    # folder (the dataset guarantees a constant size within a sequence).
    depth_sizes = np.array(sizes)
    first_depth: dict[str, tuple[int, int]] = {}
    for i, d in enumerate(depth_paths):
        if d is not None:
            key = str(d.parent)
            if key not in first_depth:
                first_depth[key] = C.image_size(d)
            depth_sizes[i] = first_depth[key]

    intr_f = root / "intrinsics.txt"
    if intr_f.is_file():
        K0, size0 = read_intrinsics_txt(intr_f)
        K = np.stack([C.scale_to_size(K0, size0, s, p) for s, p in zip(sizes, paths, strict=True)])
        depth_K = np.stack([C.scale_to_size(K0, size0, s) for s in depth_sizes])
    else:
        K0 = C.pinhole(RGB_F, RGB_F, CX, CY)
        Kd0 = C.pinhole(DEPTH_F, DEPTH_F, CX, CY)
        K = np.stack([C.scale_to_size(K0, (W0, H0), s) for s in sizes])
        depth_K = np.stack([C.scale_to_size(Kd0, (W0, H0), s) for s in depth_sizes])

    if pgt is not None:
        table = read_pgt(Path(pgt))
        by_stem = {_strip_ext(k): v for k, v in table.items()}
        used = 0
        for i, name in enumerate(names):
            entry = table.get(name) or by_stem.get(_strip_ext(name))
            if entry is None:
                continue
            Rp, tp, f, _ = entry
            R[i], t[i] = Rp, tp
            K[i] = C.scale_to_size(C.pinhole(f, f, CX, CY), (W0, H0), sizes[i])
            used += 1
        if used == 0:
            raise VrsError("no image of the scene is listed in the pseudo-ground-truth file",
                           pgt)
        if used < n:
            warnings.warn(f"{pgt}: {n - used} of {n} images have no pseudo-ground-truth pose; "
                          "they keep the dataset poses", stacklevel=2)

    return C.make_scene(root, names, paths, K, None, sizes, R, t, np.ones(n, bool), is_query,
                        "7scenes", depth_paths=depth_paths, depth_K=depth_K,
                        depth_scale=DEPTH_SCALE)
