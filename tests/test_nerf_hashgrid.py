"""Hash-grid encoding: numpy reference interpolation, level weights, gradients, field training,
ILM save/load with the table."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.stats import norm

from vrs_jax.errors import VrsError
from vrs_jax.nerf import hashgrid as H
from vrs_jax.nerf import ilm as ilm_lib
from vrs_jax.nerf import mipnerf
from vrs_jax.nerf.config import NerfConfig, get_config
from vrs_jax.nerf.model import HASH_TABLE, Field, init_stacked_params, render_rays


def _np_index(corner, n, dense, table_size):
    """Independent reference: dense vertex id, or Instant-NGP's XOR hash, mod T."""
    x, y, z = (int(c) for c in corner)
    if dense:
        i = x + y * (n + 1) + z * (n + 1) ** 2
    else:
        i = (x * 1) ^ ((y * 2654435761) & 0xFFFFFFFF) ^ ((z * 805459861) & 0xFFFFFFFF)
    return i % table_size


def _np_corners(pt, res, dense, table_size):
    """Loop-based float64 reference: (level, table index, trilinear weight) of each of the 8
    corners of the point's cell on each level."""
    for level, n in enumerate(int(r) for r in res):
        pos = np.clip(np.asarray(pt, np.float64), 0, 1) * n
        i0 = np.minimum(np.floor(pos), n - 1)
        f = pos - i0
        for dx in (0, 1):
            for dy in (0, 1):
                for dz in (0, 1):
                    w = ((f[0] if dx else 1 - f[0]) * (f[1] if dy else 1 - f[1])
                         * (f[2] if dz else 1 - f[2]))
                    c = i0.astype(int) + (dx, dy, dz)
                    yield level, _np_index(c, n, dense[level], table_size), w


def _np_interpolate(table, x, res, dense):
    """Loop-based float64 trilinear interpolation per level: [N, L, F]."""
    table = np.asarray(table, np.float64)
    n_levels, table_size, n_feat = table.shape
    out = np.zeros((len(x), n_levels, n_feat))
    for p, pt in enumerate(np.asarray(x, np.float64)):
        for level, i, w in _np_corners(pt, res, dense, table_size):
            out[p, level] += w * table[level, i]
    return out


def test_resolutions_and_dense_levels():
    res = H.level_resolutions(16, 16, 2048)
    assert res[0] == 16 and res[-1] == 2048 and np.all(np.diff(res) > 0)
    b = (2048 / 16) ** (1 / 15)
    np.testing.assert_array_equal(res, np.floor(16 * b ** np.arange(16) + 1e-6))
    dense = H.dense_levels(np.array([2, 3, 4, 8]), 64)
    np.testing.assert_array_equal(dense, [True, True, False, False])  # 27, 64 <= 64 < 125


def test_interpolation_matches_numpy_reference():
    rng = np.random.default_rng(0)
    table = rng.normal(size=(4, 64, 3)).astype(np.float32)
    res = np.array([2, 3, 5, 11])
    dense = H.dense_levels(res, 64)
    assert dense.tolist() == [True, True, False, False]  # both index paths are exercised
    x = rng.uniform(-0.05, 1.05, size=(50, 3)).astype(np.float32)  # some outside: clipped
    x[0] = [1.0, 1.0, 1.0]  # the far corner lies in the last cell
    x[1] = [0.5, 0.5, 0.5]  # exactly on vertices
    got = H.interpolate(jnp.asarray(table), jnp.asarray(x), res, dense)
    np.testing.assert_allclose(np.asarray(got), _np_interpolate(table, x, res, dense),
                               rtol=1e-5, atol=1e-5)


def test_corner_indices_match_the_reference_index_at_full_scale():
    # cpu-small's levels with a 2^14 table (dense 16 and 22, hashed up to 1024): products of
    # large coordinates and the primes wrap in uint32, as Instant-NGP's hash does
    res = H.level_resolutions(16, 16, 1024)
    T = 1 << 14
    dense = H.dense_levels(res, T)
    assert dense[:2].all() and not dense[2:].any()
    rng = np.random.default_rng(3)
    cells = [rng.integers(0, res, size=(40, len(res))) for _ in range(3)]
    cells[0][0], cells[1][0], cells[2][0] = res - 1, res - 1, res - 1  # the last cell
    got = np.asarray(H.corner_indices([jnp.asarray(c, jnp.uint32) for c in cells], res, dense,
                                      T))
    assert got.shape == (40, len(res), 8)
    for p in range(40):
        for level in range(len(res)):
            for k, off in enumerate(H.CORNERS):
                c = [cells[a][p, level] + int(off[a]) for a in range(3)]
                want = level * T + _np_index(c, int(res[level]), dense[level], T)
                assert got[p, level, k] == want


