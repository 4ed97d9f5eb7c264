"""Scene division: K-means on reference camera centres, with shared border images.

Small and host-side (numpy): N is the number of reference images (hundreds to a few
thousands), so a plain Lloyd iteration is instantaneous. Deterministic for a fixed seed.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from vrs_jax.errors import VrsError


class Clustering(NamedTuple):
    """centers: [C, 3]; primary: [N] int cluster of each image (nearest centre);
    membership: [C, N] bool, images each cluster trains on (primary + shared borders)."""

    centers: np.ndarray
    primary: np.ndarray
    membership: np.ndarray


def kmeans_pp_init(points: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding: each new centre drawn with probability ~ squared distance.

    points: [N, D] -> centres [k, D].
    """
    n = len(points)
    centers = [points[rng.integers(n)]]
    d2 = np.sum((points - centers[0]) ** 2, axis=1)
    for _ in range(1, k):
        total = d2.sum()
        if total <= 0:  # all remaining points coincide with centres: pick any
            idx = int(rng.integers(n))
        else:
            idx = int(rng.choice(n, p=d2 / total))
        centers.append(points[idx])
        d2 = np.minimum(d2, np.sum((points - points[idx]) ** 2, axis=1))
    return np.stack(centers)


def kmeans(points: np.ndarray, k: int, seed: int = 0, iters: int = 100
           ) -> tuple[np.ndarray, np.ndarray]:
    """Lloyd's K-means with k-means++ seeding.

    Args:
      points: [N, D] float.
      k: number of clusters (1 <= k <= N).
    Returns:
      centres [k, D] and labels [N] int. A cluster that ends up empty keeps its centre and
      has no label (callers check; see :func:`cluster_cameras`).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or len(points) == 0:
        raise VrsError(f"K-means needs points [N, D] with N >= 1, got shape {points.shape}")
    if not 1 <= k <= len(points):
        raise VrsError(f"cannot make {k} clusters from {len(points)} reference images")
    rng = np.random.default_rng(seed)
    centers = kmeans_pp_init(points, k, rng)
    labels = np.zeros(len(points), dtype=np.int64)
    for it in range(iters):
        d2 = np.sum((points[:, None, :] - centers[None]) ** 2, axis=-1)  # [N, k]
        new_labels = np.argmin(d2, axis=1)
        if it > 0 and np.array_equal(new_labels, labels):
            break
        labels = new_labels
        for j in range(k):
            sel = labels == j
            if sel.any():
                centers[j] = points[sel].mean(axis=0)
    return centers, labels


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
    centers, labels = kmeans(x, n_clusters, seed=seed)
    check_nonempty(np.eye(n_clusters, dtype=bool)[:, labels])
    dist = np.sqrt(np.sum((x[:, None, :] - centers[None]) ** 2, axis=-1))  # [N, C]
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
