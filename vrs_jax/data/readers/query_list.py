"""hloc query lists with intrinsics (``*_queries_with_intrinsics.txt``).

One query per line, as hloc writes and reads them::

    name MODEL width height params...

``MODEL`` and ``params`` are a COLMAP camera model and its parameters in COLMAP's order
(``SIMPLE_RADIAL 1024 768 977 512 384 -0.01`` = f, cx, cy, k1). Supported: SIMPLE_PINHOLE,
PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, and FULL_OPENCV with k4 = k5 = k6 = 0 (see
:func:`vrs_jax.data.readers.colmap.camera_to_K_dist`, the one place the models are mapped).
Empty lines and lines starting with ``#`` are skipped.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np

from vrs_jax.data.readers import _common as C
from vrs_jax.data.readers import colmap as colmap_reader
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError, require_dir


class QueryEntry(NamedTuple):
    """One line of a query list.

    Attributes:
      name: image name (relative to the images folder).
      model: COLMAP camera model name as written.
      width, height: image size in pixels the intrinsics refer to.
      K: [3, 3] float64 intrinsics (COLMAP pixel convention).
      dist: [5] float64 OpenCV distortion (k1, k2, p1, p2, k3).
      line: 1-based line number in the file (for messages).
    """

    name: str
    model: str
    width: int
    height: int
    K: np.ndarray
    dist: np.ndarray
    line: int


def read_query_list(path: str | Path) -> list[QueryEntry]:
    """Parse a query list with intrinsics -> entries in file order.

    Raises:
      VrsError naming ``path:line`` for a malformed line (too few fields, a width/height that
      is not a positive integer, non-numeric parameters), an unsupported camera model
      ("unsupported camera model X"), a wrong parameter count, a FULL_OPENCV camera with
      k4/k5/k6 != 0, or a name listed twice.
    """
    path = Path(path)
    out: list[QueryEntry] = []
    seen: dict[str, int] = {}
    for lineno, text in C.text_lines(path, "query list"):
        if text.startswith("#"):
            continue
        parts = text.split()
        if len(parts) < 5:
            raise VrsError("malformed query line: expected 'name MODEL width height params...'",
                           path, lineno)
        wh = C.parse_floats(parts[2:4], path, lineno, "query line (width height)")
        if not all(C.finite_positive(x) and float(x).is_integer() for x in wh):
            raise VrsError("malformed query line: width and height must be positive integers",
                           path, lineno)
        params = C.parse_floats(parts[4:], path, lineno, "query line (camera parameters)")
        K, dist = colmap_reader.camera_to_K_dist(parts[1], params, path, lineno)
        name = parts[0]
        if name in seen:
            raise VrsError(f"query {name} listed twice (first on line {seen[name]})", path,
                           lineno)
        seen[name] = lineno
        out.append(QueryEntry(name, parts[1], int(wh[0]), int(wh[1]), K, dist, lineno))
    return out


def query_scene(list_path: str | Path, images_dir: str | Path) -> Scene:
    """A Scene of the queries of a list, for localizing them (no ground truth).

    Args:
      list_path: the query list with intrinsics.
      images_dir: folder the list's names are relative to.
    Returns:
      Scene (format ``query_list``, root ``images_dir``) with one image per entry in file
      order: names as listed, K/dist from the list, sizes [N, 2] as read (equal to the list's),
      ``has_pose`` False and placeholder poses (identity, zero), ``is_query`` True.
    Raises:
      VrsError for a malformed list (see :func:`read_query_list`), an empty list, no listed
      image under ``images_dir`` (naming the first), or an image whose size differs from the
      list's ``width height`` (naming the list line). An image that is missing or cannot be
      read (empty, not an image) is not an error here: localizing it flags it, with its
      reason, while the other queries are localized.
    """
    list_path = Path(list_path)
    img_dir = require_dir(images_dir, "images folder")
    entries = read_query_list(list_path)
    if not entries:
        raise VrsError("query list has no queries", list_path)
    paths = [img_dir / e.name for e in entries]
    if not any(p.is_file() for p in paths):  # none there: a wrong --images folder
        e = entries[0]
        raise VrsError(f"image of query {e.name} (line {e.line} of {list_path}) not found "
                       f"(nor any other listed image: is {img_dir} the right folder?)",
                       paths[0])
    # an unreadable query image keeps the list's size; localizing it flags it
    sizes = C.image_sizes(paths, tolerate=[True] * len(paths),
                          declared=[(e.width, e.height) for e in entries])
    for e, (w, h) in zip(entries, sizes, strict=True):
        if (w, h) != (e.width, e.height):
            raise VrsError(f"image {e.name} is {w}x{h} but the list gives {e.width}x{e.height}",
                           list_path, e.line)
    n = len(entries)
    R, t = C.identity_poses(n)
    return C.make_scene(img_dir, [e.name for e in entries], paths,
                        np.stack([e.K for e in entries]), np.stack([e.dist for e in entries]),
                        sizes, R, t, np.zeros(n, bool), np.ones(n, bool), "query_list")