def test_interpolation_reproduces_a_trilinear_function_on_dense_levels():
    # A dense level whose vertex values are an affine function interpolates it exactly.
    n = 3
    ii = np.arange(n + 1)
    z, y, x = np.meshgrid(ii, ii, ii, indexing="ij")  # vertex id x + y(n+1) + z(n+1)^2
    val = (0.3 + 1.0 * x - 2.0 * y + 0.5 * z) / n
    table = np.zeros((1, 64, 1), np.float32)
    table[0, : (n + 1) ** 3, 0] = val.reshape(-1)
    p = np.random.default_rng(1).uniform(size=(20, 3)).astype(np.float32)
    got = H.interpolate(jnp.asarray(table), jnp.asarray(p), np.array([n]), np.array([True]))
    want = 0.3 / n + p[:, 0] - 2 * p[:, 1] + 0.5 * p[:, 2]
    np.testing.assert_allclose(np.asarray(got)[:, 0, 0], want, atol=1e-5)


def test_level_weights_closed_form_range_and_monotonicity():
    res = np.array([16, 64, 256, 1024])
    sigma = jnp.asarray(np.geomspace(1e-5, 1e-1, 40), jnp.float32)
    w = np.asarray(H.level_weights(sigma, res))
    assert np.all(w >= 0) and np.all(w <= 1)
    assert np.all(np.diff(w, axis=0) <= 1e-7)  # non-increasing as the footprint grows
    assert np.all(np.diff(w, axis=1) <= 1e-7)  # finer levels never weigh more
    # = P(|X| < c / 2), X ~ N(0, sigma^2): the probability of staying in the mean's cell
    c = 1.0 / res[None, :]
    s = np.asarray(sigma, np.float64)[:, None]
    np.testing.assert_allclose(w, 2 * norm.cdf(c / (2 * s)) - 1, atol=1e-6)
    np.testing.assert_allclose(np.asarray(H.level_weights(jnp.zeros(2), res)), 1.0)


def test_footprint_std_is_the_frustum_radial_std():
    t = jnp.asarray([[1.0, 1.01, 2.0, 2.02]])
    r = jnp.asarray([0.01])
    s = np.asarray(H.footprint_std(t, r))[0]
    _, _, r_var = mipnerf.conical_frustum_moments(t[:, :-1], t[:, 1:], r[:, None])
    np.testing.assert_allclose(s, np.sqrt(np.asarray(r_var))[0], rtol=1e-6)
    # thin intervals: ~ radius(t) / 2
    np.testing.assert_allclose(s[[0, 2]], [0.01 * 1.005 / 2, 0.01 * 2.01 / 2], rtol=1e-3)


def test_gradients_are_finite_and_the_table_gradient_is_the_interpolation_weights():
    rng = np.random.default_rng(2)
    table = jnp.asarray(rng.normal(size=(3, 128, 2)).astype(np.float32))
    res = np.array([4, 9, 20])
    dense = H.dense_levels(res, 128)
    x = jnp.asarray(rng.uniform(size=(7, 3)).astype(np.float32))
    sigma = jnp.asarray(rng.uniform(0, 0.05, size=7).astype(np.float32))

    def f(tab, x, s):
        return jnp.sum(H.encode(tab, x, s, res, dense) ** 2)

    gt, gx, gs = jax.jit(jax.grad(f, argnums=(0, 1, 2)))(table, x, sigma)
    assert all(np.all(np.isfinite(np.asarray(g))) for g in (gt, gx, gs))
    # d/dtable of sum(encode) without anti-aliasing: each point spreads weight 1 per level
    g1 = jax.jit(jax.grad(lambda tab: jnp.sum(H.encode(tab, x, None, res, dense)[:, ::2])))(
        table)
    np.testing.assert_allclose(np.asarray(g1[..., 0]).sum(axis=1), [7.0] * 3, rtol=1e-5)
    # zero footprint: still finite
    g0 = jax.jit(jax.grad(f, argnums=2))(table, x, jnp.zeros(7))
    assert np.all(np.isfinite(np.asarray(g0)))


