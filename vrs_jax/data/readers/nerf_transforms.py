"""NeRF ``transforms.json``: Blender (nerf_synthetic) and instant-ngp / nerfstudio styles.

- Poses: ``transform_matrix`` is camera-to-world in OpenGL camera axes (x right, y up, looking
  down -z); the camera's y and z axes are flipped to OpenCV's and the matrix inverted.
- Blender intrinsics: ``camera_angle_x`` (horizontal field of view) gives
  ``f = 0.5 * W / tan(0.5 * camera_angle_x)`` for the actual image width W, so it needs no
  scaling; ``camera_angle_y`` gives fy when present (else fy = fx); the principal point is the
  image centre.
- instant-ngp / nerfstudio intrinsics: ``fl_x fl_y cx cy w h`` and distortion
  ``k1 k2 p1 p2 (k3)`` (OpenCV's model), at the top level or per frame (per-frame values win).
  When ``w``/``h`` are given and the image on disk has another size, K is scaled to it.
  ``camera_model`` other than OPENCV/PINHOLE (e.g. fisheye) is refused.
- Pixel convention: a principal point of W/2 in these files is the exact image centre
  (Blender renders about it; colmap2nerf copies COLMAP's cx), which is our (COLMAP) pixel
  convention, so cx, cy pass through unchanged.
- Images: ``file_path`` is relative to the JSON's folder and may lack its extension
  (nerf_synthetic writes ``./train/r_0`` for ``train/r_0.png``). Frames whose file is missing
  are skipped with one warning. RGBA images are composited on ``background`` (recorded in
  ``Scene.background``, which ``images.read_image`` takes).
- Split lists (nerfstudio): ``train_filenames`` / ``val_filenames`` / ``test_filenames`` at
  the top level of a transforms file name frames by their ``file_path`` (relative to the JSON's
  folder, ``./`` optional, with or without the image's extension). See :func:`load` for how
  they choose queries; an entry that matches no frame, or a frame in both the train list and
  a val/test list, is a VrsError.
- Masks (``mask_path`` per frame, or at the top level) are NOT used: one warning says so and
  every pixel of the images is used.
"""

from __future__ import annotations

import json
import math
import posixpath
import warnings
from pathlib import Path

import numpy as np

from vrs_jax import geometry
from vrs_jax.data.readers import _common as C
from vrs_jax.errors import VrsError, require_dir

_DIST_KEYS = ("k1", "k2", "p1", "p2", "k3")
_SPLITS = ("train", "val", "test")


def _num(d: dict, key: str, path: Path, where: str) -> float | None:
    if key not in d or d[key] is None:
        return None
    try:
        v = float(d[key])
    except (TypeError, ValueError):
        raise VrsError(f"{where}: '{key}' must be a number, got {d[key]!r}", path) from None
    if not math.isfinite(v):
        raise VrsError(f"{where}: '{key}' is not finite", path)
    return v


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        raise VrsError(f"malformed JSON: {e.msg}", path, e.lineno) from None
    except OSError as e:
        raise VrsError(f"cannot read: {e.strerror or e}", path) from None
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise VrsError("not a NeRF transforms file (no 'frames' list)", path)
    return data


def _intrinsics(meta: dict, frame: dict, size: tuple[int, int], path: Path, where: str
                ) -> tuple[np.ndarray, np.ndarray]:
    """K [3, 3], dist [5] for one frame of actual image ``size`` (w, h)."""
    get = lambda k: (_num(frame, k, path, where) if k in frame  # noqa: E731
                     else _num(meta, k, path, "top level"))
    w, h = size
    model = frame.get("camera_model", meta.get("camera_model", "OPENCV"))
    if model not in ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE"):
        raise VrsError(f"{where}: unsupported camera_model {model!r} (OPENCV or PINHOLE only)",
                       path)
    ax = get("camera_angle_x")
    flx = get("fl_x")
    dist = np.asarray([get(k) or 0.0 for k in _DIST_KEYS])
    if flx is not None:
        fly = get("fl_y") or flx
        w0, h0 = get("w"), get("h")
        cx = get("cx")
        cy = get("cy")
        if w0 is None or h0 is None:
            # No stated size: the intrinsics refer to the images as they are.
            w0, h0 = float(w), float(h)
        if w0 <= 0 or h0 <= 0:
            raise VrsError(f"{where}: image size w, h must be positive, got {w0:g}, {h0:g}",
                           path)
        K = C.pinhole(flx, fly, w0 / 2 if cx is None else cx, h0 / 2 if cy is None else cy)
        if flx <= 0 or fly <= 0:
            raise VrsError(f"{where}: focal lengths must be positive", path)
        return C.scale_to_size(K, (w0, h0), (w, h)), dist
    if ax is not None:
        if not 0 < ax < math.pi:
            raise VrsError(f"{where}: camera_angle_x must be in (0, pi)", path)
        fx = 0.5 * w / math.tan(0.5 * ax)
        ay = get("camera_angle_y")
        fy = fx if ay is None else 0.5 * h / math.tan(0.5 * ay)
        return C.pinhole(fx, fy, w / 2, h / 2), dist
    raise VrsError(f"{where}: no intrinsics (need camera_angle_x or fl_x)", path)


