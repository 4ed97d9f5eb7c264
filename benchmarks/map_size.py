"""Map size benchmark: bytes on disk by part, the VRS map against descriptor maps stored the
way the field stores them, on the same scenes, plus an extrapolation to large scenes.

    python -m benchmarks.map_size [--scenes synthetic,fern,lego,scan24] [--json FILE]

The VRS map is what render-mode localization loads: ``map.json`` + ``egm.npz`` (3D points,
keypoints and their point links, poses and intrinsics, global descriptors with the
vocabulary; quantised, see :mod:`vrs_jax.egm.map`) + ``ilm.npz`` (the NeRF weights,
float16). A descriptor map (the hierarchical method) is the same EGM plus one local
descriptor per kept keypoint and no NeRF; it is reported with 128-D descriptors at one byte
per dimension (COLMAP stores SIFT as uint8), at float16 (hloc stores its features so; this is
our real-patch map's descriptors.npz) and at float32.

The scaling table extrapolates the measured bytes per reference image (poses, intrinsics),
per global-descriptor dimension, per kept keypoint and per 3D point (with the measured points
per keypoint), and per NeRF cluster, to 7Scenes chess (4,000 reference images, one cluster)
and Aachen (4,328 images, 16 clusters) with the `paper` configuration (1,024 keypoints kept
per image, 2048-D global descriptors, its NeRF); point indices are costed at the width the
extrapolated point count needs (3 bytes there, 2 on the benchmark scenes). Beside the paper's
own table.
"""

from __future__ import annotations

import argparse

import jax
import numpy as np

from benchmarks import common
from vrs_jax import maps
from vrs_jax.egm import map as egm_map
from vrs_jax.errors import cli_main
from vrs_jax.maps import map as map_io
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
    """Bytes of the VRS map and of descriptor maps (uint8, float16, float32) of one scene,
    with the unit costs the extrapolation scales (see :func:`unit_costs`)."""
    b = maps.map_bytes(ctx.map_dir)
    egm = ctx.m.egm
    n_img, n_pts = egm.num_images, egm.num_points
    n_kp = int(np.asarray(egm.kp_mask).sum())
    dim = ctx.m.config.features.descriptor.dim
    base = b["metadata"] + b["egm"]
    desc = {"uint8": base + n_kp * dim, "float16": b["real"], "float32": base + n_kp * dim * 4}
    parts = b["egm_parts"]
    return {"vrs": b["vrs"], "egm": b["egm"], "ilm": b["ilm"], "metadata": b["metadata"],
            "descriptor_maps": desc, "egm_parts": parts,
            "ratio": {k: v / b["vrs"] for k, v in desc.items()},
            "n_images": n_img, "n_keypoints": n_kp, "n_points": n_pts, "desc_dim": dim,
            "global_dim": int(egm.global_desc.shape[1]),
            **unit_costs(parts, n_img, n_kp, n_pts, int(egm.global_desc.shape[1]))}


def unit_costs(parts: dict[str, int], n_img: int, n_kp: int, n_pts: int, g_dim: int) -> dict:
    """Measured bytes of egm.npz per unit: ``bytes_per_image`` (poses, intrinsics, size),
    ``global_bytes_per_dim`` (global descriptor bytes per image and dimension, vocabulary
    included), ``bytes_per_keypoint`` (position, scale, angle, count), ``bytes_per_point``
    (3D points), ``points_per_keypoint`` (points / kept keypoints). The point links are
    costed at the extrapolated scale (:func:`link_bytes`), not measured: their width grows
    with the number of points."""
    return {"bytes_per_image": parts.get("poses+intrinsics", 0) / n_img,
            "global_bytes_per_dim": parts.get("global descriptors", 0) / (n_img * g_dim),
            "bytes_per_keypoint": parts.get("keypoints", 0) / max(n_kp, 1),
            "link_bytes_measured": parts.get("links", 0) / max(n_kp, 1),
            "bytes_per_point": parts.get("points3d", 0) / max(n_pts, 1),
            "points_per_keypoint": n_pts / max(n_kp, 1)}


def link_bytes(n_points: int) -> int:
    """Bytes of one stored point index among ``n_points`` (the EGM stores the fewest that
    fit, uncompressed here: indices of a large map do not deflate)."""
    return int(egm_map.pack_indices(np.zeros(1, np.int64), max(n_points, 1)).shape[1])


