"""Helpers shared by the dataset readers: cheap image sizes, text parsing, scene assembly.

Everything that can go wrong with user files raises :class:`VrsError` naming the file (and the
line), never a bare traceback.
"""

from __future__ import annotations

import math
import struct
import warnings
from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np

from vrs_jax import geometry
from vrs_jax.data.scene import Scene, hold_out_every
from vrs_jax.errors import VrsError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")

# JPEG start-of-frame markers carry the image size; C4 (DHT), C8 (JPG) and CC (DAC) do not.
_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
# Markers without a length field.
_JPEG_STANDALONE = {0x01, *range(0xD0, 0xD9)}


def _png_size(f) -> tuple[int, int] | None:
    head = f.read(24)
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    w, h = struct.unpack(">II", head[16:24])
    return int(w), int(h)


def _jpeg_size(f) -> tuple[int, int] | None:
    if f.read(2) != b"\xff\xd8":
        return None
    while True:
        b = f.read(1)
        if not b:
            return None
        if b != b"\xff":
            return None  # every segment must start with 0xFF
        marker = f.read(1)
        while marker == b"\xff":  # fill bytes
            marker = f.read(1)
        if not marker:
            return None
        m = marker[0]
        if m in _JPEG_STANDALONE:
            continue
        if m == 0xD9 or m == 0xDA:  # end of image / start of scan before any frame header
            return None
        seg = f.read(2)
        if len(seg) < 2:
            return None
        length = struct.unpack(">H", seg)[0]
        if length < 2:
            return None
        if m in _JPEG_SOF:
            data = f.read(5)
            if len(data) < 5:
                return None
            h, w = struct.unpack(">HH", data[1:5])
            return int(w), int(h)
        f.seek(length - 2, 1)


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, read from the PNG/JPEG header without decoding.

    Other formats (and headers the parser does not follow) are decoded once with OpenCV. The
    size is that of the stored pixel array (EXIF orientation is not applied), which is what
    ``images.read_image`` returns, since it reads with ``IMREAD_UNCHANGED``.

    Raises:
      VrsError naming the file if it is missing or not a readable image.
    """
    p = Path(path)
    if not p.is_file():
        raise VrsError("image not found", p)
    try:
        with open(p, "rb") as f:
            magic = f.read(2)
            f.seek(0)
            size = None
            if magic == b"\x89P":
                size = _png_size(f)
            elif magic == b"\xff\xd8":
                size = _jpeg_size(f)
        if size is None:  # another format, or a header this parser does not follow: decode
            img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
            if img is not None and img.size > 0:
                size = (img.shape[1], img.shape[0])
    except OSError as e:
        raise VrsError(f"cannot read image: {e.strerror or e}", p) from None
    if size is None or size[0] <= 0 or size[1] <= 0:
        raise VrsError("unreadable image (not a PNG/JPEG OpenCV can decode, or corrupt header)",
                       p)
    return size


def image_sizes(paths: Sequence[str | Path], tolerate: Sequence[bool] | None = None,
                declared: Sequence[Sequence[int]] | None = None) -> np.ndarray:
    """[N, 2] int (width, height) of image files (header reads; see :func:`image_size`).

    Args:
      paths: N image files.
      tolerate: [N] bool, the images (queries) whose unreadable or missing file is not an
        error here (unless every image is missing: a wrong folder): it is flagged when the
        query is localized (reading it raises the VrsError that ``localize_scene`` records)
        while the other queries are localized. Such an image gets
        its ``declared`` size, else the size of the first readable image.
      declared: [N, 2] sizes the dataset gives for the images (e.g. a query list's).
    Raises:
      VrsError naming the first unreadable image that is not tolerated (or every image
      unreadable and no declared size).
    """
    sizes: list[tuple[int, int] | None] = []
    first_error: VrsError | None = None
    n_missing = 0
    for i, p in enumerate(paths):
        try:
            sizes.append(image_size(p))
        except VrsError as e:
            if tolerate is None or not tolerate[i]:
                raise
            sizes.append(None if declared is None else tuple(int(x) for x in declared[i]))
            first_error = first_error or e
            n_missing += not Path(p).is_file()
    known = [s for s in sizes if s is not None]
    if (len(known) < len(sizes) and not known) or (paths and n_missing == len(paths)):
        raise first_error  # nothing readable, or every file missing: a wrong folder
    sizes = [known[0] if s is None else s for s in sizes]
    return np.asarray(sizes, dtype=np.int64).reshape(-1, 2)


def find_image(stem: Path) -> Path | None:
    """``stem`` itself if it is a file, else ``stem`` + the first image suffix that exists."""
    if stem.is_file():
        return stem
    for suffix in IMAGE_SUFFIXES:
        for s in (suffix, suffix.upper()):
            cand = stem.with_name(stem.name + s)
            if cand.is_file():
                return cand
    return None


def list_images(folder: Path) -> list[Path]:
    """Image files (PNG/JPEG, any case) directly in ``folder``, sorted by name."""
    return sorted(p for p in folder.iterdir()
                  if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)


def read_text(path: str | Path, what: str = "file") -> str:
    """The text of a UTF-8 file, a leading byte-order mark dropped (Windows editors write one;
    it would otherwise stick to the first name); VrsError naming the file when it is missing
    or unreadable."""
    p = Path(path)
    if not p.is_file():
        raise VrsError(f"{what} not found" if not p.exists() else f"{what} is not a file", p)
    try:
        return p.read_text(encoding="utf-8-sig", errors="replace")
    except OSError as e:
        raise VrsError(f"cannot read {what}: {e.strerror or e}", p) from None


def text_lines(path: str | Path, what: str = "file") -> list[tuple[int, str]]:
    """(1-based line number, stripped text) of every non-empty line of :func:`read_text`;
    CRLF, tabs and a byte-order mark are fine."""
    text = read_text(path, what)
    return [(i + 1, s.strip()) for i, s in enumerate(text.splitlines()) if s.strip()]


def parse_floats(tokens: Iterable[str], path: Path, line: int, what: str) -> np.ndarray:
    """Tokens -> float64 array, or VrsError naming file, line and what was expected."""
    try:
        return np.asarray([float(x) for x in tokens], dtype=np.float64)
    except ValueError:
        raise VrsError(f"malformed {what}: expected numbers", path, line) from None


def rotation_from_matrix(M: np.ndarray, path: Path, line: int | None = None,
                         tol: float = 1e-2) -> np.ndarray:
    """Nearest rotation to a 3x3 matrix that should be one (SVD), or VrsError if it is not.

    Files store rotations in a few significant digits, so ``M`` is re-orthonormalised; a
    matrix further than ``tol`` (max abs entry of ``M^T M - I``) from orthonormal, or with
    determinant -1, is rejected.
    """
    if not np.all(np.isfinite(M)):
        raise VrsError("pose has non-finite entries", path, line)
    err = np.abs(M.T @ M - np.eye(3)).max()
    if err > tol or np.linalg.det(M) < 0:
        raise VrsError(f"not a rotation (|R^T R - I| = {err:.3g}, det = {np.linalg.det(M):.3g})",
                       path, line)
    U, _, Vt = np.linalg.svd(M)
    return U @ Vt


def pinhole(fx, fy, cx, cy) -> np.ndarray:
    """[3, 3] float64 intrinsics."""
    return np.asarray(geometry.intrinsics_matrix(np.float64(fx), np.float64(fy),
                                                 np.float64(cx), np.float64(cy)))


def scale_to_size(K: np.ndarray, from_size: Sequence[float], to_size: Sequence[float],
                  path: str | Path | None = None) -> np.ndarray:
    """Intrinsics [..., 3, 3] given for images of ``from_size`` (w, h) -> ``to_size`` (w, h).

    With ``path`` (the image of size ``to_size``): VrsError naming it when the two sizes have
    another aspect ratio (an image that contradicts its intrinsics is not silently stretched;
    a uniformly downscaled image is fine).
    """
    if path is not None:
        from vrs_jax.data.images import check_size

        check_size(tuple(int(x) for x in to_size), tuple(float(x) for x in from_size), path)
    sx = float(to_size[0]) / float(from_size[0])
    sy = float(to_size[1]) / float(from_size[1])
    if sx == 1.0 and sy == 1.0:
        return np.asarray(K, np.float64)
    return np.asarray(geometry.scale_intrinsics(np.asarray(K, np.float64), sx, sy))


def query_mask(names: Sequence[str], every: int) -> np.ndarray:
    """[N] bool holding out every ``every``-th image in name order (none if every <= 0)."""
    order = np.argsort(np.asarray(names, dtype=object), kind="stable")
    mask = np.zeros(len(names), dtype=bool)
    mask[order] = hold_out_every(len(names), int(every))
    return mask


def warn_list(what: str, items: Sequence[str], limit: int = 5) -> None:
    """One ``warnings.warn`` naming the first few items."""
    if not items:
        return
    shown = ", ".join(str(x) for x in items[:limit])
    more = f" and {len(items) - limit} more" if len(items) > limit else ""
    warnings.warn(f"{what} ({len(items)}): {shown}{more}", stacklevel=3)


def make_scene(root: Path, names: list[str], image_paths: list[Path], K, dist, sizes, R, t,
               has_pose, is_query, fmt: str, **extra) -> Scene:
    """Assemble a :class:`Scene` with the arrays converted to their documented dtypes."""
    n = len(names)
    if n == 0:
        raise VrsError("no images found", root)
    dist = np.zeros((n, 5)) if dist is None else np.asarray(dist, np.float64).reshape(n, 5)
    return Scene(
        root=Path(root), names=list(names), image_paths=[Path(p) for p in image_paths],
        K=np.asarray(K, np.float64).reshape(n, 3, 3), dist=dist,
        sizes=np.asarray(sizes, np.int64).reshape(n, 2),
        R=np.asarray(R, np.float64).reshape(n, 3, 3), t=np.asarray(t, np.float64).reshape(n, 3),
        has_pose=np.asarray(has_pose, bool).reshape(n),
        is_query=np.asarray(is_query, bool).reshape(n), format=fmt, **extra,
    )


def identity_poses(n: int) -> tuple[np.ndarray, np.ndarray]:
    """[n, 3, 3] identities and [n, 3] zeros (the placeholder pose where none is known)."""
    return np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3))


def finite_positive(x: float) -> bool:
    return math.isfinite(x) and x > 0
