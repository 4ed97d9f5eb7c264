"""The Map pytree and its folder on disk (saved and loaded as one unit).

A map folder holds::

    MAPDIR/map.json         kind, format version, the MapConfig's VALUES, where the map came
                            from (dataset format, root, reader options, the query images held
                            out), image names, a SHA-256 and byte count per data file, stats
    MAPDIR/egm.npz          the EGM arrays (3D points, poses, intrinsics, keypoints linked to
                            points, global descriptors and vocabulary), deflated; no local
                            descriptors. Quantised (vrs_jax.egm.map, "arrays"): keypoint x, y
                            as int8 steps of 1/16 px from the linked point's projection, log2
                            scale and angle as uint8, point indices in the fewest bytes, 3D
                            points as 16-32-bit fixed point, global descriptors as int8; all
                            float32 again in memory; and the MapConfig it was built with (JSON),
                            against which map.json's config is checked on loading
    MAPDIR/descriptors.npz  the real-patch descriptors of the EGM keypoints (float16, as hloc
                            stores them): what the real-patch mode matches against; the VRS
                            map (rendered patches) never reads it
    MAPDIR/ilm.npz          the NeRFs, stacked per cluster, with each image's cluster (weights
                            as float16, float32 in memory)
    MAPDIR/nerf/            orbax training checkpoints (resume only; not part of the map)

Loading checks everything before returning: kind, format version, every config field (an
unknown, missing or ill-typed field fails), each data file's checksum, the arrays' shapes
against each other and the config, and the ILM against the EGM (same images, same NeRF
config). Anything off is one :class:`~vrs_jax.errors.VrsError` line naming the file.
"""

from __future__ import annotations

import dataclasses
import io
import json
import zipfile
from pathlib import Path
from typing import Any

import flax.struct
import jax
import numpy as np

from vrs_jax import configio, fileio
from vrs_jax.egm import map as egm_map
from vrs_jax.egm.map import EGM
from vrs_jax.errors import VrsError
from vrs_jax.maps.config import MapConfig
from vrs_jax.nerf import ilm as ilm_lib
from vrs_jax.nerf.ilm import ILM

KIND = "vrs_jax.map"
# 3: quantised storage (vrs_jax.egm.map: keypoints, points, global descriptors; float16 NeRF)
# 4: NerfConfig gained cluster_method (K-means or a uniform grid of the cameras)
FORMAT_VERSION = 4
META = "map.json"
EGM_FILE = "egm.npz"
DESC_FILE = "descriptors.npz"
ILM_FILE = "ilm.npz"
# egm.npz members deflated (the quantised keypoint residuals, scales and angles compress).
EGM_COMPRESSED = True
# NeRF weights stored as float16 (read back as float32): renders differ from float32 weights'
# by far less than the field's own error (README, "Map size").
NERF_FLOAT16 = True
# The hash tables (most of a NeRF's bytes: cpu-small's 16 x 2^15 x 2 entries take 1.05 of its
# 1.08 MB) stored as int8, one scale per cluster and level (vrs_jax.nerf.ilm.quantize_int8):
# the ILM at about half its float16 size, patch fidelity and recall unchanged on the six
# benchmark maps (README, "The NeRF at half its bytes").
NERF_HASH_INT8 = True


@dataclasses.dataclass(frozen=True)
class MapSource:
    """Where a map's images came from, and its split (the held-out query images).

    format: dataset format (``vrs_jax.data.readers``); root: dataset folder; options: the
    reader options as (key, value-as-text) pairs; query_names: images held out as queries.
    """

    format: str = ""
    root: str = ""
    options: tuple[tuple[str, str], ...] = ()
    query_names: tuple[str, ...] = ()


@flax.struct.dataclass
class Map:
    """One map: EGM + ILM + its configuration (by value) + where it came from.

    egm: the explicit geometric map; ``egm.local_desc`` [N, K_max, D] holds the real-patch
      descriptors when the map keeps them (real-patch mode), else None.
    ilm: the stacked per-cluster NeRFs (None only while a map is being built); its
      ``image_cluster`` [N] is the one record of each reference image's cluster.
    config: :class:`~vrs_jax.maps.config.MapConfig` (static).
    source: :class:`MapSource` (static).
    """

    egm: EGM
    ilm: ILM | None
    config: MapConfig = flax.struct.field(pytree_node=False)
    source: MapSource = flax.struct.field(pytree_node=False, default=MapSource())

    @property
    def names(self) -> tuple[str, ...]:
        return self.egm.names

    @property
    def has_descriptors(self) -> bool:
        """Whether real-patch mode can run (the map keeps real-patch descriptors)."""
        return self.egm.local_desc is not None

    @property
    def cluster(self):
        """[N] int32 NeRF cluster of each reference image."""
        if self.ilm is None:
            raise VrsError("this map has no trained NeRF yet")
        return self.ilm.image_cluster

    def without_descriptors(self) -> Map:
        """The VRS map proper: the same map without the real-patch descriptors."""
        return self.replace(egm=self.egm.without_local_descriptors())


