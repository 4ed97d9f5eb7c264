"""Keypoint-patch training rays: teach the NeRF exactly what localization will ask of it.

VRS-NeRF's map renders only small patches around the reference images' 3D-linked keypoints,
always from the reference cameras themselves. A NeRF trained on whole images spends most of
its (on a CPU, scarce) capacity and steps on pixels no patch ever covers. This module builds
a second pool of training rays: the canonical patch samples of every map keypoint, cast as
the same cones the localizer casts (:func:`vrs_jax.features.rays.patch_rays`: radius from
the sample spacing), with targets read from the real image through the same anti-aliased
blur stack as the real ("GT") patches (:func:`vrs_jax.features.patches.extract_patches`).
Training mixes this pool with ordinary pixel rays (``NerfConfig.patch_ray_fraction``), so the
rendered patches converge towards the real patches the baseline describes, at every sample
footprint the localizer uses, while full views stay renderable. This departs from the paper
(which trains on whole images; docs/design.md, section 5). Measured effect (README): none on
the synthetic room at the cpu-small budget (both 100% at 5 cm / 5 deg).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax.data.images import read_image
from vrs_jax.data.scene import Scene
from vrs_jax.features.patches import PatchConfig, extract_patches
from vrs_jax.features.rays import patch_rays

Array = Any


@functools.partial(jax.jit, static_argnames="cfg")
def _image_patches(rgb: Array, kp: Array, K: Array, R: Array, t: Array, dist: Array | None,
                   cfg: PatchConfig) -> tuple[Array, Any]:
    """One reference image's real RGB patch samples [K_max, P, P, 3] (the targets) and the
    patch rays (PatchRays of [K_max, P, P, ...]) of its keypoints [K_max, 4] (every row a
    valid keypoint); image [H, W, 3], camera K [3, 3], R [3, 3], t [3], dist [5] or None.
    Fixed shapes: one compilation per image size, not one per keypoint count."""
    targets = jnp.stack([extract_patches(rgb[..., c], kp, cfg) for c in range(3)], axis=-1)
    return targets, patch_rays(kp, K, R, t, cfg, dist)


def patch_pool(refs: Scene, keypoints: np.ndarray, kp_mask: np.ndarray, cfg: PatchConfig,
               near: np.ndarray, far: np.ndarray, max_rays: int, seed: int = 0,
               background: np.ndarray | None = None, depths: np.ndarray | None = None
               ) -> dict[str, np.ndarray]:
    """Training rays of the patches of the map keypoints of each reference image.

    Args:
      refs: the N reference images (same order as ``keypoints``).
      keypoints: [N, K_max, 4] map keypoints; kp_mask: [N, K_max] valid ones.
      cfg: the map's patch config (the localizer renders exactly these samples).
      near, far: [N] per-image sampling bounds (t = z-depth).
      max_rays: cap on the pool size (patch samples are subsampled uniformly, fixed seed).
      background: RGB that RGBA images are composited on (as for pixel rays).
      depths: optional [N, K_max] z-depth of each keypoint's 3D point (<= 0: none), given
        to every sample of its patch (the depth loss's window, NerfConfig.depth_loss_mult).
    Returns:
      dict(origins [M, 3], directions [M, 3], radii [M], near [M], far [M], rgb [M, 3],
      depth [M] (0 without ``depths``), image [M] int32) float32 arrays, M <= max_rays.
    """
    rng = np.random.default_rng(seed)
    n_total = int(np.asarray(kp_mask).sum()) * cfg.size ** 2
    keep_frac = min(1.0, max_rays / max(n_total, 1))
    out: dict[str, list[np.ndarray]] = {k: [] for k in ("origins", "directions", "radii",
                                                          "near", "far", "rgb", "depth",
                                                          "image")}
    bg = None if background is None else tuple(float(v) for v in background)
    for i in range(len(refs)):
        kp = np.asarray(keypoints[i])[np.asarray(kp_mask[i])]
        z = (np.zeros(len(kp)) if depths is None
             else np.maximum(np.asarray(depths[i], np.float64)[np.asarray(kp_mask[i])], 0.0))
        if len(kp) == 0:
            continue
        w, h = (int(s) for s in refs.sizes[i])
        rgb = read_image(refs.image_paths[i], background=bg, size=(w, h))
        valid = np.asarray(kp_mask[i], bool)
        # padded rows repeat a valid keypoint: every row is computed, the valid ones kept
        kp_all = np.where(valid[:, None], np.asarray(keypoints[i], np.float32), kp[0])
        f32 = (jnp.asarray(np.asarray(a, np.float32)) for a in (refs.K[i], refs.R[i], refs.t[i]))
        targets, pr = _image_patches(jnp.asarray(rgb, jnp.float32), jnp.asarray(kp_all), *f32,
                                     jnp.asarray(np.asarray(refs.dist[i], np.float32))
                                     if np.any(refs.dist[i]) else None, cfg)
        targets = np.asarray(targets)[valid].reshape(-1, 3)
        o = np.asarray(pr.origins)[valid].reshape(-1, 3)
        d = np.asarray(pr.directions)[valid].reshape(-1, 3)
        r = np.asarray(pr.radii)[valid].reshape(-1)
        pos = np.asarray(pr.positions)[valid].reshape(-1, 2)
        inside = (pos[:, 0] >= 0) & (pos[:, 0] <= w) & (pos[:, 1] >= 0) & (pos[:, 1] <= h)
        sel = np.flatnonzero(inside & (rng.random(len(o)) < keep_frac))
        out["origins"].append(o[sel])
        out["directions"].append(d[sel])
        out["radii"].append(r[sel])
        out["near"].append(np.full(len(sel), near[i]))
        out["far"].append(np.full(len(sel), far[i]))
        out["rgb"].append(np.clip(targets[sel], 0.0, 1.0))
        out["depth"].append(np.repeat(z, cfg.size ** 2)[sel])
        out["image"].append(np.full(len(sel), i))
    if not out["image"]:
        return {}
    res = {k: np.concatenate(v).astype(np.float32) for k, v in out.items() if k != "image"}
    res["image"] = np.concatenate(out["image"]).astype(np.int32)
    return res
