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

FORMAT_VERSION = 1
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


def to_arrays(egm: EGM) -> dict[str, np.ndarray]:
    """The EGM's arrays as stored (padding removed; no local descriptors: see
    :func:`descriptor_arrays`). Keypoints and links are one concatenated list plus a count per
    image."""
    mask = np.asarray(egm.kp_mask)
    counts = mask.sum(1).astype(np.int32)
    prefix = np.arange(mask.shape[1])[None, :] < counts[:, None]
    if not np.array_equal(mask, prefix):
        raise VrsError("EGM kp_mask must be a prefix of each row (valid keypoints first)")
    out = {
        "points3d": np.asarray(egm.points3d, np.float32),
        "R": np.asarray(egm.R, np.float32),
        "t": np.asarray(egm.t, np.float32),
        "K": np.asarray(egm.K, np.float32),
        "dist": np.asarray(egm.dist, np.float32),
        "sizes": np.asarray(egm.sizes, np.int32),
        "kp_counts": counts,
        "keypoints": np.asarray(egm.keypoints, np.float32)[mask],
        "point_idx": np.asarray(egm.point_idx, np.int32)[mask],
        # float16: the unit-norm VLAD's cosine similarities change by < 1e-3, half the bytes
        "global_desc": np.asarray(egm.global_desc, np.float16),
        "vocab_centers": np.asarray(egm.vocab.centers, np.float32),
        "vocab_power": np.asarray(egm.vocab.power, np.float32),
    }
    if egm.vocab.pca_proj is not None:
        out["pca_mean"] = np.asarray(egm.vocab.pca_mean, np.float32)
        out["pca_proj"] = np.asarray(egm.vocab.pca_proj, np.float32)
    return out


def descriptor_arrays(egm: EGM) -> dict[str, np.ndarray]:
    """The real-patch descriptors of the map keypoints [O, D] as stored: float16, as hloc
    stores local descriptors (unit vectors; their dot products change by < 1e-3)."""
    if egm.local_desc is None:
        raise VrsError("this EGM has no real-patch descriptors")
    mask = np.asarray(egm.kp_mask)
    return {"local_desc": np.asarray(egm.local_desc)[mask].astype(np.float16)}


def from_arrays(a: dict[str, np.ndarray], names: tuple[str, ...], k_max: int, where: Path,
                descriptors: np.ndarray | None = None) -> EGM:
    """Inverse of :func:`to_arrays` (+ optional ``descriptors`` [O, D] from
    :func:`descriptor_arrays`); VrsError naming ``where`` for inconsistent arrays."""
    need = ["points3d", "R", "t", "K", "dist", "sizes", "kp_counts", "keypoints", "point_idx",
            "global_desc", "vocab_centers", "vocab_power"]
    missing = [k for k in need if k not in a]
    if missing:
        raise VrsError(f"map arrays lack {missing}", where)
    n = len(names)
    counts = a["kp_counts"].astype(np.int64)
    total = int(counts.sum()) if len(counts) else 0
    m = len(a["points3d"])
    checks = [
        (a["points3d"].ndim == 2 and a["points3d"].shape[1] == 3, "points3d is not [M, 3]"),
        (a["R"].shape == (n, 3, 3) and a["t"].shape == (n, 3), "poses are not [N, 3, 3]/[N, 3]"),
        (a["K"].shape == (n, 3, 3) and a["dist"].shape == (n, 5), "intrinsics shapes"),
        (a["sizes"].shape == (n, 2), "sizes shape"),
        (counts.shape == (n,) and (counts >= 0).all() and (counts <= k_max).all(),
         "keypoint counts"),
        (a["keypoints"].shape == (total, 4) and a["point_idx"].shape == (total,),
         "keypoints/point_idx do not match the counts"),
        (total == 0 or (a["point_idx"].min() >= 0 and a["point_idx"].max() < m),
         "point index out of range"),
        (a["global_desc"].ndim == 2 and a["global_desc"].shape[0] == n, "global_desc shape"),
        (("pca_proj" in a) == ("pca_mean" in a), "PCA mean/projection incomplete"),
        (descriptors is None or (descriptors.ndim == 2 and descriptors.shape[0] == total),
         "real-patch descriptors do not match the keypoints"),
    ]
    for ok, what in checks:
        if not ok:
            raise VrsError(f"inconsistent map: {what}", where)
    splits = np.cumsum(counts)[:-1]
    kps = np.split(a["keypoints"], splits)
    pis = np.split(a["point_idx"], splits)
    lds = None if descriptors is None else np.split(descriptors.astype(np.float32), splits)
    vocab = Vocabulary(centers=jnp.asarray(a["vocab_centers"]),
                       pca_mean=jnp.asarray(a["pca_mean"]) if "pca_mean" in a else None,
                       pca_proj=jnp.asarray(a["pca_proj"]) if "pca_proj" in a else None,
                       power=float(a["vocab_power"]))
    return make_egm(a["points3d"], a["R"], a["t"], a["K"], a["dist"], a["sizes"], kps, pis,
                    a["global_desc"].astype(np.float32), vocab, names, k_max=k_max,
                    local_desc=lds)


# npz member -> part of the byte breakdown
PARTS = {
    "points3d": "points3d",
    "kp_counts": "keypoints+links",
    "keypoints": "keypoints+links",
    "point_idx": "keypoints+links",
    "R": "poses+intrinsics",
    "t": "poses+intrinsics",
    "K": "poses+intrinsics",
    "dist": "poses+intrinsics",
    "sizes": "poses+intrinsics",
    "global_desc": "global descriptors",
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
