"""The implicit learning map (ILM): C per-cluster NeRFs stacked on a leading axis.

Saved as ONE ``.npz`` file (written atomically, :mod:`vrs_jax.fileio`) holding
every array plus a JSON header with the format version and the full config, so a map is
self-describing and its size on disk is simply the file size.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct, traverse_util

from vrs_jax import fileio
from vrs_jax.errors import VrsError
from vrs_jax.nerf.clusters import cluster_cameras
from vrs_jax.nerf.config import NerfConfig
from vrs_jax.nerf.model import HASH_TABLE, Field, init_params, init_stacked_params, select_field

# 2: NerfConfig gained cluster_method (K-means or a uniform grid of the cameras)
# 3: hash tables may be stored as int8 with a scale per cluster and level (``qscale/...``);
#    a version-2 file (no such scales) reads as before
FORMAT_VERSION = 3
READABLE_VERSIONS = (2, 3)
_META = "__meta__"
_QSCALE = "qscale/"  # per-(cluster, level) scales of a parameter stored as int8
INT8_PARAMS = (HASH_TABLE,)  # the parameters ``hash_int8`` stores as int8


def quantize_int8(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Symmetric int8 of a stacked hash table, one scale per table.

    Args:
      v: [..., T, F] float (e.g. [C, L, T, F]: clusters, levels, entries, features).
    Returns:
      (q [..., T, F] int8 in [-127, 127], scale [...] float32) with v ~= q * scale[..., None,
      None]: each table's largest magnitude maps to 127, so nothing is clipped and the
      rounding error is at most half a step (scale / 2). A table holding a non-finite value
      gets a NaN scale (q 0), so that it decodes to NaN and loading refuses the diverged
      field as it refuses a float one, instead of reading back finite garbage.
    """
    v = np.asarray(v, np.float32)
    finite = np.all(np.isfinite(v), axis=(-2, -1))
    v = np.where(finite[..., None, None], v, 0.0)
    scale = np.max(np.abs(v), axis=(-2, -1)) / 127.0
    scale = np.where(scale > 0, scale, 1.0)
    q = np.clip(np.rint(v / scale[..., None, None]), -127, 127).astype(np.int8)
    return q, np.where(finite, scale, np.nan).astype(np.float32)


def stored_param_bytes(cfg: NerfConfig, float16: bool, hash_int8: bool) -> int:
    """Bytes one cluster's network parameters take in :func:`to_bytes` with these options
    (array payloads only: the npz container and header are not counted)."""
    shapes = traverse_util.flatten_dict(
        jax.eval_shape(lambda: init_params(jax.random.key(0), cfg)), sep="/")
    total = 0
    for k, x in shapes.items():
        n = int(np.prod(x.shape))
        if hash_int8 and k.rsplit("/", 1)[-1] in INT8_PARAMS:
            total += n + 4 * int(np.prod(x.shape[:-2]))  # int8 entries, a float32 scale each
        else:
            total += n * (2 if float16 else 4)
    return total


