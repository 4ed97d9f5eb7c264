"""Localizer: the same result as prepare_query + localize, batches equal singles, a bad image
in a batch is flagged while the others are localized, an image size contradicting K fails."""

from __future__ import annotations

import numpy as np
import pytest

from vrs_jax import localize, maps
from vrs_jax.data.images import as_gray as to_gray
from vrs_jax.data.images import check_intrinsics, read_gray, read_image
from vrs_jax.data.readers import load_scene
from vrs_jax.errors import VrsError
from vrs_jax.localize.localizer import Localizer


@pytest.fixture(scope="module")
def loc(tiny_map):
    return Localizer(tiny_map, "test", source="real")


@pytest.fixture(scope="module")
def queries(small_synthetic_scene):
    return load_scene("7scenes", small_synthetic_scene).queries()


def _same(a, b):
    np.testing.assert_allclose(np.asarray(a.R), np.asarray(b.R), atol=1e-5)
    np.testing.assert_allclose(np.asarray(a.t), np.asarray(b.t), atol=1e-5)
    assert bool(a.success) == bool(b.success)
    assert bool(a.fallback) == bool(b.fallback)
    assert int(a.n_inliers) == int(b.n_inliers)
    assert int(a.n_matches) == int(b.n_matches)
    np.testing.assert_array_equal(np.asarray(a.retrieved), np.asarray(b.retrieved))


def test_localize_image_equals_localize(loc, queries, tiny_map):
    m = maps.load_map(tiny_map)
    cfg = localize.get_config("test", source="real")
    path, K, dist = queries.image_paths[0], queries.K[0], queries.dist[0]
    ref = localize.localize(m, localize.prepare_query(m, read_gray(path), K, dist, cfg), cfg)
    r = loc.localize_image(path, K, dist)
    assert isinstance(r.R, np.ndarray)
    _same(r, ref)
    assert bool(r.success)
    # the same image as an RGB uint8 array and as a float grey array
    rgb8 = np.round(read_image(path) * 255).astype(np.uint8)
    _same(loc.localize_image(to_gray(rgb8).astype(np.float32), K, dist),
          loc.localize_image(rgb8, K, dist))


def test_batch_equals_singles_and_flags_bad_image(loc, queries, tmp_path):
    bad = tmp_path / "broken.png"
    bad.write_bytes(b"not a png")
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    images = [queries.image_paths[1], bad, queries.image_paths[2], empty]
    Ks = [queries.K[1], queries.K[1], queries.K[2], queries.K[2]]
    dists = [queries.dist[1], None, queries.dist[2], None]
    results, errors = loc.localize_batch(images, Ks, dists)
    assert results[1] is None and str(bad) in errors[1]
    assert results[3] is None and str(empty) in errors[3] and "unreadable" in errors[3]
    assert errors[0] is None and errors[2] is None
    for i, j in ((0, 1), (2, 2)):
        _same(results[i], loc.localize_image(queries.image_paths[j], queries.K[j],
                                             queries.dist[j]))


def test_unreadable_image_names_path(loc, queries, tmp_path):
    with pytest.raises(VrsError, match="missing.png"):
        loc.localize_image(tmp_path / "missing.png", queries.K[0])


def test_size_contradicting_K(loc, queries):
    K = np.asarray(queries.K[0]).copy()
    w, h = (int(s) for s in queries.sizes[0])
    gray = read_gray(queries.image_paths[0])
    K2 = K.copy()
    K2[:2] *= 2  # the K of an image twice as large
    with pytest.raises(VrsError, match=f"{w}x{h}"):
        loc.localize_image(gray, K2)
    check_intrinsics(w, h, K)  # the right K passes
    K_half = K.copy()
    K_half[:2] /= 2  # the K of an image half as large: its principal point at a quarter
    with pytest.raises(VrsError, match="principal point"):
        check_intrinsics(w, h, K_half)
    with pytest.raises(VrsError, match="principal point"):
        check_intrinsics(2 * w, 2 * h, K)
    with pytest.raises(VrsError, match="principal point"):
        check_intrinsics(h, w, np.array([[100, 0, 150], [0, 100, 10], [0, 0, 1.0]]))
    with pytest.raises(VrsError, match=r"\[H, W\]"):
        loc.localize_image(np.zeros((4, 4, 4)), K)


def test_warmup_and_render_source(tiny_map):
    loc = Localizer(maps.load_map(tiny_map), localize.get_config("test"), source=None)
    assert loc.cfg.source == "render"
    loc.warmup(160, 120)  # blank image: compiles, no failure
    # with a retry, the retry's config is compiled too: no query pays for it later
    retry = Localizer(maps.load_map(tiny_map), localize.get_config("test", retries=1))
    before = localize.localize._cache_size()
    retry.warmup(160, 120)
    assert localize.localize._cache_size() == before + 2


