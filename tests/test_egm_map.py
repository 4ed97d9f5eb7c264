"""EGM pytree: stored arrays round trip, consistency checks, byte breakdown by part."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from vrs_jax import geometry as g
from vrs_jax.egm import map as M
from vrs_jax.egm.build import select_keypoints
from vrs_jax.egm.retrieval import Vocabulary
from vrs_jax.errors import VrsError


def _toy(n=3, m=40, k_max=16, baseline=False, seed=0, dist=True) -> M.EGM:
    """A consistent map: m points seen by n cameras, keypoints = exact projections."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-1, -1, 3], [1, 1, 5], (m, 3))
    R = np.stack([g.axis_angle_to_rot(np.array([0.0, 0.05 * i, 0.01 * i])) for i in range(n)])
    t = np.stack([np.array([-0.2 * i, 0.0, 0.1 * i]) for i in range(n)])
    K = np.tile(g.intrinsics_matrix(200.0, 210.0, 160.0, 120.0), (n, 1, 1))
    D = np.zeros((n, 5))
    if dist:
        D[1] = [-0.1, 0.02, 0.001, -0.001, 0.0]
        D[2] = [-0.1, 0.02, 0.0, 0.0, 0.003]
    kps, pis, lds = [], [], []
    for i in range(n):
        idx = rng.choice(m, size=min(k_max - i, m), replace=False)  # rows of different lengths
        uv, _ = g.project(K[i], R[i], t[i], X[idx], D[i])
        kp = np.concatenate([uv, rng.uniform(1, 5, (len(idx), 1)),
                             rng.uniform(-3, 3, (len(idx), 1))], 1)
        kps.append(kp)
        pis.append(idx)
        lds.append(rng.normal(size=(len(idx), 8)))
    vocab = Vocabulary(centers=jnp.asarray(rng.normal(size=(4, 8)), jnp.float32), power=0.5)
    gd = rng.normal(size=(n, 32))
    gd /= np.linalg.norm(gd, axis=1, keepdims=True)
    return M.make_egm(X, R, t, K, D, np.tile([320, 240], (n, 1)), kps, pis, gd, vocab,
                      [f"seq/im{i}.png" for i in range(n)], k_max=k_max,
                      local_desc=lds if baseline else None)


def _angle_diff(a, b):
    return np.abs(np.mod(np.asarray(a, np.float64) - b + np.pi, 2 * np.pi) - np.pi)


def _assert_same(a: M.EGM, b: M.EGM):
    """``b`` is ``a`` after the storage round trip: exact where stored exactly, within the
    quantisation bounds elsewhere."""
    assert a.names == b.names
    for f in ("R", "t", "K", "dist", "sizes", "point_idx", "kp_mask"):
        np.testing.assert_array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)),
                                      err_msg=f)
    X, X2 = np.asarray(a.points3d, np.float64), np.asarray(b.points3d, np.float64)
    extent = X.max(0) - X.min(0)
    assert np.all(np.abs(X - X2) <= extent / (2 * 65535) + 1e-6)  # 16-bit fixed point
    mask = np.asarray(a.kp_mask)
    ka, kb = np.asarray(a.keypoints, np.float64)[mask], np.asarray(b.keypoints, np.float64)[mask]
    assert np.abs(ka[:, :2] - kb[:, :2]).max() <= 1 / 32 + 1e-3  # float32 at a few 100 px
    ls = np.log2(ka[:, 2])
    assert np.abs(ls - np.log2(kb[:, 2])).max() <= (ls.max() - ls.min()) / 510 + 1e-5
    assert _angle_diff(ka[:, 3], kb[:, 3]).max() <= np.pi / 256 + 1e-5
    k32, pi32 = np.asarray(b.keypoints)[mask][:, 3], np.float32(np.pi)
    assert np.all((k32 >= -pi32) & (k32 < pi32))  # [-pi, pi) as float32
    ga, gb = np.asarray(a.global_desc), np.asarray(b.global_desc)
    np.testing.assert_allclose(np.linalg.norm(gb, axis=1), 1.0, atol=1e-5)
    np.testing.assert_allclose(ga @ ga.T, gb @ gb.T, atol=1e-2)  # int8 on disk
    np.testing.assert_array_equal(a.vocab.centers, b.vocab.centers)
    for f in ("local_mean", "local_proj"):
        va, vb = getattr(a.vocab, f), getattr(b.vocab, f)
        assert (va is None) == (vb is None), f
        if va is not None:
            np.testing.assert_array_equal(va, vb, err_msg=f)
    assert (a.local_desc is None) == (b.local_desc is None)
    if a.local_desc is not None:
        np.testing.assert_allclose(a.local_desc, b.local_desc, atol=2e-3)  # float16 on disk


