"""The whole system end to end: build a map (EGM + ILM) and localize a scene's queries.

This module only orchestrates the stages (each lives in its own sub-package); the experiments
are thin command-line wrappers around it. A map folder holds::

    MAPDIR/map.json            kind, format version, pipeline config, scene, stats
    MAPDIR/egm/                the VRS map's EGM (no local descriptors)
    MAPDIR/egm_baseline/       the same EGM plus real-patch descriptors (hierarchical baseline)
    MAPDIR/ilm.npz             the NeRFs, stacked per cluster
    MAPDIR/nerf/checkpoints/   orbax training checkpoints (resume; not needed to localize)

Re-running a build skips what is finished (hloc style) and resumes NeRF training from the
last checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np
from tqdm import tqdm

from vrs_jax import geometry
from vrs_jax.data.images import read_gray
from vrs_jax.data.scene import Scene
from vrs_jax.egm import build as egm_build
from vrs_jax.egm.map import EGM, load_egm, save_egm
from vrs_jax.egm.map import map_bytes as egm_bytes
from vrs_jax.errors import VrsError
from vrs_jax.eval import metrics
from vrs_jax.localize import config as loc_config
from vrs_jax.localize.localize import (
    STAGES,
    LocalizeResult,
    localize,
    localize_timed,
    nerf_evals_per_ray,
    rays_per_query,
)
from vrs_jax.localize.query import prepare_query
from vrs_jax.nerf import config as nerf_config
from vrs_jax.nerf import ilm as ilm_lib
from vrs_jax.nerf import train as nerf_train

KIND = "vrs_jax.map"
FORMAT_VERSION = 1


@dataclasses.dataclass(frozen=True)
class PipelineConfig:
    """Named bundle of the stage configs, plus the NeRF training budget."""

    name: str
    egm: str  # vrs_jax.egm.build config name
    nerf: str  # vrs_jax.nerf.config config name
    localize: str  # vrs_jax.localize.config config name
    # NeRF training length: total steps, and an optional wall-clock cap (minutes) per run.
    nerf_steps: int
    nerf_minutes: float | None = None


CONFIGS: dict[str, PipelineConfig] = {
    # The paper's scale: 2048 SIFT keypoints, 8x256 Mip-NeRF 128+128 samples; a GPU job.
    "paper": PipelineConfig("paper", egm="paper", nerf="paper", localize="paper",
                            nerf_steps=200_000),
    # Two CPU cores: the demo's setting (minutes per scene).
    "cpu-small": PipelineConfig("cpu-small", egm="cpu-small", nerf="cpu-small",
                                localize="cpu-small", nerf_steps=10_000, nerf_minutes=7.0),
    # Tests and `demo --quick`: seconds per stage.
    "test": PipelineConfig("test", egm="test", nerf="test", localize="test", nerf_steps=300,
                           nerf_minutes=2.0),
}


def get_config(name: str) -> PipelineConfig:
    if name not in CONFIGS:
        raise VrsError(f"unknown config {name!r}; choose from {sorted(CONFIGS)}")
    return CONFIGS[name]


def localize_config(pcfg: PipelineConfig, egm_cfg: egm_build.EGMConfig, mode: str,
                    **overrides: Any) -> loc_config.LocalizeConfig:
    """The localizer's config, with the map's patch and descriptor settings (they must agree:
    query descriptors are compared with descriptors of the map's keypoints' patches)."""
    base = loc_config.get_config(pcfg.localize)
    fixed = {"mode": mode, "descriptor": egm_cfg.features.descriptor}
    if mode == "gt" or "patches" not in overrides:
        fixed["patches"] = egm_cfg.features.patches
    return dataclasses.replace(base, **{**overrides, **fixed})


# ----------------------------------------------------------------------------- map building


def _atomic_json(path: Path, obj: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=1, default=float) + "\n")
    os.replace(tmp, path)


def _check_map_dir(out: Path, pcfg: PipelineConfig, scene: Scene) -> dict:
    """Refuse to mix a different config or scene into an existing map folder."""
    meta_p = out / "map.json"
    key = {"config": pcfg.name, "format": scene.format, "root": str(scene.root),
           "references": int((~scene.is_query).sum())}
    if meta_p.is_file():
        try:
            meta = json.loads(meta_p.read_text())
        except json.JSONDecodeError:
            raise VrsError("corrupt map.json", meta_p) from None
        if meta.get("key") != key:
            raise VrsError(f"this map folder was built with {meta.get('key')}; use another --out",
                           meta_p)
        return meta
    if out.exists() and any(out.iterdir()):
        raise VrsError("folder exists and is not a vrs-jax map; choose an empty --out", out)
    return {"kind": KIND, "format_version": FORMAT_VERSION, "key": key, "stats": {}}


def build_map(scene: Scene, out_dir: str | Path, pcfg: PipelineConfig, progress: bool = True,
              log=print, nerf_steps: int | None = None, nerf_minutes: float | None = None,
              n_clusters: int | None = None, nerf_overrides: dict | None = None) -> Path:
    """EGM (VRS + baseline), then the ILM trained on the reference images; resumable."""
    out = Path(out_dir)
    meta = _check_map_dir(out, pcfg, scene)
    out.mkdir(parents=True, exist_ok=True)
    _atomic_json(out / "map.json", meta)
    egm_cfg = egm_build.get_config(pcfg.egm)

    if not (out / "egm_baseline" / "egm.json").is_file():
        log(f"[1/3] EGM: features, pairs, triangulation ({len(scene.references())} references)")
        full, stats = egm_build.build_egm(scene, dataclasses.replace(egm_cfg, baseline=True),
                                          progress=progress)
        log(egm_build.format_stats(stats))
        meta["stats"]["egm"] = stats
        save_egm(full.without_local_descriptors(), out / "egm")
        save_egm(full, out / "egm_baseline")
        _atomic_json(out / "map.json", meta)
    else:
        log("[1/3] EGM: already built, skipping")
    egm = load_egm(out / "egm_baseline")

    ilm_path = out / "ilm.npz"
    steps = nerf_steps if nerf_steps is not None else pcfg.nerf_steps
    minutes = nerf_minutes if nerf_minutes is not None else pcfg.nerf_minutes
    if not ilm_path.is_file():
        over = dict(nerf_overrides or {})
        if n_clusters is not None:
            over["n_clusters"] = n_clusters
        ncfg = nerf_config.get_config(pcfg.nerf, **over)
        log(f"[2/3] ILM: {ncfg.n_clusters} Mip-NeRF cluster(s), config {ncfg.name}, "
            f"{steps} steps" + (f" or {minutes:g} min" if minutes else ""))
        # references only: the queries stay unseen (held-out PSNR is not computed here)
        refs_scene = scene.references()
        prep = nerf_train.prepare(refs_scene, ncfg, points3d=np.asarray(egm.points3d),
                                  patch_keypoints=(egm.keypoints, egm.kp_mask,
                                                   egm_cfg.features.patches))
        res = nerf_train.train(prep, out / "nerf", steps=steps, minutes=minutes,
                               progress=progress)
        ilm = res.ilm
        ilm_lib.save_ilm(ilm_path, ilm)
        meta["stats"]["ilm"] = {"steps": int(res.state.step), "steps_per_s": res.steps_per_s,
                                "train_s": res.seconds,
                                "history": res.history[-5:] if res.history else []}
        _atomic_json(out / "map.json", meta)
    else:
        log("[2/3] ILM: already trained, skipping")
    ilm = ilm_lib.load_ilm(ilm_path)
    _attach_clusters(egm, ilm, ilm_path)
    meta["stats"]["map_bytes"] = map_size(out)
    _atomic_json(out / "map.json", meta)
    return out


def _attach_clusters(egm: EGM, ilm: ilm_lib.ILM, where: Path) -> EGM:
    """EGM with each reference image's NeRF cluster; the image order must agree."""
    if tuple(ilm.image_names) != tuple(egm.names):
        raise VrsError("the NeRF map and the EGM list different reference images; rebuild",
                       where)
    return egm.replace(cluster=ilm.image_cluster)


