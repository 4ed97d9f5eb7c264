"""Build the explicit geometric map (EGM) of a dataset's reference images, without the NeRF.

    python -m experiments.build_egm --format F --root DIR --out MAPDIR [--config C]
        [--export-colmap DIR] [--binary]

Writes a map folder (see vrs_jax.maps.map) holding the EGM and the real-patch descriptors but
no trained NeRF yet: ``experiments.localize --mode real`` localizes with it as it is (real
patches need no NeRF), and ``experiments.train`` with the same --out and settings continues it
into a complete map. ``--format images`` takes a folder of unposed photos: pycolmap's incremental
SfM recovers the poses first (work files in MAPDIR/sfm). Re-running with the same settings
skips the build; a folder holding another map is refused.
"""

from __future__ import annotations

import argparse
import time

from vrs_jax import fileio, maps
from vrs_jax.cli.common import (
    HelpFormatter,
    add_scene_args,
    load_scene_from_args,
    prog,
    record_run,
    scene_opts,
    start_run,
)
from vrs_jax.egm.colmap import export_colmap
from vrs_jax.errors import cli_main


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog("experiments.build_egm"),
        description="Triangulate the reference images of a dataset with their known poses "
                    "(SfM first for --format images) and write the explicit geometric map: "
                    "3D points, per image its pose, intrinsics and the keypoints linked to "
                    "3D points, VLAD global descriptors and the real-patch descriptors.",
        formatter_class=HelpFormatter)
    add_scene_args(p)
    p.add_argument("--out", required=True, help="map folder to write")
    p.add_argument("--config", default="cpu-small", choices=sorted(maps.CONFIGS),
                   help="named map configuration")
    p.add_argument("--export-colmap", metavar="DIR",
                   help="also write the map as a COLMAP model (cameras, images, points3D)")
    p.add_argument("--binary", action="store_true", help="COLMAP export in binary (.bin)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a COLMAP model already in --export-colmap DIR")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--verbose", action="store_true",
                   help="debug log lines, and COLMAP's log lines")
    return p


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    start_run(args)
    t0 = time.perf_counter()
    cfg = maps.get_config(args.config)
    fileio.check_apart(args.out, [args.root])
    if args.export_colmap:  # the COLMAP export never replaces the dataset or the map
        fileio.check_apart(args.export_colmap, [args.root, args.out])
        fileio.refuse_map_part(args.export_colmap)
    with fileio.folder_lock(args.out):  # one run per map folder
        out = fileio.check_writable(args.out)
        scene = load_scene_from_args(args, sfm_dir=out / "sfm")
        maps.build_map(scene, out, cfg, progress=not args.quiet, source_options=scene_opts(args),
                       train_nerf=False)
        m = maps.load_map(out, require_ilm=False)
        print(f"EGM written to {out}")
        if args.export_colmap:
            d = export_colmap(m.egm, args.export_colmap, text=not args.binary,
                              overwrite=args.overwrite)
            print(f"COLMAP model written to {d}")
        record_run(out, args, cfg, {"total": time.perf_counter() - t0}, argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
