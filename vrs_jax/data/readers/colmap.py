"""COLMAP sparse models, text or binary, read with pycolmap.

COLMAP's conventions are the project's own (world-to-camera poses, OpenCV camera axes, pixel
centres at +0.5), so poses and intrinsics pass through unchanged; only the camera models are
mapped to a pinhole K plus OpenCV distortion ``(k1, k2, p1, p2, k3)``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import struct
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pycolmap

from vrs_jax.data.readers import _common as C
from vrs_jax.errors import VrsError, require_dir

# Camera models that are a pinhole plus (a subset of) OpenCV's 5-coefficient distortion, with
# their parameter counts (order as in COLMAP's models.h). FULL_OPENCV is accepted only when its
# rational part k4 = k5 = k6 = 0 (then it is OPENCV plus k3).
_N_PARAMS = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8,
             "FULL_OPENCV": 12}
SUPPORTED_MODELS = tuple(_N_PARAMS)
MODEL_PARTS = ("cameras", "images", "points3D")
"""The files of a COLMAP sparse model that the reader reads (.bin or .txt)."""


def camera_to_K_dist(model: str, params, where: Path | str | None = None,
                     line: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A COLMAP camera model and its parameters -> (K [3, 3], dist [5] OpenCV order).

    ``dist`` is ``(k1, k2, p1, p2, k3)``: SIMPLE_RADIAL fills k1, RADIAL k1 k2, OPENCV k1 k2
    p1 p2, FULL_OPENCV all five (its k4 k5 k6 must be 0). The projection of
    ``geometry.project(K, ..., dist)`` then equals COLMAP's ``img_from_cam`` for that camera.

    Raises VrsError (naming ``where``/``line``) for another model ("unsupported camera model
    X"), a wrong parameter count, non-finite values, a non-positive focal length, or a
    FULL_OPENCV camera with a rational distortion part.
    """
    p = np.asarray(params, np.float64).ravel()
    if model not in _N_PARAMS:
        raise VrsError(f"unsupported camera model {model} (supported: "
                       f"{', '.join(SUPPORTED_MODELS)})", where, line)
    if p.size != _N_PARAMS[model]:
        raise VrsError(f"camera model {model} takes {_N_PARAMS[model]} parameters, got {p.size}",
                       where, line)
    if not np.all(np.isfinite(p)):
        raise VrsError(f"non-finite {model} camera parameters", where, line)
    if model == "FULL_OPENCV" and np.any(p[9:] != 0):
        raise VrsError("FULL_OPENCV camera with k4, k5, k6 = "
                       f"{p[9]:g}, {p[10]:g}, {p[11]:g}: the rational distortion part is not "
                       "supported (only OpenCV's k1 k2 p1 p2 k3; k4 = k5 = k6 = 0 is required)",
                       where, line)
    dist = np.zeros(5)
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        K = C.pinhole(p[0], p[0], p[1], p[2])
        dist[: p.size - 3] = p[3:]  # k1 (, k2)
    else:
        K = C.pinhole(p[0], p[1], p[2], p[3])
        dist[: min(p.size - 4, 5)] = p[4:9]  # k1 k2 p1 p2 (OPENCV) (, k3: FULL_OPENCV)
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise VrsError(f"{model} camera has a non-positive focal length", where, line)
    return K, dist


def find_model(root: Path) -> Path:
    """The model folder: ``root`` itself, or ``root/sparse/0``, or ``root/sparse``."""
    for cand in (root, root / "sparse" / "0", root / "sparse"):
        if any((cand / f"cameras.{e}").is_file() for e in ("bin", "txt")):
            return cand
    raise VrsError("no COLMAP model here (cameras.bin/.txt not found in it, in sparse/0 or in "
                   "sparse)", root)


def _check_model_files(model: Path) -> None:
    for part in MODEL_PARTS:
        if not any((model / f"{part}.{e}").is_file() for e in ("bin", "txt")):
            raise VrsError(f"incomplete COLMAP model: {part}.bin / {part}.txt missing", model)


def read_reconstruction(model: str | Path) -> pycolmap.Reconstruction:
    """pycolmap.Reconstruction of a text or binary model folder, with clear VrsErrors: the
    model's files are checked first (:func:`check_model`: pycolmap hangs on some truncated
    binary files and reports other damage without naming the file)."""
    model = require_dir(model, "COLMAP model folder")
    _check_model_files(model)
    check_model(model)
    try:
        with _model_files_only(model) as d:
            return pycolmap.Reconstruction(str(d))
    except Exception as e:  # pycolmap raises ValueError/RuntimeError with C++ context
        raise VrsError(f"cannot read COLMAP model: {str(e).splitlines()[0][:200]}",
                       model) from None