# ----------------------------------------------------------------------------- save


def _npz(arrays: dict[str, np.ndarray], compressed: bool = False) -> bytes:
    buf = io.BytesIO()
    if compressed:
        np.savez_compressed(buf, **arrays)  # into memory; fileio-exempt (fileio writes them)
    else:
        np.savez(buf, **arrays)
    return buf.getvalue()


MAP_FILES = (META, EGM_FILE, DESC_FILE, ILM_FILE)
# egm.npz member holding the MapConfig the map was built with (JSON, as uint8 bytes): a
# hand-edited config field in map.json that keeps every array's shape (a patch sample count,
# the descriptor's blur, a keypoint threshold) would otherwise load and localize silently
# wrong. Maps written before it existed lack it and load as before.
CONFIG_MEMBER = "map_config_json"


def _config_json(cfg: dict) -> str:
    """Canonical JSON text of a config dict (key order and tuple/list spelling removed)."""
    return json.dumps(cfg, sort_keys=True, separators=(",", ":"))


def _first_difference(a: Any, b: Any, path: str = "") -> tuple[str, Any, Any]:
    """(dotted field path, value in a, value in b) of the first place two JSON values differ."""
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if a.get(k, "<absent>") != b.get(k, "<absent>"):
                return _first_difference(a.get(k, "<absent>"), b.get(k, "<absent>"),
                                         f"{path}.{k}" if path else k)
    return path or "config", a, b