def _transforms_files(root: Path, split: str | None) -> list[tuple[Path, bool]]:
    """[(json path, frames are queries)] for the requested split."""
    if split is not None:
        f = root / f"transforms_{split}.json"
        if not f.is_file():
            raise VrsError(f"transforms file for split {split!r} not found", f)
        return [(f, split == "test")]
    if (root / "transforms.json").is_file():
        return [(root / "transforms.json", False)]
    found = [(root / f"transforms_{s}.json", s == "test") for s in ("train", "val", "test")]
    found = [(f, q) for f, q in found if f.is_file()]
    if not found:
        raise VrsError("no transforms.json or transforms_{train,val,test}.json", root)
    return found


def _split_lists(meta: dict, path: Path) -> dict[str, set[str]]:
    """{split: normalised file paths} of the ``{split}_filenames`` lists present in ``meta``."""
    out = {}
    for split in _SPLITS:
        key = f"{split}_filenames"
        if key not in meta:
            continue
        lst = meta[key]
        if not isinstance(lst, list) or not all(isinstance(x, str) for x in lst):
            raise VrsError(f"'{key}' must be a list of file paths", path)
        out[split] = {_norm(x) for x in lst}
    return out


def _norm(file_path: str) -> str:
    """A ``file_path`` as a comparable key: posix separators, no ``./``."""
    return posixpath.normpath(str(file_path).replace("\\", "/"))


def _frame_keys(frame: dict, img: Path | None, folder: Path) -> set[str]:
    """The keys a split list may name a frame by: its file_path, and its image's path with
    and without the extension."""
    keys = {_norm(frame["file_path"])}
    if img is not None:
        try:
            rel = img.relative_to(folder)
        except ValueError:
            return keys
        keys |= {rel.as_posix(), rel.with_suffix("").as_posix()}
    return keys


def _roles(lists: dict[str, set[str]], keys: list[set[str]], file_paths: list[str],
           path: Path) -> list[str]:
    """Per frame of one file: "query" (in val/test), "ref" (in train, or in no list when
    there is no train list) or "skip" (in no list while a train list exists)."""
    for split, names in lists.items():
        known = set().union(*keys) if keys else set()
        unknown = sorted(names - known)
        if unknown:
            raise VrsError(f"{split}_filenames names {len(unknown)} file(s) that no frame has "
                           f"as file_path: {', '.join(unknown[:3])}", path)
    roles = []
    for k, fp in zip(keys, file_paths, strict=True):
        in_eval = any(k & lists.get(s, set()) for s in ("val", "test"))
        in_train = bool(k & lists.get("train", set()))
        if in_eval and in_train:
            raise VrsError(f"frame {fp} is in train_filenames and in a val/test list", path)
        roles.append("query" if in_eval else "ref" if in_train or "train" not in lists
                     else "skip")
    return roles


