"""From a Scene to NeRF training data: near/far priors, normalisation, rays, ray bank.

Rays are pixel cones in COLMAP's pixel convention (``geometry.pixel_rays``): the ray of
pixel ``img[i, j]`` passes through ``(u, v) = (j + 0.5, i + 0.5)`` and its direction has
camera-frame z = 1, so the ray parameter t IS the z-depth; near/far (from depth priors,
which are z-depths) are therefore directly t bounds. The cone radius at t = 1 is
:func:`vrs_jax.geometry.cone_radius` (mip-NeRF's pixel radius).

Training images stay on the device as uint8 [N, H, W, 3] plus their cameras; every step
draws random (image, pixel) pairs from a cluster's image list and generates the rays inside
the jitted step. Cluster image lists are padded to one fixed shape with counts, so one
compiled step serves every cluster.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from vrs_jax import geometry
from vrs_jax.data.images import read_depth, read_image
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError

Array = jax.Array

def pixel_radii(K: np.ndarray) -> np.ndarray:
    """Cone radius at t = 1 of one pixel, per camera: K [..., 3, 3] -> [...]."""
    return geometry.cone_radius(np.asarray(K, dtype=np.float64))


# ----------------------------------------------------------------------------- near / far


def near_far_from_depths(depths: list[np.ndarray], percentiles: tuple[float, float] = (1, 99),
                         margin: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Per-image near/far from samples of its depths (EGM point depths, depth-map pixels).

    near = P_lo * (1 - margin), far = P_hi * (1 + margin), over the valid (finite, > 0)
    samples of each image. An image without samples gets the bounds of all images pooled.

    Args:
      depths: N arrays of z-depths (any shape; invalid values ignored).
    Returns:
      near [N], far [N] float32. Raises VrsError if no image has any valid depth.
    """
    lo, hi = percentiles
    valid = [np.asarray(d, np.float64).ravel() for d in depths]
    valid = [d[np.isfinite(d) & (d > 0)] for d in valid]
    pooled = np.concatenate(valid) if valid else np.zeros(0)
    if len(pooled) == 0:
        raise VrsError("no valid depth samples to derive near/far from; pass near/far")
    g_near, g_far = np.percentile(pooled, lo), np.percentile(pooled, hi)
    near = np.array([np.percentile(d, lo) if len(d) else g_near for d in valid])
    far = np.array([np.percentile(d, hi) if len(d) else g_far for d in valid])
    near = near * (1.0 - margin)
    far = np.maximum(far * (1.0 + margin), near * 1.01 + 1e-6)
    return near.astype(np.float32), far.astype(np.float32)


def point_depths(scene: Scene, points3d: np.ndarray) -> list[np.ndarray]:
    """z-depths of the 3D points that project inside each image (N arrays)."""
    pts = np.asarray(points3d, np.float64)
    out = []
    for i in range(len(scene)):
        uv, z = geometry.project(scene.K[i], scene.R[i], scene.t[i], pts)
        w, h = scene.sizes[i]
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= w) & (uv[:, 1] >= 0) & (uv[:, 1] <= h)
        out.append(z[inside])
    return out


