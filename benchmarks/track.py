"""Tracking benchmark: a stream of queries localized by tracking (``Localizer.track``) against
full localization of every frame and the COLMAP SIFT reference, per frame.

    python -m benchmarks.track --map MAPDIR [--format F --root DIR [--opt query_range=A:B]]
        [--mode render|real] [--modes track,full,cached,sift] [--jump-at N --jump-len M]
        [--max-frames N] [--localize KEY=VALUE] [--track KEY=VALUE] [--json FILE]
        [--plot FILE.png]

The queries (the map's own held-out split, or those of --format/--root as for
``experiments.localize``) are taken in name order, the capture order of a video, as one
stream. ``track``: the first frame and any frame whose tracking is rejected are localized in
full, every other frame by the guided pass alone from the constant-velocity prediction
(``vrs_jax.localize.track``; in render mode its full localizations share a cache of
rendered reference descriptors, ``track.cache_mb``); ``full``: every frame localized in
full (retrieval, first pass, guided passes) by the same ``Localizer``, no cache; ``cached``
(render mode): the same with a cache of ``track.cache_mb`` for the whole stream, as a
stream's full localizations have it; ``sift``: the COLMAP SIFT reference per frame
(``benchmarks.localize.sift_row``). With --jump-at N --jump-len M a fourth run tracks the
stream with frames N .. N+M-1 dropped (the camera jumps), and reports how many frames after
the gap it takes to track again and to be right again (within 2% of the scene scale and
2 deg). Reported per run: recall at 1%/1deg and 2%/2deg of the scene scale (the median
distance of the cameras to their centroid, as benchmarks.localize), median errors, the
median latency per frame (reading and query preparation included, compilation excluded by
a warm-up), and how the frames were localized: tracked (in brackets those whose pose is
the check pass's: the tracking pass's disagreed with the frame's own matches; then those
whose pose is the frame pass's, ``track.frame_pass``), relocalized
(tracking rejected, then localized in full), in full without a prior (the first frame, after
a gap), flagged (unreadable or blank); and wrong 'localized': poses more than 5% of the
scene scale or 5 deg off whose verdict is "localized" (a wrong pose reported as right).
--plot draws the error and the latency along the stream.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import types
from pathlib import Path

import numpy as np

from benchmarks import common
from benchmarks.confidence import WRONG_R, WRONG_T
from vrs_jax import localize, maps
from vrs_jax.cli.common import add_scene_args, load_scene_from_args
from vrs_jax.errors import VrsError, cli_main
from vrs_jax.eval import metrics
from vrs_jax.localize import Localizer
from vrs_jax.localize.config import TrackConfig
from vrs_jax.localize.track import frame_image

RUNS = ("track", "full", "cached", "sift")
RIGHT = (0.02, 2.0)  # "right again" after a jump: 2% of the scene scale, 2 deg


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.track", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--map", required=True, help="map folder (experiments.train*)")
    add_scene_args(p, required=False)
    p.add_argument("--mode", default="render", choices=("render", "real"),
                   help="render: VRS-NeRF; real: the real-patch baseline")
    p.add_argument("--config", default=None,
                   help="named localize config (default: the map's config name)")
    p.add_argument("--modes", default=",".join(RUNS),
                   help="comma-separated runs among track, full, sift")
    p.add_argument("--jump-at", type=int, default=None, metavar="N",
                   help="also track the stream with frames N .. N+M-1 dropped (a jump)")
    p.add_argument("--jump-len", type=int, default=5, metavar="M",
                   help="frames dropped by --jump-at (default %(default)s)")
    p.add_argument("--max-frames", type=int, default=None,
                   help="only the first N frames of the stream")
    p.add_argument("--localize", action="append", default=[], metavar="KEY=VALUE",
                   help="override a number/bool LocalizeConfig field (repeatable)")
    p.add_argument("--track", action="append", default=[], metavar="KEY=VALUE",
                   help="override a number field of the TrackConfig (repeatable), e.g. "
                        "radius_px=8")
    p.add_argument("--work", default=common.DEFAULT_WORK,
                   help="folder of the SIFT reference's work files")
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/track.json)")
    p.add_argument("--plot", default=None, metavar="FILE.png",
                   help="draw the per-frame error and latency of the runs")
    common.add_overwrite_arg(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def stream_of(m: maps.Map, args) -> tuple:
    """(the whole scene, its queries in name order) of the map's split or --format/--root."""
    from vrs_jax.cli.localize import query_scene

    args.images = args.queries = None
    queries = query_scene(m, args, Path(args.work) / "sfm")  # fills args from the map
    scene = load_scene_from_args(args)
    queries = queries.subset(np.argsort(np.asarray(queries.names, object), kind="stable"))
    if args.max_frames is not None:
        if args.max_frames < 2:
            raise VrsError("--max-frames must be >= 2 (a stream)")
        queries = queries.subset(np.arange(min(args.max_frames, len(queries))))
    if not np.asarray(queries.has_pose, bool).all():
        raise VrsError("the queries need ground-truth poses", queries.root)
    return scene, queries