@contextlib.contextmanager
def _model_files_only(model: Path) -> Iterator[Path]:
    """``model``, or when it also holds COLMAP >= 3.12's rigs and frames files, a temporary
    folder of links to its cameras, images and points3D files alone: pycolmap hangs on some
    damaged frames files, and the images file holds each image's pose (read back the same
    without them)."""
    if not any((model / f"{p}.{e}").exists() for p in ("rigs", "frames") for e in ("bin", "txt")):
        yield model
        return
    ext = "bin" if all((model / f"{p}.bin").is_file() for p in MODEL_PARTS) else "txt"
    with tempfile.TemporaryDirectory(prefix="vrs_jax_colmap_") as d:  # fileio-exempt: links
        for part in MODEL_PARTS:
            os.symlink((model / f"{part}.{ext}").resolve(), Path(d) / f"{part}.{ext}")
        yield Path(d)


# ----------------------------------------------------------------------------- model checks

# Parameter count of every COLMAP camera model, by id and by name (models.h).
_ALL_MODELS = (("SIMPLE_PINHOLE", 3), ("PINHOLE", 4), ("SIMPLE_RADIAL", 4), ("RADIAL", 5),
               ("OPENCV", 8), ("OPENCV_FISHEYE", 8), ("FULL_OPENCV", 12), ("FOV", 5),
               ("SIMPLE_RADIAL_FISHEYE", 4), ("RADIAL_FISHEYE", 5), ("THIN_PRISM_FISHEYE", 12),
               ("RAD_TAN_THIN_PRISM_FISHEYE", 16))
_MODEL_PARAMS = dict(_ALL_MODELS)


@dataclasses.dataclass
class ModelIndex:
    """What a COLMAP model's three files hold, read without pycolmap (for the checks).

    cameras: id -> (model name, width, height, params); images: id -> (name, camera id,
    qvec wxyz + tvec [7], number of 2D points); where: (file, line or None) of each camera
    and image, keyed by (part, id). The points as arrays (a model holds millions):
    point_id [M], xyz [M, 3], per track element its point's row [T], image id [T] and 2D
    point index [T]; points_file and points_line [M] (None for a binary file).
    """

    cameras: dict = dataclasses.field(default_factory=dict)
    images: dict = dataclasses.field(default_factory=dict)
    where: dict = dataclasses.field(default_factory=dict)
    point_id: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    xyz: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    track_row: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    track_image: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    track_idx: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    points_file: Path | None = None
    points_line: np.ndarray | None = None

    def point_where(self, row: int) -> tuple:
        """(file, line or None) of point row ``row``, for a VrsError."""
        return self.points_file, (None if self.points_line is None
                                  else int(self.points_line[row]))


class _Bytes:
    """A cursor over a binary file: each read past the end is a VrsError naming it."""

    def __init__(self, path: Path):
        self.path, self.data, self.off = path, path.read_bytes(), 0

    def take(self, fmt: str):
        try:
            v = struct.unpack_from("<" + fmt, self.data, self.off)
        except struct.error:
            raise VrsError(f"truncated at byte {self.off} of {len(self.data)}",
                           self.path) from None
        self.off += struct.calcsize("<" + fmt)
        return v

    def count(self, record_bytes: int) -> int:
        """A record count, refused when the file cannot hold that many records."""
        (n,) = self.take("Q")
        if n * record_bytes > len(self.data) - self.off:
            raise VrsError(f"truncated or damaged: says {n} records, {len(self.data)} bytes "
                           "cannot hold them", self.path)
        return n

    def name(self) -> str:
        end = self.data.find(b"\0", self.off)
        if end < 0:
            raise VrsError(f"truncated at byte {self.off} (an image name)", self.path)
        text, self.off = self.data[self.off:end].decode("utf-8", "replace"), end + 1
        return text

    def done(self) -> None:
        if self.off != len(self.data):
            raise VrsError(f"damaged: {len(self.data) - self.off} bytes after the last record",
                           self.path)


def _cameras_bin(path: Path, ix: ModelIndex) -> None:
    f = _Bytes(path)
    for _ in range(f.count(24)):
        cid, mid, w, h = f.take("iiQQ")
        if not 0 <= mid < len(_ALL_MODELS):
            raise VrsError(f"camera {cid}: unknown camera model id {mid}", f.path)
        name, n = _ALL_MODELS[mid]
        _add(ix, "cameras", cid, (name, w, h, np.array(f.take(f"{n}d"))), (f.path, None))
    f.done()


