"""The explicit geometric map (EGM): a pytree of fixed-shape arrays, saved as npz + JSON.

In memory every per-image array is padded to ``K_max`` keypoints with a mask, so that jit
and vmap apply without retracing (DESIGN.md section 4). Within a row the valid keypoints come
first (best first: longest tracks, spread over the image), padding after.

On disk (a map folder)::

    egm.json   metadata: FORMAT_VERSION, names, shapes, config, checksum of egm.npz
    egm.npz    arrays (uncompressed, so that byte counts are the real storage cost), with the
               padding removed: keypoints and links are stored as one concatenated list plus
               a count per image, and re-padded on load.

``map_bytes`` gives the on-disk byte breakdown by part (DESIGN.md section 6): 3D points,
keypoints + links, poses + intrinsics, global descriptors (with the vocabulary queries need),
local descriptors (baseline map only), clusters, metadata and the zip container.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
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

# npz member -> part of the byte breakdown
_PARTS = {
    "points3d": "points3d",
    "kp_counts": "keypoints+links",
    "keypoints": "keypoints+links",
    "point_idx": "keypoints+links",
    "R": "poses+intrinsics",
    "t": "poses+intrinsics",
    "K": "poses+intrinsics",
    "dist": "poses+intrinsics",
    "sizes": "poses+intrinsics",
    "cluster": "clusters",
    "global_desc": "global descriptors",
    "vocab_centers": "global descriptors",
    "pca_mean": "global descriptors",
    "pca_proj": "global descriptors",
    "local_desc": "local descriptors",
}
PART_NAMES = ("points3d", "keypoints+links", "poses+intrinsics", "global descriptors",
              "local descriptors", "clusters", "metadata", "container")


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
      cluster: [N] int32 NeRF cluster of each image (0 until the ILM clustering fills it).
      global_desc: [N, G] float32 unit global descriptors (VLAD).
      vocab: :class:`~vrs_jax.egm.retrieval.Vocabulary` for query global descriptors.
      local_desc: [N, K_max, D] float32 descriptors of the keypoints' patches read from the
        real reference images (the hierarchical baseline map), or None (the VRS map).
      names: [N] image names (static).
      config: name of the EGMConfig that built the map (static).
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
    cluster: jax.Array
    global_desc: jax.Array
    vocab: Vocabulary
    local_desc: jax.Array | None = None
    names: tuple[str, ...] = flax.struct.field(pytree_node=False, default=())
    config: str = flax.struct.field(pytree_node=False, default="")

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
             k_max: int | None = None, cluster=None, local_desc: list[np.ndarray] | None = None,
             config: str = "") -> EGM:
    """Build an EGM from per-image lists (padded here to ``k_max``, default the longest row).

    Args:
      keypoints: [N] arrays [K_i, 4]; point_idx: [N] arrays [K_i]; local_desc: [N] arrays
      [K_i, D] or None. Rows longer than ``k_max`` are truncated (callers order them best
      first).
    """
    n = len(names)
    counts = [min(len(k), k_max) if k_max is not None else len(k) for k in keypoints]
    km = int(k_max if k_max is not None else max(counts + [0]))
    kp = np.zeros((n, km, 4), np.float32)
    kp[..., 2] = 1.0  # padding: harmless unit-scale keypoints at the origin
    pi = np.full((n, km), -1, np.int32)
    mask = np.zeros((n, km), bool)
    ld = None
    if local_desc is not None:
        d = max([x.shape[-1] for x in local_desc if x.ndim == 2] + [0])
        ld = np.zeros((n, km, d), np.float32)
    for i in range(n):
        c = counts[i]
        kp[i, :c] = np.asarray(keypoints[i], np.float32)[:c]
        pi[i, :c] = np.asarray(point_idx[i], np.int32)[:c]
        mask[i, :c] = True
        if ld is not None:
            ld[i, :c] = np.asarray(local_desc[i], np.float32)[:c]
    f32 = lambda a: jnp.asarray(np.asarray(a, np.float32))  # noqa: E731
    return EGM(points3d=f32(np.reshape(points3d, (-1, 3))), R=f32(R), t=f32(t), K=f32(K),
               dist=f32(dist), sizes=jnp.asarray(np.asarray(sizes, np.int32)),
               keypoints=jnp.asarray(kp), point_idx=jnp.asarray(pi), kp_mask=jnp.asarray(mask),
               cluster=jnp.asarray(np.zeros(n, np.int32) if cluster is None
                                   else np.asarray(cluster, np.int32)),
               global_desc=f32(global_desc), vocab=vocab,
               local_desc=None if ld is None else jnp.asarray(ld),
               names=tuple(names), config=config)


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


# ----------------------------------------------------------------------------- save / load


def _arrays(egm: EGM) -> dict[str, np.ndarray]:
    """The npz members of a map (padding removed)."""
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
        "cluster": np.asarray(egm.cluster, np.int32),
        # float16: the unit-norm VLAD's cosine similarities change by < 1e-3, half the bytes
        "global_desc": np.asarray(egm.global_desc, np.float16),
        "vocab_centers": np.asarray(egm.vocab.centers, np.float32),
    }
    if egm.vocab.pca_proj is not None:
        out["pca_mean"] = np.asarray(egm.vocab.pca_mean, np.float32)
        out["pca_proj"] = np.asarray(egm.vocab.pca_proj, np.float32)
    if egm.local_desc is not None:
        # float32, as computed and matched; see build.py for the byte comparison
        out["local_desc"] = np.asarray(egm.local_desc, np.float32)[mask]
    return out


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _metadata(egm: EGM, npz: bytes, extra: dict | None) -> dict:
    return {
        "kind": KIND,
        "format_version": FORMAT_VERSION,
        "names": list(egm.names),
        "num_images": egm.num_images,
        "num_points": egm.num_points,
        "k_max": egm.k_max,
        "global_dim": int(egm.global_desc.shape[1]),
        "desc_dim": None if egm.local_desc is None else int(egm.local_desc.shape[2]),
        "baseline": egm.is_baseline,
        "vocab_power": float(egm.vocab.power),
        "config": egm.config,
        "npz_sha256": hashlib.sha256(npz).hexdigest(),
        "info": extra or {},
    }


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def save_egm(egm: EGM, map_dir: str | Path, info: dict | None = None) -> Path:
    """Write ``egm.npz`` and ``egm.json`` into ``map_dir`` (each atomically; JSON last).

    Args:
      info: extra JSON-serialisable metadata stored under "info" (e.g. the build key).
    Returns:
      the folder.
    """
    d = Path(map_dir)
    d.mkdir(parents=True, exist_ok=True)
    npz = _npz_bytes(_arrays(egm))
    meta = _metadata(egm, npz, info)
    _write_atomic(d / NPZ_NAME, npz)
    _write_atomic(d / JSON_NAME, (json.dumps(meta, indent=1) + "\n").encode())
    return d


def read_metadata(map_dir: str | Path) -> dict:
    """The map's JSON metadata (checked for kind and format version)."""
    p = Path(map_dir) / JSON_NAME
    if not p.is_file():
        raise VrsError("not an EGM map folder (no egm.json)" if Path(map_dir).is_dir()
                       else "map folder not found", p if Path(map_dir).is_dir() else map_dir)
    try:
        meta = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise VrsError(f"corrupt map metadata: {e}", p) from None
    if not isinstance(meta, dict) or meta.get("kind") != KIND:
        raise VrsError("not an EGM metadata file", p)
    v = meta.get("format_version")
    if v != FORMAT_VERSION:
        raise VrsError(f"map format version {v}, this vrs-jax reads version {FORMAT_VERSION}; "
                       "rebuild the map", p)
    return meta


