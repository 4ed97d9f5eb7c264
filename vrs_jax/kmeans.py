"""K-means in JAX: k-means++ seeding then Lloyd iterations, deterministic for a seed.

The one k-means of the project, below every stage: the EGM's retrieval vocabulary
(:func:`vrs_jax.egm.retrieval.learn_vocabulary`, descriptors [M, 128]) and the NeRF scene
division (:func:`vrs_jax.nerf.clusters.cluster_cameras`, camera centres [N, 3]) both call
:func:`kmeans`. Seeding and Lloyd iterations are jitted ``lax.fori_loop`` loops in float32;
:func:`sq_dists` is also the nearest-word assignment of the VLAD.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax.errors import VrsError


def sq_dists(x, c):
    """[M, D], [k, D] -> [M, k] squared Euclidean distances (>= 0), one matrix product."""
    d2 = (jnp.sum(x * x, -1)[:, None] + jnp.sum(c * c, -1)[None, :]
          - 2.0 * jnp.matmul(x, c.T, precision="highest"))
    return jnp.maximum(d2, 0.0)


@partial(jax.jit, static_argnames=("k",))
def kmeans_pp_init(key, x, k: int):
    """k-means++ seeding (Arthur & Vassilvitskii 2007).

    Args:
      key: PRNG key.  x: [M, D] points (M >= 1).  k: number of centres.
    Returns:
      [k, D] centres: the first uniform, each next one drawn with probability proportional
      to the squared distance to the nearest centre chosen so far.
    """
    m = x.shape[0]
    k0, key = jax.random.split(key)
    first = x[jax.random.randint(k0, (), 0, m)]
    centers = jnp.zeros((k, x.shape[1]), x.dtype).at[0].set(first)
    d2 = jnp.sum((x - first) ** 2, -1)

    def body(i, state):
        centers, d2, key = state
        key, sub = jax.random.split(key)
        # all-zero d2 (fewer distinct points than k): fall back to uniform sampling
        logits = jnp.where(jnp.sum(d2) > 0, jnp.log(jnp.maximum(d2, 1e-30)), 0.0)
        j = jax.random.categorical(sub, logits)
        c = x[j]
        centers = centers.at[i].set(c)
        d2 = jnp.minimum(d2, jnp.sum((x - c) ** 2, -1))
        return centers, d2, key

    centers, _, _ = jax.lax.fori_loop(1, k, body, (centers, d2, key))
    return centers


@partial(jax.jit, static_argnames=("iters",))
def lloyd(x, centers, iters: int):
    """Lloyd iterations: [M, D] points, [k, D] initial centres -> [k, D] centres.

    An empty cluster keeps its previous centre.
    """
    k = centers.shape[0]

    def body(_, c):
        a = jnp.argmin(sq_dists(x, c), axis=1)
        onehot = jax.nn.one_hot(a, k, dtype=x.dtype)  # [M, k]
        s = jnp.matmul(onehot.T, x, precision="highest")
        n = onehot.sum(0)[:, None]
        return jnp.where(n > 0, s / jnp.maximum(n, 1.0), c)

    return jax.lax.fori_loop(0, iters, body, centers)


def kmeans(x: np.ndarray, k: int, iters: int = 25, seed: int = 0) -> np.ndarray:
    """k-means++ then ``iters`` Lloyd iterations: [M, D] -> [k, D] float32 centres.

    Deterministic for a seed (``jax.random.PRNGKey(seed)``). A cluster that ends up empty
    keeps its seed; callers that need every cluster populated check (see
    :func:`vrs_jax.nerf.clusters.cluster_cameras`).

    Raises:
      VrsError for an empty or non-2D ``x`` or k outside [1, M].
    """
    x = jnp.asarray(x, jnp.float32)
    if x.ndim != 2 or x.shape[0] < 1:
        raise VrsError(f"k-means needs a non-empty [M, D] array, got shape {tuple(x.shape)}")
    if not 1 <= k <= x.shape[0]:
        raise VrsError(f"cannot make {k} clusters from {x.shape[0]} points")
    c0 = kmeans_pp_init(jax.random.PRNGKey(seed), x, k)
    return np.asarray(lloyd(x, c0, iters))
