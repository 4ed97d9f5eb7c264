"""Full-view rendering (chunked, jitted), image metrics (PSNR, SSIM) and PNG export."""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax import geometry
from vrs_jax.data.images import write_image
from vrs_jax.data.scene import Scene
from vrs_jax.nerf.config import NerfConfig
from vrs_jax.nerf.ilm import ILM
from vrs_jax.nerf.model import Field, render_rays, select_field

Array = jax.Array


@functools.lru_cache(maxsize=16)
def image_renderer(cfg: NerfConfig, width: int, height: int, use_dist: bool
                   ) -> Callable[..., dict[str, Array]]:
    """Jitted renderer of one full view, compiled once per (config, image size).

    Returns ``fn(fields, c, K [3,3], R [3,3], t [3], dist [5], near [], far [])`` ->
    dict(rgb [H, W, 3], depth [H, W], acc [H, W]) using cluster ``c`` of the stacked
    ``fields`` (c is traced: one compilation serves every cluster).
    """
    uv = jnp.asarray(geometry.pixel_grid(width, height).reshape(-1, 2), jnp.float32)
    n = width * height
    chunk = min(cfg.render_chunk, n)
    pad = (-n) % chunk

    def fn(fields: Field, c, K, R, t, dist, near, far):
        field = select_field(fields, c)
        o, d = geometry.pixel_rays(K, R, t, uv, dist if use_dist else None)
        r = jnp.full((n,), geometry.cone_radius(K), jnp.float32)
        rays = {"o": o, "d": d, "r": r}
        rays = {k: jnp.concatenate([v, jnp.repeat(v[:1], pad, axis=0)]) for k, v in rays.items()}
        rays = jax.tree.map(lambda x: x.reshape((-1, chunk) + x.shape[1:]), rays)

        def one(b):
            m = b["r"].shape[0]
            return render_rays(field, b["o"], b["d"], b["r"], jnp.full((m,), near),
                               jnp.full((m,), far), None, cfg)

        out = jax.lax.map(one, rays)
        out = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:])[:n], out)
        return {"rgb": out["rgb"].reshape(height, width, 3),
                "depth": out["depth"].reshape(height, width),
                "acc": out["acc"].reshape(height, width)}

    return jax.jit(fn)


def render_view(ilm: ILM, cluster: int, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                size: tuple[int, int], near: float, far: float,
                dist: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Render a whole image (world-to-camera pose R, t; intrinsics K; size (w, h)) with the
    map's cluster ``cluster``. Returns numpy rgb [H, W, 3], depth [H, W], acc [H, W]."""
    use_dist = dist is not None and bool(np.any(dist))
    fn = image_renderer(ilm.config, int(size[0]), int(size[1]), use_dist)
    f32 = lambda a: jnp.asarray(np.asarray(a, np.float32))  # noqa: E731
    out = fn(ilm.fields, jnp.int32(cluster), f32(K), f32(R), f32(t),
             f32(dist if use_dist else np.zeros(5)), jnp.float32(near), jnp.float32(far))
    return {k: np.asarray(v) for k, v in out.items()}


# ----------------------------------------------------------------------------- metrics


def psnr(pred: Array, target: Array) -> Array:
    """Peak signal-to-noise ratio in dB of images in [0, 1]: [..., H, W, 3] -> [...]."""
    mse = jnp.mean((jnp.asarray(pred) - jnp.asarray(target)) ** 2, axis=(-3, -2, -1))
    return -10.0 * jnp.log10(mse)


def _gaussian_kernel(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    x = np.arange(size) - (size - 1) / 2
    g = np.exp(-0.5 * (x / sigma) ** 2)
    return (g / g.sum()).astype(np.float32)


@jax.jit
def ssim(pred: Array, target: Array) -> Array:
    """Structural similarity (Wang et al. 2004) of RGB images in [0, 1], as the NeRF papers
    report it: 11 x 11 Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, 'valid' filtering,
    per-channel maps averaged. pred, target: [H, W, 3] (H, W >= 11) -> []."""
    g = jnp.asarray(_gaussian_kernel())

    def filt(z):  # separable 'valid' Gaussian filter of [H, W, 3]
        z = jnp.moveaxis(z, -1, 0)  # [3, H, W]
        z = jax.vmap(jax.vmap(lambda r: jnp.convolve(r, g, mode="valid")))(z)
        z = jax.vmap(jax.vmap(lambda c: jnp.convolve(c, g, mode="valid"), in_axes=1,
                              out_axes=1))(z)
        return z

    x, y = jnp.asarray(pred, jnp.float32), jnp.asarray(target, jnp.float32)
    c1, c2 = 0.01**2, 0.03**2
    mx, my = filt(x), filt(y)
    sxx = filt(x * x) - mx**2
    syy = filt(y * y) - my**2
    sxy = filt(x * y) - mx * my
    num = (2 * mx * my + c1) * (2 * sxy + c2)
    den = (mx**2 + my**2 + c1) * (sxx + syy + c2)
    return jnp.mean(num / den)


def side_by_side(pred: np.ndarray, real: np.ndarray, gap: int = 4) -> np.ndarray:
    """[H, W, 3] rendered | white gap | real image -> [H, 2W + gap, 3]."""
    h = pred.shape[0]
    sep = np.ones((h, gap, 3), np.float32)
    return np.concatenate([np.clip(pred, 0, 1), sep, np.clip(real, 0, 1)], axis=1)


def safe_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name)


def evaluate_views(ilm: ILM, views: Scene, images: list[np.ndarray], near: np.ndarray,
                   far: np.ndarray, out_dir: str | Path | None = None,
                   clusters: np.ndarray | None = None, progress: bool = False
                   ) -> list[dict[str, float | str]]:
    """Render each view, compare with its real image; optionally write side-by-side PNGs.

    Args:
      views: Scene of the views (poses, intrinsics); images: their real images [H, W, 3];
      near, far: [N] per view. clusters: [N] cluster per view (default: the nearest
      cluster centre to each camera centre).
    Returns:
      per view dict(name, psnr, ssim, cluster, png).
    """
    from tqdm.auto import tqdm

    if clusters is None:
        clusters = ilm.cluster_of_position(views.centers)
    rows = []
    for i in tqdm(range(len(views)), desc="render", disable=not progress):
        out = render_view(ilm, int(clusters[i]), views.K[i], views.R[i], views.t[i],
                          tuple(views.sizes[i]), float(near[i]), float(far[i]), views.dist[i])
        real = images[i]
        row: dict[str, float | str] = {
            "name": views.names[i], "cluster": int(clusters[i]),
            "psnr": float(psnr(out["rgb"], real)), "ssim": float(ssim(out["rgb"], real))}
        if out_dir is not None:
            p = Path(out_dir) / f"{safe_name(Path(views.names[i]).stem)}.png"
            write_image(p, side_by_side(out["rgb"], real))
            row["png"] = str(p)
        rows.append(row)
    return rows