def load_egm(map_dir: str | Path) -> EGM:
    """Read a map written by :func:`save_egm`.

    Raises:
      VrsError naming the file for a missing/corrupt file, another format version, or
      arrays inconsistent with each other or with the metadata.
    """
    d = Path(map_dir)
    meta = read_metadata(d)
    p = d / NPZ_NAME
    if not p.is_file():
        raise VrsError("map arrays missing", p)
    raw = p.read_bytes()
    if hashlib.sha256(raw).hexdigest() != meta.get("npz_sha256"):
        raise VrsError("map arrays do not match egm.json (corrupt or from another map)", p)
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            a = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise VrsError(f"corrupt map arrays: {e}", p) from None
    return _from_arrays(a, meta, p)


def _from_arrays(a: dict[str, np.ndarray], meta: dict, where: Path) -> EGM:
    need = ["points3d", "R", "t", "K", "dist", "sizes", "kp_counts", "keypoints", "point_idx",
            "cluster", "global_desc", "vocab_centers"]
    missing = [k for k in need if k not in a]
    if missing:
        raise VrsError(f"map arrays lack {missing}", where)
    n = len(meta["names"])
    counts = a["kp_counts"].astype(np.int64)
    total = int(counts.sum()) if len(counts) else 0
    m = len(a["points3d"])
    checks = [
        (a["points3d"].ndim == 2 and a["points3d"].shape[1] == 3, "points3d is not [M, 3]"),
        (m == meta["num_points"], "point count differs from egm.json"),
        (a["R"].shape == (n, 3, 3) and a["t"].shape == (n, 3), "poses are not [N, 3, 3]/[N, 3]"),
        (a["K"].shape == (n, 3, 3) and a["dist"].shape == (n, 5), "intrinsics shapes"),
        (a["sizes"].shape == (n, 2) and a["cluster"].shape == (n,), "sizes/cluster shapes"),
        (counts.shape == (n,) and (counts >= 0).all() and (counts <= meta["k_max"]).all(),
         "keypoint counts"),
        (a["keypoints"].shape == (total, 4) and a["point_idx"].shape == (total,),
         "keypoints/point_idx do not match the counts"),
        (total == 0 or (a["point_idx"].min() >= 0 and a["point_idx"].max() < m),
         "point index out of range"),
        (a["global_desc"].ndim == 2 and a["global_desc"].shape[0] == n, "global_desc shape"),
        (("pca_proj" in a) == ("pca_mean" in a), "PCA mean/projection incomplete"),
        ("local_desc" not in a or a["local_desc"].shape[0] == total, "local_desc shape"),
    ]
    for ok, what in checks:
        if not ok:
            raise VrsError(f"inconsistent map: {what}", where)
    splits = np.cumsum(counts)[:-1]
    kps = np.split(a["keypoints"], splits)
    pis = np.split(a["point_idx"], splits)
    lds = np.split(a["local_desc"], splits) if "local_desc" in a else None
    vocab = Vocabulary(centers=jnp.asarray(a["vocab_centers"]),
                       pca_mean=jnp.asarray(a["pca_mean"]) if "pca_mean" in a else None,
                       pca_proj=jnp.asarray(a["pca_proj"]) if "pca_proj" in a else None,
                       power=float(meta.get("vocab_power", 0.5)))
    return make_egm(a["points3d"], a["R"], a["t"], a["K"], a["dist"], a["sizes"], kps, pis,
                    a["global_desc"].astype(np.float32), vocab, meta["names"],
                    k_max=int(meta["k_max"]), cluster=a["cluster"], local_desc=lds,
                    config=str(meta.get("config", "")))


