"""Localize every query image of a Scene with one map (the experiments' and benchmarks' loop).

Query preparation runs on the host per image; ``localize`` is compiled once (first query) and
reused for all. A query image that cannot be read is flagged in its result (``error``) and the
run goes on with the others.

Batches (:func:`localize_batch`): ``jax.vmap(localize)`` over a stacked batch of queries
(``query.stack_queries``). With a mesh of several devices the query axis is split over them
(the map copied to every device; queries never interact, so each device localizes its own
slice with no communication). The batch is padded to a multiple of the device count by
repeating its last query; the padding rows are dropped from the result.
"""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm import tqdm

from vrs_jax.data.images import read_gray
from vrs_jax.data.scene import Scene
from vrs_jax.errors import VrsError
from vrs_jax.localize.confidence import map_scale
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.localize.query import Query, prepare_query
from vrs_jax.localize.render import full_image_evals, nerf_evals_per_ray, rays_per_patch
from vrs_jax.localize.retry import localize_with_retries
from vrs_jax.localize.run import localize, localize_stacked, localize_timed
from vrs_jax.localize.stages import STAGE_NAMES, LocalizeResult
from vrs_jax.maps import Map

log = logging.getLogger("vrs_jax")
QUERY_AXIS = "queries"


def localize_scene(m: Map, queries: Scene, cfg: LocalizeConfig, progress: bool = True,
                   timed: bool = True) -> tuple[list[LocalizeResult | None], dict[str, Any]]:
    """Localize every image of ``queries``; returns per-query results and run info.

    A query whose image cannot be used gets ``None`` and its reason in ``info["errors"]``.
    With ``timed``, a warm-up call is made first and each query is run stage by stage
    (:func:`localize_timed`) to report median seconds per stage. With ``cfg.retries`` a
    query that is not "localized" is tried again with the next references
    (:mod:`~vrs_jax.localize.retry`; its time and rendered patches are all its attempts');
    ``info["retried"]``: per query retried, {"attempts": made, "kept": the attempt kept}.
    """
    results: list[LocalizeResult | None] = []
    times, prep_s, errors, retried = [], [], {}, {}
    warm: set[LocalizeConfig] = set()  # configs (attempts) whose stages are compiled
    scale = map_scale(m)
    for i in tqdm(range(len(queries)), desc=f"localize ({cfg.source})", unit="query",
                  disable=not progress):
        t0 = time.perf_counter()
        size = tuple(int(s) for s in queries.sizes[i])
        try:
            gray = read_gray(queries.image_paths[i], size=size)
            q = prepare_query(m, gray, queries.K[i], queries.dist[i], cfg,
                              str(queries.image_paths[i]))
        except VrsError as e:  # unreadable, or contradicting its camera: flagged, skipped
            errors[queries.names[i]] = str(e)
            log.warning("skipping query: %s", e)
            results.append(None)
            continue
        prep_s.append(time.perf_counter() - t0)
        tms: list[dict[str, float]] = []  # per attempt: seconds per stage
        made: list[LocalizeConfig] = []  # the attempts' configs

        def once(c: LocalizeConfig, q=q, tms=tms, made=made) -> LocalizeResult:
            made.append(c)
            if not timed:
                return localize(m, q, c)
            if c not in warm:
                localize_timed(m, q, c)  # compile every stage once
                warm.add(c)
            res, tm = localize_timed(m, q, c)
            tms.append(tm)
            return res

        res, kept = localize_with_retries(m, q, cfg, once, scale)
        if tms:  # a query's time is all its attempts'
            times.append({k: sum(t[k] for t in tms) for k in tms[0]})
        if len(made) > 1:
            retried[queries.names[i]] = {"attempts": len(made), "kept": kept}
        results.append(res)
    timing = {s: float(np.median([t[s] for t in times])) if times else None for s in STAGE_NAMES}
    timing["query_preparation"] = float(np.median(prep_s)) if prep_s else None
    rays = rays_rendered(m, cfg, results)
    info = {
        "rays_per_query": rays,
        "nerf_evals_per_query": rays * nerf_evals_per_ray(m, cfg) if cfg.source == "render"
        else 0.0,
        "full_image_evals_per_query": float(np.mean(
            [full_image_evals(m, r.retrieved) for r in results if r is not None] or [0.0]))
        if cfg.source == "render" else 0.0,
        "timing_s": timing,
        "n_success": int(sum(bool(r.success) for r in results if r is not None)),
        "errors": errors,
        "retried": retried,
    }
    return results, info


