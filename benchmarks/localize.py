"""Localization benchmark: per-stage latency and accuracy, VRS-NeRF (render) vs the
real-patch baseline (real) vs the COLMAP SIFT reference localizer (sift), on the same split.

    python -m benchmarks.localize [--scenes synthetic,fern,lego,scan24] [--json FILE]

For each scene, every query is localized in ``render`` mode (descriptors of NeRF-rendered
patches: VRS-NeRF), ``real`` mode (the map's stored descriptors of the real reference
patches: the hierarchical baseline) and by the SIFT reference (``vrs_jax.reference.sift``:
COLMAP SIFT, triangulation with the known poses, pycolmap absolute pose), with the map's
patch size. ``render`` samples each patch ray depth-guided (the config's narrow interval
around the keypoint's 3D point); ``render-full`` renders the same map with the NeRF's full
coarse + fine sampling (the ``paper`` localize config's choice). When the config makes guided
passes (``guided_passes``: the map points re-matched near their projections under the first
pose, render mode rendering them from that pose), each mode also gets a ``... pass 1`` row:
the first pass's pose from the same run. Reported per scene and
method: median translation / rotation error, recall at hloc's thresholds and relative to the
scene size (median distance of the cameras to their centroid), failures and fallbacks,
distinct inliers, the median time per query of each stage (query preparation separately; a
warm-up query compiles first), rays and NeRF evaluations per query, and map bytes. Each run
is measured afresh and recorded in WORK/runs/ (the ablation and figures reuse those
records). ``--repeat N`` runs the render and real rows N times, the modes in turn, and reports
each stage's median time over the runs: on a shared machine one run's times move 15-30%.
``--seeds N`` localizes the render and real rows again with N - 1 other seeds of the RANSAC
seed's random sampling (``PnPConfig.seed``: 0 is the configs', then 1, 2, ...) and reports,
beside the seed-0 row, each recall's range and mean over the seeds: on the phone walk one
seed's render recall within 1% / 1 deg differs from another's by up to 13 points with
nothing else changed, so a difference between two configurations counts only beyond that.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import jax
import numpy as np

from benchmarks import common
from vrs_jax.errors import cli_main
from vrs_jax.eval import metrics
from vrs_jax.localize import STAGE_NAMES as STAGES

# render: depth-guided sampling (the config's narrow interval around the keypoint's point);
# render-full: the same map rendered with the NeRF's full coarse + fine sampling.
MODES = ("render", "render-full", "real", "sift")
RECALL_KEYS = tuple(metrics.RECALL_THRESHOLDS)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.localize", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_scene_args(p, default_scenes=("synthetic", "fern", "lego", "scan24"))
    p.add_argument("--modes", default="render,real,sift",
                   help="comma-separated: render (VRS-NeRF, depth-guided sampling), "
                        "render-full (coarse + fine sampling), real (real-patch baseline), "
                        "sift (the COLMAP SIFT reference localizer, vrs_jax.reference.sift)")
    p.add_argument("--full-sampling", action="store_true",
                   help="render mode: coarse + fine sampling instead of the depth-guided "
                        "interval (~6x slower rendering on cpu-small)")
    p.add_argument("--top-k", type=int, default=None,
                   help="retrieved reference images (default: the config's)")
    p.add_argument("--localize", action="append", default=[], metavar="KEY=VALUE",
                   help="override a number/bool LocalizeConfig field in the render and real "
                        "rows (repeatable), e.g. early_exit_inliers=40 or guided_passes=0")
    p.add_argument("--repeat", type=int, default=1, metavar="N",
                   help="run every render/real row N times, the modes in turn (render, real, "
                        "render, real, ...), and report each stage's median time over the N "
                        "runs (each run's times stay in the JSON; accuracy is the first run's, "
                        "and the row says whether every run gave the same poses). Times on a "
                        "shared or throttled machine move 15-30%% between runs: a ratio of "
                        "modes is only as good as N")
    p.add_argument("--seeds", type=int, default=1, metavar="N",
                   help="localize every render/real row with N RANSAC seeds (the configs' "
                        "seed 0, then 1 .. N-1; accuracy only, nothing else changes) and "
                        "print each recall's range and mean over them beside the seed-0 "
                        "rows (each seed's per-query errors stay in the JSON)")
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/localize.json)")
    common.add_overwrite_arg(p)
    return p


def relative(s: dict, scale: float) -> dict:
    """Recall at thresholds relative to the scene scale, and the median relative error."""
    import numpy as np

    from vrs_jax.eval import metrics

    dt = np.asarray(s["per_query"]["t_err_m"], np.float64)
    dr = np.asarray(s["per_query"]["R_err_deg"], np.float64)
    rel = {k: (f * scale, r) for k, (f, r) in metrics.RELATIVE_THRESHOLDS.items()}
    return {"scene_scale": scale, "recall_relative": metrics.relative_recall(dt, dr, scale),
            "median_t_rel": float(np.median(dt) / scale) if len(dt) else None,
            "recall_interval": metrics.recall_interval(dt, dr),
            "recall_relative_interval": metrics.recall_interval(dt, dr, rel)}


def sift_row(ctx: common.SceneCtx, args, scale: float) -> dict:
    """The COLMAP SIFT reference on the same map images and queries as the other rows."""
    import time

    from benchmarks import sift_reference
    from vrs_jax.reference import sift

    cfg = sift.SiftReferenceConfig()
    work = Path(args.work) / "sift" / ctx.name
    smap = sift.build_sift_map(ctx.scene, work, cfg, progress=not args.quiet)
    t0 = time.perf_counter()
    results = sift.localize_sift(smap, ctx.queries, cfg, progress=not args.quiet)
    row = sift_reference.row_of(ctx.name, ctx.queries, results, smap, cfg, scale,
                                time.perf_counter() - t0)
    row.update(relative(row, scale))
    return row


def row_of(scene: str, mode: str, s: dict) -> dict:
    """The JSON/table row of one run (a summary from common.localize_run)."""
    timing = {k: s["timing_s"].get(k) for k in (*STAGES, "query_preparation")}
    return {"scene": scene, "mode": mode, "n_queries": s["n_queries"],
            "patch_size": s["patch_size"], "depth_guided": s["depth_guided"],
            "median_t_cm": s["median_t_cm"], "median_R_deg": s["median_R_deg"],
            "recall": s["recall"], "n_success": s["n_success"], "n_fallback": s["n_fallback"],
            "median_inliers": s["median_inliers"], "timing_s": timing,
            "localize_s_per_query": s["localize_s_per_query"],
            "rays_per_query": s["rays_per_query"],
            "nerf_evals_per_query": s["nerf_evals_per_query"],
            "nerf_evals_per_query_median": s.get("nerf_evals_per_query_median", 0.0),
            "full_image_evals_per_query": s.get("full_image_evals_per_query", 0.0),
            "map_bytes": s["map_bytes"],
            "per_query": s["per_query"], "retried": s.get("retried", {}),
            "measured_at": s["measured_at"],
            "reused": s["reused"], "record": s["record"]}


def accuracy_table(rows: list[dict]) -> str:
    rel = lambda r, k: common.pct(r["recall_relative"][k])  # noqa: E731
    return common.table(
        ["scene / mode", "queries", "median (cm, deg)", "median (% scale)", "1cm/1deg",
         "2cm/2deg", "5cm/5deg", "1%/1deg", "2%/2deg", "5%/5deg", "1%/1deg 95% CI",
         "fail/fallback", "inliers", "map (MB)"],
        [[f"{r['scene']} / {r['mode']}", r["n_queries"],
          f"{common.fmt(r['median_t_cm'])}, {common.fmt(r['median_R_deg'])}",
          common.fmt(None if r["median_t_rel"] is None else 100 * r["median_t_rel"]),
          *(common.pct(r["recall"][k] if r["recall"] else None)
            for k in ("1cm_1deg", "2cm_2deg", "5cm_5deg")),
          *(rel(r, k) for k in ("1pct_1deg", "2pct_2deg", "5pct_5deg")),
          "{}-{}".format(*(common.pct(x) for x in r["recall_relative_interval"]["1pct_1deg"])),
          r["n_queries"] - r["n_success"], common.fmt(r["median_inliers"], 0),
          common.fmt(r["map_bytes"]["total"] / 1e6, 3)] for r in rows],
        title="Accuracy (render = VRS-NeRF, rendered patches; real = baseline, real patches; "
              "sift = COLMAP SIFT reference; % scale = of the median camera distance to the "
              "cameras' centroid; CI: percentile bootstrap over the queries; inliers are "
              "distinct 2D-3D pairs)")


def latency_table(rows: list[dict]) -> str:
    ms = lambda x: common.fmt(None if x is None else 1000.0 * x, 1)  # noqa: E731
    real = {r["scene"]: r for r in rows if r["mode"] == "real"}

    def vs_real(r, prep: bool):
        b = real.get(r["scene"])
        if b is None or r["mode"] == "real":
            return "-"
        p = lambda x: x["localize_s_per_query"] + (  # noqa: E731
            (x["timing_s"]["query_preparation"] or 0.0) if prep else 0.0)
        return common.fmt(p(r) / p(b), 1)

    def fewer(r):
        full, ev = r.get("full_image_evals_per_query") or 0.0, r["nerf_evals_per_query"]
        return common.fmt(full / ev, 1) if full and ev else "-"

    return common.table(
        ["scene / mode", *STAGES, "total", "query prep", "x real", "x real (with prep)",
         "rays/query", "NeRF evals/query", "(median)", "x fewer than full images"],
        [[f"{r['scene']} / {r['mode']}", *(ms(r["timing_s"][k]) for k in STAGES),
          ms(r["localize_s_per_query"]), ms(r["timing_s"]["query_preparation"]),
          vs_real(r, False), vs_real(r, True),
          common.fmt(r["rays_per_query"], 0), common.fmt(r["nerf_evals_per_query"], 0),
          common.fmt(r["nerf_evals_per_query_median"], 0), fewer(r)]
         for r in rows if r["mode"] != "sift"],
        title="Median latency per query (ms); rays and NeRF evaluations per query: the mean "
              "and the median; the SIFT reference's times are in the JSON")


def mode_cfg(ctx: common.SceneCtx, mode: str, args, overrides: dict):
    """The LocalizeConfig of a render / render-full / real row: the map's named config with
    the command's overrides (top-k, sampling, --localize)."""
    over = dict(overrides)
    if args.top_k is not None:
        over["top_k"] = args.top_k
    if mode == "render-full" or (mode == "render" and args.full_sampling):
        over["depth_guided"] = False
    return common.localize_cfg(ctx, "render" if mode == "render-full" else mode, **over)


