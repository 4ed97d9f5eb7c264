"""Localization: query preparation, the stages (retrieval, patch rendering, description,
matching, PnP), and ``localize(map, query, cfg)``.

    from vrs_jax import maps, localize
    m = maps.load_map("maps/lego")
    cfg = localize.get_config("cpu-small")            # cfg.source: "render" or "real"
    q = localize.prepare_query(m, gray, K, dist, cfg)
    result = localize.localize(m, q, cfg)

    loc = localize.Localizer("maps/lego", "cpu-small")   # load once, compile once
    result = loc.localize_image("query.png", K, dist)
    loc.failure_reason(result)       # why it has no PnP pose (e.g. a blank image), or None
    frames = loc.track(paths, K, dist)                    # a video stream: tracking
"""

from vrs_jax.localize.config import CONFIGS, LocalizeConfig, TrackConfig, get_config
from vrs_jax.localize.localizer import Localizer
from vrs_jax.localize.query import Query, prepare_query, stack_queries
from vrs_jax.localize.run import localize, localize_stacked, localize_timed, run_stages
from vrs_jax.localize.stages import STAGE_NAMES, LocalizeResult, failure_reason

__all__ = ["CONFIGS", "STAGE_NAMES", "LocalizeConfig", "LocalizeResult", "Localizer", "Query",
           "TrackConfig", "failure_reason",
           "get_config", "localize", "localize_stacked", "localize_timed", "prepare_query",
           "run_stages", "stack_queries"]
