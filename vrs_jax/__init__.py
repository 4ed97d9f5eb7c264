"""vrs-jax: visual relocalization with sparse neural radiance fields, in functional JAX.

Stages live in sub-packages named after them:

- ``vrs_jax.data``      dataset readers, the Scene structure, the embedded synthetic scene
- ``vrs_jax.features``  keypoints, canonical patches, the JAX descriptor, matching
- ``vrs_jax.egm``       the explicit geometric map: triangulation, retrieval, save/load
- ``vrs_jax.nerf``      the implicit learning map: Mip-NeRF per cluster, training, rendering
- ``vrs_jax.localize``  patch rays, patch rendering, PnP, the jitted ``localize``
- ``vrs_jax.eval``      pose errors, recall tables, results files
"""

from vrs_jax.errors import VrsError

__all__ = ["VrsError"]
__version__ = "0.1.0"