def with_seed(cfg, seed: int):
    """``cfg`` (a LocalizeConfig) with its RANSAC seed's generator seeded by ``seed``."""
    return dataclasses.replace(cfg, pnp=dataclasses.replace(cfg.pnp, seed=seed))


SEED_KEYS = ("1pct_1deg", "2pct_2deg", "5pct_5deg")


def seed_spread(per_seed: list[dict], scale: float) -> dict:
    """Accuracy of one row over RANSAC seeds. per_seed: a summary (``per_query``'s t_err_m,
    R_err_deg) per seed, seed 0 first. Returns ``n``, ``recall_relative`` {key: [per seed]},
    ``median_t_rel`` [per seed], and per key its ``min``, ``max`` and ``mean``."""
    rel = [relative(s, scale) for s in per_seed]
    rec = {k: [r["recall_relative"][k] for r in rel] for k in SEED_KEYS}
    return {"n": len(per_seed), "recall_relative": rec,
            "median_t_rel": [r["median_t_rel"] for r in rel],
            "min": {k: float(min(v)) for k, v in rec.items()},
            "max": {k: float(max(v)) for k, v in rec.items()},
            "mean": {k: float(np.mean(v)) for k, v in rec.items()},
            "per_query": [{"t_err_m": s["per_query"]["t_err_m"],
                           "R_err_deg": s["per_query"]["R_err_deg"]} for s in per_seed]}


