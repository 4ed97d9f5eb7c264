"""Image and depth I/O with clear errors. Images are float32 RGB in [0, 1], arrays [H, W, 3]."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vrs_jax import fileio
from vrs_jax.errors import VrsError


def same_aspect(from_size: tuple[float, float], to_size: tuple[float, float],
                slack: float = 0.0) -> bool:
    """Whether ``to_size`` (w, h) is ``from_size`` scaled by one factor, up to the rounding of
    one axis to whole pixels (what a downscale by N, or images stored at 1/N, gives), plus
    ``slack`` times that axis (a principal point is only near the image centre)."""
    (w0, h0), (w1, h1) = (float(x) for x in from_size), (float(x) for x in to_size)
    if min(w0, h0, w1, h1) <= 0:
        return False
    return (abs(w1 - w0 * h1 / h0) <= 1.0 + slack * w1 + 1e-9
            or abs(h1 - h0 * w1 / w0) <= 1.0 + slack * h1 + 1e-9)


def check_size(actual: tuple[int, int], declared: tuple[float, float], path: str | Path,
               what: str = "its intrinsics") -> None:
    """VrsError naming ``path`` when an image of ``actual`` (w, h) pixels cannot be the image
    ``declared`` (w, h) describes at some scale (another aspect ratio)."""
    if not same_aspect(declared, actual):
        raise VrsError(f"image is {int(actual[0])}x{int(actual[1])} pixels but {what} are for "
                       f"{declared[0]:g}x{declared[1]:g} (another aspect ratio): wrong or "
                       "damaged image file?", path)


# The principal point must lie within this fraction of the image size from the image centre
# (|cx - w/2| <= f * w and |cy - h/2| <= f * h), and the size it implies, (2 cx, 2 cy), must
# have the image's aspect ratio within this slack (same_aspect). Real cameras keep it within a
# few percent of the centre; a K meant for another image size (the full-resolution K with a
# half-size image, a transposed image) puts it at the border, outside, or off the diagonal,
# and a K for an image half as large as the one given (a half-size K with the full image)
# puts it a quarter of the size from the centre: 0.15 refuses that (at 0.25 it passed by
# equality) and every scale above 1.4x, and still admits any real camera's offset.
PRINCIPAL_POINT_TOLERANCE = 0.15


def check_intrinsics(width: int, height: int, K: np.ndarray, name: str = "image") -> None:
    """VrsError naming ``name`` when an image of ``width`` x ``height`` pixels contradicts the
    principal point of ``K`` [3, 3] (checked first by
    :func:`vrs_jax.geometry.check_camera`): outside the image, farther than
    :data:`PRINCIPAL_POINT_TOLERANCE` of the size from its centre, or centring an image of
    another aspect ratio (:func:`same_aspect`)."""
    cx, cy = float(K[0, 2]), float(K[1, 2])
    tol = PRINCIPAL_POINT_TOLERANCE
    if (abs(cx - width / 2) > tol * width or abs(cy - height / 2) > tol * height
            or not same_aspect((2 * cx, 2 * cy), (width, height), slack=tol)):
        raise VrsError(f"{name}: image is {width}x{height} but K's principal point is "
                       f"({cx:g}, {cy:g}), the centre of a {2 * cx:g}x{2 * cy:g} image: K "
                       "belongs to another image size (or the image is transposed)")


# Pixel values of a float image above this are taken for a 0-255 image passed as floats.
_BYTE_RANGE = 255.0 + 1e-6


def _value_range(a: np.ndarray, name: str) -> tuple[float, float]:
    """(min, max) of an image array; VrsError for non-finite values."""
    if not np.all(np.isfinite(a)):
        raise VrsError(f"{name}: image has non-finite values (NaN or inf)")
    return float(a.min()), float(a.max())


def as_gray(image: np.ndarray, name: str = "image") -> np.ndarray:
    """An image array -> float32 grey [H, W] in [0, 1] (luma as :func:`read_gray`).

    Args:
      image: [H, W] grey or [H, W, 3] RGB: uint8 in 0..255, uint16 in 0..65535, or float in
        [0, 1] (a nested list of one of these).
      name: the image in messages.
    Raises:
      VrsError naming ``name`` for another shape or dtype (complex, bool, int64...), an empty
      image, non-finite values, or floats outside [0, 1] (values up to 255: a 0-255 image
      passed as floats: pass uint8 or divide by 255).
    """
    try:
        a = np.asarray(image)
    except ValueError:
        raise VrsError(f"{name}: image must be an [H, W] or [H, W, 3] array, got a ragged "
                       "nested list") from None
    if a.dtype == object or not (a.ndim == 2 or (a.ndim == 3 and a.shape[2] == 3)):
        shape = "a ragged nested list" if a.dtype == object else f"shape {a.shape}"
        raise VrsError(f"{name}: expected an [H, W] grey or [H, W, 3] RGB array, got {shape}")
    if a.shape[0] == 0 or a.shape[1] == 0:
        raise VrsError(f"{name}: image is empty ({a.shape[1]}x{a.shape[0]} pixels)")
    if a.dtype in (np.uint8, np.uint16):
        a = a.astype(np.float32) / (255.0 if a.dtype == np.uint8 else 65535.0)
    elif np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer):
        lo, hi = _value_range(a, name)
        floats = np.issubdtype(a.dtype, np.floating)
        if not floats or lo < 0 or hi > 1:  # int64 says nothing of the range: refused too
            if lo >= 0 and hi <= _BYTE_RANGE and (hi > 1 or not floats):
                raise VrsError(f"{name}: {a.dtype} image with values up to {hi:g}: the values "
                               "look like 0-255; pass uint8, or floats divided by 255")
            raise VrsError(f"{name}: {a.dtype} image values must be in [0, 1] (or pass "
                           f"uint8 0-255), got [{lo:g}, {hi:g}]")
        a = a.astype(np.float32)
    else:
        raise VrsError(f"{name}: image dtype {a.dtype} is not supported: pass uint8 (0-255) "
                       "or float in [0, 1]")
    return luma(a) if a.ndim == 3 else a


# ITU-R BT.601 luma weights (R, G, B): the one grey conversion of the project, for real
# images read here and for rendered patches (vrs_jax.features.descriptor.rgb_to_gray), so
# that both sides of a match see the same grey.
LUMA = (0.299, 0.587, 0.114)


def luma(rgb: np.ndarray) -> np.ndarray:
    """[..., 3] float32 RGB -> [...] float32 grey (BT.601 :data:`LUMA`)."""
    return rgb @ np.asarray(LUMA, np.float32)


def read_image(path: str | Path, background: tuple[float, float, float] | None = None,
               size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a colour image as float32 RGB [H, W, 3] in [0, 1].

    Args:
      path: image file (any format OpenCV reads).
      background: RGB in [0, 1]; an image with an alpha channel is composited on it
        (white if None).
      size: optional (width, height) to resize to (area interpolation when shrinking): the
        size the dataset declares for this image, possibly downscaled; a file whose aspect
        ratio differs is an error, not silently stretched.
    Raises:
      VrsError naming the file if it is missing, cannot be decoded or contradicts ``size``.
    """
    p = Path(path)
    if not p.is_file():
        raise VrsError("image not found", p)
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None or img.size == 0:
        raise VrsError("unreadable image (not a format OpenCV can decode, or corrupt)", p)
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    img = img.astype(np.float32) / scale
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    elif img.shape[2] == 4:
        bg = np.asarray(background if background is not None else (1.0, 1.0, 1.0), np.float32)
        alpha = img[..., 3:4]
        img = img[..., :3][..., ::-1] * alpha + bg * (1 - alpha)
    else:
        img = img[..., :3][..., ::-1]
    if size is not None and (img.shape[1], img.shape[0]) != tuple(size):
        check_size((img.shape[1], img.shape[0]), size, p, "the dataset's camera and size")
        shrink = size[0] < img.shape[1]
        img = cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA if shrink
                         else cv2.INTER_LINEAR)
    return np.ascontiguousarray(img, dtype=np.float32)


