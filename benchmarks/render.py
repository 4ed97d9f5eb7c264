"""Rendering benchmark: the cost of sparse patches vs full images, and of the samplers.

    python -m benchmarks.render [--scenes synthetic] [--sizes 9 11 13 15 31] [--json FILE]

Two measurements per scene, on a real query (--query, default the first) and the reference
images it retrieves (top-k of the map's config):

1. Query vs full images (the paper's "2.7x fewer rays" claim, measured): the rays of the
   patches of the top-k images' 3D-linked keypoints (k x valid keypoints x P^2, the map's P)
   against all pixels of the same k images; then the wall time of rendering them: the
   patches with the depth-guided sampler (one pass of a few samples in a narrow interval
   around each keypoint's 3D point), the patches with coarse + fine sampling, the
   paper-literal axis-aligned patches (overlapping pixels rendered once; depth-guided), and
   the k full images (coarse + fine, as NeRF renders images).
2. Patch-size sweep: for every P and both samplers, the patches of --sweep-keypoints
   keypoints of the top-1 image are rendered: ms per patch, rays/s, NeRF (MLP) evaluations
   per ray and per second, and per query (k images x all their keypoints): rays, NeRF
   evaluations and the render time this implies.

Every timing is the median of up to --repeats calls (fewer once they add up to 2 s) of a
function compiled ahead of time (no compilation inside the timings). Defaults: the synthetic
scene only (the map is built once into --work, shared with the other benchmarks), all five
patch sizes, both samplers, 64 sweep keypoints: about 2-3 minutes on 2 CPU cores once the
map exists.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from benchmarks import common
from vrs_jax.data.images import read_gray
from vrs_jax.errors import VrsError, cli_main
from vrs_jax.features import rays as rays_mod
from vrs_jax.features.patches import PATCH_SIZES, patch_grid
from vrs_jax.localize import prepare_query, run_stages
from vrs_jax.localize.render import nerf_evals_per_ray, rays_per_query, render_reference
from vrs_jax.nerf.render import image_renderer


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.render", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_scene_args(p, default_scenes=("synthetic",))
    p.add_argument("--sizes", type=int, nargs="+", default=list(PATCH_SIZES),
                   help="patch sizes P of the sweep")
    p.add_argument("--samplers", default="dg,full",
                   help="samplers of the sweep: dg (depth-guided) and/or full (coarse+fine)")
    p.add_argument("--sweep-keypoints", type=int, default=64,
                   help="patches (keypoints of the top-1 image) rendered per sweep timing")
    p.add_argument("--query", type=int, default=0, help="index of the query image used")
    p.add_argument("--repeats", type=int, default=3,
                   help="timed calls per measurement (fewer once they add up to 2 s)")
    p.add_argument("--no-full-images", action="store_true",
                   help="skip timing the full-image renders (still counts their rays)")
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/render.json)")
    common.add_overwrite_arg(p)
    return p


def patch_renderer(cfg, patches):
    """Jitted ``fn(map, idx) -> grey patches [k, K_max, P, P]`` (the localize render stage)."""
    def fn(m, idx):
        return jax.lax.map(lambda i: render_reference(m, i, patches, cfg), idx)
    return jax.jit(fn)


def truncate_keypoints(m, n: int):
    """The map with only the first n keypoint slots of every image (valid ones come first)."""
    egm = m.egm
    return m.replace(egm=egm.replace(keypoints=egm.keypoints[:, :n],
                                     point_idx=egm.point_idx[:, :n],
                                     kp_mask=egm.kp_mask[:, :n], local_desc=None))


def literal_pixels(egm, idx: np.ndarray, patches) -> int:
    """Distinct whole pixels of the paper-literal patches of images ``idx`` (rays needed)."""
    lit = dataclasses.replace(patches, mode="literal")
    total = 0
    for i in idx:
        pos, _ = patch_grid(jnp.asarray(egm.keypoints[i]), lit)
        _, _, count = rays_mod.unique_literal_pixels(pos, jnp.asarray(egm.kp_mask[i]))
        total += int(count)
    return total


def time_full_images(m, idx: np.ndarray, repeats: int) -> tuple[float, float]:
    """Seconds to render the full reference images ``idx`` (coarse + fine), compile seconds.

    One compilation per image size serves every image of that size.
    """
    egm, ilm = m.egm, m.ilm
    total, compile_total = 0.0, 0.0
    compiled: dict[tuple, object] = {}
    f32 = lambda a: jnp.asarray(np.asarray(a, np.float32))  # noqa: E731
    for i in idx:
        w, h = (int(s) for s in np.asarray(egm.sizes[i]))
        dist = np.asarray(egm.dist[i])
        use_dist = bool(np.any(dist))
        args = (ilm.fields, jnp.int32(int(ilm.image_cluster[i])), f32(egm.K[i]), f32(egm.R[i]),
                f32(egm.t[i]), f32(dist), jnp.float32(ilm.near[i]), jnp.float32(ilm.far[i]))
        key = (w, h, use_dist)
        if key not in compiled:
            fn = image_renderer(ilm.config, w, h, use_dist)
            t0 = time.perf_counter()
            compiled[key] = fn.lower(*args).compile()
            compile_total += time.perf_counter() - t0
        sec, _ = common.time_calls(compiled[key], *args, repeats=repeats)
        total += sec
    return total, compile_total


def query_comparison(ctx, q, idx: np.ndarray, args) -> dict:
    """Measurement 1: a query's patches vs the same k reference images in full."""
    m = ctx.m.without_descriptors()
    egm = m.egm
    cfg = common.localize_cfg(ctx, "render")
    patches = common.patch_config(ctx)
    literal = dataclasses.replace(patches, mode="literal")
    P = patches.size
    valid = np.asarray(egm.kp_mask)[idx].sum(1)
    sizes = np.asarray(egm.sizes)[idx]
    pixels = int(np.prod(sizes, axis=1).sum())
    patch_rays = int(valid.sum()) * P * P
    lit_rays = literal_pixels(egm, idx, patches)
    full_epr = nerf_evals_per_ray(m, dataclasses.replace(cfg, depth_guided=False))
    variants = [
        ("patches, depth-guided", dataclasses.replace(cfg, depth_guided=True), patches,
         patch_rays),
        ("patches, coarse+fine", dataclasses.replace(cfg, depth_guided=False), patches,
         patch_rays),
        ("literal patches (distinct pixels), depth-guided",
         dataclasses.replace(cfg, depth_guided=True), literal, lit_rays),
    ]
    idx_j = jnp.asarray(idx, jnp.int32)
    rows = []
    for label, c, pc, rays in variants:
        sec, comp, _ = common.compile_and_time(patch_renderer(c, pc), m, idx_j,
                                               repeats=args.repeats)
        epr = nerf_evals_per_ray(m, c)
        rows.append({"method": label, "rays": rays, "nerf_evals_per_ray": epr,
                     "nerf_evals": rays * epr, "seconds": sec, "compile_s": comp,
                     "depth_guided": c.depth_guided, "patch_mode": pc.mode})
    full = {"method": "full images, coarse+fine", "rays": pixels,
            "nerf_evals_per_ray": full_epr, "nerf_evals": pixels * full_epr,
            "seconds": None, "compile_s": None, "depth_guided": False, "patch_mode": None}
    if not args.no_full_images:
        full["seconds"], full["compile_s"] = time_full_images(m, idx, args.repeats)
    rows.append(full)
    for r in rows:
        r["full_over_this_rays"] = pixels / r["rays"] if r["rays"] else None
        r["full_over_this_time"] = (full["seconds"] / r["seconds"]
                                    if full["seconds"] and r["seconds"] else None)
    return {"patch_size": P, "top_k": len(idx), "retrieved": idx.tolist(),
            "retrieved_names": [egm.names[i] for i in idx],
            "valid_keypoints": valid.tolist(), "image_sizes": sizes.tolist(),
            "patch_rays": patch_rays, "full_image_pixels": pixels,
            "literal_distinct_pixels": lit_rays,
            "fewer_rays_factor": pixels / patch_rays if patch_rays else None, "rows": rows}