def _np_table_gradient(table_shape, x, g, res, dense):
    """Loop-based d/dtable of sum(interpolate * g): each point adds its corner weight x g."""
    out = np.zeros(table_shape)
    for p, pt in enumerate(np.asarray(x, np.float64)):
        for level, i, w in _np_corners(pt, res, dense, table_shape[1]):
            out[level, i] += w * g[p, level]
    return out


def test_custom_backward_matches_loop_reference_and_finite_differences():
    # interpolate's backward is written by hand (weighted_gather's custom VJP): the table's
    # gradient against a loop over points and corners (hash collisions accumulate), the
    # points' gradient against central differences of the float64 reference
    rng = np.random.default_rng(5)
    table = rng.normal(size=(4, 64, 2)).astype(np.float32)
    res = np.array([2, 3, 7, 13])
    dense = H.dense_levels(res, 64)
    assert dense.tolist() == [True, True, False, False]
    x = rng.uniform(0.02, 0.98, size=(40, 3)).astype(np.float32)
    g = rng.normal(size=(40, 4, 2)).astype(np.float32)

    def loss(tab, pts):
        return jnp.sum(H.interpolate(tab, pts, res, dense) * g)

    d_tab, d_x = jax.jit(jax.grad(loss, argnums=(0, 1)))(jnp.asarray(table), jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(d_tab), _np_table_gradient(table.shape, x, g, res,
                                                                      dense),
                               rtol=1e-5, atol=1e-5)
    eps = 1e-4
    for a in range(3):
        e = np.zeros(3)
        e[a] = eps
        hi = (_np_interpolate(table, x.astype(np.float64) + e, res, dense) * g).sum(axis=(1, 2))
        lo = (_np_interpolate(table, x.astype(np.float64) - e, res, dense) * g).sum(axis=(1, 2))
        fd = (hi - lo) / (2 * eps)
        # a point within eps of a cell face has a kinked difference: skip those
        inside = np.all(np.abs(np.asarray(x, np.float64)[:, None, a] * res[None]
                               - np.round(np.asarray(x, np.float64)[:, None, a] * res[None]))
                        > 2 * eps * res[None], axis=1)
        assert inside.sum() >= 20
        np.testing.assert_allclose(np.asarray(d_x)[inside, a], fd[inside], rtol=1e-3,
                                   atol=1e-3)


def _init(cfg, n):
    return jax.jit(init_stacked_params, static_argnums=(1, 2))(jax.random.key(0), cfg, n)


HG = get_config("test", encoding="hashgrid", hash_levels=8, hash_log2_table=12,
                hash_max_res=128, net_depth=1, net_width=32, lr_init=1e-2, lr_final=1e-3)


def test_hashgrid_field_renders_and_anti_aliases():
    params = _init(HG, 1)
    assert params[HASH_TABLE].shape == (1, 8, 4096, 2)
    p = jax.tree.map(lambda a: a[0], params)
    # a non-trivial table so that the levels matter
    p[HASH_TABLE] = jax.random.normal(jax.random.key(1), p[HASH_TABLE].shape)
    field = Field(p, jnp.zeros(3), jnp.ones(()), jnp.zeros(3))
    o = jnp.tile(jnp.asarray([[0.0, 0.0, -3.0]]), (4, 1))
    d = jnp.tile(jnp.asarray([[0.01, 0.02, 1.0]]), (4, 1))
    near, far = jnp.full(4, 2.0), jnp.full(4, 4.0)
    radii = jnp.asarray([1e-4, 1e-3, 1e-1, 1.0])
    render = jax.jit(render_rays, static_argnames=("cfg",))
    rgb = np.asarray(render(field, o, d, radii, near, far, None, cfg=HG)["rgb"])
    assert np.all(np.isfinite(rgb))
    # the same ray with a wider cone renders differently (the radius has meaning) ...
    assert np.abs(rgb[0] - rgb[3]).max() > 1e-3
    # ... and without anti-aliasing it does not
    cfg = NerfConfig.from_dict({**HG.to_dict(), "hash_antialias": False})
    rgb2 = np.asarray(render(field, o, d, radii, near, far, None, cfg=cfg)["rgb"])
    np.testing.assert_allclose(rgb2[0], rgb2[3], atol=1e-6)