def map_size(map_dir: str | Path) -> dict[str, int]:
    """Bytes on disk of what localization needs: the VRS map (EGM + ILM) and the baseline."""
    d = Path(map_dir)
    egm_b = egm_bytes(d / "egm")
    base_b = egm_bytes(d / "egm_baseline")
    ilm_b = ilm_lib.map_bytes(d / "ilm.npz") if (d / "ilm.npz").is_file() else 0
    return {"egm": egm_b["total"], "ilm": ilm_b, "total": egm_b["total"] + ilm_b,
            "baseline_total": base_b["total"], "egm_parts": egm_b, "baseline_parts": base_b}


@dataclasses.dataclass
class LoadedMap:
    meta: dict
    egm: EGM  # with baseline local descriptors (drop them for render mode)
    ilm: ilm_lib.ILM
    pcfg: PipelineConfig
    egm_cfg: egm_build.EGMConfig


def load_map(map_dir: str | Path) -> LoadedMap:
    """Read a map folder written by :func:`build_map` (one-line VrsError if unusable)."""
    d = Path(map_dir)
    meta_p = d / "map.json"
    if not d.is_dir():
        raise VrsError("map folder not found", d)
    if not meta_p.is_file():
        raise VrsError("not a vrs-jax map folder (no map.json)", d)
    try:
        meta = json.loads(meta_p.read_text())
    except json.JSONDecodeError:
        raise VrsError("corrupt map.json", meta_p) from None
    if meta.get("kind") != KIND:
        raise VrsError("not a vrs-jax map", meta_p)
    if meta.get("format_version") != FORMAT_VERSION:
        raise VrsError(f"map format version {meta.get('format_version')}, this vrs-jax reads "
                       f"version {FORMAT_VERSION}; rebuild the map", meta_p)
    if not (d / "ilm.npz").is_file():
        raise VrsError("the map has no trained NeRF yet (ilm.npz); finish the training run", d)
    pcfg = get_config(meta["key"]["config"])
    egm = load_egm(d / "egm_baseline")
    ilm = ilm_lib.load_ilm(d / "ilm.npz")
    egm = _attach_clusters(egm, ilm, d / "ilm.npz")
    return LoadedMap(meta, egm, ilm, pcfg, egm_build.get_config(pcfg.egm))


