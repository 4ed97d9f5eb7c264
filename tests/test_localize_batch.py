"""Batch localization sharded over the query axis: 2 forced CPU devices (a subprocess: the
device count is fixed when jax starts) give the unsharded batch's results; padding."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from vrs_jax.errors import VrsError
from vrs_jax.localize import batch as B
from vrs_jax.localize.query import Query

REPO = Path(__file__).resolve().parents[1]

_SCRIPT = textwrap.dedent("""
    import sys
    import jax, numpy as np
    from vrs_jax import localize, maps
    from vrs_jax.data.images import read_gray
    from vrs_jax.data.readers import load_scene
    from vrs_jax.localize import batch as B
    assert len(jax.devices()) == 2, jax.devices()
    m = maps.load_map(sys.argv[1], descriptors=True)
    qs = load_scene("7scenes", sys.argv[2]).queries()
    cfg = localize.get_config("test", source="real")
    q = localize.stack_queries([localize.prepare_query(m, read_gray(qs.image_paths[i]),
                                                       qs.K[i], qs.dist[i], cfg)
                                for i in range(3)])  # 3 queries: padded to 4 on 2 devices
    ref = jax.device_get(B.localize_batch(m, q, cfg))
    mesh = B.query_mesh(2)
    placed = B.place_map(m, mesh)
    assert [jax.tree.leaves(p)[0].devices() for p in placed] == [{d} for d in jax.devices()]
    q4 = jax.tree.map(lambda x: np.concatenate([x, x[:1]]), q)
    four = B.localize_batch(placed, q4, cfg, mesh)
    assert len(four.R.sharding.device_set) == 2  # two queries per device
    assert four.R.addressable_shards[0].data.shape[0] == 2
    sh = jax.device_get(B.localize_batch(m, q, cfg, mesh))
    np.testing.assert_allclose(np.asarray(four.R)[:3], sh.R, atol=1e-5)
    for k in ("R", "t", "success", "fallback", "n_inliers", "n_matches", "retrieved"):
        a, b = np.asarray(getattr(ref, k)), np.asarray(getattr(sh, k))
        assert a.shape == b.shape and a.shape[0] == 3, (k, a.shape, b.shape)
        assert np.allclose(a, b, atol=1e-5), (k, a, b)
    print("successes", int(np.sum(ref.success)))
""")


def test_sharded_batch_equals_unsharded_on_two_devices(tiny_map, small_synthetic_scene):
    from conftest import xla_flags_with

    env = dict(os.environ, XLA_FLAGS=xla_flags_with("--xla_force_host_platform_device_count=2"),
               JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO), TF_CPP_MIN_LOG_LEVEL="2")
    r = subprocess.run([sys.executable, "-c", _SCRIPT, str(tiny_map),
                        str(small_synthetic_scene)], env=env, capture_output=True, text=True,
                       timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stdout + r.stderr[-3000:]
    assert int(r.stdout.split("successes")[1]) >= 2  # a batch that localizes: not vacuous


def test_pad_queries_repeats_the_last_query():
    q = Query(*(jnp.arange(3 * 2, dtype=jnp.float32).reshape(3, 2) for _ in range(6)))
    p, valid = B.pad_queries(q, 4)
    assert p.K.shape == (4, 2) and valid.tolist() == [True, True, True, False]
    np.testing.assert_array_equal(np.asarray(p.K[3]), np.asarray(q.K[2]))
    same, valid = B.pad_queries(q, 3)
    assert same is q and valid.all()
    with pytest.raises(VrsError, match="devices requested"):
        B.query_mesh(64)