@pytest.mark.parametrize("baseline", [False, True])
def test_arrays_roundtrip(baseline):
    egm = _toy(baseline=baseline)
    a = M.to_arrays(egm)
    desc = M.descriptor_arrays(egm)["local_desc"] if baseline else None
    assert "local_desc" not in a  # the EGM's arrays never hold the descriptors
    back = M.from_arrays(a, egm.names, egm.k_max, Path("x"), desc)
    _assert_same(egm, back)
    assert back.is_baseline == baseline


def test_local_whitening_of_the_vocabulary_round_trips_and_is_checked():
    """A vocabulary that whitens the local descriptors (RetrievalConfig.local_dim) is stored
    with the map; a projection that does not fit the words is refused in one line."""
    rng = np.random.default_rng(7)
    egm = _toy()
    vocab = egm.vocab.replace(local_mean=jnp.asarray(rng.normal(size=16), jnp.float32),
                              local_proj=jnp.asarray(rng.normal(size=(16, 8)), jnp.float32))
    egm = egm.replace(vocab=vocab)
    a = M.to_arrays(egm)
    _assert_same(egm, M.from_arrays(a, egm.names, egm.k_max, Path("x")))
    a["local_proj"] = a["local_proj"][:, :5]
    with pytest.raises(VrsError, match="local projection") as e:
        M.from_arrays(a, egm.names, egm.k_max, Path("m/egm.npz"))
    assert "m/egm.npz" in str(e.value) and "\n" not in str(e.value)


def test_egm_is_a_pytree_for_jit():
    egm = _toy()

    @jax.jit
    def n_links(e: M.EGM):
        return jnp.sum(e.kp_mask), e.points3d[jnp.maximum(e.point_idx, 0)].sum()

    c, _ = n_links(egm)
    assert int(c) == int(np.asarray(egm.kp_mask).sum())
    leaves = jax.tree_util.tree_leaves(egm)
    assert all(isinstance(x, jax.Array) for x in leaves)
    assert egm.without_local_descriptors().local_desc is None


def test_mask_is_prefix_and_padding():
    egm = _toy()
    mask = np.asarray(egm.kp_mask)
    counts = mask.sum(1)
    assert counts.tolist() == [16, 15, 14]
    assert np.all(np.asarray(egm.point_idx)[~mask] == -1)


def test_reprojection_errors_of_exact_map_are_zero():
    egm = _toy()
    err = M.reprojection_errors(egm)
    assert len(err) == int(np.asarray(egm.kp_mask).sum())
    assert err.max() < 1e-3  # float32 storage
    # with other poses they are not
    t2 = np.asarray(egm.t) + [0.05, 0, 0]
    assert np.median(M.reprojection_errors(egm, t=t2)) > 1.0


def test_inconsistent_arrays_are_rejected():
    egm = _toy()
    arrays = M.to_arrays(egm)
    arrays["point_idx"] = M.pack_indices(np.full(len(arrays["kp_scale"]), 1000), 2000)
    with pytest.raises(VrsError, match="point index out of range") as e:
        M.from_arrays(arrays, egm.names, egm.k_max, Path("m/egm.npz"))
    assert "m/egm.npz" in str(e.value)
    arrays = M.to_arrays(egm)
    del arrays["R"]
    with pytest.raises(VrsError, match="lack"):
        M.from_arrays(arrays, egm.names, egm.k_max, Path("m/egm.npz"))


@pytest.mark.parametrize("key, value, match", [
    ("kp_scale", lambda x: x.astype(np.int16), "kp_scale has dtype int16"),
    ("kp_xy_res", lambda x: x.astype(np.float32), "kp_xy_res has dtype float32"),
    ("point_idx", lambda x: x.astype(np.int64), "point_idx has dtype int64"),
    ("points_q", lambda x: x[..., :1].astype(np.uint16), "points_q has dtype uint16"),
    ("global_desc", lambda x: x.astype(np.float16), "global_desc has dtype float16"),
    ("kp_angle", lambda x: x[:-1], "keypoints/point_idx do not match the counts"),
    ("kp_xy_exact_idx", lambda x: np.array([10 ** 6], np.uint32), "exact keypoint positions"),
    ("points_step", lambda x: -x, "positive step"),
    ("kp_log2_scale_range", lambda x: np.array([0, np.nan], np.float32), "scale range"),
])
def test_ill_typed_or_tampered_arrays_fail_in_one_line(key, value, match):
    egm = _toy()
    arrays = M.to_arrays(egm)
    arrays[key] = value(arrays[key])
    with pytest.raises(VrsError, match=match) as e:
        M.from_arrays(arrays, egm.names, egm.k_max, Path("m/egm.npz"))
    assert "m/egm.npz" in str(e.value) and "\n" not in str(e.value)


