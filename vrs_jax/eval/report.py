"""The summary of one localization run (summary.json): accuracy, work and map size."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from vrs_jax.data.scene import Scene
from vrs_jax.eval import metrics
from vrs_jax.localize.batch import rays_rendered
from vrs_jax.localize.confidence import result_verdicts
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.localize.render import nerf_evals_per_ray
from vrs_jax.localize.stages import LocalizeResult
from vrs_jax.maps import Map, map_bytes


def summarize(queries: Scene, results: list[LocalizeResult | None], info: dict, m: Map,
              cfg: LocalizeConfig, map_dir: str | Path) -> dict[str, Any]:
    """summary.json: metrics where ground truth exists (a query without a result counts as
    failed), map bytes of the variant this mode loads, time per stage, work per query, and
    how many results each verdict of the pose confidence has (``n_localized``,
    ``n_uncertain``, ``n_failed``: no PnP pose or no result; localize.confidence)."""
    n = len(results)
    has = np.array([r is not None for r in results], bool)
    R = np.stack([np.asarray(r.R, np.float64) if r is not None else np.eye(3) for r in results]
                 ) if n else np.zeros((0, 3, 3))
    t = np.stack([np.asarray(r.t, np.float64) if r is not None else np.zeros(3)
                  for r in results]) if n else np.zeros((0, 3))
    gt = np.asarray(queries.has_pose, bool)
    sizes = map_bytes(map_dir)
    variant = "vrs" if cfg.source == "render" else "real"
    out: dict[str, Any] = {"n_queries": n, "mode": cfg.source, "config": m.config.name,
                           "patch_size": (cfg.patches or m.config.features.patches).size,
                           "depth_guided": cfg.depth_guided}
    if gt.any():
        dt, dr = metrics.pose_errors(R[gt], t[gt], queries.R[gt], queries.t[gt], has[gt])
        s = metrics.summarize(dt, dr)
        out.update({"median_t_cm": s["median_t_cm"], "median_R_deg": s["median_R_deg"],
                    "recall": s["recall"], "n_with_ground_truth": int(gt.sum())})
    else:
        out.update({"median_t_cm": None, "median_R_deg": None, "recall": None,
                    "n_with_ground_truth": 0})
    done = [r for r in results if r is not None]
    out.update({"map_bytes": {"total": sizes[variant], "egm": sizes["egm"],
                              "ilm": sizes["ilm"] if variant == "vrs" else 0,
                              "descriptors": sizes["descriptors"] if variant == "real" else 0},
                "timing_s": info["timing_s"],
                "rays_per_query": info["rays_per_query"],
                "nerf_evals_per_query": info["nerf_evals_per_query"],
                "nerf_evals_per_query_median": median_evals(m, cfg, results),
                "full_image_evals_per_query": info.get("full_image_evals_per_query", 0.0),
                "n_success": info["n_success"],
                "n_fallback": int(sum(bool(r.fallback) for r in done)),
                "n_unreadable": int(n - len(done)),
                **verdict_counts(result_verdicts(m, results, cfg.confidence)[1]),
                "errors": info.get("errors", {}),
                "median_inliers": float(np.median([int(r.n_inliers) for r in done]))
                if done else 0.0})
    return out


def verdict_counts(verdict) -> dict[str, int]:
    """``n_localized``, ``n_uncertain``, ``n_failed`` of an array of verdicts."""
    v = np.asarray(verdict, object)
    return {f"n_{k}": int(np.sum(v == k)) for k in ("localized", "uncertain", "failed")}


def median_evals(m: Map, cfg: LocalizeConfig, results: list[LocalizeResult | None]) -> float:
    """Median NeRF evaluations per query over the queries with a result (0 in real-patch
    mode; the summary's ``nerf_evals_per_query`` is the mean)."""
    if cfg.source != "render":
        return 0.0
    return rays_rendered(m, cfg, results, np.median) * nerf_evals_per_ray(m, cfg)