def nerf_weight_bytes() -> list[dict]:
    """Parameters and stored bytes of one cluster's field for every named NeRF config (float16
    when the map stores its weights so, :data:`vrs_jax.maps.map.NERF_FLOAT16`)."""
    per = 2 if map_io.NERF_FLOAT16 else 4
    out = []
    for name, cfg in nerf_config.CONFIGS.items():
        shapes = jax.eval_shape(lambda cfg=cfg: init_params(jax.random.key(0), cfg))
        n = count_params(shapes)
        out.append({"config": name, "params": int(n), "bytes_per_cluster": int(per * n)})
    return out


def extrapolate(unit: dict[str, float], cluster_bytes: int, k: int, dim: int, g_dim: int
                ) -> list[dict]:
    """VRS and descriptor-map bytes of the large scenes from the measured unit costs
    (:func:`unit_costs`, medians over the scenes), ``k`` keypoints kept per image, ``g_dim``-D
    global descriptors and ``dim``-D local descriptors."""
    rows = []
    for name, (n, c) in LARGE.items():
        n_kp = n * k
        n_pts = int(round(n_kp * unit["points_per_keypoint"]))
        per_kp = (unit["bytes_per_keypoint"] + link_bytes(n_pts)
                  + unit["points_per_keypoint"] * unit["bytes_per_point"])
        per_img = unit["bytes_per_image"] + g_dim * unit["global_bytes_per_dim"]
        egm = n * per_img + n_kp * per_kp
        vrs = egm + c * cluster_bytes
        row = {"scene": name, "images": n, "clusters": c, "keypoints_per_image": k,
               "points": n_pts, "link_bytes": link_bytes(n_pts), "bytes_per_keypoint": per_kp,
               "bytes_per_image": per_img, "egm": egm, "nerf": c * cluster_bytes, "vrs": vrs}
        for fmt_, nbytes in (("uint8", 1), ("float16", 2), ("float32", 4)):
            row[f"descriptors_{fmt_}"] = egm + n_kp * dim * nbytes
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
        keys = ("bytes_per_image", "global_bytes_per_dim", "bytes_per_keypoint",
                "bytes_per_point", "points_per_keypoint")
        unit = {k: float(np.median([r[k] for r in results.values()])) for k in keys}
        dim = next(iter(results.values()))["desc_dim"]
        pcfg = maps.get_config("paper")
        k = pcfg.egm.k_max
        g_dim = pcfg.egm.retrieval.n_words * dim
        if pcfg.egm.retrieval.pca_dim is not None:
            g_dim = pcfg.egm.retrieval.pca_dim
        scaling = extrapolate(unit, paper["bytes_per_cluster"], k, dim, g_dim)
        print(f"measured (median over the scenes): {unit['bytes_per_image']:,.0f} B per image "
              f"(poses, intrinsics) + {unit['global_bytes_per_dim']:.2f} B per global "
              f"descriptor dimension ({g_dim}-D in the paper config); "
              f"{unit['bytes_per_keypoint']:.2f} B per kept keypoint (position, scale, angle) "
              f"+ its point index; {unit['bytes_per_point']:.2f} B per 3D point, "
              f"{unit['points_per_keypoint']:.3f} points per kept keypoint; paper NeRF "
              f"{paper['bytes_per_cluster']:,} B per cluster")
        print(common.table(
            ["scene (extrapolated)", "images", "clusters", "B / keypoint", "VRS (GB)",
             "uint8 (GB)", "float16 (GB)", "uint8 / VRS", "float16 / VRS"],
            [[r["scene"], r["images"], r["clusters"], f"{r['bytes_per_keypoint']:.2f}",
              common.fmt(r["vrs"] / 1e9, 4), common.fmt(r["descriptors_uint8"] / 1e9, 3),
              common.fmt(r["descriptors_float16"] / 1e9, 3), f"{r['ratio_uint8']:.1f}x",
              f"{r['ratio_float16']:.1f}x"] for r in scaling],
            title=f"Extrapolation with the paper configuration ({k:,} keypoints per image); "
                  "the paper reports chess: SFD2+IMP 4.0 GB, VRS-NeRF 1.0 GB (4x)"))
        print()
    print(common.table(["NeRF config", "params", "MB per cluster"],
                       [[r["config"], common.fmt(r["params"]), mb(r["bytes_per_cluster"])]
                        for r in nerf],
                       title="NeRF weights per cluster by config (as stored: "
                             f"{'float16' if map_io.NERF_FLOAT16 else 'float32'})"))
    for s in skipped:
        print(f"skipped {s['scene']}: {s['reason']}")
    doc.update({"maps": infos, "sizes": results, "nerf_configs": nerf, "scaling": scaling,
                "paper_chess_bytes": PAPER_CHESS, "skipped": skipped})
    out = common.write_json(common.json_path(args, "map_size"), doc)
    print(f"\nwrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
