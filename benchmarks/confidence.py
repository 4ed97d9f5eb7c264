"""Calibration of the pose confidence (``vrs_jax.localize.confidence``) on labelled poses.

    python -m benchmarks.confidence [--work DIR] [--seeds 0 1 2] [--queries 16]
        [--modes real render] [--loose-min-inliers 6] [--json FILE]

Generates small synthetic rooms (one per seed: 24 references and --queries queries at
160x120), builds a ``test`` map of each in --work (reused when present) and localizes
every room's queries against every map with the ``test`` localize config plus one guided
pass. Labels: a query localized against its own room's map is right when its pose is within
5% of the scene scale and 5 deg of the ground truth, else wrong; every pose of a query
localized against ANOTHER room's map is wrong (a wrong-place retrieval). Prints, per mode
and labelled set, how many wrong poses are flagged (uncertain or failed) and how many right
ones are wrongly flagged, with the distribution of each test's quantity, and writes the
per-result quantities to --json (--from-json re-evaluates changed thresholds on them
without localizing). The same runs are repeated with PnP accepting poses of
--loose-min-inliers inliers (the config's floor is 12): most wrong poses are then PnP poses
rather than failures, so they test the uncertain verdict's tests themselves.
"""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import numpy as np

from benchmarks import common
from vrs_jax import fileio, maps
from vrs_jax.data import synthetic
from vrs_jax.data.readers import load_scene
from vrs_jax.errors import VrsError, cli_main
from vrs_jax.eval import metrics
from vrs_jax.localize import get_config
from vrs_jax.localize.batch import localize_scene
from vrs_jax.localize.confidence import (
    LOCALIZED_AT,
    ConfidenceConfig,
    evidence_quantities,
    map_scale,
    pose_confidence,
    result_fields,
    score_quantities,
    weakest_test,
)

TESTS = ("inlier_ratio", "coverage", "pass_shift", "pass_rotation", "guided_ratio")

ROOM = dict(width=160, height=120, n_reference=24)
WRONG_T, WRONG_R = 0.05, 5.0  # wrong pose: beyond 5% of the scene scale or 5 deg


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.confidence", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", default="work/confidence", help="scenes and maps (reused)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--queries", type=int, default=16, help="queries per room")
    p.add_argument("--modes", nargs="+", default=["real", "render"], choices=["real", "render"])
    p.add_argument("--loose-min-inliers", type=int, default=6,
                   help="also localize with PnP accepting poses of this many inliers (0: no): "
                        "the chance poses a permissive PnP would return, wrong ones the "
                        "confidence must flag without the PnP inlier floor")
    p.add_argument("--json", default=None, help="per-result quantities and labels")
    p.add_argument("--from-json", default=None, metavar="FILE",
                   help="re-evaluate the current thresholds on a --json written before "
                        "(no localization)")
    common.add_overwrite_arg(p)
    return p


def room_map(work: Path, seed: int, n_query: int) -> tuple[Path, Path]:
    """(scene folder, map folder) of the room of ``seed`` (generated and built once)."""
    scene_dir = work / f"room{seed}_q{n_query}"
    map_dir = work / f"map{seed}_q{n_query}"
    cfg = dataclasses.replace(synthetic.get_config("default"), seed=seed, n_query=n_query,
                              **ROOM)
    synthetic.generate(scene_dir, cfg)  # skipped when complete
    if not (map_dir / "map.json").exists():
        maps.build_map(load_scene("7scenes", scene_dir), map_dir, maps.get_config("test"),
                       progress=False, log=lambda s: None)
    return scene_dir, map_dir


def measure(work: Path, seeds: list[int], n_query: int, modes: list[str],
            min_inliers: int | None = None) -> list[dict]:
    """Per mode, map and query room: the results' fields, errors and labels (PnP with
    ``min_inliers`` when given, else the config's)."""
    rooms = {s: room_map(work, s, n_query) for s in seeds}
    out = []
    for mode in modes:
        cfg = get_config("test", source=mode, guided_passes=1)
        if min_inliers:
            cfg = dataclasses.replace(cfg, pnp=dataclasses.replace(cfg.pnp,
                                                                   min_inliers=min_inliers))
        for ms in seeds:
            m = maps.load_map(rooms[ms][1], descriptors=mode == "real")
            scale = map_scale(m)
            for qs in seeds:
                queries = load_scene("7scenes", rooms[qs][0]).queries()
                results, _ = localize_scene(m, queries, cfg, progress=False, timed=False)
                f = result_fields(results)
                dt, dr = metrics.pose_errors(f["R"], f["t"], queries.R, queries.t)
                out.append({"mode": mode + (f" pnp>={min_inliers}" if min_inliers else ""),
                            "map": ms, "queries": qs, "scale": scale,
                            "fields": f, "t_err": dt, "R_err": dr})
    return out


