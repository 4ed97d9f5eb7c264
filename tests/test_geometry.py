"""Geometry against independent references: OpenCV, pycolmap and closed forms."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pycolmap
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from vrs_jax import geometry as g

rng = np.random.default_rng(0)


def random_rotations(n, rng=rng):
    q = rng.normal(size=(n, 4))
    return g.quat_to_rot(q / np.linalg.norm(q, axis=1, keepdims=True))


@given(st.lists(st.floats(-1, 1), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1))
@settings(max_examples=60, deadline=None)
def test_quaternion_roundtrip_and_pycolmap(qv):
    q = np.asarray(qv) / np.linalg.norm(qv)
    R = g.quat_to_rot(q)
    # pycolmap stores quaternions as (x, y, z, w).
    R_ref = pycolmap.Rotation3d(np.array([q[1], q[2], q[3], q[0]])).matrix()
    np.testing.assert_allclose(R, R_ref, atol=1e-12)
    q2 = g.rot_to_quat(R)
    # q and -q are the same rotation; rot_to_quat picks w >= 0
    assert q2[0] >= 0
    assert min(np.abs(q2 - q).max(), np.abs(q2 + q).max()) < 1e-9


def test_rot_to_quat_near_pi_and_jax():
    Rs = np.stack([g.axis_angle_to_rot(np.array(a) * np.pi) for a in
                   ([1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.6, 0.8, 0])])
    Rs = np.concatenate([Rs, random_rotations(50)])
    q = g.rot_to_quat(Rs)
    np.testing.assert_allclose(g.quat_to_rot(q), Rs, atol=1e-9)
    qj = g.rot_to_quat(jnp.asarray(Rs, jnp.float32))
    assert isinstance(qj, jax.Array)
    np.testing.assert_allclose(g.quat_to_rot(np.asarray(qj, np.float64)), Rs, atol=1e-5)


def test_rodrigues_against_opencv():
    for _ in range(50):
        w = rng.normal(size=3) * rng.uniform(0, 3)
        R_ref, _ = cv2.Rodrigues(w)
        np.testing.assert_allclose(g.axis_angle_to_rot(w), R_ref, atol=1e-12)
        np.testing.assert_allclose(g.rot_to_axis_angle(R_ref), cv2.Rodrigues(R_ref)[0][:, 0],
                                   atol=1e-9)
    # smooth at zero, and differentiable there in jax
    jac = jax.jacfwd(lambda w: g.axis_angle_to_rot(w))(jnp.zeros(3))
    np.testing.assert_allclose(jac[:, :, 0], g.skew(np.array([1.0, 0, 0])), atol=1e-6)


def test_pose_inverse_compose_center():
    R, t = random_rotations(5), rng.normal(size=(5, 3))
    Ri, ti = g.pose_inverse(R, t)
    Rc, tc = g.pose_compose(R, t, Ri, ti)
    np.testing.assert_allclose(Rc, np.broadcast_to(np.eye(3), Rc.shape), atol=1e-12)
    np.testing.assert_allclose(tc, 0, atol=1e-12)
    c = g.camera_center(R, t)
    np.testing.assert_allclose(g.transform_points(R, t, c[:, None])[:, 0], 0, atol=1e-12)
    rig = pycolmap.Rigid3d(pycolmap.Rotation3d(R[0]), t[0])
    np.testing.assert_allclose(rig.inverse().translation, c[0], atol=1e-12)


@pytest.mark.parametrize("with_dist", [False, True])
def test_project_against_opencv(with_dist):
    K = g.intrinsics_matrix(500.0, 480.0, 320.5, 240.2)
    dist = np.array([-0.2, 0.05, 0.001, -0.002, 0.01]) if with_dist else np.zeros(5)
    R, t = random_rotations(1)[0], np.array([0.1, -0.2, 3.0])
    X = rng.uniform(-1, 1, size=(100, 3))
    uv, z = g.project(K, R, t, X, dist if with_dist else None)
    ref, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, dist)
    np.testing.assert_allclose(uv, ref[:, 0], atol=1e-8)
    np.testing.assert_allclose(z, (X @ R.T + t)[:, 2], atol=1e-12)
    # jax path agrees in float32
    uvj, _ = g.project(*(jnp.asarray(a, jnp.float32) for a in (K, R, t, X, dist)))
    np.testing.assert_allclose(uvj, ref[:, 0], atol=2e-2)


def test_unproject_inverts_project_and_opencv_undistort():
    K = g.intrinsics_matrix(400.0, 400.0, 160.0, 120.0)
    dist = np.array([-0.1, 0.02, 0.0005, 0.0003, 0.0])
    uv = rng.uniform([10, 10], [310, 230], size=(50, 2))
    d = g.unproject(K, uv, dist)
    ref = cv2.undistortPoints(uv[:, None], K, dist)[:, 0]
    np.testing.assert_allclose(d[:, :2], ref, atol=1e-6)
    uv2, _ = g.project(K, np.eye(3), np.zeros(3), d * 2.0, dist)
    np.testing.assert_allclose(uv2, uv, atol=1e-6)


def test_pixel_rays_hit_the_projected_point_and_colmap_convention():
    K = g.intrinsics_matrix(300.0, 300.0, 100.0, 50.0)
    R, t = random_rotations(1)[0], np.array([0.3, 0.1, 2.0])
    X = rng.uniform(-0.5, 0.5, size=(20, 3))
    uv, z = g.project(K, R, t, X)
    o, d = g.pixel_rays(K, R, t, uv)
    np.testing.assert_allclose(o + z[:, None] * d, X, atol=1e-10)
    # COLMAP pixel convention: the top-left pixel centre is (0.5, 0.5)
    grid = g.pixel_grid(4, 3)
    assert grid.shape == (3, 4, 2) and tuple(grid[0, 0]) == (0.5, 0.5)
    cam = pycolmap.Camera(model="PINHOLE", width=200, height=100, params=[300, 300, 100, 50])
    np.testing.assert_allclose(cam.cam_from_img(uv), g.unproject(K, uv)[:, :2], atol=1e-10)


def test_scale_intrinsics_keeps_image_corners():
    K = g.intrinsics_matrix(525.0, 525.0, 320.0, 240.0)
    K2 = g.scale_intrinsics(K, 0.5)
    # the image corner (0, 0) and (640, 480) map to (0, 0) and (320, 240) in COLMAP convention
    ray = g.unproject(K, np.array([[640.0, 480.0]]))
    uv, _ = g.project(K2, np.eye(3), np.zeros(3), ray)
    np.testing.assert_allclose(uv, [[320.0, 240.0]], atol=1e-10)


def test_pose_errors_closed_form():
    R = random_rotations(1)[0]
    t = np.array([0.2, 0.0, 1.0])
    angle = np.radians(7.0)
    dR = g.axis_angle_to_rot(np.array([0, 0, angle]))
    # same centre, rotated by 7 degrees
    c = g.camera_center(R, t)
    R2 = dR @ R
    t2 = -R2 @ c
    dt, dr = g.pose_errors(R2, t2, R, t)
    assert abs(dt) < 1e-12 and abs(dr - 7.0) < 1e-9
    # shifted centre by 5 cm, same rotation
    t3 = -R @ (c + np.array([0.03, 0.04, 0.0]))
    dt, dr = g.pose_errors(R, t3, R, t)
    assert abs(dt - 0.05) < 1e-12 and abs(dr) < 1e-6


def test_opengl_to_opencv():
    c2w_gl = np.eye(4)
    c2w_gl[:3, 3] = [0, 0, 4]  # camera at z=4 looking down -z (towards the origin) in OpenGL
    R, t = g.pose_from_c2w(g.opengl_to_opencv_c2w(c2w_gl))
    _, z = g.project(np.eye(3), R, t, np.zeros((1, 3)))
    assert z[0] == pytest.approx(4.0)
