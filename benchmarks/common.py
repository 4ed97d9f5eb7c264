"""Shared pieces of the benchmarks: the scenes, their maps, run records, tables and JSON.

Every benchmark (``python -m benchmarks.NAME``) takes the same scene arguments
(:func:`add_scene_args`): ``--scenes``, ``--config``, ``--nerf-minutes``, ``--work``,
``--data-root``, ``--map NAME=DIR``, ``--max-queries``. Maps are built with
:func:`vrs_jax.maps.build_map` into ``WORK/NAME-CONFIG/map`` and reused when they exist
(``build_map`` skips finished work), so the suite pays for map building once.

Scenes (:data:`SCENES`):

- ``synthetic``: the embedded synthetic room (the demo's scene, 60 references + 20 queries
  at 320x240), generated into ``WORK/synthetic/scene``;
- ``fern``: LLFF fern (20 photos at 504x378), every 5th image a query;
- ``lego``: NeRF synthetic lego (100 views at 200x200), every 8th image a query;
- ``scan24``: DTU scan 24 (49 real photos at 384x384, calibrated poses), every 5th a query.

NeRF training length is a step budget per scene (:attr:`SceneSpec.nerf_steps`, stored in the
map's config), so a benchmark map does not depend on machine load. Suggested order: map_size
(builds the maps), localize, ablation, render, figures.

The real scenes are read from ``--data-root`` (default ``$VRS_SHARED_DATA`` or the
``shared/data`` folder beside the checkout) and skipped with a note when absent.

Localization runs (per scene, mode, patch size, sampler, top-k, queries) are recorded as
JSON under ``WORK/runs/NAME/``; a record is reused only when its key matches exactly: the
same map files (path, size, modification time), the same LocalizeConfig, the same query
list and the same vrs_jax source code (a hash of every ``vrs_jax/**/*.py`` file). So a
benchmark can reuse another's measurement (the ablation's 15 x 15 and GT rows are the
localize benchmark's) and a code change re-measures everything.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import shlex
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from vrs_jax import runrecord
from vrs_jax.errors import VrsError

REPO = Path(__file__).resolve().parents[1]
DEFAULT_WORK = "outputs/bench_work"
DEFAULT_JSON_DIR = "outputs/benchmarks"
RUNS_VERSION = 4  # 4: per-query verdict, confidence and the evidence it reads


# ----------------------------------------------------------------------------- scenes


@dataclasses.dataclass(frozen=True)
class SceneSpec:
    """A benchmark scene: where its data is and how to split it."""

    name: str
    fmt: str  # reader format (vrs_jax.data.readers)
    parts: tuple[str, ...]  # path under --data-root; () for the generated synthetic scene
    # reader options (vrs_jax.data.readers.load_scene) as (key, value) pairs: the split
    # (query_every: every N-th image a query; query_range: a stretch held out) and downscale
    options: tuple[tuple[str, Any], ...]
    # NeRF training steps (cpu-small) when the suite builds the map: the synthetic room (the
    # demo's scene) trains as the config says; the small real scenes 3000 steps each (~5 min
    # on 2 cores) so that map building stays within ~25 minutes for the four of them.
    nerf_steps: int | None
    note: str
    # NeRF config overrides of the scene's map (unbounded scenes: the scene contraction)
    nerf: tuple[tuple[str, Any], ...] = ()

    @property
    def reader_options(self) -> dict[str, Any]:
        return dict(self.options)


# the phone walk's held-out leg: frames 141-190 walk out to the far end of the roof and back
# (the map keeps the walk's earlier visits there, frames 41-80)
WALK_LEG = "140:190"

SCENES: dict[str, SceneSpec] = {
    "synthetic": SceneSpec("synthetic", "7scenes", (), (), None,
                           "embedded synthetic room, 60 references + 20 queries at 320x240"),
    "fern": SceneSpec("fern", "llff", ("llff_fern", "data", "nerf_llff_data", "fern"),
                      (("query_every", 5),), 3000,
                      "LLFF fern, 20 photos at 504x378, every 5th a query"),
    "lego": SceneSpec("lego", "nerf", ("nerf_synthetic_lego_200",), (("query_every", 8),),
                      3000, "NeRF synthetic lego, 100 views at 200x200, every 8th a query"),
    "scan24": SceneSpec("scan24", "nerf", ("dtu_scan24",), (("query_every", 5),), 3000,
                        "DTU scan 24, 49 real photos at 384x384, every 5th a query"),
    "fox": SceneSpec("fox", "nerf", ("instant_ngp_fox",),
                     (("query_every", 5), ("downscale", 4)), 3000,
                     "instant-ngp fox, 50 handheld photos at 270x480 (1/4), every 5th a "
                     "query"),
    "walk": SceneSpec("walk", "nerf", ("phone_walk",), (("query_every", 10),), 4000,
                      "phone walk over a rooftop, 302 frames at 480x270, every 10th a query; "
                      "unbounded: contracted NeRF", (("contraction", True),)),
    "walk-leg": SceneSpec("walk-leg", "nerf", ("phone_walk",), (("query_range", WALK_LEG),),
                          4000, f"phone walk, frames {WALK_LEG} (one out-and-back leg) held "
                          "out as queries; contracted NeRF", (("contraction", True),)),
}


def default_data_root() -> Path:
    env = os.environ.get("VRS_SHARED_DATA")
    return Path(env) if env else (REPO / ".." / "shared" / "data").resolve()


def add_scene_args(p: argparse.ArgumentParser, default_scenes: Sequence[str]) -> None:
    """The scene and map arguments every benchmark shares."""
    p.add_argument("--scenes", default=",".join(default_scenes),
                   help=f"comma-separated scenes among {', '.join(SCENES)} (scenes whose data "
                        "is absent are skipped with a note)")
    p.add_argument("--config", default="cpu-small",
                   help="map and localize config of the maps the benchmark builds (paper, "
                        "cpu-small, test)")
    p.add_argument("--nerf-steps", type=int, default=None,
                   help="NeRF training steps when a map is built (default per scene: "
                        + ", ".join(f"{s.name} {s.nerf_steps or 'the config'}"
                                    for s in SCENES.values()) + ")")
    p.add_argument("--work", default=DEFAULT_WORK,
                   help="folder of the benchmark maps, scenes and run records (reused)")
    p.add_argument("--data-root", default=None,
                   help="folder holding the real datasets (default: $VRS_SHARED_DATA or "
                        "../shared/data beside the checkout)")
    p.add_argument("--synthetic-root", default=None,
                   help="use this synthetic scene folder (7Scenes layout) instead of "
                        "generating the default one into WORK/synthetic/scene")
    p.add_argument("--map", action="append", default=[], metavar="SCENE=DIR",
                   help="use an existing map folder for a scene (e.g. "
                        "synthetic=outputs/demo/map) instead of building one; repeatable")
    p.add_argument("--max-queries", type=int, default=None,
                   help="localize at most N queries per scene (evenly spaced; default all)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")


def parse_scenes(text: str) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    bad = [s for s in names if s not in SCENES]
    if bad or not names:
        raise VrsError(f"unknown scene(s) {', '.join(bad) or '(none)'}; choose from "
                       f"{', '.join(SCENES)}")
    return names


def parse_maps(items: list[str]) -> dict[str, Path]:
    out = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or name not in SCENES or not path:
            raise VrsError(f"--map expects SCENE=DIR with SCENE in {', '.join(SCENES)}, "
                           f"got {item!r}")
        out[name] = Path(path)
    return out


@dataclasses.dataclass
class SceneCtx:
    """A scene ready to benchmark: its data, its map and the queries to localize."""

    name: str
    spec: SceneSpec
    scene: Any  # vrs_jax.data.scene.Scene (references + queries)
    queries: Any  # Scene of the queries used (possibly an evenly spaced subset)
    map_dir: Path
    m: Any  # vrs_jax.maps.Map


def _load_scene(fmt: str, root: Path, opts: dict[str, Any]):
    from vrs_jax.data.readers import load_scene

    return load_scene(fmt, root, **opts)


def _parse_option(text: Any) -> Any:
    """A reader option as a map records it (text) -> its value (int where it is one)."""
    try:
        return int(text)
    except (TypeError, ValueError):
        return text


def scene_root(name: str, args, log: Callable[[str], None] = print) -> Path | None:
    """The dataset folder of a scene (generating the synthetic one), or None if absent."""
    spec = SCENES[name]
    if name == "synthetic":
        if args.synthetic_root:
            root = Path(args.synthetic_root)
            if not root.is_dir():
                raise VrsError("synthetic scene folder not found", root)
            return root
        from vrs_jax.data import synthetic

        root = Path(args.work) / "synthetic" / "scene"
        return synthetic.generate(root, synthetic.get_config("default"),
                                  progress=not args.quiet)
    root = Path(args.data_root) if args.data_root else default_data_root()
    root = root.joinpath(*spec.parts)
    if not root.exists():
        log(f"[{name}] skipped: data not found at {root}")
        return None
    return root


def given_map_root(name: str, recorded: Path, args, map_dir: Path,
                   log: Callable[[str], None] = print) -> Path:
    """The dataset folder of a map given with --map: the scene's folder under --data-root
    when one is given (a map built elsewhere, or on another copy of the data), else the
    folder the map recorded, else the scene's default folder. VrsError when none exists."""
    candidates = []
    if args.data_root and name != "synthetic":
        candidates.append(Path(args.data_root).joinpath(*SCENES[name].parts))
    candidates.append(recorded)
    if not args.data_root and name != "synthetic":
        candidates.append(default_data_root().joinpath(*SCENES[name].parts))
    for root in candidates:
        if root.exists():
            if root != recorded:
                log(f"[{name}] reading the map's images from {root} (recorded: {recorded})")
            return root
    raise VrsError("the map's dataset folder is not there (recorded "
                   f"{recorded}; looked in {', '.join(str(c) for c in candidates)}): "
                   "pass --data-root", map_dir)


