"""The explicit geometric map (EGM): a pytree of fixed-shape arrays.

In memory every per-image array is padded to ``K_max`` keypoints with a mask, so that jit
and vmap apply without retracing (docs/design.md, section 4). Within a row the valid keypoints
come first (best first: longest tracks, spread over the image), padding after.

The EGM is stored inside a map (:mod:`vrs_jax.maps`): :func:`to_arrays` gives the arrays as
stored (padding removed: keypoints and links as one concatenated list plus a count per image),
:func:`descriptor_arrays` the real-patch descriptors (only maps that keep them), and
:func:`from_arrays` the inverse. :func:`npz_parts` breaks a stored npz down by part (3D points,
keypoints + links, poses + intrinsics, global descriptors with the vocabulary queries need,
local descriptors).
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax import geometry
from vrs_jax.egm.retrieval import Vocabulary
from vrs_jax.errors import VrsError

FORMAT_VERSION = 2  # 2: quantised keypoints, points, global descriptors
KIND = "vrs-jax explicit geometric map"
NPZ_NAME = "egm.npz"
JSON_NAME = "egm.json"

@flax.struct.dataclass
class EGM:
    """Explicit geometric map of N reference images and M 3D points.

    Attributes:
      points3d: [M, 3] float32 world points.
      R: [N, 3, 3] float32 world-to-camera rotations.  t: [N, 3] float32 translations.
      K: [N, 3, 3] float32 intrinsics (COLMAP pixel convention).  dist: [N, 5] float32 OpenCV.
      sizes: [N, 2] int32 image (width, height).
      keypoints: [N, K_max, 4] float32 (x, y, scale, angle) of the keypoints with a 3D point.
      point_idx: [N, K_max] int32 index into ``points3d`` (-1 in padding).
      kp_mask: [N, K_max] bool, True for real keypoints (a prefix of each row).
      global_desc: [N, G] float32 unit global descriptors (VLAD).
      vocab: :class:`~vrs_jax.egm.retrieval.Vocabulary` for query global descriptors.
      local_desc: [N, K_max, D] float32 descriptors of the keypoints' patches read from the
        real reference images (the hierarchical baseline map), or None (the VRS map).
      names: [N] image names (static).
    """

    points3d: jax.Array
    R: jax.Array
    t: jax.Array
    K: jax.Array
    dist: jax.Array
    sizes: jax.Array
    keypoints: jax.Array
    point_idx: jax.Array
    kp_mask: jax.Array
    global_desc: jax.Array
    vocab: Vocabulary
    local_desc: jax.Array | None = None
    names: tuple[str, ...] = flax.struct.field(pytree_node=False, default=())

    @property
    def num_images(self) -> int:
        return int(self.R.shape[0])

    @property
    def num_points(self) -> int:
        return int(self.points3d.shape[0])

    @property
    def k_max(self) -> int:
        return int(self.keypoints.shape[1])

    @property
    def is_baseline(self) -> bool:
        return self.local_desc is not None

    def without_local_descriptors(self) -> EGM:
        """The same map without the baseline's local descriptors (the VRS map)."""
        return self.replace(local_desc=None)