def test_warmup_compiles_the_cached_path_and_leaves_the_cache_empty(tiny_map, queries):
    from vrs_jax.localize.run import JITTED_STAGES

    loc = Localizer(maps.load_map(tiny_map), localize.get_config("test", retries=1),
                    cache_mb=5)
    loc.warmup(160, 120)
    assert len(loc.cache) == 0 and loc.cache.misses == 0 and loc.cache.budget == 5_000_000
    sizes = {k: f._cache_size() for k, f in JITTED_STAGES.items()}
    loc.localize_image(queries.image_paths[0], queries.K[0], queries.dist[0])
    assert len(loc.cache) > 0  # it rendered and kept references, compiling nothing new
    assert {k: f._cache_size() for k, f in JITTED_STAGES.items()} == sizes


def test_descriptor_cache_is_lru_within_budget():
    from vrs_jax.localize.cache import DescriptorCache

    c = DescriptorCache(budget_mb=3 * 4 * 8 * 2 / 1e6)  # three [4, 8] float16 entries
    for i in range(3):
        c.put(i, np.full((4, 8), i, np.float32))
    assert c.get(0) is not None  # 0 becomes the most recent
    c.put(3, np.ones((4, 8)))  # evicts 1, the least recently used
    assert c.get(1) is None and c.get(2) is not None and c.get(3) is not None
    assert c.bytes <= c.budget and len(c) == 3 and c.evictions == 1
    assert DescriptorCache(0).budget == 0


def test_cached_render_mode_equals_uncached_and_hits(tiny_map, queries):
    plain = Localizer(tiny_map, "test")
    cached = Localizer(plain.map, "test", cache_mb=5)
    path, K, dist = queries.image_paths[0], queries.K[0], queries.dist[0]
    a = plain.localize_image(path, K, dist)
    b = cached.localize_image(path, K, dist)  # cold: renders its references
    assert cached.cache.misses == len(np.asarray(b.retrieved)) and cached.cache.hits == 0
    c = cached.localize_image(path, K, dist)  # warm: renders nothing
    assert cached.cache.hits == len(np.asarray(c.retrieved))
    np.testing.assert_array_equal(np.asarray(a.retrieved), np.asarray(b.retrieved))
    # the cache stores float16 descriptors: the same pose to well under a centimetre
    for r in (b, c):
        assert bool(r.success) == bool(a.success)
        np.testing.assert_allclose(np.asarray(r.t), np.asarray(a.t), atol=5e-3)


def test_cached_path_exits_early_like_the_fused_path(tiny_map, queries):
    """With an early exit, a cold cache renders the candidates the fused ``localize`` renders
    (the same rule, best first), and a warm one uses its cached references and renders none;
    an unreachable threshold renders every miss."""
    cfg = localize.get_config("test", top_k=3, early_exit_inliers=12)
    never = localize.get_config("test", top_k=3, early_exit_inliers=10**6)
    plain = Localizer(tiny_map, cfg)
    saved = 0
    for i in range(3):
        path, K, dist = queries.image_paths[i], queries.K[i], queries.dist[i]
        a = plain.localize_image(path, K, dist)
        cold = Localizer(plain.map, cfg, cache_mb=5)
        b = cold.localize_image(path, K, dist)
        assert int(b.n_rendered) == int(a.n_rendered_first)
        if bool(a.success):
            np.testing.assert_allclose(np.asarray(b.t), np.asarray(a.t), atol=5e-3)
        assert cold.cache.misses == len(cold.cache) and cold.cache.hits == 0
        warm = cold.localize_image(path, K, dist)
        assert int(warm.n_rendered) == 0 and cold.cache.hits == len(cold.cache)
        full = Localizer(plain.map, never, cache_mb=5)
        full.localize_image(path, K, dist)
        assert len(full.cache) == 3
        saved += len(cold.cache) < 3
    assert saved > 0  # the exit happened somewhere (the test can fail)


def test_egm_only_map_localizes_with_real_patches(tiny_map, queries, tmp_path, loc):
    """Real patches need no NeRF: a map saved before (or without) its NeRF training gives the
    full map's real-patch pose; render mode refuses it with a clear error."""
    m = maps.load_map(tiny_map)
    egm_only = maps.save_map(m.replace(ilm=None), tmp_path / "egm_only")
    with pytest.raises(VrsError, match="no trained NeRF"):
        maps.load_map(egm_only)
    path, K, dist = queries.image_paths[0], queries.K[0], queries.dist[0]
    _same(Localizer(egm_only, "test", source="real").localize_image(path, K, dist),
          loc.localize_image(path, K, dist))
    with pytest.raises(VrsError, match="no trained NeRF"):
        Localizer(egm_only, "test", source="render")
    assert maps.load_map_for(egm_only, "gt").has_descriptors  # the CLI's alias of "real"
