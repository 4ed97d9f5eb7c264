"""Map size benchmark: bytes on disk by part, the VRS map against descriptor maps stored the
way the field stores them, on the same scenes, plus an extrapolation to large scenes.

    python -m benchmarks.map_size [--scenes synthetic,fern,lego,scan24] [--json FILE]

The VRS map is what render-mode localization loads: ``map.json`` + ``egm.npz`` (3D points,
keypoints and their point links, poses and intrinsics, global descriptors with the
vocabulary) + ``ilm.npz`` (the NeRF weights). A descriptor map (the hierarchical method) is
the same EGM plus one local descriptor per kept keypoint and no NeRF; it is reported with
128-D descriptors at one byte per dimension (COLMAP stores SIFT as uint8), at float16 (hloc
stores its features so; this is our real-patch map's descriptors.npz) and at float32. The
scaling table extrapolates the measured bytes per reference image, per kept keypoint and per
NeRF cluster to 7Scenes chess (4,000 reference images, one cluster) and Aachen (4,328
images, 16 clusters) with the `paper` configuration's 1,024 keypoints kept per image and its
NeRF, beside the paper's own table.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from benchmarks import common
from vrs_jax import maps
from vrs_jax.errors import cli_main
from vrs_jax.nerf import config as nerf_config
from vrs_jax.nerf.model import count_params, init_params

# Large scenes for the extrapolation: (reference images, NeRF clusters).
LARGE = {"7scenes chess": (4000, 1), "aachen": (4328, 16)}
# The paper's table (chess): SFD2+IMP 4.0 GB, VRS-NeRF 1.0 GB.
PAPER_CHESS = {"descriptor map (SFD2+IMP)": 4.0e9, "VRS-NeRF": 1.0e9}


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.map_size", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_scene_args(p, default_scenes=("synthetic", "fern", "lego", "scan24"))
    p.add_argument("--json", default=None,
                   help=f"output JSON (default {common.DEFAULT_JSON_DIR}/map_size.json)")
    return p


def sizes_of(ctx: common.SceneCtx) -> dict:
    """Bytes of the VRS map and of descriptor maps (uint8, float16, float32) of one scene."""
    b = maps.map_bytes(ctx.map_dir)
    n_img = ctx.m.egm.num_images
    n_kp = int(np.asarray(ctx.m.egm.kp_mask).sum())
    dim = ctx.m.config.features.descriptor.dim
    base = b["metadata"] + b["egm"]
    desc = {"uint8": base + n_kp * dim, "float16": b["real"], "float32": base + n_kp * dim * 4}
    parts = b["egm_parts"]
    return {"vrs": b["vrs"], "egm": b["egm"], "ilm": b["ilm"], "metadata": b["metadata"],
            "descriptor_maps": desc, "egm_parts": parts,
            "ratio": {k: v / b["vrs"] for k, v in desc.items()},
            "n_images": n_img, "n_keypoints": n_kp, "desc_dim": dim,
            "bytes_per_image": (parts.get("poses+intrinsics", 0)
                                + parts.get("global descriptors", 0)) / n_img,
            "bytes_per_keypoint": (parts.get("keypoints+links", 0)
                                   + parts.get("points3d", 0)) / max(n_kp, 1)}


def nerf_weight_bytes() -> list[dict]:
    """Parameters and float32 bytes of one cluster's field for every named NeRF config."""
    out = []
    for name, cfg in nerf_config.CONFIGS.items():
        shapes = jax.eval_shape(lambda cfg=cfg: init_params(jax.random.key(0), cfg))
        n = count_params(shapes)
        out.append({"config": name, "params": int(n), "bytes_per_cluster": int(4 * n)})
    return out


def extrapolate(per_image: float, per_kp: float, cluster_bytes: int, k: int, dim: int
                ) -> list[dict]:
    """VRS and descriptor-map bytes of the large scenes from measured unit costs."""
    rows = []
    for name, (n, c) in LARGE.items():
        egm = n * (per_image + k * per_kp)
        vrs = egm + c * cluster_bytes
        row = {"scene": name, "images": n, "clusters": c, "keypoints_per_image": k,
               "vrs": vrs}
        for fmt_, nbytes in (("uint8", 1), ("float16", 2), ("float32", 4)):
            row[f"descriptors_{fmt_}"] = egm + n * k * dim * nbytes
            row[f"ratio_{fmt_}"] = row[f"descriptors_{fmt_}"] / vrs
        rows.append(row)
    return rows


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    doc = common.base_doc("map_size", args, argv)
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
    paper = next(r for r in nerf if r["config"] == "paper")
    scaling = []
    if results:
        per_image = float(np.median([r["bytes_per_image"] for r in results.values()]))
        per_kp = float(np.median([r["bytes_per_keypoint"] for r in results.values()]))
        dim = next(iter(results.values()))["desc_dim"]
        k = maps.get_config("paper").egm.k_max
        scaling = extrapolate(per_image, per_kp, paper["bytes_per_cluster"], k, dim)
        print(f"measured: {per_image:,.0f} B per reference image, {per_kp:,.1f} B per kept "
              f"keypoint (median over the scenes); paper NeRF {paper['bytes_per_cluster']:,} B "
              "per cluster")
        print(common.table(
            ["scene (extrapolated)", "images", "clusters", "VRS (GB)", "uint8 (GB)",
             "float16 (GB)", "uint8 / VRS", "float16 / VRS"],
            [[r["scene"], r["images"], r["clusters"], common.fmt(r["vrs"] / 1e9, 3),
              common.fmt(r["descriptors_uint8"] / 1e9, 3),
              common.fmt(r["descriptors_float16"] / 1e9, 3), f"{r['ratio_uint8']:.1f}x",
              f"{r['ratio_float16']:.1f}x"] for r in scaling],
            title="Extrapolation with the paper configuration (1,024 keypoints per image); "
                  "the paper reports chess: SFD2+IMP 4.0 GB, VRS-NeRF 1.0 GB (4x)"))
        print()
    print(common.table(["NeRF config", "params", "MB per cluster"],
                       [[r["config"], common.fmt(r["params"]), mb(r["bytes_per_cluster"])]
                        for r in nerf], title="NeRF weights per cluster by config (float32)"))
    for s in skipped:
        print(f"skipped {s['scene']}: {s['reason']}")
    doc.update({"maps": infos, "sizes": results, "nerf_configs": nerf, "scaling": scaling,
                "paper_chess_bytes": PAPER_CHESS, "skipped": skipped})
    out = common.write_json(common.json_path(args, "map_size"), doc)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