def make_egm(points3d, R, t, K, dist, sizes, keypoints: list[np.ndarray],
             point_idx: list[np.ndarray], global_desc, vocab: Vocabulary, names,
             k_max: int | None = None, local_desc: list[np.ndarray] | None = None) -> EGM:
    """Build an EGM from per-image lists (padded here to ``k_max``, default the longest row).

    Args:
      keypoints: [N] arrays [K_i, 4]; point_idx: [N] arrays [K_i]; local_desc: [N] arrays
      [K_i, D] or None. Rows longer than ``k_max`` are truncated (callers order them best
      first).
    """
    n = len(names)
    lengths = np.array([len(k) for k in keypoints], np.int64).reshape(n)
    counts = lengths if k_max is None else np.minimum(lengths, k_max)
    km = int(k_max if k_max is not None else counts.max(initial=0))
    mask = np.arange(km)[None, :] < counts[:, None]  # [N, km]: the first counts[i] slots
    # within-row position of every concatenated input row: rows past the count are dropped
    pos = np.arange(int(lengths.sum())) - np.repeat(np.cumsum(lengths) - lengths, lengths)
    keep = pos < np.repeat(counts, lengths)
    kp = np.zeros((n, km, 4), np.float32)
    kp[..., 2] = 1.0  # padding: harmless unit-scale keypoints at the origin
    kp[mask] = _rows(keypoints, 4, np.float32)[keep]
    pi = np.full((n, km), -1, np.int32)
    pi[mask] = _rows(point_idx, None, np.int32)[keep]
    ld = None
    if local_desc is not None:
        d = max([x.shape[-1] for x in local_desc if x.ndim == 2] + [0])
        ld = np.zeros((n, km, d), np.float32)
        ld[mask] = _rows(local_desc, d, np.float32)[keep]
    f32 = lambda a: jnp.asarray(np.asarray(a, np.float32))  # noqa: E731
    return EGM(points3d=f32(np.reshape(points3d, (-1, 3))), R=f32(R), t=f32(t), K=f32(K),
               dist=f32(dist), sizes=jnp.asarray(np.asarray(sizes, np.int32)),
               keypoints=jnp.asarray(kp), point_idx=jnp.asarray(pi), kp_mask=jnp.asarray(mask),
               global_desc=f32(global_desc), vocab=vocab,
               local_desc=None if ld is None else jnp.asarray(ld),
               names=tuple(names))


def _rows(arrays: list[np.ndarray], width: int | None, dtype) -> np.ndarray:
    """Per-image arrays [K_i, width] (or [K_i] when width is None) -> [sum K_i, ...] in
    ``dtype``, one concatenation."""
    shape = (-1,) if width is None else (-1, width)
    parts = [np.asarray(a, dtype).reshape(shape) for a in arrays]
    return np.concatenate(parts) if parts else np.zeros((0, *shape[1:]), dtype)


