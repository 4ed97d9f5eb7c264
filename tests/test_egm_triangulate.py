"""Matching, epipolar verification and known-pose triangulation through pycolmap."""

from __future__ import annotations

import itertools
import warnings
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from vrs_jax import geometry as g
from vrs_jax.data.scene import Scene
from vrs_jax.egm import triangulate as T
from vrs_jax.errors import VrsError

W, H = 320, 240


def _scene(n=4, dist=None, seed=0) -> Scene:
    """n cameras on an arc 3-4 m in front of a point cloud around the origin."""
    R, t = [], []
    for i in range(n):
        a = np.radians(-15 + 30 * i / max(n - 1, 1))
        Ri = g.axis_angle_to_rot(np.array([0.0, -a, 0.0]))  # optical axis towards the origin
        c = np.array([-3.5 * np.sin(a), 0.1 * i, -3.5 * np.cos(a)])
        R.append(Ri)
        t.append(-Ri @ c)
    K = np.tile(g.intrinsics_matrix(250.0, 260.0, 161.0, 119.0), (n, 1, 1))
    d = np.zeros((n, 5)) if dist is None else np.tile(dist, (n, 1))
    return Scene(root=Path("/synthetic"), names=[f"im{i}.png" for i in range(n)],
                 image_paths=[Path(f"/synthetic/im{i}.png") for i in range(n)], K=K, dist=d,
                 sizes=np.tile([W, H], (n, 1)), R=np.stack(R), t=np.stack(t),
                 has_pose=np.ones(n, bool), is_query=np.zeros(n, bool))


def _observe(scene, X, noise=0.2, seed=0):
    """Keypoints [M, 4] per image: the projections of X (+ noise), keypoint k = point k."""
    rng = np.random.default_rng(seed)
    kps = []
    for i in range(len(scene)):
        uv, z = g.project(scene.K[i], scene.R[i], scene.t[i], X, scene.dist[i])
        assert np.all(z > 0) and np.all((uv > 0) & (uv < [W, H]))
        kp = np.zeros((len(X), 4), np.float32)
        kp[:, :2] = uv + rng.normal(0, noise, uv.shape)
        kp[:, 2] = 2.0
        kps.append(kp)
    return kps


def _points(m=200, seed=0):
    return np.random.default_rng(seed).uniform([-0.8, -0.6, -0.5], [0.8, 0.6, 0.5], (m, 3))


def _dlt(scene, obs):
    """Independent multi-view linear triangulation (numpy), obs = [(image, uv)] undistorted."""
    rows = []
    for i, uv in obs:
        x = g.unproject(scene.K[i], np.asarray(uv, float)[None], scene.dist[i])[0]
        P = np.concatenate([scene.R[i], scene.t[i][:, None]], 1)
        rows += [x[0] * P[2] - P[0], x[1] * P[2] - P[1]]
    _, _, vt = np.linalg.svd(np.asarray(rows))
    return vt[-1, :3] / vt[-1, 3]


def _all_matches(n, m):
    idx = np.stack([np.arange(m), np.arange(m)], 1)
    return {(i, j): idx.copy() for i, j in itertools.combinations(range(n), 2)}


@pytest.mark.parametrize("dist", [None, np.array([-0.12, 0.05, 1e-3, -2e-3, 0.0]),
                                  np.array([-0.1, 0.02, 0.0, 0.0, 0.01])])
def test_triangulation_recovers_points(dist):
    scene = _scene(4, dist)
    X = _points()
    kps = _observe(scene, X)
    tr = T.triangulate_known_poses(scene, kps, _all_matches(4, len(X)))
    assert tr.num_points >= 0.95 * len(X)
    # each point's track is the 4 observations of one true point
    assert np.all(tr.track_lengths == 4)
    true_idx = np.array([tr.obs_kp[tr.obs_point == p][0] for p in range(tr.num_points)])
    err = np.linalg.norm(tr.points3d - X[true_idx], axis=1)
    # 0.2 px noise at 250 px focal length, 3.5 m away, 30 deg arc: a few mm
    assert np.median(err) < 1e-2
    # as accurate as an independent multi-view DLT on the same observations
    dlt = np.stack([_dlt(scene, [(i, kps[i][k, :2]) for i in range(4)]) for k in true_idx])
    assert np.median(np.linalg.norm(tr.points3d - dlt, axis=1)) < 1e-3
    assert np.median(err) < 1.2 * np.median(np.linalg.norm(dlt - X[true_idx], axis=1))
    assert np.median(tr.obs_errors) < 0.4
    assert np.all(tr.obs_errors <= T.TriangulationConfig().max_reproj_error + 1e-6)
    # point_of_kp agrees with the observation lists
    for i in range(4):
        sel = tr.obs_image == i
        np.testing.assert_array_equal(tr.point_of_kp[i][tr.obs_kp[sel]], tr.obs_point[sel])


