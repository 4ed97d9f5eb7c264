"""Localize query images against a vrs-jax map.

    python -m experiments.localize --map MAPDIR --out OUTDIR [--mode render|real]
        [--format F --root DIR [--query-every N] | --images DIR --queries LIST]
        [--patch-size P] [--top-k K] [--full-sampling] [--sequence] [--basename] [--report]
        [--overwrite] [--verbose]

The queries default to the map's own held-out split (its dataset and reader options are
recorded in the map); --format/--root name another dataset; --images/--queries name a folder
of query photos and an hloc query list with intrinsics (``name MODEL width height params...``,
COLMAP camera models; no ground truth, so no recall). Query images that are map images
are refused. Writes OUTDIR/results.txt (one line per query: ``name qw qx qy qz tx ty tz``,
world-to-camera; --basename writes bare file names as the Aachen benchmark wants) and
OUTDIR/summary.json (metrics when the queries have ground truth, map bytes, median time per
stage, rays and NeRF evaluations per query, per-query diagnostics). A query that fails (no
keypoints, no matches, RANSAC failure) still gets a line: the pose of its top-1 retrieved
reference image, flagged in summary.json; an unreadable query image is listed with its reason.
--sequence localizes the queries in name order as a video stream (``Localizer.track``): the
first frame, and any frame whose tracking is rejected, in full; every other frame by the
guided pass alone from the pose predicted by constant velocity (no retrieval, no first
pass), checked by a pass without the prediction (render mode with ``cpu-small``: both on
the nearest references' own-view descriptors, rendered once per stream and cached).
summary.json then gives per query whether it was ``tracked``, its confidence and its
``latency_s``, and under ``tracking`` the counts and the stream's descriptor cache (hits,
misses); a blank or unreadable frame is listed with its reason and tracking resumes after it.
An existing --out is never replaced without --overwrite, and only once the new run is
complete (written into OUTDIR.tmp-PID first; OUTDIR.lock marks a folder in use). A run record
(command line, settings, code and library versions, timings) goes to OUTDIR/run.json.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from vrs_jax import fileio, localize, maps
from vrs_jax.cli.common import (
    HelpFormatter,
    add_scene_args,
    count_at_least,
    load_scene_from_args,
    prog,
    record_run,
    start_run,
)
from vrs_jax.data.readers import FORMATS
from vrs_jax.data.readers.query_list import query_scene as query_list_scene
from vrs_jax.errors import VrsError, cli_main
from vrs_jax.eval import metrics
from vrs_jax.eval.report import summarize
from vrs_jax.eval.results import write_results
from vrs_jax.features.patches import PATCH_SIZES
from vrs_jax.localize.batch import localize_scene
from vrs_jax.localize.confidence import LOCALIZED_AT, result_verdicts


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog("experiments.localize"),
                                description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("--map", required=True, help="map folder written by experiments.train*")
    add_scene_args(p, required=False)
    p.add_argument("--images", metavar="DIR",
                   help="folder of query images (with --queries; instead of --format/--root)")
    p.add_argument("--queries", metavar="LIST",
                   help="hloc query list with intrinsics, names relative to --images")
    p.add_argument("--out", required=True, help="output folder (results.txt, summary.json)")
    p.add_argument("--config", default="cpu-small", choices=sorted(localize.CONFIGS),
                   help="named query-time configuration (retrieval, matching, rendering, PnP)")
    p.add_argument("--mode", default="render", choices=["render", "real", "gt"],
                   help="render: VRS-NeRF (NeRF-rendered patches); real: the hierarchical "
                        "baseline (the map's stored descriptors of real reference patches); "
                        "gt: an alias of real")
    p.add_argument("--patch-size", type=int, default=None, choices=PATCH_SIZES,
                   help="rendered patch size P (render mode; default: the map's)")
    p.add_argument("--literal", action="store_true",
                   help="paper-literal patches: axis-aligned whole pixels, no scale/rotation")
    p.add_argument("--top-k", type=count_at_least(1), default=None,
                   help="retrieved reference images")
    p.add_argument("--retries", type=count_at_least(0), default=None,
                   help="a query whose pose is not 'localized' is tried again with the next "
                        "top-k references, up to this many times; the most confident result "
                        "is kept (default: the config's)")
    p.add_argument("--full-sampling", action="store_true",
                   help="render with coarse+fine sampling instead of the depth-guided interval")
    p.add_argument("--sequence", action="store_true",
                   help="the queries are a video stream: localize them in name order, "
                        "tracking each frame from the previous poses (guided pass from a "
                        "constant-velocity prediction) and localizing in full only the first "
                        "frame and frames whose tracking is rejected")
    p.add_argument("--basename", action="store_true",
                   help="write bare file names in results.txt (Aachen benchmark)")
    p.add_argument("--no-timing", action="store_true",
                   help="run the fused jitted localize (no per-stage times)")
    p.add_argument("--report", action="store_true",
                   help="also write OUTDIR/report.html: a self-contained page with the results "
                        "table and, per query, its matches and its rendered and real patches "
                        "(runs the stages once more per query)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing --out (once the new run is complete)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--verbose", action="store_true", help="debug log lines")
    return p


def make_config(m: maps.Map, args) -> localize.LocalizeConfig:
    """The named query-time config with the command line's overrides."""
    over = {"source": args.mode}
    if args.patch_size is not None or args.literal:
        patches = m.config.features.patches
        if args.patch_size is not None:
            patches = dataclasses.replace(patches, size=args.patch_size)
        if args.literal:
            patches = dataclasses.replace(patches, mode="literal")
        over["patches"] = patches
    if args.top_k is not None:
        over["top_k"] = args.top_k
    if args.retries is not None:
        over["retries"] = args.retries
    if args.full_sampling:
        over["depth_guided"] = False
    return localize.get_config(args.config, **over)


