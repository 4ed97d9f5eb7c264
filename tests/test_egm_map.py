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


def _assert_same(a: M.EGM, b: M.EGM):
    assert a.names == b.names
    for f in ("points3d", "R", "t", "K", "dist", "sizes", "keypoints", "point_idx", "kp_mask"):
        np.testing.assert_array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)),
                                      err_msg=f)
    np.testing.assert_allclose(a.global_desc, b.global_desc, atol=1e-3)  # float16 on disk
    np.testing.assert_array_equal(a.vocab.centers, b.vocab.centers)
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
    arrays["point_idx"] = arrays["point_idx"] + 1000  # out of range
    with pytest.raises(VrsError, match="point index out of range") as e:
        M.from_arrays(arrays, egm.names, egm.k_max, Path("m/egm.npz"))
    assert "m/egm.npz" in str(e.value)
    arrays = M.to_arrays(egm)
    del arrays["R"]
    with pytest.raises(VrsError, match="lack"):
        M.from_arrays(arrays, egm.names, egm.k_max, Path("m/egm.npz"))


def test_npz_parts_add_up():
    egm = _toy(baseline=True)
    buf = io.BytesIO()
    np.savez(buf, **M.to_arrays(egm), **M.descriptor_arrays(egm))
    raw = buf.getvalue()
    parts = M.npz_parts(raw)
    assert sum(parts.values()) == len(raw)
    links = int(np.asarray(egm.kp_mask).sum())
    assert parts["keypoints+links"] >= links * (16 + 4)
    assert parts["points3d"] >= egm.num_points * 12
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
