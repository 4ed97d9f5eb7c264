"""Build the explicit geometric map (EGM) of a dataset's reference images.

    python -m experiments.build_egm --format F --root DIR --out MAPDIR [--baseline]
        [--export-colmap DIR] [--config C] [--overwrite]

Writes MAPDIR/egm.npz + MAPDIR/egm.json (the map, see vrs_jax.egm.map) and MAPDIR/stats.json
(points, mean track length, median reprojection error, bytes by part for this map and for the
other variant -- VRS map without local descriptors vs the baseline map with them -- and
timings). ``--format images`` takes a folder of unposed photos: pycolmap's incremental SfM
recovers the poses first (work files in MAPDIR/sfm).

Re-running with the same inputs and settings skips the build (``--overwrite`` rebuilds); a
MAPDIR holding a different map is never overwritten without ``--overwrite``.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
from pathlib import Path

from vrs_jax.data.readers import FORMATS, load_scene
from vrs_jax.egm import build, sfm
from vrs_jax.egm.colmap import export_colmap
from vrs_jax.egm.map import (
    JSON_NAME,
    load_egm,
    map_bytes,
    read_metadata,
    save_egm,
)
from vrs_jax.errors import VrsError, cli_main

STATS_NAME = "stats.json"


def _positive(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid integer {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {v}")
    return v


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m experiments.build_egm",
        description="Triangulate the reference images of a dataset with their known poses "
                    "(SfM first for --format images) and write the explicit geometric map: "
                    "3D points, per image its pose, intrinsics and the keypoints linked to "
                    "3D points, and VLAD global descriptors.")
    p.add_argument("--format", required=True, choices=(*FORMATS, "images"),
                   help="dataset format (see vrs_jax.data.readers); 'images' = a folder of "
                        "unposed photos, posed by incremental SfM")
    p.add_argument("--root", required=True, help="dataset root folder")
    p.add_argument("--out", required=True, help="map folder to write (egm.npz, egm.json, "
                   "stats.json)")
    p.add_argument("--config", default="paper", choices=sorted(build.CONFIGS),
                   help="named EGMConfig (default: paper)")
    p.add_argument("--baseline", action="store_true",
                   help="keep the local descriptors of the kept keypoints (the hierarchical "
                        "'GT patches' baseline map)")
    p.add_argument("--export-colmap", metavar="DIR",
                   help="also write the map as a COLMAP model (cameras, images, points3D)")
    p.add_argument("--binary", action="store_true", help="COLMAP export in binary (.bin)")
    p.add_argument("--query-every", type=_positive, metavar="N",
                   help="hold out every N-th image as a query (formats without a split)")
    p.add_argument("--downscale", type=_positive, metavar="N",
                   help="read images at 1/N of their size")
    p.add_argument("--overwrite", action="store_true",
                   help="rebuild even if MAPDIR holds a map (of these or other settings)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--verbose", action="store_true", help="show COLMAP's log lines")
    return p


def build_key(args: argparse.Namespace, cfg: build.EGMConfig) -> dict:
    """What identifies a map: inputs and the full configuration (hashed)."""
    return {
        "format": args.format,
        "root": str(Path(args.root).resolve()),
        "config": cfg.name,
        "config_sha256": hashlib.sha256(repr(cfg).encode()).hexdigest()[:16],
        "baseline": bool(args.baseline),
        "query_every": args.query_every,
        "downscale": args.downscale,
    }


def _write_json(path: Path, obj) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=1) + "\n")
    os.replace(tmp, path)


def _existing(out: Path, key: dict, overwrite: bool) -> bool:
    """True if ``out`` already holds this map; VrsError if it holds another one."""
    if overwrite or not (out / JSON_NAME).exists():
        return False
    try:
        meta = read_metadata(out)
    except VrsError as e:
        raise VrsError(f"{e}; pass --overwrite to replace it", out) from None
    old = meta.get("info", {}).get("build_key")
    if old == key:
        return True
    what = "unknown settings" if not isinstance(old, dict) else (
        f"format {old.get('format')}, root {old.get('root')}, config {old.get('config')}, "
        f"baseline {old.get('baseline')}")
    raise VrsError(f"holds a different map ({what}); pass --overwrite or choose another --out",
                   out)


def load_input_scene(args: argparse.Namespace, out: Path):
    """The Scene to map (SfM for unposed image folders)."""
    if args.format == "images":
        if args.query_every or args.downscale:
            raise VrsError("--query-every/--downscale do not apply to --format images")
        return sfm.scene_from_images(args.root, out / "sfm", overwrite=args.overwrite,
                                     verbose=args.verbose)
    opts = {}
    if args.query_every:
        opts["query_every"] = args.query_every
    if args.downscale:
        opts["downscale"] = args.downscale
    return load_scene(args.format, args.root, **opts)


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    cfg = build.get_config(args.config)
    if args.baseline:
        cfg = dataclasses.replace(cfg, baseline=True)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise VrsError("--out exists and is not a folder", out)
    key = build_key(args, cfg)
    if _existing(out, key, args.overwrite):
        egm = load_egm(out)
        print(f"{out} already holds this map; skipping the build (--overwrite to rebuild)")
        stats_path = out / STATS_NAME
        if stats_path.is_file():
            print(build.format_stats(json.loads(stats_path.read_text())))
    else:
        scene = load_input_scene(args, out)
        egm, stats = build.build_egm(scene, cfg, progress=not args.quiet, verbose=args.verbose)
        out.mkdir(parents=True, exist_ok=True)
        save_egm(egm, out, info={"build_key": key})
        stats["bytes"] = map_bytes(out)  # exact on-disk figures of the files just written
        stats["build_key"] = key
        _write_json(out / STATS_NAME, stats)
        print(build.format_stats(stats))
        print(f"map written to {out}")
    if args.export_colmap:
        d = export_colmap(egm, args.export_colmap, text=not args.binary)
        print(f"COLMAP model written to {d}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