def query_scene(m: maps.Map, args, sfm_dir: Path):
    """The query images: the map's own held-out split, those of the named dataset (a photo
    folder is posed by SfM with its work files in ``sfm_dir``), or those of a query list."""
    if args.images is not None or args.queries is not None:
        if args.images is None or args.queries is None:
            raise VrsError("pass both --images and --queries")
        if args.root is not None or args.fmt is not None:
            raise VrsError("--images/--queries and --format/--root are exclusive: name one "
                           "set of queries")
        queries = query_list_scene(args.queries, args.images)
        refuse_map_images(m, queries)
        return queries
    if args.root is None and args.fmt is None:
        src = m.source
        sfm_dir = Path(args.map) / "sfm"  # photos: the map's own SfM poses (same frame)
        if not src.format or not src.root:
            raise VrsError("the map records no dataset; pass --format and --root", args.map)
        meta = Path(args.map) / "map.json"
        if src.format not in (*FORMATS, "images"):
            raise VrsError(f"source: unknown dataset format {src.format!r} (an edited "
                           "map.json?)", meta)
        args.fmt, args.root = src.format, src.root
        opts = dict(src.options)
        args.query_every = _source_count(opts, "query_every", meta)
        args.downscale = _source_count(opts, "downscale", meta)
        args.opt = [f"{k}={v}" for k, v in opts.items() if k not in ("query_every",
                                                                   "downscale")]
    elif args.root is None or args.fmt is None:
        raise VrsError("pass both --format and --root (or neither: the map's own queries)")
    scene = load_scene_from_args(args, sfm_dir=sfm_dir)
    queries = scene.queries()
    if len(queries) == 0:
        raise VrsError("the dataset has no query images (for formats without a split pass "
                       "--query-every N)", scene.root)
    refuse_map_images(m, queries)
    return queries


def _source_count(opts: dict, key: str, meta: Path) -> int | None:
    """The integer reader option ``key`` a map's source records (None when absent)."""
    if key not in opts:
        return None
    try:
        return int(opts[key])
    except (TypeError, ValueError):
        raise VrsError(f"source option {key} must be an integer, got {opts[key]!r} (an "
                       "edited map.json?)", meta) from None


def refuse_map_images(m: maps.Map, queries) -> None:
    """VrsError if any query image is one of the map's reference images (a split mismatch
    would leak test images into the map). When the map records its image folder and the
    queries come from another one, the image files are compared (photos in two folders may
    share names); else the names."""
    if m.source.root and Path(m.source.root).resolve() != Path(queries.root).resolve():
        ref_files = {(Path(m.source.root) / n).resolve() for n in m.names}
        leaked = sorted(n for n, p in zip(queries.names, queries.image_paths, strict=True)
                        if Path(p).resolve() in ref_files)
    else:
        leaked = sorted(set(queries.names) & set(m.names))
    if leaked:
        raise VrsError(f"{len(leaked)} query images are map images ({', '.join(leaked[:3])}"
                       f"{' ...' if len(leaked) > 3 else ''}): the split differs from the map's",
                       queries.root)