def read_gray(path: str | Path, size: tuple[int, int] | None = None,
              background: tuple[float, float, float] | None = None) -> np.ndarray:
    """Read an image as float32 grey [H, W] in [0, 1]: the :func:`luma` of
    :func:`read_image` (same ``size`` and ``background``)."""
    return luma(read_image(path, background=background, size=size))


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, decoding it (raises VrsError if unreadable)."""
    img = read_image(path)
    return img.shape[1], img.shape[0]


def read_depth(path: str | Path, scale: float = 0.001, invalid: int = 65535) -> np.ndarray:
    """Read a 16-bit depth PNG as float32 metres [H, W]; 0 where invalid or missing.

    Args:
      path: 16-bit single-channel PNG.
      scale: metres per stored unit (0.001: millimetres).
      invalid: stored value marking no measurement (7Scenes uses 65535).
    """
    p = Path(path)
    if not p.is_file():
        raise VrsError("depth image not found", p)
    d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if d is None:
        raise VrsError("unreadable depth image", p)
    if d.ndim != 2 or d.dtype != np.uint16:
        raise VrsError(f"depth image must be 16-bit single channel, got {d.dtype} {d.shape}", p)
    out = d.astype(np.float32) * scale
    out[(d == invalid) | (d == 0)] = 0.0
    return out


def write_image(path: str | Path, rgb: np.ndarray) -> None:
    """Write float RGB [H, W, 3] in [0, 1] (or uint8) as an 8-bit image, atomically
    (:func:`vrs_jax.fileio.write_atomic`: mode 0644, VrsError naming the file on failure)."""
    if rgb.dtype != np.uint8:
        rgb = np.clip(np.round(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint8)
    fileio.write_image(path, np.ascontiguousarray(rgb[..., ::-1]))


def write_depth(path: str | Path, depth_m: np.ndarray, scale: float = 0.001) -> None:
    """Write depth in metres [H, W] as a 16-bit PNG in units of ``scale`` (0 = invalid)."""
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), np.round(depth_m / scale), 0)
    d = np.clip(d, 0, 65534).astype(np.uint16)
    fileio.write_image(path, d)