def seeds_table(rows: list[dict]) -> str:
    """Recall over RANSAC seeds: per row with ``seeds``, each threshold's seed-0 value, its
    min-max and mean over the seeds, and the median error's range."""
    pct = common.pct

    def cell(sp, k):
        return (f"{pct(sp['recall_relative'][k][0])} ({pct(sp['min'][k])}-"
                f"{pct(sp['max'][k])}, mean {pct(sp['mean'][k])})")

    def med(sp):
        v = [100 * x for x in sp["median_t_rel"] if x is not None]
        return f"{common.fmt(min(v))}-{common.fmt(max(v))}" if v else "-"

    return common.table(
        ["scene / mode", "seeds", "1%/1deg: seed 0 (min-max, mean)", "2%/2deg", "5%/5deg",
         "median % scale (min-max)"],
        [[f"{r['scene']} / {r['mode']}", r["seeds"]["n"],
          *(cell(r["seeds"], k) for k in SEED_KEYS), med(r["seeds"])]
         for r in rows if "seeds" in r],
        title="Recall over RANSAC seeds (PnPConfig.seed 0 .. N-1, nothing else changed): a "
              "difference between configurations inside these ranges is not evidence")


def repeated(summaries: list[dict]) -> dict:
    """One summary of N runs of the same config: the first run's accuracy and counts, each
    stage's median time over the runs (and ``localize_s_per_query``, their sum, as one run
    reports it); with N > 1 ``repeats`` holds each run's ``timing_s`` and
    ``localize_s_per_query`` and ``same_poses`` (every run's per-query errors equal the
    first's)."""
    import numpy as np

    first = summaries[0]
    if len(summaries) == 1:
        return first
    timing = {k: (None if first["timing_s"][k] is None else
                  float(np.median([s["timing_s"][k] for s in summaries])))
              for k in first["timing_s"]}
    errors = lambda s: (s["per_query"]["t_err_m"], s["per_query"]["R_err_deg"])  # noqa: E731
    return {**first, "timing_s": timing,
            "localize_s_per_query": float(sum(timing.get(k) or 0.0 for k in STAGES)),
            "repeats": {"n": len(summaries),
                        "timing_s": [s["timing_s"] for s in summaries],
                        "localize_s_per_query": [s["localize_s_per_query"] for s in summaries],
                        "same_poses": all(errors(s) == errors(first) for s in summaries)}}


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.repeat < 1 or args.seeds < 1:
        from vrs_jax.errors import VrsError

        raise VrsError(f"--repeat and --seeds must be >= 1, got {args.repeat} and "
                       f"{args.seeds}")
    common.check_outputs(args, [common.json_path(args, "localize")])
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    if not modes or any(m not in MODES for m in modes):
        from vrs_jax.errors import VrsError

        raise VrsError(f"--modes must list some of {', '.join(MODES)}, got {args.modes!r}")
    overrides = common.localize_overrides(args.localize)
    doc = common.base_doc("localize", args, argv)
    # real patches and the SIFT reference need no NeRF: an EGM-only map will do for them
    ctxs, skipped = common.prepare_scenes(args, need_nerf="render" in modes)
    rows, maps = [], {}
    for ctx in ctxs:
        maps[ctx.name] = common.map_info(ctx)
        c = ctx.scene.centers[np.asarray(ctx.scene.has_pose, bool)]
        scale = metrics.scene_scale(c)
        cfgs = {mode: mode_cfg(ctx, mode, args, overrides) for mode in modes
                if mode != "sift"}
        runs: dict[str, list[dict]] = {mode: [] for mode in cfgs}
        for _ in range(args.repeat):  # the modes in turn, so that a slow spell hits both
            for mode, cfg in cfgs.items():
                runs[mode].append(common.localize_run(ctx, cfg, args.work, fresh=True,
                                                      progress=not args.quiet))
        others: dict[str, list[dict]] = {mode: [] for mode in cfgs}
        for seed in range(1, args.seeds):  # accuracy only: the seed-0 runs keep the times
            for mode, cfg in cfgs.items():
                others[mode].append(common.localize_run(ctx, with_seed(cfg, seed), args.work,
                                                        fresh=True, progress=not args.quiet))
                # each seed is another static config, compiled anew: without this the
                # executables of six scenes x two modes x three seeds outgrew the process's
                # memory maps (vm.max_map_count) and XLA aborted mid-run
                jax.clear_caches()
        for mode in modes:
            if mode == "sift":
                rows.append(sift_row(ctx, args, scale))
                continue
            s = runs[mode][0]
            for label, pick in ((f"{mode} pass 1", lambda r: r.get("first_pass")),
                                (mode, lambda r: r)):
                if pick(s) is None:
                    continue
                summary = repeated([pick(r) for r in runs[mode]])
                row = row_of(ctx.name, label, {**summary, "reused": s["reused"],
                                               "record": s["record"]})
                row.update(relative(summary, scale))
                row["localize_config"] = dataclasses.asdict(cfgs[mode])
                if args.repeat > 1:
                    row["repeats"] = summary["repeats"]
                if args.seeds > 1:
                    row["seeds"] = seed_spread([pick(r) for r in [s, *others[mode]]], scale)
                rows.append(row)
    print()
    print(accuracy_table(rows))
    print()
    print(latency_table(rows))
    if args.seeds > 1:
        print()
        print(seeds_table(rows))
    if args.repeat > 1:
        differ = [f"{r['scene']} / {r['mode']}" for r in rows
                  if "repeats" in r and not r["repeats"]["same_poses"]]
        print(f"times: each stage's median over {args.repeat} runs of every mode, the modes "
              f"in turn; accuracy: the first run's"
              + (f" (other poses in a later run: {', '.join(differ)})" if differ
                 else " (every run gave the same poses)"))
    for s in skipped:
        print(f"skipped {s['scene']}: {s['reason']}")
    doc.update({"maps": maps, "rows": rows, "skipped": skipped})
    out = common.write_json(common.json_path(args, "localize"), doc)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
