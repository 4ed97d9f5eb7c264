"""Localizer: the same result as prepare_query + localize, batches equal singles, a bad image
in a batch is flagged while the others are localized, an image size contradicting K fails."""

from __future__ import annotations

import numpy as np
import pytest

from vrs_jax import localize, maps
from vrs_jax.data.images import read_gray, read_image
from vrs_jax.data.readers import load_scene
from vrs_jax.errors import VrsError
from vrs_jax.localize.localizer import Localizer, check_intrinsics, to_gray


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
    images = [queries.image_paths[1], bad, queries.image_paths[2]]
    Ks = [queries.K[1], queries.K[1], queries.K[2]]
    dists = [queries.dist[1], None, queries.dist[2]]
    results, errors = loc.localize_batch(images, Ks, dists)
    assert results[1] is None and str(bad) in errors[1]
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
    with pytest.raises(VrsError, match="principal point"):
        check_intrinsics(h, w, np.array([[100, 0, 150], [0, 100, 10], [0, 0, 1.0]]))
    with pytest.raises(VrsError, match=r"\[H, W\]"):
        loc.localize_image(np.zeros((4, 4, 4)), K)


def test_warmup_and_render_source(tiny_map):
    loc = Localizer(maps.load_map(tiny_map), localize.get_config("test"), source=None)
    assert loc.cfg.source == "render"
    loc.warmup(160, 120)  # blank image: compiles, no failure
