"""Host helper: keypoints + canonical patches + descriptors of one image, and named configs.

``extract_features(gray, cfg)`` runs OpenCV's SIFT detector on the host, then the jitted JAX
path patches -> describe. The keypoint count is padded to a power of two before the JAX part,
so a sequence of images of one size compiles a handful of programs, not one per image.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from vrs_jax.errors import VrsError
from vrs_jax.features.descriptor import DescriptorConfig, describe
from vrs_jax.features.keypoints import KeypointConfig, detect
from vrs_jax.features.patches import PatchConfig, extract_patches
from vrs_jax.padding import padded_size


@dataclasses.dataclass(frozen=True)
class FeatureConfig:
    """Detector, patch and descriptor settings together (hashable)."""

    keypoints: KeypointConfig = KeypointConfig()
    patches: PatchConfig = PatchConfig()
    descriptor: DescriptorConfig = DescriptorConfig()


CONFIGS: dict[str, FeatureConfig] = {
    # The paper's patch size (15) on our canonical (scaled, rotated) grid; 2048 keypoints.
    "paper": FeatureConfig(),
    # Aachen: the paper uses 31 x 31 patches there (same support, finer sampling).
    "aachen": FeatureConfig(keypoints=KeypointConfig(max_keypoints=4096),
                            patches=PatchConfig(size=31)),
    # Paper-literal patches: whole pixels, axis-aligned, no scale or rotation (ablation).
    "literal": FeatureConfig(patches=PatchConfig(mode="literal")),
    # Laptop CPU: fewer keypoints than the paper (matching is O(Nq * Nr), rendering
    # O(K * P^2)); the EGM keeps at most 256 of them per reference (EGMConfig.k_max). 1024
    # detected, as many as a query keeps (LocalizeConfig.query_keypoints): with 512 the phone
    # walk's references linked 134 keypoints each to a 3D point, too few near ones to fix a
    # translation along the optical axis (real patches 90.3% / 96.8% within 1% / 2% of the
    # scale, its held-out leg 20% / 36%); with 1024 they link 214 and real patches reach
    # 100% / 100% (the leg 28% / 50%), fox, scan24, fern and lego unchanged at 1% and 2%
    # (README, "Keypoints detected per reference").
    "cpu-small": FeatureConfig(keypoints=KeypointConfig(max_keypoints=1024)),
    # Unit tests: tiny budget, small patches.
    "test": FeatureConfig(keypoints=KeypointConfig(max_keypoints=128),
                          patches=PatchConfig(size=9)),
}


def get_config(name: str) -> FeatureConfig:
    """Named FeatureConfig; VrsError listing the names for an unknown one."""
    if name not in CONFIGS:
        raise VrsError(f"unknown feature config {name!r}; choose from {sorted(CONFIGS)}")
    return CONFIGS[name]


def describe_keypoints(image, kp, patch_cfg: PatchConfig = PatchConfig(),
                       desc_cfg: DescriptorConfig = DescriptorConfig()):
    """Descriptors of keypoints read from a real grey image (pure JAX, jittable).

    Args:
      image: [H, W] float32 grey image.  kp: [K, 4] keypoints.
    Returns:
      [K, D] unit descriptors of the keypoints' patches (patches.extract_patches ->
      descriptor.describe): the "GT patches" path, the same one rendered patches take.
    """
    return describe(extract_patches(image, kp, patch_cfg), desc_cfg)


# Two compiled programs (extract_patches and describe are each jitted), not one: with both
# in one XLA program, 1,024 keypoints of a 480 x 270 image took 57 ms on 2 CPU cores against
# 32 ms as two programs (the fused one's gathers and gradient ops ran ~3x slower than either
# part alone; an optimization_barrier between them did not help). Same descriptors.
describe_keypoints_jit = describe_keypoints


def extract_features(gray, cfg: FeatureConfig | KeypointConfig | None = None,
                     patch_cfg: PatchConfig | None = None,
                     desc_cfg: DescriptorConfig | None = None, return_response: bool = False):
    """Keypoints and descriptors of a grey image (host function).

    Call either as ``extract_features(gray, feature_cfg)`` or
    ``extract_features(gray, kp_cfg, patch_cfg, desc_cfg)``; missing parts take defaults.

    Args:
      gray: [H, W] float grey image in [0, 1] (images.read_gray) or uint8.
    Returns:
      keypoints [K, 4] float32 (keypoints.detect), descriptors [K, D] float32 numpy arrays;
      K may be 0 (then shapes [0, 4] and [0, D]); with return_response also response [K].
    """
    if isinstance(cfg, FeatureConfig):
        kp_cfg = cfg.keypoints
        patch_cfg = patch_cfg or cfg.patches
        desc_cfg = desc_cfg or cfg.descriptor
    else:
        kp_cfg = cfg or KeypointConfig()
        patch_cfg = patch_cfg or PatchConfig()
        desc_cfg = desc_cfg or DescriptorConfig()
    g = np.asarray(gray)
    kp, resp = detect(g, kp_cfg, return_response=True)
    if g.dtype == np.uint8:
        g = g.astype(np.float32) / 255.0
    k = kp.shape[0]
    if k == 0:
        desc = np.zeros((0, desc_cfg.dim), np.float32)
    else:
        pad = np.zeros((padded_size(k), 4), np.float32)
        pad[:k] = kp
        pad[k:, 2] = 1.0  # harmless dummy keypoints (scale 1 at the origin)
        d = describe_keypoints_jit(jnp.asarray(g, jnp.float32), jnp.asarray(pad),
                                   patch_cfg, desc_cfg)
        desc = np.asarray(d)[:k]
    return (kp, desc, resp) if return_response else (kp, desc)
