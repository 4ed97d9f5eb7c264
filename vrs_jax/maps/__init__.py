"""The map: one object holding the EGM, the ILM and the map's own configuration by value.

    from vrs_jax import maps
    m = maps.load_map("maps/lego")          # a Map pytree (egm, ilm, config, source)
    maps.build_map(scene, "maps/lego", maps.get_config("cpu-small"))

Stage order: data -> features -> egm / nerf -> **maps** -> localize -> eval.
"""

from vrs_jax.maps.build import build_map, seed_from
from vrs_jax.maps.config import CONFIGS, MapConfig, get_config
from vrs_jax.maps.map import (
    Map,
    MapSource,
    load_map,
    load_map_for,
    map_bytes,
    read_stats,
    save_map,
)

__all__ = ["CONFIGS", "Map", "MapConfig", "MapSource", "build_map", "get_config", "load_map",
           "load_map_for", "map_bytes", "read_stats", "save_map", "seed_from"]