def test_outlier_matches_are_rejected_by_verification_and_filters():
    scene = _scene(3)
    X = _points(150)
    kps = _observe(scene, X)
    rng = np.random.default_rng(3)
    cfg = T.TriangulationConfig()
    matches = {}
    for i, j in itertools.combinations(range(3), 2):
        good = np.stack([np.arange(100), np.arange(100)], 1)
        bad = np.stack([np.arange(100, 150), rng.permutation(np.arange(100, 150))], 1)
        m = np.concatenate([good, bad])
        v = T.verify_matches(scene, i, j, kps[i], kps[j], m, cfg)
        # all true matches survive; nearly all random ones are off their epipolar line
        assert set(map(tuple, good)) <= set(map(tuple, v))
        assert len(v) - len(good) < 10
        matches[(i, j)] = v
    tr = T.triangulate_known_poses(scene, kps, matches, cfg)
    # tracks of true matches (same keypoint index everywhere) are complete and accurate
    consistent = np.array([len(set(tr.obs_kp[tr.obs_point == p])) == 1
                           for p in range(tr.num_points)])
    true_idx = np.array([tr.obs_kp[tr.obs_point == p][0] for p in range(tr.num_points)])
    good = consistent & (true_idx < 100)
    assert good.sum() >= 98
    assert np.all(tr.track_lengths[good] == 3)
    assert np.all(np.linalg.norm(tr.points3d[good] - X[true_idx[good]], axis=1) < 0.03)
    # a wrong match that lies on its epipolar line cannot be caught with two views; it can
    # make a two-view point (a longer wrong track must be consistent in 3 views: rare)
    n_wrong = sum(len(v) - 100 for v in matches.values())
    assert (~good).sum() <= n_wrong
    assert np.mean(tr.track_lengths[~good] == 2) >= 0.8


def test_sampson_errors_match_opencv():
    scene = _scene(2)
    rng = np.random.default_rng(0)
    uv1 = rng.uniform([0, 0], [W, H], (50, 2))
    uv2 = rng.uniform([0, 0], [W, H], (50, 2))
    K = scene.K[0].copy()
    K[1, 1] = K[0, 0]  # OpenCV's Sampson distance is in pixels: equal focal lengths
    e = T.sampson_errors(uv1, uv2, K, None, scene.R[0], scene.t[0], K, None, scene.R[1],
                         scene.t[1])
    Rr = scene.R[1] @ scene.R[0].T
    tr = scene.t[1] - Rr @ scene.t[0]
    F = np.linalg.inv(K).T @ g.skew(tr) @ Rr @ np.linalg.inv(K)
    ref = [np.sqrt(cv2.sampsonDistance(np.r_[a, 1.0][:, None], np.r_[b, 1.0][:, None], F))
           for a, b in zip(uv1, uv2, strict=True)]
    np.testing.assert_allclose(e, ref, rtol=1e-6)
    # exact correspondences have zero error
    X = _points(20)
    p1, _ = g.project(scene.K[0], scene.R[0], scene.t[0], X)
    p2, _ = g.project(scene.K[1], scene.R[1], scene.t[1], X)
    e0 = T.sampson_errors(p1, p2, scene.K[0], None, scene.R[0], scene.t[0], scene.K[1], None,
                          scene.R[1], scene.t[1])
    assert e0.max() < 1e-6


def test_match_pair_finds_identical_descriptors():
    rng = np.random.default_rng(0)
    d = rng.normal(size=(40, 128)).astype(np.float32)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    perm = rng.permutation(40)
    m = T.match_pair(d, d[perm], T.TriangulationConfig())
    assert len(m) == 40
    np.testing.assert_array_equal(perm[m[:, 1]], m[:, 0])
    assert T.match_pair(d[:0], d, T.TriangulationConfig()).shape == (0, 2)


def test_max_tri_angles_brute_force():
    rng = np.random.default_rng(0)
    centers = rng.normal(size=(30, 3))
    X = rng.normal(size=(30, 3)) + [0, 0, 5]
    obs_point = rng.integers(0, 8, 30)
    ang = T._max_tri_angles(centers, X, obs_point, 8)
    for p in range(8):
        rays = [(X[o] - centers[o]) / np.linalg.norm(X[o] - centers[o])
                for o in np.flatnonzero(obs_point == p)]
        best = max([np.arccos(np.clip(a @ b, -1, 1)) for a, b in
                    itertools.combinations(rays, 2)] + [0.0])
        assert ang[p] == pytest.approx(best, abs=1e-9)