def test_keypoints_off_their_projection_round_trip_within_bounds():
    """Keypoints 0-6 px from their point's projection (residual int8 at 1/16 px) and a few
    far off (stored exactly): positions within 1/32 px, scale and angle within half a
    level, against the float64 originals."""
    egm = _toy(n=4, m=300, k_max=200, seed=3)
    rng = np.random.default_rng(1)
    mask = np.asarray(egm.kp_mask)
    kp = np.asarray(egm.keypoints).copy()
    kp[..., :2] += np.where(mask[..., None], rng.uniform(-6, 6, kp[..., :2].shape), 0)
    kp[0, :3, :2] += 40.0  # residual beyond int8 at 1/16 px
    kp[..., 2] = np.where(mask, np.exp2(rng.uniform(-1, 6, mask.shape)), 1.0)
    kp[..., 3] = np.where(mask, rng.uniform(-np.pi, np.pi, mask.shape), 0.0)
    egm = egm.replace(keypoints=jnp.asarray(kp))
    a = M.to_arrays(egm)
    assert len(a["kp_xy_exact_idx"]) == 3 and a["kp_xy_res"].dtype == np.int8
    assert a["point_idx"].shape == (mask.sum(), 2)  # 300 points: two bytes
    assert a["points_q"].shape == (300, 3, 2)
    back = M.from_arrays(a, egm.names, egm.k_max, Path("x"))
    _assert_same(egm, back)
    # the map's links reproject as before, to within the keypoint and point quantisation
    e0, e1 = M.reprojection_errors(egm), M.reprojection_errors(back)
    assert np.abs(e0 - e1).max() <= 1 / 32 * np.sqrt(2) + M.POINT_MAX_PX + 1e-3


def test_points_take_more_bytes_when_two_would_move_projections():
    """A point 100 km away stretches the box: 16-bit steps (1.5 m) would move the near points'
    projections by pixels, so more bytes are used and no projection moves > POINT_MAX_PX."""
    egm = _toy(m=40)
    X = np.asarray(egm.points3d).copy()
    X[0] = [1e5, 0, 4]
    egm = egm.replace(points3d=jnp.asarray(X))
    a = M.to_arrays(egm)
    assert a["points_q"].shape[2] > 2
    back = M.from_arrays(a, egm.names, egm.k_max, Path("x"))
    img, slot, pts = M.observations(egm)
    moved = np.abs(
        M.link_projections(back.points3d, egm.R, egm.t, egm.K, egm.dist, img, pts)
        - M.link_projections(egm.points3d, egm.R, egm.t, egm.K, egm.dist, img, pts))
    assert moved.max() <= M.POINT_MAX_PX + 1e-3


def test_link_projections_match_geometry_project():
    egm = _toy()
    img, slot, pts = M.observations(egm)
    uv = M.link_projections(egm.points3d, egm.R, egm.t, egm.K, egm.dist, img, pts)
    for i in range(egm.num_images):
        ref, _ = g.project(np.asarray(egm.K[i], np.float64), np.asarray(egm.R[i], np.float64),
                           np.asarray(egm.t[i], np.float64),
                           np.asarray(egm.points3d, np.float64)[pts[img == i]],
                           np.asarray(egm.dist[i], np.float64))
        np.testing.assert_allclose(uv[img == i], ref, atol=1e-6)


@pytest.mark.parametrize("n, nbytes", [(1, 1), (256, 1), (257, 2), (65536, 2), (65537, 3),
                                       (2 ** 24 + 1, 4)])
def test_pack_indices_uses_the_fewest_bytes(n, nbytes):
    idx = np.unique(np.r_[0, n - 1, np.random.default_rng(0).integers(0, n, 50)])
    b = M.pack_indices(idx, n)
    assert b.dtype == np.uint8 and b.shape == (len(idx), nbytes)
    np.testing.assert_array_equal(M.unpack_indices(b), idx)
    # the same bytes numpy writes for the natural little-endian integer
    np.testing.assert_array_equal(b, idx.astype("<u8").view(np.uint8).reshape(-1, 8)[:, :nbytes])


