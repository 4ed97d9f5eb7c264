"""The COLMAP SIFT reference localizer the accuracy figures are compared against.

A plain hierarchical structure-based localizer built from pycolmap alone (no NeRF, no EGM):
COLMAP SIFT on the reference images, exhaustive matching with geometric verification,
points triangulated with the known reference poses; each query is matched against the map
images, its matches are lifted to 2D-3D correspondences and its pose is estimated with
LO-RANSAC + refinement (:mod:`vrs_jax.reference.sift`).
"""

from vrs_jax.reference.sift import (
    SiftMap,
    SiftReferenceConfig,
    SiftResult,
    build_sift_map,
    localize_sift,
    match_sift,
    result_arrays,
    sift_map_bytes,
    unique_correspondences,
)

__all__ = ["SiftMap", "SiftReferenceConfig", "SiftResult", "build_sift_map", "localize_sift",
           "match_sift", "result_arrays", "sift_map_bytes", "unique_correspondences"]
