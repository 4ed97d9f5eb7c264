"""Scene division benchmark: one NeRF vs K-means clusters vs a uniform grid, at equal size.

    python -m benchmarks.clusters [--steps 2000] [--clusters 4] [--config test] [--json FILE]

The paper divides a large scene into NeRF clusters by K-means on the reference camera centres.
This benchmark builds three maps of the large synthetic scene (``rooms4`` of
:mod:`vrs_jax.data.synthetic`: an 8 m hall and three 3.5 m offices in a row, joined by
doorways, one camera loop per room), identical but for the implicit map:

- ``one``: a single NeRF of the config's width W;
- ``kmeans``: C NeRFs (K-means++ clusters of the cameras, best of 8 seedings);
- ``grid``: C NeRFs over a uniform grid of C equal cells of the cameras' bounding box;

at EQUAL TOTAL PARAMETERS (each of the C MLPs has the width whose parameter count times C is
closest to the single NeRF's; the counts are printed) and equal compute per step (an MLP
costs about 2 FLOPs per parameter per sample, so C NeRFs of 1/C the parameters each training
on R rays per step cost what the single NeRF training on R rays costs; ``--cluster-rays
split`` gives each cluster R / C rays instead: the same rays, ~1/C of the compute), for the
same number of steps. Reported per configuration: parameter counts,
training time and steps per second, map size, images per cluster (primary and with shared
border images), how the clusters cut the rooms, and localization of every query in render
mode (VRS-NeRF: patches rendered by the reference image's cluster NeRF) and real-patch mode
(the stored real patches: the same EGM in every map, so the same numbers; a control), with
median errors and recall at 7Scenes-style thresholds, overall and per room. A figure of the
camera positions coloured by cluster is written when matplotlib is installed.

Maps and run records go to WORK (default outputs/bench_work) and are reused when they match.
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import common
from vrs_jax.errors import VrsError, cli_main

LABELS = ("one", "kmeans", "grid")
MODES = ("render", "real")
RECALLS = ("2cm_2deg", "5cm_5deg", "10cm_5deg")
SCENE_CONFIG = "rooms4"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.clusters", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--config", default="test",
                   help="map and localize config the three maps start from (default test: "
                        "a 3 x 64 Mip-NeRF, fits the CPU budget)")
    p.add_argument("--clusters", type=int, default=4, help="clusters C (default 4)")
    p.add_argument("--steps", type=int, default=2000,
                   help="NeRF training steps of every configuration (default 2000)")
    p.add_argument("--width", type=int, default=128,
                   help="trunk width of the single NeRF (default 128: the test config's 64 is "
                        "too small for this scene; the view head scales with it); the "
                        "clusters get the width of equal total size")
    p.add_argument("--cluster-rays", choices=("full", "split"), default="full",
                   help="rays per step of each cluster: full (--rays each: equal FLOPs per "
                        "step, the default) or split (--rays / C each: equal rays)")
    p.add_argument("--rays", type=int, default=256,
                   help="rays per training step of the single NeRF (default 256)")
    p.add_argument("--modes", default="render,real",
                   help="comma-separated localization modes: render, real")
    p.add_argument("--only", default=",".join(LABELS),
                   help=f"comma-separated configurations among {', '.join(LABELS)}")
    p.add_argument("--max-queries", type=int, default=None,
                   help="localize at most N queries (evenly spaced; default all)")
    p.add_argument("--work", default=common.DEFAULT_WORK,
                   help="folder of the scene, the maps and the run records (reused)")
    p.add_argument("--fresh", action="store_true",
                   help="localize afresh even when a matching run record exists")
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/clusters.json)")
    p.add_argument("--figure", default=None,
                   help=f"output PNG (default {common.DEFAULT_JSON_DIR}/clusters.png)")
    common.add_overwrite_arg(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


# ----------------------------------------------------------------------------- configs


@functools.cache
def param_count(ncfg) -> int:
    """Parameters of one cluster's NeRF (counted from shapes, nothing initialised)."""
    import jax

    from vrs_jax.nerf.model import init_params

    shapes = jax.eval_shape(lambda k: init_params(k, ncfg), jax.random.PRNGKey(0))
    return int(sum(math.prod(x.shape) for x in jax.tree_util.tree_leaves(shapes)))