def run(args, argv: list[str] | None = None) -> dict:
    """Localize into a fresh staging folder under the lock of --out; it replaces --out only
    once complete (an existing --out needs --overwrite), so a failed run changes nothing."""
    start_run(args)
    t_start = time.perf_counter()
    out = Path(args.out)
    fileio.check_apart(out, [args.map, args.root, args.images, args.queries])
    fileio.refuse_map_part(out)  # a run never replaces a map, even with --overwrite
    with fileio.folder_lock(out):
        fileio.check_new(out, args.overwrite)
        with fileio.staged_folder(out) as stage:
            summary, title = localize_into(stage, args, argv, t_start)
    if summary["recall"] is not None:
        print(metrics.format_table(summary, title=title))
    print(f"{summary['n_success']}/{summary['n_queries']} localized, {summary['n_fallback']} "
          f"fallback, {summary['n_unreadable']} unreadable; results in {out / 'results.txt'}")
    if "tracking" in summary:
        tk = summary["tracking"]
        print(f"tracking: {tk['n_tracked']} tracked ({tk['n_by_check']} by the check pass, "
              f"{tk['n_by_frame']} by the frame pass), "
              f"{tk['n_relocalized']} relocalized, "
              f"{tk['n_full']} localized in full without a prior, {tk['n_flagged']} flagged")
    print(f"verdicts: {summary['n_localized']} localized, {summary['n_uncertain']} uncertain, "
          f"{summary['n_failed']} failed (confidence below {LOCALIZED_AT}: uncertain; no PnP "
          "pose: failed)")
    return summary


def localize_into(out: Path, args, argv: list[str] | None, t_start: float
                  ) -> tuple[dict, str]:
    """Load the map, localize the queries, write results.txt, summary.json and run.json
    into ``out``. Returns (summary, title of its table)."""
    m = maps.load_map_for(args.map, args.mode)
    cfg = make_config(m, args)
    queries = query_scene(m, args, out / "sfm")
    # the map's own dataset (its root recorded in the map) must not be replaced either
    fileio.check_apart(args.out, [queries.root, m.source.root or None])
    tracks = None
    if args.sequence:
        if args.report:
            raise VrsError("--report draws each query's full localization stages; it is not "
                           "available with --sequence")
        queries, results, info, tracks = localize_sequence(m, queries, cfg,
                                                           progress=not args.quiet)
    else:
        results, info = localize_scene(m, queries, cfg, progress=not args.quiet,
                                       timed=not args.no_timing)
    ok = [i for i, r in enumerate(results) if r is not None]
    R = np.stack([np.asarray(results[i].R, np.float64) for i in ok]) if ok else np.zeros((0, 3,
                                                                                        3))
    t = np.stack([np.asarray(results[i].t, np.float64) for i in ok]) if ok else np.zeros((0, 3))
    write_results(out / "results.txt", [queries.names[i] for i in ok], R, t,
                  basename=args.basename)
    summary = summarize(queries, results, info, m, cfg, Path(args.map))
    conf, verdict = result_verdicts(m, results, cfg.confidence)
    summary["per_query"] = [per_query(n, r, info["errors"].get(n), float(c), str(v),
                                      cfg.pnp.min_inliers)
                            for n, r, c, v in zip(queries.names, results, conf, verdict,
                                                  strict=True)]
    for pq in summary["per_query"]:  # retried queries: attempts made, the one kept
        if pq["name"] in info.get("retried", {}):
            pq["retry"] = info["retried"][pq["name"]]
    if tracks is not None:
        for pq, tr in zip(summary["per_query"], tracks, strict=True):
            pq.update(tracked=tr.tracked, by_check=tr.by_check, by_frame=tr.by_frame,
                      unconfirmed=tr.unconfirmed,
                      relocalized=tr.relocalized,
                      latency_s=round(tr.latency_s, 4), rejected=tr.rejected,
                      frame_rejected=tr.frame_rejected)
        summary["tracking"] = {**tracking_counts(tracks),
                               "descriptor_cache": info.get("stream_cache")}
    fileio.write_json(out / "summary.json", metrics.json_ready(summary))
    if args.report:
        from vrs_jax.eval.html import write_report

        write_report(out / "report.html", m, queries, results, summary, cfg, info["errors"],
                     progress=not args.quiet, confidence=(conf, verdict))
        print(f"report: {Path(args.out) / 'report.html'}")  # where it lands once complete
    record_run(out, args, cfg, {"total": time.perf_counter() - t_start,
                                **{k: v for k, v in info["timing_s"].items() if v is not None}},
               argv)
    return summary, f"{cfg.source} mode, {len(queries)} queries"


