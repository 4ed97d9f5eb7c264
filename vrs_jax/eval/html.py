"""A self-contained HTML page of one localization run (``experiments.localize --report``).

One file, every picture inside it (PNG data URIs), so it opens anywhere and can be mailed:

- the run: map, mode, config, counts, the recall table when the queries have ground truth;
- a results table, one row per query (verdict, inliers, matches, errors), linking to
- per query: the query image with its matched keypoints (first pass: PnP inliers green,
  other matches red; guided pass inliers ringed cyan), the reference image it matched best
  with the matched keypoints, and pairs of patches for up to ``max_pairs`` inliers: the
  query's real patch | the map's patch (NeRF-rendered in render mode) | the reference
  image's real patch (when the map's images are still on disk).

The pictures come from running localize's stages once more per query (``run_stages``, the
one definition, jitted), so ``--report`` costs about one more localization per query.
"""

from __future__ import annotations

import base64
import html
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import jax
import numpy as np
from tqdm import tqdm

from vrs_jax import fileio
from vrs_jax.data.images import luma, read_gray, read_image
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError
from vrs_jax.eval import metrics
from vrs_jax.features.patches import extract_patches
from vrs_jax.localize import prepare_query, run_stages
from vrs_jax.localize.confidence import result_verdicts
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.localize.stages import LocalizeResult
from vrs_jax.maps import Map

GREEN, RED, CYAN = (40, 200, 40), (220, 40, 40), (0, 220, 220)  # RGB
THUMB = 480  # longest side of the images on the page, pixels