def equal_size_width(ncfg, n_clusters: int) -> tuple[int, int]:
    """(trunk width, head width) of each of ``n_clusters`` NeRFs whose total parameter count
    is closest to one NeRF of ``ncfg`` (the head width scales with the trunk's).

    The count grows with the width, so a bisection finds the crossing; the closer of its two
    neighbours wins.
    """
    target = param_count(ncfg)

    def shape(w: int) -> tuple[int, int]:
        return w, max(1, round(ncfg.net_width_condition * w / ncfg.net_width))

    def total(w: int) -> int:
        w, wc = shape(w)
        return n_clusters * param_count(dataclasses.replace(ncfg, net_width=w,
                                                            net_width_condition=wc))

    lo, hi = 1, ncfg.net_width  # total(lo) <= target < total(hi) for n_clusters >= 2
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (mid, hi) if total(mid) <= target else (lo, mid)
    return shape(min((lo, hi), key=lambda w: abs(total(w) - target)))


def map_configs(base, n_clusters: int, steps: int, rays: int, width: int | None = None,
                cluster_rays: str = "full") -> dict[str, Any]:
    """The MapConfig of each configuration (``one``, ``kmeans``, ``grid``); ``width``: the
    single NeRF's trunk width (default the config's); ``cluster_rays``: "full" (each cluster
    trains on ``rays`` rays per step: equal FLOPs) or "split" (``rays / C``: equal rays)."""
    if n_clusters < 2:
        raise VrsError("--clusters must be >= 2 (the comparison is with one NeRF)")
    if cluster_rays == "split" and rays % n_clusters:
        raise VrsError(f"--rays {rays} must be a multiple of --clusters {n_clusters}")
    one = dataclasses.replace(base.nerf, n_clusters=1, max_steps=steps, batch_size=rays)
    if width is not None and width != one.net_width:
        one = dataclasses.replace(one, net_width=width, net_width_condition=max(
            1, round(one.net_width_condition * width / one.net_width)))
    w, wc = equal_size_width(one, n_clusters)
    split = dataclasses.replace(one, n_clusters=n_clusters, net_width=w, net_width_condition=wc,
                                batch_size=rays // n_clusters if cluster_rays == "split"
                                else rays)
    return {
        "one": dataclasses.replace(base, nerf=one),
        "kmeans": dataclasses.replace(base, nerf=dataclasses.replace(
            split, cluster_method="kmeans")),
        "grid": dataclasses.replace(base, nerf=dataclasses.replace(split, cluster_method="grid")),
    }


# ----------------------------------------------------------------------------- scene


def make_scene(work: Path, quiet: bool):
    """The rooms4 scene (generated into WORK/rooms4/scene) and its layout."""
    from vrs_jax.data import synthetic
    from vrs_jax.data.readers import load_scene

    cfg = synthetic.get_config(SCENE_CONFIG)
    root = synthetic.generate(work / SCENE_CONFIG / "scene", cfg, progress=not quiet)
    return load_scene("7scenes", root), synthetic.build_layout(cfg)


def room_of(centers: np.ndarray, layout) -> np.ndarray:
    """Room index [N] of camera centres [N, 3] (by x between the partition walls)."""
    x = np.asarray(centers)[:, 0]
    return np.clip(np.searchsorted(layout.room_x, x) - 1, 0, len(layout.room_x) - 2)


def balance(ilm, rooms: np.ndarray) -> dict[str, Any]:
    """Images per cluster, their spread, and how the clusters cut the rooms.

    ``rooms_split``: rooms whose images fall in more than one cluster (primary);
    ``purity``: fraction of images in their cluster's majority room.
    """
    primary = np.asarray(ilm.image_cluster)
    c = ilm.n_clusters
    counts = np.bincount(primary, minlength=c)
    table = np.zeros((int(rooms.max()) + 1, c), np.int64)
    np.add.at(table, (rooms, primary), 1)
    return {"images_per_cluster": counts.tolist(),
            "images_trained_per_cluster": np.asarray(ilm.membership).sum(1).tolist(),
            "min_over_max": float(counts.min() / counts.max()),
            "cv": float(counts.std() / counts.mean()),
            "room_by_cluster": table.tolist(),
            "rooms_split": int(((table > 0).sum(1) > 1).sum()),
            "purity": float(table.max(0).sum() / table.sum()),
            "cluster_centers": np.asarray(ilm.cluster_centers).tolist()}