def load(root: str | Path, *, split: str | None = None,
         background: tuple[float, float, float] = (1.0, 1.0, 1.0), query_every: int = 0):
    """Read a NeRF dataset folder.

    Args:
      root: folder holding the transforms JSON file(s).
      split: ``"train"``, ``"val"``, ``"test"``: read ``transforms_{split}.json``; None:
        ``transforms.json`` if present, else all of ``transforms_{train,val,test}.json`` that
        exist, with the test frames as queries.
      background: RGB in [0, 1] that RGBA images are composited on (``Scene.background``).
      query_every: hold out every N-th frame (by name) as a query when no test split file
        is read. It wins over split lists: with ``query_every > 0`` the lists are ignored
        (with a warning) and every frame is used.
    Returns:
      Scene with names relative to ``root`` (e.g. ``train/r_0.png``).

    Queries, in order of precedence: the frames of ``transforms_test.json`` when the split
    files are read; else, when ``query_every > 0``, every N-th frame by name; else, when the
    file has nerfstudio split lists, the frames in ``val_filenames`` or ``test_filenames``
    (references: the frames in ``train_filenames``; frames in no list are skipped with a
    warning when a train list exists, and are references when it does not); else none.
    """
    root = require_dir(root, "NeRF dataset folder")
    bg = tuple(float(x) for x in background)
    if len(bg) != 3 or not all(0.0 <= x <= 1.0 for x in bg):
        raise VrsError(f"background must be 3 numbers in [0, 1], got {background}", root)
    files = _transforms_files(root, split)
    names, paths, frames, is_query, missing = [], [], [], [], []
    masks, unlisted, ignored_lists = False, [], []
    for jf, query in files:
        meta = _read_json(jf)
        lists = _split_lists(meta, jf)
        masks = masks or "mask_path" in meta
        if lists and query_every > 0:
            ignored_lists.append(jf)
            lists = {}
        keys, fps, roles = [], [], None
        if lists:
            for frame in meta["frames"]:
                ok = isinstance(frame, dict) and "file_path" in frame
                fps.append(str(frame["file_path"]) if ok else "")
                keys.append(_frame_keys(frame, C.find_image(jf.parent / fps[-1]), jf.parent)
                            if ok else set())
            roles = _roles(lists, keys, fps, jf)
        for k, frame in enumerate(meta["frames"]):
            where = f"frame {k}"
            if not isinstance(frame, dict) or "file_path" not in frame \
                    or "transform_matrix" not in frame:
                raise VrsError(f"{where}: needs 'file_path' and 'transform_matrix'", jf)
            masks = masks or "mask_path" in frame
            if roles is not None and roles[k] == "skip":
                unlisted.append(str(frame["file_path"]))
                continue
            img = C.find_image(jf.parent / str(frame["file_path"]))
            if img is None:
                missing.append(str(frame["file_path"]))
                continue
            try:
                M = np.asarray(frame["transform_matrix"], np.float64)
            except (TypeError, ValueError):
                raise VrsError(f"{where}: transform_matrix is not a numeric matrix", jf) \
                    from None
            if M.shape not in ((4, 4), (3, 4)) or not np.all(np.isfinite(M)):
                raise VrsError(f"{where}: transform_matrix must be a finite 4x4 or 3x4 matrix, "
                               f"got shape {M.shape}", jf)
            try:
                name = img.resolve().relative_to(root.resolve()).as_posix()
            except ValueError:
                name = img.name
            names.append(name)
            paths.append(img)
            frames.append((meta, frame, M, jf, where))
            is_query.append(query or (roles is not None and roles[k] == "query"))
    C.warn_list("NeRF frames whose image file is missing, skipped", missing)
    C.warn_list("NeRF frames in none of train/val/test_filenames, skipped", unlisted)
    if ignored_lists:
        warnings.warn(f"query_every={query_every} given: the train/val/test_filenames split of "
                      f"{ignored_lists[0]} is ignored (every frame used, every "
                      f"{query_every}-th by name is a query)", stacklevel=2)
    if masks:
        warnings.warn(f"{files[0][0]}: mask_path given, but vrs-jax does not use masks: all "
                      "pixels of the images are used", stacklevel=2)
    if not names:
        raise VrsError("no frame with an existing image file", files[0][0])
    is_query = np.asarray(is_query)
    if not is_query.any():
        is_query = C.query_mask(names, query_every)
    sizes = C.image_sizes(paths, tolerate=is_query)
    K, dist, R, t = [], [], [], []
    for (meta, frame, M, jf, where), size in zip(frames, sizes, strict=True):
        Ki, di = _intrinsics(meta, frame, (int(size[0]), int(size[1])), jf, where)
        c2w = geometry.opengl_to_opencv_c2w(M[:3] if M.shape[0] == 4 else M)
        Rc2w = C.rotation_from_matrix(c2w[:3, :3], jf)
        Ri, ti = geometry.pose_inverse(Rc2w, c2w[:3, 3])
        K.append(Ki)
        dist.append(di)
        R.append(Ri)
        t.append(ti)
    n = len(names)
    return C.make_scene(root, names, paths, np.stack(K), np.stack(dist), sizes, np.stack(R),
                        np.stack(t), np.ones(n, bool), is_query, "nerf", background=bg)