def evenly_spaced(n: int, k: int | None) -> np.ndarray:
    """k indices spread evenly over range(n) (all of them when k is None or >= n)."""
    if k is None or k >= n:
        return np.arange(n)
    if k < 1:
        raise VrsError("--max-queries must be >= 1")
    return np.unique(np.round(np.linspace(0, n - 1, k)).astype(int))


def prepare_scene(name: str, args, log: Callable[[str], None] = print, need_nerf: bool = True
                  ) -> SceneCtx | None:
    """Load (building if needed) the map of scene ``name``; None if its data is absent.
    ``need_nerf`` False: a map without a trained NeRF will do (real-patch mode only), and a map
    built here stops after the EGM (a later build continues it)."""
    from vrs_jax import maps

    spec = SCENES[name]
    given = parse_maps(args.map)
    if name in given:
        map_dir = given[name]
        src = maps.load_map(map_dir, require_ilm=False).source
        # the map's own split (its recorded reader options), else the scene's
        opts = ({k: _parse_option(v) for k, v in src.options} if src.format
                else spec.reader_options)
        root = given_map_root(name, Path(src.root), args, map_dir, log)
        scene = _load_scene(src.format or spec.fmt, root, opts)
    else:
        root = scene_root(name, args, log)
        if root is None:
            return None
        opts = spec.reader_options
        scene = _load_scene(spec.fmt, root, opts)
        steps = args.nerf_steps if args.nerf_steps is not None else spec.nerf_steps
        nerf = {**dict(spec.nerf), **({"max_steps": steps} if steps else {})}
        cfg = maps.get_config(args.config, **nerf)
        map_dir = Path(args.work) / f"{name}-{cfg.name}" / "map"
        log(f"[{name}] map {map_dir} (built if missing; " + (
            f"NeRF {cfg.nerf.max_steps} steps)" if need_nerf else "the EGM only)"))
        maps.build_map(scene, map_dir, cfg, progress=not args.quiet,
                       log=lambda s: log(f"[{name}] {s}"), source_options=opts,
                       train_nerf=need_nerf)
    m = maps.load_map(map_dir, require_ilm=need_nerf)
    if set(m.egm.names) != set(scene.references().names):
        raise VrsError(f"the map's reference images are not the {name} scene's references "
                       "(another split or dataset?)", map_dir)
    queries = scene.queries()
    if len(queries) == 0:
        raise VrsError("the scene has no query images", scene.root)
    queries = queries.subset(evenly_spaced(len(queries), args.max_queries))
    return SceneCtx(name, spec, scene, queries, map_dir, m)


