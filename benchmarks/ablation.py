"""Patch-size ablation (the paper's table): rendered P x P patches for P = 9, 11, 13, 15, and GT.

    python -m benchmarks.ablation [--scenes synthetic,fern] [--sizes 9 11 13 15] [--json FILE]

Render mode changes the patch size at localization time: the map's keypoints are rendered
as P x P patches (same support, finer or coarser sampling) and the query is described with
the same P. The GT row is the baseline map's descriptors of the real reference patches (the
map's own patch size). Reported per row: median translation / rotation error, recall
(1/1, 2/2, 5/5, 10/5 cm/deg and 25 cm/2 deg), median render time per query (the render
stage), rays and NeRF evaluations per query, and the total localization time per query.

Defaults: synthetic and fern (the issue's scenes), cpu-small maps in --work (built once,
shared with the other benchmarks), the depth-guided sampler. Runs recorded by
``benchmarks.localize`` with identical settings (same map, config, queries and code) are
reused (the map's P and GT rows), so after it this takes ~3 minutes on 2 CPU cores;
--fresh re-measures everything. --with-full-sampling adds a coarse + fine row at the map's P
(what the depth-guided sampler costs in accuracy; ~6x the render time).
"""

from __future__ import annotations

import argparse
import dataclasses

from benchmarks import common
from vrs_jax.errors import VrsError, cli_main
from vrs_jax.features.patches import PATCH_SIZES

ABLATION_SIZES = (9, 11, 13, 15)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.ablation", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_scene_args(p, default_scenes=("synthetic", "fern"))
    p.add_argument("--sizes", type=int, nargs="+", default=list(ABLATION_SIZES),
                   help=f"render-mode patch sizes P (from {PATCH_SIZES})")
    p.add_argument("--no-real", action="store_true",
                   help="leave out the real-patch (GT, baseline) row")
    p.add_argument("--with-full-sampling", action="store_true",
                   help="add a render row at the map's P with coarse + fine sampling")
    p.add_argument("--fresh", action="store_true",
                   help="re-measure every row (do not reuse recorded runs)")
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/ablation.json)")
    common.add_overwrite_arg(p)
    return p


def row_of(scene: str, label: str, cfg, s: dict) -> dict:
    return {"scene": scene, "method": label, "mode": cfg.source,
            "patch_size": s["patch_size"],
            "depth_guided": cfg.depth_guided if cfg.source == "render" else None,
            "n_queries": s["n_queries"], "median_t_cm": s["median_t_cm"],
            "median_R_deg": s["median_R_deg"], "recall": s["recall"],
            "n_fallback": s["n_fallback"], "median_inliers": s["median_inliers"],
            "render_s_per_query": s["timing_s"]["render"] if cfg.source == "render" else 0.0,
            "localize_s_per_query": s["localize_s_per_query"],
            "rays_per_query": s["rays_per_query"],
            "nerf_evals_per_query": s["nerf_evals_per_query"],
            "map_bytes_total": s["map_bytes"]["total"], "measured_at": s["measured_at"],
            "reused": s["reused"], "record": s["record"],
            "localize_config": dataclasses.asdict(cfg)}


def ablation_table(rows: list[dict]) -> str:
    return common.table(
        ["scene / method", "queries", "median (cm, deg)", "1cm/1deg", "2cm/2deg", "5cm/5deg",
         "10cm/5deg", "25cm/2deg", "render (ms)", "total (ms)", "rays/query"],
        [[f"{r['scene']} / {r['method']}", r["n_queries"],
          f"{common.fmt(r['median_t_cm'])}, {common.fmt(r['median_R_deg'])}",
          *(common.pct(r["recall"][k] if r["recall"] else None)
            for k in ("1cm_1deg", "2cm_2deg", "5cm_5deg", "10cm_5deg", "25cm_2deg")),
          common.fmt(1000 * r["render_s_per_query"], 1),
          common.fmt(1000 * r["localize_s_per_query"], 1),
          common.fmt(r["rays_per_query"], 0)] for r in rows],
        title="Patch-size ablation (median per query; times exclude query preparation)")


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    common.check_outputs(args, [common.json_path(args, "ablation")])
    bad = [s for s in args.sizes if s not in PATCH_SIZES]
    if bad:
        raise VrsError(f"--sizes must be among {PATCH_SIZES}, got {bad}")
    doc = common.base_doc("ablation", args, argv)
    ctxs, skipped = common.prepare_scenes(args)
    rows, maps = [], {}
    for ctx in ctxs:
        maps[ctx.name] = common.map_info(ctx)
        plan = [(f"render {P}x{P}", common.localize_cfg(ctx, "render", P))
                for P in args.sizes]
        map_p = common.patch_config(ctx).size
        if args.with_full_sampling:
            plan.append((f"render {map_p}x{map_p} coarse+fine",
                         common.localize_cfg(ctx, "render", map_p, depth_guided=False)))
        if not args.no_real:
            plan.append((f"real {map_p}x{map_p} (GT)", common.localize_cfg(ctx, "real")))
        for label, cfg in plan:
            s = common.localize_run(ctx, cfg, args.work, fresh=args.fresh,
                                    progress=not args.quiet)
            rows.append(row_of(ctx.name, label, cfg, s))
    print()
    print(ablation_table(rows))
    for s in skipped:
        print(f"skipped {s['scene']}: {s['reason']}")
    doc.update({"maps": maps, "rows": rows, "skipped": skipped})
    out = common.write_json(common.json_path(args, "ablation"), doc)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