def rays_rendered(m: Map, cfg: LocalizeConfig, results: Sequence[LocalizeResult | None],
                  stat: Callable[[Any], Any] = np.mean) -> float:
    """Patch rays rendered per query (``n_rendered`` x rays per patch), their mean (or
    ``stat``, e.g. np.median) over the queries with a result; 0 in real-patch mode."""
    counts = [int(r.n_rendered) for r in results if r is not None]
    if cfg.source != "render" or not counts:
        return 0.0
    return float(stat(counts) * rays_per_patch(m, cfg))


# ----------------------------------------------------------------------------- batches


def query_mesh(devices: Sequence[Any] | int | None = None) -> Mesh:
    """A 1-D mesh (axis ``"queries"``) over ``devices``: a list, the first N of
    ``jax.devices()``, or None for all of them."""
    all_devices = jax.devices()
    if devices is None:
        devices = all_devices
    elif isinstance(devices, int):
        if not 1 <= devices <= len(all_devices):
            raise VrsError(f"{devices} devices requested, {len(all_devices)} available")
        devices = all_devices[:devices]
    return Mesh(np.asarray(list(devices)), (QUERY_AXIS,))


def pad_queries(q: Query, multiple: int) -> tuple[Query, np.ndarray]:
    """Pad a stacked batch of B queries to the next multiple of ``multiple`` by repeating the
    last query (a valid query: no NaN, the same work). Returns (padded batch, valid [B_pad]
    bool)."""
    b = int(q.K.shape[0])
    if b == 0:
        raise VrsError("empty batch of queries")
    pad = (-b) % multiple
    valid = np.arange(b + pad) < b
    if pad == 0:
        return q, valid
    return jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]),
                        q), valid


@functools.lru_cache(maxsize=16)
def make_localize_batch(cfg: LocalizeConfig) -> Callable[[Map, Query], LocalizeResult]:
    """The jitted batched ``localize``: ``(map, queries [B, ...]) -> LocalizeResult [B, ...]``
    (:func:`~vrs_jax.localize.run.localize_stacked`: vmapped, rendering query by query; runs on
    the device its inputs are on)."""
    return functools.partial(localize_stacked, cfg=cfg)


def place_map(m: Map, mesh: Mesh) -> list[Map]:
    """One copy of the map on each device of ``mesh`` (a long-lived caller keeps them)."""
    return [jax.device_put(m, d) for d in mesh.devices.flat]


def localize_batch(m: Map | list[Map], q: Query, cfg: LocalizeConfig,
                   mesh: Mesh | None = None) -> LocalizeResult:
    """Localize a stacked batch of B queries (``stack_queries``), its query axis sharded over
    the devices of ``mesh`` (None or one device: unsharded).

    Args:
      m: the map, or its per-device copies (:func:`place_map`, to skip the copies per call).
      q: Query [B, ...]; padded here to a multiple of the device count.
    Returns:
      LocalizeResult [B, ...]: device arrays, split along the query axis
      (``NamedSharding(mesh, P("queries"))``) when sharded.

    Each device localizes its contiguous slice of the padded batch with the jitted vmapped
    ``localize``, all dispatched asynchronously (the devices run concurrently) and assembled
    into one sharded array: no collective, no cross-device step. (Not one SPMD program:
    ``jax.shard_map`` breaks optimistix's LM solve in the pose refinement, and under GSPMD
    the RANSAC host callback is placed on the first device, the batch gathered there, and
    forced CPU devices could deadlock in that exchange.)
    """
    fn = make_localize_batch(cfg)
    if mesh is None or mesh.size == 1:
        return fn(m[0] if isinstance(m, list) else m, q)
    n = mesh.size
    b = int(q.K.shape[0])
    qp, _ = pad_queries(q, n)
    per = int(qp.K.shape[0]) // n
    maps_ = m if isinstance(m, list) else place_map(m, mesh)
    outs = []
    for i, d in enumerate(mesh.devices.flat):
        qi = jax.device_put(jax.tree.map(lambda x, i=i: x[i * per:(i + 1) * per], qp), d)
        outs.append(fn(maps_[i], qi))
    rows = NamedSharding(mesh, PartitionSpec(QUERY_AXIS))
    out = jax.tree.map(lambda *xs: jax.make_array_from_single_device_arrays(
        (n * xs[0].shape[0],) + xs[0].shape[1:], rows, list(xs)), *outs)
    return jax.tree.map(lambda x: x[:b], out)