def prepare_scenes(args, log: Callable[[str], None] = print, need_nerf: bool = True
                   ) -> tuple[list[SceneCtx], list[dict[str, str]]]:
    """Every scene of ``--scenes``: (ready scenes, skipped scenes with the reason);
    ``need_nerf`` as :func:`prepare_scene`."""
    ready, skipped = [], []
    for name in parse_scenes(args.scenes):
        ctx = prepare_scene(name, args, log, need_nerf=need_nerf)
        if ctx is None:
            skipped.append({"scene": name, "reason": "data not found"})
        else:
            ready.append(ctx)
    return ready, skipped


def map_info(ctx: SceneCtx) -> dict[str, Any]:
    """What the JSON records about a map: folder, config values, training stats, sizes."""
    from vrs_jax import configio, maps

    m = ctx.m
    stats = maps.read_stats(ctx.map_dir)
    return {"map_dir": str(ctx.map_dir), "map_config": configio.to_dict(m.config),
            "n_references": m.egm.num_images, "n_points3d": m.egm.num_points,
            "k_max": m.egm.k_max,
            "mean_keypoints_per_image": float(np.asarray(m.egm.kp_mask).sum(1).mean()),
            "n_queries_used": len(ctx.queries), "n_queries_scene": int(ctx.scene.is_query.sum()),
            "nerf_training": {k: v for k, v in stats.get("ilm", {}).items() if k != "history"},
            "map_bytes": maps.map_bytes(ctx.map_dir), "scene": ctx.spec.note}