# ----------------------------------------------------------------------------- rows


def build(label: str, cfg, scene, work: Path, quiet: bool) -> tuple[Path, float | None]:
    """Build (or reuse) the map of one configuration; (folder, build seconds if built now)."""
    from vrs_jax import maps

    n = cfg.nerf
    name = (f"{label}-{cfg.name}-c{n.n_clusters}-w{n.net_width}-r{n.batch_size * n.n_clusters}"
            f"-s{n.max_steps}")
    map_dir = work / SCENE_CONFIG / name / "map"
    done = (map_dir / "map.json").is_file() and "map_bytes" in maps.read_stats(map_dir)
    t0 = time.perf_counter()
    maps.build_map(scene, map_dir, cfg, progress=not quiet,
                   log=lambda s: print(f"[{label}] {s}"))
    return map_dir, None if done else time.perf_counter() - t0


def localize_rows(label: str, ctx: common.SceneCtx, modes: list[str], args, scale: float,
                  q_rooms: np.ndarray) -> list[dict[str, Any]]:
    from benchmarks.localize import relative
    from vrs_jax.eval import metrics

    rows = []
    for mode in modes:
        lcfg = common.localize_cfg(ctx, mode)
        s = common.localize_run(ctx, lcfg, args.work, fresh=args.fresh,
                                progress=not args.quiet)
        dt = np.asarray(s["per_query"]["t_err_m"], np.float64)
        dr = np.asarray(s["per_query"]["R_err_deg"], np.float64)
        per_room = {}
        for r in np.unique(q_rooms):
            sel = q_rooms == r
            med_t, med_r = metrics.median_errors(dt[sel], dr[sel])
            per_room[int(r)] = {"n_queries": int(sel.sum()),
                                "recall": metrics.recall(dt[sel], dr[sel]),
                                "median_t_cm": med_t, "median_R_deg": med_r}
        row = {"config": label, "mode": mode, "n_queries": s["n_queries"],
               "median_t_cm": s["median_t_cm"], "median_R_deg": s["median_R_deg"],
               "recall": s["recall"], "n_success": s["n_success"],
               "n_fallback": s["n_fallback"], "median_inliers": s["median_inliers"],
               "localize_s_per_query": s["localize_s_per_query"], "wall_s": s["wall_s"],
               "per_room": per_room, "per_query": s["per_query"],
               "measured_at": s["measured_at"], "reused": s["reused"], "record": s["record"],
               "localize_config": dataclasses.asdict(lcfg)}
        row.update(relative(s, scale))
        rows.append(row)
    return rows


def map_row(label: str, ctx: common.SceneCtx, build_s: float | None, rooms: np.ndarray
            ) -> dict[str, Any]:
    from vrs_jax import configio, maps

    n = ctx.m.config.nerf
    stats = maps.read_stats(ctx.map_dir)
    ilm_stats = stats.get("ilm", {})
    per = param_count(n)
    return {"config": label, "map_dir": str(ctx.map_dir), "method": n.cluster_method
            if n.n_clusters > 1 else "-", "n_clusters": n.n_clusters,
            "net_width": n.net_width, "net_width_condition": n.net_width_condition,
            "params_per_cluster": per, "params_total": per * n.n_clusters,
            "rays_per_step": n.batch_size * n.n_clusters, "steps": ilm_stats.get("steps"),
            "train_s": ilm_stats.get("train_s"), "steps_per_s": ilm_stats.get("steps_per_s"),
            "build_s_this_run": build_s, "map_bytes": maps.map_bytes(ctx.map_dir),
            "balance": balance(ctx.m.ilm, rooms),
            "map_config": configio.to_dict(ctx.m.config)}


