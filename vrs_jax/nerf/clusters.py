"""Scene division: K-means on reference camera centres, with shared border images.

N is the number of reference images (hundreds to a few thousands). The K-means is the
project's one (:func:`vrs_jax.kmeans.kmeans`: k-means++ and Lloyd in JAX, deterministic for a
fixed seed), run on the centred camera positions so that float32 keeps its precision in
world coordinates far from the origin; the rest is host-side numpy in float64.
The alternative division (``method="grid"``, :func:`grid_partition`) cuts the cameras'
bounding box into a uniform grid of equal cells, the baseline the paper compares K-means with.
"""

from __future__ import annotations

import itertools
import math
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


METHODS = ("kmeans", "grid")
KMEANS_RESTARTS = 8  # K-means++ seedings tried by cluster_cameras (the best one is kept)


def kmeans_best_of(points: np.ndarray, k: int, seed: int = 0, n_init: int = KMEANS_RESTARTS
                   ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`kmeans` from ``n_init`` seedings (seed, seed + 1, ...); the result of least
    within-cluster sum of squares wins (the first on ties), as sklearn's ``n_init``.

    One seeding can stop in a poor local optimum when clusters differ in size (e.g. a long
    hall beside small rooms: the hall split in two, two rooms merged).
    points: [N, D] -> centres [k, D], labels [N].
    """
    x = np.asarray(points, dtype=np.float64)
    if x.ndim != 2 or len(x) == 0:
        raise VrsError(f"K-means needs points [N, D] with N >= 1, got shape {x.shape}")
    if not 1 <= k <= len(x):
        raise VrsError(f"cannot make {k} clusters from {len(x)} reference images")
    mean = x.mean(axis=0)
    best, best_sse = None, math.inf
    for i in range(max(1, n_init)):
        centers = np.asarray(kmeans(x - mean, k, iters=KMEANS_ITERS, seed=seed + i),
                             np.float64) + mean
        labels = np.argmin(np.sum((x[:, None, :] - centers[None]) ** 2, axis=-1), axis=1)
        sse = float(np.sum((x - centers[labels]) ** 2))
        if best is None or sse < best_sse * (1.0 - 1e-12):
            best, best_sse = (centers, labels), sse
    return best


def grid_shape(extent: np.ndarray, k: int) -> tuple[int, ...]:
    """Cells per axis of a uniform grid of ``k`` cells over a box of ``extent`` [D] (metres).

    Among the factorisations of k into D integers (cells only along axes of positive
    extent), the one whose cells are closest to cubes (least log aspect ratio) wins; ties
    go to more cells along the longer axes.
    """
    extent = np.asarray(extent, np.float64)
    d = len(extent)
    best, best_cost = None, math.inf
    for shape in itertools.product(range(1, k + 1), repeat=d):
        if math.prod(shape) != k or any(n > 1 and e <= 0 for n, e in zip(shape, extent,
                                                                          strict=True)):
            continue
        cell = [e / n for n, e in zip(shape, extent, strict=True) if e > 0]
        cost = (math.log(max(cell) / min(cell)) if cell else 0.0)
        cost -= 1e-9 * float(np.dot(shape, extent))  # tie-break: cells along long axes
        if cost < best_cost:
            best, best_cost = shape, cost
    if best is None:
        raise VrsError(f"cannot cut the cameras' bounding box {extent.tolist()} into {k} "
                       "grid cells")
    return best


def grid_partition(points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """A uniform grid of ``k`` equal cells over the points' bounding box.

    The grid has cells along every axis of the box (:func:`grid_shape`; cameras at one
    height give a 2D grid in x, y). Its cell centres are the cluster centres, so the cells
    are exactly the Voronoi cells of the centres: assigning a point to its nearest centre
    (:func:`assign_to_clusters`, as for queries) picks the cell holding it.

    Args:
      points: [N, D] float; k >= 1.
    Returns:
      centres [k, D] (cell centres, row-major over the axes) and labels [N] int (the cell of
      each point; cells may be empty).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or len(points) == 0:
        raise VrsError(f"a grid needs points [N, D] with N >= 1, got shape {points.shape}")
    if k < 1:
        raise VrsError(f"cannot make {k} grid cells")
    lo, hi = points.min(axis=0), points.max(axis=0)
    extent = hi - lo
    shape = grid_shape(extent, k)
    size = np.where(extent > 0, extent / np.asarray(shape), 1.0)
    idx = np.clip(np.floor((points - lo) / size).astype(np.int64), 0, np.asarray(shape) - 1)
    labels = np.ravel_multi_index(tuple(idx.T), shape)
    cells = np.stack(np.unravel_index(np.arange(k), shape), axis=-1)  # [k, D]
    centers = lo + (cells + 0.5) * size
    return centers, labels


def cluster_cameras(camera_centers: np.ndarray, n_clusters: int, overlap: float = 0.2,
                    seed: int = 0, method: str = "kmeans") -> Clustering:
    """Divide reference cameras into clusters, sharing border images between neighbours.

    Image i (primary cluster a) also trains cluster b != a when
    ``|x_i - c_b| <= (1 + overlap) |x_i - c_a|``: an image about as close to a neighbouring
    centre as to its own lies near the border, and both NeRFs should see it so that neither
    has a blind strip along the border.

    Args:
      camera_centers: [N, 3] world camera centres of the reference images.
      n_clusters: C >= 1.
      overlap: relative margin (0: a partition, no sharing).
      method: "kmeans" (K-means++ centres) or "grid" (uniform grid cells,
        :func:`grid_partition`).
    Returns:
      Clustering. Raises VrsError if a cluster is empty (e.g. fewer distinct camera centres
      than clusters).
    """
    x = np.asarray(camera_centers, dtype=np.float64)
    if method not in METHODS:
        raise VrsError(f"unknown clustering method {method!r}; choose from {', '.join(METHODS)}")
    if method == "grid":
        centers, _ = grid_partition(x, n_clusters)
    else:
        centers, _ = kmeans_best_of(x, n_clusters, seed=seed)
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