def png_uri(img: np.ndarray) -> str:
    """[H, W] or [H, W, 3] image (uint8, or float in [0, 1], RGB) -> ``data:image/png`` URI."""
    a = np.asarray(img)
    if a.dtype != np.uint8:
        a = np.round(np.clip(a, 0.0, 1.0) * 255.0).astype(np.uint8)
    if a.ndim == 3:
        a = cv2.cvtColor(a, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", a)
    if not ok:  # cv2 encodes any uint8 array of these shapes; a guard, not a code path
        raise ValueError(f"cannot encode an image of shape {a.shape} as PNG")
    return "data:image/png;base64," + base64.b64encode(buf.tobytes()).decode("ascii")


def to_rgb8(img: np.ndarray, longest: int = THUMB) -> tuple[np.ndarray, float]:
    """Grey [H, W] or RGB [H, W, 3] float in [0, 1] -> uint8 RGB scaled so that its longest
    side is at most ``longest``; returns (image, scale factor applied to pixel coordinates)."""
    a = np.asarray(img, np.float32)
    if a.ndim == 2:
        a = np.repeat(a[..., None], 3, axis=-1)
    s = min(1.0, longest / max(a.shape[:2]))
    if s < 1.0:
        a = cv2.resize(a, (max(1, round(a.shape[1] * s)), max(1, round(a.shape[0] * s))),
                       interpolation=cv2.INTER_AREA)
    return np.round(np.clip(a, 0, 1) * 255).astype(np.uint8), s


def draw_points(img: np.ndarray, uv: np.ndarray, color: tuple[int, int, int], scale: float,
                radius: int = 3, ring: bool = False) -> np.ndarray:
    """Draw keypoints uv [n, 2] (COLMAP convention, full-resolution pixels) on the uint8 RGB
    thumbnail ``img`` (modified and returned): dots, or rings with ``ring``."""
    for x, y in np.asarray(uv, np.float64).reshape(-1, 2):
        c = (int(round((x - 0.5) * scale)), int(round((y - 0.5) * scale)))
        cv2.circle(img, c, radius + (2 if ring else 0), color, 1 if ring else -1, cv2.LINE_AA)
    return img


def patch_table(rows: Sequence[Sequence[np.ndarray | None]], size: int = 64) -> np.ndarray:
    """Patches [P, P] in [0, 1] as a grid image: one column per pair (its patches stacked top
    to bottom), with gaps; a None cell stays grey. Returns float
    [n_kinds * (size + 4), len(rows) * (size + 4)]."""
    n_kinds = max(len(r) for r in rows)
    cell = size + 4
    out = np.full((n_kinds * cell, len(rows) * cell), 0.5, np.float32)
    for j, r in enumerate(rows):
        for i, p in enumerate(r):
            if p is None:
                continue
            big = cv2.resize(np.asarray(p, np.float32), (size, size),
                             interpolation=cv2.INTER_NEAREST)
            out[i * cell + 2:i * cell + 2 + size, j * cell + 2:j * cell + 2 + size] = big
    return out


def reference_image(m: Map, i: int) -> np.ndarray | None:
    """Reference image i as float RGB at the map's size, or None when the map's dataset is no
    longer on disk (names are relative to the recorded dataset root)."""
    if not m.source.root:
        return None
    path = Path(m.source.root) / m.egm.names[i]
    if not path.is_file():
        return None
    try:
        return read_image(path, size=tuple(int(s) for s in np.asarray(m.egm.sizes[i])))
    except VrsError:
        return None


_stages = jax.jit(run_stages, static_argnames=("cfg",))


def query_views(m: Map, gray: np.ndarray, K: np.ndarray, dist: np.ndarray,
                cfg: LocalizeConfig, max_pairs: int = 8) -> dict[str, Any]:
    """What the report shows of one query, from its stages.

    Returns dict: ``kq`` [Kq, 2] query keypoints; ``matched`` / ``inliers`` [Kq] bool of the
    best candidate (most first-pass inliers); ``guided`` [Kq] bool guided-pass inliers;
    ``ref`` its reference index; ``kp_ref`` [Kq, 2] the matched reference keypoints;
    ``pairs``: up to ``max_pairs`` (query patch, map patch, real reference patch or None).
    """
    q = prepare_query(m, gray, K, dist, cfg)
    st = jax.device_get(_stages(m, q, cfg))
    k = len(st["idx"])
    ok = np.asarray(st["ok"]).reshape(k, -1)
    inl = np.asarray(st["inliers"]).reshape(k, -1)
    j = np.asarray(st["j"])
    c = int(np.argmax(inl.sum(1))) if inl.any() else int(np.argmax(ok.sum(1)))
    i = int(st["idx"][c])
    kq = np.asarray(q.keypoints)
    kp_ref = np.asarray(m.egm.keypoints[i])
    patch_cfg = cfg.patches or m.config.features.patches
    use = np.flatnonzero(inl[c]) if inl[c].any() else np.flatnonzero(ok[c])
    use = use[np.unique(np.linspace(0, len(use) - 1, min(max_pairs, len(use))).round()
                        .astype(int))] if len(use) else use
    pairs = []
    if len(use):
        mine = np.asarray(extract_patches(gray, kq[use], patch_cfg))
        if "gray" in st:  # render mode: the NeRF's patches of the candidate
            theirs = np.asarray(st["gray"])[c][j[c][use]]
        else:
            theirs = [None] * len(use)
        ref_img = reference_image(m, i)
        real = (np.asarray(extract_patches(luma(ref_img), kp_ref[j[c][use]], patch_cfg))
                if ref_img is not None else [None] * len(use))
        pairs = list(zip(mine, theirs, real, strict=True))
    guided = np.asarray(st["guided_inliers"]) if "guided_inliers" in st else np.zeros(
        len(kq), bool)
    return {"kq": kq[:, :2], "matched": ok[c], "inliers": inl[c], "guided": guided,
            "ref": i, "candidate": c, "kp_ref": kp_ref[j[c], :2], "pairs": pairs,
            "render": "gray" in st}


def _verdict(r: LocalizeResult | None, error: str | None, verdict: str = "",
             confidence: float = 0.0) -> str:
    """The verdict of the pose confidence with the confidence (localize.confidence), or why
    there is no pose."""
    if r is None:
        return f"failed: unreadable: {error or 'no result'}"
    if verdict == "failed" or not bool(r.success):
        return "failed (top-1 reference pose written)"
    return f"{verdict or 'localized'} (confidence {confidence:.2f})"


def _errors(queries: Scene, results: Sequence[LocalizeResult | None]
            ) -> tuple[np.ndarray, np.ndarray]:
    """Per-query errors [N] (cm, deg); NaN where there is no ground truth or no result."""
    n = len(results)
    dt, dr = np.full(n, np.nan), np.full(n, np.nan)
    for i, r in enumerate(results):
        if r is not None and queries.has_pose[i]:
            e_t, e_r = metrics.pose_errors(np.asarray(r.R)[None], np.asarray(r.t)[None],
                                           queries.R[i][None], queries.t[i][None])
            dt[i], dr[i] = 100.0 * float(e_t[0]), float(e_r[0])
    return dt, dr


CSS = """body{font-family:sans-serif;margin:1.5em;max-width:1400px}
table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 8px;text-align:right}
td:first-child,th:first-child{text-align:left}.bad{color:#b00}.ok{color:#070}.warn{color:#b60}
section{border-top:1px solid #aaa;margin-top:1.5em}img{margin:4px}img.view{height:300px}
figure{display:inline-block;margin:0 8px;vertical-align:top}
figcaption{font-size:80%;color:#444;max-width:640px}"""


def _figure(uri: str, caption: str, cls: str = "view") -> str:
    return (f'<figure><img class="{cls}" src="{uri}" alt="{html.escape(caption)}">'
            f"<figcaption>{html.escape(caption)}</figcaption></figure>")


def query_section(name: str, idx: int, queries: Scene, m: Map, r: LocalizeResult | None,
                  error: str | None, views: dict | None, dt: float, dr: float,
                  verdict: str = "", confidence: float = 0.0) -> str:
    """The HTML of one query: its facts, its images and its patch pairs."""
    facts = [_verdict(r, error, verdict, confidence)]
    if r is not None:
        facts.append(f"{int(r.n_inliers)} inliers of {int(r.n_matches)} matches "
                     f"(first pass {int(r.n_inliers_first)})")
    if np.isfinite(dt):
        facts.append(f"error {dt:.2f} cm, {dr:.3f} deg")
    parts = [f'<section id="q{idx}"><h3>{html.escape(name)}</h3>'
             f"<p>{html.escape('; '.join(facts))}</p>"]
    if views is not None:
        img, s = to_rgb8(read_image(queries.image_paths[idx], background=queries.background,
                                    size=tuple(int(v) for v in queries.sizes[idx])))
        draw_points(img, views["kq"][views["matched"] & ~views["inliers"]], RED, s, 2)
        draw_points(img, views["kq"][views["inliers"]], GREEN, s)
        draw_points(img, views["kq"][views["guided"]], CYAN, s, ring=True)
        parts.append(_figure(png_uri(img), "query: PnP inliers (green), other matches (red), "
                                           "guided-pass inliers (cyan rings)"))
        ref = reference_image(m, views["ref"])
        if ref is not None:
            rimg, rs = to_rgb8(ref)
            draw_points(rimg, views["kp_ref"][views["matched"] & ~views["inliers"]], RED, rs, 2)
            draw_points(rimg, views["kp_ref"][views["inliers"]], GREEN, rs)
            parts.append(_figure(png_uri(rimg), f"best reference {m.egm.names[views['ref']]} "
                                                f"(candidate {views['candidate'] + 1})"))
        if views["pairs"]:
            what = "rendered patch" if views["render"] else "(real mode: no rendering)"
            parts.append(_figure(png_uri(patch_table(views["pairs"])),
                                 f"patches of up to 8 inliers, top to bottom: query | {what} | "
                                 "real reference", cls="patches"))
    parts.append("</section>")
    return "\n".join(parts)


def write_report(path: str | Path, m: Map, queries: Scene,
                 results: Sequence[LocalizeResult | None], summary: dict, cfg: LocalizeConfig,
                 errors: dict[str, str] | None = None, progress: bool = True,
                 confidence: tuple[np.ndarray, np.ndarray] | None = None) -> Path:
    """Write the run's HTML page (see the module docstring); returns its path.
    ``confidence``: (confidence [N], verdict [N]) of the results (default: computed with
    ``cfg.confidence``)."""
    errors = errors or {}
    conf, verdict = (confidence if confidence is not None
                     else result_verdicts(m, results, cfg.confidence))
    dt, dr = _errors(queries, results)
    rows, sections = [], []
    for i in tqdm(range(len(results)), desc="report", unit="query", disable=not progress):
        name, r = queries.names[i], results[i]
        views = None
        if r is not None:
            gray = read_gray(queries.image_paths[i], background=queries.background,
                             size=tuple(int(v) for v in queries.sizes[i]))
            views = query_views(m, gray, queries.K[i], queries.dist[i], cfg)
        cls = {"localized": "ok", "uncertain": "warn"}.get(str(verdict[i]), "bad")
        shown = _verdict(r, errors.get(name), str(verdict[i]), float(conf[i]))
        err = f"{dt[i]:.2f}</td><td>{dr[i]:.3f}" if np.isfinite(dt[i]) else "-</td><td>-"
        rows.append(f'<tr><td><a href="#q{i}">{html.escape(name)}</a></td>'
                    f'<td class="{cls}">{html.escape(shown)}</td>'
                    f"<td>{int(r.n_inliers) if r is not None else 0}</td>"
                    f"<td>{int(r.n_matches) if r is not None else 0}</td><td>{err}</td></tr>")
        sections.append(query_section(name, i, queries, m, r, errors.get(name), views,
                                      dt[i], dr[i], str(verdict[i]), float(conf[i])))
    head = (f"<p>dataset <code>{html.escape(str(m.source.root or ''))}</code> (map config "
            f"{m.config.name}, "
            f"{m.egm.num_images} reference images); mode <b>{cfg.source}</b>; "
            f"{summary['n_success']}/{len(results)} localized, {summary['n_fallback']} "
            f"fallback, {summary['n_unreadable']} unreadable; verdicts: "
            f"{summary.get('n_localized', 0)} localized, {summary.get('n_uncertain', 0)} "
            f"uncertain, {summary.get('n_failed', 0)} failed</p>")
    if summary.get("recall") is not None:
        head += "<pre>" + html.escape(metrics.format_table(summary, title="accuracy")) + "</pre>"
    doc = ("<!DOCTYPE html><html><head><meta charset='utf-8'><title>vrs-jax localization "
           f"report</title><style>{CSS}</style></head><body><h1>vrs-jax localization report"
           f"</h1>{head}<table><tr><th>query</th><th>verdict</th><th>inliers</th>"
           "<th>matches</th><th>t error (cm)</th><th>R error (deg)</th></tr>"
           + "\n".join(rows) + "</table>\n" + "\n".join(sections) + "</body></html>\n")
    return fileio.write_text(Path(path), doc)
