"""Global retrieval without downloaded weights: VLAD over our own local descriptors, in JAX.

* Vocabulary: k-means on descriptors sampled from the reference images -- k-means++
  initialisation (fixed seed) and Lloyd iterations, both in jitted ``lax.fori_loop`` loops
  (the project's one k-means, :func:`vrs_jax.kmeans.kmeans`).
* VLAD (Jegou et al. 2010): each descriptor's residual to its nearest word is summed per
  word; then intra-normalisation (each word's block L2-normalised, Arandjelovic & Zisserman
  2013: damps bursty words), power normalisation (signed square root) and a global L2
  normalisation. Padding rows are excluded by a mask, so a batch of images vmaps.
* Optional PCA-whitening learned on the reference VLADs (then L2 again).
* Retrieval: cosine similarity = dot product of unit vectors, top-k with ``lax.top_k``, jitted.

The same host helper :func:`global_descriptor` serves reference images (at mapping time)
and queries (at localization time), so both sides are computed identically.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import Any, ClassVar

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from vrs_jax.errors import VrsError
from vrs_jax.kmeans import kmeans, sq_dists
from vrs_jax.padding import padded_size


@dataclasses.dataclass(frozen=True)
class RetrievalConfig:
    """VLAD vocabulary and normalisation settings."""

    # Visual words. VLAD's dimension is n_words * D (16 * 128 = 2048): small enough that the
    # global descriptor (stored as float16, 4 KB per image) stays a minor part of the EGM,
    # large enough to separate the places of a room-sized scene. Jegou et al. use 16-256.
    n_words: int = 16
    # Lloyd iterations after k-means++; k-means on ~1e4-1e5 descriptors converges in ~20.
    kmeans_iters: int = 25
    # Descriptors sampled (uniformly, fixed seed) from all reference images to learn words.
    max_train_descriptors: int = 50_000
    seed: int = 0
    # Power normalisation exponent (0.5 = signed square root, Perronnin et al. 2010).
    power: float = 0.5
    # PCA-whitening to this many dimensions (at most n_reference - 1); None: off. With the
    # few dozen references of a small scene the whitening is estimated from too few vectors
    # to help, so it is off by default.
    pca_dim: int | None = None
    # Added to the PCA eigenvalues before whitening (regularises the smallest directions).
    whiten_eps: float = 1e-6
    # Local descriptors PCA-whitened to this many dimensions before VLAD (learned on the
    # sampled reference descriptors, as Jegou et al. 2012 reduce SIFT to 64-D); None: the raw
    # descriptors. At a fixed VLAD size (n_words * local_dim) it buys more visual words:
    # the words then separate places rather than descriptor directions that carry little.
    local_dim: int | None = None
    # Fields added after maps were written: such a map meant these values (configio).
    ADDED_FIELDS: ClassVar[dict[str, Any]] = {"local_dim": None}

    def __post_init__(self):
        if self.n_words < 1 or (self.local_dim is not None and self.local_dim < 1) \
                or (self.pca_dim is not None and self.pca_dim < 1):
            raise VrsError("RetrievalConfig.n_words, local_dim and pca_dim must be >= 1")


@flax.struct.dataclass
class Vocabulary:
    """What a query needs to compute a global descriptor comparable to the references'.

    Attributes:
      centers: [k, D] float32 visual words (D: the local descriptors' dimension after the
        local projection, if any).
      pca_mean: [k * D] float32 or None.
      pca_proj: [k * D, G] float32 whitening projection, or None (then G = k * D).
      power: power-normalisation exponent (static).
      local_mean: [D0] float32 or None.
      local_proj: [D0, D] float32 whitening of the local descriptors (D0: theirs), or None
        (then D0 = D).
    """

    centers: jax.Array
    pca_mean: jax.Array | None = None
    pca_proj: jax.Array | None = None
    power: float = flax.struct.field(pytree_node=False, default=0.5)
    local_mean: jax.Array | None = None
    local_proj: jax.Array | None = None

    @property
    def input_dim(self) -> int:
        """Dimension D0 of the local descriptors the vocabulary takes."""
        if self.local_proj is not None:
            return int(self.local_proj.shape[0])
        return int(self.centers.shape[1])

    @property
    def dim(self) -> int:
        """Dimension G of the global descriptors."""
        if self.pca_proj is not None:
            return int(self.pca_proj.shape[1])
        return int(self.centers.shape[0] * self.centers.shape[1])


# ----------------------------------------------------------------------------- VLAD


def vlad(desc, mask, centers, power: float = 0.5):
    """VLAD of one image (pure JAX; vmap over images for a batch).

    Args:
      desc: [K, D] local descriptors.  mask: [K] bool (padding rows False).
      centers: [k, D] visual words.  power: signed power-normalisation exponent.
    Returns:
      [k * D] float32 unit vector (all zeros if no descriptor is valid).
    """
    desc = jnp.asarray(desc, jnp.float32)
    centers = jnp.asarray(centers, jnp.float32)
    k = centers.shape[0]
    a = jnp.argmin(sq_dists(desc, centers), axis=1)
    w = jax.nn.one_hot(a, k, dtype=jnp.float32) * jnp.asarray(mask, jnp.float32)[:, None]
    # sum over assigned descriptors of (x - c): W^T X - (sum W) c
    v = jnp.matmul(w.T, desc, precision="highest") - w.sum(0)[:, None] * centers  # [k, D]
    v = v / jnp.maximum(jnp.linalg.norm(v, axis=-1, keepdims=True), 1e-12)  # intra-norm
    v = jnp.sign(v) * jnp.abs(v) ** power
    v = v.reshape(-1)
    return v / jnp.maximum(jnp.linalg.norm(v), 1e-12)


def project_local(desc, vocab: Vocabulary):
    """Local descriptors [..., D0] -> [..., D] through the vocabulary's local whitening
    (unchanged without one)."""
    if vocab.local_proj is None:
        return desc
    return jnp.matmul(desc - vocab.local_mean, vocab.local_proj, precision="highest")


def apply_pca(v, vocab: Vocabulary):
    """Whitening projection of VLAD vectors [..., k * D] -> [..., G], L2-normalised."""
    if vocab.pca_proj is None:
        return v
    y = (v - vocab.pca_mean) @ vocab.pca_proj
    return y / jnp.maximum(jnp.linalg.norm(y, axis=-1, keepdims=True), 1e-12)


@jax.jit
def _global_batch(desc, mask, vocab: Vocabulary):
    """[B, K, D], [B, K] -> [B, G] global descriptors."""
    desc = project_local(jnp.asarray(desc, jnp.float32), vocab)
    v = jax.vmap(lambda d, m: vlad(d, m, vocab.centers, vocab.power))(desc, mask)
    return apply_pca(v, vocab)


def global_descriptor(desc: np.ndarray, mask: np.ndarray | None, vocab: Vocabulary
                      ) -> np.ndarray:
    """Host helper: one image's global descriptor [G] float32 (references and queries alike).

    Args:
      desc: [K, D] local descriptors (any K, including 0).
      mask: [K] bool or None (all valid).
      vocab: the map's :class:`Vocabulary`.
    """
    return global_descriptors([desc], None if mask is None else [mask], vocab)[0]


def global_descriptors(descs: list[np.ndarray], masks: list[np.ndarray] | None,
                       vocab: Vocabulary) -> np.ndarray:
    """Global descriptors [N, G] float32 of N images (padded to one shape, one jitted call)."""
    d = vocab.input_dim
    kmax = padded_size(max([len(x) for x in descs] + [1]))
    n = len(descs)
    D = np.zeros((n, kmax, d), np.float32)
    M = np.zeros((n, kmax), bool)
    for i, x in enumerate(descs):
        x = np.asarray(x, np.float32).reshape(-1, d)
        D[i, :len(x)] = x
        M[i, :len(x)] = True if masks is None else np.asarray(masks[i], bool)
    return np.asarray(_global_batch(jnp.asarray(D), jnp.asarray(M), vocab))


def learn_vocabulary(descs: list[np.ndarray], cfg: RetrievalConfig = RetrievalConfig()
                     ) -> Vocabulary:
    """Vocabulary from the reference images' descriptors (and PCA-whitening if configured).

    Args:
      descs: [N] arrays [K_i, D] of the reference images' local descriptors.
    Raises:
      VrsError if there are fewer descriptors than words.
    """
    nonempty = [np.asarray(x, np.float32) for x in descs if len(x)]
    if not nonempty:
        raise VrsError("cannot learn a retrieval vocabulary: no reference image has keypoints")
    allx = np.concatenate(nonempty)
    if len(allx) < cfg.n_words:
        raise VrsError(f"cannot learn {cfg.n_words} visual words from {len(allx)} descriptors")
    rng = np.random.default_rng(cfg.seed)
    if len(allx) > cfg.max_train_descriptors:
        allx = allx[np.sort(rng.choice(len(allx), cfg.max_train_descriptors, replace=False))]
    local = {}
    if cfg.local_dim is not None:
        if cfg.local_dim > allx.shape[1]:
            raise VrsError(f"RetrievalConfig.local_dim {cfg.local_dim} exceeds the local "
                           f"descriptors' dimension {allx.shape[1]}")
        mean, proj = pca_whitening(allx, cfg.local_dim, cfg.whiten_eps)
        allx = (allx - mean) @ proj
        local = dict(local_mean=jnp.asarray(mean), local_proj=jnp.asarray(proj))
    centers = kmeans(allx, cfg.n_words, cfg.kmeans_iters, cfg.seed)
    vocab = Vocabulary(centers=jnp.asarray(centers), power=cfg.power, **local)
    if cfg.pca_dim is not None:
        v = global_descriptors(descs, None, vocab)
        dim = min(cfg.pca_dim, len(v) - 1)
        if dim < 1:
            raise VrsError(f"PCA-whitening needs at least 2 reference images, got {len(v)}")
        mean, proj = pca_whitening(v, dim, cfg.whiten_eps)
        vocab = vocab.replace(pca_mean=jnp.asarray(mean), pca_proj=jnp.asarray(proj))
    return vocab


def pca_whitening(v: np.ndarray, dim: int, eps: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """PCA-whitening of row vectors v [N, G0]: (mean [G0], projection [G0, dim]) float32.

    ``(x - mean) @ proj`` has identity covariance over the training vectors.
    """
    v = np.asarray(v, np.float64)
    mean = v.mean(0)
    _, s, vt = np.linalg.svd(v - mean, full_matrices=False)
    var = s[:dim] ** 2 / max(len(v) - 1, 1)
    proj = vt[:dim].T / np.sqrt(var + eps)
    return mean.astype(np.float32), proj.astype(np.float32)


# ----------------------------------------------------------------------------- retrieval


@partial(jax.jit, static_argnames=("k",))
def topk(query, database, k: int, db_mask=None):
    """Top-k database entries by dot product (cosine for unit vectors).

    Args:
      query: [Q, G] or [G].  database: [N, G].  k: results per query (k <= N).
      db_mask: optional [N] bool; False entries are never returned while k valid exist.
    Returns:
      idx [Q, k] (or [k]) int32, scores [Q, k] (or [k]) float32, best first.
    """
    q = jnp.asarray(query, jnp.float32)
    single = q.ndim == 1
    q = q[None] if single else q
    s = jnp.matmul(q, jnp.asarray(database, jnp.float32).T, precision="highest")
    if db_mask is not None:
        s = jnp.where(jnp.asarray(db_mask)[None, :], s, -jnp.inf)
    scores, idx = jax.lax.top_k(s, k)
    idx = idx.astype(jnp.int32)
    return (idx[0], scores[0]) if single else (idx, scores)