def _images_bin(path: Path, ix: ModelIndex) -> None:
    f = _Bytes(path)
    for _ in range(f.count(73)):
        iid, *pose = f.take("I7d")
        (cid,) = f.take("I")
        name = f.name()
        n = f.count(24)
        f.off += 24 * n
        _add(ix, "images", iid, (name, cid, np.array(pose), n), (f.path, None))
    f.done()


_POINT_HEAD = struct.Struct("<Q")


def _gather(buf: np.ndarray, starts: np.ndarray, n: int, dtype: str) -> np.ndarray:
    """The ``dtype`` values of ``n`` bytes at each of ``starts`` in ``buf``."""
    return buf[starts[:, None] + np.arange(n)].copy().view(dtype).reshape(len(starts), -1)


def _points_bin(path: Path, ix: ModelIndex) -> None:
    # Per point: id u64, xyz 3 f64, rgb 3 u8, error f64, track length u64 (51 bytes), then
    # the track: (image id u32, 2D point index u32) pairs. One pass finds the records, numpy
    # reads them.
    f = _Bytes(path)
    n, data = f.count(51), f.data
    starts, lens, off = np.empty(n, np.int64), np.empty(n, np.int64), f.off
    for k in range(n):
        if off + 51 > len(data):
            raise VrsError(f"truncated at byte {off} of {len(data)} (point {k + 1} of {n})",
                           path)
        (tl,) = _POINT_HEAD.unpack_from(data, off + 43)
        starts[k], lens[k] = off, tl
        off += 51 + 8 * tl
    if off > len(data):
        raise VrsError(f"truncated at byte {len(data)} (the track of point {n})", path)
    f.off = off
    f.done()
    buf = np.frombuffer(data, np.uint8)
    first = np.repeat(starts + 51, lens) + 8 * (np.arange(int(lens.sum()))
                                                 - np.repeat(np.cumsum(lens) - lens, lens))
    _set_points(ix, _gather(buf, starts, 8, "<u8")[:, 0].astype(np.int64),
                _gather(buf, starts + 8, 24, "<f8"), lens,
                _gather(buf, first, 4, "<u4")[:, 0], _gather(buf, first + 4, 4, "<u4")[:, 0],
                path, None)


def _set_points(ix: ModelIndex, ids, xyz, lens, image, idx, path: Path, lines) -> None:
    ix.point_id, ix.xyz = np.asarray(ids, np.int64), np.asarray(xyz, np.float64).reshape(-1, 3)
    ix.track_row = np.repeat(np.arange(len(ix.point_id)), lens)
    ix.track_image, ix.track_idx = np.asarray(image, np.int64), np.asarray(idx, np.int64)
    ix.points_file, ix.points_line = path, lines
    uniq, first = np.unique(ix.point_id, return_index=True)
    if len(uniq) != len(ix.point_id):
        dup = np.setdiff1d(np.arange(len(ix.point_id)), first)[0]
        raise VrsError(f"points id {ix.point_id[dup]} appears twice", *ix.point_where(dup))


def _fields(path: Path, line: int, text: str, n: int, what: str, more: bool = False) -> list:
    tok = text.split()
    if len(tok) < n or (len(tok) != n and not more):
        raise VrsError(f"malformed {what} line: {len(tok)} fields, expected "
                       f"{'at least ' if more else ''}{n}", path, line)
    return tok


def _ints(tokens, path: Path, line: int, what: str) -> list[int]:
    try:
        return [int(t) for t in tokens]
    except ValueError:
        raise VrsError(f"malformed {what} line: expected integers, got "
                       f"{' '.join(tokens)[:60]!r}", path, line) from None


def _cameras_txt(path: Path, ix: ModelIndex) -> None:
    for line, text in C.text_lines(path, "cameras.txt"):
        if text.startswith("#"):
            continue
        tok = _fields(path, line, text, 4, "camera", more=True)
        if tok[1] not in _MODEL_PARAMS:
            raise VrsError(f"unknown camera model {tok[1]!r}", path, line)
        (cid, w, h) = _ints([tok[0], tok[2], tok[3]], path, line, "camera")
        _fields(path, line, text, 4 + _MODEL_PARAMS[tok[1]], f"{tok[1]} camera")
        params = C.parse_floats(tok[4:], path, line, "camera line")
        _add(ix, "cameras", cid, (tok[1], w, h, params), (path, line))