def dequantize_int8(q: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """[..., T, F] float32 from :func:`quantize_int8`'s (q [..., T, F] int8, scale [...])."""
    return np.asarray(q, np.float32) * np.asarray(scale, np.float32)[..., None, None]


@struct.dataclass
class ILM:
    """Stacked per-cluster NeRFs and the data needed to pick the right one.

    fields: Field with every leaf stacked [C, ...] (MLP params, per-cluster normalisation
      centre [C, 3] and scale [C], background [C, 3]).
    cluster_centers: [C, 3] K-means centres of the reference camera centres.
    image_cluster: [N] int32 primary cluster of each reference image.
    membership: [C, N] bool images each cluster was trained on.
    near, far: [N] float32 per reference image (t = z-depth bounds used in training).
    image_names: N reference image names (static).
    config: the NerfConfig it was trained with (static).
    """

    fields: Field
    cluster_centers: jax.Array
    image_cluster: jax.Array
    membership: jax.Array
    near: jax.Array
    far: jax.Array
    image_names: tuple[str, ...] = struct.field(pytree_node=False, default=())
    config: NerfConfig = struct.field(pytree_node=False, default=NerfConfig())

    @property
    def n_clusters(self) -> int:
        return int(self.cluster_centers.shape[0])

    def field(self, c: int | jax.Array) -> Field:
        """Cluster c's Field (c may be traced)."""
        return select_field(self.fields, c)

    def cluster_of_image(self, name: str) -> int:
        try:
            return int(self.image_cluster[self.image_names.index(name)])
        except ValueError:
            raise VrsError(f"image {name!r} is not a reference image of this map") from None

    def cluster_of_position(self, centers: np.ndarray) -> np.ndarray:
        """Nearest cluster of camera centres [M, 3] (e.g. queries) -> [M] int32."""
        d2 = np.sum((np.asarray(centers)[:, None] - np.asarray(self.cluster_centers)[None]) ** 2,
                    axis=-1)
        return np.argmin(d2, axis=1).astype(np.int32)


def untrained(cfg: NerfConfig, image_names: tuple[str, ...], camera_centers: np.ndarray,
              seed: int = 0) -> ILM:
    """An ILM of ``cfg.n_clusters`` NeRFs at their initial parameters: the shapes and dtypes
    a trained one has (the cameras clustered as training clusters them), so :func:`to_bytes`
    gives it exactly the bytes of a trained ILM of the same config and images (what
    ``benchmarks.map_size --series`` measures for scenes it does not train). Normalisation,
    background and near/far are placeholders (zeros / ones), not usable for rendering.

    camera_centers: [N, 3] world centres of the N reference images ``image_names``.
    """
    c, n = cfg.n_clusters, len(image_names)
    cl = cluster_cameras(np.asarray(camera_centers), c, cfg.cluster_overlap, seed=cfg.seed,
                         method=cfg.cluster_method)
    fields = Field(params=init_stacked_params(jax.random.key(seed), cfg, c),
                   center=jnp.zeros((c, 3), jnp.float32), scale=jnp.ones((c,), jnp.float32),
                   background=jnp.zeros((c, 3), jnp.float32))
    return ILM(fields=fields, cluster_centers=jnp.asarray(cl.centers, jnp.float32),
               image_cluster=jnp.asarray(cl.primary), membership=jnp.asarray(cl.membership),
               near=jnp.ones((n,), jnp.float32), far=jnp.ones((n,), jnp.float32),
               image_names=tuple(image_names), config=cfg)


def _flatten(ilm: ILM) -> dict[str, np.ndarray]:
    out = {f"params/{k}": np.asarray(v) for k, v in
           traverse_util.flatten_dict(jax.device_get(ilm.fields.params), sep="/").items()}
    for name in ("center", "scale", "background"):
        out[name] = np.asarray(getattr(ilm.fields, name))
    for name in ("cluster_centers", "image_cluster", "membership", "near", "far"):
        out[name] = np.asarray(getattr(ilm, name))
    return out


def to_bytes(ilm: ILM, float16: bool = False, hash_int8: bool = False) -> bytes:
    """The ILM as one npz file's bytes: every array plus a JSON header (format version, the
    full NerfConfig, the image names). ``float16``: the network parameters (MLP weights, hash
    tables) at half precision, halving the file; ``hash_int8``: the hash tables
    (:data:`INT8_PARAMS`) as int8 with one float32 scale per cluster and level
    (:func:`quantize_int8`), halving them again. :func:`from_bytes` reads both back as float32
    (rendering from the rounded parameters is measured by ``benchmarks.fidelity``)."""
    arrays = _flatten(ilm)
    if float16:
        arrays = {k: (v.astype(np.float16) if k.startswith("params/")
                      and np.issubdtype(v.dtype, np.floating) else v)
                  for k, v in arrays.items()}
    if hash_int8:
        for k in [k for k in arrays if k.startswith("params/")
                  and k.rsplit("/", 1)[-1] in INT8_PARAMS]:
            arrays[k], arrays[_QSCALE + k[len("params/"):]] = quantize_int8(arrays[k])
    meta = {"format": "vrs_jax.ilm", "format_version": FORMAT_VERSION,
            "config": ilm.config.to_dict(), "image_names": list(ilm.image_names)}
    arrays[_META] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def save_ilm(path: str | Path, ilm: ILM, float16: bool = False, hash_int8: bool = False
             ) -> Path:
    """Write the ILM to ``path`` (.npz), atomically (see :func:`to_bytes`). Returns the path."""
    return fileio.write_bytes(path, to_bytes(ilm, float16, hash_int8))


def load_ilm(path: str | Path) -> ILM:
    """Read an ILM written by :func:`save_ilm`; VrsError for a missing, corrupt or
    other-version file."""
    p = Path(path)
    if not p.is_file():
        raise VrsError("ILM map file not found", p)
    return from_bytes(p.read_bytes(), p)


def upgrade_config(version: int, config: dict) -> dict:
    """A NeRF config dict written by an earlier ILM format ``version`` (a map of format 2
    stores the same one), completed to the current fields. Version 2 added cluster_method
    (every earlier map was clustered with K-means)."""
    return {"cluster_method": "kmeans", **config} if version == 1 else config


OLD_VERSIONS = (1,)


def from_bytes(raw: bytes, p: Path, upgrade: bool = False) -> ILM:
    """Inverse of :func:`to_bytes` (``p`` names the file in errors); ``upgrade`` also reads
    the earlier format versions (their config completed with the defaults of its new
    fields)."""
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise VrsError(f"corrupt or unreadable ILM map ({type(e).__name__})", p) from None
    if _META not in arrays:
        raise VrsError("not an ILM map (no header)", p)
    try:
        meta = json.loads(arrays.pop(_META).tobytes().decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise VrsError("corrupt ILM map header", p) from None
    if meta.get("format") != "vrs_jax.ilm":
        raise VrsError("not an ILM map", p)
    v = fileio.format_version(meta, p, "ILM map")
    if upgrade and v in OLD_VERSIONS:
        meta["config"] = upgrade_config(v, meta.get("config") or {})
    elif v not in READABLE_VERSIONS:
        raise VrsError(f"ILM map format version {v} is not supported "
                       f"(expected {FORMAT_VERSION}); retrain the map", p)
    scales = {k[len(_QSCALE):]: arrays.pop(k) for k in list(arrays) if k.startswith(_QSCALE)}
    cfg = NerfConfig.from_dict(meta["config"], p)
    try:
        flat = {k[len("params/"):]: v for k, v in arrays.items() if k.startswith("params/")}
        for k, sc in scales.items():  # int8 tables back to float32
            if k not in flat or flat[k].dtype != np.int8 or sc.shape != flat[k].shape[:-2]:
                raise VrsError(f"ILM map has a malformed int8 parameter {k!r}", p)
            flat[k] = dequantize_int8(flat[k], sc)
        unscaled = [k for k, v in flat.items() if v.dtype == np.int8]
        if unscaled:  # an int8 table without its scales: not a field we can read back
            raise VrsError(f"ILM map has a malformed int8 parameter {unscaled[0]!r} "
                           "(no scales)", p)
        params = traverse_util.unflatten_dict(
            {k: jnp.asarray(v, jnp.float32 if np.issubdtype(v.dtype, np.floating) else v.dtype)
             for k, v in flat.items()}, sep="/")
        fields = Field(params=params, center=jnp.asarray(arrays["center"]),
                       scale=jnp.asarray(arrays["scale"]),
                       background=jnp.asarray(arrays["background"]))
        ilm = ILM(fields=fields, cluster_centers=jnp.asarray(arrays["cluster_centers"]),
                  image_cluster=jnp.asarray(arrays["image_cluster"]),
                  membership=jnp.asarray(arrays["membership"]),
                  near=jnp.asarray(arrays["near"]), far=jnp.asarray(arrays["far"]),
                  image_names=tuple(meta["image_names"]), config=cfg)
    except KeyError as e:
        raise VrsError(f"ILM map lacks array {e}", p) from None
    _check_shapes(ilm, p)
    return ilm


def _check_shapes(ilm: ILM, p: Path) -> None:
    c = ilm.n_clusters
    expect = jax.eval_shape(lambda: init_params(jax.random.key(0), ilm.config))
    got = jax.tree.map(lambda x: tuple(x.shape[1:]), ilm.fields.params)
    want = jax.tree.map(lambda x: tuple(x.shape), expect)
    ok = jax.tree.structure(got) == jax.tree.structure(want) and all(
        a == b for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want), strict=True))
    lead = {x.shape[0] for x in jax.tree.leaves(ilm.fields)}
    if not ok or lead != {c}:
        raise VrsError("ILM map arrays do not match its config (corrupt file?)", p)


def map_bytes(path: str | Path) -> int:
    """Size on disk of a saved map."""
    return Path(path).stat().st_size


def ilm_summary(ilm: ILM) -> dict[str, Any]:
    return {"clusters": ilm.n_clusters, "images": len(ilm.image_names),
            "config": ilm.config.name,
            "params": int(sum(x.size for x in jax.tree.leaves(ilm.fields.params)))}