def test_subset_points_reindexes():
    scene = _scene(3)
    X = _points(60)
    tr = T.triangulate_known_poses(scene, _observe(scene, X), _all_matches(3, 60))
    keep = np.arange(tr.num_points) % 2 == 0
    sub = T.subset_points(tr, keep)
    assert sub.num_points == keep.sum()
    np.testing.assert_allclose(sub.points3d, tr.points3d[keep])
    for i in range(3):
        ok = sub.point_of_kp[i] >= 0
        np.testing.assert_allclose(sub.points3d[sub.point_of_kp[i][ok]],
                                   tr.points3d[tr.point_of_kp[i][ok]])
        assert np.all(keep[tr.point_of_kp[i][ok]])


def test_depth_range_filter_drops_implausible_points():
    scene = _scene(3)
    X = _points(60)
    kps = _observe(scene, X)
    ranges = np.tile([1.0, 10.0], (3, 1))
    tr = T.triangulate_known_poses(scene, kps, _all_matches(3, 60), depth_ranges=ranges)
    assert tr.num_points >= 57
    with pytest.warns(UserWarning, match="no 3D point"):
        tr = T.triangulate_known_poses(scene, kps, _all_matches(3, 60),
                                       depth_ranges=np.tile([20.0, 30.0], (3, 1)))
    assert tr.num_points == 0 and tr.stats["points_outside_depth_range"] >= 57


# ----------------------------------------------------------------------------- bad input


def test_bad_inputs_raise_vrs_error():
    scene = _scene(3)
    X = _points(30)
    kps = _observe(scene, X)
    m = _all_matches(3, 30)
    with pytest.raises(VrsError, match="index keypoints that do not exist"):
        T.triangulate_known_poses(scene, kps, {**m, (0, 1): np.array([[0, 99]])})
    with pytest.raises(VrsError, match="bad image pair"):
        T.triangulate_known_poses(scene, kps, {(0, 7): np.array([[0, 0]])})
    with pytest.raises(VrsError, match="given twice"):
        T.triangulate_known_poses(scene, kps, {**m, (1, 0): m[(0, 1)]})
    bad = [k.copy() for k in kps]
    bad[1][3, 0] = np.nan
    with pytest.raises(VrsError, match="NaN"):
        T.triangulate_known_poses(scene, bad, m)
    R = scene.R.copy()
    R[2] *= 2.0
    with pytest.raises(VrsError, match="rotation"):
        T.triangulate_known_poses(Scene(**{**scene.__dict__, "R": R}), kps, m)
    K = scene.K.copy()
    K[0, 0, 0] = -1
    with pytest.raises(VrsError, match="focal"):
        T.triangulate_known_poses(Scene(**{**scene.__dict__, "K": K}), kps, m)