def _images_txt(path: Path, ix: ModelIndex) -> None:
    lines = C.read_text(path, "images.txt").splitlines()
    i = 0
    while i < len(lines):
        text, line = lines[i].strip(), i + 1
        i += 1
        if not text or text.startswith("#"):
            continue
        tok = _fields(path, line, text, 10, "image")
        (iid, cid) = _ints([tok[0], tok[8]], path, line, "image")
        pose = C.parse_floats(tok[1:8], path, line, "image line")
        pts = lines[i].split() if i < len(lines) else []
        i += 1  # the image's 2D points: the next line, empty when it has none
        if len(pts) % 3:
            raise VrsError(f"malformed 2D points line of image {iid}: {len(pts)} fields, "
                           "expected X Y POINT3D_ID triples", path, line + 1)
        _add(ix, "images", iid, (tok[9], cid, pose, len(pts) // 3), (path, line))


def _points_txt(path: Path, ix: ModelIndex) -> None:
    rows = [(line, text.split()) for line, text in C.text_lines(path, "points3D.txt")
            if not text.startswith("#")]
    for line, tok in rows:
        if len(tok) < 8 or (len(tok) - 8) % 2:
            raise VrsError(f"malformed points3D line: {len(tok)} fields, expected 8 then "
                           "IMAGE_ID POINT2D_IDX pairs", path, line)
    try:
        ids = np.fromiter((int(t[0]) for _, t in rows), np.int64, len(rows))
        xyz = np.fromiter((float(x) for _, t in rows for x in t[1:4]), np.float64)
        track = np.fromiter((int(x) for _, t in rows for x in t[8:]), np.int64).reshape(-1, 2)
    except ValueError:  # find the line, for the message
        for line, tok in rows:
            C.parse_floats(tok[1:4], path, line, "points3D line")
            _ints([tok[0], *tok[8:]], path, line, "points3D")
        raise
    lens = np.array([(len(t) - 8) // 2 for _, t in rows], np.int64)
    _set_points(ix, ids, xyz, lens, track[:, 0], track[:, 1], path,
                np.array([line for line, _ in rows], np.int64))


_READERS = {"bin": (_cameras_bin, _images_bin, _points_bin),
            "txt": (_cameras_txt, _images_txt, _points_txt)}


def _index(model: Path, ext: str) -> ModelIndex:
    ix = ModelIndex()
    for part, read in zip(MODEL_PARTS, _READERS[ext], strict=True):
        read(model / f"{part}.{ext}", ix)
    return ix


def _add(ix: ModelIndex, part: str, key: int, value, where: tuple) -> None:
    table = getattr(ix, part)
    if key in table:
        raise VrsError(f"{part} id {key} appears twice", *where)
    table[key] = value
    ix.where[part, key] = where


def _check_index(ix: ModelIndex) -> None:
    """Each record's values and every cross-reference of a model (VrsError naming the file
    and line, or the record in a binary file)."""
    for cid, (_, w, h, params) in ix.cameras.items():
        if w <= 0 or h <= 0:
            raise VrsError(f"camera {cid} has size {w}x{h}", *ix.where["cameras", cid])
        if not np.all(np.isfinite(params)):
            raise VrsError(f"camera {cid} has non-finite parameters", *ix.where["cameras", cid])
    names: dict[str, int] = {}
    for iid, (name, cid, pose, _) in ix.images.items():
        where = ix.where["images", iid]
        if cid not in ix.cameras:
            raise VrsError(f"image {iid} ({name}) names camera {cid}, which is not in the "
                           "model's cameras", *where)
        if not np.all(np.isfinite(pose)) or np.linalg.norm(pose[:4]) < 1e-6:
            raise VrsError(f"image {iid} ({name}) has a non-finite pose or a zero quaternion",
                           *where)
        if name in names:
            raise VrsError(f"image name {name} appears twice (images {names[name]} and "
                           f"{iid})", *where)
        names[name] = iid
    bad = np.flatnonzero(~np.isfinite(ix.xyz).all(axis=1))
    if len(bad):
        raise VrsError(f"point {ix.point_id[bad[0]]} has non-finite coordinates",
                       *ix.point_where(bad[0]))
    ids = np.array(sorted(ix.images), np.int64)
    n2d = np.array([ix.images[i][3] for i in ids], np.int64)
    at = np.clip(np.searchsorted(ids, ix.track_image), 0, max(len(ids) - 1, 0))
    known = (ids[at] == ix.track_image) if len(ids) else np.zeros(len(at), bool)
    for e in np.flatnonzero(~known)[:1]:
        row = ix.track_row[e]
        raise VrsError(f"point {ix.point_id[row]} is seen in image {ix.track_image[e]}, which "
                       "is not in the model's images", *ix.point_where(row))
    for e in np.flatnonzero(known & (ix.track_idx >= n2d[at]))[:1]:
        row = ix.track_row[e]
        raise VrsError(f"point {ix.point_id[row]} is seen at 2D point {ix.track_idx[e]} of "
                       f"image {ix.track_image[e]}, which has {n2d[at[e]]}",
                       *ix.point_where(row))


def _same(a: ModelIndex, b: ModelIndex) -> str | None:
    """The first difference between two indexes of one model (None: they agree)."""
    if not (np.array_equal(a.point_id, b.point_id) and np.allclose(a.xyz, b.xyz, rtol=1e-6,
                                                                   atol=1e-9)
            and all(np.array_equal(getattr(a, k), getattr(b, k))
                    for k in ("track_row", "track_image", "track_idx"))):
        return f"points: {len(a.point_id)} against {len(b.point_id)}, or other values"
    for part in ("cameras", "images"):
        ta, tb = getattr(a, part), getattr(b, part)
        if ta.keys() != tb.keys():
            return f"{part}: {len(ta)} records against {len(tb)}, or other ids"
        for key, va in ta.items():
            for x, y in zip(va, tb[key], strict=True):
                if isinstance(x, np.ndarray):
                    if not np.allclose(x, y, rtol=1e-6, atol=1e-9):
                        return f"{part} id {key} differs"
                elif x != y:
                    return f"{part} id {key} differs"
    return None


def check_model(model: str | Path) -> ModelIndex:
    """Read a model's cameras, images and points3D files (binary where COLMAP reads binary:
    all three .bin files present, else text) and check them: sizes, counts, fields, finite
    values, and that every image's camera and every point's image exist. A folder holding a
    complete binary and a complete text model must hold the same model.

    Raises VrsError naming the file (and its line) and the problem.
    """
    model = Path(model)
    has = {e: all((model / f"{p}.{e}").is_file() for p in MODEL_PARTS)
           for e in ("bin", "txt")}
    ix = _index(model, "bin" if has["bin"] else "txt")
    _check_index(ix)
    if has["bin"] and has["txt"]:
        diff = _same(ix, _index(model, "txt"))
        if diff:
            raise VrsError(f"holds a binary and a text COLMAP model that disagree ({diff}); "
                           "COLMAP reads the .bin files: remove the stale model", model)
    return ix


def _cam_from_world(image) -> tuple[np.ndarray, np.ndarray]:
    # pycolmap >= 3.13 made cam_from_world a method; before, it was a property.
    pose = image.cam_from_world
    pose = pose() if callable(pose) else pose
    return np.asarray(pose.rotation.matrix(), np.float64), np.asarray(pose.translation,
                                                                      np.float64)


def _image_has_pose(image) -> bool:
    hp = getattr(image, "has_pose", True)
    return bool(hp() if callable(hp) else hp)


def read_points3d_xyz(model: str | Path) -> np.ndarray | None:
    """[M, 3] point coordinates of ``points3D.bin``/``.txt`` alone, or None if absent.

    pycolmap refuses incomplete models (LLFF's ``sparse/0`` often ships without
    ``images.bin``), so this reads just the coordinates from the file itself.
    """
    model = Path(model)
    ix = ModelIndex()
    if (model / "points3D.txt").is_file():
        _points_txt(model / "points3D.txt", ix)
    elif (model / "points3D.bin").is_file():
        _points_bin(model / "points3D.bin", ix)
    else:
        return None
    return ix.xyz


def default_images_dir(model: Path) -> Path | None:
    """The usual images folder for a model: ``images`` beside the model folder or two up."""
    for cand in (model.parent / "images", model.parent.parent / "images", model / "images"):
        if cand.is_dir():
            return cand
    return None


def load(root: str | Path, *, model: str | Path | None = None, images: str | Path | None = None,
         query_every: int = 0):
    """Read a COLMAP model and its images.

    Args:
      root: the model folder (holding cameras/images/points3D .bin or .txt), or a project
        folder holding ``sparse/0`` or ``sparse``.
      model: explicit model folder (overrides the search under ``root``).
      images: the image folder the model's names are relative to; default: ``images`` beside
        the model folder (``project/reconstruction`` + ``project/images``) or two levels up
        (``project/sparse/0`` + ``project/images``).
      query_every: hold out every N-th registered image (by name) as a query.
    Returns:
      Scene with names as in the model (relative to the images folder), K/dist converted from
      the camera model and scaled when the files' size differs from the camera's, points3d.
      Images missing from the images folder are skipped with a warning.
    """
    root = require_dir(root, "COLMAP folder")
    model_dir = require_dir(model, "COLMAP model folder") if model is not None else \
        find_model(root)
    rec = read_reconstruction(model_dir)
    img_dir = Path(images) if images is not None else default_images_dir(model_dir)
    if img_dir is None:
        raise VrsError("no images folder found beside the model (pass images=PATH)", model_dir)
    img_dir = require_dir(img_dir, "images folder")

    names, paths, Ks, dists, model_sizes, Rs, ts, posed, missing = [], [], [], [], [], [], [],\
        [], []
    for image in sorted(rec.images.values(), key=lambda im: im.name):
        path = img_dir / image.name
        if not path.is_file():
            missing.append(image.name)
            continue
        cam = rec.cameras[image.camera_id]
        K, dist = camera_to_K_dist(cam.model.name, cam.params, model_dir)
        has = _image_has_pose(image)
        R, t = _cam_from_world(image) if has else (np.eye(3), np.zeros(3))
        names.append(image.name)
        paths.append(path)
        Ks.append(K)
        dists.append(dist)
        model_sizes.append((cam.width, cam.height))
        Rs.append(R)
        ts.append(t)
        posed.append(has)
    C.warn_list(f"images of the COLMAP model missing from {img_dir}, skipped", missing)
    if not names:
        raise VrsError(f"none of the model's {len(rec.images)} images found in {img_dir}",
                       model_dir)
    is_query = C.query_mask(names, query_every)
    sizes = C.image_sizes(paths, tolerate=is_query, declared=model_sizes)
    K = np.stack([C.scale_to_size(k, ms, s, p) for k, ms, s, p in zip(Ks, model_sizes, sizes,
                                                                       paths, strict=True)])
    # Sorted by point id so that text and binary models give the same order.
    pts = np.asarray([rec.points3D[k].xyz for k in sorted(rec.points3D)],
                     np.float64).reshape(-1, 3)
    return C.make_scene(root, names, paths, K, np.stack(dists), sizes, np.stack(Rs),
                        np.stack(ts), posed, is_query, "colmap",
                        points3d=pts)


# ----------------------------------------------------------------------------- pycolmap glue


def colmap_camera(K: np.ndarray, dist: np.ndarray, size, camera_id: int) -> pycolmap.Camera:
    """The simplest pycolmap camera that represents OpenCV intrinsics exactly.

    Args:
      K: [3, 3] intrinsics (no skew); dist: [5] OpenCV (k1, k2, p1, p2, k3) or None.
      size: (width, height).
    Returns:
      PINHOLE (fx, fy, cx, cy) when all of dist is 0, OPENCV (+ k1 k2 p1 p2) when k3 = 0,
      else FULL_OPENCV (+ k1 k2 p1 p2 k3, with k4 = k5 = k6 = 0). All three are read back by
      :func:`vrs_jax.data.readers.colmap.camera_to_K_dist` to the same K and dist.
    """
    K = np.asarray(K, np.float64)
    d = np.zeros(5) if dist is None else np.asarray(dist, np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not np.all(d == 0):
        if d[4] == 0:
            model, params = "OPENCV", [fx, fy, cx, cy, d[0], d[1], d[2], d[3]]
        else:
            model, params = "FULL_OPENCV", [fx, fy, cx, cy, d[0], d[1], d[2], d[3], d[4],
                                            0, 0, 0]
    else:
        model, params = "PINHOLE", [fx, fy, cx, cy]
    return pycolmap.Camera(model=model, width=int(size[0]), height=int(size[1]),
                           params=params, camera_id=camera_id)


@contextlib.contextmanager
def quiet_pycolmap(verbose: bool = False, errors_only: bool = False):
    """Silence COLMAP's INFO log lines (glog) inside the block unless ``verbose``; with
    ``errors_only`` its warnings too (e.g. about point colours of images given from memory)."""
    old = pycolmap.logging.minloglevel
    if not verbose:
        level = pycolmap.logging.ERROR if errors_only else pycolmap.logging.WARNING
        pycolmap.logging.minloglevel = int(level)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = old
