"""Figures (PNG, matplotlib Agg) for the README: rendering, matches, clusters, error curves.

    python -m benchmarks.figures [--out outputs/figures] [--scenes synthetic]
        [--cluster-scenes synthetic,lego] [--figures render,matches,clusters,curves,timing]
        [--localize-json outputs/benchmarks/localize.json]

- ``render_vs_real_SCENE.png``: reference images rendered by their cluster's NeRF next to
  the real images and their absolute difference (PSNR in the titles); the views are the
  top-k references retrieved for the match figure's query.
- ``matches_SCENE.png``: the paper's match figure. Left the query image; right the reference
  image it matched best, dimmed, with the NeRF-rendered patches of the inlier keypoints
  (--paste matched / all: of the matched / all keypoints) pasted at their keypoints (each
  warped to its canonical grid: position, scale, orientation, outlined in yellow); green
  lines join the PnP inliers, red ones the other matches, cyan rings mark the query keypoints
  that are inliers of the guided pass (the map points rendered from the first pose and
  matched near their projections); below, pairs of query patch and rendered patch for up to
  12 inliers. Made by running localize's stages one by one
  (retrieve, render_candidate, describe, match_candidates, lift, estimate_pose).
  ``matches_SCENE_real.png`` is the same for the baseline (real mode: the real reference
  patches, read from the reference image).
- ``clusters_SCENE.png``: scene division of the reference cameras (top view: the two
  principal axes of the camera centres) into C clusters, a uniform grid vs K-means
  (vrs_jax.nerf.clusters, with the border images each K-means cluster shares ringed).
- ``cumulative_errors.png``: per scene of a ``benchmarks.localize`` run (--localize-json),
  the fraction of queries under a translation error (percent of the scene's scale) and a
  rotation error, for render (VRS-NeRF), real (baseline) and the COLMAP SIFT reference.
- ``timing.png``: from the same run, the median seconds of each stage per query, stacked,
  per scene and method.

Also writes OUT/figures.json (what each figure shows: PSNRs, inlier counts, cluster sizes).
Defaults: the synthetic scene (its map built once into --work, shared with the other
benchmarks) and clusters of synthetic and lego (camera poses only, no map needed); curves
and timing need ``benchmarks.localize``'s JSON first. About a minute on 2 CPU cores once
the maps exist.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import cv2  # noqa: E402
import jax  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from benchmarks import common  # noqa: E402
from vrs_jax import fileio, geometry  # noqa: E402
from vrs_jax.data.images import luma, read_gray, read_image  # noqa: E402
from vrs_jax.errors import VrsError, cli_main  # noqa: E402
from vrs_jax.eval import metrics  # noqa: E402
from vrs_jax.features.patches import extract_patches, patch_grid  # noqa: E402
from vrs_jax.localize import prepare_query, run_stages  # noqa: E402
from vrs_jax.nerf import clusters as clusters_lib  # noqa: E402
from vrs_jax.nerf import config as nerf_config  # noqa: E402
from vrs_jax.nerf.render import psnr, render_view  # noqa: E402

FIGURES = ("render", "matches", "clusters", "curves", "timing")
DPI = 120


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m benchmarks.figures", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    common.add_scene_args(p, default_scenes=("synthetic",))
    p.add_argument("--out", default="outputs/figures", help="folder of the PNGs")
    common.add_overwrite_arg(p)
    p.add_argument("--figures", default=",".join(FIGURES),
                   help=f"comma-separated figures to make among {', '.join(FIGURES)}")
    p.add_argument("--cluster-scenes", default="synthetic,lego",
                   help="scenes of the cluster figure (camera poses only; absent data skipped)")
    p.add_argument("--clusters", type=int, default=4, help="clusters C of the cluster figure")
    p.add_argument("--query", type=int, default=0,
                   help="query (index among the queries used) of the match figure")
    p.add_argument("--match-modes", default="render,real",
                   help="match figures to make: render (VRS-NeRF) and/or real (baseline)")
    p.add_argument("--paste", default="inliers", choices=["inliers", "matched", "all"],
                   help="patches pasted on the reference image in the match figure (the "
                        "matched ones when there are no inliers)")
    p.add_argument("--views", type=int, default=2,
                   help="reference images in the render figure (the query's top ones)")
    p.add_argument("--localize-json", default=f"{common.DEFAULT_JSON_DIR}/localize.json",
                   help="output of benchmarks.localize that the curves and timing figures draw")
    p.add_argument("--max-pct", type=float, default=5.0,
                   help="x range of the translation curves, percent of the scene scale")
    p.add_argument("--max-deg", type=float, default=5.0, help="x range of the R-error curve")
    return p


def save(fig, path: Path) -> Path:
    """Write ``fig`` as PNG to ``path`` atomically (vrs_jax.fileio.write_atomic)."""
    fileio.write_atomic(path, lambda f: fig.savefig(f, format="png", dpi=DPI,
                                                    bbox_inches="tight"))
    plt.close(fig)
    return path


def _scene_index(scene, name: str) -> int:
    try:
        return scene.names.index(name)
    except ValueError:
        raise VrsError(f"map image {name!r} is not in the scene", scene.root) from None


def _real_image(scene, j: int) -> np.ndarray:
    return read_image(scene.image_paths[j], background=scene.background,
                      size=tuple(int(s) for s in scene.sizes[j]))


# ----------------------------------------------------------------------------- matches


def match_stages(ctx, q, cfg):
    """localize's stages (the one definition, jitted together): what the match figure draws.

    Returns dict(idx [k], gray [k, K_max, P, P] rendered patches (None in real mode),
    j [k, Kq], ok [k, Kq] (distinct 2D-3D links fed to PnP), inliers [k, Kq], guided [Kq]
    (inliers of the guided pass; None without one), success, R, t).
    """
    st = jax.device_get(jax.jit(run_stages, static_argnames=("cfg",))(ctx.m, q, cfg))
    k = len(st["idx"])
    res = st["result"]
    return {"idx": np.asarray(st["idx"]),
            "gray": np.asarray(st["gray"]) if "gray" in st else None,
            "j": np.asarray(st["j"]), "ok": np.asarray(st["ok"]).reshape(k, -1),
            "inliers": np.asarray(st["inliers"]).reshape(k, -1),
            "guided": np.asarray(st["guided_inliers"]) if "guided_inliers" in st else None,
            "success": bool(res.success), "R": np.asarray(res.R), "t": np.asarray(res.t)}


def paste_patches(base: np.ndarray, patches: np.ndarray, positions: np.ndarray,
                  order: np.ndarray) -> np.ndarray:
    """Paste grey patches [n, P, P] onto an RGB image at their sample grids [n, P, P, 2].

    Each patch is warped by the affine map from its (column, row) sample indices to the
    samples' pixel coordinates (COLMAP convention, hence -0.5 for OpenCV), so it lands with
    its keypoint's position, scale and orientation. Patches are drawn in ``order``.
    """
    out = base.copy()
    h, w = out.shape[:2]
    P = patches.shape[-1]
    src = np.float32([[0, 0], [P - 1, 0], [0, P - 1]])
    ones = np.ones((P, P), np.float32)
    for n in order:
        pos = positions[n]
        dst = np.float32([pos[0, 0], pos[0, P - 1], pos[P - 1, 0]]) - 0.5
        A = cv2.getAffineTransform(src, dst)
        val = cv2.warpAffine(np.ascontiguousarray(patches[n], np.float32), A, (w, h),
                             flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        cover = cv2.warpAffine(ones, A, (w, h), flags=cv2.INTER_LINEAR,
                               borderMode=cv2.BORDER_CONSTANT, borderValue=0.0) > 0.5
        out[cover] = val[cover, None]
    return out


def fig_matches(ctx, out_dir: Path, query: int, mode: str = "render", paste: str = "inliers"
                ) -> tuple[Path, dict]:
    cfg = common.localize_cfg(ctx, mode)
    qs = ctx.queries
    if not 0 <= query < len(qs):
        raise VrsError(f"--query {query} out of range: {len(qs)} queries", ctx.scene.root)
    size = tuple(int(s) for s in qs.sizes[query])
    q = prepare_query(ctx.m, read_gray(qs.image_paths[query], size=size), qs.K[query],
                      qs.dist[query], cfg)
    st = match_stages(ctx, q, cfg)
    n_inl = st["inliers"].sum(1)
    c = int(np.argmax(n_inl)) if n_inl.any() else int(np.argmax(st["ok"].sum(1)))
    i = int(st["idx"][c])
    egm = ctx.m.egm
    kp_ref = np.asarray(egm.keypoints[i])
    mask_ref = np.asarray(egm.kp_mask[i])
    patch_cfg = common.patch_config(ctx)
    positions, _ = patch_grid(kp_ref, patch_cfg)
    ref_real = _real_image(ctx.scene, _scene_index(ctx.scene, egm.names[i]))
    if mode == "real":  # the baseline's patches: read from the real reference image
        gray_ref = luma(ref_real)
        patches = np.asarray(extract_patches(gray_ref, kp_ref, patch_cfg))
    else:
        patches = st["gray"][c]
    valid = np.flatnonzero(mask_ref)
    matched = st["j"][c][st["ok"][c]]
    inl = st["j"][c][st["inliers"][c]]
    if paste == "inliers" and not len(inl):
        paste = "matched"
    # unmatched patches (--paste all) first, then matched ones, inliers on top
    order = np.concatenate([np.setdiff1d(valid, matched) if paste == "all" else [],
                            np.setdiff1d(np.intersect1d(valid, matched), inl)
                            if paste != "inliers" else [],
                            np.intersect1d(valid, inl)]).astype(int)
    ref = paste_patches(0.4 * ref_real, patches, positions, order)
    query_img = _real_image(ctx.scene, _scene_index(ctx.scene, qs.names[query]))

    hq, wq = query_img.shape[:2]
    hr, wr = ref.shape[:2]
    gap = max(8, wq // 40)
    canvas = np.ones((max(hq, hr), wq + gap + wr, 3), np.float32)
    canvas[:hq, :wq] = query_img
    canvas[:hr, wq + gap:] = np.clip(ref, 0, 1)
    aspect = canvas.shape[0] / canvas.shape[1]
    # strip of patch pairs below: the query's real patch | the map's (rendered or real) patch
    pairs = np.flatnonzero(st["inliers"][c]) if st["inliers"][c].any() else np.flatnonzero(
        st["ok"][c])
    pairs = pairs[np.unique(np.round(np.linspace(0, len(pairs) - 1, min(12, len(pairs))))
                            .astype(int))] if len(pairs) else pairs
    strip = None
    if len(pairs):
        gray_q = read_gray(qs.image_paths[query], size=size)
        qp = np.asarray(extract_patches(gray_q, np.asarray(q.keypoints)[pairs], patch_cfg))
        strip = pair_strip(qp, patches[st["j"][c][pairs]])
    h_strip = 12.0 * strip.shape[0] / strip.shape[1] if strip is not None else 0.3
    fig = plt.figure(figsize=(12, 12 * aspect + h_strip + 1.3))
    gs = fig.add_gridspec(2, 1, height_ratios=[12 * aspect, h_strip + 0.3], hspace=0.1)
    ax = fig.add_subplot(gs[0])
    ax.imshow(canvas, extent=(0, canvas.shape[1], canvas.shape[0], 0), interpolation="lanczos")
    off = np.array([wq + gap, 0.0])
    kq = np.asarray(q.keypoints)
    for n in np.intersect1d(valid, inl):  # outline of each inlier patch (its support)
        ax.add_patch(plt.Polygon(patch_outline(positions[n]) + off, closed=True, fill=False,
                                 ec="yellow", lw=0.5, alpha=0.8))
    for qi in np.flatnonzero(st["ok"][c]):
        a = kq[qi, :2]
        b = kp_ref[st["j"][c][qi], :2] + off
        is_in = bool(st["inliers"][c][qi])
        ax.plot([a[0], b[0]], [a[1], b[1]], "-", color="lime" if is_in else "red",
                lw=0.8 if is_in else 0.4, alpha=0.9 if is_in else 0.45)
    n_guided = 0
    if st["guided"] is not None and st["guided"].any():
        g = kq[st["guided"], :2]
        n_guided = len(g)
        ax.scatter(g[:, 0], g[:, 1], s=36, facecolors="none", edgecolors="cyan", lw=0.8)
    ax.set_xlim(0, canvas.shape[1])
    ax.set_ylim(canvas.shape[0], 0)
    dt = dr = None
    if qs.has_pose[query] and st["success"]:
        e_t, e_r = geometry.pose_errors(st["R"][None], st["t"][None], qs.R[query][None],
                                        qs.t[query][None])
        dt, dr = float(e_t[0]) * 100.0, float(e_r[0])
    err = f"pose error {dt:.1f} cm, {dr:.2f} deg" if dt is not None else (
        "pose: PnP failed (fallback)" if not st["success"] else "")
    P = patch_cfg.size
    what = "NeRF-rendered" if mode == "render" else "real (baseline)"
    ax.set_title(f"query {qs.names[query]} (left) vs {P}x{P} {what} patches of "
                 f"{egm.names[i]} (right, pasted on the dimmed real image)\n"
                 f"{int(st['ok'][c].sum())} matches, {int(n_inl[c])} PnP inliers (green) in "
                 f"candidate {c + 1} of {len(st['idx'])}; guided pass: {n_guided} inliers "
                 f"(cyan); {err}", fontsize=9)
    ax.axis("off")
    ax2 = fig.add_subplot(gs[1])
    if strip is not None:
        ax2.imshow(strip, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
    kind = "rendered" if mode == "render" else "real reference"
    ax2.set_title(f"{'inlier' if st['inliers'][c].any() else 'matched'} pairs: query patch | "
                  f"{kind} patch", fontsize=9)
    ax2.axis("off")
    suffix = "" if mode == "render" else f"_{mode}"
    path = save(fig, out_dir / f"matches_{ctx.name}{suffix}.png")
    return path, {"mode": mode, "query": qs.names[query], "reference": egm.names[i],
                  "candidate": c, "patches_pasted": len(order),
                  "matches": int(st["ok"][c].sum()), "inliers": int(n_inl[c]),
                  "inliers_all_candidates": int(n_inl.sum()), "guided_inliers": n_guided,
                  "success": st["success"],
                  "t_err_cm": dt, "R_err_deg": dr, "retrieved": st["idx"].tolist(),
                  "patch_size": P}


def patch_outline(pos: np.ndarray) -> np.ndarray:
    """Corners [4, 2] of the square a patch's samples [P, P, 2] cover (half a spacing out)."""
    P = pos.shape[0]
    corners = np.stack([pos[0, 0], pos[0, -1], pos[-1, -1], pos[-1, 0]]).astype(np.float64)
    centre = corners.mean(0)
    return centre + (corners - centre) * (P / max(P - 1, 1))