def config_of(m: maps.Map, args) -> localize.LocalizeConfig:
    over = common.localize_overrides(args.localize)
    track_over = common.localize_overrides(args.track, TrackConfig())
    cfg = localize.get_config(args.config or m.config.name, source=args.mode, **over)
    return dataclasses.replace(cfg, track=dataclasses.replace(cfg.track, **track_over))


def errors_of(queries, results: list, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Translation (scene units) and rotation (deg) errors [n] of results (None: inf, 180)
    against queries ``idx``."""
    has = np.array([r is not None for r in results], bool)
    R = np.stack([np.asarray(r.R, np.float64) if r is not None else np.eye(3)
                  for r in results])
    t = np.stack([np.asarray(r.t, np.float64) if r is not None else np.zeros(3)
                  for r in results])
    return metrics.pose_errors(R, t, queries.R[idx], queries.t[idx], has_estimate=has)


def run_track(loc: Localizer, queries, idx: np.ndarray, progress: bool) -> dict:
    """Track frames ``idx`` of the stream; per-frame arrays of the run."""
    tracks = loc.track([queries.image_paths[i] for i in idx], [queries.K[i] for i in idx],
                       [queries.dist[i] for i in idx], names=[queries.names[i] for i in idx],
                       progress=progress, sizes=[queries.sizes[i] for i in idx])
    dt, dr = errors_of(queries, [tr.localize_result() for tr in tracks], idx)
    return {"frames": idx.tolist(), "t_err": dt.tolist(), "R_err_deg": dr.tolist(),
            "latency_s": [tr.latency_s for tr in tracks],
            "tracked": [tr.tracked for tr in tracks],
            "by_check": [tr.by_check for tr in tracks],
            "by_frame": [tr.by_frame for tr in tracks],
            "unconfirmed": [tr.unconfirmed for tr in tracks],
            "relocalized": [tr.relocalized for tr in tracks],
            "full_no_prior": [tr.error is None and not tr.attempted for tr in tracks],
            "flagged": [tr.error is not None for tr in tracks],
            "rejected": [tr.rejected for tr in tracks],
            "verdict": [tr.verdict for tr in tracks],
            "confidence": [tr.confidence for tr in tracks],
            "inliers": [int(tr.n_inliers) for tr in tracks],
            "rendered": [int(tr.n_rendered) for tr in tracks]}


def run_full(loc: Localizer, queries, idx: np.ndarray, progress: bool) -> dict:
    """Localize frames ``idx`` one by one in full; per-frame arrays of the run."""
    from tqdm import tqdm

    results, secs = [], []
    for i in tqdm(idx, desc="full", unit="frame", disable=not progress):
        t0 = time.perf_counter()
        try:
            # read at the scene's size: a --downscale'd scene's K fit the scaled image
            r = loc.localize_query(loc.prepare(
                frame_image(queries.image_paths[i], queries.sizes[i]), queries.K[i],
                queries.dist[i], name=queries.names[i]))
        except VrsError:
            r = None
        results.append(r)
        secs.append(time.perf_counter() - t0)
    dt, dr = errors_of(queries, results, idx)
    return {"frames": idx.tolist(), "t_err": dt.tolist(), "R_err_deg": dr.tolist(),
            "latency_s": secs, "inliers": [int(r.n_inliers) if r is not None else 0
                                           for r in results],
            "rendered": [int(r.n_rendered) if r is not None else 0 for r in results]}


def run_sift(scene, queries, args, scale: float) -> dict:
    """The COLMAP SIFT reference on the same frames (benchmarks.localize.sift_row)."""
    from benchmarks.localize import sift_row

    ctx = types.SimpleNamespace(name=Path(str(scene.root)).resolve().name, scene=scene,
                                queries=queries)
    row = sift_row(ctx, args, scale)
    pq = row["per_query"]
    return {"frames": list(range(len(queries))), "t_err": pq["t_err_m"],
            "R_err_deg": pq["R_err_deg"],
            "latency_s": [float(sum(tm.values())) for tm in pq["timing_s"]],
            "inliers": pq["inliers"]}


def recovery(run: dict, gap_end: int, scale: float) -> dict:
    """Frames after a gap (the first frame index >= ``gap_end`` in the run) until tracked
    again and until right again (within RIGHT); None if never."""
    pos = [j for j, f in enumerate(run["frames"]) if f >= gap_end]
    tracked = right = None
    for n, j in enumerate(pos):
        if tracked is None and run["tracked"][j]:
            tracked = n
        if right is None and (run["t_err"][j] < RIGHT[0] * scale
                              and run["R_err_deg"][j] < RIGHT[1]):
            right = n
    return {"frames_until_tracked": tracked, "frames_until_right": right,
            "first_frame_after_gap": run["frames"][pos[0]] if pos else None}


def summary_row(label: str, run: dict, scale: float) -> dict:
    dt = np.asarray(run["t_err"], np.float64)
    dr = np.asarray(run["R_err_deg"], np.float64)
    row = {"run": label, "n_frames": len(dt),
           "recall_relative": metrics.relative_recall(dt, dr, scale),
           "median_t_rel": float(np.median(dt) / scale), "median_R_deg": float(np.median(dr)),
           "median_latency_s": float(np.median(run["latency_s"])),
           "mean_latency_s": float(np.mean(run["latency_s"]))}
    if "tracked" in run:
        lat = np.asarray(run["latency_s"])
        tr = np.asarray(run["tracked"], bool)
        wrong = (dt > WRONG_T * scale) | (dr > WRONG_R) | ~np.isfinite(dt)
        row.update(n_tracked=int(tr.sum()), n_relocalized=int(np.sum(run["relocalized"])),
                   n_by_check=int(np.sum(run.get("by_check", [False] * len(tr)))),
                   n_by_frame=int(np.sum(run.get("by_frame", [False] * len(tr)))),
                   n_unconfirmed=int(np.sum(run.get("unconfirmed", [False] * len(tr)))),
                   # poses more than 5% / 5 deg off that the result calls "localized"
                   n_wrong_localized=int(np.sum(wrong & (np.asarray(run["verdict"])
                                                         == "localized"))),
                   n_full_no_prior=int(np.sum(run["full_no_prior"])),
                   n_flagged=int(np.sum(run["flagged"])),
                   median_latency_tracked_s=float(np.median(lat[tr])) if tr.any() else None,
                   # lost: a tracking attempt rejected; recovered: then right (RIGHT)
                   n_lost=int(np.sum(run["relocalized"])),
                   n_lost_recovered=int(sum(
                       rel and d < RIGHT[0] * scale and r < RIGHT[1]
                       for rel, d, r in zip(run["relocalized"], dt, dr, strict=True))))
    return row


def print_table(rows: list[dict], title: str) -> None:
    print(common.table(
        ["run", "frames", "1%/1deg", "2%/2deg", "median (% scale, deg)", "median s/frame",
         "tracked s/frame", "tracked (by check, by frame)", "relocalized", "lost+recovered",
         "full (no prior)", "flagged", "wrong 'localized'"],
        [[r["run"], r["n_frames"], common.pct(r["recall_relative"]["1pct_1deg"]),
          common.pct(r["recall_relative"]["2pct_2deg"]),
          f"{common.fmt(100 * r['median_t_rel'])}, {common.fmt(r['median_R_deg'])}",
          common.fmt(r["median_latency_s"], 3), common.fmt(r.get("median_latency_tracked_s"), 3),
          f"{r['n_tracked']} ({r['n_by_check']}, {r.get('n_by_frame', 0)})"
          if "n_by_check" in r else "-",
          r.get("n_relocalized", "-"),
          f"{r['n_lost']}+{r['n_lost_recovered']}" if "n_lost" in r else "-",
          r.get("n_full_no_prior", "-"), r.get("n_flagged", "-"),
          r.get("n_wrong_localized", "-")] for r in rows],
        title=title))


def plot(runs: dict[str, dict], scale: float, path: str, jump: tuple[int, int] | None) -> Path:
    """Per-frame translation error (% of the scene scale) and latency of every run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from benchmarks.figures import save

    fig, (ax0, ax1) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    styles = {"full": ("tab:blue", "-"), "cached": ("tab:purple", "-."),
              "track": ("tab:orange", "-"),
              "sift": ("tab:gray", ":"), "track, jump": ("tab:green", "--")}
    for label, run in runs.items():
        c, ls = styles.get(label, ("k", "-"))
        x = np.asarray(run["frames"])
        err = np.minimum(100.0 * np.asarray(run["t_err"], np.float64) / scale, 1e3)
        ax0.plot(x, np.maximum(err, 1e-3), ls, color=c, label=label, lw=1.2)
        ax1.plot(x, run["latency_s"], ls, color=c, label=label, lw=1.2)
        if "tracked" in run:
            rel = np.asarray(run["relocalized"], bool)
            ax0.plot(x[rel], np.maximum(err[rel], 1e-3), "x", color=c, ms=7)
    if jump is not None:
        for ax in (ax0, ax1):
            ax.axvspan(jump[0] - 0.5, jump[1] - 0.5, color="tab:green", alpha=0.12,
                       label="dropped (jump)" if ax is ax0 else None)
    ax0.set_yscale("log")
    ax0.set_ylabel("translation error (% of scene scale)")
    ax0.axhline(100 * RIGHT[0], color="k", lw=0.6, alpha=0.5)
    ax0.legend(fontsize=8, loc="upper left")
    ax0.set_title("Tracking a stream: error and latency per frame (x: relocalized)")
    ax1.set_yscale("log")
    ax1.set_ylabel("latency (s)")
    ax1.set_xlabel("frame (name order)")
    return save(fig, Path(path))


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    common.check_outputs(args, [common.json_path(args, "track"), args.plot])
    modes = [s.strip() for s in args.modes.split(",") if s.strip()]
    if not modes or any(s not in RUNS for s in modes):
        raise VrsError(f"--modes must list some of {', '.join(RUNS)}, got {args.modes!r}")
    doc = common.base_doc("track", args, argv)
    m = maps.load_map_for(args.map, args.mode)
    cfg = config_of(m, args)
    scene, queries = stream_of(m, args)
    n = len(queries)
    jump = None
    if args.jump_at is not None:
        if args.jump_len < 1 or not 1 <= args.jump_at < n - 1:
            raise VrsError(f"--jump-at must be in [1, {n - 2}] and --jump-len >= 1 "
                           f"({n} frames)")
        jump = (args.jump_at, min(args.jump_at + args.jump_len, n - 1))
    scale = metrics.scene_scale(scene.centers[np.asarray(scene.has_pose, bool)])
    print(f"{n} frames ({queries.names[0]} .. {queries.names[-1]}), scene scale "
          f"{scale:.4g}, {cfg.source} mode, config {args.config or m.config.name}")
    if "cached" in modes and not (cfg.source == "render" and cfg.track.cache_mb > 0):
        raise VrsError("--modes cached needs render mode and a track.cache_mb > 0 "
                       "(--track cache_mb=64)")
    loc = Localizer(m, cfg)
    w, h = (int(s) for s in queries.sizes[0])
    loc.warmup(w, h, track=True)  # with the stream's cache: compiles the cached path too
    progress = not args.quiet

    runs: dict[str, dict] = {}
    every = np.arange(n)
    if "full" in modes:
        runs["full"] = run_full(loc, queries, every, progress)
    if "cached" in modes:  # a Localizer of its own: an empty cache, compiled already
        runs["cached"] = run_full(Localizer(m, cfg, cache_mb=cfg.track.cache_mb), queries,
                                  every, progress)
    if "track" in modes:  # each stream keeps its own cache (cfg.track.cache_mb)
        runs["track"] = run_track(loc, queries, every, progress)
    if jump is not None:
        keep = np.concatenate([np.arange(jump[0]), np.arange(jump[1], n)])
        runs["track, jump"] = run_track(loc, queries, keep, progress)
    if "sift" in modes:
        runs["sift"] = run_sift(scene, queries, args, scale)
    rows = [summary_row(k, v, scale) for k, v in runs.items()]
    print()
    print_table(rows, f"Tracking vs full localization, {n} frames in name order "
                      f"(% scale: of {scale:.4g} scene units; latency includes query "
                      "preparation, excludes compilation)")
    rec = None
    if jump is not None:
        rec = {"dropped": list(jump), **recovery(runs["track, jump"], jump[1], scale)}
        print(f"\njump: frames {jump[0]}..{jump[1] - 1} dropped; after it "
              f"{common.fmt(rec['frames_until_tracked'])} frames until tracked again, "
              f"{common.fmt(rec['frames_until_right'])} until right again (within "
              f"{100 * RIGHT[0]:g}% / {RIGHT[1]:g} deg)")
    doc.update({"map_dir": str(args.map), "scene_scale": scale, "n_frames": n,
                "names": list(queries.names), "localize_config": dataclasses.asdict(cfg),
                "rows": rows, "runs": runs, "jump": rec})
    out = common.write_json(common.json_path(args, "track"), doc)
    print(f"\nwrote {out}")
    if args.plot:
        print(f"plot: {plot(runs, scale, args.plot, jump)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