def observations(egm: EGM) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All (image index [O], keypoint slot [O], point index [O]) links of the map."""
    mask = np.asarray(egm.kp_mask)
    img, slot = np.nonzero(mask)
    return img, slot, np.asarray(egm.point_idx)[img, slot]


def reprojection_errors(egm: EGM, R=None, t=None) -> np.ndarray:
    """Reprojection error (pixels) [O] of every keypoint-point link of the map.

    Args:
      R, t: optional [N, 3, 3], [N, 3] poses to project with (e.g. the dataset's ground
        truth); default the map's own.
    """
    img, slot, pts = observations(egm)
    R = np.asarray(egm.R if R is None else R, np.float64)
    t = np.asarray(egm.t if t is None else t, np.float64)
    K = np.asarray(egm.K, np.float64)
    dist = np.asarray(egm.dist, np.float64)
    X = np.asarray(egm.points3d, np.float64)[pts]
    Xc = np.einsum("oij,oj->oi", R[img], X) + t[img]
    xn = geometry.distort(Xc[:, :2] / Xc[:, 2:3], dist[img])
    uv = np.einsum("oij,oj->oi", K[img, :2, :2], xn) + K[img, :2, 2]
    return np.linalg.norm(uv - np.asarray(egm.keypoints, np.float64)[img, slot, :2], axis=-1)


# ----------------------------------------------------------------------------- arrays
#
# On disk (egm.npz) the points and keypoint records are quantised; in memory they are float32:
#   points_q    [M, 3, B] uint8 fixed point (B bytes per axis, little-endian) over the box
#                             points_origin [3] float64 + q * points_step [3] float64; B = 2..4,
#                             the fewest that move no projection of a link by > POINT_MAX_PX
#   kp_xy_res   [O, 2] int8   (x, y) minus the projection of the linked 3D point with the
#                             image's stored pose, in steps of KP_XY_STEP px (|error| <= half
#                             a step); keypoints whose residual does not fit int8 are listed
#   kp_xy_exact_idx [E] uint32, kp_xy_exact [E, 2] float32: ... with their exact (x, y)
#   kp_scale    [O] uint8     log2(scale) on 256 levels over kp_log2_scale_range [2] float32
#   kp_angle    [O] uint8     angle in steps of 2 pi / 256 (|error| <= pi / 256)
#   point_idx   [O, B] uint8  point index as B little-endian bytes (the fewest that fit M)
#   kp_counts   [N] uint16    keypoints per image (the masks are implied by the counts)
#   global_desc [N, G] int8 with global_scale [N] float32: unit VLAD / scale, renormalised at
#                             load (cosine similarities change by < 1e-2; see the tests)

KP_XY_STEP = 1.0 / 16.0  # px: keypoint positions are stored to within 1/32 px
KP_LEVELS = 256  # uint8 levels of log2(scale) and of the angle


def _uint_dtype(max_value: int) -> np.dtype:
    """The smallest unsigned dtype holding 0..max_value."""
    for dt in (np.uint8, np.uint16, np.uint32):
        if max_value <= np.iinfo(dt).max:
            return np.dtype(dt)
    return np.dtype(np.uint64)


def _pack_le(values: np.ndarray, nbytes: int) -> np.ndarray:
    """Non-negative integers [...] as [..., nbytes] uint8 little-endian bytes."""
    v = np.asarray(values, np.uint64)
    le = v.astype("<u8").reshape(-1).view(np.uint8).reshape(-1, 8)[:, :nbytes]
    return np.ascontiguousarray(le).reshape(v.shape + (nbytes,))


def _unpack_le(b: np.ndarray) -> np.ndarray:
    """[..., B] uint8 little-endian bytes (B <= 8) -> [...] int64."""
    full = np.zeros(b.shape[:-1] + (8,), np.uint8)
    full[..., :b.shape[-1]] = b
    return full.reshape(-1, 8).view("<u8").reshape(b.shape[:-1]).astype(np.int64)


def pack_indices(idx: np.ndarray, n: int) -> np.ndarray:
    """Indices [O] in 0..n-1 as [O, B] uint8 little-endian bytes, B the fewest that fit n-1
    (1..8); :func:`unpack_indices` is the inverse."""
    return _pack_le(idx, max(1, (max(int(n) - 1, 0).bit_length() + 7) // 8))


def unpack_indices(b: np.ndarray) -> np.ndarray:
    """[O, B] uint8 little-endian bytes -> [O] int64 indices."""
    return _unpack_le(b)


POINT_MAX_PX = 0.05  # px: most a stored 3D point may move any of its projections


def quantise_points(points3d: np.ndarray, move_px=None) -> dict[str, np.ndarray]:
    """3D points [M, 3] as fixed point over their bounding box: ``points_q`` [M, 3, B] uint8
    (B = 2, 3 or 4 bytes per axis), ``points_origin`` [3] and ``points_step`` [3] float64.

    ``move_px(X')`` -> the largest change (px) of any link's projection with points ``X'``
    [M, 3] float64; B is the fewest bytes keeping it <= :data:`POINT_MAX_PX` (4 bytes: steps of
    extent / 4.3e9, always kept).
    """
    X = np.asarray(points3d, np.float64).reshape(-1, 3)
    lo = X.min(axis=0) if len(X) else np.zeros(3)
    extent = (X.max(axis=0) - lo) if len(X) else np.zeros(3)
    for nbytes in (2, 3, 4):
        step = np.where(extent > 0, extent / (2.0 ** (8 * nbytes) - 1), 1.0)
        q = np.clip(np.round((X - lo) / step), 0, 2.0 ** (8 * nbytes) - 1)
        if nbytes == 4 or move_px is None or move_px(lo + q * step) <= POINT_MAX_PX:
            break
    return {"points_q": _pack_le(q, nbytes), "points_origin": lo, "points_step": step}


def dequantise_points(a: dict[str, np.ndarray]) -> np.ndarray:
    """[M, 3] float64 points from :func:`quantise_points`' arrays."""
    return a["points_origin"] + _unpack_le(a["points_q"]) * a["points_step"]


def link_projections(points3d, R, t, K, dist, img: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Pixel projections [O, 2] float64 of points ``pts`` [O] in images ``img`` [O].

    Args: points3d [M, 3]; R [N, 3, 3]; t [N, 3]; K [N, 3, 3]; dist [N, 5] (any float dtype;
    computed in float64 from the values given, so that saving and loading agree exactly).
    """
    R, t, K, dist = (np.asarray(a, np.float64) for a in (R, t, K, dist))
    X = np.asarray(points3d, np.float64)[pts]
    Xc = np.einsum("oij,oj->oi", R[img], X) + t[img]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = geometry.distort(Xc[:, :2] / Xc[:, 2:3], dist[img])
    return np.einsum("oij,oj->oi", K[img, :2, :2], xn) + K[img, :2, 2]


def quantise_keypoints(kp: np.ndarray, proj: np.ndarray) -> dict[str, np.ndarray]:
    """Keypoint records [O, 4] (x, y, scale, angle) as stored (see the layout above), given the
    projections [O, 2] of their linked 3D points."""
    kp = np.asarray(kp, np.float64)
    res = np.round((kp[:, :2] - proj) / KP_XY_STEP)
    fits = np.all(np.isfinite(res) & (np.abs(res) <= 127), axis=1)
    exact = np.nonzero(~fits)[0]
    ls = np.log2(np.maximum(kp[:, 2], 1e-30))
    lo, hi = (float(ls.min()), float(ls.max())) if len(ls) else (0.0, 0.0)
    lo, hi = np.float32(lo), np.float32(hi)  # the range as stored
    span = max(float(hi) - float(lo), 1e-12)
    q_scale = np.round((ls - float(lo)) / span * (KP_LEVELS - 1))
    q_angle = np.round(np.mod(kp[:, 3] + np.pi, 2 * np.pi) / (2 * np.pi) * KP_LEVELS)
    return {
        "kp_xy_res": np.where(fits[:, None], res, 0).astype(np.int8),
        "kp_xy_exact_idx": exact.astype(np.uint32),
        "kp_xy_exact": kp[exact, :2].astype(np.float32),
        "kp_scale": np.clip(q_scale, 0, KP_LEVELS - 1).astype(np.uint8),
        "kp_log2_scale_range": np.array([lo, hi], np.float32),
        "kp_angle": np.mod(q_angle, KP_LEVELS).astype(np.uint8),
    }


def dequantise_keypoints(a: dict[str, np.ndarray], proj: np.ndarray) -> np.ndarray:
    """Inverse of :func:`quantise_keypoints`: [O, 4] float32 (angle in [-pi, pi))."""
    xy = proj + a["kp_xy_res"].astype(np.float64) * KP_XY_STEP
    xy[a["kp_xy_exact_idx"].astype(np.int64)] = a["kp_xy_exact"]
    lo, hi = (float(v) for v in a["kp_log2_scale_range"])
    scale = np.exp2(lo + a["kp_scale"].astype(np.float64) / (KP_LEVELS - 1) * (hi - lo))
    angle = a["kp_angle"].astype(np.float64) * (2 * np.pi / KP_LEVELS) - np.pi
    return np.concatenate([xy, scale[:, None], angle[:, None]], 1).astype(np.float32)


def quantise_global(gd: np.ndarray) -> dict[str, np.ndarray]:
    """Global descriptors [N, G] as int8 [N, G] with a float32 scale per row [N]."""
    gd = np.asarray(gd, np.float32)
    scale = (np.abs(gd).max(axis=1) / 127.0 if gd.size else np.zeros(len(gd))).astype(
        np.float32)
    q = np.round(gd / np.where(scale > 0, scale, 1)[:, None])
    return {"global_desc": np.clip(q, -127, 127).astype(np.int8), "global_scale": scale}


def dequantise_global(q: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """[N, G] float32 unit rows (zero rows stay zero) from :func:`quantise_global`'s arrays."""
    v = q.astype(np.float32) * scale[:, None]
    norm = np.linalg.norm(v, axis=1, keepdims=True)
    return (v / np.where(norm > 0, norm, 1)).astype(np.float32)


def to_arrays(egm: EGM) -> dict[str, np.ndarray]:
    """The EGM's arrays as stored (padding removed, keypoints quantised: see the layout above;
    no local descriptors: see :func:`descriptor_arrays`). Keypoints and links are one
    concatenated list plus a count per image."""
    mask = np.asarray(egm.kp_mask)
    counts = mask.sum(1)
    prefix = np.arange(mask.shape[1])[None, :] < counts[:, None]
    if not np.array_equal(mask, prefix):
        raise VrsError("EGM kp_mask must be a prefix of each row (valid keypoints first)")
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    geo = {k: f32(getattr(egm, k)) for k in ("R", "t", "K", "dist")}
    img, slot = np.nonzero(mask)
    pts = np.asarray(egm.point_idx)[img, slot]
    project = lambda X: link_projections(X, geo["R"], geo["t"], geo["K"], geo["dist"],  # noqa
                                         img, pts)
    exact = project(np.asarray(egm.points3d, np.float32))
    pq = quantise_points(np.asarray(egm.points3d, np.float32),
                         lambda X: float(np.nan_to_num(np.abs(project(X) - exact), nan=np.inf)
                                         .max(initial=0.0)))
    proj = project(dequantise_points(pq))
    out = {
        **pq,
        **geo,
        "sizes": np.asarray(egm.sizes, np.int32),
        "kp_counts": counts.astype(_uint_dtype(mask.shape[1])),
        **quantise_keypoints(np.asarray(egm.keypoints, np.float32)[mask], proj),
        "point_idx": pack_indices(pts, egm.num_points),
        **quantise_global(np.asarray(egm.global_desc, np.float32)),
        "vocab_centers": f32(egm.vocab.centers),
        "vocab_power": np.asarray(egm.vocab.power, np.float32),
    }
    if egm.vocab.pca_proj is not None:
        out["pca_mean"] = f32(egm.vocab.pca_mean)
        out["pca_proj"] = f32(egm.vocab.pca_proj)
    if egm.vocab.local_proj is not None:
        out["local_mean"] = f32(egm.vocab.local_mean)
        out["local_proj"] = f32(egm.vocab.local_proj)
    return out


def descriptor_arrays(egm: EGM) -> dict[str, np.ndarray]:
    """The real-patch descriptors of the map keypoints [O, D] as stored: float16, as hloc
    stores local descriptors (unit vectors; their dot products change by < 1e-3)."""
    if egm.local_desc is None:
        raise VrsError("this EGM has no real-patch descriptors")
    mask = np.asarray(egm.kp_mask)
    return {"local_desc": np.asarray(egm.local_desc)[mask].astype(np.float16)}


# member -> dtype kinds accepted ("u1": uint8 only); shapes are checked in from_arrays
_KINDS = {
    "points_q": "u1", "points_origin": "f", "points_step": "f",
    "R": "f", "t": "f", "K": "f", "dist": "f", "sizes": "iu",
    "kp_counts": "u", "kp_xy_res": "i1", "kp_xy_exact_idx": "u", "kp_xy_exact": "f",
    "kp_scale": "u1", "kp_log2_scale_range": "f", "kp_angle": "u1", "point_idx": "u1",
    "global_desc": "i1", "global_scale": "f", "vocab_centers": "f", "vocab_power": "f",
    "pca_mean": "f", "pca_proj": "f", "local_mean": "f", "local_proj": "f",
}


def _dtype_ok(x: np.ndarray, kinds: str) -> bool:
    if kinds.endswith("1"):  # exactly one byte of that kind: int8 / uint8
        return x.dtype.kind == kinds[0] and x.dtype.itemsize == 1
    return x.dtype.kind in kinds


def from_arrays(a: dict[str, np.ndarray], names: tuple[str, ...], k_max: int, where: Path,
                descriptors: np.ndarray | None = None) -> EGM:
    """Inverse of :func:`to_arrays` (+ optional ``descriptors`` [O, D] from
    :func:`descriptor_arrays`); one VrsError line naming ``where`` for a missing, ill-typed,
    ill-shaped or inconsistent array."""
    need = ["points_q", "points_origin", "points_step", "R", "t", "K", "dist", "sizes",
            "kp_counts", "kp_xy_res",
            "kp_xy_exact_idx", "kp_xy_exact", "kp_scale", "kp_log2_scale_range", "kp_angle",
            "point_idx", "global_desc", "global_scale", "vocab_centers", "vocab_power"]
    missing = [k for k in need if k not in a]
    if missing:
        raise VrsError(f"map arrays lack {missing}", where)
    for k, x in a.items():
        if k in _KINDS and not _dtype_ok(x, _KINDS[k]):
            raise VrsError(f"map array {k} has dtype {x.dtype}, expected kind {_KINDS[k]!r}",
                           where)
    n = len(names)
    counts = a["kp_counts"].astype(np.int64)
    total = int(counts.sum()) if counts.ndim == 1 and len(counts) else 0
    m = len(a["points_q"])
    pidx = a["point_idx"]
    n_exact = a["kp_xy_exact_idx"].shape[0] if a["kp_xy_exact_idx"].ndim == 1 else -1
    checks = [
        (a["points_q"].ndim == 3 and a["points_q"].shape[1] == 3
         and 1 <= a["points_q"].shape[2] <= 8 and a["points_origin"].shape == (3,)
         and a["points_step"].shape == (3,) and bool(np.all(np.isfinite(a["points_origin"])))
         and bool(np.all(a["points_step"] > 0)) and bool(np.all(np.isfinite(a["points_step"]))),
         "points are not [M, 3, B] with a finite origin and positive step"),
        (a["R"].shape == (n, 3, 3) and a["t"].shape == (n, 3), "poses are not [N, 3, 3]/[N, 3]"),
        (a["K"].shape == (n, 3, 3) and a["dist"].shape == (n, 5), "intrinsics shapes"),
        (a["sizes"].shape == (n, 2), "sizes shape"),
        (counts.shape == (n,) and (counts >= 0).all() and (counts <= k_max).all(),
         "keypoint counts"),
        (a["kp_xy_res"].shape == (total, 2) and a["kp_scale"].shape == (total,)
         and a["kp_angle"].shape == (total,) and pidx.ndim == 2 and pidx.shape[0] == total
         and 1 <= pidx.shape[1] <= 8, "keypoints/point_idx do not match the counts"),
        (n_exact >= 0 and a["kp_xy_exact"].shape == (n_exact, 2)
         and (n_exact == 0 or int(a["kp_xy_exact_idx"].max()) < total),
         "exact keypoint positions"),
        (a["kp_log2_scale_range"].shape == (2,)
         and bool(np.all(np.isfinite(a["kp_log2_scale_range"]))), "keypoint scale range"),
        (a["vocab_power"].shape == (), "vocab_power is not a scalar"),
        (a["global_desc"].ndim == 2 and a["global_desc"].shape[0] == n
         and a["global_scale"].shape == (n,), "global_desc shape"),
        (("pca_proj" in a) == ("pca_mean" in a), "PCA mean/projection incomplete"),
        (("local_proj" in a) == ("local_mean" in a)
         and ("local_proj" not in a
              or (a["local_proj"].ndim == 2 and a["local_mean"].shape == a["local_proj"].shape[:1]
                  and a["local_proj"].shape[1] == a["vocab_centers"].shape[-1])),
         "local projection incomplete or of the wrong shape for the visual words"),
        (descriptors is None or (descriptors.ndim == 2 and descriptors.shape[0] == total),
         "real-patch descriptors do not match the keypoints"),
    ]
    for ok, what in checks:
        if not ok:
            raise VrsError(f"inconsistent map: {what}", where)
    pts = unpack_indices(pidx)
    if total and (pts.min() < 0 or pts.max() >= m):
        raise VrsError("inconsistent map: point index out of range", where)
    img = np.repeat(np.arange(n), counts)
    points3d = dequantise_points(a)
    proj = link_projections(points3d, a["R"], a["t"], a["K"], a["dist"], img, pts)
    keypoints = dequantise_keypoints(a, proj)
    if not np.all(np.isfinite(keypoints)):
        raise VrsError("inconsistent map: keypoints do not follow from their 3D points", where)
    splits = np.cumsum(counts)[:-1]
    kps = np.split(keypoints, splits)
    pis = np.split(pts, splits)
    lds = None if descriptors is None else np.split(descriptors.astype(np.float32), splits)
    vocab = Vocabulary(centers=jnp.asarray(a["vocab_centers"], jnp.float32),
                       pca_mean=jnp.asarray(a["pca_mean"], jnp.float32)
                       if "pca_mean" in a else None,
                       pca_proj=jnp.asarray(a["pca_proj"], jnp.float32)
                       if "pca_proj" in a else None,
                       power=float(a["vocab_power"]),
                       local_mean=jnp.asarray(a["local_mean"], jnp.float32)
                       if "local_mean" in a else None,
                       local_proj=jnp.asarray(a["local_proj"], jnp.float32)
                       if "local_proj" in a else None)
    gd = dequantise_global(a["global_desc"], a["global_scale"].astype(np.float32))
    return make_egm(points3d, a["R"], a["t"], a["K"], a["dist"], a["sizes"], kps, pis,
                    gd, vocab, names, k_max=k_max, local_desc=lds)


# npz member -> part of the byte breakdown
PARTS = {
    "points_q": "points3d",
    "points_origin": "points3d",
    "points_step": "points3d",
    "kp_counts": "keypoints",
    "kp_xy_res": "keypoints",
    "kp_xy_exact_idx": "keypoints",
    "kp_xy_exact": "keypoints",
    "kp_scale": "keypoints",
    "kp_log2_scale_range": "keypoints",
    "kp_angle": "keypoints",
    "point_idx": "links",
    "R": "poses+intrinsics",
    "t": "poses+intrinsics",
    "K": "poses+intrinsics",
    "dist": "poses+intrinsics",
    "sizes": "poses+intrinsics",
    "global_desc": "global descriptors",
    "global_scale": "global descriptors",
    "vocab_centers": "global descriptors",
    "vocab_power": "global descriptors",
    "pca_mean": "global descriptors",
    "pca_proj": "global descriptors",
    "local_desc": "local descriptors",
}


def npz_parts(npz: bytes) -> dict[str, int]:
    """Bytes of a saved npz by map part (:data:`PARTS`; anything else is "container")."""
    out: dict[str, int] = {}
    with zipfile.ZipFile(io.BytesIO(npz)) as z:
        for info in z.infolist():
            member = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            part = PARTS.get(member, "container")
            out[part] = out.get(part, 0) + info.compress_size
    out["container"] = out.get("container", 0) + len(npz) - sum(out.values())
    return out
