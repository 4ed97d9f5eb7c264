"""NeRF benchmark: train each config on a wall-clock budget, then measure it.

    python -m benchmarks.nerf --data /data/lego --format nerf \\
        --near 2 --far 6 --minutes 10 --config cpu-small --json runs/nerf_lego.json

For each config (default: paper and cpu-small) it reports
  - training steps/s (after compilation; evaluation excluded) and the steps reached,
  - rendering rays/s and MLP evaluations/s (a full held-out view, jitted, after warm-up),
  - PSNR / SSIM on the held-out views (every --hold-out-th frame; full views; a config too
    slow to render them within --eval-minutes is scored on a pixel subset: PSNR only).
The budget --minutes covers everything of the training run: compilation, a 10-step
calibration that sets the lr schedule's horizon (max_steps) to the number of steps the
budget allows, and the training itself. Prints a table and writes JSON (machine, versions,
configs, results).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np

from benchmarks import common
from benchmarks.common import environment
from vrs_jax import fileio
from vrs_jax.errors import VrsError, cli_main


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.nerf", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", required=True, help="dataset root folder")
    p.add_argument("--format", required=True, dest="fmt",
                   help="dataset format: 7scenes, cambridge, aachen, nerf, llff, colmap")
    p.add_argument("--minutes", type=float, required=True, help="training budget per config")
    p.add_argument("--json", required=True, help="output JSON file")
    common.add_overwrite_arg(p)
    p.add_argument("--config", action="append", default=None,
                   help="config(s) to run, repeatable (default: paper and cpu-small)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a NerfConfig field of every config run")
    p.add_argument("--near", type=float, default=None, help="near bound override")
    p.add_argument("--far", type=float, default=None, help="far bound override")
    p.add_argument("--hold-out", type=int, default=8, metavar="N",
                   help="hold out every N-th frame (by name) for evaluation (default 8)")
    p.add_argument("--downscale", type=int, default=None, help="read images downscaled by N")
    p.add_argument("--eval-minutes", type=float, default=5.0,
                   help="time allowed for rendering the held-out views per config")
    p.add_argument("--renders", default=None,
                   help="folder for side-by-side PNGs of the held-out views (optional)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def _load(args):
    from vrs_jax.data.readers import load_scene, options

    opts = {}
    if "query_every" in options(args.fmt):
        opts["query_every"] = args.hold_out
    if args.downscale is not None:
        opts["downscale"] = args.downscale
    scene = load_scene(args.fmt, args.data, **opts)
    if not scene.is_query.any():
        raise VrsError("no held-out views: the format has no split and no query_every option",
                       args.data)
    return scene


def run_config(name: str, args, scene) -> dict:
    import jax
    import jax.numpy as jnp

    from vrs_jax.nerf import render
    from vrs_jax.nerf import train as T
    from vrs_jax.nerf.config import get_config, parse_overrides
    from vrs_jax.nerf.model import count_params, mlp_flops_per_sample

    cfg = get_config(name, **parse_overrides(args.set))
    t_start = time.perf_counter()
    budget = 60.0 * args.minutes
    prep = T.prepare(scene, cfg, near=args.near, far=args.far)
    # Calibration: compile + 10 steps give steps/s; the lr decay horizon is then set to the
    # number of steps the remaining budget allows (mip-NeRF's schedule ends at max_steps).
    calib = T.train(prep, None, steps=min(10, cfg.max_steps), minutes=0.1 * budget / 60,
                    progress=False)
    sps = calib.steps_per_s if calib.steps_per_s > 0 else 1.0 / max(calib.seconds, 1e-3)
    left = budget - (time.perf_counter() - t_start)
    horizon = max(1, int(0.95 * sps * max(left - calib.compile_s, 1.0)))
    cfg = dataclasses.replace(cfg, max_steps=horizon)
    prep = dataclasses.replace(prep, cfg=cfg)
    left = budget - (time.perf_counter() - t_start)
    res = T.train(prep, None, minutes=max(left, 1.0) / 60.0, progress=not args.quiet,
                  log=(lambda _: None) if args.quiet else None)
    train_s = time.perf_counter() - t_start
    steps_per_s = res.steps_per_s or sps  # a budget too short for 2 steps: calibration's

    # Rendering throughput: the fixed held-out pixel subset rendered by the jitted chunked
    # renderer, timed on a second call (the first compiles).
    batch = jax.tree.map(jnp.asarray, prep.eval_batch)
    n_px = int(prep.eval_batch["mask"].sum())
    eval_fn = T.make_eval_fn(cfg)
    t0 = time.perf_counter()
    psnr_px = float(eval_fn(res.state.params, prep.cluster_data, batch))
    t_px = time.perf_counter() - t0
    if t_px < 120:
        t0 = time.perf_counter()
        jax.block_until_ready(eval_fn(res.state.params, prep.cluster_data, batch))
        t_px = time.perf_counter() - t0
    rays_per_s = n_px / t_px
    per_ray = cfg.num_samples_coarse + cfg.num_samples_fine

    v = prep.held_out
    est_view_s = float(np.prod(v.sizes[0])) / rays_per_s
    n_views = min(len(v), int(60 * args.eval_minutes / est_view_s))
    if n_views >= 1:
        rows = render.evaluate_views(res.ilm, v.subset(np.arange(n_views)),
                                     prep.held_images[:n_views], prep.held_near[:n_views],
                                     prep.held_far[:n_views], args.renders and
                                     Path(args.renders) / cfg.name, prep.held_cluster[:n_views],
                                     progress=not args.quiet)
        psnr = float(np.mean([r["psnr"] for r in rows]))
        ssim = float(np.mean([r["ssim"] for r in rows]))
        eval_kind = f"{n_views}/{len(v)} full views"
    else:  # too slow to render a whole view in --eval-minutes: the pixel subset only
        psnr, ssim, rows = psnr_px, float("nan"), []
        eval_kind = f"{n_px} held-out pixels"
    return {
        "config": cfg.name, "config_fields": cfg.to_dict(), "budget_s": budget,
        "train_wall_s": train_s, "compile_s": res.compile_s, "steps": int(res.state.step),
        "train_steps_per_s": steps_per_s,
        "train_rays_per_s": steps_per_s * cfg.batch_size * cfg.n_clusters,
        "train_mlp_evals_per_s": steps_per_s * cfg.batch_size * cfg.n_clusters * per_ray,
        "render_rays_per_s": rays_per_s, "mlp_evals_per_s": rays_per_s * per_ray,
        "mlp_flops_per_eval": mlp_flops_per_sample(cfg), "params": count_params(
            res.state.params), "heldout_psnr": psnr, "heldout_ssim": ssim,
        "eval": eval_kind, "n_train": len(prep.refs), "n_heldout": len(prep.held_out),
        "heldout_pixel_psnr": psnr_px, "views": rows,
        "history": [h for k, h in enumerate(res.history)
                    if "heldout_psnr" in h or k % max(1, len(res.history) // 200) == 0]}


def print_table(results: list[dict]) -> None:
    head = (f"{'config':10s} {'steps':>6s} {'steps/s':>8s} {'render rays/s':>14s} "
            f"{'MLP evals/s':>12s} {'PSNR':>7s} {'SSIM':>6s}  eval")
    print(head)
    print("-" * len(head))
    for r in results:
        print(f"{r['config']:10s} {r['steps']:6d} {r['train_steps_per_s']:8.2f} "
              f"{r['render_rays_per_s']:14.0f} {r['mlp_evals_per_s']:12.3g} "
              f"{r['heldout_psnr']:7.2f} {r['heldout_ssim']:6.3f}  {r['eval']}")


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    common.check_outputs(args, [args.json])
    if args.minutes <= 0:
        raise VrsError("--minutes must be positive")
    configs = args.config or ["paper", "cpu-small"]
    info = environment()
    scene = _load(args)
    results = []
    for name in configs:
        print(f"== {name}: {args.minutes:g} min on {args.data}")
        results.append(run_config(name, args, scene))
        print_table(results[-1:])
    print()
    print_table(results)
    out = {"benchmark": "nerf", "data": str(args.data), "format": args.fmt,
           "minutes": args.minutes, "hold_out_every": args.hold_out, "near": args.near,
           "far": args.far, "machine": info, "results": results}
    p = fileio.write_text(args.json, json.dumps(out, indent=1, default=float))
    print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
