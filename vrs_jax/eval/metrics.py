"""Localization accuracy as hloc and the paper report it (DESIGN.md section 6).

Errors per query: translation = distance between the camera centres (metres inside,
centimetres in reports), rotation = angle of ``R_est R_gt^T`` (degrees). A query without an
estimate counts as an infinite error, so it lowers every recall and can raise the medians.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from vrs_jax import geometry

# Recall thresholds (translation in metres, rotation in degrees), keyed as in summary.json:
# 5cm/5deg is 7Scenes' standard, 25cm/2deg Cambridge's, 25cm/2deg + 50cm/5deg + 5m/10deg
# Aachen's three bins; 1/1, 2/2 and 10/5 are finer comparisons.
RECALL_THRESHOLDS: dict[str, tuple[float, float]] = {
    "1cm_1deg": (0.01, 1.0),
    "2cm_2deg": (0.02, 2.0),
    "5cm_5deg": (0.05, 5.0),
    "10cm_5deg": (0.10, 5.0),
    "25cm_2deg": (0.25, 2.0),
    "50cm_5deg": (0.50, 5.0),
    "500cm_10deg": (5.0, 10.0),
}


def pose_errors(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray,
                has_estimate: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-query errors; a query without an estimate gets infinite errors.

    Args:
      R_est, t_est: [N, 3, 3], [N, 3] estimated world-to-camera poses (any values where
        ``has_estimate`` is False).
      R_gt, t_gt: [N, 3, 3], [N, 3] ground truth world-to-camera poses.
      has_estimate: [N] bool, or None for all True.
    Returns:
      t_err [N] in metres, R_err [N] in degrees (float64; inf where no estimate or where the
      estimate is not finite).
    """
    R_est, t_est, R_gt, t_gt = (np.asarray(a, dtype=np.float64) for a in (R_est, t_est, R_gt,
                                                                          t_gt))
    n = len(R_gt)
    ok = np.ones(n, dtype=bool) if has_estimate is None else np.asarray(has_estimate, bool)
    ok = ok & np.isfinite(R_est).all(axis=(-1, -2)) & np.isfinite(t_est).all(axis=-1)
    R_safe = np.where(ok[:, None, None], R_est, np.eye(3))
    t_safe = np.where(ok[:, None], t_est, 0.0)
    dt, dr = geometry.pose_errors(R_safe, t_safe, R_gt, t_gt)
    return np.where(ok, dt, np.inf), np.where(ok, dr, np.inf)


def recall(t_err: np.ndarray, R_err: np.ndarray,
           thresholds: Mapping[str, tuple[float, float]] = RECALL_THRESHOLDS
           ) -> dict[str, float]:
    """Fraction of queries [0, 1] with ``t_err <= t_max`` (m) and ``R_err <= R_max`` (deg).

    Inclusive bounds, as hloc's evaluation (``(t <= th_t) & (R <= th_R)``). No queries -> 0.
    """
    t_err, R_err = np.asarray(t_err, np.float64), np.asarray(R_err, np.float64)
    if t_err.size == 0:
        return {k: 0.0 for k in thresholds}
    return {k: float(np.mean((t_err <= tm) & (R_err <= rm))) for k, (tm, rm) in thresholds.items()}


# Relative recall thresholds (translation as a fraction of the scene scale, rotation in
# degrees), for scenes whose units are arbitrary (NeRF synthetic, LLFF) or small (DTU).
RELATIVE_THRESHOLDS: dict[str, tuple[float, float]] = {
    "1pct_1deg": (0.01, 1.0),
    "2pct_2deg": (0.02, 2.0),
    "5pct_5deg": (0.05, 5.0),
}


def scene_scale(centers: np.ndarray) -> float:
    """Scale of a scene: median distance of the camera centres [N, 3] to their centroid.

    In the scene's units (metres for metric datasets); nan for no cameras.
    """
    c = np.asarray(centers, np.float64).reshape(-1, 3)
    if len(c) == 0:
        return math.nan
    return float(np.median(np.linalg.norm(c - c.mean(axis=0), axis=1)))