def _check_config_member(arrays: dict[str, np.ndarray], config: dict, p: Path) -> None:
    """VrsError unless map.json's ``config`` is the one recorded in egm.npz at build time."""
    raw = arrays.pop(CONFIG_MEMBER, None)
    if raw is None:
        return
    try:
        built = json.loads(np.asarray(raw, np.uint8).tobytes().decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise VrsError("the map's recorded build config is unreadable (corrupt file?)",
                       p.parent / EGM_FILE) from None
    now = json.loads(_config_json(config))
    if now != built:
        field, edited, was = _first_difference(now, built)
        raise VrsError(f"map.json's config was changed after the map was built ({field}: "
                       f"{edited!r} in map.json, {was!r} in the built map): restore it or "
                       "rebuild the map", p)


def save_map(m: Map, folder: str | Path, stats: dict | None = None, measure: bool = False,
             provenance: dict | None = None) -> Path:
    """Write ``m`` into ``folder`` as one transaction (:func:`vrs_jax.fileio.staged_folder`):
    the map files go into a fresh sibling folder, the folder's other entries (NeRF
    checkpoints, SfM work files, run records) are hard-linked in, and the new folder replaces
    the old one only when complete, so a failure leaves the earlier map as it was.

    Args:
      stats: build statistics recorded in ``map.json``.
      measure: also record the map's own sizes (:func:`map_bytes`) as ``stats["map_bytes"]``.
      provenance: what the map was built from (:func:`vrs_jax.maps.build.provenance`); None
        keeps the folder's earlier record.
    Returns the folder.
    """
    d = Path(folder)
    if provenance is None and (d / META).is_file():
        provenance = fileio.read_json(d / META, "map metadata").get("provenance")
    keep = [p.name for p in d.iterdir() if p.name not in MAP_FILES] if d.is_dir() else []
    with fileio.staged_folder(d, carry=keep) as tmp:
        blobs = _write_blobs(m, tmp)
        meta = {
            "kind": KIND,
            "format_version": FORMAT_VERSION,
            "config": configio.to_dict(m.config),
            "source": configio.to_dict(m.source),
            "provenance": provenance or {},
            "names": list(m.egm.names),
            "k_max": m.egm.k_max,
            "files": {name: {"sha256": fileio.sha256(b), "bytes": len(b)}
                      for name, b in blobs.items()},
            "stats": dict(stats or {}),
        }
        fileio.write_json(tmp / META, meta)
        if measure:
            meta["stats"]["map_bytes"] = map_bytes(tmp)
            fileio.write_json(tmp / META, meta)
    return d


def _write_blobs(m: Map, d: Path) -> dict[str, bytes]:
    """Write the map's data files into ``d`` (each atomically). Returns {name: bytes}."""
    arrays = dict(egm_map.to_arrays(m.egm))
    arrays[CONFIG_MEMBER] = np.frombuffer(
        _config_json(configio.to_dict(m.config)).encode("utf-8"), np.uint8)
    blobs = {EGM_FILE: _npz(arrays, compressed=EGM_COMPRESSED)}
    if m.has_descriptors:
        blobs[DESC_FILE] = _npz(egm_map.descriptor_arrays(m.egm))
    if m.ilm is not None:
        if tuple(m.ilm.image_names) != tuple(m.egm.names):
            raise VrsError("the NeRF map and the EGM list different reference images", d)
        if m.ilm.config != m.config.nerf:
            raise VrsError("the NeRF was trained with another config than the map's", d)
        blobs[ILM_FILE] = ilm_lib.to_bytes(m.ilm, float16=NERF_FLOAT16,
                                             hash_int8=NERF_HASH_INT8)
    for name, data in blobs.items():
        fileio.write_bytes(d / name, data)
    return blobs


# ----------------------------------------------------------------------------- load


def read_meta(folder: str | Path) -> dict[str, Any]:
    """``map.json`` of a map folder, checked for kind and format version."""
    d = Path(folder)
    if not d.is_dir():
        raise VrsError("map folder not found" if not d.exists() else "map path is not a folder",
                       d)
    p = d / META
    if not p.is_file():
        raise VrsError("not a vrs-jax map folder (no map.json)", d)
    meta = fileio.read_json(p, "map metadata")
    if not isinstance(meta, dict) or meta.get("kind") != KIND:
        raise VrsError("not a vrs-jax map", p)
    v = fileio.format_version(meta, p)
    if v != FORMAT_VERSION:
        raise VrsError(f"map format version {v}; this vrs-jax reads version {FORMAT_VERSION}: "
                       "rebuild the map", p)
    for key in ("config", "source", "names", "k_max", "files"):
        if key not in meta:
            raise VrsError(f"map metadata lacks {key!r}", p)
    # the kinds of the top-level fields (a hand-edited file: one line, not a TypeError)
    names = meta["names"]
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise VrsError("map metadata 'names' must be a list of image names", p)
    k_max = meta["k_max"]
    if isinstance(k_max, bool) or not isinstance(k_max, int) or k_max < 1:
        raise VrsError(f"map metadata 'k_max' must be an integer >= 1, got {k_max!r}", p)
    files = meta["files"]
    if not isinstance(files, dict) or not all(
            isinstance(r, dict) and isinstance(r.get("sha256"), str)
            and isinstance(r.get("bytes"), int) for r in files.values()):
        raise VrsError("map metadata 'files' must map each file name to its sha256 and bytes",
                       p)
    stats = meta.get("stats", {})
    if not isinstance(stats, dict) or not all(isinstance(stats.get(k, {}), dict)
                                              for k in ("egm", "ilm")):
        raise VrsError("map metadata 'stats' must be a mapping (its 'egm' and 'ilm' too)", p)
    steps = stats.get("ilm", {}).get("steps")
    if steps is not None and (isinstance(steps, bool) or not isinstance(steps, int)):
        raise VrsError(f"map metadata 'stats.ilm.steps' must be an integer, got {steps!r}", p)
    return meta


def _read_checked(d: Path, name: str, meta: dict) -> bytes:
    p = d / name
    rec = meta["files"][name]
    if not p.is_file():
        raise VrsError("map file missing", p)
    raw = p.read_bytes()
    if len(raw) != rec.get("bytes") or fileio.sha256(raw) != rec.get("sha256"):
        raise VrsError("map file does not match map.json (corrupt, truncated or from another "
                       "map)", p)
    return raw


def _npz_arrays(raw: bytes, p: Path) -> dict[str, np.ndarray]:
    try:
        with np.load(io.BytesIO(raw), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as e:
        raise VrsError(f"corrupt map arrays: {e}", p) from None


def load_map(folder: str | Path, descriptors: bool = True, require_ilm: bool = True) -> Map:
    """Read and validate a map folder written by :func:`save_map`.

    Args:
      descriptors: also load the real-patch descriptors when the map has them.
      require_ilm: fail unless the NeRF is trained (a map still being built has none).
    """
    d = Path(folder)
    meta = read_meta(d)
    p = d / META
    cfg = configio.from_dict(MapConfig, meta["config"], p)
    source = configio.from_dict(MapSource, meta["source"], p)
    names = tuple(meta["names"])
    files = meta["files"]
    if EGM_FILE not in files:
        raise VrsError("map metadata lists no EGM", p)
    arrays = _npz_arrays(_read_checked(d, EGM_FILE, meta), d / EGM_FILE)
    _check_config_member(arrays, meta["config"], p)
    desc = None
    if descriptors and DESC_FILE in files:
        desc = _npz_arrays(_read_checked(d, DESC_FILE, meta), d / DESC_FILE).get("local_desc")
        if desc is None or desc.ndim != 2 or desc.shape[1] != cfg.features.descriptor.dim:
            raise VrsError("real-patch descriptors do not match the map's descriptor config",
                           d / DESC_FILE)
    egm = egm_map.from_arrays(arrays, names, int(meta["k_max"]), d / EGM_FILE, desc)
    ilm = None
    if ILM_FILE in files:
        ilm = ilm_lib.from_bytes(_read_checked(d, ILM_FILE, meta), d / ILM_FILE)
        if tuple(ilm.image_names) != names:
            raise VrsError("the NeRF map lists other reference images than the EGM", d / ILM_FILE)
        if ilm.config != cfg.nerf:
            raise VrsError("the NeRF was trained with another config than map.json records",
                           d / ILM_FILE)
        _check_trained(ilm, meta, d / ILM_FILE)
    elif require_ilm:
        raise VrsError("the map has no trained NeRF yet: finish its training run "
                       "(experiments.train with the same --out), or localize with real "
                       "patches (--mode real), which need none", d)
    return Map(egm=egm, ilm=ilm, config=cfg, source=source)


def load_map_for(folder: str | Path, source: str) -> Map:
    """:func:`load_map` for a localization mode: ``"render"`` needs the trained NeRF; any
    other (``"real"``, its alias ``"gt"``) loads the real-patch descriptors and needs no NeRF
    (an EGM-only map will do)."""
    return load_map(folder, descriptors=source != "render", require_ilm=source == "render")


def _check_trained(ilm: ILM, meta: dict, p: Path) -> None:
    """VrsError unless the NeRF trained (``stats.ilm.steps`` > 0 where recorded) to finite
    parameters."""
    steps = (meta.get("stats") or {}).get("ilm", {}).get("steps")
    if steps is not None and steps <= 0:
        raise VrsError("the NeRF was never trained (0 steps): rebuild the map with --steps "
                       ">= 1", p)
    if not all(np.all(np.isfinite(np.asarray(x))) for x in jax.tree.leaves(ilm.fields.params)):
        raise VrsError("the NeRF parameters hold non-finite values (a diverged training "
                       "run): rebuild the map with a lower lr_init", p)


def read_stats(folder: str | Path) -> dict[str, Any]:
    """The build statistics recorded in a map's ``map.json``."""
    return read_meta(folder).get("stats", {})


# ----------------------------------------------------------------------------- size


def map_bytes(folder: str | Path) -> dict[str, Any]:
    """Bytes on disk of what localization loads, by map variant and part.

    Returns dict with ``vrs`` (map.json + egm.npz + ilm.npz: rendered-patch mode), ``real``
    (map.json + egm.npz + descriptors.npz: real-patch mode), ``metadata``, ``egm``,
    ``ilm``, ``descriptors`` totals, and ``egm_parts`` (egm.npz by part, see
    :data:`vrs_jax.egm.map.PARTS`). Also ``descriptors_uint8``: what the descriptors would take
    at one byte per dimension (as COLMAP stores SIFT), for the comparison.
    """
    d = Path(folder)
    meta = read_meta(d)
    size = {name: rec["bytes"] for name, rec in meta["files"].items()}
    js = (d / META).stat().st_size
    egm_b, ilm_b, desc_b = size.get(EGM_FILE, 0), size.get(ILM_FILE, 0), size.get(DESC_FILE, 0)
    raw = _read_checked(d, EGM_FILE, meta)
    counts = _npz_arrays(raw, d / EGM_FILE).get("kp_counts")
    if counts is None:
        raise VrsError("map arrays lack ['kp_counts']", d / EGM_FILE)
    n_kp = int(np.sum(counts))
    dim = configio.from_dict(MapConfig, meta["config"], d / META).features.descriptor.dim
    return {"vrs": js + egm_b + ilm_b, "real": js + egm_b + desc_b, "metadata": js,
            "egm": egm_b, "ilm": ilm_b, "descriptors": desc_b,
            "descriptors_uint8": n_kp * dim,
            "egm_parts": egm_map.npz_parts(raw)}