def localize_sequence(m: maps.Map, queries, cfg: localize.LocalizeConfig,
                      progress: bool = True) -> tuple:
    """Track the queries in name order (``Localizer.track``, compiled first on the first
    frame's size so that no latency includes compilation). Returns (the queries in that
    order, per query a LocalizeResult or None, run info as ``localize_scene``'s with
    ``timing_s["per_frame"]`` the median latency, the TrackResults)."""
    from vrs_jax.localize.batch import rays_rendered
    from vrs_jax.localize.render import full_image_evals, nerf_evals_per_ray

    queries = queries.subset(np.argsort(np.asarray(queries.names, object), kind="stable"))
    loc = localize.Localizer(m, cfg)
    w, h = (int(s) for s in queries.sizes[0])
    loc.warmup(w, h, track=True)
    tracks = loc.track(list(queries.image_paths), queries.K, list(queries.dist),
                       names=list(queries.names), progress=progress,
                       sizes=list(queries.sizes))  # K of a --downscale'd scene fit these
    results = [tr.localize_result() for tr in tracks]
    done = [r for r in results if r is not None]
    rays = rays_rendered(m, cfg, results)
    lat = [tr.latency_s for tr in tracks if tr.error is None]
    timing = dict.fromkeys(localize.STAGE_NAMES)
    timing.update(query_preparation=None, per_frame=float(np.median(lat)) if lat else None)
    info = {"rays_per_query": rays,
            "nerf_evals_per_query": rays * nerf_evals_per_ray(m, cfg)
            if cfg.source == "render" else 0.0,
            "full_image_evals_per_query": float(np.mean(
                [full_image_evals(m, r.retrieved) for r in done] or [0.0]))
            if cfg.source == "render" else 0.0,
            "timing_s": timing, "n_success": int(sum(bool(r.success) for r in done)),
            "errors": {tr.name: tr.error for tr in tracks if tr.error is not None},
            # the stream's cache of rendered references (render mode, track.cache_mb): entries,
            # bytes, hits, misses, evictions; None without one
            "stream_cache": loc.stream_cache_stats}
    return queries, results, info, tracks


def tracking_counts(tracks) -> dict:
    """How a stream's frames were localized: tracked (by_check: of them, those whose pose is
    the check pass's, the tracking pass's rejected; by_frame: the frame pass's), relocalized
    (tracking rejected, then localized in full), full (no prior: the first frame, or after a
    gap), flagged (unreadable or blank), and the median latency of the tracked and the full ones."""
    med = lambda xs: float(np.median(xs)) if xs else None  # noqa: E731
    full = [tr for tr in tracks if tr.error is None and not tr.tracked]
    return {"n_tracked": sum(tr.tracked for tr in tracks),
            "n_by_check": sum(tr.by_check for tr in tracks),
            "n_by_frame": sum(tr.by_frame for tr in tracks),
            "n_relocalized": sum(tr.relocalized for tr in tracks),
            "n_full": sum(tr.error is None and not tr.attempted for tr in tracks),
            "n_flagged": sum(tr.error is not None for tr in tracks),
            "median_latency_tracked_s": med([tr.latency_s for tr in tracks if tr.tracked]),
            "median_latency_full_s": med([tr.latency_s for tr in full])}


def per_query(name: str, r, error: str | None, confidence: float = 0.0,
              verdict: str = "failed", min_inliers: int = 1) -> dict:
    """A query's diagnostics for summary.json: success, fallback, inliers, matches, the
    inliers' geometry (coverage of the query image, median ray angle with the map views,
    relative depth spread, the camera centre's standard deviation from the final and from
    the first pass's inliers, in map units; None without inliers; the distance to the
    farthest pose of the query's other attempts, None without a retry's pose), the pose
    ``confidence``
    in [0, 1] and its
    ``verdict`` (localized / uncertain / failed; localize.confidence) and why it has no PnP
    pose (``error``: None when localized; localize.failure_reason with the PnP config's
    ``min_inliers``)."""
    if r is None:
        return {"name": name, "success": False, "fallback": False, "inliers": 0, "matches": 0,
                "inlier_coverage": None, "inlier_ray_angle_deg": None,
                "inlier_depth_spread": None, "inlier_centre_std": None,
                "centre_std_first": None, "attempt_shift": None, "confidence": 0.0,
                "verdict": "failed",
                "error": error or "no result"}
    ok = bool(r.success)
    geo = {k: (float(v) if np.isfinite(v) else None) for k, v in (
        ("inlier_coverage", r.inlier_coverage), ("inlier_ray_angle_deg", r.inlier_ray_angle_deg),
        ("inlier_depth_spread", r.inlier_depth_spread),
        ("inlier_centre_std", getattr(r, "inlier_centre_std", np.nan)),
        ("centre_std_first", getattr(r, "centre_std_first", np.nan)),
        ("attempt_shift", getattr(r, "attempt_shift", np.nan)))}
    return {"name": name, "success": ok, "fallback": bool(r.fallback),
            "inliers": int(r.n_inliers), "matches": int(r.n_matches), **geo,
            "confidence": round(confidence, 4), "verdict": verdict,
            "error": localize.failure_reason(r, min_inliers)}


@cli_main
def main(argv: list[str] | None = None) -> int:
    run(build_parser().parse_args(argv), argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
