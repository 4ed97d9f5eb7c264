"""MapConfig: everything that defines how a map is built, held by value inside the map.

A map stores all of these values (not the config's name) and is read back from them, so
editing a named config never changes how an existing map is read. Query-time settings
(retrieval, matching, rendering samples, PnP) are not here: see
:class:`vrs_jax.localize.config.LocalizeConfig`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from vrs_jax.egm import build as egm_build
from vrs_jax.errors import VrsError
from vrs_jax.nerf import config as nerf_config


@dataclasses.dataclass(frozen=True)
class MapConfig:
    """The EGM (keypoints, patches, descriptor, pairs, triangulation, retrieval, K_max) and the
    ILM (NeRF field, clusters, training length ``nerf.max_steps``)."""

    name: str
    egm: egm_build.EGMConfig
    nerf: nerf_config.NerfConfig

    @property
    def features(self):
        """Keypoint, patch and descriptor settings (shared by the map and its queries)."""
        return self.egm.features


CONFIGS: dict[str, MapConfig] = {
    # The paper's scale (a GPU job): 2048 SIFT keypoints detected and 1024 kept per image,
    # 15x15 patches, an 8x256 Mip-NeRF with 128 + 128 samples, 200k steps.
    "paper": MapConfig("paper", egm_build.get_config("paper"), nerf_config.get_config("paper")),
    # Two CPU cores (the demo): 1024 keypoints detected and 256 kept, 15x15 patches, a
    # 16-level hash grid with a 2x64 MLP, 32 + 32 samples, 4000 steps (7-8 minutes).
    "cpu-small": MapConfig("cpu-small", egm_build.get_config("cpu-small"),
                           nerf_config.get_config("cpu-small")),
    # Tests and `demo --quick`: 128 keypoints detected and 64 kept, 9x9 patches, a 3x64 NeRF,
    # 800 steps (about a minute per map on 2 cores).
    "test": MapConfig("test", egm_build.get_config("test"), nerf_config.get_config("test")),
}


def get_config(name: str, **nerf_overrides: Any) -> MapConfig:
    """The named MapConfig, with NeRF field overrides (``get_config("cpu-small",
    n_clusters=4, max_steps=8000)``); VrsError for an unknown name or field."""
    if name not in CONFIGS:
        raise VrsError(f"unknown map config {name!r}; choose from {sorted(CONFIGS)}")
    cfg = CONFIGS[name]
    if nerf_overrides:
        cfg = dataclasses.replace(cfg, nerf=nerf_config.get_config(cfg.nerf.name,
                                                                   **nerf_overrides))
    return cfg