# ----------------------------------------------------------------------------- output


def maps_table(rows: list[dict]) -> str:
    return common.table(
        ["config", "method", "C", "width", "params (total)", "rays/step (all)", "steps",
         "train s",
         "steps/s", "NeRF MB", "map MB", "images/cluster", "min/max", "rooms split"],
        [[r["config"], r["method"], r["n_clusters"], r["net_width"],
          common.fmt(r["params_total"]), r["rays_per_step"], common.fmt(r["steps"]),
          common.fmt(r["train_s"], 0), common.fmt(r["steps_per_s"], 1),
          common.fmt(r["map_bytes"]["ilm"] / 1e6, 3), common.fmt(r["map_bytes"]["vrs"] / 1e6, 3),
          "/".join(str(c) for c in r["balance"]["images_per_cluster"]),
          common.fmt(r["balance"]["min_over_max"]), r["balance"]["rooms_split"]]
         for r in rows],
        title="Maps (equal total parameters; train s includes compilation; map MB = "
              "map.json + EGM + NeRF, the render-mode map)")


def accuracy_table(rows: list[dict]) -> str:
    return common.table(
        ["config / mode", "queries", "median (cm, deg)", *RECALLS, "fail", "inliers",
         "ms/query"],
        [[f"{r['config']} / {r['mode']}", r["n_queries"],
          f"{common.fmt(r['median_t_cm'])}, {common.fmt(r['median_R_deg'])}",
          *(common.pct(r["recall"][k]) for k in RECALLS), r["n_queries"] - r["n_success"],
          common.fmt(r["median_inliers"], 0),
          common.fmt(1000 * r["localize_s_per_query"], 0)] for r in rows],
        title="Localization of every query (render = patches rendered by the reference "
              "image's cluster NeRF; real = stored real patches, the same EGM in every map)")


def room_table(rows: list[dict], n_rooms: int) -> str:
    rec = "5cm_5deg"
    return common.table(
        ["config / mode", *(f"room {r} ({rec})" for r in range(n_rooms))],
        [[f"{r['config']} / {r['mode']}",
          *(common.pct(r["per_room"][k]["recall"][rec]) + f" of {r['per_room'][k]['n_queries']}"
            if k in r["per_room"] else "-" for k in range(n_rooms))]
         for r in rows if r["mode"] == "render"],
        title="Render-mode recall per room (room 0: the 8 m hall; 1-3: the 3.5 m offices)")


def figure_path(args) -> Path:
    return Path(args.figure) if args.figure else Path(common.DEFAULT_JSON_DIR) / "clusters.png"


