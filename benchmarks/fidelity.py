"""Patch fidelity of the NeRF map at its own reference views: map bytes vs rendered patches.

    python -m benchmarks.fidelity --format nerf --root /data/dtu_scan24 \\
        --query-every 5 --steps 3000 --work runs/fid_scan24 --json runs/fid_ipe.json \\
        [--set encoding=hashgrid --set net_depth=2 ...] [--label NAME]
    python -m benchmarks.fidelity --map runs/map_scan24 --json runs/fid_map.json

With ``--map`` it measures an existing map folder (no training; the scene is the one the
map records unless --format/--root are given).

What it does:

1. builds the map of the scene's reference views with ``maps.build_map`` (the named
   ``--config`` with the ``--set`` NeRF overrides and ``--steps`` as the step budget, which is
   also the lr schedule's length), into ``--work/map_<hash of the config>`` (reused);
2. at every reference view (or ``--views`` of them, evenly spaced): the keypoint patches
   rendered as localization renders them (``localize.render.render_reference`` with the
   named localize config) and the real patches at the same keypoints read as the map's
   real-patch descriptors are (``features.patches.extract_patches`` on the view's grey image,
   the path of ``egm.build``); both described by ``features.descriptor.describe``.

Reported per field (and again with every float parameter rounded to float16, the map
stored at half precision):
  - patch PSNR: rendered vs real grey patches, pooled MSE over the valid keypoints' samples
    (and the median of per-patch PSNRs);
  - own-keypoint rate: for each rendered descriptor, is its nearest real descriptor of the
    same view its own keypoint's;
  - matches: mutual-NN + ratio matches rendered -> real of the same view, as localization
    matches (``features.matching.match`` with the localizer's ratio), and how many of them
    are the own keypoint;
  - surface depth: at each keypoint's centre ray, the field's rendered depth (the map's full
    coarse + fine sampler) over the keypoint's 3D point depth, and how often it lies inside
    the localizer's depth window (+- ``depth_margin``), where depth-guided rendering samples;
  - the own-keypoint rate (and the surface-in-window rate) by the keypoint's 3D point depth,
    in units of the scene's scale (the median camera distance to the cameras' centroid, as
    the localization benchmarks' "% of the scale"): near (< 1), mid (1-4), far (>= 4) --
    where a field of fixed size spends too little resolution shows here;
  - NeRF map bytes (the .npz as saved, float32 and float16), parameters, training steps/s
    (after compilation) and seconds, evaluation seconds.
Prints a table and writes JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import common
from vrs_jax.errors import VrsError, cli_main


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.fidelity", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--format", default=None, dest="fmt", help="dataset format (nerf, llff, ...)")
    p.add_argument("--root", default=None, help="dataset root folder")
    p.add_argument("--map", default=None,
                   help="measure this map folder instead of building one")
    p.add_argument("--query-every", type=int, default=None, metavar="N",
                   help="every N-th image is a query (formats without a split)")
    p.add_argument("--downscale", type=int, default=None, help="read images downscaled by N")
    p.add_argument("--config", default="cpu-small",
                   help="named map and localize config (EGM, NeRF, rendering)")
    p.add_argument("--steps", type=int, default=None,
                   help="NeRF training steps (required without --map)")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a NerfConfig field (repeatable)")
    p.add_argument("--localize", action="append", default=[], metavar="KEY=VALUE",
                   help="override a LocalizeConfig field of the renderer (depth_guided, "
                        "narrow_samples, narrow_fine, depth_margin), e.g. to separate the "
                        "field's error from the depth-guided sampling's")
    p.add_argument("--render", action="append", default=[], metavar="KEY=VALUE",
                   help="override a NerfConfig sampling field at rendering only (e.g. "
                        "num_samples_coarse=16, num_samples_fine=16 with depth_guided=false)")
    p.add_argument("--label", default=None, help="name of this field in the table")
    p.add_argument("--views", type=int, default=None,
                   help="evaluate this many reference views, evenly spaced (default: all)")
    p.add_argument("--no-fp16", action="store_true",
                   help="skip the evaluation of the float16-rounded map")
    p.add_argument("--work", default=None,
                   help="folder of the maps built (reused across runs; default beside --json)")
    p.add_argument("--json", required=True, help="output JSON file")
    common.add_overwrite_arg(p)
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


# ----------------------------------------------------------------------------- stages


def load(args):
    from vrs_jax.data.readers import load_scene, options

    opts = scene_options(args)
    if "query_every" in opts and "query_every" not in options(args.fmt):
        raise VrsError(f"format {args.fmt} has its own split (no --query-every)", args.root)
    return load_scene(args.fmt, args.root, **opts)


def map_of(scene, args, overrides: dict[str, Any], work: Path, progress: bool, log=print):
    """Build (or reuse) the map of the scene with the named config, the NeRF overrides and
    the step budget; returns (map, training info)."""
    from vrs_jax import configio, maps

    cfg = maps.get_config(args.config, **{**overrides, "max_steps": args.steps})
    key = hashlib.sha1(json.dumps(configio.to_dict(cfg), sort_keys=True).encode()
                       + str(scene.root).encode()).hexdigest()[:12]
    map_dir = work / f"map_{key}"
    maps.build_map(scene, map_dir, cfg, progress=progress, log=log,
                   source_options=scene_options(args))
    st = maps.read_stats(map_dir).get("ilm", {})
    return maps.load_map(map_dir), {"steps": st.get("steps"),
                                    "steps_per_s": st.get("steps_per_s"),
                                    "train_s": st.get("train_s"), "compile_s": None}


def scene_options(args) -> dict[str, Any]:
    opts: dict[str, Any] = {}
    if args.query_every is not None:
        opts["query_every"] = args.query_every
    if args.downscale is not None:
        opts["downscale"] = args.downscale
    return opts


# NerfConfig fields that change how a trained field is rendered, not the field itself.
RENDER_FIELDS = {"num_samples_coarse", "num_samples_fine", "resample_padding", "lindisp"}


def to_float16(ilm):
    """The ILM with every floating parameter rounded to float16 (and back to float32)."""
    import jax
    import jax.numpy as jnp

    params = jax.tree.map(lambda x: x.astype(jnp.float16).astype(x.dtype)
                          if jnp.issubdtype(x.dtype, jnp.floating) else x, ilm.fields.params)
    return ilm.replace(fields=ilm.fields.replace(params=params))


def float16_bytes(ilm, tmp: Path) -> int:
    """Bytes of the .npz with the network parameters stored as float16 (save_ilm)."""
    from vrs_jax.nerf import ilm as ilm_lib

    ilm_lib.save_ilm(tmp, ilm, float16=True)
    n = ilm_lib.map_bytes(tmp)
    tmp.unlink()
    return n


def real_gray(scene, i: int) -> np.ndarray:
    """Grey reference image [H, W] as the EGM build reads it (background composite, luma)."""
    from vrs_jax.data.images import read_gray

    return read_gray(scene.image_paths[i], size=tuple(int(s) for s in scene.sizes[i]),
                     background=scene.background)


def make_evaluator(lcfg, features):
    """Jitted per-view comparison: (map, i, gray) -> metric arrays of view i."""
    import jax
    import jax.numpy as jnp

    from vrs_jax import geometry
    from vrs_jax.features.descriptor import describe
    from vrs_jax.features.matching import match, pairwise_distances
    from vrs_jax.features.patches import extract_patches
    from vrs_jax.features.rays import keypoint_depths
    from vrs_jax.localize.render import render_reference
    from vrs_jax.nerf.model import render_rays, select_field

    def one(m, i, gray):
        egm, ilm = m.egm, m.ilm
        mask = egm.kp_mask[i]
        # the field's surface at each keypoint's centre ray against its 3D point's depth
        z = keypoint_depths(egm.points3d, egm.point_idx[i], egm.R[i], egm.t[i])
        o, d = geometry.pixel_rays(egm.K[i], egm.R[i], egm.t[i], egm.keypoints[i][:, :2],
                                   egm.dist[i])
        ones = jnp.ones(z.shape)
        rend_z = render_rays(select_field(ilm.fields, ilm.image_cluster[i]), o, d,
                             ones * geometry.cone_radius(egm.K[i], 1.0), ones * ilm.near[i],
                             ones * ilm.far[i], None, ilm.config)["depth"]
        rend = render_reference(m, i, features.patches, lcfg)  # [K, P, P]
        real = extract_patches(gray, egm.keypoints[i], features.patches)  # [K, P, P]
        d_rend = describe(rend, features.descriptor)
        d_real = describe(real, features.descriptor)
        se = jnp.mean((rend - real) ** 2, axis=(1, 2))  # [K] per-patch MSE
        dist = pairwise_distances(d_rend, d_real)
        dist = jnp.where(mask[None, :], dist, jnp.inf)
        own = jnp.argmin(dist, axis=1) == jnp.arange(mask.shape[0])
        j, valid, _ = match(d_rend, mask, d_real, mask, lcfg.ratio, lcfg.mutual)
        correct = valid & (j == jnp.arange(mask.shape[0]))
        return {"se": se, "own": own & mask, "matches": jnp.sum(valid),
                "correct": jnp.sum(correct), "mask": mask, "d_real": d_real,
                "depth_ratio": rend_z / jnp.maximum(z, 1e-6), "depth": z,
                "linked": mask & (egm.point_idx[i] >= 0)}

    return jax.jit(one)


# Depth bins of the own-keypoint rate, in units of the scene's scale (module docstring).
DEPTH_BINS = (("near", 0.0, 1.0), ("mid", 1.0, 4.0), ("far", 4.0, np.inf))


def rate_by_depth(hit: np.ndarray, depth: np.ndarray, scale: float) -> dict[str, Any]:
    """Rate of a per-keypoint test per depth bin: hit [K] bool (e.g. own keypoint), depth [K]
    point depths (world), scale -> {bin: {"rate": float or None (empty bin), "keypoints":
    int}}."""
    d = np.asarray(depth, np.float64) / scale
    out = {}
    for name, lo, hi in DEPTH_BINS:
        s = (d >= lo) & (d < hi)
        out[name] = {"rate": float(np.mean(hit[s])) if s.any() else None,
                     "keypoints": int(s.sum())}
    return out


def evaluate(m, views: np.ndarray, lcfg, grays: dict, progress: bool) -> dict[str, Any]:
    """Fidelity metrics over the given reference views (see the module docstring)."""
    import jax
    from tqdm.auto import tqdm

    from vrs_jax import geometry
    from vrs_jax.eval.metrics import scene_scale

    egm = m.egm
    fn = make_evaluator(lcfg, m.config.features)
    se, own, n_kp, n_match, n_corr, desc_err = [], [], 0, 0, 0, 0.0
    ratio, depth, linked_depth = [], [], []
    t0 = time.perf_counter()
    for i in tqdm(views, desc="fidelity", unit="view", disable=not progress):
        out = jax.device_get(fn(m, int(i), grays[int(i)]))
        m_ = np.asarray(out["mask"], bool)
        se.append(out["se"][m_])
        own.append(out["own"][m_])
        linked = np.asarray(out["linked"], bool)
        ratio.append(out["depth_ratio"][linked])
        linked_depth.append(out["depth"][linked])
        depth.append(out["depth"][m_])
        n_kp += int(m_.sum())
        n_match += int(out["matches"])
        n_corr += int(out["correct"])
        if egm.local_desc is not None:  # our real descriptors == the map's (float16)
            ref = np.asarray(egm.local_desc[int(i)])[m_]
            desc_err = max(desc_err, float(np.max(np.abs(out["d_real"][m_] - ref)))
                           if m_.any() else 0.0)
    se_all = np.concatenate(se)
    own_all = np.concatenate(own)
    n_views = len(views)
    patch_psnr = -10 * np.log10(np.maximum(se_all, 1e-10))
    ratio_all = np.concatenate(ratio)
    scale = scene_scale(np.asarray(geometry.camera_center(np.asarray(egm.R), np.asarray(egm.t))))
    return {"patch_psnr_db": float(-10 * np.log10(max(se_all.mean(), 1e-10))),
            "patch_psnr_median_db": float(np.median(patch_psnr)),
            "own_keypoint_rate": float(own_all.mean()),
            "matches_per_view": n_match / n_views,
            "correct_matches_per_view": n_corr / n_views,
            "keypoints_per_view": n_kp / n_views,
            "views": int(n_views),
            "surface_depth_ratio_median": float(np.median(ratio_all)) if len(ratio_all)
            else float("nan"),
            "surface_in_window_rate": float(np.mean(np.abs(ratio_all - 1.0)
                                                    <= lcfg.depth_margin)) if len(ratio_all)
            else float("nan"),
            "own_keypoint_rate_by_depth": rate_by_depth(own_all, np.concatenate(depth), scale),
            "surface_in_window_rate_by_depth": rate_by_depth(
                np.abs(ratio_all - 1.0) <= lcfg.depth_margin, np.concatenate(linked_depth),
                scale),
            "scene_scale": scale,
            "real_desc_vs_baseline_max_abs": desc_err,
            "eval_s": time.perf_counter() - t0}


# ----------------------------------------------------------------------------- main


def run(args) -> dict[str, Any]:
    from benchmarks.common import environment, fmt, table, write_json
    from vrs_jax import localize, maps
    from vrs_jax.nerf import ilm as ilm_lib
    from vrs_jax.nerf.config import parse_overrides
    from vrs_jax.nerf.model import count_params

    log = print
    progress = not args.quiet
    work = Path(args.work) if args.work else Path(args.json).parent / "fidelity_work"
    work.mkdir(parents=True, exist_ok=True)
    overrides = parse_overrides(args.set)
    if args.map is not None:
        if args.set:
            raise VrsError("--set applies to a trained field, not to a --map")
        m = maps.load_map(args.map)
        src = m.source
        args.fmt = args.fmt or src.format
        args.root = args.root or src.root
        opts = dict(src.options)
        if args.query_every is None and "query_every" in opts:
            args.query_every = int(opts["query_every"])
        if args.downscale is None and "downscale" in opts:
            args.downscale = int(opts["downscale"])
        scene = load(args)
        st = maps.read_stats(args.map).get("ilm", {})
        train_info = {"steps": st.get("steps"), "steps_per_s": st.get("steps_per_s"),
                      "train_s": st.get("train_s"), "compile_s": None}
        args.steps = st.get("steps")
    else:
        if args.fmt is None or args.root is None or args.steps is None:
            raise VrsError("--format, --root and --steps are required without --map")
        scene = load(args)
        m, train_info = map_of(scene, args, overrides, work, progress, log)
    ncfg = m.config.nerf
    refs = scene.references()
    if tuple(refs.names) != tuple(m.names):
        raise VrsError("the map and the scene list different reference images", args.root)
    if not np.allclose(np.asarray(refs.K, np.float64), np.asarray(m.egm.K, np.float64),
                       rtol=1e-3):
        raise VrsError("the map's intrinsics are not the scene's (another --downscale?)",
                       args.root)
    lcfg = localize.get_config(m.config.name, source="render",
                               **common.localize_overrides(args.localize))
    render_over = parse_overrides(args.render)
    if set(render_over) - RENDER_FIELDS:
        raise VrsError(f"--render accepts only {', '.join(sorted(RENDER_FIELDS))}")
    ilm = m.ilm
    if render_over:
        ilm = ilm.replace(config=dataclasses.replace(ilm.config, **render_over))
        m = m.replace(ilm=ilm)

    tmp = work / ".fidelity_ilm.npz"
    ilm_lib.save_ilm(tmp, ilm)
    bytes32 = ilm_lib.map_bytes(tmp)
    tmp.unlink()
    bytes16 = float16_bytes(ilm, tmp)

    n = len(refs)
    views = (np.arange(n) if args.views is None or args.views >= n
             else np.unique(np.round(np.linspace(0, n - 1, args.views)).astype(int)))
    grays = {int(i): real_gray(refs, int(i)) for i in views}
    res32 = evaluate(m, views, lcfg, grays, progress)
    res16 = None if args.no_fp16 else evaluate(m.replace(ilm=to_float16(ilm)), views, lcfg,
                                               grays, progress)
    extra = args.set + args.localize + args.render
    label = args.label or (", ".join(extra) if extra else ncfg.name)
    row = {"label": label, "overrides": overrides, "params": count_params(ilm.fields.params),
           "ilm_bytes": bytes32, "ilm_bytes_float16": bytes16, **train_info,
           "float32": res32, "float16": res16}
    headers = ["field", "params", "MB", "evals/patch", "PSNR dB", "med dB", "own %",
               "own % near/mid/far", "match", "correct", "surface in window %", "steps/s",
               "train s"]
    rows = [[label, row["params"], f"{bytes32 / 1e6:.3f}", f"{evals_per_patch(m, lcfg):.0f}",
             f"{res32['patch_psnr_db']:.2f}",
             f"{res32['patch_psnr_median_db']:.2f}", f"{100 * res32['own_keypoint_rate']:.1f}",
             depth_cell(res32), f"{res32['matches_per_view']:.1f}",
             f"{res32['correct_matches_per_view']:.1f}",
             f"{100 * res32['surface_in_window_rate']:.1f}",
             fmt(train_info["steps_per_s"], 1), fmt(train_info["train_s"], 0)]]
    if res16 is not None:
        rows.append([label + " (fp16)", row["params"], f"{bytes16 / 1e6:.3f}", "",
                     f"{res16['patch_psnr_db']:.2f}", f"{res16['patch_psnr_median_db']:.2f}",
                     f"{100 * res16['own_keypoint_rate']:.1f}", depth_cell(res16),
                     f"{res16['matches_per_view']:.1f}",
                     f"{res16['correct_matches_per_view']:.1f}",
                     f"{100 * res16['surface_in_window_rate']:.1f}", "", ""])
    print(table(headers, rows, title=f"patch fidelity at {len(views)} reference views of "
                                     f"{Path(scene.root).name}, {args.steps} steps"))
    doc = {"benchmark": "fidelity", "argv": vars(args), "environment": environment(),
           "render_overrides": render_over,
           "scene": {"root": str(scene.root), "format": args.fmt, "references": n,
                     "queries": int(scene.is_query.sum())},
           "map_config": m.config.name, "nerf_config": ncfg.to_dict(),
           "localize": {"patch_size": m.config.features.patches.size, "ratio": lcfg.ratio,
                        "mutual": lcfg.mutual, "depth_guided": lcfg.depth_guided,
                        "narrow_samples": lcfg.narrow_samples,
                        "narrow_fine": lcfg.narrow_fine, "depth_margin": lcfg.depth_margin,
                        "render_grid": lcfg.render_grid, "probe_grid": lcfg.probe_grid,
                        "nerf_evals_per_patch": evals_per_patch(m, lcfg)},
           "result": row}
    write_json(args.json, doc)
    log(f"wrote {args.json}")
    return doc


def depth_cell(res: dict[str, Any]) -> str:
    """'near/mid/far' own-keypoint rates (%) of an evaluate() result; '-' for an empty bin."""
    by = res["own_keypoint_rate_by_depth"]
    return "/".join("-" if by[b]["rate"] is None else f"{100 * by[b]['rate']:.0f}"
                    for b, _, _ in DEPTH_BINS)


def evals_per_patch(m, lcfg) -> float:
    """NeRF evaluations per rendered keypoint patch with the localize config's sampler."""
    from vrs_jax.localize.render import nerf_evals_per_ray, rays_per_patch

    return nerf_evals_per_ray(m, lcfg) * rays_per_patch(m, lcfg)


@cli_main
def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    common.check_outputs(args, [args.json])
    run(args)


if __name__ == "__main__":
    raise SystemExit(main())