def quantities(f: dict, scale: float) -> dict[str, np.ndarray]:
    """The tests' quantities (localize.confidence.evidence_quantities) and the inlier counts."""
    return {**evidence_quantities(f, scale), "n_inliers": f["n_inliers"].astype(float),
            "n_matches": f["n_matches"].astype(float)}


def reevaluate(rows: list[dict], cfg: ConfidenceConfig) -> dict:
    """Flag counts per labelled set of stored rows (their quantities) under ``cfg``."""
    table = {}
    for r in rows:
        failed = r["verdict"] == "failed"
        if not failed:
            sc = score_quantities({k: np.array([r[k]], float) for k in TESTS}, cfg)
            flagged = min(float(v[0]) for v in sc.values()) < LOCALIZED_AT
        key = f"{r['mode']} {'own' if r['map'] == r['queries'] else 'cross-room'}"
        d = table.setdefault(key, {"right": 0, "right_flagged": 0, "wrong": 0,
                                   "wrong_flagged": 0})
        d[r["label"]] += 1
        d[f"{r['label']}_flagged"] += int(failed or flagged)
    return table


def evaluate(runs: list[dict], cfg: ConfidenceConfig) -> dict:
    """Flag counts per (mode, labelled set) and the quantities of every result."""
    table, rows = {}, []
    for r in runs:
        f, scale = r["fields"], r["scale"]
        conf, verdict = pose_confidence(f, scale, cfg)
        weak = weakest_test(f, scale, cfg)
        q = quantities(f, scale)
        own = r["map"] == r["queries"]
        wrong = ~((r["t_err"] <= WRONG_T * scale) & (r["R_err"] <= WRONG_R)) | (not own)
        flagged = verdict != "localized"
        for i in range(len(conf)):
            key = (r["mode"], "own" if own else "cross-room")
            d = table.setdefault(key, {"right": 0, "right_flagged": 0, "wrong": 0,
                                       "wrong_flagged": 0, "verdicts": {}})
            lab = "wrong" if wrong[i] else "right"
            d[lab] += 1
            d[f"{lab}_flagged"] += int(flagged[i])
            d["verdicts"][verdict[i]] = d["verdicts"].get(verdict[i], 0) + 1
            rows.append({"mode": r["mode"], "map": r["map"], "queries": r["queries"],
                         "label": lab, "verdict": verdict[i], "confidence": float(conf[i]),
                         "weakest": weak[i], "t_err_rel": float(r["t_err"][i] / scale),
                         "R_err_deg": float(r["R_err"][i]),
                         **{k: float(v[i]) for k, v in q.items()}})
    return {"table": {f"{m} {s}": v for (m, s), v in table.items()}, "rows": rows}


def describe(rows: list[dict]) -> str:
    """Per mode and label, the range of each test's quantity over PnP poses."""
    lines = []
    keys = ("inlier_ratio", "coverage", "pass_shift", "pass_rotation", "guided_ratio",
            "n_inliers")
    for mode in sorted({r["mode"] for r in rows}):
        for lab, own in (("right", True), ("wrong", True), ("wrong", False)):
            sel = [r for r in rows if r["mode"] == mode and r["label"] == lab
                   and (r["map"] == r["queries"]) == own and r["verdict"] != "failed"]
            if not sel:
                continue
            parts = []
            for k in keys:
                v = np.array([r[k] for r in sel], float)
                v = v[np.isfinite(v)]
                if len(v):
                    parts.append(f"{k} {v.min():.3g}/{np.median(v):.3g}/{v.max():.3g}")
            lines.append(f"{mode} {lab} {'own' if own else 'cross'} (n={len(sel)} PnP poses; "
                         f"min/median/max): " + ", ".join(parts))
    return "\n".join(lines)


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    common.check_outputs(args, [args.json])
    if args.from_json:
        rows = fileio.read_json(args.from_json, "--from-json file").get("rows")
        if not isinstance(rows, list):
            raise VrsError("has no 'rows' list: not a benchmarks.confidence --json",
                           args.from_json)
        for k, v in reevaluate(rows, ConfidenceConfig()).items():
            print(f"{k}: wrong flagged {v['wrong_flagged']}/{v['wrong']}, right wrongly "
                  f"flagged {v['right_flagged']}/{v['right']}")
        return 0
    runs = measure(Path(args.work), args.seeds, args.queries, args.modes)
    if args.loose_min_inliers:
        runs += measure(Path(args.work), args.seeds, args.queries, args.modes,
                        args.loose_min_inliers)
    ev = evaluate(runs, ConfidenceConfig())
    for k, v in ev["table"].items():
        print(f"{k}: wrong flagged {v['wrong_flagged']}/{v['wrong']}, right wrongly flagged "
              f"{v['right_flagged']}/{v['right']}; verdicts {v['verdicts']}")
    print(describe(ev["rows"]))
    if args.json:
        common.write_json(args.json, {"config": dataclasses.asdict(ConfidenceConfig()), **ev})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
