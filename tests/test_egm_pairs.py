"""Reference pairs from known poses: frustum overlap, viewing angles, depth-range sources."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from vrs_jax import geometry as g
from vrs_jax.data.scene import Scene
from vrs_jax.egm import pairs as P
from vrs_jax.errors import VrsError


def _scene(R, t, size=(64, 48), f=50.0, **kw) -> Scene:
    n = len(R)
    K = np.tile(g.intrinsics_matrix(f, f, size[0] / 2, size[1] / 2), (n, 1, 1))
    return Scene(root=Path("/nowhere"), names=[f"im{i}" for i in range(n)],
                 image_paths=[Path(f"/nowhere/im{i}.png") for i in range(n)], K=K,
                 dist=np.zeros((n, 5)), sizes=np.tile(size, (n, 1)), R=np.asarray(R, float),
                 t=np.asarray(t, float), has_pose=np.ones(n, bool), is_query=np.zeros(n, bool),
                 **kw)


def _yaw(deg):
    return g.axis_angle_to_rot(np.array([0.0, np.radians(deg), 0.0]))


def test_covisibility_identical_opposite_and_shifted():
    # camera 0 and 1 identical; camera 2 looks backwards; camera 3 shifted sideways by a lot
    R = [np.eye(3), np.eye(3), _yaw(180.0), np.eye(3)]
    t = [np.zeros(3), np.zeros(3), np.zeros(3), np.array([-100.0, 0, 0])]
    ranges = np.tile([1.0, 3.0], (4, 1))
    s = P.covisibility(np.stack([g.intrinsics_matrix(50., 50., 32., 24.)] * 4), np.stack(R),
                       np.stack(t), np.tile([64.0, 48.0], (4, 1)), ranges)
    assert s[0, 1] == pytest.approx(1.0)
    assert s[0, 2] == 0.0 and s[0, 3] == 0.0
    np.testing.assert_allclose(s, s.T)
    assert np.all(np.diag(s) == 0)


def test_covisibility_matches_monte_carlo():
    """Overlap of a camera turned by 10 deg: compare with a dense Monte-Carlo estimate."""
    R = np.stack([np.eye(3), _yaw(10.0)])
    t = np.zeros((2, 3))
    K = np.stack([g.intrinsics_matrix(50., 50., 32., 24.)] * 2)
    sizes = np.tile([64.0, 48.0], (2, 1))
    ranges = np.tile([1.0, 2.0], (2, 1))
    s = P.covisibility(K, R, t, sizes, ranges, grid=16, n_depths=4)
    # Monte Carlo: random pixels of camera 0, random depths, fraction inside camera 1
    rng = np.random.default_rng(0)
    uv = rng.uniform([0, 0], [64, 48], (20000, 2))
    X = g.unproject(K[0], uv) * rng.uniform(1, 2, (20000, 1))
    uv1, z = g.project(K[1], R[1], t[1], X)
    inside = (z > 0) & (uv1[:, 0] >= 0) & (uv1[:, 0] < 64) & (uv1[:, 1] >= 0) & (uv1[:, 1] < 48)
    # rotation about the centre: depth does not matter, overlap is symmetric
    assert s[0, 1] == pytest.approx(inside.mean(), abs=0.03)


def test_select_pairs_top_n_and_thresholds():
    score = np.array([[0, .9, .5, .05], [.9, 0, .6, .2], [.5, .6, 0, .3], [.05, .2, .3, 0]])
    ang = np.zeros((4, 4))
    pairs = P.select_pairs(score, ang, num_neighbors=1, min_overlap=0.1, max_angle=1.0)
    # 0 -> 1, 1 -> 0, 2 -> 1, 3 -> 2
    assert pairs.tolist() == [[0, 1], [1, 2], [2, 3]]
    ang[0, 1] = ang[1, 0] = 2.0  # too oblique
    pairs = P.select_pairs(score, ang, num_neighbors=1, min_overlap=0.1, max_angle=1.0)
    assert [0, 1] not in pairs.tolist()
    assert P.select_pairs(score, ang, 3, 0.95, 1.0).shape == (0, 2)


def test_depth_range_sources(tmp_path):
    R = np.stack([_yaw(a) for a in (0, 5, 10)])
    t = np.tile([0.0, 0.0, 2.0], (3, 1))
    base = _scene(R, t)
    r, src = P.estimate_depth_ranges(dataclasses.replace(base, bounds=np.tile([0.5, 4.], (3, 1))))
    assert src == "bounds" and np.allclose(r, [0.5, 4.0])
    # sparse points 2 m in front of the cameras
    pts = np.random.default_rng(1).uniform([-0.3, -0.3, -0.1], [0.3, 0.3, 0.1], (200, 3))
    r, src = P.estimate_depth_ranges(dataclasses.replace(base, points3d=pts))
    assert src == "points" and np.all((r[:, 0] > 1.7) & (r[:, 1] < 2.3))
    # cameras on a circle looking at the origin: the axes converge
    angs = np.radians(np.arange(0, 360, 30))
    c = np.stack([4 * np.sin(angs), np.zeros_like(angs), -4 * np.cos(angs)], 1)
    Rs = np.stack([_yaw(np.degrees(a)) for a in angs])  # optical axis towards the origin
    ring = _scene(Rs, -np.einsum("nij,nj->ni", Rs, c))
    r, src = P.estimate_depth_ranges(ring)
    assert src == "axes" and np.allclose(r, [2.0, 6.0], atol=1e-6)
    # nothing known: a guess from the camera layout
    r, src = P.estimate_depth_ranges(base)
    assert src == "extent" and np.all(r[:, 1] > r[:, 0]) and np.all(r > 0)
    r, src = P.estimate_depth_ranges(base, P.PairsConfig(depth_range=(1.0, 2.0)))
    assert src == "config" and np.allclose(r, [1.0, 2.0])


def test_reference_pairs_on_synthetic_are_covisible(small_synthetic_scene):
    from vrs_jax.data.readers import load_scene

    scene = load_scene("7scenes", small_synthetic_scene).references()
    pairs, score = P.reference_pairs(scene)
    assert len(pairs) >= len(scene)
    assert np.all(pairs[:, 0] < pairs[:, 1])
    # every image takes part, and pairs are close in space and viewing direction
    assert set(pairs.ravel()) == set(range(len(scene)))
    dist = np.linalg.norm(scene.centers[pairs[:, 0]] - scene.centers[pairs[:, 1]], axis=1)
    ang = np.degrees(P.viewing_angles(scene.R)[pairs[:, 0], pairs[:, 1]])
    assert np.median(dist) < 1.0 and ang.max() <= 60.0
    # the depth maps gave the ranges
    _, src = P.estimate_depth_ranges(scene)
    assert src == "depth"


def test_reference_pairs_errors_and_small_inputs():
    s = _scene(np.stack([np.eye(3)] * 2), np.zeros((2, 3)))
    with pytest.raises(VrsError, match="need poses"):
        P.reference_pairs(dataclasses.replace(s, has_pose=np.array([True, False])))
    pairs, score = P.reference_pairs(s.subset([0]))
    assert pairs.shape == (0, 2) and score.shape == (1, 1)
