"""COLMAP sparse models, text or binary, read with pycolmap.

COLMAP's conventions are the project's own (world-to-camera poses, OpenCV camera axes, pixel
centres at +0.5), so poses and intrinsics pass through unchanged; only the camera models are
mapped to a pinhole K plus OpenCV distortion ``(k1, k2, p1, p2, k3)``.
"""

from __future__ import annotations

import contextlib
import struct
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
    for part in ("cameras", "images", "points3D"):
        if not any((model / f"{part}.{e}").is_file() for e in ("bin", "txt")):
            raise VrsError(f"incomplete COLMAP model: {part}.bin / {part}.txt missing", model)


def read_reconstruction(model: str | Path) -> pycolmap.Reconstruction:
    """pycolmap.Reconstruction of a text or binary model folder, with clear VrsErrors."""
    model = require_dir(model, "COLMAP model folder")
    _check_model_files(model)
    try:
        return pycolmap.Reconstruction(str(model))
    except Exception as e:  # pycolmap raises ValueError/RuntimeError with C++ context
        raise VrsError(f"cannot read COLMAP model: {str(e).splitlines()[0][:200]}",
                       model) from None


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
    txt, binf = model / "points3D.txt", model / "points3D.bin"
    if txt.is_file():
        pts = []
        for lineno, text in C.text_lines(txt, "points3D.txt"):
            if text.startswith("#"):
                continue
            v = C.parse_floats(text.split()[1:4], txt, lineno, "points3D line")
            if v.size != 3:
                raise VrsError("malformed points3D line", txt, lineno)
            pts.append(v)
        return np.asarray(pts, np.float64).reshape(-1, 3)
    if not binf.is_file():
        return None
    data = binf.read_bytes()
    try:
        (n,) = struct.unpack_from("<Q", data, 0)
        off, pts = 8, np.empty((n, 3))
        # Per point: id u64, xyz 3 f64, rgb 3 u8, error f64, track length u64, then
        # track length x (image id i32, point2D index i32).
        for k in range(n):
            pts[k] = struct.unpack_from("<3d", data, off + 8)
            (track,) = struct.unpack_from("<Q", data, off + 43)
            off += 51 + 8 * track
    except struct.error:
        raise VrsError("truncated or malformed points3D.bin", binf) from None
    if off != len(data):
        raise VrsError(f"malformed points3D.bin ({len(data) - off} trailing bytes)", binf)
    return pts


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
