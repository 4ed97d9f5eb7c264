"""Evaluate a results file against a dataset's query ground truth (docs/design.md, section 6).

    python -m experiments.evaluate --results OUT/results.txt --format 7scenes --root DIR \\
        [--query-every N] [--downscale N] [--opt KEY=VALUE ...] [--json OUT/eval.json [--overwrite]]

The queries are the dataset's query images as ``vrs_jax.data.readers.load_scene`` returns
them with the same options the localize run used (e.g. ``--query-every 8`` for lego).
A query missing from the results counts as a failure (infinite error) and is listed; a name
in the results that is not a query of the dataset is reported as a warning and ignored.
Names match exactly, or by file name when the results hold bare file names (``--basename``
results) and that file name is unique among the queries. Queries without a ground-truth pose
(Aachen) cannot be evaluated here and are left out with a warning.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path, PurePosixPath

import numpy as np

from vrs_jax import fileio
from vrs_jax.cli.common import count_at_least, parse_opts, prog, record_run, start_run
from vrs_jax.errors import VrsError, cli_main
from vrs_jax.eval import metrics
from vrs_jax.eval.results import read_results


def _load_scene(fmt: str, root: str, opts: dict):
    """The dataset through the readers (a seam for tests)."""
    from vrs_jax.data.readers import load_scene  # raises VrsError for unknown formats/options

    return load_scene(fmt, root, **opts)


def match_names(result_names: list[str], query_names: list[str]
                ) -> tuple[dict[str, str], list[str]]:
    """Map result names to query names.

    Returns:
      ({query name: result name}, [result names matching no query]). Exact matches first;
      then a bare file name matches the query with that (unique) file name.
    """
    queries = set(query_names)
    by_base: dict[str, list[str]] = {}
    for q in query_names:
        by_base.setdefault(PurePosixPath(q).name, []).append(q)
    matched: dict[str, str] = {}
    unknown = []
    for r in result_names:
        if r in queries and r not in matched:
            matched[r] = r
    for r in result_names:
        if r in queries:
            continue
        cands = by_base.get(PurePosixPath(r).name, []) if "/" not in r else []
        if len(cands) == 1 and cands[0] not in matched:
            matched[cands[0]] = r
        else:
            unknown.append(r)
    return matched, unknown


def evaluate(results: dict, scene) -> dict:
    """Errors and summary of ``results`` ({name: (R, t)}) over ``scene``'s query images.

    Returns the JSON-able report (before :func:`metrics.json_ready`): the
    :func:`metrics.summarize` keys plus ``missing``, ``unknown``, ``not_queries``,
    ``no_ground_truth`` (name lists) and ``per_query`` ({name: {t_cm, R_deg}}).
    """
    q_idx = np.flatnonzero(scene.is_query)
    if q_idx.size == 0:
        raise VrsError("the dataset has no query images; pass the split options the localize "
                       "run used (e.g. --query-every N)", scene.root)
    no_gt = [scene.names[i] for i in q_idx if not scene.has_pose[i]]
    q_idx = np.asarray([i for i in q_idx if scene.has_pose[i]], dtype=int)
    if q_idx.size == 0:
        raise VrsError("no query has a ground-truth pose here (submit the results to the "
                       "benchmark instead)", scene.root)
    q_names = [scene.names[i] for i in q_idx]
    matched, unknown = match_names(list(results), q_names)
    all_names = set(scene.names)
    not_queries = [r for r in unknown if r in all_names]
    unknown = [r for r in unknown if r not in all_names]

    n = q_idx.size
    R_est = np.tile(np.eye(3), (n, 1, 1))
    t_est = np.zeros((n, 3))
    has = np.zeros(n, dtype=bool)
    for k, name in enumerate(q_names):
        if name in matched:
            R_est[k], t_est[k] = results[matched[name]]
            has[k] = True
    t_err, R_err = metrics.pose_errors(R_est, t_est, scene.R[q_idx], scene.t[q_idx], has)
    report = metrics.summarize(t_err, R_err)
    report.update(
        n_missing=int(np.sum(~has)),
        missing=[q for q, h in zip(q_names, has, strict=True) if not h],
        unknown=unknown,
        not_queries=not_queries,
        no_ground_truth=no_gt,
        per_query={q: {"t_cm": float(te * 100.0), "R_deg": float(re)}
                   for q, te, re in zip(q_names, t_err, R_err, strict=True)},
    )
    return report


def _warn(msg: str) -> None:
    print(f"warning: {msg}", file=sys.stderr)


def _preview(names: list[str], limit: int = 5) -> str:
    more = f", ... ({len(names) - limit} more)" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=prog("experiments.evaluate"),
        description="Median errors and recall of a results file (name qw qx qy qz tx ty tz, "
                    "world-to-camera) against a dataset's query ground truth.")
    p.add_argument("--results", required=True, help="results file to evaluate")
    p.add_argument("--format", required=True, dest="fmt",
                   help="dataset format (7scenes, cambridge, aachen, nerf, llff, colmap)")
    p.add_argument("--root", required=True, help="dataset root folder")
    p.add_argument("--query-every", type=count_at_least(0), default=None, metavar="N",
                   help="hold out every N-th image as a query, as the localize run did "
                        "(formats without a split)")
    p.add_argument("--downscale", type=count_at_least(1), default=None, metavar="N",
                   help="image downscale factor used by the localize run")
    p.add_argument("--opt", action="append", default=[], metavar="KEY=VALUE",
                   help="further reader option, repeatable (e.g. --opt pgt=PATH for 7Scenes)")
    p.add_argument("--json", default=None, metavar="OUT",
                   help="also write the metrics and per-query errors as JSON here (and the "
                        "run record, run.json, beside it); an existing file is refused "
                        "unless --overwrite")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    p.add_argument("--verbose", action="store_true", help="debug log lines")
    return p


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    start_run(args)
    if args.json:  # before any work: a folder that cannot take the report fails now
        fileio.check_apart(args.json, [args.results, args.root])
        if Path(args.json).is_dir():
            raise VrsError("is a folder; --json names the file to write", args.json)
        if not Path(args.json).parent.is_dir():
            raise VrsError("output folder not found", Path(args.json).parent)
        fileio.check_writable(Path(args.json).parent)
        fileio.check_new(args.json, args.overwrite)
    results = read_results(args.results)
    opts = parse_opts(args.opt)
    if args.query_every is not None:
        opts["query_every"] = args.query_every
    if args.downscale is not None:
        opts["downscale"] = args.downscale
    scene = _load_scene(args.fmt, args.root, opts)
    report = evaluate(results, scene)

    if report["no_ground_truth"]:
        _warn(f"{len(report['no_ground_truth'])} queries have no ground-truth pose and are "
              f"left out: {_preview(report['no_ground_truth'])}")
    if report["not_queries"]:
        _warn(f"{len(report['not_queries'])} results are reference (not query) images, "
              f"ignored: {_preview(report['not_queries'])}")
    if report["unknown"]:
        _warn(f"{len(report['unknown'])} results name no image of the dataset, ignored: "
              f"{_preview(report['unknown'])}")
    if report["missing"]:
        _warn(f"{len(report['missing'])} of {report['n_queries']} queries have no result and "
              f"count as failures: {_preview(report['missing'])}")

    print(metrics.format_table(report, title=f"{args.results} ({args.fmt}: {args.root})"))
    if args.json:
        out = Path(args.json)
        if not out.parent.is_dir():
            raise VrsError("output folder not found", out.parent)
        doc = {"results": str(args.results), "format": args.fmt, "root": str(args.root),
               "options": opts, **report}
        fileio.write_text(out, json.dumps(metrics.json_ready(doc), indent=2, allow_nan=False)
                          + "\n")
        record_run(out.parent, args, None, None, argv)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
