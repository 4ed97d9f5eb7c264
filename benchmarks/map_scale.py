"""Map bytes measured along a scale series (``python -m benchmarks.map_size --series ...``).

The series is the synthetic scene with 1, 4, 16, 64, ... rooms in a row (the generator's
``n_rooms``; every room 5 m wide with its own camera loop of ``--series-refs`` reference
images), plus real scenes (``--series-real``: the phone walk). Each scene's EGM is built
(``maps.build_map(..., train_nerf=False)``, the map config of ``--config``) and measured on
disk: the VRS map (map.json + egm.npz + ilm.npz) against descriptor maps of the same EGM with
one 128-D descriptor per kept keypoint at uint8 and float16 (counted as
:func:`benchmarks.map_size.descriptor_maps` counts them).

NeRF bytes: a scene whose NeRF is not trained gets an ILM of the map's config at its initial
parameters (:func:`vrs_jax.nerf.ilm.untrained`), saved with the map by the real
:func:`vrs_jax.maps.save_map` (float16 weights), labelled "untrained, same bytes": ``ilm.npz``
is stored uncompressed, so its bytes depend on the config, the cluster count and the image
names only. ``--series-train ROOMS`` trains that scene's NeRF for real and checks that its
``ilm.npz`` has exactly the untrained one's bytes.

Cluster counts (:func:`cluster_counts`): 1; one per :data:`IMAGES_PER_CLUSTER` images (the
paper's density on Aachen: 4,328 images in 16 clusters); and one per room (the clusters
benchmark's division of the rooms scene; 16 images per NeRF here, far denser than the paper).

The chess / Aachen figures are a FIT (:func:`fit_egm`): EGM bytes = c + a * images + b *
kept keypoints (c: the vocabulary and the npz container; a per image: pose, intrinsics,
global descriptor; b per kept keypoint: position, scale, angle, point link and its share of
the 3D points), each slope fitted on the measured parts it counts, its error reported on each
measured total and on the largest one when fitted without it.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import common
from vrs_jax import maps
from vrs_jax.data import synthetic
from vrs_jax.errors import VrsError
from vrs_jax.maps import map as map_io
from vrs_jax.nerf import ilm as ilm_lib

# The series' synthetic scene: the default room at low resolution, few images per room, so
# that 64 rooms give 1,024 reference images and build on 2 cores in minutes.
SERIES_ROOMS = (1, 4, 16, 64)
SERIES_SIZE = (160, 120)
SERIES_REFS_PER_ROOM = 16  # one loop of a 5 m room (the default room has 60): ~22 deg apart
SERIES_QUERIES_PER_ROOM = 1  # unused by the EGM; the reader wants a query split
# Textures at 96 texels/m (1 cm): at 160x120 a pixel spans 1.5 cm at 2 m. 64 rooms make a
# 320 m floor, and cv2.remap reads textures of at most 32,767 texels a side (128/m, the
# rooms4 scene's, would be 40,960).
SERIES_TEXELS_PER_M = 96.0
# One ray per pixel (the default 2x2): the texture lookups stay mip-mapped (trilinear), only
# the geometric edges alias; it makes the 64-room scene 4x faster to render (~1 s a frame on
# 2 busy cores at 2x2: 1,088 frames would take ~35 minutes).
SERIES_SUPERSAMPLE = 1
# Real scenes of the series: the phone walk (302 frames, every 10th a query).
REAL_SERIES = {
    "phone_walk": common.SceneSpec("phone_walk", "nerf", ("phone_walk",),
                                   (("query_every", 10),), None,
                                   "phone walk, 302 frames, every 10th a query"),
}
# The paper's cluster density: Aachen's 4,328 reference images in 16 NeRF clusters.
IMAGES_PER_CLUSTER = 270
# Large scenes of the fit: (reference images, NeRF clusters of the paper).
LARGE = {"7scenes chess": (4000, 1), "aachen": (4328, 16)}


def series_config(rooms: int, size: tuple[int, int] = SERIES_SIZE,
                  refs: int = SERIES_REFS_PER_ROOM, queries: int = SERIES_QUERIES_PER_ROOM
                  ) -> synthetic.SyntheticConfig:
    """The synthetic scene of ``rooms`` rooms (5 m each) at ``size`` (W, H) with ``refs``
    reference and ``queries`` query images per room."""
    return dataclasses.replace(synthetic.get_config("default"), width=size[0], height=size[1],
                               n_reference=refs, n_query=queries,
                               texels_per_m=SERIES_TEXELS_PER_M,
                               supersample=SERIES_SUPERSAMPLE, n_rooms=rooms)


def cluster_counts(n_images: int, rooms: int | None) -> dict[str, int]:
    """NeRF cluster counts measured for a scene: ``one`` (1), ``paper`` (one per
    :data:`IMAGES_PER_CLUSTER` images, at least 1) and ``per_room`` (``rooms``; absent for a
    real scene)."""
    out = {"one": 1, "paper": max(1, round(n_images / IMAGES_PER_CLUSTER))}
    if rooms is not None:
        out["per_room"] = rooms
    return out


def untrained_map_dir(m: maps.Map, cfg: maps.MapConfig, n_clusters: int, out: Path,
                      provenance: dict) -> Path:
    """Save the VRS map of ``m``'s EGM with an untrained ILM of ``cfg.nerf`` at
    ``n_clusters`` clusters into ``out`` (map.json + egm.npz + ilm.npz, by
    :func:`vrs_jax.maps.save_map`). Its map.json records 0 training steps, so
    ``maps.load_map`` refuses it: it exists to be measured."""
    ncfg = dataclasses.replace(cfg.nerf, n_clusters=n_clusters)
    egm = m.egm.without_local_descriptors()
    ilm = ilm_lib.untrained(ncfg, egm.names, camera_centers(egm))
    vm = maps.Map(egm=egm, ilm=ilm, config=dataclasses.replace(cfg, nerf=ncfg), source=m.source)
    return maps.save_map(vm, out, {"ilm": {"steps": 0, "untrained": True}},
                         provenance=provenance)


def camera_centers(egm) -> np.ndarray:
    """[N, 3] world camera centres of the EGM's reference images (-R^T t)."""
    R, t = np.asarray(egm.R, np.float64), np.asarray(egm.t, np.float64)
    return -np.einsum("nji,nj->ni", R, t)