def relative_recall(t_err: np.ndarray, R_err: np.ndarray, scale: float,
                    thresholds: Mapping[str, tuple[float, float]] = RELATIVE_THRESHOLDS
                    ) -> dict[str, float]:
    """:func:`recall` with translation thresholds given as fractions of ``scale``."""
    return recall(t_err, R_err, {k: (f * scale, r) for k, (f, r) in thresholds.items()})


def median_errors(t_err: np.ndarray, R_err: np.ndarray) -> tuple[float, float]:
    """(median translation error in cm, median rotation error in degrees); inf possible
    (more than half the queries failed), nan for no queries."""
    t_err, R_err = np.asarray(t_err, np.float64), np.asarray(R_err, np.float64)
    if t_err.size == 0:
        return math.nan, math.nan
    return float(np.median(t_err) * 100.0), float(np.median(R_err))


def summarize(t_err: np.ndarray, R_err: np.ndarray) -> dict:
    """The DESIGN.md metrics of a set of queries.

    Returns:
      dict with ``n_queries``, ``n_failed`` (infinite error), ``median_t_cm``,
      ``median_R_deg`` and ``recall`` ({key of RECALL_THRESHOLDS: fraction in [0, 1]}).
      Medians may be inf; use :func:`json_ready` before writing strict JSON.
    """
    t_err, R_err = np.asarray(t_err, np.float64), np.asarray(R_err, np.float64)
    med_t, med_R = median_errors(t_err, R_err)
    return {
        "n_queries": int(t_err.size),
        "n_failed": int(np.sum(~(np.isfinite(t_err) & np.isfinite(R_err)))),
        "median_t_cm": med_t,
        "median_R_deg": med_R,
        "recall": recall(t_err, R_err),
    }


def cumulative_curve(errors: np.ndarray, max_error: float | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative error distribution for plots: fraction of queries with error <= x.

    Args:
      errors: [N] errors (any unit; inf for failures, which never enter the curve but count
        in the denominator).
      max_error: drop the steps beyond this error (the curve then ends at its value there).
    Returns:
      x [S] sorted finite errors (S <= N, starting with a 0 point), y [S] fractions in [0, 1]
      (a step function: y[i] queries have error <= x[i]).
    """
    e = np.sort(np.asarray(errors, np.float64).reshape(-1))
    n = e.size
    if n == 0:
        return np.zeros(1), np.zeros(1)
    finite = e[np.isfinite(e)]
    y = np.arange(1, finite.size + 1) / n
    x = np.concatenate([[0.0], finite])
    y = np.concatenate([[np.mean(e <= 0.0)], y])
    if max_error is not None:
        keep = x <= max_error
        x = np.concatenate([x[keep], [max_error]])
        y = np.concatenate([y[keep], [np.mean(e <= max_error)]])
    return x, y


def json_ready(obj):
    """A copy of nested dicts/lists/numbers with non-finite floats as None (strict JSON) and
    numpy scalars/arrays as Python numbers/lists."""
    if isinstance(obj, Mapping):
        return {str(k): json_ready(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_ready(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return json_ready(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer, int)):
        return int(obj)
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def format_table(summary: Mapping, title: str | None = None) -> str:
    """A plain-text two-column table of a :func:`summarize` dict (cm, deg, % recall)."""
    rows = [("queries", f"{summary['n_queries']}"),
            ("failed (no estimate)", f"{summary.get('n_failed', 0)}"),
            ("median translation error (cm)", _fmt(summary["median_t_cm"])),
            ("median rotation error (deg)", _fmt(summary["median_R_deg"]))]
    for key, value in summary["recall"].items():
        tm, rm = RECALL_THRESHOLDS.get(key, (math.nan, math.nan))
        label = f"recall @ {tm * 100:g} cm, {rm:g} deg (%)" if key in RECALL_THRESHOLDS else key
        rows.append((label, f"{100.0 * value:.1f}"))
    width = max(len(r[0]) for r in rows)
    lines = [title] if title else []
    lines += [f"{k:<{width}}  {v:>8}" for k, v in rows]
    return "\n".join(lines)


def _fmt(x) -> str:
    if x is None:
        return "inf"
    x = float(x)
    return f"{x:.2f}" if math.isfinite(x) else str(x)
