"""Descriptor matching in JAX with fixed shapes and masks: mutual nearest neighbour + ratio test.

Distances are Euclidean (for the unit RootSIFT descriptors of descriptor.py that is the
Hellinger distance of the histograms). Padding rows are excluded by masks, so a padded batch
of images matches without retracing.

Ratio test (Lowe 2004): a query keeps its nearest reference only if
``d1 < ratio * d2``, d2 being the distance to the second nearest VALID reference. When fewer
than two references are valid (including Nr < 2 by shape), there is no second neighbour:
d2 is +inf and the test passes, i.e. the ratio test is off and only mutuality (and the
optional max_dist) decide. With no valid reference at all nothing matches.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

# Lowe's value for SIFT (rejects 90% of false matches while keeping 95% of correct ones in
# his experiments); with the mutual check on top it is on the permissive side, which suits
# rendered patches whose descriptors are noisier than real ones. Callers may tune it.
DEFAULT_RATIO = 0.8


def pairwise_distances(a, b):
    """[Na, D], [Nb, D] -> [Na, Nb] Euclidean distances (clamped >= 0 before the sqrt)."""
    a = jnp.asarray(a, jnp.float32)
    b = jnp.asarray(b, jnp.float32)
    d2 = (jnp.sum(a * a, -1)[:, None] + jnp.sum(b * b, -1)[None, :]
          - 2.0 * jnp.matmul(a, b.T, precision="highest"))
    return jnp.sqrt(jnp.maximum(d2, 0.0))


def planar_sq_distances(a, b):
    """[Na, 2], [Nb, 2] -> [Na, Nb] squared distances between image points.

    Written per coordinate, not as a sum over a trailing axis of 2: XLA on CPU lowers the
    latter (broadcast, square, reduce over 2) to a kernel about ten times slower than these
    two elementwise terms (1024 x 1280 points: ~24 ms against ~2 ms on two cores)."""
    a = jnp.asarray(a, jnp.float32)
    b = jnp.asarray(b, jnp.float32)
    dx = a[:, None, 0] - b[None, :, 0]
    dy = a[:, None, 1] - b[None, :, 1]
    return dx * dx + dy * dy


def first_argmin(x, axis: int):
    """``jnp.argmin(x, axis)`` as int32 (ties to the lowest index; a slice of +inf gives 0),
    written as a min and a min of the indices where it is reached: XLA on CPU lowers argmin
    to a (value, index) pair reduction ~6x slower than these two plain ones (a 1024 x 1280
    distance matrix: 6 ms against 1 ms on two cores). A slice holding NaN gives its last
    index (argmin: the NaN's), still a valid index."""
    x = jnp.asarray(x)
    axis = axis % x.ndim
    n = x.shape[axis]
    lo = jnp.min(x, axis=axis, keepdims=True)
    at = jnp.arange(n, dtype=jnp.int32).reshape([n if a == axis else 1 for a in range(x.ndim)])
    return jnp.minimum(jnp.min(jnp.where(x == lo, at, n), axis=axis), n - 1)


@functools.partial(jax.jit, static_argnames="mutual")
def match(desc_q, mask_q, desc_r, mask_r, ratio: float | None = DEFAULT_RATIO,
          mutual: bool = True, max_dist: float | None = None):
    """Match query descriptors to reference descriptors.

    Args:
      desc_q: [Nq, D] query descriptors.  mask_q: [Nq] bool, False rows never match.
      desc_r: [Nr, D] reference descriptors.  mask_r: [Nr] bool, False rows are never chosen.
      ratio: Lowe's ratio threshold on distances (d1 < ratio * d2); None disables the test
        (then static: it changes the traced program). See the module docstring for Nr < 2.
      mutual: also require that q is the nearest valid query of its reference (static).
      max_dist: optional absolute bound on d1 (static None or a float).
    Returns:
      idx: [Nq] int32 index into the references of each query's nearest valid reference
        (0 when it has none).
      valid: [Nq] bool, the match passes every test (and both rows are unmasked).
      dist: [Nq] float32 distance to that nearest reference (+inf when the query is masked
        or no reference is valid).
    Ties go to the lowest index (numpy's argmin rule). Jitted (mutual static; ratio/max_dist
    traced floats or None), and usable inside other jitted or vmapped functions.
    """
    desc_q = jnp.asarray(desc_q, jnp.float32)
    desc_r = jnp.asarray(desc_r, jnp.float32)
    mask_q = jnp.asarray(mask_q, bool)
    mask_r = jnp.asarray(mask_r, bool)
    nq, nr = desc_q.shape[0], desc_r.shape[0]
    if nr == 0 or nq == 0:  # static shapes: nothing to match
        return (jnp.zeros((nq,), jnp.int32), jnp.zeros((nq,), bool),
                jnp.full((nq,), jnp.inf, jnp.float32))
    inf = jnp.float32(jnp.inf)
    d = pairwise_distances(desc_q, desc_r)
    d = jnp.where(mask_q[:, None] & mask_r[None, :], d, inf)
    idx = first_argmin(d, 1)
    d1 = jnp.min(d, axis=1)
    valid = jnp.isfinite(d1)
    if ratio is not None:
        if nr >= 2:
            d_wo = jnp.where(jnp.arange(nr)[None, :] == idx[:, None], inf, d)
            d2 = jnp.min(d_wo, axis=1)
        else:
            d2 = jnp.full((nq,), inf)
        # d2 == inf (fewer than two valid references): the test passes, see docstring
        valid &= (d1 < ratio * d2) | jnp.isinf(d2)
    if mutual:
        back = first_argmin(d, 0)  # [Nr] nearest valid query
        valid &= back[idx] == jnp.arange(nq, dtype=jnp.int32)
    if max_dist is not None:
        valid &= d1 <= max_dist
    return idx, valid, d1


match_jit = match  # backwards-compatible name; ``match`` itself is jitted


def guided_match(uv_q, desc_q, mask_q, uv_r, desc_r, mask_r, group_r, radius: float,
                 ratio: float | None = DEFAULT_RATIO):
    """Matching with a geometric prior: each query keypoint considers only the references
    predicted within ``radius`` pixels of it (their projection under a pose estimate).

    Mutual nearest neighbour among those candidates, and the ratio test against the nearest
    candidate of another group (references of one group are the same 3D point seen from
    several images, not rivals).

    Args:
      uv_q: [Nq, 2] query keypoint positions; desc_q: [Nq, D]; mask_q: [Nq] bool.
      uv_r: [Nr, 2] predicted reference positions; desc_r: [Nr, D]; mask_r: [Nr] bool;
      group_r: [Nr] int group id (the 3D point).
      radius: search radius in pixels; ratio: Lowe's ratio (None: off; static).
    Returns:
      idx: [Nq] int32 chosen reference per query (0 when none); valid: [Nq] bool;
      dist: [Nq] descriptor distance (+inf when none).
    """
    inf = jnp.float32(jnp.inf)
    uv_q = jnp.asarray(uv_q, jnp.float32)
    uv_r = jnp.asarray(uv_r, jnp.float32)
    near = planar_sq_distances(uv_q, uv_r) < jnp.float32(radius) ** 2
    ok = near & jnp.asarray(mask_q, bool)[:, None] & jnp.asarray(mask_r, bool)[None, :]
    d = jnp.where(ok, pairwise_distances(desc_q, desc_r), inf)  # [Nq, Nr]
    idx = first_argmin(d, 1)
    d1 = jnp.min(d, axis=1)
    valid = jnp.isfinite(d1)
    if ratio is not None:
        rival = group_r[None, :] != group_r[idx][:, None]
        d2 = jnp.min(jnp.where(rival, d, inf), axis=1)
        valid &= (d1 < ratio * d2) | jnp.isinf(d2)
    back = first_argmin(d, 0)  # [Nr] nearest candidate query
    valid &= back[idx] == jnp.arange(d.shape[0], dtype=jnp.int32)
    return idx, valid, d1
