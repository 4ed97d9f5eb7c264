"""SIFT keypoints (OpenCV) with position, scale and orientation in the project's conventions.

A keypoint is a row ``(x, y, scale, angle)`` of a float32 array [K, 4]:

- ``x, y``: position in COLMAP pixel coordinates (the centre of the top-left pixel is
  (0.5, 0.5)), i.e. OpenCV's ``kp.pt`` + 0.5.
- ``scale``: OpenCV's ``kp.size / 2`` in pixels. OpenCV's SIFT sets ``size`` to twice the
  Gaussian scale sigma of the detection (``size = 2 * 1.6 * 2^(octave + layer / layers)``), so
  ``scale`` is that sigma: the blur at which the blob was found, radius-like. The SIFT
  descriptor support is 4 cells of 3 * scale, i.e. 12 * scale wide (see patches.py).
- ``angle``: the keypoint orientation in radians, wrapped to [-pi, pi): the direction
  ``(cos(angle), sin(angle))`` in pixel axes (x right, y DOWN) is the dominant gradient
  direction (from dark to bright). Because y points down, a positive angle turns from +x
  towards +y, i.e. CLOCKWISE as the image is displayed. This is exactly OpenCV's ``kp.angle``
  converted from degrees (OpenCV measures the same direction in the same axes; verified in
  tests/test_features_keypoints.py against the image gradients and a rotated image).
  Under an image similarity ``p' = s R(phi) p + t`` with ``R(phi) = [[cos, -sin], [sin, cos]]``
  in pixel axes, a keypoint maps to ``(p', s * scale, angle + phi)``; note that
  ``cv2.getRotationMatrix2D(c, deg, s)`` rotates by ``phi = -radians(deg)`` in these axes.

Detection is host-side work (OpenCV); everything downstream is JAX.
"""

from __future__ import annotations

import dataclasses
import math

import cv2
import numpy as np

from vrs_jax.errors import VrsError


@dataclasses.dataclass(frozen=True)
class KeypointConfig:
    """SIFT detection and selection settings (single source of truth for the detector)."""

    # Keep at most this many keypoints per image, the strongest by DoG response. 2048 is
    # hloc's SIFT default order of magnitude and ample for 640x480 7Scenes frames.
    max_keypoints: int = 2048
    # (columns, rows) of a grid over the image: the budget is dealt round-robin over the cells
    # (each cell's best, then each cell's second best, ...), so keypoints spread over the
    # image instead of piling up on the most textured region; cells with fewer detections
    # than their share give their remainder to the others. None: plain global top-k.
    grid: tuple[int, int] | None = (4, 4)
    # OpenCV SIFT parameters, OpenCV's (= Lowe's) defaults: contrast threshold on the DoG
    # (image scaled to [0, 1]), edge-response threshold, 3 scales per octave, base sigma 1.6.
    contrast_threshold: float = 0.04
    edge_threshold: float = 10.0
    n_octave_layers: int = 3
    sigma: float = 1.6
    # OpenCV's SIFT doubles the image for its first octave; by default that up-sampling maps
    # pixel x to 2x + 0.5, which shifts every keypoint by +0.25 px in x and y (measured: the
    # keypoints of np.rot90(image) then disagree by 0.5 px). precise_upscale maps x to 2x
    # exactly (OpenCV >= 4.8), so kp.pt + 0.5 is the unbiased COLMAP position.
    precise_upscale: bool = True
    # Keypoints whose scale (pixels, = size / 2) lies outside [min_scale, max_scale] are
    # dropped before the cap. Defaults keep everything; min_scale ~ 1 drops the tiniest
    # keypoints of the up-sampled first octave, whose patches carry almost no information.
    min_scale: float = 0.0
    max_scale: float = math.inf

    def __post_init__(self):
        if self.max_keypoints < 0:
            raise VrsError(f"KeypointConfig.max_keypoints must be >= 0, got {self.max_keypoints}")
        if self.grid is not None and (len(self.grid) != 2 or min(self.grid) < 1):
            raise VrsError(f"KeypointConfig.grid must be (columns, rows) >= 1, got {self.grid}")


def _to_uint8(gray: np.ndarray) -> np.ndarray:
    """Grey image [H, W] (uint8, or float in [0, 1]) -> uint8 [H, W] for OpenCV's SIFT."""
    g = np.asarray(gray)
    if g.ndim != 2:
        raise VrsError(f"keypoint detection needs a grey image [H, W], got shape {g.shape}")
    if g.size == 0:
        raise VrsError(f"keypoint detection got an empty image of shape {g.shape}")
    if g.dtype == np.uint8:
        return np.ascontiguousarray(g)
    if not np.issubdtype(g.dtype, np.floating):
        raise VrsError(f"grey image must be uint8 or float in [0, 1], got dtype {g.dtype}")
    if not np.all(np.isfinite(g)):
        raise VrsError("grey image contains NaN or infinite values")
    return np.clip(np.rint(g * 255.0), 0, 255).astype(np.uint8)


