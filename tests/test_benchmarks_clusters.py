"""The cluster benchmark's pieces and multi-cluster localization on the large (rooms4) scene."""

from __future__ import annotations

import dataclasses
import math

import jax
import numpy as np
import pytest

from benchmarks import clusters as bench
from vrs_jax import maps
from vrs_jax.data import synthetic
from vrs_jax.data.readers import load_scene
from vrs_jax.nerf.config import get_config as nerf_config
from vrs_jax.nerf.model import init_params


def test_param_count_and_equal_size_width():
    cfg = nerf_config("test")
    params = init_params(jax.random.PRNGKey(0), cfg)  # independent: real arrays
    assert bench.param_count(cfg) == sum(int(np.size(x)) for x in jax.tree_util.tree_leaves(
        params))
    w, wc = bench.equal_size_width(cfg, 4)
    one = bench.param_count(cfg)
    four = 4 * bench.param_count(dataclasses.replace(cfg, net_width=w, net_width_condition=wc))
    assert abs(four - one) / one < 0.03 and w < cfg.net_width
    # one more or less unit of width is farther from the single NeRF's count
    for dw in (-1, 1):
        wc2 = round(cfg.net_width_condition * (w + dw) / cfg.net_width)
        other = 4 * bench.param_count(dataclasses.replace(cfg, net_width=w + dw,
                                                          net_width_condition=wc2))
        assert abs(other - one) >= abs(four - one)


def test_map_configs_differ_only_in_the_partition():
    cfgs = bench.map_configs(maps.get_config("test"), 4, steps=123, rays=256, width=128)
    one, km, grid = (cfgs[k].nerf for k in bench.LABELS)
    assert (one.n_clusters, km.n_clusters, grid.n_clusters) == (1, 4, 4)
    assert one.net_width == 128 and one.net_width_condition == 64 and km.net_width < 64
    assert one.batch_size == km.batch_size == 256 and one.max_steps == km.max_steps == 123
    split = bench.map_configs(maps.get_config("test"), 4, 123, 256, cluster_rays="split")
    assert split["grid"].nerf.batch_size == 64
    assert (km.cluster_method, grid.cluster_method) == ("kmeans", "grid")
    assert dataclasses.replace(km, cluster_method="grid") == grid
    assert cfgs["kmeans"].egm == cfgs["one"].egm == cfgs["grid"].egm
    with pytest.raises(Exception, match="multiple"):
        bench.map_configs(maps.get_config("test"), 3, steps=10, rays=256,
                          cluster_rays="split")


@pytest.fixture(scope="module")
def rooms_map(tmp_path_factory):
    """A reduced rooms4 scene (26 references, 9 queries at 160x120) and a 4-cluster K-means map
    with a briefly trained NeRF (test config)."""
    cfg = dataclasses.replace(synthetic.get_config("rooms4"), n_reference=8, n_query=3,
                              texels_per_m=64.0, supersample=1)
    root = synthetic.generate(tmp_path_factory.mktemp("rooms") / "scene", cfg)
    scene = load_scene("7scenes", root)
    mcfg = maps.get_config("test", n_clusters=4, max_steps=30, net_width=28,
                           net_width_condition=14, batch_size=64)
    out = maps.build_map(scene, tmp_path_factory.mktemp("rooms") / "map", mcfg,
                         progress=False, log=lambda s: None)
    return scene, synthetic.build_layout(cfg), maps.load_map(out)


@pytest.mark.slow  # ~40 s alone on 2 cores (5 min measured under a load of 15)
def test_multi_cluster_localization_on_the_large_scene(rooms_map):
    """A 4-cluster map of the large scene localizes: every room's queries are served by
    their own room's NeRF; real patches reach >= 75% within 5 cm / 5 deg. (Render-mode
    accuracy needs a trained NeRF: benchmarks/clusters.py measures it.)"""
    from vrs_jax import localize
    from vrs_jax.eval import metrics
    from vrs_jax.localize.batch import localize_scene

    scene, layout, m = rooms_map
    # one cluster per room
    rooms = bench.room_of(scene.references().centers, layout)
    bal = bench.balance(m.ilm, rooms)
    assert bal["rooms_split"] == 0 and bal["purity"] == 1.0 and m.ilm.n_clusters == 4
    queries = scene.queries()
    assert len(queries) == 9
    image_cluster = np.asarray(m.ilm.image_cluster)
    for source in ("real", "render"):
        cfg = localize.get_config("test", source=source)
        results, _ = localize_scene(m, queries, cfg, progress=False, timed=False)
        # the queries' retrieved references span every cluster: each query is served by
        # its own room's NeRF
        used = {int(image_cluster[int(r.retrieved[0])]) for r in results}
        assert used == {0, 1, 2, 3}
        q_rooms = bench.room_of(queries.centers, layout)
        top_rooms = rooms[[int(r.retrieved[0]) for r in results]]
        assert np.mean(top_rooms == q_rooms) >= 0.75
        R = np.stack([np.asarray(r.R, np.float64) for r in results])
        t = np.stack([np.asarray(r.t, np.float64) for r in results])
        assert np.all(np.isfinite(R)) and np.all(np.isfinite(t))
        if source == "real":  # the stored real patches localize every room's queries
            dt, dr = metrics.pose_errors(R, t, queries.R, queries.t)
            assert metrics.recall(dt, dr)["5cm_5deg"] >= 0.75, (dt, dr)
    assert math.isfinite(bal["cv"])
