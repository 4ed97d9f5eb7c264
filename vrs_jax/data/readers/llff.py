"""LLFF forward-facing scenes (``poses_bounds.npy``), as used by NeRF (fern, flower, ...).

``poses_bounds.npy`` is [N, 17]: per image a 3x5 matrix flattened row-major, then near and
far depth bounds. The matrix is ``[a0 a1 a2 | c | hwf]``: three camera-to-world axis columns
in LLFF's order [down, right, back], the camera centre, and (H, W, focal) at the full
resolution. OpenCV's camera axes are x = right = a1, y = down = a0, z = forward = -a2; the
resulting camera-to-world matrix is inverted. The world frame is COLMAP's (LLFF only permutes
the camera axes), so ``sparse/0/points3D`` is in the same frame.

Images are the sorted PNG/JPEG files of ``images_{factor}`` (or ``images``); the i-th file
goes with the i-th row, as in LLFF's own loader. Focal, H and W are divided by the factor; the
intrinsics are finally scaled to the actual image size (which must agree with H/factor,
W/factor to within a pixel, else a warning), principal point at the image centre.
"""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np

from vrs_jax import geometry
from vrs_jax.data.readers import _common as C
from vrs_jax.data.readers import colmap as colmap_reader
from vrs_jax.errors import VrsError, require_dir


def _default_factor(root: Path) -> int:
    """Smallest N with an ``images_N`` folder, else 1 (``images``)."""
    found = sorted(int(m.group(1)) for p in root.iterdir()
                   if p.is_dir() and (m := re.fullmatch(r"images_(\d+)", p.name)))
    found = [f for f in found if f > 0]
    return found[0] if found else 1


def load(root: str | Path, *, factor: int | None = None, query_every: int = 0,
         read_points: bool = True):
    """Read an LLFF scene folder.

    Args:
      root: folder holding ``poses_bounds.npy`` and ``images[_N]/``.
      factor: down-scale factor N, images from ``images_N`` (1: ``images``). Default: the
        smallest N for which ``images_N`` exists, else 1.
      query_every: hold out every N-th image (by name) as a query (LLFF/NeRF use 8).
      read_points: load ``sparse/0/points3D`` (coordinates only) into ``Scene.points3d``.
    Returns:
      Scene with names = image file names, ``bounds`` [N, 2] (near, far) in scene units.
    """
    root = require_dir(root, "LLFF scene folder")
    pb_path = root / "poses_bounds.npy"
    if not pb_path.is_file():
        raise VrsError("poses_bounds.npy not found", pb_path)
    try:
        pb = np.load(pb_path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:  # EOFError: a zero-byte file
        raise VrsError(f"unreadable .npy file: {e or 'empty file'}", pb_path) from None
    if pb.dtype.kind not in "biuf":
        raise VrsError(f"expected a finite [N, 17] array of numbers, got dtype {pb.dtype}",
                       pb_path)
    if pb.ndim != 2 or pb.shape[1] != 17 or not np.all(np.isfinite(pb)):
        raise VrsError(f"expected a finite [N, 17] array, got shape {pb.shape}", pb_path)
    factor = _default_factor(root) if factor is None else int(factor)
    if factor < 1:
        raise VrsError(f"factor must be >= 1, got {factor}", root)
    img_dir = require_dir(root / ("images" if factor == 1 else f"images_{factor}"),
                          "LLFF images folder")
    paths = C.list_images(img_dir)
    if len(paths) != len(pb):
        raise VrsError(f"{len(paths)} images but {len(pb)} rows in poses_bounds.npy", img_dir)
    n = len(paths)
    mats = pb[:, :15].reshape(n, 3, 5)
    hwf = mats[:, :, 4]
    down, right, back, centre = (mats[:, :, k] for k in range(4))
    Rc2w = np.stack([right, down, -back], axis=-1)  # columns = OpenCV camera axes in world
    for i in range(n):
        Rc2w[i] = C.rotation_from_matrix(Rc2w[i], pb_path)
    R, t = geometry.pose_inverse(Rc2w, centre)
    names = [p.name for p in paths]
    is_query = C.query_mask(names, query_every)
    declared = np.round(hwf[:, [1, 0]] / factor).astype(int)  # (W, H) at the factor
    sizes = C.image_sizes(paths, tolerate=is_query, declared=declared)
    K = np.zeros((n, 3, 3))
    for i, (w, h) in enumerate(sizes):
        H0, W0, f0 = hwf[i] / factor
        if abs(w - W0) > 1 or abs(h - H0) > 1:
            warnings.warn(f"{paths[i]}: image is {w}x{h} but poses_bounds.npy says "
                          f"{W0:.0f}x{H0:.0f} at factor {factor}; scaling to the image",
                          stacklevel=2)
        K[i] = C.scale_to_size(C.pinhole(f0, f0, W0 / 2, H0 / 2), (W0, H0), (w, h), paths[i])
    bounds = pb[:, 15:17].astype(np.float64)
    if np.any(bounds <= 0) or np.any(bounds[:, 0] >= bounds[:, 1]):
        raise VrsError("bounds must satisfy 0 < near < far for every image", pb_path)
    points = None
    if read_points:
        sparse = root / "sparse" / "0"
        if sparse.is_dir():
            points = colmap_reader.read_points3d_xyz(sparse)
    return C.make_scene(root, names, paths, K, None, sizes, R, t, np.ones(n, bool),
                        is_query, "llff", bounds=bounds,
                        points3d=points)