def _grid_select(xy: np.ndarray, response: np.ndarray, width: int, height: int,
                 grid: tuple[int, int] | None, k: int) -> np.ndarray:
    """Indices of the selected keypoints, by decreasing response.

    Round-robin over grid cells: a keypoint's priority is its rank by response inside its
    cell; the first k by (rank, -response) are kept. Hence every cell gets its best keypoint
    before any gets a second, and a cell with fewer detections than its share keeps all.
    """
    order = np.argsort(-response, kind="stable")
    if grid is None or len(order) <= k:
        sel = order[:k]
    else:
        sel = order[np.sort(grid_round_robin(xy[order], width, height, grid)[:k])]
    return sel


def grid_round_robin(xy: np.ndarray, width: float, height: float, grid: tuple[int, int]
                     ) -> np.ndarray:
    """Round-robin order over grid cells of points given best first.

    Args:
      xy: [n, 2] pixel positions, best first.  width, height: image size.
      grid: (columns, rows) of the grid over the image.
    Returns:
      [n] int64 permutation sorting the points by (rank of the point within its cell, input
      position): every cell gives its best point before any gives its second.
    """
    gx, gy = grid
    cx = np.clip(np.floor(xy[:, 0] / width * gx), 0, gx - 1).astype(np.int64)
    cy = np.clip(np.floor(xy[:, 1] / height * gy), 0, gy - 1).astype(np.int64)
    cell = cy * gx + cx
    srt = np.argsort(cell, kind="stable")  # by cell, input order inside a cell
    rank = np.empty(len(cell), np.int64)
    rank[srt] = np.arange(len(cell)) - np.searchsorted(cell[srt], cell[srt])
    return np.lexsort((np.arange(len(cell)), rank))


def detect(gray: np.ndarray, cfg: KeypointConfig = KeypointConfig(),
           return_response: bool = False):
    """SIFT keypoints of a grey image.

    Args:
      gray: [H, W] grey image, float in [0, 1] (as images.read_gray gives) or uint8.
      cfg: detector settings.
      return_response: also return the DoG responses.
    Returns:
      keypoints [K, 4] float32 (x, y, scale, angle) as defined in the module docstring,
      ordered by decreasing response, K <= cfg.max_keypoints; K may be 0 (a blank image):
      the result is then a [0, 4] array and the caller decides whether to warn.
      With return_response: (keypoints, response [K] float32).
    Raises:
      VrsError if ``gray`` is not a finite 2-D image.
    """
    img = _to_uint8(gray)
    sift = cv2.SIFT_create(nfeatures=0, nOctaveLayers=cfg.n_octave_layers,
                           contrastThreshold=cfg.contrast_threshold,
                           edgeThreshold=cfg.edge_threshold, sigma=cfg.sigma,
                           enable_precise_upscale=cfg.precise_upscale)
    kps = sift.detect(img, None)
    if kps:
        kp = np.array([(k.pt[0] + 0.5, k.pt[1] + 0.5, k.size / 2.0, k.angle) for k in kps],
                      np.float64)
        resp = np.array([k.response for k in kps], np.float64)
    else:
        kp = np.zeros((0, 4), np.float64)
        resp = np.zeros((0,), np.float64)
    keep = (kp[:, 2] >= cfg.min_scale) & (kp[:, 2] <= cfg.max_scale)
    kp, resp = kp[keep], resp[keep]
    # degrees -> radians in [-pi, pi); OpenCV reports [0, 360)
    kp[:, 3] = np.mod(np.deg2rad(kp[:, 3]) + np.pi, 2 * np.pi) - np.pi
    sel = _grid_select(kp[:, :2], resp, img.shape[1], img.shape[0], cfg.grid,
                       cfg.max_keypoints)
    kp = kp[sel].astype(np.float32)
    resp = resp[sel].astype(np.float32)
    return (kp, resp) if return_response else kp


def to_cv_keypoints(kp: np.ndarray) -> list:
    """[K, 4] keypoints (project convention) -> list of cv2.KeyPoint (OpenCV convention)."""
    kp = np.asarray(kp, np.float64).reshape(-1, 4)
    return [cv2.KeyPoint(float(x - 0.5), float(y - 0.5), float(2 * s),
                         float(np.rad2deg(a) % 360.0)) for x, y, s, a in kp]
