"""The whole pipeline on the embedded synthetic scene, no download needed.

    python -m experiments.demo [--out DIR] [--quick]

1. generates the synthetic textured room in the 7Scenes layout (exact poses and depth),
2. builds the map: EGM (SIFT, triangulation with the known poses, VLAD) and the NeRFs,
3. localizes the query trajectory in ``render`` mode (VRS-NeRF: descriptors of NeRF-rendered
   patches) and ``real`` mode (the hierarchical baseline: stored descriptors of real patches),
4. prints one table in the paper's layout and writes OUT/demo.json.

Everything goes under --out (default ./outputs/demo); re-running skips finished stages.
--quick uses a smaller scene and the tiny `test` configs (a smoke run for CI; its accuracy is
not representative).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

from vrs_jax import fileio, localize, maps
from vrs_jax.cli.common import HelpFormatter, prog, record_run, start_run
from vrs_jax.data import synthetic
from vrs_jax.data.readers import load_scene
from vrs_jax.errors import cli_main
from vrs_jax.eval import metrics
from vrs_jax.eval.report import summarize
from vrs_jax.localize.batch import localize_scene

PAPER_ROWS = (("render", "VRS-NeRF (rendered {P}x{P} patches)"),
              ("real", "Baseline (real {P}x{P} patches, GT)"))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog("experiments.demo"),
                                description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("--out", default="outputs/demo", help="output folder")
    p.add_argument("--quick", action="store_true",
                   help="small scene and tiny configs (minutes; a smoke run)")
    p.add_argument("--seed", type=int, default=0, help="synthetic scene seed")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--verbose", action="store_true", help="debug log lines")
    return p


def format_table(rows: list[dict]) -> str:
    """The paper's layout: method | median (cm, deg) | recall 5cm/5deg | map MB | s/query."""
    head = (f"{'method':<36} {'median (cm, deg)':>18} {'5cm/5deg':>9} {'2cm/2deg':>9} "
            f"{'map (MB)':>9} {'s/query':>8}")
    lines = [head, "-" * len(head)]
    for r in rows:
        med = f"{r['median_t_cm']:.2f}, {r['median_R_deg']:.2f}"
        lines.append(f"{r['label']:<36} {med:>18} {100 * r['recall']['5cm_5deg']:>8.1f}% "
                     f"{100 * r['recall']['2cm_2deg']:>8.1f}% "
                     f"{r['map_bytes']['total'] / 1e6:>9.2f} {r['seconds_per_query']:>8.2f}")
    return "\n".join(lines)


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    start_run(args)
    out = Path(args.out)
    t_start = time.perf_counter()
    if args.quick:
        scfg = dataclasses.replace(synthetic.get_config("default"), seed=args.seed, width=160,
                                   height=120, n_reference=36, n_query=8)
        name = "test"
    else:
        scfg = dataclasses.replace(synthetic.get_config("default"), seed=args.seed)
        name = "cpu-small"
    print(f"[demo] scene: {scfg.n_reference} reference + {scfg.n_query} query frames at "
          f"{scfg.width}x{scfg.height} -> {out / 'scene'}")
    synthetic.generate(out / "scene", scfg, progress=not args.quiet)
    scene = load_scene("7scenes", out / "scene")
    maps.build_map(scene, out / "map", maps.get_config(name), progress=not args.quiet)
    m = maps.load_map(out / "map")
    queries = scene.queries()
    rows = []
    for mode, label in PAPER_ROWS:
        cfg = localize.get_config(name, source=mode)
        t0 = time.perf_counter()
        results, info = localize_scene(m, queries, cfg, progress=not args.quiet)
        elapsed = time.perf_counter() - t0
        s = summarize(queries, results, info, m, cfg, out / "map")
        s.update(label=label.format(P=m.config.features.patches.size), seconds_per_query=float(sum(
            v for v in s["timing_s"].values() if v is not None)), wall_s=elapsed)
        rows.append(s)
    table = format_table(rows)
    print()
    print(f"vrs-jax demo: synthetic room, {len(queries)} queries, config {name}")
    print(table)
    doc = {"config": name, "quick": args.quick, "scene": dataclasses.asdict(scfg),
           "rows": rows, "total_s": time.perf_counter() - t_start}
    fileio.write_text(out / "demo.json", json.dumps(metrics.json_ready(doc), indent=2,
                                                    default=str) + "\n")
    record_run(out, args, {"scene": scfg, "map": maps.get_config(name),
                           "localize": localize.get_config(name)},
               {"total": doc["total_s"]}, argv)
    print(f"\n[demo] done in {doc['total_s'] / 60:.1f} min; details in {out / 'demo.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
