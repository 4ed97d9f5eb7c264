"""Scene division: K-means on reference camera centres, with shared border images.

N is the number of reference images (hundreds to a few thousands). The K-means is the
project's one (:func:`vrs_jax.kmeans.kmeans`: k-means++ and Lloyd in JAX, deterministic for a
fixed seed), run on the centred camera positions so that float32 keeps its precision in
world coordinates far from the origin; the rest is host-side numpy in float64.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vrs_jax.errors import VrsError
from vrs_jax.kmeans import kmeans

# Lloyd iterations: a few hundred camera positions converge in well under 100.
KMEANS_ITERS = 100


class Clustering(NamedTuple):
    """centers: [C, 3]; primary: [N] int cluster of each image (nearest centre);
    membership: [C, N] bool, images each cluster trains on (primary + shared borders)."""

    centers: np.ndarray
    primary: np.ndarray
    membership: np.ndarray


def cluster_cameras(camera_centers: np.ndarray, n_clusters: int, overlap: float = 0.2,
                    seed: int = 0) -> Clustering:
    """Divide reference cameras into clusters, sharing border images between neighbours.

    Image i (primary cluster a) also trains cluster b != a when
    ``|x_i - c_b| <= (1 + overlap) |x_i - c_a|``: an image about as close to a neighbouring
    centre as to its own lies near the border, and both NeRFs should see it so that neither
    has a blind strip along the border.

    Args:
      camera_centers: [N, 3] world camera centres of the reference images.
      n_clusters: C >= 1.
      overlap: relative margin (0: a partition, no sharing).
    Returns:
      Clustering. Raises VrsError if a cluster is empty (e.g. fewer distinct camera centres
      than clusters).
    """
    x = np.asarray(camera_centers, dtype=np.float64)
    if x.ndim != 2 or len(x) == 0:
        raise VrsError(f"camera centres must be [N, 3] with N >= 1, got shape {x.shape}")
    if not 1 <= n_clusters <= len(x):
        raise VrsError(f"cannot make {n_clusters} clusters from {len(x)} reference images")
    mean = x.mean(axis=0)
    centers = kmeans(x - mean, n_clusters, iters=KMEANS_ITERS, seed=seed) + mean
    dist = np.sqrt(np.sum((x[:, None, :] - centers[None]) ** 2, axis=-1))  # [N, C]
    labels = np.argmin(dist, axis=1)  # nearest centre
    check_nonempty(np.eye(n_clusters, dtype=bool)[:, labels])
    own = dist[np.arange(len(x)), labels]
    membership = (dist <= (1.0 + overlap) * own[:, None]).T  # [C, N]
    membership[labels, np.arange(len(x))] = True
    return Clustering(centers, labels.astype(np.int32), membership)


def check_nonempty(membership: np.ndarray) -> None:
    """Raise VrsError naming the first cluster with no images. membership: [C, N] bool."""
    counts = np.asarray(membership).sum(axis=1)
    empty = np.flatnonzero(counts == 0)
    if len(empty):
        raise VrsError(
            f"cluster {int(empty[0])} of {len(counts)} has no reference images "
            f"(fewer distinct camera positions than clusters?); use fewer clusters")


def assign_to_clusters(points: np.ndarray, centers: np.ndarray) -> np.ndarray:
    """Nearest cluster centre of each point (e.g. a query's camera centre). [M, 3] -> [M]."""
    d2 = np.sum((np.asarray(points)[:, None, :] - np.asarray(centers)[None]) ** 2, axis=-1)
    return np.argmin(d2, axis=1).astype(np.int32)
