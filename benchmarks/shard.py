"""Batch localization sharded over devices: queries per second against the number of devices.

    python -m benchmarks.shard [--devices 1,2,4] [--batch 8] [--source render] [--json FILE]

One map (the synthetic room, ``--config test`` by default; built into --work when missing), one
batch of queries (the scene's queries repeated to ``--batch``), localized with
:func:`vrs_jax.localize.batch.localize_batch`: the batch's query axis is sharded over N devices
(padded to a multiple of N). Each N runs in its own process, since JAX fixes the device count
when it starts: on CPU the N devices are forced with
``XLA_FLAGS=--xla_force_host_platform_device_count=N`` (they share the machine's cores, so the
scaling measured there is bounded by the core count); on an accelerator host pass
``--platform gpu`` (or tpu) and N takes the first N real devices. Reports median seconds per
batch call (compilation excluded: compiled ahead of time, then timed), queries per second,
speed-up over one device, and checks every N's poses against the N = 1 run.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from benchmarks import common
from vrs_jax.errors import VrsError, cli_main

REPO = Path(__file__).resolve().parents[1]


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.shard", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_scene_args(p, default_scenes=("synthetic",))
    p.set_defaults(config="test")
    p.add_argument("--devices", default="1,2,4",
                   help="comma-separated device counts to measure (default %(default)s)")
    p.add_argument("--batch", type=int, default=8,
                   help="queries per batch call (default %(default)s)")
    p.add_argument("--source", default="render", choices=("render", "real"),
                   help="render: VRS-NeRF (patches rendered); real: the real-patch baseline")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per device count")
    p.add_argument("--platform", default="cpu",
                   help="JAX platform of the workers: cpu (forced host devices) or gpu/tpu")
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/shard.json)")
    common.add_overwrite_arg(p)
    p.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--map-dir", default=None, help=argparse.SUPPRESS)
    p.add_argument("--scene-root", default=None, help=argparse.SUPPRESS)
    return p


def worker(args: argparse.Namespace) -> dict:
    """One device count (this process's devices): compile, time, return a row."""
    import jax

    from vrs_jax import localize, maps
    from vrs_jax.data.images import read_gray
    from vrs_jax.data.readers import load_scene
    from vrs_jax.localize import batch as B

    n = args.worker
    if len(jax.devices()) < n:
        raise VrsError(f"{n} devices wanted, {len(jax.devices())} available")
    m = maps.load_map_for(args.map_dir, args.source)
    qs = load_scene("7scenes", args.scene_root).queries()
    cfg = localize.get_config(m.config.name, source=args.source)
    idx = np.arange(args.batch) % len(qs)
    q = localize.stack_queries([localize.prepare_query(m, read_gray(qs.image_paths[i]),
                                                       qs.K[i], qs.dist[i], cfg) for i in idx])
    mesh = B.query_mesh(n)
    placed = B.place_map(m, mesh)  # once, as a long-lived Localizer does
    t0 = time.perf_counter()
    jax.block_until_ready(B.localize_batch(placed, q, cfg, mesh))  # compiles
    compile_s = time.perf_counter() - t0
    sec, out = common.time_calls(lambda: B.localize_batch(placed, q, cfg, mesh),
                                 repeats=args.repeats, budget_s=60.0)
    out = jax.device_get(out)
    return {"devices": n, "device_kind": jax.devices()[0].device_kind,
            "platform": jax.devices()[0].platform, "batch": args.batch,
            "padded_batch": args.batch + (-args.batch) % n, "seconds_per_batch": sec,
            "queries_per_s": args.batch / sec, "first_call_s": compile_s,
            "n_success": int(np.sum(out.success)),
            "R": np.asarray(out.R).tolist(), "t": np.asarray(out.t).tolist()}


def run_worker(n: int, args: argparse.Namespace, map_dir: Path, scene_root: Path) -> dict:
    env = dict(os.environ, JAX_PLATFORMS=args.platform, PYTHONPATH=str(REPO),
               TF_CPP_MIN_LOG_LEVEL="2")
    if args.platform == "cpu":
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") +
                            f" --xla_force_host_platform_device_count={n}").strip()
    cmd = [sys.executable, "-m", "benchmarks.shard", "--worker", str(n), "--map-dir",
           str(map_dir), "--scene-root", str(scene_root), "--batch", str(args.batch),
           "--source", args.source, "--repeats", str(args.repeats)]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=REPO)
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    if r.returncode != 0 or not lines:
        raise VrsError(f"the {n}-device worker failed: {(r.stderr or r.stdout)[-600:]}")
    return json.loads(lines[-1])


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.worker is None:
        common.check_outputs(args, [common.json_path(args, "shard")])
    if args.worker is not None:
        print(json.dumps(worker(args)))
        return 0
    counts = sorted({int(x) for x in args.devices.split(",") if x.strip()})
    if not counts or counts[0] < 1 or args.batch < 1:
        raise VrsError("--devices needs positive counts and --batch >= 1")
    doc = common.base_doc("shard", args, argv)
    ctxs, skipped = common.prepare_scenes(args)
    rows = []
    for ctx in ctxs:
        for n in counts:
            print(f"[{ctx.name}] {n} device(s)...", flush=True)
            row = run_worker(n, args, ctx.map_dir, Path(ctx.scene.root))
            rows.append({"scene": ctx.name, **row})
        base = next(r for r in rows if r["scene"] == ctx.name)
        for r in rows:
            if r["scene"] != ctx.name:
                continue
            r["speedup"] = r["queries_per_s"] / base["queries_per_s"]
            r["max_pose_diff_vs_first"] = float(max(
                np.max(np.abs(np.asarray(r["R"]) - np.asarray(base["R"]))),
                np.max(np.abs(np.asarray(r["t"]) - np.asarray(base["t"])))))
    for r in rows:
        del r["R"], r["t"]
    print()
    print(common.table(
        ["scene", "devices", "batch (padded)", "s / batch", "queries/s", "speed-up",
         "localized", "max pose diff"],
        [[r["scene"], r["devices"], f"{r['batch']} ({r['padded_batch']})",
          common.fmt(r["seconds_per_batch"], 3), common.fmt(r["queries_per_s"], 2),
          common.fmt(r["speedup"], 2), f"{r['n_success']}/{r['batch']}",
          f"{r['max_pose_diff_vs_first']:.1e}"] for r in rows],
        title=f"Sharded batch localization ({args.source}, config {args.config}, "
              f"{args.platform} devices; compilation excluded)"))
    for s in skipped:
        print(f"skipped {s['scene']}: {s['reason']}")
    doc.update({"rows": rows, "skipped": skipped, "cpu_count": os.cpu_count()})
    out = common.write_json(common.json_path(args, "shard"), doc)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
