"""Cambridge Landmarks (PoseNet's outdoor scenes: King's College, Shop Facade, ...).

``root/dataset_train.txt`` and ``root/dataset_test.txt`` have 3 header lines, then one line
per image ``name X Y Z W P Q R``: the camera centre ``c = (X, Y, Z)`` and the world-to-camera
rotation as a quaternion ``(W, P, Q, R)`` (w first), so ``t = -R c``. A few poses in the
original files are garbage (|c| of order 1e5 or more); those with ``|c| > 1e4`` (or
non-finite values) are dropped with a warning naming them.

Intrinsics, in order of preference:
  1. ``focal=F``: one focal length (pixels of the actual images) for every image;
  2. ``colmap=PATH``: a COLMAP model of the scene (e.g. hloc's), matched by image name (file
     extension ignored), scaled from the model camera's size to the actual image size;
  3. ``nvm=PATH`` (default ``root/reconstruction.nvm``): per-image focal lengths of the
     VisualSFM model shipped with the dataset, matched by name without extension (the NVM
     lists ``.jpg`` where the split files list ``.png``). The NVM was built on the original
     1920x1080 video frames: ASSUMPTION: ``nvm_size`` = (1920, 1080) is the frame size its
     focals refer to, so fx = f * w / 1920 and fy = f * h / 1080 for an image of w x h
     (pass ``nvm_size`` if your NVM refers to other frames). The principal point is the
     image centre (VisualSFM's assumption). NVM radial distortion becomes OpenCV
     ``k1 = -r`` (first-order inverse of NVM's model, as COLMAP's NVM import does).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from vrs_jax import geometry
from vrs_jax.data.readers import _common as C
from vrs_jax.data.readers import colmap as colmap_reader
from vrs_jax.data.readers import nvm as nvm_reader
from vrs_jax.errors import VrsError, require_dir

MAX_CENTER = 1e4  # metres; larger camera centres in the split files are known-bad entries
NVM_SIZE = (1920, 1080)  # frame size the Cambridge NVM focals refer to (see module docstring)


def _key(name: str) -> str:
    """Image name without extension, ``/`` separators: matches NVM/COLMAP to split names."""
    return re.sub(r"\.[A-Za-z0-9]+$", "", name.replace("\\", "/").lstrip("./"))


def read_split_file(path: Path) -> list[tuple[str, np.ndarray, np.ndarray, int]]:
    """``dataset_*.txt`` -> [(name, R [3, 3], c [3], line)]; VrsError on malformed lines."""
    out = []
    for lineno, text in C.text_lines(path, "split file"):
        if lineno <= 3:  # the 3 header lines (the third is usually empty)
            continue
        parts = text.split()
        if len(parts) != 8:
            raise VrsError(f"malformed pose line: expected 'name X Y Z W P Q R', got "
                           f"{len(parts)} fields", path, lineno)
        v = C.parse_floats(parts[1:], path, lineno, "pose line")
        out.append((parts[0], v[3:7], v[:3], lineno))
    return out


def load(root: str | Path, *, nvm: str | Path | None = None, nvm_size=NVM_SIZE,
         colmap: str | Path | None = None, focal: float | None = None,
         read_points: bool = True, query_every: int = 0):
    """Read a Cambridge Landmarks scene folder (see the module docstring for intrinsics).

    Args:
      root: scene folder holding ``dataset_train.txt``, ``dataset_test.txt`` and ``seqN/``.
      nvm, nvm_size, colmap, focal: intrinsics sources (module docstring).
      read_points: load the NVM's 3D points into ``Scene.points3d``.
      query_every: only used when ``dataset_test.txt`` is absent.
    Returns:
      Scene with names as in the split files (relative to ``root``); test images are queries.
    """
    root = require_dir(root, "Cambridge Landmarks scene folder")
    train_f, test_f = root / "dataset_train.txt", root / "dataset_test.txt"
    if not train_f.is_file():
        raise VrsError("dataset_train.txt not found", train_f)
    entries = [(e, False) for e in read_split_file(train_f)]
    if test_f.is_file():
        entries += [(e, True) for e in read_split_file(test_f)]

    dropped, kept = [], []
    for (name, q, c, _line), query in entries:
        ok = np.all(np.isfinite(q)) and np.all(np.isfinite(c)) and np.linalg.norm(q) > 1e-9
        if not ok or np.linalg.norm(c) > MAX_CENTER:
            dropped.append(name)
            continue
        kept.append((name, q, c, query))
    C.warn_list(f"Cambridge poses with |c| > {MAX_CENTER:g} or non-finite values dropped",
                dropped)
    if not kept:
        raise VrsError("no usable pose in the split files", root)

    names = [e[0] for e in kept]
    paths = [root / n for n in names]
    for p in paths:
        if not p.is_file():
            raise VrsError("image listed in the split file not found", p)
    is_query = np.asarray([e[3] for e in kept])
    if not test_f.is_file():
        is_query = C.query_mask(names, query_every)
    sizes = C.image_sizes(paths, tolerate=is_query)
    R = geometry.quat_to_rot(np.stack([e[1] for e in kept]))
    centres = np.stack([e[2] for e in kept])
    t = -(R @ centres[..., None])[..., 0]
    n = len(names)
    dist = np.zeros((n, 5))
    points3d = None

    if focal is not None:
        if not C.finite_positive(float(focal)):
            raise VrsError(f"focal must be a positive number, got {focal}", root)
        K = np.stack([C.pinhole(focal, focal, w / 2, h / 2) for w, h in sizes])
    elif colmap is not None:
        rec = colmap_reader.read_reconstruction(colmap)
        by_key = {_key(im.name): im for im in rec.images.values()}
        K = np.zeros((n, 3, 3))
        missing = []
        for i, name in enumerate(names):
            im = by_key.get(_key(name))
            if im is None:
                missing.append(name)
                continue
            cam = rec.cameras[im.camera_id]
            Ki, dist[i] = colmap_reader.camera_to_K_dist(cam.model.name, cam.params, colmap)
            K[i] = C.scale_to_size(Ki, (cam.width, cam.height), sizes[i], paths[i])
        if missing:
            raise VrsError(f"{len(missing)} images have no camera in the COLMAP model, e.g. "
                           f"{missing[0]}", colmap)
    else:
        nvm_path = Path(nvm) if nvm is not None else root / "reconstruction.nvm"
        if not nvm_path.is_file():
            raise VrsError("no intrinsics: NVM model not found (pass nvm=, colmap= or focal=)",
                           nvm_path)
        model = nvm_reader.read_nvm(nvm_path, read_points=read_points)
        by_key = {_key(nm): i for i, nm in enumerate(model.names)}
        K = np.zeros((n, 3, 3))
        missing = []
        for i, name in enumerate(names):
            j = by_key.get(_key(name))
            if j is None:
                missing.append(name)
                continue
            w, h = sizes[i]
            f = model.focal[j]
            K[i] = C.pinhole(f * w / nvm_size[0], f * h / nvm_size[1], w / 2, h / 2)
            dist[i, 0] = nvm_reader.nvm_k1(model.radial[j])
        if missing:
            raise VrsError(f"{len(missing)} images have no camera in the NVM model, e.g. "
                           f"{missing[0]}", nvm_path)
        if read_points:
            points3d = model.points

    return C.make_scene(root, names, paths, K, dist, sizes, R, t, np.ones(n, bool), is_query,
                        "cambridge", points3d=points3d)
