"""Query-stream benchmark: render mode with a bounded cache of rendered reference descriptors.

    python -m benchmarks.stream [--scenes synthetic] [--cache-mb 20] [--json FILE]

A robot or an app localizes a stream of nearby frames with one long-lived
``vrs_jax.localize.Localizer``. Render mode renders each retrieved reference from its own
camera, so those descriptors do not depend on the query and a bounded LRU cache
(``Localizer(cache_mb=...)``) serves them again. The scene's queries are localized in order
three ways, reporting median seconds per query (query preparation included, compilation
excluded by a warm-up image) and cache hits: without a cache (every query renders), cold (the
cache starts empty and fills along the stream) and warm (a second pass over the stream). The
real-patch mode runs beside them as the reference time.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from benchmarks import common
from vrs_jax.errors import cli_main
from vrs_jax.localize import Localizer


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.stream", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_scene_args(p, default_scenes=("synthetic",))
    p.add_argument("--cache-mb", type=float, default=20.0,
                   help="cache budget in MB (default %(default)s)")
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/stream.json)")
    common.add_overwrite_arg(p)
    return p


def run_stream(loc: Localizer, queries) -> tuple[list[float], list]:
    """Seconds per query and results, in stream order."""
    secs, res = [], []
    for i in range(len(queries)):
        t0 = time.perf_counter()
        res.append(loc.localize_image(queries.image_paths[i], queries.K[i], queries.dist[i]))
        secs.append(time.perf_counter() - t0)
    return secs, res


def success_rate(res) -> float:
    return float(np.mean([bool(r.success) for r in res])) if res else 0.0


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    common.check_outputs(args, [common.json_path(args, "stream")])
    doc = common.base_doc("stream", args, argv)
    ctxs, skipped = common.prepare_scenes(args)
    rows = []
    for ctx in ctxs:
        q = ctx.queries
        w, h = (int(s) for s in q.sizes[0])
        name = ctx.m.config.name
        runs = {"real": Localizer(ctx.m, name, source="real"),
                "render, no cache": Localizer(ctx.m.without_descriptors(), name),
                "render, cache": Localizer(ctx.m.without_descriptors(), name,
                                           cache_mb=args.cache_mb)}
        for label, loc in runs.items():
            loc.warmup(w, h)
            passes = [("cold" if "cache" in label and "no" not in label else "-",
                       *run_stream(loc, q))]
            if loc.cache is not None:
                hits0 = loc.cache.hits
                passes.append(("warm", *run_stream(loc, q)))
                warm_hits = loc.cache.hits - hits0
            for kind, secs, res in passes:
                row = {"scene": ctx.name, "method": label, "pass": kind, "n_queries": len(q),
                       "median_s_per_query": float(np.median(secs)),
                       "mean_s_per_query": float(np.mean(secs)),
                       "success_rate": success_rate(res)}
                if loc.cache is not None:
                    row["cache"] = loc.cache.stats()
                    if kind == "warm":
                        row["warm_hits"] = warm_hits
                rows.append(row)
    print()
    print(common.table(
        ["scene / method", "pass", "queries", "median s/query", "mean s/query", "localized",
         "cache MB", "hits/misses"],
        [[f"{r['scene']} / {r['method']}", r["pass"], r["n_queries"],
          common.fmt(r["median_s_per_query"], 3), common.fmt(r["mean_s_per_query"], 3),
          common.pct(r["success_rate"]),
          common.fmt(r["cache"]["bytes"] / 1e6, 2) if "cache" in r else "-",
          f"{r['cache']['hits']}/{r['cache']['misses']}" if "cache" in r else "-"]
         for r in rows],
        title=f"Query stream (cache budget {args.cache_mb:g} MB; compilation excluded)"))
    for s in skipped:
        print(f"skipped {s['scene']}: {s['reason']}")
    doc.update({"rows": rows, "skipped": skipped})
    out = common.write_json(common.json_path(args, "stream"), doc)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
