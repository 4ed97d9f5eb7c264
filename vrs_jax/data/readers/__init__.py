"""Dataset readers: every format is converted to one :class:`vrs_jax.data.scene.Scene`.

    scene = load_scene("7scenes", "/data/7scenes/chess", query_every=0)

Formats (see each module's docstring for the layout and the conventions converted):

========== ======================= ==================================================
format     module                  root
========== ======================= ==================================================
7scenes    ``sevenscenes``         scene folder with ``seq-XX/`` (also synthetic scenes)
cambridge  ``cambridge``           scene folder with ``dataset_{train,test}.txt``
aachen     ``aachen``              dataset folder with ``3D-models/``, ``queries/``
nerf       ``nerf_transforms``     folder with ``transforms*.json``
llff       ``llff``                folder with ``poses_bounds.npy`` and ``images_N/``
colmap     ``colmap``              model folder, or project with ``sparse/0``
========== ======================= ==================================================

Common options: ``query_every`` (hold out every N-th image by name as a query, for formats
without a split), ``query_range`` (``"A:B"``: the images at positions A..B-1 in name order are
queries as well -- a whole stretch of a video held out of the map, as 7-Scenes' separate
test sequences are) and ``downscale`` (images will be read at 1/downscale of their size: sizes
and K are adjusted here; the consumer resizes with
``images.read_image(path, size=tuple(scene.sizes[i]))``; depth images keep their size and
``depth_K``).
"""

from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path

import numpy as np

from vrs_jax.data.readers import aachen, cambridge, colmap, llff, nerf_transforms, sevenscenes
from vrs_jax.data.readers._common import scale_to_size
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError

_LOADERS = {
    "7scenes": sevenscenes.load,
    "cambridge": cambridge.load,
    "aachen": aachen.load,
    "nerf": nerf_transforms.load,
    "llff": llff.load,
    "colmap": colmap.load,
}
FORMATS = tuple(_LOADERS)


def options(fmt: str) -> tuple[str, ...]:
    """Names of the options a format accepts (besides ``downscale``)."""
    if fmt not in _LOADERS:
        raise VrsError(f"unknown dataset format {fmt!r} (known: {', '.join(FORMATS)})")
    params = inspect.signature(_LOADERS[fmt]).parameters
    return tuple(k for k, p in params.items() if p.kind is inspect.Parameter.KEYWORD_ONLY)


def downscale_scene(scene: Scene, factor: int) -> Scene:
    """Sizes -> round(size / factor) and K scaled to match (exactly, per axis)."""
    if factor == 1:
        return scene
    sizes = np.maximum(np.round(scene.sizes / float(factor)), 1).astype(np.int64)
    K = np.stack([scale_to_size(k, s0, s1) for k, s0, s1 in
                  zip(scene.K, scene.sizes, sizes, strict=True)])
    return dataclasses.replace(scene, sizes=sizes, K=K)


def load_scene(fmt: str, root: str | Path, **opts) -> Scene:
    """Read a dataset of format ``fmt`` (one of FORMATS) at ``root`` into a Scene.

    Raises:
      VrsError: unknown format or option, missing/malformed files (message names the file and
        the line where there is one).
    """
    known = options(fmt)
    downscale = opts.pop("downscale", None)
    query_range = opts.pop("query_range", None)
    bad = sorted(set(opts) - set(known))
    if bad:
        raise VrsError(f"unknown option(s) {', '.join(bad)} for format {fmt!r} (known: "
                       f"{', '.join(known + ('downscale', 'query_range'))})", root)
    qe = opts.get("query_every", 0)
    if qe is not None and (not isinstance(qe, (int, np.integer)) or qe < 0):
        raise VrsError(f"query_every must be an integer >= 0, got {qe!r}", root)
    scene = _LOADERS[fmt](root, **opts)
    if downscale is not None:
        if not isinstance(downscale, (int, np.integer)) or downscale < 1:
            raise VrsError(f"downscale must be an integer >= 1, got {downscale!r}", root)
        scene = downscale_scene(scene, int(downscale))
    if query_range is not None:
        scene = hold_out_range(scene, query_range, root)
    return scene


def parse_range(text: str, n: int, where=None) -> tuple[int, int]:
    """``"A:B"`` -> (A, B) with 0 <= A < B <= n (positions in name order); VrsError else."""
    a, sep, b = str(text).partition(":")
    try:
        lo, hi = int(a), int(b)
    except ValueError:
        lo, hi = -1, -1
    if not sep or not 0 <= lo < hi <= n:
        raise VrsError(f"query_range must be A:B with 0 <= A < B <= {n} (the dataset's "
                       f"images in name order), got {text!r}", where)
    return lo, hi


def hold_out_range(scene: Scene, text: str, where=None) -> Scene:
    """The images at positions A..B-1 of the name order (``text`` = "A:B") become queries."""
    lo, hi = parse_range(text, len(scene), where)
    order = np.argsort(np.asarray(scene.names, dtype=object), kind="stable")
    is_query = np.asarray(scene.is_query, bool).copy()
    is_query[order[lo:hi]] = True
    if not np.any(~is_query):
        raise VrsError(f"query_range {text} leaves no reference image", where)
    return dataclasses.replace(scene, is_query=is_query)


__all__ = ["FORMATS", "load_scene", "options", "downscale_scene", "hold_out_range"]
