"""EGM pytree: save/load, format version, corrupt files, byte breakdown."""

from __future__ import annotations

import json
import zipfile

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
                      local_desc=lds if baseline else None, config="toy")


def _assert_same(a: M.EGM, b: M.EGM):
    assert a.names == b.names and a.config == b.config
    for f in ("points3d", "R", "t", "K", "dist", "sizes", "keypoints", "point_idx", "kp_mask",
              "cluster"):
        np.testing.assert_array_equal(np.asarray(getattr(a, f)), np.asarray(getattr(b, f)),
                                      err_msg=f)
    np.testing.assert_allclose(a.global_desc, b.global_desc, atol=1e-3)  # float16 on disk
    np.testing.assert_array_equal(a.vocab.centers, b.vocab.centers)
    assert (a.local_desc is None) == (b.local_desc is None)
    if a.local_desc is not None:
        np.testing.assert_array_equal(a.local_desc, b.local_desc)


@pytest.mark.parametrize("baseline", [False, True])
def test_save_load_roundtrip(tmp_path, baseline):
    egm = _toy(baseline=baseline)
    M.save_egm(egm, tmp_path / "map", info={"note": "x"})
    back = M.load_egm(tmp_path / "map")
    _assert_same(egm, back)
    assert M.read_metadata(tmp_path / "map")["info"] == {"note": "x"}
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


def test_wrong_version_and_corrupt_files(tmp_path):
    d = M.save_egm(_toy(), tmp_path / "map")
    meta = json.loads((d / M.JSON_NAME).read_text())
    meta["format_version"] = 999
    (d / M.JSON_NAME).write_text(json.dumps(meta))
    with pytest.raises(VrsError, match="format version 999") as e:
        M.load_egm(d)
    assert M.JSON_NAME in str(e.value)

    d = M.save_egm(_toy(), tmp_path / "map2")
    (d / M.JSON_NAME).write_text("{not json")
    with pytest.raises(VrsError, match="corrupt map metadata"):
        M.load_egm(d)

    d = M.save_egm(_toy(), tmp_path / "map3")
    raw = bytearray((d / M.NPZ_NAME).read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    (d / M.NPZ_NAME).write_bytes(bytes(raw))
    with pytest.raises(VrsError, match="do not match") as e:
        M.load_egm(d)
    assert M.NPZ_NAME in str(e.value)

    d = M.save_egm(_toy(), tmp_path / "map4")
    (d / M.NPZ_NAME).unlink()
    with pytest.raises(VrsError, match="arrays missing"):
        M.load_egm(d)
    with pytest.raises(VrsError, match="not found"):
        M.load_egm(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(VrsError, match="no egm.json"):
        M.load_egm(tmp_path / "empty")


def test_inconsistent_arrays_are_rejected(tmp_path):
    """A truncated npz whose checksum was updated (e.g. a hand-edited file) still fails."""
    egm = _toy()
    arrays = M._arrays(egm)
    arrays["point_idx"] = arrays["point_idx"] + 1000  # out of range
    npz = M._npz_bytes(arrays)
    d = tmp_path / "map"
    d.mkdir()
    (d / M.NPZ_NAME).write_bytes(npz)
    (d / M.JSON_NAME).write_text(json.dumps(M._metadata(egm, npz, None)))
    with pytest.raises(VrsError, match="point index out of range"):
        M.load_egm(d)


def test_map_bytes_match_files(tmp_path):
    for baseline in (False, True):
        egm = _toy(baseline=baseline)
        d = M.save_egm(egm, tmp_path / f"m{baseline}")
        b = M.map_bytes(d)
        on_disk = (d / M.NPZ_NAME).stat().st_size + (d / M.JSON_NAME).stat().st_size
        assert b["total"] == on_disk
        assert b == M.map_bytes(egm)  # in-memory figures are the saved ones
        assert (b["local descriptors"] > 0) == baseline
        # each part is at least its raw array bytes
        links = int(np.asarray(egm.kp_mask).sum())
        assert b["keypoints+links"] >= links * (16 + 4)
        assert b["points3d"] >= egm.num_points * 12
        if baseline:
            assert b["local descriptors"] >= links * 8 * 4
            assert b["total_without_local_descriptors"] == b["total"] - b["local descriptors"]
        with zipfile.ZipFile(d / M.NPZ_NAME) as z:
            assert all(i.compress_type == zipfile.ZIP_STORED for i in z.infolist())


def test_baseline_bytes_without_materialising():
    base = _toy(baseline=True)
    assert M.baseline_bytes(base.without_local_descriptors(), 8) == M.map_bytes(base)


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
