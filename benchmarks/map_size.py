"""Map size benchmark: bytes on disk by part, VRS map vs baseline map, on the same scenes.

    python -m benchmarks.map_size [--scenes synthetic,fern,lego] [--json FILE] [--work DIR]

The VRS map is what render-mode localization loads: the EGM without local descriptors
(3D points, keypoints and their point links, poses and intrinsics, global descriptors with
the vocabulary, clusters, metadata, zip container) plus the NeRF weights (ilm.npz). The
baseline map (the hierarchical method, gt mode) is the same EGM plus the local descriptors
of every kept keypoint, and no NeRF. Sizes are the files on disk (uncompressed npz), as
``vrs_jax.pipeline.map_size`` measures them; the ratio is baseline / VRS. A second table
gives the NeRF weight bytes per cluster of every NeRF config (computed from the parameter
count, float32), since the trained configs here are the small CPU ones.

Defaults: all three scenes (lego with every 8th view a query, fern every 5th); the maps are
built once into --work with the cpu-small config (~13 minutes on 2 cores including NeRF
training, shared with the other benchmarks) and the measurement itself takes seconds.
"""

from __future__ import annotations

import argparse

import jax

from benchmarks import common
from vrs_jax import pipeline
from vrs_jax.egm.map import PART_NAMES
from vrs_jax.errors import cli_main
from vrs_jax.nerf import config as nerf_config
from vrs_jax.nerf.model import count_params, init_params

NERF = "NeRF weights"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.map_size", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_scene_args(p, default_scenes=("synthetic", "fern", "lego"))
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/map_size.json)")
    return p


def sizes_of(map_dir) -> dict:
    """{vrs: {part: bytes, total}, baseline: {...}, ratio} of a map folder."""
    ms = pipeline.map_size(map_dir)
    vrs = {k: int(ms["egm_parts"][k]) for k in PART_NAMES}
    vrs[NERF] = int(ms["ilm"])
    vrs["total"] = int(ms["total"])
    base = {k: int(ms["baseline_parts"][k]) for k in PART_NAMES}
    base[NERF] = 0
    base["total"] = int(ms["baseline_total"])
    return {"vrs": vrs, "baseline": base, "ratio_baseline_over_vrs": base["total"] / vrs["total"],
            "vrs_egm_only": int(ms["egm"])}


def nerf_weight_bytes() -> list[dict]:
    """Parameters and float32 bytes of one cluster's MLP for every named NeRF config."""
    out = []
    for name, cfg in nerf_config.CONFIGS.items():
        shapes = jax.eval_shape(lambda cfg=cfg: init_params(jax.random.key(0), cfg))
        n = count_params(shapes)
        out.append({"config": name, "params": int(n), "bytes_per_cluster": int(4 * n),
                    "samples_per_ray": cfg.num_samples_coarse + cfg.num_samples_fine})
    return out


def size_table(results: dict) -> str:
    names = list(results)
    headers = ["part (MB)"]
    for n in names:
        headers += [f"{n} VRS", f"{n} baseline"]
    rows = []
    for part in (*PART_NAMES, NERF, "total"):
        r = [part]
        for n in names:
            r += [common.fmt(results[n]["vrs"][part] / 1e6, 3),
                  common.fmt(results[n]["baseline"][part] / 1e6, 3)]
        rows.append(r)
    rows.append(["baseline / VRS"] + sum(
        (["", f"{results[n]['ratio_baseline_over_vrs']:.2f}x"] for n in names), []))
    return common.table(headers, rows, title="Map size on disk (MB = 1e6 bytes)")


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    doc = common.base_doc("map_size", args, argv)
    ctxs, skipped = common.prepare_scenes(args)
    results, maps = {}, {}
    for ctx in ctxs:
        maps[ctx.name] = common.map_info(ctx)
        results[ctx.name] = sizes_of(ctx.map_dir)
    nerf = nerf_weight_bytes()
    print()
    if results:
        print(size_table(results))
        print()
    print(common.table(["NeRF config", "params", "MB per cluster", "samples/ray"],
                       [[r["config"], common.fmt(r["params"]),
                         common.fmt(r["bytes_per_cluster"] / 1e6, 3), r["samples_per_ray"]]
                        for r in nerf],
                       title="NeRF weights per cluster by config (float32)"))
    for s in skipped:
        print(f"skipped {s['scene']}: {s['reason']}")
    doc.update({"maps": maps, "sizes": results, "nerf_configs": nerf, "skipped": skipped})
    out = common.write_json(common.json_path(args, "map_size"), doc)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