def file_sizes(folder: Path) -> dict[str, int]:
    """Bytes on disk of the VRS map files of a folder (map.json, egm.npz, ilm.npz)."""
    return {n: (folder / n).stat().st_size for n in (map_io.META, map_io.EGM_FILE,
                                                      map_io.ILM_FILE)
            if (folder / n).is_file()}


# ----------------------------------------------------------------------------- measurement


@dataclasses.dataclass(frozen=True)
class SeriesScene:
    """One point of the series: a name, its dataset and where its EGM map is (or goes)."""

    name: str
    rooms: int | None  # None: a real scene
    scene: Any  # vrs_jax.data.scene.Scene (None for a given EGM folder)
    egm_dir: Path
    given: bool  # the EGM folder was given (--series-egm): read only, never built into
    source_options: dict[str, Any]


def measure(s: SeriesScene, cfg: maps.MapConfig, work: Path, train: bool,
            progress: bool = False, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Build (or reuse) the EGM of ``s`` (and its NeRF when ``train``), then measure its VRS
    maps at every cluster count of :func:`cluster_counts` and its descriptor maps.

    Returns the scene's row: counts (images, 3D points, kept keypoints), ``egm_parts``
    (egm.npz by part), ``descriptor_maps`` (uint8, float16, float32 bytes), ``vrs`` (one entry
    per cluster policy: clusters, folder, bytes by file, total, ratios; ``trained`` False:
    an untrained ILM of the same bytes), ``trained`` (the trained map's bytes and the check
    that its ilm.npz has the untrained one's bytes) when trained, ``build_s``.
    """
    from benchmarks.map_size import descriptor_maps

    t0 = time.perf_counter()
    if not s.given:
        maps.build_map(s.scene, s.egm_dir, cfg, progress=progress, train_nerf=train,
                       source_options=s.source_options, log=lambda x: log(f"[{s.name}] {x}"))
    build_s = time.perf_counter() - t0
    m = maps.load_map(s.egm_dir, require_ilm=False)
    if m.config.egm != cfg.egm:
        raise VrsError(f"the EGM of {s.name} was built with other EGM settings than config "
                       f"{cfg.name!r}", s.egm_dir)
    b = maps.map_bytes(s.egm_dir)
    egm = m.egm
    n_img, n_pts = egm.num_images, egm.num_points
    n_kp = int(np.asarray(egm.kp_mask).sum())
    dim = m.config.features.descriptor.dim
    desc = descriptor_maps(b, n_kp, dim)
    prov = map_io.read_meta(s.egm_dir).get("provenance") or {}
    vrs = {}
    for policy, c in cluster_counts(n_img, s.rooms).items():
        folder = work / "series" / s.name / f"vrs-c{c}"
        if not any(v["clusters"] == c for v in vrs.values()):
            untrained_map_dir(m, cfg, c, folder, prov)
        sizes = file_sizes(folder)
        total = sum(sizes.values())
        vrs[policy] = {"clusters": c, "folder": str(folder), "files": sizes,
                       "metadata": sizes[map_io.META], "egm": sizes[map_io.EGM_FILE],
                       "ilm": sizes[map_io.ILM_FILE], "total": total, "trained": False,
                       "ratio_uint8": desc["uint8"] / total,
                       "ratio_float16": desc["float16"] / total}
    row = {"scene": s.name, "rooms": s.rooms, "egm_dir": str(s.egm_dir), "images": n_img,
           "points": n_pts, "kept_keypoints": n_kp, "desc_dim": dim,
           "keypoints_per_image": n_kp / n_img, "egm": b["egm"], "metadata": b["metadata"],
           "egm_parts": b["egm_parts"], "descriptor_maps": desc, "vrs": vrs,
           "build_s": None if s.given else build_s,
           "image_size": [int(x) for x in np.asarray(egm.sizes)[0]]}
    if b["ilm"]:  # a trained NeRF in the EGM folder (config cfg, one cluster)
        one = vrs["one"]
        if m.config.nerf != cfg.nerf:
            raise VrsError(f"the NeRF of {s.name} was trained with another config", s.egm_dir)
        row["trained"] = {"folder": str(s.egm_dir), "metadata": b["metadata"],
                          "egm": b["egm"], "ilm": b["ilm"], "total": b["vrs"],
                          "untrained_ilm": one["ilm"],
                          "ilm_bytes_equal": b["ilm"] == one["ilm"],
                          "egm_bytes_equal": b["egm"] == one["egm"],
                          "steps": (maps.read_stats(s.egm_dir).get("ilm") or {}).get("steps"),
                          "ratio_uint8": desc["uint8"] / b["vrs"],
                          "ratio_float16": desc["float16"] / b["vrs"]}
    return row


# ----------------------------------------------------------------------------- the fit


# egm.npz parts (vrs_jax.egm.map.PARTS) by what their size grows with.
PER_IMAGE_PARTS = ("poses+intrinsics", "global descriptors")
PER_KEYPOINT_PARTS = ("keypoints", "links", "points3d")


def _line(x: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """(intercept, slope) of y ~ c + s x, least squares on residuals relative to y."""
    X = np.stack([np.ones_like(x), x], axis=1) / y[:, None]
    (c, slope), *_ = np.linalg.lstsq(X, np.ones_like(y), rcond=None)
    return float(c), float(slope)


def _fit_parts(rows: list[dict[str, Any]]) -> np.ndarray:
    """[c, a, b] of egm.npz = c + a * images + b * kept keypoints, a and b each fitted on the
    parts that grow with them (images and kept keypoints grow together along the series, so
    a fit of the total alone cannot tell them apart); c: their intercepts plus the mean of the
    rest (the npz container)."""
    n = np.array([r["images"] for r in rows], np.float64)
    k = np.array([r["kept_keypoints"] for r in rows], np.float64)
    part = lambda names: np.array([sum(r["egm_parts"].get(p, 0) for p in names)  # noqa: E731
                                   for r in rows], np.float64)
    ci, a = _line(n, part(PER_IMAGE_PARTS))
    ck, b = _line(k, part(PER_KEYPOINT_PARTS))
    rest = np.array([r["egm"] for r in rows], np.float64) - part(PER_IMAGE_PARTS) - part(
        PER_KEYPOINT_PARTS)
    return np.array([ci + ck + float(rest.mean()), a, b])


def fit_egm(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """egm.npz bytes = c + a * images + b * kept keypoints (:func:`_fit_parts`: a on the
    per-image parts, b on the per-keypoint parts, c the vocabulary and the npz container),
    fitted on the measured ``rows`` (at least 3; each with ``egm`` and ``egm_parts``).
    Returns c, a (bytes per image), b (bytes per kept keypoint), ``errors`` (fit of the total
    / measured total - 1 per row, in order), ``max_abs_error`` and ``holdout`` (the largest
    row predicted by the fit of the others: its error; None with fewer than 4 rows)."""
    if len(rows) < 3:
        raise VrsError("the fit needs at least 3 measured scenes")

    def err(coef, r):
        return float((coef @ [1.0, r["images"], r["kept_keypoints"]]) / r["egm"] - 1.0)

    coef = _fit_parts(rows)
    errors = [err(coef, r) for r in rows]
    holdout = None
    if len(rows) >= 4:
        big = max(range(len(rows)), key=lambda i: rows[i]["images"])
        c2 = _fit_parts([r for i, r in enumerate(rows) if i != big])
        holdout = {"scene": rows[big]["scene"], "c": float(c2[0]), "a": float(c2[1]),
                   "b": float(c2[2]), "error": err(c2, rows[big])}
    return {"c_bytes": float(coef[0]), "a_bytes_per_image": float(coef[1]),
            "b_bytes_per_keypoint": float(coef[2]),
            "scenes": [r["scene"] for r in rows], "errors": errors,
            "max_abs_error": float(max(abs(e) for e in errors)), "holdout": holdout}


def cluster_bytes(rows: list[dict[str, Any]]) -> float:
    """Measured ilm.npz bytes per extra NeRF cluster: the slope between the fewest and the
    most clusters of the scene with the most (untrained ILMs, same bytes)."""
    best = max(rows, key=lambda r: max(v["clusters"] for v in r["vrs"].values()))
    vs = sorted(best["vrs"].values(), key=lambda v: v["clusters"])
    lo, hi = vs[0], vs[-1]
    if hi["clusters"] == lo["clusters"]:
        return float(lo["ilm"])
    return (hi["ilm"] - lo["ilm"]) / (hi["clusters"] - lo["clusters"])


def fit_rows(fit: dict[str, Any], rows: list[dict[str, Any]], cfg: maps.MapConfig
             ) -> list[dict[str, Any]]:
    """The large scenes (:data:`LARGE`) from the fit, labelled ``fit``: with the measured
    config (kept keypoints per image: the series' pooled mean; the NeRF's measured bytes per
    cluster) and with the ``paper`` config (1,024 kept keypoints per image, its global
    descriptor width costed at the measured bytes per global dimension, its NeRF's float16
    weights counted from its parameter shapes)."""
    from benchmarks.map_size import nerf_weight_bytes

    a, b = fit["a_bytes_per_image"], fit["b_bytes_per_keypoint"]
    kpi = sum(r["kept_keypoints"] for r in rows) / sum(r["images"] for r in rows)
    g_cpu = global_dim(cfg)
    per_dim = float(np.median([r["egm_parts"].get("global descriptors", 0)
                               / (r["images"] * g_cpu) for r in rows]))
    pcfg = maps.get_config("paper")
    paper_nerf = next(x for x in nerf_weight_bytes() if x["config"] == "paper")
    per_cluster = cluster_bytes(rows)
    one_cluster = float(np.median([r["vrs"]["one"]["ilm"] for r in rows]))
    dim = rows[0]["desc_dim"]
    out = []
    for name, (n, c) in LARGE.items():
        for which, k, a_img, nerf in (
                (cfg.name, kpi, a, one_cluster + (c - 1) * per_cluster),
                ("paper", pcfg.egm.k_max, a + (global_dim(pcfg) - g_cpu) * per_dim,
                 c * paper_nerf["bytes_per_cluster"])):
            n_kp = n * k
            egm = fit["c_bytes"] + a_img * n + b * n_kp
            vrs = egm + nerf
            r = {"scene": name, "label": "fit", "config": which, "images": n, "clusters": c,
                 "keypoints_per_image": float(k), "egm": egm, "nerf": nerf, "vrs": vrs,
                 "descriptors_uint8": egm + n_kp * dim, "descriptors_float16": egm + n_kp * dim * 2}
            r["ratio_uint8"] = r["descriptors_uint8"] / vrs
            r["ratio_float16"] = r["descriptors_float16"] / vrs
            out.append(r)
    return out


def global_dim(cfg: maps.MapConfig) -> int:
    """Dimension of the map config's global descriptor (VLAD words x local dim, or PCA)."""
    r = cfg.egm.retrieval
    return int(r.pca_dim if r.pca_dim is not None else r.n_words * cfg.features.descriptor.dim)


# ----------------------------------------------------------------------------- CLI


def add_args(p) -> None:
    """The series arguments of ``benchmarks.map_size``."""
    from vrs_jax.cli.make_synthetic import _size

    p.add_argument("--series", default=None, metavar="ROOMS",
                   help="measure the scale series instead of the scenes: comma-separated "
                        "room counts of the synthetic scene (e.g. "
                        f"{','.join(map(str, SERIES_ROOMS))}), plus --series-real")
    p.add_argument("--series-size", type=_size, default=SERIES_SIZE, metavar="WxH",
                   help=f"image size of the series' synthetic scenes (default "
                        f"{SERIES_SIZE[0]}x{SERIES_SIZE[1]})")
    p.add_argument("--series-refs", type=int, default=SERIES_REFS_PER_ROOM, metavar="N",
                   help=f"reference images per room (default {SERIES_REFS_PER_ROOM})")
    p.add_argument("--series-queries", type=int, default=SERIES_QUERIES_PER_ROOM, metavar="N",
                   help=f"query images per room (default {SERIES_QUERIES_PER_ROOM})")
    p.add_argument("--series-real", default=",".join(REAL_SERIES),
                   help=f"real scenes of the series among {', '.join(REAL_SERIES)} (comma-"
                        "separated, '' for none; skipped when the data is absent)")
    p.add_argument("--series-egm", action="append", default=[], metavar="NAME=DIR",
                   help="use an EGM map folder built elsewhere for a real series scene "
                        "(read only), e.g. phone_walk=../main/outputs/walk/egm10")
    p.add_argument("--series-train", default="", metavar="ROOMS",
                   help="room counts whose NeRF is trained for real (the map config's steps; "
                        "checks that the trained ilm.npz has the untrained one's bytes)")
    p.add_argument("--plot", default=None, metavar="FILE.png",
                   help="figure of map bytes against reference images (log-log)")


def _ints(text: str) -> list[int]:
    try:
        out = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise VrsError(f"expected comma-separated integers, got {text!r}") from None
    if any(x < 1 for x in out):
        raise VrsError(f"room counts must be >= 1, got {text!r}")
    return out


def series_scenes(args, log: Callable[[str], None] = print) -> list[SeriesScene]:
    """The scenes of the series: the synthetic rooms (generated into WORK/series/roomsN/scene)
    and the real scenes whose data or EGM folder is there."""
    from vrs_jax.data.readers import load_scene

    work = Path(args.work) / "series"
    out = []
    for r in _ints(args.series):
        cfg = series_config(r, tuple(args.series_size), args.series_refs, args.series_queries)
        root = synthetic.generate(work / f"rooms{r}" / "scene", cfg, progress=not args.quiet)
        out.append(SeriesScene(f"rooms{r}", r, load_scene("7scenes", root),
                               work / f"rooms{r}" / "egm", False, {}))
    given = {}
    for item in args.series_egm:
        name, sep, path = item.partition("=")
        if not sep or name not in REAL_SERIES:
            raise VrsError(f"--series-egm expects NAME=DIR with NAME in "
                           f"{', '.join(REAL_SERIES)}, got {item!r}")
        given[name] = Path(path)
    for name in [x.strip() for x in args.series_real.split(",") if x.strip()]:
        if name not in REAL_SERIES:
            raise VrsError(f"unknown real series scene {name!r}; choose from "
                           f"{', '.join(REAL_SERIES)}")
        spec = REAL_SERIES[name]
        opts = spec.reader_options
        if name in given:  # measured as it is: the dataset is not read
            out.append(SeriesScene(name, None, None, given[name], True, opts))
            continue
        root = Path(args.data_root) if args.data_root else common.default_data_root()
        root = root.joinpath(*spec.parts)
        if not root.exists():
            log(f"[{name}] skipped: data not found at {root}")
            continue
        out.append(SeriesScene(name, None, load_scene(spec.fmt, root, **opts),
                               work / name / "egm", False, opts))
    return out


def run(args, doc: dict[str, Any]) -> dict[str, Any]:
    """Measure the series, print its tables, fill ``doc`` (written by the caller), draw the
    figure with ``--plot``."""
    cfg = maps.get_config(args.config, **({"max_steps": args.nerf_steps}
                                          if args.nerf_steps else {}))
    train = set(_ints(args.series_train)) if args.series_train else set()
    rows = []
    for s in series_scenes(args):
        rows.append(measure(s, cfg, Path(args.work), train=s.rooms in train,
                            progress=not args.quiet))
        r = rows[-1]
        print(f"[{s.name}] {r['images']} images, {r['kept_keypoints']} kept keypoints, "
              f"EGM {r['egm'] / 1e6:.3f} MB" + (f" (built in {r['build_s']:.0f} s)"
                                                 if r["build_s"] else ""))
    if not rows:
        raise VrsError("the series has no scene")
    synth = [r for r in rows if r["rooms"] is not None]
    fit = fit_egm(synth) if len(synth) >= 3 else None
    large = fit_rows(fit, synth, cfg) if fit else []
    print()
    print(tables(rows, fit, large, cfg))
    doc.update({"series": {"config": cfg.name, "rows": rows, "fit": fit, "large": large,
                           "images_per_cluster": IMAGES_PER_CLUSTER,
                           "synthetic": {"size": list(args.series_size),
                                         "refs_per_room": args.series_refs,
                                         "queries_per_room": args.series_queries,
                                         "texels_per_m": SERIES_TEXELS_PER_M,
                                         "supersample": SERIES_SUPERSAMPLE}}})
    if args.plot:
        p = plot(rows, large, Path(args.plot))
        print(f"wrote {p}")
    return doc


def tables(rows: list[dict], fit: dict | None, large: list[dict], cfg) -> str:
    """The series' tables: map bytes per scene and cluster count, the EGM by part, the fit."""
    mb = lambda x: common.fmt(x / 1e6, 3)  # noqa: E731
    body = []
    for r in rows:
        d = r["descriptor_maps"]
        seen = set()
        for policy, v in r["vrs"].items():
            if v["clusters"] in seen:
                continue
            seen.add(v["clusters"])
            body.append([r["scene"], r["images"], r["points"], r["kept_keypoints"],
                         f"{v['clusters']} ({policy})", mb(v["metadata"]), mb(v["egm"]),
                         mb(v["ilm"]) + "*", mb(v["total"]), mb(d["uint8"]), mb(d["float16"]),
                         f"{v['ratio_uint8']:.2f}x", f"{v['ratio_float16']:.2f}x"])
        t = r.get("trained")
        if t:
            body.append([r["scene"] + " trained", r["images"], r["points"], r["kept_keypoints"],
                         "1", mb(t["metadata"]), mb(t["egm"]), mb(t["ilm"]), mb(t["total"]),
                         mb(d["uint8"]), mb(d["float16"]), f"{t['ratio_uint8']:.2f}x",
                         f"{t['ratio_float16']:.2f}x"])
    out = [common.table(
        ["scene", "images", "3D points", "kept keypoints", "NeRF clusters", "map.json (MB)",
         "egm.npz", "ilm.npz", "VRS map", "desc. uint8", "desc. float16", "uint8 / VRS",
         "float16 / VRS"], body,
        title=f"Map bytes measured along the series (config {cfg.name}; MB = 1e6 bytes; "
              "* untrained NeRF, same bytes as trained)")]
    for r in rows:
        t = r.get("trained")
        if t:
            out.append(f"{r['scene']}: trained ilm.npz {t['ilm']:,} B ({t['steps']} steps), "
                       f"untrained {t['untrained_ilm']:,} B: "
                       + ("equal" if t["ilm_bytes_equal"] else "DIFFERENT"))
    parts = ["poses+intrinsics", "global descriptors", "keypoints", "links", "points3d",
             "container"]
    out.append("")
    out.append(common.table(
        ["scene"] + [f"{p} (kB)" for p in parts] + ["egm.npz (kB)", "B / kept keypoint"],
        [[r["scene"]] + [common.fmt(r["egm_parts"].get(p, 0) / 1e3, 1) for p in parts]
         + [common.fmt(r["egm"] / 1e3, 1), f"{r['egm'] / max(r['kept_keypoints'], 1):.2f}"]
         for r in rows], title="egm.npz by part"))
    if fit:
        out.append("")
        errs = ", ".join(f"{s} {100 * e:+.1f}%" for s, e in zip(fit["scenes"], fit["errors"],
                                                                strict=True))
        ho = fit["holdout"]
        out.append(f"fit on the synthetic series: egm.npz = {fit['c_bytes']:,.0f} B + "
                   f"{fit['a_bytes_per_image']:,.0f} B x images + "
                   f"{fit['b_bytes_per_keypoint']:.2f} B x kept keypoints; error "
                   f"on the measured points: {errs}" + (
                       f"; {ho['scene']} predicted from the others: {100 * ho['error']:+.1f}%"
                       if ho else ""))
        out.append(common.table(
            ["scene (FIT, not measured)", "config", "images", "clusters", "kp / image",
             "VRS (GB)", "uint8 (GB)", "float16 (GB)", "uint8 / VRS", "float16 / VRS"],
            [[r["scene"], r["config"], r["images"], r["clusters"],
              common.fmt(r["keypoints_per_image"], 0), common.fmt(r["vrs"] / 1e9, 4),
              common.fmt(r["descriptors_uint8"] / 1e9, 3),
              common.fmt(r["descriptors_float16"] / 1e9, 3), f"{r['ratio_uint8']:.1f}x",
              f"{r['ratio_float16']:.1f}x"] for r in large],
            title="Large scenes from the fit (the paper reports chess: SFD2+IMP 4.0 GB, "
                  "VRS-NeRF 1.0 GB)"))
    return "\n".join(out)


def plot(rows: list[dict], large: list[dict], path: Path) -> Path:
    """Map bytes against reference images, log-log: the VRS map at each cluster policy, the
    uint8 and float16 descriptor maps; the real scenes as squares, the trained map as a star,
    the fit's large scenes as crosses."""
    from benchmarks.figures import plt, save

    synth = sorted((r for r in rows if r["rooms"] is not None), key=lambda r: r["images"])
    real = [r for r in rows if r["rooms"] is None]
    fig, ax = plt.subplots(figsize=(7.5, 5.2))
    series = [("VRS, 1 NeRF", "C0", "-", lambda r: r["vrs"]["one"]["total"]),
              (f"VRS, 1 NeRF / {IMAGES_PER_CLUSTER} images", "C1", "-.",
               lambda r: r["vrs"]["paper"]["total"]),
              ("VRS, 1 NeRF / room", "C4", ":",
               lambda r: r["vrs"].get("per_room", {}).get("total")),
              ("descriptors uint8 (COLMAP)", "C2", "--",
               lambda r: r["descriptor_maps"]["uint8"]),
              ("descriptors float16 (hloc)", "C3", "--",
               lambda r: r["descriptor_maps"]["float16"])]
    for label, color, ls, get in series:
        pts = [(r["images"], get(r)) for r in synth if get(r)]
        if pts:
            x, y = zip(*pts, strict=True)
            ax.plot(x, y, ls, marker="o", color=color, label=label)
        pts = [(r["images"], get(r)) for r in real if get(r)]
        if pts:
            x, y = zip(*pts, strict=True)
            ax.plot(x, y, "s", color=color, markerfacecolor="none", markersize=9)
    for r in rows:
        if r.get("trained"):
            ax.plot(r["images"], r["trained"]["total"], "*", color="k", markersize=13,
                    label=f"VRS, trained NeRF ({r['scene']})")
    for r in large:
        if r["config"] == "paper":
            continue
        ax.plot(r["images"], r["vrs"], "x", color="C0" if r["clusters"] == 1 else "C1",
                markersize=9)
        ax.plot(r["images"], r["descriptors_float16"], "x", color="C3", markersize=9)
        ax.plot(r["images"], r["descriptors_uint8"], "x", color="C2", markersize=9)
        ax.annotate(f"{r['scene']} (fit)", (r["images"], r["descriptors_float16"]),
                    textcoords="offset points", fontsize=8, ha="right",
                    xytext=(-6, 8 if r["clusters"] == 1 else -14))
    if real:
        ax.plot([], [], "s", color="gray", markerfacecolor="none",
                label="real: " + ", ".join(r["scene"] for r in real))
    ax.plot([], [], "x", color="gray", label="fit (not measured)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("reference images")
    ax.set_ylabel("map bytes on disk")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_title("Map size along the scale series (measured)")
    fig.tight_layout()
    return save(fig, path)