def test_npz_parts_add_up():
    egm = _toy(baseline=True)
    buf = io.BytesIO()
    np.savez(buf, **M.to_arrays(egm), **M.descriptor_arrays(egm))
    raw = buf.getvalue()
    parts = M.npz_parts(raw)
    assert sum(parts.values()) == len(raw)
    links = int(np.asarray(egm.kp_mask).sum())
    assert parts["keypoints"] >= links * 4  # int8 x, y residual, uint8 scale and angle
    assert parts["links"] >= links  # one byte per point index (40 points)
    assert parts["points3d"] >= egm.num_points * 6  # 16-bit fixed point
    assert parts["local descriptors"] >= links * 8 * 2  # float16
    with zipfile.ZipFile(io.BytesIO(raw)) as z:
        assert all(i.compress_type == zipfile.ZIP_STORED for i in z.infolist())


def test_select_keypoints_prefers_long_tracks_and_spreads():
    rng = np.random.default_rng(0)
    # 100 keypoints in the left half with long tracks, 20 in the right half with short ones
    kp = np.zeros((120, 4))
    kp[:100, :2] = rng.uniform([0, 0], [50, 100], (100, 2))
    kp[100:, :2] = rng.uniform([50, 0], [100, 100], (20, 2))
    point_of_kp = np.arange(120)
    point_of_kp[5] = -1
    track = np.r_[np.full(100, 5), np.full(20, 2)]
    err = np.zeros(120)
    sel = select_keypoints(kp, point_of_kp, track, err, (100, 100), 40, (2, 1))
    assert len(sel) == 40 and 5 not in sel and len(set(sel)) == 40
    assert np.sum(sel >= 100) == 20  # the right half keeps all it has despite short tracks
    sel = select_keypoints(kp, point_of_kp, track, err, (100, 100), 10, (1, 1))
    assert np.all(sel < 100)  # no spreading: longest tracks win
    assert select_keypoints(kp, np.full(120, -1), track, err, (100, 100), 10, (2, 2)).size == 0


def _old_padded_rows(keypoints, point_idx, local_desc, n, k_max):
    """Frozen copy of make_egm's per-image padding loop before it was vectorised."""
    counts = [min(len(k), k_max) if k_max is not None else len(k) for k in keypoints]
    km = int(k_max if k_max is not None else max(counts + [0]))
    kp = np.zeros((n, km, 4), np.float32)
    kp[..., 2] = 1.0
    pi = np.full((n, km), -1, np.int32)
    mask = np.zeros((n, km), bool)
    ld = None
    if local_desc is not None:
        d = max([x.shape[-1] for x in local_desc if x.ndim == 2] + [0])
        ld = np.zeros((n, km, d), np.float32)
    for i in range(n):
        c = counts[i]
        kp[i, :c] = np.asarray(keypoints[i], np.float32)[:c]
        pi[i, :c] = np.asarray(point_idx[i], np.int32)[:c]
        mask[i, :c] = True
        if ld is not None:
            ld[i, :c] = np.asarray(local_desc[i], np.float32)[:c]
    return kp, pi, mask, ld


@pytest.mark.parametrize("k_max", [None, 0, 5, 16, 40])
def test_make_egm_padding_equals_the_former_loop(k_max):
    rng = np.random.default_rng(7)
    lengths = [12, 0, 30, 1, 16, 0]  # empty rows, rows shorter and longer than k_max
    n = len(lengths)
    kps = [rng.normal(size=(c, 4)) for c in lengths]  # float64 in: cast as before
    pis = [rng.integers(0, 50, c) for c in lengths]
    lds = [rng.normal(size=(c, 8)).astype(np.float32) for c in lengths]
    vocab = Vocabulary(centers=jnp.zeros((2, 8), jnp.float32))
    egm = M.make_egm(rng.normal(size=(50, 3)), np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 3)),
                     np.tile(np.eye(3), (n, 1, 1)), np.zeros((n, 5)), np.ones((n, 2)), kps, pis,
                     np.zeros((n, 4)), vocab, [f"im{i}" for i in range(n)], k_max=k_max,
                     local_desc=lds)
    for got, want in zip((egm.keypoints, egm.point_idx, egm.kp_mask, egm.local_desc),
                         _old_padded_rows(kps, pis, lds, n, k_max), strict=True):
        got = np.asarray(got)
        assert got.dtype == want.dtype and got.shape == want.shape
        np.testing.assert_array_equal(got, want)