def figure(path: Path, ctxs: dict[str, common.SceneCtx], layout, map_rows: dict) -> str:
    """PNG of the reference cameras coloured by cluster, one panel per clustered map."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return "matplotlib is not installed: no figure"
    panels = [k for k in ctxs if ctxs[k].m.ilm.n_clusters > 1]
    if not panels:
        return "no clustered map: no figure"
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 2.4 * len(panels)), squeeze=False)
    q = ctxs[panels[0]].queries.centers
    for ax, label in zip(axes[:, 0], panels, strict=True):
        ctx = ctxs[label]
        ilm = ctx.m.ilm
        refs = ctx.scene.references()
        c = np.asarray(ilm.image_cluster)
        ax.scatter(refs.centers[:, 0], refs.centers[:, 1], c=c, cmap="tab10", vmin=0, vmax=9,
                   s=18, edgecolors="none", label="reference")
        ctr = np.asarray(ilm.cluster_centers)
        ax.scatter(ctr[:, 0], ctr[:, 1], c=np.arange(len(ctr)), cmap="tab10", vmin=0, vmax=9,
                   marker="X", s=90, edgecolors="k", label="cluster centre")
        ax.scatter(q[:, 0], q[:, 1], marker="x", c="0.3", s=14, label="query")
        for x in layout.room_x:
            ax.axvline(x, color="k", lw=1.5)
        if ctx.m.config.nerf.cluster_method == "grid":
            xs = np.sort(np.unique(np.round(ctr[:, 0], 6)))
            for a, b in zip(xs[:-1], xs[1:], strict=True):
                ax.axvline(0.5 * (a + b), color="r", ls="--", lw=1)
        bal = map_rows[label]["balance"]
        ax.set_title(f"{label}: images per cluster "
                     f"{'/'.join(map(str, bal['images_per_cluster']))}, "
                     f"rooms split {bal['rooms_split']}", fontsize=9)
        ax.set_xlim(layout.room_min[0], layout.room_max[0])
        ax.set_ylim(layout.room_min[1], layout.room_max[1])
        ax.set_aspect("equal")
        ax.set_ylabel("y (m)")
    axes[0, 0].legend(loc="upper right", fontsize=7, ncols=3)
    axes[-1, 0].set_xlabel("x (m); black: walls (doorways in the partitions), red dashed: "
                           "grid cell borders")
    fig.tight_layout()
    from benchmarks.figures import save

    return f"wrote {save(fig, path)}"


@cli_main
def main(argv: list[str] | None = None) -> int:
    from vrs_jax import maps
    from vrs_jax.eval import metrics

    args = build_parser().parse_args(argv)
    common.check_outputs(args, [common.json_path(args, "clusters"), figure_path(args)])
    modes = [m.strip() for m in args.modes.split(",") if m.strip()]
    only = [m.strip() for m in args.only.split(",") if m.strip()]
    if not modes or any(m not in MODES for m in modes):
        raise VrsError(f"--modes must list some of {', '.join(MODES)}, got {args.modes!r}")
    if not only or any(m not in LABELS for m in only):
        raise VrsError(f"--only must list some of {', '.join(LABELS)}, got {args.only!r}")
    doc = common.base_doc("clusters", args, argv)
    work = Path(args.work)
    t_start = time.perf_counter()
    scene, layout = make_scene(work, args.quiet)
    cfgs = map_configs(maps.get_config(args.config), args.clusters, args.steps, args.rays,
                       args.width, args.cluster_rays)
    spec = common.SceneSpec(SCENE_CONFIG, "7scenes", (), (), args.steps,
                            "synthetic rooms4: an 8 m hall and three 3.5 m offices in a row, "
                            f"{len(scene.references())} references + "
                            f"{len(scene.queries())} queries at 160x120")
    queries = scene.queries()
    queries = queries.subset(common.evenly_spaced(len(queries), args.max_queries))
    c = scene.centers[np.asarray(scene.has_pose, bool)]
    scale = metrics.scene_scale(c)
    ref_rooms = room_of(scene.references().centers, layout)
    q_rooms = room_of(queries.centers, layout)
    map_rows, acc_rows, ctxs = {}, [], {}
    for label in only:
        map_dir, build_s = build(label, cfgs[label], scene, work, args.quiet)
        m = maps.load_map(map_dir)
        ctx = common.SceneCtx(f"{SCENE_CONFIG}-{label}", spec, scene, queries, map_dir, m)
        ctxs[label] = ctx
        map_rows[label] = map_row(label, ctx, build_s, ref_rooms)
        acc_rows += localize_rows(label, ctx, modes, args, scale, q_rooms)
    fig_msg = figure(figure_path(args), ctxs, layout, map_rows)
    print()
    print(maps_table(list(map_rows.values())))
    print()
    print(accuracy_table(acc_rows))
    print()
    print(room_table(acc_rows, len(layout.room_x) - 1))
    print()
    print(fig_msg)
    total = time.perf_counter() - t_start
    doc.update({"scene": spec.note, "scene_scale_m": scale,
                "n_references": len(scene.references()), "n_queries": len(queries),
                "reference_rooms": np.bincount(ref_rooms).tolist(),
                "query_rooms": np.bincount(q_rooms, minlength=len(layout.room_x) - 1).tolist(),
                "room_x": np.asarray(layout.room_x).tolist(), "maps": map_rows,
                "rows": acc_rows, "figure": fig_msg, "total_s": total})
    out = common.write_json(common.json_path(args, "clusters"), doc)
    print(f"wrote {out} [{total:.0f} s in all]")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