# ----------------------------------------------------------------------------- localization


def patch_config(ctx: SceneCtx, size: int | None = None, mode: str | None = None):
    """The map's patch config with another size P / mode (render mode may change them)."""
    p = ctx.m.config.features.patches
    over = {k: v for k, v in (("size", size), ("mode", mode)) if v is not None}
    return dataclasses.replace(p, **over) if over else p


def localize_cfg(ctx: SceneCtx, mode: str, size: int | None = None, config: str | None = None,
                 **overrides):
    """The named localize config for ``mode`` ("render"/"real"), with an optional patch
    size P (render mode only)."""
    from vrs_jax import localize

    if mode == "render" and size is not None and size != patch_config(ctx).size:
        overrides["patches"] = patch_config(ctx, size)
    return localize.get_config(config or ctx.m.config.name, source=mode, **overrides)


def localize_overrides(items: list[str], defaults: Any = None) -> dict[str, Any]:
    """``KEY=VALUE`` -> typed LocalizeConfig overrides (bool, int or float fields, optional
    floats: ``none`` or a number, and tuples of names joined by ``+``, e.g.
    ``guided_sources=render+real``); ``defaults``: another config dataclass instance whose
    fields to override (e.g. a TrackConfig)."""
    from vrs_jax.localize.config import LocalizeConfig

    defaults = LocalizeConfig() if defaults is None else defaults
    out: dict[str, Any] = {}
    for item in items:
        key, _, val = item.partition("=")
        key = key.strip().replace("-", "_")
        cur = getattr(defaults, key, "") if key in {
            f.name for f in dataclasses.fields(defaults)} else ""
        if cur is None:  # an optional number: "none" or a float
            cur = 0.0
            if val.strip().lower() == "none":
                out[key] = None
                continue
        if _ and isinstance(cur, tuple) and all(isinstance(v, str) for v in cur):
            out[key] = tuple(v.strip() for v in val.split("+") if v.strip())
            continue
        if not _ or not isinstance(cur, (bool, int, float)):
            raise VrsError(f"expected KEY=VALUE of a number/bool field of "
                           f"{type(defaults).__name__}, got {item!r}")
        try:
            if isinstance(cur, bool):
                out[key] = val.lower() in ("1", "true", "yes")
            else:
                out[key] = type(cur)(val)
        except ValueError:
            raise VrsError(f"bad value for {key}: {val!r}") from None
    return out


