"""Rewrite a format-2 map folder (float32 keypoints and points, float32 NeRF weights) in the
current format, without rebuilding it:

    python -m vrs_jax.maps.upgrade OLD_MAP_DIR NEW_MAP_DIR

The arrays are read as format 2 stored them (checksums checked), assembled into a Map and
saved with :func:`vrs_jax.maps.save_map` (quantised, see :mod:`vrs_jax.egm.map`). The NeRF
training checkpoints (``nerf/``) are not copied: the new folder localizes but does not resume
training.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from vrs_jax import configio, fileio
from vrs_jax.egm import map as egm_map
from vrs_jax.egm.retrieval import Vocabulary
from vrs_jax.errors import VrsError, cli_main
from vrs_jax.maps import map as map_io
from vrs_jax.maps.config import MapConfig
from vrs_jax.nerf import ilm as ilm_lib

OLD_VERSION = 2
_NEED = ("points3d", "R", "t", "K", "dist", "sizes", "kp_counts", "keypoints", "point_idx",
         "global_desc", "vocab_centers", "vocab_power")


def load_format2(folder: str | Path) -> tuple[map_io.Map, dict]:
    """A format-2 map folder as a Map (float32 in memory) and its map.json."""
    d = Path(folder)
    p = d / map_io.META
    if not p.is_file():
        raise VrsError("not a vrs-jax map folder (no map.json)", d)
    meta = fileio.read_json(p, "map metadata")
    if not isinstance(meta, dict) or meta.get("kind") != map_io.KIND:
        raise VrsError("not a vrs-jax map", p)
    v = fileio.format_version(meta, p)
    if v != OLD_VERSION:
        raise VrsError(f"map format version {v}; this upgrades "
                       f"version {OLD_VERSION}", p)
    files = meta.get("files", {})
    for name in (map_io.EGM_FILE, map_io.ILM_FILE):
        if name not in files:
            raise VrsError(f"map metadata lists no {name}", p)
    a = map_io._npz_arrays(map_io._read_checked(d, map_io.EGM_FILE, meta), d / map_io.EGM_FILE)
    missing = [k for k in _NEED if k not in a]
    if missing:
        raise VrsError(f"map arrays lack {missing}", d / map_io.EGM_FILE)
    counts = a["kp_counts"].astype(np.int64)
    total = int(counts.sum())
    if a["keypoints"].shape != (total, 4) or a["point_idx"].shape != (total,):
        raise VrsError("inconsistent map: keypoints/point_idx do not match the counts",
                       d / map_io.EGM_FILE)
    desc = None
    if map_io.DESC_FILE in files:
        desc = map_io._npz_arrays(map_io._read_checked(d, map_io.DESC_FILE, meta),
                                  d / map_io.DESC_FILE).get("local_desc")
        if desc is None or desc.shape[0] != total:
            raise VrsError("real-patch descriptors do not match the keypoints",
                           d / map_io.DESC_FILE)
    splits = np.cumsum(counts)[:-1]
    vocab = Vocabulary(centers=jnp.asarray(a["vocab_centers"], jnp.float32),
                       pca_mean=jnp.asarray(a["pca_mean"]) if "pca_mean" in a else None,
                       pca_proj=jnp.asarray(a["pca_proj"]) if "pca_proj" in a else None,
                       power=float(a["vocab_power"]))
    egm = egm_map.make_egm(
        a["points3d"], a["R"], a["t"], a["K"], a["dist"], a["sizes"],
        np.split(a["keypoints"], splits), np.split(a["point_idx"], splits),
        a["global_desc"].astype(np.float32), vocab, tuple(meta["names"]),
        k_max=int(meta["k_max"]),
        local_desc=None if desc is None else np.split(desc.astype(np.float32), splits))
    ilm = ilm_lib.from_bytes(map_io._read_checked(d, map_io.ILM_FILE, meta),
                             d / map_io.ILM_FILE, upgrade=True)
    conf = meta["config"]
    if isinstance(conf, dict) and isinstance(conf.get("nerf"), dict):
        conf = {**conf, "nerf": ilm_lib.upgrade_config(1, conf["nerf"])}  # format 2 = ILM v1
    cfg = configio.from_dict(MapConfig, conf, p)
    src = configio.from_dict(map_io.MapSource, meta["source"], p)
    return map_io.Map(egm=egm, ilm=ilm, config=cfg, source=src), meta


def upgrade_map(old: str | Path, new: str | Path) -> Path:
    """Write the format-2 map ``old`` into the folder ``new`` in the current format."""
    if Path(new).resolve() == Path(old).resolve():
        raise VrsError("write the upgraded map into another folder", new)
    m, meta = load_format2(old)
    return map_io.save_map(m, new, stats=meta.get("stats") or {})


@cli_main
def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m vrs_jax.maps.upgrade", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("old")
    p.add_argument("new")
    args = p.parse_args(argv)
    out = upgrade_map(args.old, args.new)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
