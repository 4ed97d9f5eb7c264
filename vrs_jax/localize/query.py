"""Query preparation on the host: decode, detect, describe, global descriptor -> Query pytree.

Everything here is host work (image decoding, OpenCV's detector) or a jitted call with padded
shapes; the result is a pytree of fixed shapes that :func:`vrs_jax.localize.localize` takes.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax import geometry
from vrs_jax.data import images
from vrs_jax.egm.retrieval import global_descriptor
from vrs_jax.features.descriptor import DescriptorConfig
from vrs_jax.features.extract import extract_features
from vrs_jax.features.keypoints import KeypointConfig
from vrs_jax.features.patches import PatchConfig
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.maps import Map

Array = Any


@flax.struct.dataclass
class Query:
    """One query image, ready for ``localize`` (fixed shapes; Kq = cfg.query_keypoints).

    keypoints: [Kq, 4] (x, y, scale, angle) as detected (COLMAP convention).
    points2d: [Kq, 2] keypoint positions with the query's lens distortion removed (what PnP
      sees with ``K`` alone).
    desc: [Kq, D] unit descriptors; mask: [Kq] bool valid rows (a prefix).
    global_desc: [G] unit global descriptor.  K: [3, 3] intrinsics.
    """

    keypoints: Array
    points2d: Array
    desc: Array
    mask: Array
    global_desc: Array
    K: Array


def undistort_points(uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None) -> np.ndarray:
    """Pixel coordinates [M, 2] with distortion removed (same K): what a pinhole would see."""
    if dist is None or not np.any(dist):
        return np.asarray(uv, np.float64)
    rays = geometry.unproject(np.asarray(K, np.float64), np.asarray(uv, np.float64),
                              np.asarray(dist, np.float64))
    uvu, _ = geometry.project(np.asarray(K, np.float64), np.eye(3), np.zeros(3), rays)
    return uvu


def query_features(m: Map, cfg: LocalizeConfig) -> tuple[KeypointConfig, PatchConfig,
                                                           DescriptorConfig]:
    """The detector, patch and descriptor settings of a map's queries: the map's, with the
    query's keypoint budget and the config's patch override (render mode)."""
    f = m.config.features
    kp = dataclasses.replace(f.keypoints, max_keypoints=cfg.query_keypoints)
    return kp, cfg.patches or f.patches, f.descriptor


def validate(image: Any, K: Any, dist: Any, name: str = "image"
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The one check of a query's inputs, for every entry point (``prepare_query``, and
    through it ``Localizer``, ``localize_batch``, ``localize_scene``).

    Args:
      image: [H, W] grey or [H, W, 3] RGB array (uint8, uint16, or float in [0, 1]).
      K: [3, 3] intrinsics of that image size; dist: OpenCV distortion ([4] or [5]) or None.
      name: the image in messages.
    Returns:
      (gray float32 [H, W] in [0, 1], K float64 [3, 3], dist float64 [5] or None).
    Raises:
      VrsError naming ``name`` and the argument: the image
      (:func:`~vrs_jax.data.images.as_gray`), K and dist
      (:func:`~vrs_jax.geometry.check_camera`), then the image size against K's principal
      point (:func:`~vrs_jax.data.images.check_intrinsics`), in that order.
    """
    gray = images.as_gray(image, name)
    K, dist = geometry.check_camera(K, dist, name)
    h, w = gray.shape
    images.check_intrinsics(w, h, K, name)
    return gray, K, dist


def prepare_query(m: Map, gray: np.ndarray, K: np.ndarray, dist: np.ndarray | None,
                  cfg: LocalizeConfig, name: str = "image") -> Query:
    """Keypoints, descriptors and global descriptor of a query image (host function).

    Args:
      m: the map (its feature settings and VLAD vocabulary).
      gray: [H, W] float32 grey image in [0, 1] (or any image :func:`validate` takes).
      K: [3, 3] intrinsics; dist: [5] OpenCV distortion or None.
      cfg: LocalizeConfig (the query keypoint budget: the padded size).
      name: the image in messages.
    Returns:
      Query with arrays padded to cfg.query_keypoints. An image with no keypoints gives an
      all-False mask (localize then returns a flagged fallback result).
    Raises:
      VrsError naming ``name`` for an image, K or dist that :func:`validate` refuses.
    """
    gray, K, dist = validate(gray, K, dist, name)
    kq = cfg.query_keypoints
    kp_cfg, patch_cfg, desc_cfg = query_features(m, cfg)
    kp, desc = extract_features(gray, kp_cfg, patch_cfg, desc_cfg)
    kp, desc = kp[:kq], desc[:kq]
    n = len(kp)
    d = desc_cfg.dim
    kp_pad = np.zeros((kq, 4), np.float32)
    kp_pad[:, 2] = 1.0
    kp_pad[:n] = kp
    desc_pad = np.zeros((kq, d), np.float32)
    desc_pad[:n] = desc
    mask = np.zeros(kq, bool)
    mask[:n] = True
    pts = np.zeros((kq, 2), np.float32)
    if n:
        pts[:n] = undistort_points(kp[:, :2], K, dist)
    g = global_descriptor(desc, None, m.egm.vocab)
    return Query(keypoints=jnp.asarray(kp_pad), points2d=jnp.asarray(pts),
                 desc=jnp.asarray(desc_pad), mask=jnp.asarray(mask),
                 global_desc=jnp.asarray(g, jnp.float32),
                 K=jnp.asarray(np.asarray(K, np.float32)))


def stack_queries(queries: list[Query]) -> Query:
    """Stack Queries of one config into a batch (leading axis) for ``jax.vmap(localize)``."""
    return jax.tree.map(lambda *xs: jnp.stack(xs), *queries)
