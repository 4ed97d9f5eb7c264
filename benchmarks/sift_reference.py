"""The COLMAP SIFT reference row: a plain hierarchical SIFT localizer on one scene.

    python -m benchmarks.sift_reference --format nerf --root DATA/dtu_scan24 --query-every 5 \\
        [--json out.json] [--work DIR] [--max-queries N]

Loads the scene (``vrs_jax.data.readers.load_scene``, the same --format/--root/
--query-every/--downscale/--opt arguments as the experiments), builds the SIFT reference map
of its reference images with their known poses (:func:`vrs_jax.reference.build_sift_map`:
COLMAP SIFT, exhaustive matching + geometric verification, triangulation), localizes every
query (:func:`vrs_jax.reference.localize_sift`) and reports: median translation / rotation
error, recall at the absolute thresholds of ``eval.metrics.RECALL_THRESHOLDS`` (1cm/1deg,
2cm/2deg, 5cm/5deg, 10cm/5deg, ...), recall at thresholds RELATIVE to the scene scale (1%/1deg,
2%/2deg, 5%/5deg; scale = median distance of all cameras to their centroid, in the scene's
units), failures (no pose: infinite error), median distinct inliers, seconds per query by
stage, and the map bytes (uint8 SIFT descriptors of the 3D-linked keypoints, keypoint
positions, 3D points, poses).

Translation errors are reported in "cm" = 0.01 scene units: centimetres for metric scenes
(7Scenes, the synthetic room, DTU scan24's transforms.json); for NeRF synthetic and LLFF the
units are arbitrary, so read the relative recall there. The JSON row has the keys of
``benchmarks.localize``'s rows where they mean the same thing (mode "sift").
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from benchmarks import common
from vrs_jax.cli.common import add_scene_args, load_scene_from_args
from vrs_jax.errors import VrsError, cli_main
from vrs_jax.eval import metrics
from vrs_jax.reference import sift

STAGES = ("read", "extract", "match", "pose")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.sift_reference", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_scene_args(p)
    p.add_argument("--name", default=None, help="scene label in the row (default: the root "
                                                "folder's name)")
    p.add_argument("--work", default=None, help="folder of COLMAP's database and model "
                   f"(default {common.DEFAULT_WORK}/sift/NAME; replaced)")
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/sift_reference.json)")
    common.add_overwrite_arg(p)
    p.add_argument("--max-queries", type=int, default=None,
                   help="localize at most N queries (evenly spaced; default all)")
    d = sift.SiftReferenceConfig()
    p.add_argument("--max-features", type=int, default=d.max_num_features,
                   help="SIFT features per image (COLMAP's default %(default)s)")
    p.add_argument("--ransac-px", type=float, default=d.ransac_max_error_px,
                   help="RANSAC max reprojection error in pixels (hloc: %(default)s)")
    p.add_argument("--min-inliers", type=int, default=d.min_inliers,
                   help="fewer inliers = failure (default %(default)s)")
    p.add_argument("--keep-unlinked", action="store_true",
                   help="keep map keypoints without a 3D point for matching (as hloc does; "
                        "counted in the map bytes)")
    p.add_argument("--matcher", default=d.matcher, choices=("numpy", "colmap"),
                   help="query matcher: numpy (COLMAP's rule on BLAS) or colmap (pycolmap's "
                        "CPU matcher, same matches, slower)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def evaluate(queries, results: list[sift.SiftResult], scale: float) -> dict:
    """Accuracy of the results against the queries' ground truth.

    Returns median_t_cm, median_R_deg (over all queries, failures infinite), recall
    (absolute thresholds), recall_relative (fractions of ``scale``), median_t_rel (median
    translation error / scale), n_failed and per-query errors t_err_m / R_err_deg.
    """
    gt = np.asarray(queries.has_pose, bool)
    if not gt.all():
        raise VrsError(f"{int((~gt).sum())} queries have no ground-truth pose", queries.root)
    R, t, ok = sift.result_arrays(results)
    dt, dr = metrics.pose_errors(R, t, queries.R, queries.t, has_estimate=ok)
    s = metrics.summarize(dt, dr)
    return {"median_t_cm": s["median_t_cm"], "median_R_deg": s["median_R_deg"],
            "recall": s["recall"], "recall_relative": metrics.relative_recall(dt, dr, scale),
            "median_t_rel": float(np.median(dt) / scale) if len(dt) else None,
            "n_failed": s["n_failed"], "t_err_m": dt, "R_err_deg": dr}


def row_of(name: str, queries, results: list[sift.SiftResult], sift_map: sift.SiftMap,
           cfg: sift.SiftReferenceConfig, scale: float, wall_s: float) -> dict:
    """The JSON/table row of the reference on one scene (benchmarks.localize's keys where
    they mean the same; mode "sift"; failures are no pose, never a fallback)."""
    ev = evaluate(queries, results, scale)
    timing = {k: float(np.median([r.timing[k] for r in results])) if results else None
              for k in STAGES}
    mb = sift.sift_map_bytes(sift_map)
    return {
        "scene": name, "mode": "sift", "n_queries": len(results),
        "median_t_cm": ev["median_t_cm"], "median_R_deg": ev["median_R_deg"],
        "recall": ev["recall"], "recall_relative": ev["recall_relative"],
        "scene_scale": scale, "median_t_rel": ev["median_t_rel"],
        "n_success": int(sum(r.success for r in results)), "n_failed": ev["n_failed"],
        "n_fallback": 0,
        "median_inliers": float(np.median([r.n_inliers for r in results])) if results else 0.0,
        "median_correspondences": float(np.median([r.n_correspondences for r in results]))
        if results else 0.0,
        "timing_s": timing,
        "localize_s_per_query": float(sum(v or 0.0 for v in timing.values())),
        "wall_s_per_query": wall_s / max(len(results), 1),
        "map_bytes": mb, "map_stats": sift_map.stats, "sift_config": dataclasses.asdict(cfg),
        "per_query": {"names": [r.name for r in results], "t_err_m": ev["t_err_m"].tolist(),
                      "R_err_deg": ev["R_err_deg"].tolist(),
                      "success": [bool(r.success) for r in results],
                      "fallback": [False] * len(results),
                      "inliers": [int(r.n_inliers) for r in results],
                      "inlier_keypoints": [int(r.n_inlier_keypoints) for r in results],
                      "correspondences": [int(r.n_correspondences) for r in results],
                      "matches": [int(r.n_matches) for r in results],
                      "timing_s": [r.timing for r in results]},
        "measured_at": common.now(),
    }


def accuracy_table(rows: list[dict]) -> str:
    return common.table(
        ["scene", "queries", "median (cm, deg)", "median (% scale)", "1cm/1deg", "2cm/2deg",
         "5cm/5deg", "10cm/5deg", "1%/1deg", "2%/2deg", "5%/5deg", "failed", "inliers",
         "s/query", "map (MB)"],
        [[r["scene"], r["n_queries"],
          f"{common.fmt(r['median_t_cm'])}, {common.fmt(r['median_R_deg'])}",
          common.fmt(None if r["median_t_rel"] is None else 100.0 * r["median_t_rel"]),
          *(common.pct(r["recall"][k]) for k in ("1cm_1deg", "2cm_2deg", "5cm_5deg",
                                                 "10cm_5deg")),
          *(common.pct(r["recall_relative"][k]) for k in metrics.RELATIVE_THRESHOLDS),
          r["n_failed"], common.fmt(r["median_inliers"], 0),
          common.fmt(r["localize_s_per_query"], 3), common.fmt(r["map_bytes"]["total"] / 1e6, 3)]
         for r in rows],
        title="COLMAP SIFT reference (scale = median camera distance to the centroid)")


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    common.check_outputs(args, [common.json_path(args, "sift_reference")])
    doc = common.base_doc("sift_reference", args, argv)
    scene = load_scene_from_args(args)
    name = args.name or Path(args.root).resolve().name
    queries = scene.queries()
    if len(queries) == 0:
        raise VrsError("the scene has no query images (give --query-every N for formats "
                       "without a split)", args.root)
    queries = queries.subset(common.evenly_spaced(len(queries), args.max_queries))
    cfg = sift.SiftReferenceConfig(max_num_features=args.max_features,
                                   ransac_max_error_px=args.ransac_px,
                                   min_inliers=args.min_inliers,
                                   keep_unlinked=args.keep_unlinked, matcher=args.matcher)
    work = Path(args.work) if args.work else Path(common.DEFAULT_WORK) / "sift" / name
    scale = metrics.scene_scale(scene.centers[np.asarray(scene.has_pose, bool)])
    print(f"[{name}] {len(scene) - int(scene.is_query.sum())} references, {len(queries)} "
          f"queries, scene scale {scale:.4g} (scene units)")
    sift_map = sift.build_sift_map(scene, work, cfg, progress=not args.quiet)
    st = sift_map.stats
    print(f"[{name}] map: {st['n_points3d']} points, {st['n_keypoints_kept']} linked keypoints "
          f"of {st['n_keypoints_extracted']}, {st['n_verified_pairs']} verified pairs, "
          f"{st['total_s']:.1f} s")
    t0 = time.perf_counter()
    results = sift.localize_sift(sift_map, queries, cfg, progress=not args.quiet)
    wall = time.perf_counter() - t0
    row = row_of(name, queries, results, sift_map, cfg, scale, wall)
    print()
    print(accuracy_table([row]))
    doc.update({"scene": {"name": name, "format": scene.format, "root": str(scene.root),
                          "n_references": int((~scene.is_query).sum()),
                          "n_queries_scene": int(scene.is_query.sum()),
                          "scene_scale": scale},
                "rows": [row]})
    out = common.write_json(common.json_path(args, "sift_reference"), doc)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
