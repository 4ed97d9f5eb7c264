"""Localization settings: one frozen dataclass (hashable, so a static jit argument).

The authors released no code, so every value here except the patch size (15, the paper's) is
ours; each carries its reason.
"""

from __future__ import annotations

import dataclasses

from vrs_jax.errors import VrsError
from vrs_jax.features.descriptor import DescriptorConfig
from vrs_jax.features.keypoints import KeypointConfig
from vrs_jax.features.patches import PatchConfig
from vrs_jax.localize.pnp import PnPConfig

MODES = ("render", "gt")


@dataclasses.dataclass(frozen=True)
class LocalizeConfig:
    """Everything ``localize`` needs besides the maps and the query."""

    # "render": describe NeRF-rendered patches (VRS-NeRF); "gt": describe the real reference
    # patches stored in the baseline map (the hierarchical-method baseline).
    mode: str = "render"
    # Retrieved reference images per query. The paper (like hloc on 7Scenes) uses a handful;
    # each one costs K_max * P^2 rendered rays, so 5 balances recall and render time.
    top_k: int = 5
    # Query keypoints kept (by SIFT response), padded to this static count.
    query_max_keypoints: int = 1024
    keypoints: KeypointConfig = KeypointConfig(max_keypoints=1024)
    patches: PatchConfig = PatchConfig()
    descriptor: DescriptorConfig = DescriptorConfig()
    # Lowe ratio for query-to-rendered matching. Rendered patches are slightly blurrier than
    # real ones, so distances are larger overall; 0.9 with the mutual check keeps enough
    # matches while RANSAC removes the rest (measured on the synthetic scene).
    ratio: float = 0.9
    mutual: bool = True
    # Depth-guided rendering: sample each patch ray only within +-depth_margin (relative)
    # around its keypoint's 3D point depth, with narrow_samples samples (one MLP pass instead
    # of coarse + fine). The margin covers the depth change across a patch on oblique surfaces.
    depth_guided: bool = True
    depth_margin: float = 0.2
    narrow_samples: int = 24
    # Rays rendered per jitted chunk (bounds memory: chunk x samples x MLP width floats).
    render_chunk: int = 8192
    pnp: PnPConfig = PnPConfig()

    def __post_init__(self):
        if self.mode not in MODES:
            raise VrsError(f"localize mode must be one of {MODES}, got {self.mode!r}")
        if self.top_k < 1:
            raise VrsError("LocalizeConfig.top_k must be >= 1")


CONFIGS: dict[str, LocalizeConfig] = {
    # The paper's setting on a GPU: 15x15 patches, 2048 keypoints per reference image (set in
    # the EGM), top-5 retrieval, full coarse + fine sampling available (depth_guided False).
    "paper": LocalizeConfig(top_k=5, query_max_keypoints=2048,
                            keypoints=KeypointConfig(max_keypoints=2048)),
    # Two CPU cores: fewer retrieved images and query keypoints, depth-guided sampling.
    "cpu-small": LocalizeConfig(top_k=3, query_max_keypoints=1024, narrow_samples=16),
    # Unit tests.
    "test": LocalizeConfig(top_k=2, query_max_keypoints=256,
                           keypoints=KeypointConfig(max_keypoints=256),
                           patches=PatchConfig(size=9), narrow_samples=8, render_chunk=4096),
}


def get_config(name: str, **overrides) -> LocalizeConfig:
    """Named LocalizeConfig with optional field overrides; VrsError for an unknown name."""
    if name not in CONFIGS:
        raise VrsError(f"unknown localize config {name!r}; choose from {sorted(CONFIGS)}")
    return dataclasses.replace(CONFIGS[name], **overrides)