# ----------------------------------------------------------------------------- localization


def localize_queries(m: LoadedMap, queries: Scene, cfg: loc_config.LocalizeConfig,
                     progress: bool = True, timed: bool = True
                     ) -> tuple[list[LocalizeResult], dict[str, Any]]:
    """Localize every query image of a Scene; returns per-query results and a summary.

    Query preparation runs on the host per image; ``localize`` is compiled once (first query)
    and reused for all. With ``timed``, a warm-up call is made first and each query is run
    stage by stage to report median seconds per stage.
    """
    egm = m.egm if cfg.mode == "gt" else m.egm.without_local_descriptors()
    params = None if cfg.mode == "gt" else m.ilm
    results, times, prep_s = [], [], []
    warm = False
    for i in tqdm(range(len(queries)), desc=f"localize ({cfg.mode})", unit="query",
                  disable=not progress):
        t0 = time.perf_counter()
        size = tuple(int(s) for s in queries.sizes[i])
        q = prepare_query(read_gray(queries.image_paths[i], size=size), queries.K[i],
                          queries.dist[i], egm.vocab, cfg)
        prep_s.append(time.perf_counter() - t0)
        if timed:
            if not warm:
                localize_timed(params, egm, q, cfg)  # compile every stage once
                warm = True
            res, tm = localize_timed(params, egm, q, cfg)
            times.append(tm)
        else:
            res = localize(params, egm, q, cfg=cfg)
        results.append(jax.device_get(res))
    timing = {s: float(np.median([t[s] for t in times])) if times else None for s in STAGES}
    timing["query_preparation"] = float(np.median(prep_s)) if prep_s else None
    info = {
        "rays_per_query": rays_per_query(egm, cfg),
        "nerf_evals_per_query": (rays_per_query(egm, cfg) * nerf_evals_per_ray(m.ilm, cfg)
                                 if cfg.mode == "render" else 0.0),
        "timing_s": timing,
        "n_success": int(sum(bool(r.success) for r in results)),
    }
    return results, info


def summarize(queries: Scene, results: list[LocalizeResult], info: dict, m: LoadedMap,
              cfg: loc_config.LocalizeConfig, map_dir: Path) -> dict[str, Any]:
    """The summary.json content (DESIGN.md section 6 metrics when ground truth exists)."""
    R = np.stack([np.asarray(r.R, np.float64) for r in results]) if results else np.zeros(
        (0, 3, 3))
    t = np.stack([np.asarray(r.t, np.float64) for r in results]) if results else np.zeros((0, 3))
    gt = np.asarray(queries.has_pose, bool)
    sizes = map_size(map_dir)
    mb = ({"egm": sizes["baseline_total"], "ilm": 0, "total": sizes["baseline_total"]}
          if cfg.mode == "gt" else
          {"egm": sizes["egm"], "ilm": sizes["ilm"], "total": sizes["total"]})
    out: dict[str, Any] = {"n_queries": len(results), "mode": cfg.mode,
                           "config": m.pcfg.name, "patch_size": cfg.patches.size,
                           "depth_guided": cfg.depth_guided}
    if gt.any():
        dt, dr = geometry.pose_errors(R[gt], t[gt], queries.R[gt], queries.t[gt])
        s = metrics.summarize(dt, dr)
        out.update({"median_t_cm": s["median_t_cm"], "median_R_deg": s["median_R_deg"],
                    "recall": s["recall"], "n_with_ground_truth": int(gt.sum())})
    else:
        out.update({"median_t_cm": None, "median_R_deg": None, "recall": None,
                    "n_with_ground_truth": 0})
    out.update({"map_bytes": mb, "timing_s": info["timing_s"],
                "rays_per_query": info["rays_per_query"],
                "nerf_evals_per_query": info["nerf_evals_per_query"],
                "n_success": info["n_success"],
                "n_fallback": int(sum(bool(r.fallback) for r in results)),
                "median_inliers": float(np.median([int(r.n_inliers) for r in results]))
                if results else 0.0})
    return out