# ----------------------------------------------------------------------------- bytes


def _breakdown(npz: bytes, json_len: int) -> dict[str, int]:
    out = dict.fromkeys(PART_NAMES, 0)
    with zipfile.ZipFile(io.BytesIO(npz)) as z:
        for info in z.infolist():
            member = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
            out[_PARTS.get(member, "container")] += info.compress_size
    out["container"] += len(npz) - sum(v for k, v in out.items() if k != "container")
    out["metadata"] = json_len
    out["total"] = sum(out[k] for k in PART_NAMES)
    out["total_without_local_descriptors"] = out["total"] - out["local descriptors"]
    return out


def map_bytes(egm_or_dir: EGM | str | Path) -> dict[str, int]:
    """On-disk bytes of a map by part (see PART_NAMES), plus "total" and
    "total_without_local_descriptors".

    Given a folder, measures the files; given an EGM, serialises it in memory exactly as
    :func:`save_egm` would (so the figures match the saved map's).
    """
    if isinstance(egm_or_dir, EGM):
        npz = _npz_bytes(_arrays(egm_or_dir))
        meta = json.dumps(_metadata(egm_or_dir, npz, None), indent=1) + "\n"
        return _breakdown(npz, len(meta.encode()))
    d = Path(egm_or_dir)
    read_metadata(d)
    p = d / NPZ_NAME
    if not p.is_file():
        raise VrsError("map arrays missing", p)
    try:
        return _breakdown(p.read_bytes(), (d / JSON_NAME).stat().st_size)
    except zipfile.BadZipFile as e:
        raise VrsError(f"corrupt map arrays: {e}", p) from None


def baseline_bytes(egm: EGM, desc_dim: int) -> dict[str, int]:
    """:func:`map_bytes` of ``egm`` with float32 local descriptors [desc_dim] added for every
    keypoint link, computed without materialising them (the npy header of an empty array has
    the same padded length, and the stored zip member grows by exactly the data bytes).
    """
    arrays = _arrays(egm.without_local_descriptors())
    arrays["local_desc"] = np.zeros((0, desc_dim), np.float32)
    npz = _npz_bytes(arrays)
    meta = _metadata(egm, npz, None)
    meta["baseline"], meta["desc_dim"] = True, desc_dim
    out = _breakdown(npz, len((json.dumps(meta, indent=1) + "\n").encode()))
    data = int(np.asarray(egm.kp_mask).sum()) * desc_dim * 4
    out["local descriptors"] += data
    out["total"] += data
    return out