def pair_strip(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Patches a, b [n, P, P] -> one grey image: a_1 | b_1   a_2 | b_2 ... (white gaps)."""
    n, P = a.shape[0], a.shape[-1]
    gap, inner = max(2, P // 2), 1
    w = n * (2 * P + inner) + (n - 1) * gap
    out = np.ones((P, w), np.float32)
    for k in range(n):
        x = k * (2 * P + inner + gap)
        out[:, x:x + P] = a[k]
        out[:, x + P + inner:x + 2 * P + inner] = b[k]
    return np.clip(out, 0, 1)


# ----------------------------------------------------------------------------- rendering


def fig_render(ctx, out_dir: Path, ref_idx: list[int]) -> tuple[Path, dict]:
    m = ctx.m
    egm, ilm = m.egm, m.ilm
    n = len(ref_idx)
    aspect = float(egm.sizes[ref_idx[0], 1]) / float(egm.sizes[ref_idx[0], 0])
    fig, axes = plt.subplots(n, 3, figsize=(12, n * 3.9 * aspect + 0.7), squeeze=False,
                             layout="constrained")
    rows = []
    for r, i in enumerate(ref_idx):
        j = _scene_index(ctx.scene, egm.names[i])
        real = _real_image(ctx.scene, j)
        size = (int(egm.sizes[i, 0]), int(egm.sizes[i, 1]))
        c = int(ilm.image_cluster[i])
        out = render_view(ilm, c, np.asarray(egm.K[i]), np.asarray(egm.R[i]),
                          np.asarray(egm.t[i]), size, float(ilm.near[i]), float(ilm.far[i]),
                          np.asarray(egm.dist[i]))
        rgb = np.clip(out["rgb"], 0, 1)
        p = float(psnr(rgb, real))
        diff = np.abs(rgb - real).mean(-1)
        for ax, img, title in ((axes[r, 0], rgb, f"NeRF render (cluster {c})"),
                               (axes[r, 1], real, f"real {egm.names[i]}"),
                               (axes[r, 2], diff, f"|difference|, PSNR {p:.1f} dB")):
            ax.imshow(img, cmap="magma" if img.ndim == 2 else None,
                      vmin=0, vmax=0.5 if img.ndim == 2 else None)
            ax.set_title(title, fontsize=9)
            ax.axis("off")
        rows.append({"reference": egm.names[i], "psnr": p, "cluster": c})
    fig.suptitle(f"{ctx.name}: reference images rendered by the map's NeRF "
                 f"({ilm.config.name} config) vs real", fontsize=10)
    path = save(fig, out_dir / f"render_vs_real_{ctx.name}.png")
    return path, {"views": rows}


# ----------------------------------------------------------------------------- clusters


def top_view(centers: np.ndarray) -> np.ndarray:
    """[N, 3] camera centres -> [N, 2] coordinates on their two principal axes."""
    c = np.asarray(centers, np.float64)
    c = c - c.mean(0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    return c @ vt[:2].T


def grid_shape(n: int, aspect: float) -> tuple[int, int]:
    """(nx, ny) with nx * ny = n whose cell aspect best matches the extent (x / y)."""
    pairs = [(a, n // a) for a in range(1, n + 1) if n % a == 0]
    return min(pairs, key=lambda p: abs(np.log((p[0] / p[1]) / max(aspect, 1e-9))))


def grid_clusters(xy: np.ndarray, n: int) -> tuple[np.ndarray, tuple[int, int], np.ndarray]:
    """Uniform grid over the bounding box: labels [N], (nx, ny), edges [2] (x and y)."""
    lo, hi = xy.min(0), xy.max(0)
    span = np.maximum(hi - lo, 1e-9)
    nx, ny = grid_shape(n, span[0] / span[1])
    ix = np.clip(((xy[:, 0] - lo[0]) / span[0] * nx).astype(int), 0, nx - 1)
    iy = np.clip(((xy[:, 1] - lo[1]) / span[1] * ny).astype(int), 0, ny - 1)
    edges = (np.linspace(lo[0], hi[0], nx + 1), np.linspace(lo[1], hi[1], ny + 1))
    return ix * ny + iy, (nx, ny), edges


def fig_clusters(name: str, centers: np.ndarray, n: int, out_dir: Path) -> tuple[Path, dict]:
    if not 1 <= n <= len(centers):
        raise VrsError(f"--clusters {n}: the {name} scene has {len(centers)} reference images")
    xy = top_view(centers)
    g_labels, (nx, ny), edges = grid_clusters(xy, n)
    overlap = nerf_config.get_config("paper").cluster_overlap
    km = clusters_lib.cluster_cameras(centers, n, overlap=overlap)
    k_labels = km.primary
    shared = km.membership.sum(0) > 1
    g_counts = np.bincount(g_labels, minlength=n)
    k_counts = np.bincount(k_labels, minlength=n)
    cmap = plt.get_cmap("tab10" if n <= 10 else "tab20")
    fig, axes = plt.subplots(1, 2, figsize=(12, 5.4), sharex=True, sharey=True)
    for ax, labels, counts, title in (
            (axes[0], g_labels, g_counts, f"uniform {nx}x{ny} grid"),
            (axes[1], k_labels, k_counts, f"K-means, {n} clusters")):
        ax.scatter(xy[:, 0], xy[:, 1], c=[cmap(int(lab) % cmap.N) for lab in labels], s=28,
                   edgecolors="none", zorder=2)
        ax.set_title(f"{title}: images per cluster {'/'.join(str(int(c)) for c in counts)}"
                     f"\n(min {int(counts.min())}, max {int(counts.max())})", fontsize=9)
        ax.set_aspect("equal")
        ax.grid(alpha=0.2)
        ax.set_xlabel("principal axis 1 (scene units)")
    for e in edges[0]:
        axes[0].axvline(e, color="k", lw=0.8, zorder=1)
    for e in edges[1]:
        axes[0].axhline(e, color="k", lw=0.8, zorder=1)
    axes[1].scatter(xy[shared, 0], xy[shared, 1], s=70, facecolors="none", edgecolors="k",
                    lw=0.8, zorder=3, label=f"shared with a neighbour ({int(shared.sum())})")
    kc = top_view_project(centers, km.centers)
    axes[1].scatter(kc[:, 0], kc[:, 1], marker="*", s=220, c=[cmap(c % cmap.N)
                                                              for c in range(n)],
                    edgecolors="k", zorder=4, label="cluster centres")
    axes[1].legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2)
    axes[0].set_ylabel("principal axis 2 (scene units)")
    fig.suptitle(f"{name}: scene division of {len(centers)} reference cameras (top view)",
                 fontsize=10)
    path = save(fig, out_dir / f"clusters_{name}.png")
    return path, {"n_clusters": n, "grid": [nx, ny], "grid_counts": g_counts.tolist(),
                  "kmeans_counts": k_counts.tolist(), "kmeans_shared_images": int(shared.sum())}


def top_view_project(centers: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Project ``points`` [M, 3] with the top-view frame of ``centers`` [N, 3]."""
    c = np.asarray(centers, np.float64)
    mean = c.mean(0)
    _, _, vt = np.linalg.svd(c - mean, full_matrices=False)
    return (np.asarray(points, np.float64) - mean) @ vt[:2].T


# ----------------------------------------------------------------------------- curves

METHODS = {"render": ("VRS-NeRF (rendered patches)", "-", "C0"),
           "real": ("real patches (baseline)", "--", "C1"),
           "sift": ("COLMAP SIFT reference", ":", "k")}


def final_rows(doc: dict) -> dict[str, dict[str, dict]]:
    """{scene: {mode: row}} of a ``benchmarks.localize`` JSON: the final pose of render,
    real and sift (not the "pass 1" rows, not render-full)."""
    out: dict[str, dict[str, dict]] = {}
    for r in doc["rows"]:
        if r["mode"] in METHODS:
            out.setdefault(r["scene"], {})[r["mode"]] = r
    return out


def fig_curves(doc: dict, out_dir: Path, max_pct: float, max_deg: float
               ) -> tuple[Path, dict]:
    """Cumulative error curves per scene of a ``benchmarks.localize`` run: translation as a
    percentage of the scene's scale (median camera distance to the centroid), and rotation;
    render, real and the SIFT reference on the same queries."""
    by_scene = final_rows(doc)
    if not by_scene:
        raise VrsError("the localize JSON has no render / real / sift rows")
    n = len(by_scene)
    fig, axes = plt.subplots(2, n, figsize=(3.6 * n + 0.6, 6.4), squeeze=False)
    info = {}
    for col, (scene, rows) in enumerate(by_scene.items()):
        for mode, r in rows.items():
            label, ls, color = METHODS[mode]
            scale = r.get("scene_scale") or 1.0
            t_pct = 100.0 * np.asarray(common._inf(r["per_query"]["t_err_m"])) / scale
            r_deg = np.asarray(common._inf(r["per_query"]["R_err_deg"], 180.0))
            for ax, e, mx in ((axes[0, col], t_pct, max_pct), (axes[1, col], r_deg, max_deg)):
                x, y = metrics.cumulative_curve(e, max_error=mx)
                ax.step(x, 100.0 * y, where="post", ls=ls, color=color, label=label)
            info[f"{scene}/{mode}"] = {"n_queries": len(t_pct),
                                       "median_t_pct": float(np.median(t_pct)),
                                       "median_R_deg": float(np.median(r_deg))}
        axes[0, col].set_title(f"{scene} ({len(t_pct)} queries)", fontsize=10)
        for ax, unit in ((axes[0, col], "translation error (% of scene scale)"),
                         (axes[1, col], "rotation error (deg)")):
            ax.axvline(1.0, color="0.6", lw=0.8, ls=":")
            ax.set_xlabel(unit, fontsize=8)
            ax.set_ylim(0, 101)
            ax.set_xlim(0, None)
            ax.grid(alpha=0.3)
        axes[0, col].set_ylabel("queries with a smaller error (%)" if col == 0 else "")
        axes[1, col].set_ylabel("queries with a smaller error (%)" if col == 0 else "")
    axes[1, 0].legend(fontsize=8, loc="lower right")
    fig.suptitle("Cumulative localization error on the same queries (a failure counts as an "
                 "infinite error; dotted line: 1% / 1 deg)", fontsize=10)
    fig.tight_layout()
    return save(fig, out_dir / "cumulative_errors.png"), info


def fig_timing(doc: dict, out_dir: Path) -> tuple[Path, dict]:
    """Where a query's time goes: the median seconds of each stage (query preparation
    first) per scene and method, stacked, from a ``benchmarks.localize`` run."""
    by_scene = final_rows(doc)
    bars = [(f"{scene} / {mode}", r["timing_s"]) for scene, rows in by_scene.items()
            for mode, r in rows.items()]
    stages: list[str] = []
    for _, t in bars:
        for k in ("query_preparation", *t):
            if k not in stages and t.get(k) is not None:
                stages.append(k)
    fig, ax = plt.subplots(figsize=(10, 0.42 * len(bars) + 1.6))
    cmap = plt.get_cmap("tab20")  # 20 distinct colours: every stage of every method its own
    colors = {k: cmap(i % 20) for i, k in enumerate(stages)}
    info = {}
    for y, (label, t) in enumerate(bars):
        left = 0.0
        for k in stages:
            v = t.get(k)
            if v is None:
                continue
            ax.barh(y, v, left=left, color=colors[k], edgecolor="white", lw=0.5,
                    label=k if y == next(i for i, (_, tt) in enumerate(bars)
                                         if tt.get(k) is not None) else None)
            left += v
        ax.text(left, y, f" {left:.2f} s", va="center", fontsize=8)
        info[label] = {"total_s": left, **{k: t.get(k) for k in stages}}
    ax.set_yticks(range(len(bars)), [b[0] for b in bars], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("median seconds per query (each stage's median; compilation excluded)")
    ax.legend(fontsize=7, ncol=4, loc="lower right")
    ax.grid(axis="x", alpha=0.3)
    ax.set_title("Where a query's time goes (2 CPU cores)", fontsize=10)
    return save(fig, out_dir / "timing.png"), info


# ----------------------------------------------------------------------------- main


def output_paths(args, which: list[str], match_modes: list[str], out: Path) -> list[Path]:
    """Every file a run of these figures may write (checked before any work)."""
    paths = [out / "figures.json"]
    if "clusters" in which:
        paths += [out / f"clusters_{n}.png" for n in common.parse_scenes(args.cluster_scenes)]
    paths += [out / f"{f}.png" for f, name in (("cumulative_errors", "curves"),
                                               ("timing", "timing")) if name in which]
    for name in common.parse_scenes(args.scenes):
        if "matches" in which or "render" in which:  # render draws the match figure first
            modes = match_modes if "matches" in which else ["render"]
            paths += [out / f"matches_{name}{'' if m == 'render' else '_' + m}.png"
                      for m in modes]
        if "render" in which:
            paths.append(out / f"render_vs_real_{name}.png")
    return paths


@cli_main
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    which = [f.strip() for f in args.figures.split(",") if f.strip()]
    bad = [f for f in which if f not in FIGURES]
    if bad or not which:
        raise VrsError(f"--figures must list some of {', '.join(FIGURES)}, got {args.figures!r}")
    match_modes = [m.strip() for m in args.match_modes.split(",") if m.strip()]
    if not match_modes or any(m not in ("render", "real") for m in match_modes):
        raise VrsError(f"--match-modes must list render and/or real, got {args.match_modes!r}")
    out = Path(args.out)
    common.check_outputs(args, output_paths(args, which, match_modes, out))
    doc = common.base_doc("figures", args, argv)
    paths: list[Path] = []
    info: dict = {}
    if "clusters" in which:
        for name in common.parse_scenes(args.cluster_scenes):
            root = None
            maps = common.parse_maps(args.map)
            if name in maps:  # the map's scene
                ctx = common.prepare_scene(name, args)
                centers = ctx.scene.references().centers
            else:
                root = common.scene_root(name, args)
                if root is None:
                    continue
                spec = common.SCENES[name]
                centers = common._load_scene(spec.fmt, root,
                                             spec.reader_options).references().centers
            p, info[f"clusters_{name}"] = fig_clusters(name, centers, args.clusters, out)
            paths.append(p)
    if "curves" in which or "timing" in which:
        loc = fileio.read_json(args.localize_json)  # VrsError naming the file if absent
        if "curves" in which:
            p, info["curves"] = fig_curves(loc, out, args.max_pct, args.max_deg)
            paths.append(p)
        if "timing" in which:
            p, info["timing"] = fig_timing(loc, out)
            paths.append(p)
    need_maps = [f for f in which if f in ("render", "matches")]
    if need_maps:
        ctxs, skipped = common.prepare_scenes(args)
        info["skipped"] = skipped
        for ctx in ctxs:
            if "matches" in which or "render" in which:
                modes = match_modes if "matches" in which else ["render"]
                for mode in modes:
                    p, mi = fig_matches(ctx, out, args.query, mode, args.paste)
                    if "matches" in which:
                        paths.append(p)
                        info[f"matches_{ctx.name}_{mode}"] = mi
                    else:
                        p.unlink()
                if "render" in which:
                    views = mi["retrieved"][:max(1, args.views)]
                    p, info[f"render_{ctx.name}"] = fig_render(ctx, out, views)
                    paths.append(p)
    doc.update({"figures": [str(p) for p in paths], "info": info})
    common.write_json(out / "figures.json", doc)
    for p in paths:
        print(p)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