def _file_stamp(p: Path) -> list:
    st = p.stat()
    return [str(p.resolve()), st.st_size, st.st_mtime_ns]


def map_stamp(map_dir: Path) -> list:
    d = Path(map_dir)
    return [_file_stamp(d / n) for n in ("map.json", "egm.npz", "ilm.npz", "descriptors.npz")
            if (d / n).is_file()]


_SOURCE_HASH: str | None = None


def source_hash() -> str:
    """sha256 of every vrs_jax source file and this module (a run record's code version)."""
    global _SOURCE_HASH
    if _SOURCE_HASH is None:
        h = hashlib.sha256()
        files = sorted((REPO / "vrs_jax").rglob("*.py")) + [Path(__file__).resolve()]
        for f in files:
            h.update(str(f.relative_to(REPO)).encode())
            h.update(f.read_bytes())
        _SOURCE_HASH = h.hexdigest()
    return _SOURCE_HASH


def run_tag(ctx: SceneCtx, cfg) -> str:
    p = cfg.patches or patch_config(ctx)
    lit = "-literal" if p.mode == "literal" else ""
    if cfg.source == "real":
        return f"real_P{p.size}{lit}_k{cfg.top_k}"
    sampler = "dg" if cfg.depth_guided else "full"
    return f"render_P{p.size}{lit}_{sampler}_k{cfg.top_k}"


