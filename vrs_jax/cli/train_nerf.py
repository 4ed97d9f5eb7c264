"""Train the implicit map (per-cluster Mip-NeRFs) on any supported dataset, render views.

    python -m experiments.train_nerf --format nerf --root /data/lego \\
        --query-every 8 --near 2 --far 6 --config cpu-small --minutes 10 --out runs/lego

Writes into --out only:
  checkpoints/      orbax checkpoints (atomic; re-running the command resumes from them)
  ilm.npz           the trained map (vrs_jax.nerf.ilm)
  renders/NAME.png  rendered | real, side by side, for the held-out views (or --views)
  metrics.json      config, training history, per-view PSNR / SSIM, timings

Multi-process / multi-host (JAX's own runtime, ``jax.distributed``): start the same command
once per process, all with the same --out on a shared file system, adding
``--coordinator HOST0:PORT --num-processes N --process-id I`` (I = 0..N-1; HOST0 runs
process 0). Each process trains its shard of the clusters (use a multiple of N clusters);
orbax writes the checkpoints from all processes; process 0 writes the map, renders, metrics.
"""

from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path

import numpy as np

from vrs_jax import fileio
from vrs_jax.cli.common import (
    RawHelpFormatter,
    add_distributed_args,
    add_scene_args,
    count_at_least,
    init_distributed,
    load_scene_from_args,
    positive_float,
    prog,
    record_run,
    start_run,
)
from vrs_jax.errors import VrsError, cli_main


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog("experiments.train_nerf"), description=__doc__,
                                formatter_class=RawHelpFormatter)
    add_scene_args(p)
    p.add_argument("--out", required=True, help="output folder (created; resumed if present)")
    p.add_argument("--config", default="cpu-small", help="NeRF config: paper, cpu-small, test")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a NerfConfig field, repeatable (e.g. --set lindisp=true)")
    p.add_argument("--clusters", type=count_at_least(1), default=None,
                   help="number of clusters (K-means)")
    p.add_argument("--steps", type=count_at_least(1), default=None,
                   help="total training steps")
    p.add_argument("--minutes", type=positive_float("minutes"), default=None,
                   help="wall-clock budget of this run (compilation included)")
    p.add_argument("--near", type=positive_float("near bound"), default=None,
                   help="near bound override (t = depth)")
    p.add_argument("--far", type=positive_float("far bound"), default=None,
                   help="far bound override")
    p.add_argument("--views", type=count_at_least(1), default=None, metavar="N",
                   help="render at most N held-out views (default: all; training views if "
                        "there are no held-out ones)")
    p.add_argument("--no-resume", action="store_true", help="ignore existing checkpoints")
    add_distributed_args(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--verbose", action="store_true", help="debug log lines")
    return p


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    start_run(args)
    multi = init_distributed(args)
    from vrs_jax.nerf import distributed

    # one run per output folder: process 0 holds the lock (the other processes of a
    # multi-process run train into the same folder by design)
    lock = (fileio.folder_lock(args.out) if distributed.is_primary()
            else contextlib.nullcontext())
    with lock:
        return train_into(args, argv, multi)


OWN_ENTRIES = ("checkpoints", "ilm.npz", "metrics.json", "renders")
"""What a train_nerf --out holds (besides its run records ``run*.json``)."""


def check_nerf_out(out: Path, root: str | None) -> None:
    """--out must be new, empty or an earlier train_nerf output (resumed): never the dataset,
    a folder holding it, a map folder (whose ilm.npz this run would replace) or any other
    folder with files of its own."""
    fileio.check_apart(out, [root])
    fileio.refuse_map_part(out)
    if out.is_dir():
        foreign = sorted(p.name for p in out.iterdir() if p.name not in OWN_ENTRIES
                         and not (p.name.startswith("run") and p.name.endswith(".json"))
                         and not p.name.endswith(".tmp"))
        if foreign:
            raise VrsError(f"folder holds files that are not a train_nerf output "
                           f"({', '.join(foreign[:3])}{' ...' if len(foreign) > 3 else ''}); "
                           "choose a new or empty --out", out)


def train_into(args: argparse.Namespace, argv: list[str] | None, multi: bool) -> int:
    """Train into ``args.out`` (checkpoints, ilm.npz, renders, metrics.json); 0 on success."""
    from vrs_jax.nerf import distributed, render
    from vrs_jax.nerf import ilm as ilm_lib
    from vrs_jax.nerf import train as T
    from vrs_jax.nerf.config import get_config, parse_overrides

    overrides = parse_overrides(args.set)
    if args.clusters is not None:
        overrides["n_clusters"] = args.clusters
    cfg = get_config(args.config, **overrides)
    out = Path(args.out)
    check_nerf_out(out, args.root)
    if args.no_resume and (out / "checkpoints").exists():
        raise VrsError("--no-resume given but the folder holds checkpoints; use another --out",
                       out / "checkpoints")
    fileio.check_writable(out)  # before any work starts
    scene = load_scene_from_args(args)
    prep = T.prepare(scene, cfg, near=args.near, far=args.far)
    primary = distributed.is_primary()
    if multi:
        import jax

        print(f"process {jax.process_index()} of {jax.process_count()}: "
              f"{len(jax.local_devices())} local / {len(jax.devices())} global device(s)")
    if primary:
        print(f"{len(prep.refs)} training / {len(prep.held_out)} held-out images, "
          f"{cfg.n_clusters} cluster(s), near/far {float(prep.near.min()):.3g}.."
              f"{float(prep.far.max()):.3g}, config {cfg.name}")
    res = T.train(prep, out, steps=args.steps, minutes=args.minutes,
                  resume=not args.no_resume, progress=not args.quiet,
                  log=(lambda _: None) if args.quiet else None)
    if not primary:  # the map, renders and reports are process 0's
        return 0
    ilm_path = ilm_lib.save_ilm(out / "ilm.npz", res.ilm)

    views, images, near, far = prep.held_out, prep.held_images, prep.held_near, prep.held_far
    if len(views) == 0:  # no held-out images: show training views instead
        k = min(len(prep.refs), args.views or 4)
        idx = np.linspace(0, len(prep.refs) - 1, k).round().astype(int)
        from vrs_jax.nerf.data import load_images
        views = prep.refs.subset(idx)
        images, near, far = load_images(views, prep.background), prep.near[idx], prep.far[idx]
    elif args.views is not None:
        views = views.subset(np.arange(min(args.views, len(views))))
        images, near, far = images[: len(views)], near[: len(views)], far[: len(views)]
    t0 = time.perf_counter()
    rows = render.evaluate_views(res.ilm, views, images, near, far, out / "renders",
                                 progress=not args.quiet)
    render_s = time.perf_counter() - t0
    psnr = float(np.mean([r["psnr"] for r in rows]))
    ssim = float(np.mean([r["ssim"] for r in rows]))
    metrics = {"config": cfg.to_dict(), "steps": int(res.state.step),
               "steps_per_s": res.steps_per_s, "train_s": res.seconds,
               "compile_s": res.compile_s, "render_s": render_s, "mean_psnr": psnr,
               "mean_ssim": ssim, "held_out": len(prep.held_out) > 0, "views": rows,
               "history": res.history, "ilm_bytes": ilm_lib.map_bytes(ilm_path)}
    fileio.write_json(out / "metrics.json", metrics)
    record_run(out, args, cfg, {"train": res.seconds, "compile": res.compile_s,
                                "render": render_s}, argv)
    kind = "held-out" if len(prep.held_out) else "training"
    print(f"{int(res.state.step)} steps ({res.steps_per_s:.2f} steps/s); {kind} views: "
          f"PSNR {psnr:.2f} dB, SSIM {ssim:.3f} over {len(rows)} view(s); "
          f"renders in {out / 'renders'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