def sweep(ctx, idx: np.ndarray, args) -> list[dict]:
    """Measurement 2: ms per patch etc. for each P and sampler."""
    m = ctx.m.without_descriptors()
    sub = truncate_keypoints(m, args.sweep_keypoints)
    top1 = jnp.asarray(idx[:1], jnp.int32)
    n_patches = int(np.asarray(sub.egm.kp_mask)[idx[0]].sum())
    if n_patches == 0:
        raise VrsError("the top-1 reference image has no 3D-linked keypoints", ctx.map_dir)
    rows = []
    for P in args.sizes:
        for dg in [s == "dg" for s in samplers(args)]:
            cfg = common.localize_cfg(ctx, "render", P, depth_guided=dg)
            sec, comp, _ = common.compile_and_time(
                patch_renderer(cfg, common.patch_config(ctx, P)), sub, top1,
                repeats=args.repeats)
            epr = nerf_evals_per_ray(m, cfg)
            rays = n_patches * P * P
            rpq = rays_per_query(m, cfg)
            ms_patch = 1000.0 * sec / n_patches
            rows.append({
                "patch_size": P, "depth_guided": dg,
                "sampler": f"depth-guided {cfg.narrow_samples}+{cfg.narrow_fine}" if dg else
                           f"coarse+fine {m.config.nerf.num_samples_coarse}"
                           f"+{m.config.nerf.num_samples_fine}",
                "patches_timed": n_patches, "seconds": sec, "compile_s": comp,
                "ms_per_patch": ms_patch, "rays_per_s": rays / sec,
                "nerf_evals_per_ray": epr, "nerf_evals_per_s": rays * epr / sec,
                "rays_per_query": rpq, "nerf_evals_per_query": rpq * epr,
                "patches_per_query": rpq / (P * P),
                "est_render_s_per_query": ms_patch * rpq / (P * P) / 1000.0})
    return rows


