"""Features stage: SIFT keypoints, canonical patches, the JAX descriptor, matching."""