def test_no_matches_and_empty_images_warn_and_return_empty():
    scene = _scene(3)
    kps = [np.zeros((0, 4), np.float32)] * 3
    with pytest.warns(UserWarning, match="no verified matches"):
        tr = T.triangulate_known_poses(scene, kps, {(0, 1): np.zeros((0, 2), np.int64)})
    assert tr.num_points == 0 and all(len(p) == 0 for p in tr.point_of_kp)
    # one image without keypoints among good ones is fine (it just gets no points)
    X = _points(40)
    kps = _observe(scene, X)
    kps[2] = np.zeros((0, 4), np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        tr = T.triangulate_known_poses(scene, kps, {(0, 1): _all_matches(2, 40)[(0, 1)]})
    assert tr.num_points >= 38 and len(tr.point_of_kp[2]) == 0


def test_degenerate_geometry_yields_nothing_with_a_warning():
    # all cameras at the same centre (pure rotation): no triangulation angle
    scene = _scene(3)
    scene = Scene(**{**scene.__dict__, "t": np.zeros((3, 3))})
    X = _points(40) + [0, 0, 4]
    kps = _observe(scene, X)
    with pytest.warns(UserWarning, match="no 3D point"):
        tr = T.triangulate_known_poses(scene, kps, _all_matches(3, 40))
    assert tr.num_points == 0


def test_build_reconstruction_poses_roundtrip():
    scene = _scene(3)
    rec = T.build_reconstruction(scene, [np.zeros((5, 2))] * 3)
    assert rec.num_reg_images() == 3
    for i in range(3):
        im = rec.image(i + 1)
        np.testing.assert_allclose(im.cam_from_world().rotation.matrix(), scene.R[i],
                                   atol=1e-12)
        np.testing.assert_allclose(im.cam_from_world().translation, scene.t[i], atol=1e-12)
        assert isinstance(im, pycolmap.Image) and im.num_points2D() == 5


# ----------------------------------------------- vectorised collection: same result as before


def _old_collect(scene, keypoints, rec, stats):
    """Frozen copy of T._collect before it was vectorised (per-observation loop)."""
    ids = sorted(rec.point3D_ids())
    X = np.array([rec.point3D(p).xyz for p in ids], np.float64).reshape(-1, 3)
    obs_image, obs_kp, obs_point = [], [], []
    for m, p in enumerate(ids):
        for el in rec.point3D(p).track.elements:
            obs_image.append(el.image_id - 1)
            obs_kp.append(el.point2D_idx)
            obs_point.append(m)
    obs_image = np.asarray(obs_image, np.int64)
    obs_kp = np.asarray(obs_kp, np.int64)
    obs_point = np.asarray(obs_point, np.int64)
    obs_err = np.zeros(len(obs_image))
    point_of_kp = [np.full(len(k), -1, np.int64) for k in keypoints]
    for i in np.unique(obs_image):
        sel = obs_image == i
        uv, _ = g.project(scene.K[i], scene.R[i], scene.t[i], X[obs_point[sel]], scene.dist[i])
        obs_err[sel] = np.linalg.norm(uv - keypoints[i][obs_kp[sel], :2], axis=-1)
        point_of_kp[i][obs_kp[sel]] = obs_point[sel]
    m = len(X)
    track_len = np.bincount(obs_point, minlength=m)
    errors = np.bincount(obs_point, weights=obs_err, minlength=m) / np.maximum(track_len, 1)
    tri_angles = T._max_tri_angles(scene.centers[obs_image], X[obs_point], obs_point, m)
    return T.Triangulation(X, errors, track_len.astype(np.int64), tri_angles, obs_image,
                           obs_kp, obs_point, obs_err, point_of_kp, stats)


def _old_subset_point_of_kp(tr, keep):
    """Frozen copy of subset_points' per-image reindexing before it was vectorised."""
    new_index = np.cumsum(keep) - 1
    out = []
    for p in tr.point_of_kp:
        q = np.full(len(p), -1, np.int64)
        ok = p >= 0
        ok[ok] = keep[p[ok]]
        q[ok] = new_index[p[ok]]
        out.append(q)
    return out


def _assert_same(a: T.Triangulation, b: T.Triangulation):
    for f in ("points3d", "errors", "track_lengths", "tri_angles", "obs_image", "obs_kp",
              "obs_point", "obs_errors"):
        x, y = getattr(a, f), getattr(b, f)
        assert x.dtype == y.dtype, f
        np.testing.assert_array_equal(x, y, err_msg=f)
    for x, y in zip(a.point_of_kp, b.point_of_kp, strict=True):
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(x, y)


def test_vectorised_collect_and_subset_equal_the_former_loops():
    scene = _scene(5, np.array([-0.1, 0.02, 1e-3, 0.0, 0.01]))
    X = _points(120)
    kps = _observe(scene, X, noise=0.5)
    rng = np.random.default_rng(5)
    # tracks of mixed lengths (some pairs missing), a few wrong matches, one empty image
    matches = {(i, j): np.stack([rng.permutation(120)[:90]] * 2, 1)
               for i, j in itertools.combinations(range(4), 2)}
    matches[(0, 1)][:5, 1] = rng.permutation(120)[:5]
    kps[4] = kps[4][:0]
    rec = T.build_reconstruction(scene, [k[:, :2] for k in kps])
    T._run_triangulator(rec, kps, matches, T.TriangulationConfig(), False)
    new, old = T._collect(scene, kps, rec, {}), _old_collect(scene, kps, rec, {})
    assert new.num_points > 50 and len(set(new.track_lengths.tolist())) > 1
    _assert_same(new, old)
    for keep in (np.arange(new.num_points) % 3 != 1, np.zeros(new.num_points, bool),
                 np.ones(new.num_points, bool)):
        sub = T.subset_points(new, keep)
        for x, y in zip(sub.point_of_kp, _old_subset_point_of_kp(new, keep), strict=True):
            assert x.dtype == y.dtype
            np.testing.assert_array_equal(x, y)
