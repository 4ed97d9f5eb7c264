"""Image and depth I/O with clear errors. Images are float32 RGB in [0, 1], arrays [H, W, 3]."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from vrs_jax.errors import VrsError


def read_image(path: str | Path, background: tuple[float, float, float] | None = None,
               size: tuple[int, int] | None = None) -> np.ndarray:
    """Read a colour image as float32 RGB [H, W, 3] in [0, 1].

    Args:
      path: image file (any format OpenCV reads).
      background: RGB in [0, 1]; an image with an alpha channel is composited on it
        (white if None).
      size: optional (width, height) to resize to (area interpolation when shrinking).
    Raises:
      VrsError naming the file if it is missing or cannot be decoded.
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
        shrink = size[0] < img.shape[1]
        img = cv2.resize(img, tuple(size), interpolation=cv2.INTER_AREA if shrink
                         else cv2.INTER_LINEAR)
    return np.ascontiguousarray(img, dtype=np.float32)


def read_gray(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image as float32 grey [H, W] in [0, 1] (luma of the RGB image)."""
    rgb = read_image(path, size=size)
    return rgb @ np.asarray([0.299, 0.587, 0.114], np.float32)


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
    """Write float RGB [H, W, 3] in [0, 1] (or uint8) as an 8-bit image, atomically."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    if rgb.dtype != np.uint8:
        rgb = np.clip(np.round(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint8)
    tmp = p.with_name(p.stem + ".tmp" + p.suffix)
    if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1])):
        raise VrsError("could not write image", p)
    tmp.replace(p)


def write_depth(path: str | Path, depth_m: np.ndarray, scale: float = 0.001) -> None:
    """Write depth in metres [H, W] as a 16-bit PNG in units of ``scale`` (0 = invalid)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    d = np.where(np.isfinite(depth_m) & (depth_m > 0), np.round(depth_m / scale), 0)
    d = np.clip(d, 0, 65534).astype(np.uint16)
    tmp = p.with_name(p.stem + ".tmp" + p.suffix)
    if not cv2.imwrite(str(tmp), d):
        raise VrsError("could not write depth image", p)
    tmp.replace(p)