def samplers(args) -> list[str]:
    out = [s.strip() for s in args.samplers.split(",") if s.strip()]
    if not out or any(s not in ("dg", "full") for s in out):
        raise VrsError(f"--samplers must list dg and/or full, got {args.samplers!r}")
    return out


def comparison_table(c: dict) -> str:
    return common.table(
        ["method", "rays", "full/this rays", "evals/ray", "NeRF evals (M)", "time (s)",
         "full/this time"],
        [[r["method"], common.fmt(r["rays"]), common.fmt(r["full_over_this_rays"]),
          r["nerf_evals_per_ray"], common.fmt(r["nerf_evals"] / 1e6),
          common.fmt(r["seconds"], 3), common.fmt(r["full_over_this_time"])]
         for r in c["rows"]],
        title=(f"One query's top-{c['top_k']} reference images: {c['patch_size']}x"
               f"{c['patch_size']} patches of {sum(c['valid_keypoints'])} keypoints vs "
               f"{c['full_image_pixels']:,} full-image pixels ({c['fewer_rays_factor']:.2f}x "
               "fewer rays)"))


def sweep_table(rows: list[dict]) -> str:
    return common.table(
        ["P", "sampler", "ms/patch", "rays/s", "evals/ray", "M evals/s", "rays/query",
         "M evals/query", "est. render s/query"],
        [[r["patch_size"], r["sampler"], common.fmt(r["ms_per_patch"], 3),
          common.fmt(r["rays_per_s"], 0), r["nerf_evals_per_ray"],
          common.fmt(r["nerf_evals_per_s"] / 1e6), common.fmt(r["rays_per_query"], 0),
          common.fmt(r["nerf_evals_per_query"] / 1e6), common.fmt(r["est_render_s_per_query"])]
         for r in rows],
        title="Patch-size sweep (timed on the top-1 image's first keypoints; per query = "
              "top-k images x all their keypoints)")


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    common.check_outputs(args, [common.json_path(args, "render")])
    bad = [s for s in args.sizes if s not in PATCH_SIZES]
    if bad:
        raise VrsError(f"--sizes must be among {PATCH_SIZES}, got {bad}")
    if args.sweep_keypoints < 1 or args.repeats < 1:
        raise VrsError("--sweep-keypoints and --repeats must be >= 1")
    samplers(args)
    doc = common.base_doc("render", args, argv)
    ctxs, skipped = common.prepare_scenes(args)
    scenes = {}
    for ctx in ctxs:
        queries = ctx.scene.queries()
        if not 0 <= args.query < len(queries):
            raise VrsError(f"--query {args.query} out of range: {len(queries)} queries",
                           ctx.scene.root)
        cfg = common.localize_cfg(ctx, "render")
        size = tuple(int(s) for s in queries.sizes[args.query])
        q = prepare_query(ctx.m, read_gray(queries.image_paths[args.query], size=size),
                          queries.K[args.query], queries.dist[args.query], cfg)
        idx = np.asarray(run_stages(ctx.m, q, cfg, until="retrieval")["idx"])
        print(f"[{ctx.name}] query {queries.names[args.query]}: top-{len(idx)} "
              f"{[ctx.m.egm.names[i] for i in idx]}")
        comp = query_comparison(ctx, q, idx, args)
        rows = sweep(ctx, idx, args)
        scenes[ctx.name] = {"map": common.map_info(ctx), "query": queries.names[args.query],
                            "localize_config": dataclasses.asdict(cfg),
                            "query_vs_full": comp, "sweep": rows}
        print()
        print(f"== {ctx.name}")
        print(comparison_table(comp))
        print()
        print(sweep_table(rows))
    for s in skipped:
        print(f"skipped {s['scene']}: {s['reason']}")
    doc.update({"scenes": scenes, "skipped": skipped})
    out = common.write_json(common.json_path(args, "render"), doc)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
