"""Build a complete vrs-jax map (EGM + NeRF ILM) from any supported dataset or photo folder.

    python -m experiments.train --format F --root DIR --out MAPDIR [--config C]
        [--downscale N] [--query-every N] [--steps N] [--minutes M] [--set KEY=VALUE]
        [--egm-from MAPDIR]

The reference images (the dataset's training split, or all but every N-th image) are mapped:
SIFT keypoints, covisible pairs matched and verified, 3D points triangulated with the known
poses (pycolmap), keypoints linked to points kept per image, VLAD global descriptors, the
real-patch descriptors (for the real-patch mode). Then one Mip-NeRF per K-means cluster of
reference cameras is trained (orbax checkpoints; re-running resumes; a larger --steps continues
a finished map). ``--format images`` takes a folder of unposed photos and poses them with
pycolmap's incremental SfM first (work files in MAPDIR/sfm). Everything is written into --out.

Multi-process (``jax.distributed``, one process per host or GPU, the same --out on a shared
file system): run the same command once per process with ``--coordinator HOST0:PORT
--num-processes N --process-id I``; process 0 builds the EGM while the others wait for it,
then every process trains its shard of the clusters (use a multiple of N clusters) and
process 0 writes the map.
"""

from __future__ import annotations

import argparse

from vrs_jax import maps
from vrs_jax.cli.common import (
    HelpFormatter,
    add_distributed_args,
    add_scene_args,
    count_at_least,
    init_distributed,
    load_scene_from_args,
    positive_float,
    prog,
    record_run,
    scene_opts,
    start_run,
)
from vrs_jax.errors import cli_main
from vrs_jax.nerf.config import parse_overrides


def build_parser(fmt: str | None = None, default_config: str = "cpu-small",
                 description: str | None = None) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog(f"experiments.{'train' if fmt is None else 'train_' + fmt}"),
        description=description or __doc__.split("\n\n")[0],
        formatter_class=HelpFormatter)
    add_scene_args(p, fmt)
    p.add_argument("--out", required=True, help="map folder to write (created; resumable)")
    p.add_argument("--config", default=default_config, choices=sorted(maps.CONFIGS),
                   help="named map configuration (EGM and NeRF settings, stored by value)")
    p.add_argument("--steps", type=count_at_least(1), default=None,
                   help="NeRF training steps, also the lr schedule's length (default: the "
                        "config's; a larger value continues a finished map)")
    p.add_argument("--minutes", type=positive_float("minutes"), default=None,
                   help="wall-clock cap on this run's NeRF training (re-run to continue)")
    p.add_argument("--egm-from", default=None, metavar="MAPDIR",
                   help="take the EGM of this map (same dataset, split and EGM settings; any "
                        "NeRF) instead of building it: trains a NeRF of other settings into "
                        "--out without repeating features, matching and triangulation")
    p.add_argument("--clusters", type=count_at_least(1), default=None,
                   help="number of NeRF clusters (default: the config's)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a NeRF config field, repeatable (e.g. patch_ray_fraction=0 "
                        "trains on whole images only, as the paper)")
    add_distributed_args(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--verbose", action="store_true",
                   help="debug log lines, and COLMAP's log lines (SfM)")
    return p


def map_config(args: argparse.Namespace) -> maps.MapConfig:
    """The named config with the command line's NeRF overrides."""
    over = parse_overrides(args.set)
    if args.steps is not None:
        over["max_steps"] = args.steps
    if args.clusters is not None:
        over["n_clusters"] = args.clusters
    return maps.get_config(args.config, **over)


def run(args: argparse.Namespace, fmt: str | None = None, argv: list[str] | None = None) -> int:
    import contextlib
    import time
    from pathlib import Path

    from vrs_jax import fileio
    from vrs_jax.errors import VrsError

    start_run(args)
    t0 = time.perf_counter()
    cfg = map_config(args)
    out = Path(args.out)
    fileio.check_apart(out, [args.root])
    multi = init_distributed(args)  # before any JAX computation
    if multi and (fmt or getattr(args, "format", None)) == "images":
        raise VrsError("--format images poses the photos with SfM first, in one process: "
                       "build the map with one process (--steps 1), then continue its "
                       "training with a larger --steps and --num-processes")
    from vrs_jax.nerf import distributed

    primary = distributed.is_primary()
    # one run per map folder: process 0 holds the lock (the other processes of a
    # multi-process build train into the same folder by design)
    with fileio.folder_lock(out) if primary else contextlib.nullcontext():
        if primary:
            fileio.check_writable(out)  # before any work starts
        scene = load_scene_from_args(args, fmt, sfm_dir=out / "sfm")
        if multi:
            import jax

            print(f"process {jax.process_index()} of {jax.process_count()}: "
                  f"{len(jax.local_devices())} local / {len(jax.devices())} global device(s)")
        if primary:
            print(f"{scene.format} scene at {scene.root}: {int((~scene.is_query).sum())} "
                  f"reference and {int(scene.is_query.sum())} query images")
        if primary and args.egm_from and maps.seed_from(args.egm_from, out, scene, cfg,
                                                        scene_opts(args), log=print):
            print(f"EGM taken from {args.egm_from}")
        maps.build_map(scene, out, cfg, progress=not args.quiet, minutes=args.minutes,
                       source_options=scene_opts(args), primary=primary)
        if primary:
            record_run(out, args, cfg, {"total": time.perf_counter() - t0}, argv)
    return 0


@cli_main
def main(argv: list[str] | None = None) -> int:
    return run(build_parser().parse_args(argv), argv=argv)


if __name__ == "__main__":
    raise SystemExit(main())