def test_hashgrid_field_trains_on_the_toy_scene(tmp_path):
    from vrs_jax.nerf import train as T
    from vrs_jax.nerf.toy import make_toy_scene

    scene = make_toy_scene(tmp_path, n_images=12, size=24, query_every=4)
    prep = T.prepare(scene, HG, near=2.0, far=6.0)
    batch = jax.tree.map(jnp.asarray, prep.eval_batch)
    res = T.train(prep, None, steps=150, progress=False)
    after = float(T.make_eval_fn(HG)(res.state.params, prep.cluster_data, batch))
    # Stated margin: >= 21 dB held-out after 150 steps (measured 22.5 dB; the IPE test
    # config reaches 20.4 dB only after 200 steps).
    print(f"hash-grid held-out PSNR after 150 steps: {after:.2f} dB")
    assert after >= 21.0


def test_ilm_round_trip_with_a_hash_table(tmp_path):
    params = _init(HG, 2)
    fields = Field(params, jnp.zeros((2, 3)), jnp.ones(2), jnp.ones((2, 3)))
    m = ilm_lib.ILM(fields=fields, cluster_centers=jnp.zeros((2, 3)),
                    image_cluster=jnp.asarray([0, 1], jnp.int32),
                    membership=jnp.ones((2, 2), bool), near=jnp.ones(2), far=jnp.full(2, 3.0),
                    image_names=("a.png", "b.png"), config=HG)
    p = ilm_lib.save_ilm(tmp_path / "ilm.npz", m)
    back = ilm_lib.load_ilm(p)
    assert back.config == HG and NerfConfig.from_dict(HG.to_dict()) == HG
    for a, b in zip(jax.tree.leaves(m), jax.tree.leaves(back), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # a table that does not match the config is refused
    bad = m.replace(config=NerfConfig.from_dict({**HG.to_dict(), "hash_log2_table": 11}))
    ilm_lib.save_ilm(tmp_path / "bad.npz", bad)
    with pytest.raises(VrsError, match="do not match its config"):
        ilm_lib.load_ilm(tmp_path / "bad.npz")


def test_unknown_encoding_is_an_error():
    with pytest.raises(VrsError, match="unknown NeRF encoding"):
        get_config("test", encoding="fourier")
    assert math.isclose(get_config("cpu-small").hash_init_scale, 1e-4)


def _hash_ilm(seed=0):
    """A two-cluster hash-grid ILM whose tables hold trained-like values (N(0, 0.5), one
    level left all zero, as a level no sample reached keeps its tiny init)."""
    params = _init(HG, 2)
    t = np.asarray(params[HASH_TABLE])  # [C, L, T, F]
    v = np.random.default_rng(seed).normal(0.0, 0.5, t.shape).astype(np.float32)
    v[1, 3] = 0.0
    params = {**params, HASH_TABLE: jnp.asarray(v)}
    fields = Field(params, jnp.zeros((2, 3)), jnp.ones(2), jnp.ones((2, 3)))
    return ilm_lib.ILM(fields=fields, cluster_centers=jnp.zeros((2, 3)),
                       image_cluster=jnp.asarray([0, 1], jnp.int32),
                       membership=jnp.ones((2, 2), bool), near=jnp.ones(2),
                       far=jnp.full(2, 3.0), image_names=("a.png", "b.png"), config=HG)


def test_int8_quantization_against_its_closed_form():
    v = np.random.default_rng(1).normal(0.0, 0.7, (2, 3, 50, 2)).astype(np.float32)
    v[0, 1] = 0.0
    q, scale = ilm_lib.quantize_int8(v)
    assert q.dtype == np.int8 and scale.shape == (2, 3) and scale.dtype == np.float32
    # each table's largest magnitude maps to +-127; an all-zero table decodes to zeros
    np.testing.assert_allclose(scale[1], np.abs(v[1]).max(axis=(-2, -1)) / 127.0, rtol=1e-6)
    assert np.abs(q[1]).max(axis=(-2, -1)).tolist() == [127, 127, 127]
    back = ilm_lib.dequantize_int8(q, scale)
    assert back.dtype == np.float32 and not np.any(back[0, 1])
    # rounding: within half a step of every value
    assert np.all(np.abs(back - v) <= 0.5 * scale[..., None, None] * (1 + 1e-5))


def test_int8_hash_tables_halve_the_stored_field_and_load_within_half_a_step(tmp_path):
    m = _hash_ilm()
    p16 = ilm_lib.save_ilm(tmp_path / "f16.npz", m, float16=True)
    p8 = ilm_lib.save_ilm(tmp_path / "i8.npz", m, float16=True, hash_int8=True)
    table = np.asarray(m.fields.params[HASH_TABLE])
    saved = ilm_lib.map_bytes(p16) - ilm_lib.map_bytes(p8)
    # one byte less per entry, a float32 scale more per (cluster, level)
    expect = table.size - 4 * table.shape[0] * table.shape[1]
    assert abs(saved - expect) < 1024
    assert ilm_lib.stored_param_bytes(HG, True, True) == (
        ilm_lib.stored_param_bytes(HG, True, False) - table[0].size + 4 * table.shape[1])
    back = ilm_lib.load_ilm(p8)
    got = np.asarray(back.fields.params[HASH_TABLE])
    assert got.dtype == np.float32
    t16 = table.astype(np.float16).astype(np.float32)  # float16 first, then int8 of that
    step = np.abs(t16).max(axis=(-2, -1)) / 127.0
    assert np.all(np.abs(got - t16) <= 0.5 * step[..., None, None] * (1 + 1e-5))
    assert not np.any(got[1, 3])
    # every other parameter as float16 storage gives it
    f16 = ilm_lib.load_ilm(p16)
    for k in back.fields.params:
        if k != HASH_TABLE:
            for a, b in zip(jax.tree.leaves(f16.fields.params[k]),
                            jax.tree.leaves(back.fields.params[k]), strict=True):
                np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # the field renders nearly as before: densities and colours of random rays
    rays_o = jnp.zeros((64, 3)) + jnp.asarray([0.0, 0.0, -2.5])
    d = jax.random.normal(jax.random.key(3), (64, 3)) * 0.2 + jnp.asarray([0.0, 0.0, 1.0])
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    r, near, far = jnp.full(64, 1e-3), jnp.ones(64), jnp.full(64, 4.0)
    a = render_rays(f16.field(0), rays_o, d, r, near, far, None, HG)
    b = render_rays(back.field(0), rays_o, d, r, near, far, None, HG)
    assert float(jnp.max(jnp.abs(a["rgb"] - b["rgb"]))) < 0.05


def test_version2_files_and_malformed_int8_tables(tmp_path):
    import io
    import json

    m = _hash_ilm()
    with np.load(io.BytesIO(ilm_lib.to_bytes(m, float16=True)), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays["__meta__"].tobytes().decode())
    meta["format_version"] = 2  # a map saved before int8 tables existed reads as it did
    arrays["__meta__"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    back = ilm_lib.from_bytes(buf.getvalue(), tmp_path / "v2.npz")
    np.testing.assert_array_equal(
        np.asarray(back.fields.params[HASH_TABLE]),
        np.asarray(m.fields.params[HASH_TABLE]).astype(np.float16).astype(np.float32))
    with np.load(io.BytesIO(ilm_lib.to_bytes(m, float16=True, hash_int8=True)),
                 allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    key = "qscale/" + HASH_TABLE
    arrays[key] = arrays[key][:, :2]  # scales that do not fit the table
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    with pytest.raises(VrsError, match="malformed int8 parameter"):
        ilm_lib.from_bytes(buf.getvalue(), tmp_path / "bad.npz")
    del arrays[key]  # an int8 table without its scales
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    with pytest.raises(VrsError, match="no scales"):
        ilm_lib.from_bytes(buf.getvalue(), tmp_path / "bad.npz")


def test_int8_keeps_a_diverged_table_non_finite():
    """A table holding NaN must not read back as finite int8 garbage: loading refuses a
    non-finite field (maps.map), and that check must still see it."""
    v = np.random.default_rng(2).normal(0.0, 0.5, (1, 2, 8, 2)).astype(np.float32)
    v[0, 1, 3, 0] = np.nan
    q, scale = ilm_lib.quantize_int8(v)
    back = ilm_lib.dequantize_int8(q, scale)
    assert np.all(np.isfinite(back[0, 0])) and np.all(np.isnan(back[0, 1]))
    np.testing.assert_allclose(back[0, 0], v[0, 0], atol=0.5 * float(scale[0, 0]) * 1.00001)
