"""A tiny procedural scene (analytically ray-traced textured sphere) for tests and demos.

Cameras on a ring look at a unit sphere whose colour is a smooth function of the surface
normal; images are exact (one ray per pixel centre, COLMAP convention), tiny, and written
as PNGs so that the whole NeRF pipeline (image reading included) runs on them in seconds.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vrs_jax import geometry
from vrs_jax.data.images import write_image
from vrs_jax.data.scene import Scene, hold_out_every


def look_at(center: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)
            ) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R [3,3], t [3]) of an OpenCV camera at ``center`` looking at ``target``."""
    z = target - center
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x = x / np.linalg.norm(x)
    y = np.cross(z, x)
    Rc2w = np.stack([x, y, z], axis=1)
    return geometry.pose_inverse(Rc2w, center)


def sphere_colour(n: np.ndarray) -> np.ndarray:
    """Smooth RGB texture of unit normals [..., 3] -> [..., 3] in [0.1, 0.9]."""
    r = 0.5 + 0.4 * np.sin(3.0 * n[..., 0] + 1.0) * np.cos(2.0 * n[..., 2])
    g = 0.5 + 0.4 * np.sin(2.5 * n[..., 1] - 0.5)
    b = 0.5 + 0.4 * np.cos(3.0 * n[..., 2] + 2.0 * n[..., 0])
    return np.stack([r, g, b], axis=-1)


def trace_sphere(o: np.ndarray, d: np.ndarray, background: np.ndarray) -> np.ndarray:
    """Colour of rays o + t d [M, 3] hitting the unit sphere at the origin (else background)."""
    a = np.sum(d * d, -1)
    b = 2 * np.sum(o * d, -1)
    c = np.sum(o * o, -1) - 1.0
    disc = b * b - 4 * a * c
    hit = disc > 0
    t = (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a)
    p = o + t[:, None] * d
    col = sphere_colour(p / np.linalg.norm(p, axis=-1, keepdims=True))
    return np.where(hit[:, None], col, background[None])


def make_toy_scene(out_dir: str | Path, n_images: int = 12, size: int = 32,
                   query_every: int = 4, radius: float = 4.0,
                   background: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> Scene:
    """Write ``n_images`` views of the textured unit sphere and return their Scene.

    Cameras on a ring of ``radius`` at height 1 (alternating +-0.5) look at the origin,
    focal length ``1.2 * size``. Every ``query_every``-th image is a query. The surface
    lies at depths in [radius - 1.2, radius + 0.2]: near 2 / far 6 bound it.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    f = 1.2 * size
    K = geometry.intrinsics_matrix(f, f, size / 2, size / 2)
    bg = np.asarray(background, float)
    Rs, ts, paths = [], [], []
    for i in range(n_images):
        ang = 2 * np.pi * i / n_images
        c = np.array([radius * np.cos(ang), radius * np.sin(ang), 1.0 + 0.5 * (-1) ** i])
        R, t = look_at(c, np.zeros(3))
        o, d = geometry.pixel_rays(K, R, t, geometry.pixel_grid(size, size).reshape(-1, 2))
        img = trace_sphere(o, d, bg).reshape(size, size, 3)
        p = out / f"view_{i:03d}.png"
        write_image(p, img)
        Rs.append(R)
        ts.append(t)
        paths.append(p)
    n = n_images
    return Scene(root=out, names=[p.name for p in paths], image_paths=paths,
                 K=np.repeat(K[None], n, 0), dist=np.zeros((n, 5)),
                 sizes=np.tile([size, size], (n, 1)), R=np.stack(Rs), t=np.stack(ts),
                 has_pose=np.ones(n, bool), is_query=hold_out_every(n, query_every),
                 background=tuple(background), format="toy")