def depth_map_samples(scene: Scene, max_pixels: int = 4096) -> list[np.ndarray]:
    """Valid depths (metres; a strided subset) of each image's depth map."""
    out = []
    for i in range(len(scene)):
        p = scene.depth_paths[i] if scene.depth_paths is not None else None
        if p is None:
            out.append(np.zeros(0))
            continue
        d = read_depth(p, scale=scene.depth_scale).ravel()
        step = max(1, len(d) // max_pixels)
        out.append(d[::step])
    return out


def scene_near_far(scene: Scene, near: float | None = None, far: float | None = None,
                   points3d: np.ndarray | None = None, percentiles: tuple[float, float] = (1, 99),
                   margin: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """Per-image near/far [N] for a scene, from the best prior available.

    Order: explicit ``near``/``far`` (either one overrides that bound); depths of
    ``points3d`` (e.g. the EGM's points) seen by each image; the dataset's bounds (LLFF,
    already percentiles: only the margin is applied); the scene's own sparse points;
    its depth maps. Raises VrsError if none exists and no explicit pair is given.
    """
    n = len(scene)
    if near is not None and far is not None:
        if not 0 < near < far:
            raise VrsError(f"need 0 < near < far, got near={near} far={far}")
        return np.full(n, near, np.float32), np.full(n, far, np.float32)
    if points3d is not None and len(points3d):
        nr, fr = near_far_from_depths(point_depths(scene, points3d), percentiles, margin)
    elif scene.bounds is not None:
        b = np.asarray(scene.bounds, np.float64)
        nr = (b[:, 0] * (1 - margin)).astype(np.float32)
        fr = (b[:, 1] * (1 + margin)).astype(np.float32)
    elif scene.points3d is not None and len(scene.points3d):
        nr, fr = near_far_from_depths(point_depths(scene, scene.points3d), percentiles, margin)
    elif scene.depth_paths is not None and any(p is not None for p in scene.depth_paths):
        nr, fr = near_far_from_depths(depth_map_samples(scene), percentiles, margin)
    else:
        raise VrsError("no depth prior (points, bounds or depth maps) for near/far: "
                       "pass --near and --far", scene.root)
    if near is not None:
        nr = np.full(n, near, np.float32)
    if far is not None:
        fr = np.full(n, far, np.float32)
    if np.any(~(nr > 0)) or np.any(~(fr > nr)):
        raise VrsError("near/far prior gives near <= 0 or far <= near", scene.root)
    return nr, fr


# ----------------------------------------------------------------------------- normalisation


def frustum_points(K: np.ndarray, R: np.ndarray, t: np.ndarray, sizes: np.ndarray,
                   near: np.ndarray, far: np.ndarray, grid: int = 5, n_depths: int = 9
                   ) -> np.ndarray:
    """Points spanning each camera's sampled region: a grid x grid of pixel rays, each at
    n_depths depths in [near, far]. K [N,3,3], R [N,3,3], t [N,3], sizes [N,2], near/far
    [N] -> [N * grid^2 * n_depths, 3]."""
    pts = []
    for i in range(len(K)):
        w, h = sizes[i]
        u, v = np.meshgrid(np.linspace(0, w, grid), np.linspace(0, h, grid))
        uv = np.stack([u.ravel(), v.ravel()], -1)
        o, d = geometry.pixel_rays(np.asarray(K[i], np.float64), np.asarray(R[i], np.float64),
                                   np.asarray(t[i], np.float64), uv)
        ts = np.linspace(near[i], far[i], n_depths)
        pts.append((o[:, None, :] + d[:, None, :] * ts[None, :, None]).reshape(-1, 3))
    return np.concatenate(pts)


def normalization(points: np.ndarray, radius: float = math.pi) -> tuple[np.ndarray, float]:
    """Centre and isotropic scale mapping the points' bounding box into [-radius, radius]^3.

    The lowest IPE frequency is 2^0, so a coordinate range of 2 pi is the largest that
    never aliases (sin is 2 pi periodic); the box is the region where samples are drawn,
    so every sample stays inside it. points: [M, 3] -> (center [3], scale).
    """
    lo, hi = points.min(axis=0), points.max(axis=0)
    center = 0.5 * (lo + hi)
    half = float(np.max(hi - lo)) / 2
    if not np.isfinite(half) or half <= 0:
        raise VrsError("degenerate scene extent: cannot normalise the scene")
    return center.astype(np.float32), float(radius / half)


def inner_ball(cam_centers: np.ndarray, depths: np.ndarray) -> tuple[np.ndarray, float]:
    """The ball a contracted field keeps at full resolution: centre and radius (world).

    Centred on the cameras' centroid, it holds every camera plus the median depth of what
    they see (so near content keeps the finest grid cells and what lies beyond is
    contracted). cam_centers: [N, 3]; depths: [M] typical z-depths of the images' content
    (e.g. the median EGM point depth per image) -> (centre [3] float32, radius).
    """
    c = np.asarray(cam_centers, np.float64)
    d = np.asarray(depths, np.float64)
    d = d[np.isfinite(d) & (d > 0)]
    center = c.mean(axis=0)
    radius = float(np.max(np.linalg.norm(c - center, axis=1))) + (
        float(np.median(d)) if len(d) else 0.0)
    if not np.isfinite(radius) or radius <= 0:
        raise VrsError("degenerate scene extent: cannot place the contraction's inner ball")
    return center.astype(np.float32), radius


# A scene is unbounded when the median far bound exceeds this many inner-ball radii. Measured
# (cpu-small EGMs): phone walk 17.4; fern 2.6, lego 0.70, dtu_scan24 0.81.
UNBOUNDED_RATIO = 8.0


def unbounded_ratio(cam_centers: np.ndarray, depths: np.ndarray, far: np.ndarray) -> float:
    """Median far bound [N] over the radius of :func:`inner_ball` (cameras [N, 3], their
    typical depths [N]): large when most of the sampled region lies far beyond the cameras'
    neighbourhood."""
    return float(np.median(far)) / inner_ball(cam_centers, depths)[1]


def typical_depths(near: np.ndarray, far: np.ndarray,
                   depths: list[np.ndarray] | None = None) -> np.ndarray:
    """Per image one typical content depth [N]: the median of its depth samples when
    given (EGM point depths), else the geometric mean of its near and far bounds."""
    out = np.sqrt(np.asarray(near, np.float64) * np.asarray(far, np.float64))
    if depths is not None:
        for i, d in enumerate(depths):
            d = np.asarray(d, np.float64)
            d = d[np.isfinite(d) & (d > 0)]
            if len(d):
                out[i] = np.median(d)
    return out


# ----------------------------------------------------------------------------- rays


def image_rays(K: np.ndarray, R: np.ndarray, t: np.ndarray, size: tuple[int, int],
               dist: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays of every pixel of one image, row-major: origins, directions [H*W, 3], radii
    [H*W] (float32; world frame)."""
    w, h = int(size[0]), int(size[1])
    uv = geometry.pixel_grid(w, h).reshape(-1, 2)
    o, d = geometry.pixel_rays(np.asarray(K, np.float64), np.asarray(R, np.float64),
                               np.asarray(t, np.float64), uv,
                               None if dist is None or not np.any(dist) else
                               np.asarray(dist, np.float64))
    r = np.full(len(uv), pixel_radii(K), np.float32)
    return o.astype(np.float32), d.astype(np.float32), r


@struct.dataclass
class RayBank:
    """All training images and cameras, device-resident, for in-step ray sampling.

    images [N, Hmax, Wmax, 3] uint8 (zero padded); K [N,3,3], R [N,3,3], t [N,3],
    dist [N,5] float32; sizes [N,2] int32 (w, h); near, far, radii [N] float32.
    """

    images: Array
    K: Array
    R: Array
    t: Array
    dist: Array
    sizes: Array
    near: Array
    far: Array
    radii: Array
    # Optional keypoint-patch pool (nerf/patch_pool.py), sorted by image: rays [M, ...] and
    # per image its slice [pool_start[i], pool_start[i] + pool_count[i]).
    pool_origins: Array | None = None
    pool_directions: Array | None = None
    pool_radii: Array | None = None
    pool_rgb: Array | None = None
    pool_depth: Array | None = None  # [M] keypoint point depth (t units), 0: none
    pool_start: Array | None = None
    pool_count: Array | None = None
    use_dist: bool = struct.field(pytree_node=False, default=False)
    pool_fraction: float = struct.field(pytree_node=False, default=0.0)


def load_images(scene: Scene, background: np.ndarray | None = None) -> list[np.ndarray]:
    """Images as float32 [H, W, 3] at each image's declared size (``scene.sizes``)."""
    bg = None if background is None else tuple(float(v) for v in background)
    return [read_image(p, background=bg, size=(int(s[0]), int(s[1])))
            for p, s in zip(scene.image_paths, scene.sizes, strict=True)]


def build_bank(scene: Scene, near: np.ndarray, far: np.ndarray,
               images: list[np.ndarray], pool: dict[str, np.ndarray] | None = None,
               pool_fraction: float = 0.0) -> RayBank:
    """Ray bank of a scene's images (float [H, W, 3] in [0, 1], as from load_images).

    ``pool``: optional keypoint-patch rays (patch_pool.patch_pool, image indices into
    ``scene``); ``pool_fraction`` of each batch is then drawn from it.
    """
    n = len(scene)
    wmax, hmax = int(np.max(scene.sizes[:, 0])), int(np.max(scene.sizes[:, 1]))
    stack = np.zeros((n, hmax, wmax, 3), np.uint8)
    for i, img in enumerate(images):
        stack[i, : img.shape[0], : img.shape[1]] = np.round(np.clip(img, 0, 1) * 255)
    dist = np.zeros((n, 5)) if scene.dist is None else np.asarray(scene.dist)
    f32 = lambda a: jnp.asarray(np.asarray(a, np.float32))  # noqa: E731
    extra: dict[str, Any] = {}
    if pool and pool_fraction > 0:
        order = np.argsort(pool["image"], kind="stable")
        count = np.bincount(pool["image"], minlength=n).astype(np.int32)
        start = (np.cumsum(count) - count).astype(np.int32)
        extra = dict(pool_origins=f32(pool["origins"][order]),
                     pool_directions=f32(pool["directions"][order]),
                     pool_radii=f32(pool["radii"][order]), pool_rgb=f32(pool["rgb"][order]),
                     pool_depth=f32(pool["depth"][order] if "depth" in pool
                                    else np.zeros(len(order))),
                     pool_start=jnp.asarray(start), pool_count=jnp.asarray(count),
                     pool_fraction=float(pool_fraction))
    return RayBank(images=jnp.asarray(stack), K=f32(scene.K), R=f32(scene.R), t=f32(scene.t),
                   dist=f32(dist), sizes=jnp.asarray(np.asarray(scene.sizes, np.int32)),
                   near=f32(near), far=f32(far), radii=f32(pixel_radii(scene.K)),
                   use_dist=bool(np.any(dist)), **extra)


def pool_rays_per_batch(bank: RayBank, batch_size: int) -> int:
    """How many of a batch's rays :func:`sample_rays` draws from the keypoint-patch pool
    (they lead the batch; static)."""
    return int(round(bank.pool_fraction * batch_size)) if bank.pool_count is not None else 0


def sample_rays(bank: RayBank, members: Array, count: Array, key: Array, batch_size: int
                ) -> dict[str, Array]:
    """Random training rays of one cluster (jittable, fixed shapes).

    Args:
      members: [M] image indices of the cluster (the first ``count`` are valid).
      count: [] number of valid entries.
      batch_size: B (static).
    Returns:
      dict(origins [B,3], directions [B,3], radii [B], near [B], far [B], rgb [B,3],
      image [B] int32, pixel [B, 2] int32 (row i, column j), depth [B]: the keypoint's
      point depth for patch-pool rays of a 3D-linked keypoint, else 0).
    """
    k1, k2, k3 = jax.random.split(key, 3)
    slot = jax.random.randint(k1, (batch_size,), 0, jnp.maximum(count, 1))
    img = members[slot]
    size = bank.sizes[img].astype(jnp.float32)  # [B, 2] (w, h)
    j = jnp.minimum(jnp.floor(jax.random.uniform(k2, (batch_size,)) * size[:, 0]),
                    size[:, 0] - 1).astype(jnp.int32)
    i = jnp.minimum(jnp.floor(jax.random.uniform(k3, (batch_size,)) * size[:, 1]),
                    size[:, 1] - 1).astype(jnp.int32)
    rgb = bank.images[img, i, j].astype(jnp.float32) / 255.0
    uv = jnp.stack([j + 0.5, i + 0.5], axis=-1)[:, None, :]  # [B, 1, 2]
    o, d = geometry.pixel_rays(bank.K[img], bank.R[img], bank.t[img], uv,
                               bank.dist[img] if bank.use_dist else None)
    out = {"origins": o[:, 0], "directions": d[:, 0], "radii": bank.radii[img],
           "near": bank.near[img], "far": bank.far[img], "rgb": rgb, "image": img,
           "pixel": jnp.stack([i, j], axis=-1), "depth": jnp.zeros((batch_size,))}
    n_pool = pool_rays_per_batch(bank, batch_size)
    if n_pool > 0:
        # the first n_pool rays come from the keypoint-patch pool of the same images (an image
        # without pool rays keeps its pixel ray)
        k4 = jax.random.fold_in(key, 1)
        im = img[:n_pool]
        cnt = bank.pool_count[im]
        pick = bank.pool_start[im] + jnp.minimum(
            jnp.floor(jax.random.uniform(k4, (n_pool,)) * cnt).astype(jnp.int32),
            jnp.maximum(cnt - 1, 0))
        has = (cnt > 0)[:, None]
        for name, src in (("origins", bank.pool_origins), ("directions", bank.pool_directions),
                          ("rgb", bank.pool_rgb)):
            out[name] = out[name].at[:n_pool].set(jnp.where(has, src[pick], out[name][:n_pool]))
        for name, src in (("radii", bank.pool_radii), ("depth", bank.pool_depth)):
            out[name] = out[name].at[:n_pool].set(jnp.where(has[:, 0], src[pick],
                                                            out[name][:n_pool]))
    return out


def pad_members(membership: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """membership [C, N] bool -> members [C, Mmax] int32 (padded by repetition), counts [C]."""
    lists = [np.flatnonzero(m) for m in membership]
    mmax = max(1, max(len(x) for x in lists))
    members = np.zeros((len(lists), mmax), np.int32)
    for c, lst in enumerate(lists):
        if len(lst):
            members[c] = np.resize(lst, mmax)
    return members, np.array([len(x) for x in lists], np.int32)


def eval_rays(scene: Scene, near: np.ndarray, far: np.ndarray, images: list[np.ndarray],
              n_rays: int, seed: int = 0) -> dict[str, np.ndarray]:
    """A fixed random subset of the pixels of the given (held-out) images, as rays.

    Returns dict(origins, directions [M,3], radii, near, far [M], rgb [M,3], image [M] int).
    """
    rng = np.random.default_rng(seed)
    per = max(1, n_rays // max(1, len(scene)))
    out = {k: [] for k in ("origins", "directions", "radii", "near", "far", "rgb", "image")}
    for i, img in enumerate(images):
        h, w = img.shape[:2]
        flat = rng.choice(h * w, size=min(per, h * w), replace=False)
        uv = np.stack([flat % w + 0.5, flat // w + 0.5], -1)
        o, d = geometry.pixel_rays(np.asarray(scene.K[i], np.float64),
                                   np.asarray(scene.R[i], np.float64),
                                   np.asarray(scene.t[i], np.float64), uv,
                                   np.asarray(scene.dist[i], np.float64)
                                   if np.any(scene.dist[i]) else None)
        out["origins"].append(o)
        out["directions"].append(d)
        out["radii"].append(np.full(len(uv), pixel_radii(scene.K[i])))
        out["near"].append(np.full(len(uv), near[i]))
        out["far"].append(np.full(len(uv), far[i]))
        out["rgb"].append(img.reshape(-1, 3)[flat])
        out["image"].append(np.full(len(uv), i))
    res = {k: np.concatenate(v).astype(np.float32) for k, v in out.items() if k != "image"}
    res["image"] = np.concatenate(out["image"]).astype(np.int32)
    return res


def check_scene_for_training(scene: Scene) -> None:
    """Raise VrsError for scenes a NeRF cannot be trained on."""
    where = getattr(scene, "root", None)
    refs = ~np.asarray(scene.is_query) & np.asarray(scene.has_pose)
    if refs.sum() == 0:
        raise VrsError("scene has no posed reference images to train a NeRF on", where)
    if refs.sum() < 2:
        raise VrsError("scene has a single posed reference image: a NeRF needs at least two "
                       "views", where)
