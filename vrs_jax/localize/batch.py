"""Localize every query image of a Scene with one map (the experiments' and benchmarks' loop).

Query preparation runs on the host per image; ``localize`` is compiled once (first query) and
reused for all. A query image that cannot be read is flagged in its result (``error``) and the
run goes on with the others.
"""

from __future__ import annotations

import logging
import time
from typing import Any

import jax
import numpy as np
from tqdm import tqdm

from vrs_jax.data.images import read_gray
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.localize.query import prepare_query
from vrs_jax.localize.render import nerf_evals_per_ray, rays_per_query
from vrs_jax.localize.run import localize, localize_timed
from vrs_jax.localize.stages import STAGE_NAMES, LocalizeResult
from vrs_jax.maps import Map

log = logging.getLogger("vrs_jax")


def localize_scene(m: Map, queries: Scene, cfg: LocalizeConfig, progress: bool = True,
                   timed: bool = True) -> tuple[list[LocalizeResult | None], dict[str, Any]]:
    """Localize every image of ``queries``; returns per-query results and run info.

    A query whose image cannot be used gets ``None`` and its reason in ``info["errors"]``.
    With ``timed``, a warm-up call is made first and each query is run stage by stage
    (:func:`localize_timed`) to report median seconds per stage.
    """
    results: list[LocalizeResult | None] = []
    times, prep_s, errors = [], [], {}
    warm = False
    for i in tqdm(range(len(queries)), desc=f"localize ({cfg.source})", unit="query",
                  disable=not progress):
        t0 = time.perf_counter()
        size = tuple(int(s) for s in queries.sizes[i])
        try:
            gray = read_gray(queries.image_paths[i], size=size)
        except VrsError as e:
            errors[queries.names[i]] = str(e)
            log.warning("skipping query: %s", e)
            results.append(None)
            continue
        q = prepare_query(m, gray, queries.K[i], queries.dist[i], cfg)
        prep_s.append(time.perf_counter() - t0)
        if timed:
            if not warm:
                localize_timed(m, q, cfg)  # compile every stage once
                warm = True
            res, tm = localize_timed(m, q, cfg)
            times.append(tm)
        else:
            res = localize(m, q, cfg)
        results.append(jax.device_get(res))
    timing = {s: float(np.median([t[s] for t in times])) if times else None for s in STAGE_NAMES}
    timing["query_preparation"] = float(np.median(prep_s)) if prep_s else None
    rays = rays_per_query(m, cfg)
    info = {
        "rays_per_query": rays,
        "nerf_evals_per_query": rays * nerf_evals_per_ray(m, cfg) if cfg.source == "render"
        else 0.0,
        "timing_s": timing,
        "n_success": int(sum(bool(r.success) for r in results if r is not None)),
        "errors": errors,
    }
    return results, info
