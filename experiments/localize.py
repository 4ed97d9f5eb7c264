"""Localize a dataset's query images against a vrs-jax map.

    python -m experiments.localize --map MAPDIR --format F --root DIR --out OUTDIR
        [--mode render|gt] [--patch-size P] [--top-k K] [--full-sampling] [--basename]

Writes OUTDIR/results.txt (one line per query: ``name qw qx qy qz tx ty tz``, world-to-camera;
``name`` is the image path relative to the dataset root, or the bare file name with
--basename as the Aachen benchmark wants) and OUTDIR/summary.json (metrics when the queries
have ground truth, map bytes, median time per stage, rays and NeRF evaluations per query).
A query that fails (no keypoints, no matches, RANSAC failure) still gets a line: the pose of
its top-1 retrieved reference image, flagged in summary.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from experiments.common import add_scene_args, load_scene_from_args
from vrs_jax import pipeline
from vrs_jax.errors import VrsError, cli_main
from vrs_jax.eval import metrics
from vrs_jax.eval.results import write_results
from vrs_jax.features.patches import PATCH_SIZES


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m experiments.localize",
                                description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--map", required=True, help="map folder written by experiments.train*")
    add_scene_args(p)
    p.add_argument("--out", required=True, help="output folder (results.txt, summary.json)")
    p.add_argument("--mode", default="render", choices=["render", "gt"],
                   help="render: VRS-NeRF (rendered patches); gt: the hierarchical baseline "
                        "(descriptors of real reference patches)")
    p.add_argument("--patch-size", type=int, default=None, choices=PATCH_SIZES,
                   help="rendered patch size P (render mode; default: the map's)")
    p.add_argument("--literal", action="store_true",
                   help="paper-literal patches: axis-aligned whole pixels, no scale/rotation")
    p.add_argument("--top-k", type=int, default=None, help="retrieved reference images")
    p.add_argument("--full-sampling", action="store_true",
                   help="render with coarse+fine sampling instead of the depth-guided interval")
    p.add_argument("--basename", action="store_true",
                   help="write bare file names in results.txt (Aachen benchmark)")
    p.add_argument("--no-timing", action="store_true",
                   help="run the fused jitted localize (no per-stage times)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def make_config(m: pipeline.LoadedMap, args) -> object:
    over = {}
    patches = m.egm_cfg.features.patches
    if args.patch_size is not None:
        patches = dataclasses.replace(patches, size=args.patch_size)
    if args.literal:
        patches = dataclasses.replace(patches, mode="literal")
    if args.mode == "render" and patches != m.egm_cfg.features.patches:
        over["patches"] = patches
    elif args.mode == "gt" and (args.patch_size or args.literal):
        raise VrsError("gt mode uses the patches stored in the baseline map; --patch-size and "
                       "--literal apply to render mode")
    if args.top_k is not None:
        over["top_k"] = args.top_k
    if args.full_sampling:
        over["depth_guided"] = False
    return pipeline.localize_config(m.pcfg, m.egm_cfg, args.mode, **over)


def write_json(path: Path, doc: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(metrics.json_ready(doc), indent=2, allow_nan=False) + "\n")
    os.replace(tmp, path)


def run(args) -> dict:
    m = pipeline.load_map(args.map)
    cfg = make_config(m, args)
    scene = load_scene_from_args(args)
    queries = scene.queries()
    if len(queries) == 0:
        raise VrsError("the dataset has no query images (for formats without a split pass "
                       "--query-every N)", scene.root)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise VrsError("output path exists and is not a folder", out)
    out.mkdir(parents=True, exist_ok=True)
    results, info = pipeline.localize_queries(m, queries, cfg, progress=not args.quiet,
                                              timed=not args.no_timing)
    R = np.stack([np.asarray(r.R, np.float64) for r in results])
    t = np.stack([np.asarray(r.t, np.float64) for r in results])
    write_results(out / "results.txt", queries.names, R, t, basename=args.basename)
    summary = pipeline.summarize(queries, results, info, m, cfg, Path(args.map))
    summary["per_query"] = [
        {"name": n, "success": bool(r.success), "fallback": bool(r.fallback),
         "inliers": int(r.n_inliers), "matches": int(r.n_matches)}
        for n, r in zip(queries.names, results, strict=True)]
    write_json(out / "summary.json", summary)
    if summary["recall"] is not None:
        print(metrics.format_table(summary, title=f"{cfg.mode} mode, {len(queries)} queries"))
    print(f"{summary['n_success']}/{len(queries)} localized, {summary['n_fallback']} fallback; "
          f"results in {out / 'results.txt'}")
    return summary


@cli_main
def main(argv: list[str] | None = None) -> int:
    run(build_parser().parse_args(argv))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
