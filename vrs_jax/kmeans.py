"""K-means (k-means++ seeding, then Lloyd), host-side numpy, deterministic for a seed.

The one k-means of the project, below every stage: the EGM's retrieval vocabulary
(:func:`vrs_jax.egm.retrieval.learn_vocabulary`, descriptors [M, 128]) and the NeRF scene
division (:func:`vrs_jax.nerf.clusters.cluster_cameras`, camera centres [N, 3]) both call
:func:`kmeans`. Computed in float64. Lloyd's assignment step takes either exact sums of
squared differences (``exact=True``, evaluated in row blocks so that [M, k, D] never has to
fit in memory at once; the camera clustering) or ``|x|^2 + |c|^2 - 2 x.c`` with one matrix
product (``exact=False``: ~20x faster for 128-dimensional descriptors; float64 keeps its
cancellation far below any distance that decides an assignment; the vocabulary).
"""

from __future__ import annotations

import numpy as np

from vrs_jax.errors import VrsError

# Elements of the [rows, k, D] difference block evaluated at once (128 MiB of float64).
_BLOCK_ELEMENTS = 1 << 24


def sq_dists(points: np.ndarray, centers: np.ndarray, exact: bool = True) -> np.ndarray:
    """Squared Euclidean distances [N, k] of float64 points [N, D] to centres [k, D].

    exact: sums of squared differences; else the expansion through one matrix product
    (clamped at 0).
    """
    if not exact:
        d2 = (np.sum(points * points, axis=1)[:, None] + np.sum(centers * centers, axis=1)[None]
              - 2.0 * (points @ centers.T))
        return np.maximum(d2, 0.0)
    n, k = len(points), len(centers)
    rows = max(1, _BLOCK_ELEMENTS // max(1, k * points.shape[1]))
    out = np.empty((n, k), np.float64)
    for s in range(0, n, rows):  # blocks of rows, one block for small inputs
        out[s:s + rows] = np.sum((points[s:s + rows, None, :] - centers[None]) ** 2, axis=-1)
    return out


def kmeans_pp_init(points: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """k-means++ seeding (Arthur & Vassilvitskii 2007): the first centre uniform, each next
    one drawn with probability proportional to the squared distance to the nearest centre
    chosen so far (uniform again when every point coincides with a centre).

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


def kmeans(points: np.ndarray, k: int, seed: int = 0, iters: int = 100, exact: bool = True
           ) -> tuple[np.ndarray, np.ndarray]:
    """Lloyd's K-means with k-means++ seeding.

    Stops early once the assignment no longer changes (the centres then no longer change
    either, so the result equals that of running all ``iters`` iterations).

    Args:
      points: [N, D] float.
      k: number of clusters (1 <= k <= N).
      seed: seed of the numpy generator used for the seeding.
      iters: maximum number of Lloyd iterations.
      exact: assignment distances as exact differences, else by the matrix-product
        expansion (see :func:`sq_dists`).
    Returns:
      centres [k, D] float64 and labels [N] int64. A cluster that ends up empty keeps its
      centre and has no label (callers check).
    Raises:
      VrsError for an empty or non-2D ``points`` or k outside [1, N].
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or len(points) == 0:
        raise VrsError(f"K-means needs points [N, D] with N >= 1, got shape {points.shape}")
    if not 1 <= k <= len(points):
        raise VrsError(f"cannot make {k} clusters from {len(points)} points")
    rng = np.random.default_rng(seed)
    centers = kmeans_pp_init(points, k, rng)
    labels = np.zeros(len(points), dtype=np.int64)
    for it in range(iters):
        new_labels = np.argmin(sq_dists(points, centers, exact), axis=1)
        if it > 0 and np.array_equal(new_labels, labels):
            break
        labels = new_labels
        for j in range(k):
            sel = labels == j
            if sel.any():
                centers[j] = points[sel].mean(axis=0)
    return centers, labels
