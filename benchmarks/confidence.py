"""Calibration of the pose confidence (``vrs_jax.localize.confidence``) on labelled poses.

    python -m benchmarks.confidence [--work DIR] [--seeds 0 1 2] [--queries 16]
        [--modes real render] [--loose-min-inliers 6] [--json FILE]
        [--scenes fern,lego,scan24,fox,walk [--map fern=DIR ...] [--cross-queries 4]]

Synthetic rooms (--seeds; none: ``--seeds``): generates small rooms (one per seed: 24
references and --queries queries at 160x120), builds a ``test`` map of each in --work
(reused when present) and localizes every room's queries against every map with the
``test`` localize config plus one guided pass. Labels: a query localized against its own
room's map is right when its pose is within 5% of the scene scale and 5 deg of the ground
truth, else wrong; every pose of a query localized against ANOTHER room's map is wrong (a
wrong-place retrieval).

Real benchmark scenes (--scenes, benchmarks.common's scenes; each map from ``--map
SCENE=DIR``, read only, else built into --bench-work as the benchmarks build it, without
its NeRF unless --train-nerf; a map without a trained NeRF is measured in real mode only):
each scene's own queries (--max-queries) localized against its map with the map's own
localize config (``cpu-small``), labelled by their error as above, and --cross-queries of
each scene's queries localized against every OTHER scene's map (a wrong place: every PnP
pose there is wrong; queries carry their own K, so this works across datasets).

Prints, per labelled set (rooms or scene, mode, own or cross), how many wrong poses are
flagged (uncertain or failed) and how many right ones are wrongly flagged, with the
distribution of each test's quantity, and writes the per-result quantities to --json
(--from-json re-evaluates the current thresholds on the rows of one or more such files,
without localizing). Every run is repeated with PnP accepting poses of --loose-min-inliers
inliers (the configs' floor is 12): most wrong poses are then PnP poses rather than
failures, so they test the uncertain verdict's tests themselves.

Calibration (ConfidenceConfig's numbers), before the benchmark maps' NeRFs exist:

    python -m benchmarks.confidence --work outputs/confidence \\
        --scenes fern,lego,scan24,fox,walk --bench-work outputs/confidence/scenes \\
        --json docs/figures/confidence.json

and with the benchmark maps (render mode on the scenes; the walk stays real-only):

    python -m benchmarks.confidence --work outputs/confidence \\
        --scenes fern,lego,scan24,fox,walk --bench-work outputs/confidence/scenes \\
        --map fern=outputs/bench_work/fern-cpu-small/map ... (lego, scan24, fox) \\
        --json docs/figures/confidence.json
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
    ConfidenceConfig,
    evidence,
    map_scale,
    result_fields,
    verdict_of_quantities,
    weakest_test,
)

# the quantities the tests read (localize.confidence.evidence_quantities)
TESTS = ("inlier_ratio", "coverage", "pass_shift", "pass_rotation", "guided_ratio",
         "n_inliers", "centre_std", "attempt_shift")

ROOM = dict(width=160, height=120, n_reference=24)
WRONG_T, WRONG_R = 0.05, 5.0  # wrong pose: beyond 5% of the scene scale or 5 deg


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.confidence", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--work", default="work/confidence", help="rooms and their maps (reused)")
    p.add_argument("--seeds", type=int, nargs="*", default=[0, 1, 2],
                   help="synthetic rooms (none: real scenes only)")
    p.add_argument("--queries", type=int, default=16, help="queries per room")
    p.add_argument("--modes", nargs="+", default=["real", "render"], choices=["real", "render"])
    p.add_argument("--loose-min-inliers", type=int, default=6,
                   help="also localize with PnP accepting poses of this many inliers (0: no): "
                        "the chance poses a permissive PnP would return, wrong ones the "
                        "confidence must flag without the PnP inlier floor")
    p.add_argument("--scenes", default="",
                   help="also these real benchmark scenes, comma-separated among "
                        f"{', '.join(common.SCENES)}: own queries and cross-scene queries")
    p.add_argument("--map", action="append", default=[], metavar="SCENE=DIR",
                   help="the map of a --scenes scene (read only); repeatable")
    p.add_argument("--bench-work", default=common.DEFAULT_WORK,
                   help="where a --scenes map without --map is built (as the benchmarks do)")
    p.add_argument("--train-nerf", action="store_true",
                   help="train the NeRF of a --scenes map built here (else it stops after the "
                        "EGM, and that scene is measured in real mode only)")
    p.add_argument("--data-root", default=None,
                   help="the real datasets (default: $VRS_SHARED_DATA or ../shared/data)")
    p.add_argument("--max-queries", type=int, default=None,
                   help="own queries per real scene (evenly spaced; default all)")
    p.add_argument("--cross-queries", type=int, default=4,
                   help="queries of each real scene localized against each other scene's "
                        "map (evenly spaced)")
    p.add_argument("--json", default=None, help="per-result quantities and labels")
    p.add_argument("--from-json", nargs="+", default=None, metavar="FILE",
                   help="re-evaluate the current thresholds on the rows of --json files "
                        "written before, together (no localization)")
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


def loose(cfg, min_inliers: int | None):
    """``cfg`` with PnP accepting poses of ``min_inliers`` inliers (None: unchanged)."""
    if not min_inliers:
        return cfg
    return dataclasses.replace(cfg, pnp=dataclasses.replace(cfg.pnp, min_inliers=min_inliers))


def run(m, queries, cfg, group: str, mode: str, map_name: str, query_name: str,
        min_inliers: int | None) -> dict:
    """Localize ``queries`` against map ``m``: the results' fields, errors and what they are
    (group: "rooms" or the real scene of the map; the mode with its PnP floor)."""
    results, _ = localize_scene(m, queries, cfg, progress=False, timed=False)
    f = result_fields(results)
    dt, dr = metrics.pose_errors(f["R"], f["t"], queries.R, queries.t)
    return {"group": group, "mode": mode + (f" pnp>={min_inliers}" if min_inliers else ""),
            "map": map_name, "queries": query_name, "scale": map_scale(m),
            "fields": f, "t_err": dt, "R_err": dr}


def measure(work: Path, seeds: list[int], n_query: int, modes: list[str],
            min_inliers: int | None = None) -> list[dict]:
    """Per mode, room map and query room: :func:`run` (PnP with ``min_inliers`` when given,
    else the config's)."""
    rooms = {s: room_map(work, s, n_query) for s in seeds}
    out = []
    for mode in modes:
        cfg = loose(get_config("test", source=mode, guided_passes=1), min_inliers)
        for ms in seeds:
            m = maps.load_map(rooms[ms][1], descriptors=mode == "real")
            for qs in seeds:
                queries = load_scene("7scenes", rooms[qs][0]).queries()
                out.append(run(m, queries, cfg, "rooms", mode, f"room{ms}", f"room{qs}",
                               min_inliers))
    return out


def scene_args(args) -> argparse.Namespace:
    """The arguments benchmarks.common.prepare_scene reads, from this benchmark's."""
    return argparse.Namespace(map=args.map, work=args.bench_work, data_root=args.data_root,
                              synthetic_root=None, quiet=True, config="cpu-small",
                              nerf_steps=None, max_queries=args.max_queries)


def measure_scenes(ctxs: list, modes: list[str], cross_queries: int,
                   min_inliers: int | None = None) -> list[dict]:
    """Per mode and real scene map (its own localize config; render mode only on maps with
    a trained NeRF): its own queries and ``cross_queries`` of every other scene's
    (:func:`run`)."""
    out = []
    for mode in modes:
        for mc in ctxs:
            if mode == "render" and mc.m.ilm is None:
                continue  # a map without a trained NeRF renders nothing
            cfg = loose(common.localize_cfg(mc, mode), min_inliers)
            for qc in ctxs:
                q = qc.queries if qc is mc else qc.queries.subset(
                    common.evenly_spaced(len(qc.queries), cross_queries))
                out.append(run(mc.m, q, cfg, mc.name, mode, mc.name, qc.name, min_inliers))
    return out


def set_key(r: dict) -> str:
    """A labelled set: group (rooms or the map's scene), mode, own or cross queries."""
    own = r["map"] == r["queries"]
    return f"{r.get('group', 'rooms')} {r['mode']} {'own' if own else 'cross'}"


def count(rows: list[dict], verdicts: np.ndarray) -> dict[str, dict]:
    """Per labelled set (:func:`set_key`): right and wrong poses, how many of each are
    flagged (verdict not "localized"), and the verdicts."""
    table: dict[str, dict] = {}
    for r, v in zip(rows, verdicts, strict=True):
        d = table.setdefault(set_key(r), {"right": 0, "right_flagged": 0, "wrong": 0,
                                          "wrong_flagged": 0, "verdicts": {}})
        d[r["label"]] += 1
        d[f"{r['label']}_flagged"] += int(v != "localized")
        d["verdicts"][v] = d["verdicts"].get(v, 0) + 1
    return table


def reevaluate(rows: list[dict], cfg: ConfidenceConfig) -> tuple[dict, np.ndarray]:
    """(flag counts per labelled set, verdicts [N]) of stored rows (their quantities) under
    ``cfg``."""
    q = {k: np.array([np.nan if r.get(k) is None else r[k] for r in rows], float)
         for k in TESTS}
    ok = np.array([r["verdict"] != "failed" for r in rows], bool)
    verdict = verdict_of_quantities(q, ok, cfg)[1] if rows else np.zeros(0, object)
    return count(rows, verdict), verdict


def evaluate(runs: list[dict], cfg: ConfidenceConfig) -> dict:
    """Flag counts per labelled set and the quantities of every result."""
    rows = []
    for r in runs:
        f, scale = r["fields"], r["scale"]
        ev = evidence(f, scale, cfg)
        weak = weakest_test(f, scale, cfg)
        own = r["map"] == r["queries"]
        wrong = ~((r["t_err"] <= WRONG_T * scale) & (r["R_err"] <= WRONG_R)) | (not own)
        for i in range(len(wrong)):
            rows.append({"group": r["group"], "mode": r["mode"], "map": r["map"],
                         "queries": r["queries"], "label": "wrong" if wrong[i] else "right",
                         "weakest": weak[i], "t_err_rel": float(r["t_err"][i] / scale),
                         "R_err_deg": float(r["R_err"][i]),
                         **{k: v[i] if k == "verdict" else float(v[i])
                            for k, v in ev.items()},
                         "n_matches": float(f["n_matches"][i])})
    return {"table": count(rows, np.array([r["verdict"] for r in rows], object)),
            "rows": rows}


def describe(rows: list[dict]) -> str:
    """Per set and label, the range of each test's quantity over PnP poses."""
    lines = []
    for key in sorted({set_key(r) for r in rows}):
        for lab in ("right", "wrong"):
            sel = [r for r in rows if set_key(r) == key and r["label"] == lab
                   and r["verdict"] != "failed"]
            if not sel:
                continue
            parts = []
            for k in TESTS:
                v = np.array([np.nan if r.get(k) is None else r[k] for r in sel], float)
                v = v[np.isfinite(v)]
                if len(v):
                    parts.append(f"{k} {v.min():.3g}/{np.median(v):.3g}/{v.max():.3g}")
            lines.append(f"{key} {lab} (n={len(sel)} PnP poses; min/median/max): "
                         + ", ".join(parts))
    return "\n".join(lines)


def flag_table(table: dict[str, dict]) -> str:
    """The flag counts per labelled set, and over all sets."""
    tot = {k: sum(v[k] for v in table.values())
           for k in ("wrong_flagged", "wrong", "right_flagged", "right")}
    rows = [[k, f"{v['wrong_flagged']} / {v['wrong']}", f"{v['right_flagged']} / {v['right']}",
             ", ".join(f"{n} {c}" for n, c in sorted(v.get("verdicts", {}).items()))]
            for k, v in sorted(table.items())]
    rows.append(["all", f"{tot['wrong_flagged']} / {tot['wrong']}",
                 f"{tot['right_flagged']} / {tot['right']}", ""])
    return common.table(["set (map, mode, queries)", "wrong flagged", "right flagged",
                         "verdicts"], rows,
                        title="Poses flagged (uncertain or failed) per labelled set")


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    common.check_outputs(args, [args.json])
    cfg = ConfidenceConfig()
    doc = common.base_doc("confidence", args, argv)  # the code as the run starts
    if args.from_json:
        rows = []
        for f in args.from_json:
            got = fileio.read_json(f, "--from-json file").get("rows")
            if not isinstance(got, list):
                raise VrsError("has no 'rows' list: not a benchmarks.confidence --json", f)
            rows += got
        print(flag_table(reevaluate(rows, cfg)[0]))
        print(describe(rows))
        return 0
    ctxs = []
    if args.scenes:
        sa = scene_args(args)
        ctxs = [c for c in (common.prepare_scene(n, sa, need_nerf=args.train_nerf) for n in
                            common.parse_scenes(args.scenes)) if c is not None]
        for c in ctxs:
            if c.m.ilm is None and "render" in args.modes:
                print(f"[{c.name}] the map has no trained NeRF: no render-mode runs against it")
    runs = []
    for floor in [None] + ([args.loose_min_inliers] if args.loose_min_inliers else []):
        if args.seeds:
            runs += measure(Path(args.work), args.seeds, args.queries, args.modes, floor)
        runs += measure_scenes(ctxs, args.modes, args.cross_queries, floor)
    ev = evaluate(runs, cfg)
    print(flag_table(ev["table"]))
    print(describe(ev["rows"]))
    if args.json:
        common.write_json(args.json, {**doc, "config": dataclasses.asdict(cfg), **ev})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
