"""Retry a doubtful query with the next references by appearance.

    result, attempt = localize_with_retries(m, q, cfg, once)

``once(c)`` localizes the prepared query with config ``c`` (the jitted ``localize``, the
timed stages or the descriptor cache's path). The first attempt uses ``cfg``. While the
best result so far is not "localized" (:mod:`~vrs_jax.localize.confidence`: uncertain, or
failed) and the map has references left, attempt ``a`` (1 .. ``cfg.retries``) retrieves the
next ``top_k`` by global descriptor (ranks ``a * top_k`` on: ``retrieval_offset``). A query
whose top references show another place, or only far points of the right one, gets a second
look from other views, as hloc tries its retrieved images' covisibility clusters in turn.
The result with the highest confidence is kept (the earliest on ties); its ``n_rendered``
counts the patches every attempt rendered (what the query cost), ``retrieved`` the
references of the attempt kept, and ``attempt_shift`` how far its camera centre is from the
farthest PnP pose of the other attempts: the confidence flags a pose whose attempts put the
camera in different places (``ConfidenceConfig.max_attempt_shift``), since keeping the more
confident of two disagreeing poses is a guess.

Host code around the jitted stages: each attempt's config is a static argument, so a map
compiles once per attempt index used.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import jax
import numpy as np

from vrs_jax.geometry import pose_errors
from vrs_jax.localize.confidence import map_scale, one_confidence
from vrs_jax.localize.config import LocalizeConfig
from vrs_jax.localize.stages import LocalizeResult
from vrs_jax.maps import Map


def attempt_config(cfg: LocalizeConfig, a: int) -> LocalizeConfig:
    """The config of attempt ``a`` (0: ``cfg`` itself): the references ranked ``a *
    top_k`` further down, no retries of its own."""
    if a == 0:
        return cfg
    return dataclasses.replace(cfg, retrieval_offset=cfg.retrieval_offset + a * cfg.top_k,
                               retries=0)


def attempts(m: Map, cfg: LocalizeConfig) -> int:
    """How many attempts ``cfg`` allows on map ``m``: 1 + retries, fewer where the map runs
    out of references to retrieve."""
    left = m.egm.num_images - cfg.retrieval_offset  # references at and after the offset
    return 1 + min(cfg.retries, max(0, -(-left // cfg.top_k) - 1))


def attempt_shift(kept: LocalizeResult, others: list[LocalizeResult]) -> float:
    """Camera-centre distance (map units) from ``kept``'s pose to the farthest PnP pose (a
    success, not the fallback) among ``others``; NaN when none has one (numpy results)."""
    f64 = lambda x: np.asarray(x, np.float64)  # noqa: E731
    d = [float(pose_errors(f64(kept.R), f64(kept.t), f64(r.R), f64(r.t))[0])
         for r in others if bool(r.success) and not bool(r.fallback)]
    return max(d) if d else float("nan")


def localize_with_retries(m: Map, q, cfg: LocalizeConfig,
                          once: Callable[[LocalizeConfig], LocalizeResult],
                          scale: float | None = None) -> tuple[LocalizeResult, int]:
    """Localize with retries (module docstring).

    Args:
      m: the map; q: unused here but by ``once`` (kept for the call sites' symmetry).
      cfg: the query config (``cfg.retries``; 0: one attempt).
      once: ``once(config) -> LocalizeResult`` for this query.
      scale: the map's scene scale (:func:`~vrs_jax.localize.confidence.map_scale`).
    Returns:
      (result as numpy values, the attempt it came from: 0 the first retrieval).
    """
    best = jax.device_get(once(cfg))
    n = attempts(m, cfg)
    if n == 1:
        return best, 0
    scale = map_scale(m) if scale is None else scale
    conf, verdict = one_confidence(best, scale, cfg.confidence)
    kept, made = 0, [best]
    for a in range(1, n):
        if verdict == "localized":
            break
        r = jax.device_get(once(attempt_config(cfg, a)))
        made.append(r)
        c, v = one_confidence(r, scale, cfg.confidence)
        if c > conf:
            best, conf, verdict, kept = r, c, v, a
    rendered = sum(int(r.n_rendered) for r in made)
    shift = attempt_shift(best, made[:kept] + made[kept + 1:]) if len(made) > 1 else np.nan
    return best.replace(n_rendered=np.asarray(rendered, np.int32),
                        attempt_shift=np.asarray(shift, np.float32)), kept