def localize_run(ctx: SceneCtx, cfg, work: str | Path, fresh: bool = False,
                 progress: bool = True, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Localize the scene's queries with ``cfg`` (or reuse a matching record).

    Returns :func:`vrs_jax.eval.report.summarize`'s dict plus ``per_query`` (names, t_err_m,
    R_err_deg (inf / 180 for failures), success, fallback, inliers, matches, rendered, and
    the pose confidence: verdict, confidence and the quantities it reads, :func:`_per_query`),
    ``localize_s_per_query`` (sum of the median stage times), ``wall_s``, ``measured_at``,
    ``reused`` and ``record``.
    """
    from vrs_jax.eval.report import median_evals, summarize
    from vrs_jax.localize import STAGE_NAMES
    from vrs_jax.localize.batch import localize_scene, rays_rendered
    from vrs_jax.localize.render import nerf_evals_per_ray
    from vrs_jax.localize.stages import guided_on

    key = {"version": RUNS_VERSION, "map": map_stamp(ctx.map_dir), "cfg": repr(cfg),
           "queries": list(ctx.queries.names), "source": source_hash()}
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
    tag = run_tag(ctx, cfg)
    path = Path(work) / "runs" / ctx.name / f"{tag}_{digest}.json"
    if not fresh and path.is_file():
        try:
            doc = json.loads(path.read_text())
        except json.JSONDecodeError:
            doc = None
        if doc is not None and doc.get("key") == key:
            log(f"[{ctx.name}] {tag}: reusing {path} ({doc['summary']['measured_at']})")
            out = doc["summary"]
            for o in (out, out.get("first_pass")):
                if o:
                    o["per_query"]["t_err_m"] = _inf(o["per_query"]["t_err_m"])
                    o["per_query"]["R_err_deg"] = _inf(o["per_query"]["R_err_deg"], 180.0)
            return {**out, "reused": True, "record": str(path)}
    t0 = time.perf_counter()
    results, info = localize_scene(ctx.m, ctx.queries, cfg, progress=progress)
    wall = time.perf_counter() - t0
    # the first pass alone: its pose and inliers, no guided pass (so no guided-ratio test)
    first = [None if r is None else r.replace(R=r.R_first, t=r.t_first,
                                               n_inliers=r.n_inliers_first,
                                               n_inliers_guided=np.int32(-1),
                                               n_rendered=r.n_rendered_first) for r in results]
    out = {}
    for which, res in (("final", results), ("first", first)):
        s = summarize(ctx.queries, res, info, ctx.m, cfg, ctx.map_dir)
        s["per_query"] = _per_query(ctx.queries, res, ctx.m, cfg)
        if which == "first":  # the first pass alone: no guided stage, its rays only
            cfg1 = dataclasses.replace(cfg, guided_passes=0)
            s["timing_s"] = {**s["timing_s"], "guided": 0.0}
            s["rays_per_query"] = rays_rendered(ctx.m, cfg1, first)
            s["nerf_evals_per_query"] = s["rays_per_query"] * nerf_evals_per_ray(ctx.m, cfg1)
            s["nerf_evals_per_query_median"] = median_evals(ctx.m, cfg1, first)
        s["localize_s_per_query"] = float(sum(s["timing_s"][k] or 0.0 for k in STAGE_NAMES))
        s["wall_s"] = wall
        s["measured_at"] = now()
        out[which] = s
    s = out["final"]
    s["retried"] = info["retried"]  # per query retried: attempts made, the one kept
    s["first_pass"] = out["first"] if guided_on(cfg) else None
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, {"key": key, "summary": s})
    return {**s, "reused": False, "record": str(path)}


def _per_query(q, results: list, m, cfg) -> dict[str, list]:
    """Per-query errors (inf / 180 for a query without a result), success, inliers, matches,
    patches rendered, and the pose confidence against map ``m`` with ``cfg.confidence``:
    ``verdict``, ``confidence`` and each quantity it reads (inlier_ratio, coverage,
    pass_shift, pass_rotation, guided_ratio, ...: localize.confidence.evidence; None where
    not defined, as JSON reads it back), so that which verdict a wrong pose got can be checked."""
    from vrs_jax.eval import metrics
    from vrs_jax.localize.confidence import evidence, map_scale, result_fields

    has = np.array([r is not None for r in results]) & np.asarray(q.has_pose, bool)
    R = np.stack([np.asarray(r.R, np.float64) if r is not None else np.eye(3)
                  for r in results])
    t = np.stack([np.asarray(r.t, np.float64) if r is not None else np.zeros(3)
                  for r in results])
    dt, dr = metrics.pose_errors(R, t, q.R, q.t, has_estimate=has)
    return {"names": list(q.names), "t_err_m": dt.tolist(), "R_err_deg": dr.tolist(),
            "success": [bool(r is not None and r.success) for r in results],
            "fallback": [bool(r is not None and r.fallback) for r in results],
            "inliers": [int(r.n_inliers) if r is not None else 0 for r in results],
            "matches": [int(r.n_matches) if r is not None else 0 for r in results],
            "rendered": [int(r.n_rendered) if r is not None else 0 for r in results],
            **{k: [None if isinstance(x, float) and not math.isfinite(x) else x
                   for x in v.tolist()]
               for k, v in evidence(result_fields(results), map_scale(m),
                                    cfg.confidence).items()}}


def _inf(xs: list, missing: float = math.inf) -> list[float]:
    """Errors read back from JSON (where inf was written as null)."""
    return [missing if x is None else float(x) for x in xs]


# ----------------------------------------------------------------------------- timing


def compile_and_time(fn, *args, repeats: int = 3, budget_s: float = 2.0
                     ) -> tuple[float, float, Any]:
    """Compile a jitted ``fn`` for ``args`` ahead of time, then time calls of it.

    Calls it ``repeats`` times, or fewer once the calls made add up to ``budget_s`` (at least
    once): long calls are measured once, short ones several times. Returns (median seconds
    per call, compile seconds, last output). Compiling with ``lower().compile()`` spares the
    warm-up call, which matters for calls of many seconds.
    """
    t0 = time.perf_counter()
    compiled = fn.lower(*args).compile()
    compile_s = time.perf_counter() - t0
    sec, out = time_calls(compiled, *args, repeats=repeats, budget_s=budget_s)
    return sec, compile_s, out


def time_calls(fn, *args, repeats: int = 3, budget_s: float = 2.0) -> tuple[float, Any]:
    """Median seconds of up to ``repeats`` calls (fewer past ``budget_s``), last output."""
    import jax

    times: list[float] = []
    out = None
    while not times or (len(times) < repeats and sum(times) < budget_s):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


# ----------------------------------------------------------------------------- records


def now() -> str:
    return runrecord.utc_now()


def environment() -> dict[str, Any]:
    """Machine, device, library versions and code version, for every benchmark JSON
    (:func:`vrs_jax.runrecord.environment` plus matplotlib and the source hash)."""
    env = runrecord.environment()
    env["versions"]["matplotlib"] = runrecord.package_version("matplotlib")
    env["code"]["vrs_jax_source_sha256"] = source_hash()
    return env


def base_doc(benchmark: str, args: argparse.Namespace, argv: list[str] | None
             ) -> dict[str, Any]:
    """The common head of a benchmark JSON: name, command, environment, arguments."""
    argv = sys.argv[1:] if argv is None else list(argv)
    command = " ".join(["python", "-m", f"benchmarks.{benchmark}"] + [shlex.quote(a)
                                                                       for a in argv])
    return {"benchmark": benchmark, "command": command, **environment(),
            "args": {k: v for k, v in vars(args).items()}}


def write_json(path: str | Path, doc: dict) -> Path:
    """Strict JSON (non-finite numbers as null), written atomically."""
    from vrs_jax import fileio

    fileio.refuse_map_part(path)  # --json pointed into a map folder (its map.json)
    return fileio.write_json(path, doc)


# ----------------------------------------------------------------------------- tables


def fmt(x: Any, digits: int = 2) -> str:
    """A number for a table: None/nan -> '-', inf -> 'inf', ints as ints."""
    if x is None:
        return "-"
    if isinstance(x, (bool, np.bool_)):
        return "yes" if x else "no"
    if isinstance(x, (int, np.integer)):
        return f"{int(x):,}"
    x = float(x)
    if math.isnan(x):
        return "-"
    if math.isinf(x):
        return "inf"
    return f"{x:,.{digits}f}"


def pct(x: Any) -> str:
    return "-" if x is None else f"{100.0 * float(x):.1f}%"


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]], title: str | None = None
          ) -> str:
    """A plain-text table: first column left-aligned, the others right-aligned."""
    cells = [[str(c) for c in r] for r in rows]
    widths = [max([len(h)] + [len(r[i]) for r in cells]) for i, h in enumerate(headers)]

    def line(r):
        return "  ".join(c.ljust(w) if i == 0 else c.rjust(w)
                         for i, (c, w) in enumerate(zip(r, widths, strict=True)))

    out = [title] if title else []
    out += [line(headers), "  ".join("-" * w for w in widths)]
    out += [line(r) for r in cells]
    return "\n".join(out)


def json_path(args, name: str) -> Path:
    return Path(args.json) if args.json else Path(DEFAULT_JSON_DIR) / f"{name}.json"


# ----------------------------------------------------------------------------- outputs

INPUT_ARGS = ("map", "series_egm", "data_root", "synthetic_root", "root", "data",
              "localize_json", "from_json")
"""Arguments of the benchmarks that name what they read (``NAME=DIR`` items: the DIR)."""


def add_overwrite_arg(p: argparse.ArgumentParser) -> None:
    p.add_argument("--overwrite", action="store_true",
                   help="replace existing output files (--json, --plot, the figures)")


def input_paths(args: argparse.Namespace) -> list[str]:
    """The paths a benchmark reads, from its :data:`INPUT_ARGS`."""
    out = []
    for name in INPUT_ARGS:
        value = getattr(args, name, None)
        for item in value if isinstance(value, list) else [value]:
            if item and name in ("map", "series_egm") and isinstance(value, list):
                item = item.partition("=")[2]
            if item:
                out.append(str(item))
    return out


def check_outputs(args: argparse.Namespace, paths: Sequence[str | Path | None]) -> None:
    """Before any work, each output file of a benchmark (None: not written): never an input
    of the run nor part of a map folder, and an existing file is refused unless --overwrite
    (:mod:`vrs_jax.fileio`'s rules, one VrsError line naming it); its folder must be
    writable."""
    from vrs_jax import fileio

    inputs = input_paths(args)
    for path in paths:
        if path is None:
            continue
        fileio.refuse_map_part(path)
        fileio.check_apart(path, inputs)
        if Path(path).is_dir():
            raise VrsError("is a folder; name the file to write", path)
        fileio.check_new(path, getattr(args, "overwrite", False))
        fileio.check_writable(Path(path).parent)
