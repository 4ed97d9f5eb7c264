"""``localize(map, query, cfg)``: the stages of :mod:`stages` chained, fused or timed.

``localize`` is one jitted function per map shape and config (all queries of a map share one
compilation) and vmappable over a batch of queries. ``localize_timed`` runs the very same stage
functions one jit each, reporting wall time per stage; ``run_stages`` stops after a named stage
(the figures use it). All three are the one loop below over :data:`stages.STAGES`.
"""

from __future__ import annotations

import time

import jax
import numpy as np

from vrs_jax import geometry
from vrs_jax.errors import VrsError
from vrs_jax.localize import stages as st
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.localize.query import Query
from vrs_jax.localize.stages import LocalizeResult
from vrs_jax.maps import Map


def run_stages(m: Map, q: Query, cfg: LocalizeConfig, until: str | None = None,
               jitted: dict | None = None, times: dict | None = None,
               state: st.State | None = None, after: str | None = None) -> st.State:
    """Run the config's stages in order (up to and including ``until``); returns the state.

    ``jitted``: stage name -> compiled stage to call instead (``localize_timed``); ``times``:
    filled with wall seconds per stage (each stage's outputs waited for). ``state`` and
    ``after``: resume from a state holding the outputs of the stages up to ``after`` (e.g.
    reference descriptors taken from a cache instead of rendered).
    """
    st.check(m, cfg)
    s: st.State = dict(state or {})
    names = [n for n, _ in st.stages_for(cfg)]
    skip = names.index(after) + 1 if after is not None else 0
    for name, fn in st.stages_for(cfg)[skip:]:
        f = jitted[name] if jitted else fn
        t0 = time.perf_counter()
        out = f(m, q, cfg, s)
        if times is not None:
            jax.block_until_ready(out)
            times[name] = time.perf_counter() - t0
        s.update(out)
        if name == until:
            break
    return s


def _localize(m: Map, q: Query, cfg: LocalizeConfig) -> LocalizeResult:
    return run_stages(m, q, cfg)["result"]


_localize_jit = jax.jit(_localize, static_argnames=("cfg",))


def check_inputs(m: Map, q: Query, cfg: LocalizeConfig) -> None:
    """VrsError unless ``m`` is a Map, ``cfg`` a LocalizeConfig and ``q`` a Query whose K
    :func:`~vrs_jax.geometry.check_camera` accepts (when concrete: under jit/vmap the
    values are traced, and ``prepare_query`` has validated them)."""
    for arg, value, cls in (("map", m, Map), ("query", q, Query), ("cfg", cfg, LocalizeConfig)):
        if not isinstance(value, cls):
            raise VrsError(f"localize: {arg} must be a {cls.__name__}, got "
                           f"{type(value).__name__}")
    if not isinstance(q.K, jax.core.Tracer):
        geometry.check_camera(np.asarray(q.K), None, "localize query")


def localize(m: Map, q: Query, cfg: LocalizeConfig) -> LocalizeResult:
    """Localize one query: ``localize(map, query, cfg)`` (jitted; cfg static).

    Args:
      m: a :class:`vrs_jax.maps.Map` (``maps.load_map``).
      q: a :class:`~vrs_jax.localize.query.Query` (``prepare_query(map, image, K, dist, cfg)``).
      cfg: :class:`~vrs_jax.localize.config.LocalizeConfig` (``cfg.source``: "render" or "real").
    Returns:
      LocalizeResult. Compiled once per (map shapes, cfg); ``jax.vmap(localize, (None, 0,
      None))`` localizes a stacked batch of queries.
    Raises:
      VrsError for arguments of another type or a query whose K is not a camera
      (:func:`check_inputs`).
    """
    check_inputs(m, q, cfg)
    return _localize_jit(m, q, cfg)


localize._cache_size = _localize_jit._cache_size  # compilations so far (tests)

# Stages that render: a batch runs them one query after the other (lax.map), because under
# vmap the renderer's "skip chunks past the last valid keypoint" branch becomes a select that
# renders the padding too; every other stage is vmapped over the batch.
SEQUENTIAL_STAGES = ("render", "guided")


def _localize_stacked(m: Map, qs: Query, cfg: LocalizeConfig) -> LocalizeResult:
    st.check(m, cfg)
    s: st.State = {}
    for name, fn in st.stages_for(cfg):
        if name in SEQUENTIAL_STAGES and cfg.source == "render":
            out = jax.lax.map(lambda a, fn=fn: fn(m, a[0], cfg, a[1]), (qs, s))
        else:
            out = jax.vmap(lambda q, s_, fn=fn: fn(m, q, cfg, s_))(qs, s)
        s.update(out)
    return s["result"]


localize_stacked = jax.jit(_localize_stacked, static_argnames=("cfg",))
localize_stacked.__doc__ = """Localize a stacked batch of queries (leading axis B) on one device:
the same stages as :func:`localize`, vmapped, except that the rendering stages run query by
query so that no padding is rendered (see :data:`SEQUENTIAL_STAGES`). Returns a
LocalizeResult with a leading axis B, equal to ``jax.vmap(localize)``'s."""

_JITTED = {name: jax.jit(fn, static_argnames=("cfg",)) for name, fn in st.STAGES}
JITTED_STAGES = _JITTED  # one jitted function per stage (compiled once per map and config)


def localize_timed(m: Map, q: Query, cfg: LocalizeConfig
                   ) -> tuple[LocalizeResult, dict[str, float]]:
    """The same stages as :func:`localize`, one jit each, with wall seconds per stage
    (:data:`stages.STAGE_NAMES`; 0 for a stage the config skips). The first call of each stage
    includes its compilation: time a warm-up query first."""
    times = dict.fromkeys(st.STAGE_NAMES, 0.0)
    s = run_stages(m, q, cfg, jitted=_JITTED, times=times)
    return s["result"], times
