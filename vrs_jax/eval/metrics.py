"""Localization accuracy computed exactly as hloc's ``evaluate`` (docs/design.md, section 6).

Follows ``hloc/pipelines/Cambridge/utils.py::evaluate`` (cvg/Hierarchical-Localization,
checked at commit c13273b, Dec 2025; the 7Scenes and Aachen pipelines reuse it):

- translation error = ``|| -R_gt^T t_gt + R_est^T t_est ||`` (distance between the camera
  centres, metres; centimetres in reports);
- rotation error = ``degrees(|arccos(clip((trace(R_gt^T R_est) - 1) / 2, -1, 1))|)`` (the
  same formula, so the same rounding as hloc, also near 0 and on a threshold);
- a query without an estimate gets translation error ``inf`` and rotation error ``180``
  (hloc's values); it enters the medians with those values (``np.median`` over all queries)
  and never counts as recalled. A non-finite estimate is treated as missing;
- recall at (t_max, R_max) = fraction of all queries with ``t_err < t_max`` **and**
  ``R_err < R_max`` (strict inequalities, as hloc);
- medians = ``np.median`` of each error over all queries (failures included).

hloc prints 1cm/1deg, 2/2, 3/3, 5/5, 25cm/2deg, 50cm/5deg and 5m/10deg; we report the same
plus 10cm/5deg.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from vrs_jax.fileio import json_ready  # noqa: F401  (re-exported: reports use it)
from vrs_jax.geometry import camera_center, quat_to_rot, rot_to_quat

# Recall thresholds (translation in metres, rotation in degrees), keyed as in summary.json:
# hloc's seven (5cm/5deg is 7Scenes' standard, 25cm/2deg Cambridge's, 25cm/2deg + 50cm/5deg
# + 5m/10deg Aachen's three bins) plus 10cm/5deg.
RECALL_THRESHOLDS: dict[str, tuple[float, float]] = {
    "1cm_1deg": (0.01, 1.0),
    "2cm_2deg": (0.02, 2.0),
    "3cm_3deg": (0.03, 3.0),
    "5cm_5deg": (0.05, 5.0),
    "10cm_5deg": (0.10, 5.0),
    "25cm_2deg": (0.25, 2.0),
    "50cm_5deg": (0.50, 5.0),
    "500cm_10deg": (5.0, 10.0),
}

# hloc's errors for a query without an estimate.
MISSING_T_ERR = math.inf
MISSING_R_ERR_DEG = 180.0


def pose_errors(R_est: np.ndarray, t_est: np.ndarray, R_gt: np.ndarray, t_gt: np.ndarray,
                has_estimate: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per-query errors with hloc's formulas; a query without an estimate gets (inf, 180).

    Args:
      R_est, t_est: [N, 3, 3], [N, 3] estimated world-to-camera poses (any values where
        ``has_estimate`` is False).
      R_gt, t_gt: [N, 3, 3], [N, 3] ground truth world-to-camera poses.
      has_estimate: [N] bool, or None for all True.
    Returns:
      t_err [N] in metres, R_err [N] in degrees (float64). Where there is no estimate, or the
      estimate is not finite: t_err = inf, R_err = 180.
    """
    R_est, t_est, R_gt, t_gt = (np.asarray(a, dtype=np.float64) for a in (R_est, t_est, R_gt,
                                                                          t_gt))
    n = len(R_gt)
    ok = np.ones(n, dtype=bool) if has_estimate is None else np.asarray(has_estimate, bool)
    ok = ok & np.isfinite(R_est).all(axis=(-1, -2)) & np.isfinite(t_est).all(axis=-1)
    R_safe = np.where(ok[:, None, None], R_est, np.eye(3))
    # As a results file stores them: the rotation of the nearest unit quaternion. A float32
    # rotation from the solver is orthonormal only to ~1e-7, which the arccos below turns
    # into ~0.02 deg; so a run's summary and `evaluate` on its results.txt give one number.
    R_safe = quat_to_rot(rot_to_quat(R_safe))
    t_safe = np.where(ok[:, None], t_est, 0.0)
    dt = np.linalg.norm(camera_center(R_safe, t_safe) - camera_center(R_gt, t_gt), axis=-1)
    # hloc's arccos formula on purpose (not geometry.rotation_angle's atan2), so that the
    # reported errors are hloc's to the last digit.
    R_gt_T = np.swapaxes(R_gt, -1, -2)
    cos = np.clip((np.trace(R_gt_T @ R_safe, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    dr = np.rad2deg(np.abs(np.arccos(cos)))
    return np.where(ok, dt, MISSING_T_ERR), np.where(ok, dr, MISSING_R_ERR_DEG)


def recall(t_err: np.ndarray, R_err: np.ndarray,
           thresholds: Mapping[str, tuple[float, float]] = RECALL_THRESHOLDS
           ) -> dict[str, float]:
    """Fraction of queries [0, 1] with ``t_err < t_max`` (m) and ``R_err < R_max`` (deg).

    Strict bounds, as hloc's evaluate (``np.mean((errors_t < th_t) & (errors_R < th_R))``):
    a query exactly on a threshold is not recalled. No queries -> 0 (hloc: nan).
    """
    t_err, R_err = np.asarray(t_err, np.float64), np.asarray(R_err, np.float64)
    if t_err.size == 0:
        return {k: 0.0 for k in thresholds}
    return {k: float(np.mean((t_err < tm) & (R_err < rm))) for k, (tm, rm) in thresholds.items()}


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


def recall_interval(t_err: np.ndarray, R_err: np.ndarray,
                    thresholds: Mapping[str, tuple[float, float]] = RECALL_THRESHOLDS,
                    level: float = 0.95, n_boot: int = 2000, seed: int = 0
                    ) -> dict[str, tuple[float, float]]:
    """Percentile-bootstrap interval of each :func:`recall` over the queries.

    The queries [N] are resampled with replacement ``n_boot`` times (a fixed seed: the same
    errors give the same interval); returns {key: (low, high)} at ``level``. With 4 queries
    one query moves a recall by 25 points, and the interval shows it.
    """
    t_err, R_err = np.asarray(t_err, np.float64), np.asarray(R_err, np.float64)
    if t_err.size == 0:
        return {k: (0.0, 0.0) for k in thresholds}
    idx = np.random.default_rng(seed).integers(0, t_err.size, size=(n_boot, t_err.size))
    a = (1.0 - level) / 2.0
    out = {}
    for k, (tm, rm) in thresholds.items():
        hit = ((t_err < tm) & (R_err < rm)).astype(np.float64)
        lo, hi = np.quantile(hit[idx].mean(axis=1), [a, 1.0 - a])
        out[k] = (float(lo), float(hi))
    return out


def median_errors(t_err: np.ndarray, R_err: np.ndarray) -> tuple[float, float]:
    """(median translation error in cm, median rotation error in degrees) over all queries,
    failures included (``np.median``, as hloc). The translation median is inf when at least
    half the queries failed (np.median of an even count averages the two middle values); nan
    for no queries."""
    t_err, R_err = np.asarray(t_err, np.float64), np.asarray(R_err, np.float64)
    if t_err.size == 0:
        return math.nan, math.nan
    return float(np.median(t_err) * 100.0), float(np.median(R_err))


def summarize(t_err: np.ndarray, R_err: np.ndarray) -> dict:
    """The docs/design.md (section 6) metrics of a set of queries.

    Returns:
      dict with ``n_queries``, ``n_failed`` (no estimate: infinite translation error),
      ``median_t_cm``,
      ``median_R_deg`` and ``recall`` ({key of RECALL_THRESHOLDS: fraction in [0, 1]}).
      Medians may be inf; use :func:`json_ready` before writing strict JSON.
    """
    t_err, R_err = np.asarray(t_err, np.float64), np.asarray(R_err, np.float64)
    med_t, med_R = median_errors(t_err, R_err)
    return {
        "n_queries": int(t_err.size),
        "n_failed": int(np.sum(~np.isfinite(t_err))),
        "median_t_cm": med_t,
        "median_R_deg": med_R,
        "recall": recall(t_err, R_err),
    }


def cumulative_curve(errors: np.ndarray, max_error: float | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Cumulative error distribution for plots: fraction of queries with error <= x.

    Args:
      errors: [N] errors (any unit; inf values never enter the curve but count in the
        denominator; a failure's rotation error of 180 deg enters at 180 unless
        ``max_error`` cuts it off).
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
