"""Map size benchmark: bytes on disk by part, the VRS map against descriptor maps stored the
way the field stores them, on the same scenes; with --series, measured along a scale series.

    python -m benchmarks.map_size [--scenes synthetic,fern,lego,scan24] [--json FILE]

The VRS map is what render-mode localization loads: ``map.json`` + ``egm.npz`` (3D points,
keypoints and their point links, poses and intrinsics, global descriptors with the
vocabulary; quantised, see :mod:`vrs_jax.egm.map`) + ``ilm.npz`` (the NeRF weights,
float16; the hash tables int8, one scale per level). A descriptor map (the hierarchical
method) is the same EGM plus one local descriptor per kept keypoint and no NeRF; it is
reported with 128-D descriptors at one byte per dimension (COLMAP stores SIFT as uint8), at
float16 (hloc stores its features so; this is our real-patch map's descriptors.npz) and at
float32.

``--series ROOMS`` measures instead the scale series (:mod:`benchmarks.map_scale`): the
synthetic scene with 1, 4, 16, 64 rooms (hundreds to a thousand images) and the phone walk,
their EGMs built and every map measured on disk; 7Scenes chess and Aachen only as a fit of
the measured points, its error reported.

    python -m benchmarks.map_size --series 1,4,16,64 [--series-train 1] [--plot FILE.png]
        [--json FILE]
"""

from __future__ import annotations

import argparse
from typing import Any

import jax
import numpy as np

from benchmarks import common, map_scale
from vrs_jax import maps
from vrs_jax.errors import cli_main
from vrs_jax.maps import map as map_io
from vrs_jax.nerf import config as nerf_config
from vrs_jax.nerf import ilm as ilm_lib
from vrs_jax.nerf.model import count_params, init_params

# The paper's table (chess): SFD2+IMP 4.0 GB, VRS-NeRF 1.0 GB.
PAPER_CHESS = {"descriptor map (SFD2+IMP)": 4.0e9, "VRS-NeRF": 1.0e9}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.map_size", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_scene_args(p, default_scenes=("synthetic", "fern", "lego", "scan24"))
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/map_size.json)")
    map_scale.add_args(p)
    common.add_overwrite_arg(p)
    return p


def sizes_of(ctx: common.SceneCtx) -> dict:
    """Bytes of the VRS map and of descriptor maps (uint8, float16, float32) of one scene."""
    b = maps.map_bytes(ctx.map_dir)
    egm = ctx.m.egm
    n_img, n_pts = egm.num_images, egm.num_points
    n_kp = int(np.asarray(egm.kp_mask).sum())
    dim = ctx.m.config.features.descriptor.dim
    desc = descriptor_maps(b, n_kp, dim)
    parts = b["egm_parts"]
    return {"vrs": b["vrs"], "egm": b["egm"], "ilm": b["ilm"], "metadata": b["metadata"],
            "descriptor_maps": desc, "egm_parts": parts,
            "ratio": {k: v / b["vrs"] for k, v in desc.items()},
            "n_images": n_img, "n_keypoints": n_kp, "n_points": n_pts, "desc_dim": dim,
            "global_dim": int(egm.global_desc.shape[1])}


def descriptor_maps(b: dict[str, Any], n_kp: int, dim: int) -> dict[str, int]:
    """Bytes of the descriptor map of a map folder (``b``: :func:`vrs_jax.maps.map_bytes`):
    its map.json and egm.npz plus one ``dim``-D descriptor per kept keypoint (``n_kp``), at
    ``uint8`` (as COLMAP stores SIFT: counted), ``float16`` (as hloc stores them: the
    folder's real-patch descriptors.npz, measured) and ``float32`` (counted)."""
    base = b["metadata"] + b["egm"]
    return {"uint8": base + n_kp * dim, "float16": b["real"], "float32": base + n_kp * dim * 4}


def nerf_weight_bytes() -> list[dict]:
    """Parameters and stored bytes of one cluster's field for every named NeRF config, as a
    map stores them (float16 weights, int8 hash tables: :data:`vrs_jax.maps.map.NERF_FLOAT16`,
    :data:`~vrs_jax.maps.map.NERF_HASH_INT8`)."""
    out = []
    for name, cfg in nerf_config.CONFIGS.items():
        shapes = jax.eval_shape(lambda cfg=cfg: init_params(jax.random.key(0), cfg))
        n = count_params(shapes)
        stored = ilm_lib.stored_param_bytes(cfg, map_io.NERF_FLOAT16, map_io.NERF_HASH_INT8)
        out.append({"config": name, "params": int(n), "bytes_per_cluster": stored})
    return out


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    common.check_outputs(args, [common.json_path(args, "map_size_series" if args.series
                                                 else "map_size"), args.plot])
    doc = common.base_doc("map_size", args, argv)
    if args.series:
        map_scale.run(args, doc)
        out = common.write_json(common.json_path(args, "map_size_series"), doc)
        print(f"\nwrote {out}")
        return 0
    ctxs, skipped = common.prepare_scenes(args)
    results, infos = {}, {}
    for ctx in ctxs:
        infos[ctx.name] = common.map_info(ctx)
        results[ctx.name] = sizes_of(ctx)
    nerf = nerf_weight_bytes()
    mb = lambda x: common.fmt(x / 1e6, 3)  # noqa: E731
    print()
    if results:
        print(common.table(
            ["scene", "VRS map (MB)", "EGM", "NeRF", "desc. uint8 (COLMAP)", "float16 (hloc)",
             "float32", "uint8 / VRS", "float16 / VRS"],
            [[n, mb(r["vrs"]), mb(r["egm"]), mb(r["ilm"]), mb(r["descriptor_maps"]["uint8"]),
              mb(r["descriptor_maps"]["float16"]), mb(r["descriptor_maps"]["float32"]),
              f"{r['ratio']['uint8']:.2f}x", f"{r['ratio']['float16']:.2f}x"]
             for n, r in results.items()],
            title="Map size on disk (MB = 1e6 bytes)"))
        print()
    print(common.table(["NeRF config", "params", "MB per cluster"],
                       [[r["config"], common.fmt(r["params"]), mb(r["bytes_per_cluster"])]
                        for r in nerf],
                       title="NeRF weights per cluster by config (as stored: "
                             f"{'float16' if map_io.NERF_FLOAT16 else 'float32'}"
                             f"{', hash tables int8' if map_io.NERF_HASH_INT8 else ''})"))
    for s in skipped:
        print(f"skipped {s['scene']}: {s['reason']}")
    print("\nlarge scenes: measured along a scale series by --series (benchmarks.map_scale)")
    doc.update({"maps": infos, "sizes": results, "nerf_configs": nerf,
                "paper_chess_bytes": PAPER_CHESS, "skipped": skipped})
    out = common.write_json(common.json_path(args, "map_size"), doc)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
