"""ILM map file: round trip, format version, corrupt files."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vrs_jax.errors import VrsError
from vrs_jax.nerf import ilm as ilm_lib
from vrs_jax.nerf.config import get_config
from vrs_jax.nerf.model import Field, init_stacked_params

CFG = get_config("test", n_clusters=2)


def _ilm():
    params = jax.jit(init_stacked_params, static_argnums=(1, 2))(jax.random.key(0), CFG, 2)
    fields = Field(params, jnp.asarray([[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]]),
                   jnp.asarray([0.5, 0.25]), jnp.ones((2, 3)))
    return ilm_lib.ILM(fields=fields, cluster_centers=jnp.asarray([[0.0, 0, 0], [5.0, 0, 0]]),
                       image_cluster=jnp.asarray([0, 1, 1], jnp.int32),
                       membership=jnp.asarray([[True, True, False], [False, True, True]]),
                       near=jnp.full(3, 2.0), far=jnp.full(3, 6.0),
                       image_names=("a.png", "b.png", "c.png"), config=CFG)


def test_round_trip(tmp_path):
    m = _ilm()
    p = ilm_lib.save_ilm(tmp_path / "map" / "ilm.npz", m)
    assert ilm_lib.map_bytes(p) > 0 and not list(p.parent.glob("*.tmp"))
    back = ilm_lib.load_ilm(p)
    assert back.config == CFG and back.image_names == m.image_names
    for a, b in zip(jax.tree.leaves(m), jax.tree.leaves(back), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert back.cluster_of_image("c.png") == 1
    np.testing.assert_array_equal(back.cluster_of_position(np.array([[4.0, 0, 0]])), [1])
    f1 = back.field(1)
    assert float(f1.scale) == 0.25 and f1.params["trunk_0"]["kernel"].ndim == 2
    with pytest.raises(VrsError, match="not a reference image"):
        back.cluster_of_image("zzz.png")


def test_missing_corrupt_and_other_version(tmp_path):
    with pytest.raises(VrsError, match="not found"):
        ilm_lib.load_ilm(tmp_path / "none.npz")
    p = ilm_lib.save_ilm(tmp_path / "ilm.npz", _ilm())
    data = p.read_bytes()
    bad = tmp_path / "truncated.npz"
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(VrsError, match="corrupt or unreadable"):
        ilm_lib.load_ilm(bad)
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file at all")
    with pytest.raises(VrsError, match="corrupt or unreadable"):
        ilm_lib.load_ilm(junk)
    # Another format version.
    with np.load(p) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays["__meta__"].tobytes())
    meta["format_version"] = 99
    arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    old = tmp_path / "v99.npz"
    np.savez(old, **arrays)
    with pytest.raises(VrsError, match="version 99 is not supported"):
        ilm_lib.load_ilm(old)
    # Arrays that don't match the config.
    meta["format_version"] = ilm_lib.FORMAT_VERSION
    arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    arrays["params/trunk_0/kernel"] = arrays["params/trunk_0/kernel"][:, :3]
    wrong = tmp_path / "wrong.npz"
    np.savez(wrong, **arrays)
    with pytest.raises(VrsError, match="do not match its config"):
        ilm_lib.load_ilm(wrong)


def test_float16_storage_halves_the_parameters_and_loads_as_float32(tmp_path):
    m = _ilm()
    p32 = ilm_lib.save_ilm(tmp_path / "a.npz", m)
    p16 = ilm_lib.save_ilm(tmp_path / "b.npz", m, float16=True)
    n_params = sum(x.size for x in jax.tree.leaves(m.fields.params))
    saved = ilm_lib.map_bytes(p32) - ilm_lib.map_bytes(p16)
    assert abs(saved - 2 * n_params) < 0.05 * 2 * n_params + 2048
    back = ilm_lib.load_ilm(p16)
    for a, b in zip(jax.tree.leaves(m.fields.params), jax.tree.leaves(back.fields.params),
                    strict=True):
        assert b.dtype == jnp.float32
        np.testing.assert_array_equal(np.asarray(b),
                                      np.asarray(a).astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(np.asarray(back.near), np.asarray(m.near))


def test_version1_files_load_only_when_upgrading(tmp_path):
    """An ILM file of format 1 (no cluster_method in its config) is refused on load and read
    as K-means clustered by maps.upgrade's path."""
    import io

    ilm = _ilm()
    with np.load(io.BytesIO(ilm_lib.to_bytes(ilm)), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays["__meta__"].tobytes().decode())
    meta["format_version"] = 1
    del meta["config"]["cluster_method"]
    arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    p = tmp_path / "ilm.npz"
    with pytest.raises(VrsError, match="version 1"):
        ilm_lib.from_bytes(buf.getvalue(), p)
    back = ilm_lib.from_bytes(buf.getvalue(), p, upgrade=True)
    assert back.config == ilm.config and back.config.cluster_method == "kmeans"
