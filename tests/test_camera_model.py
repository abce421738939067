"""The camera model against OpenCV and finite differences."""

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from dronecal_field.core.camera import (
    Camera,
    Distortion,
    intersect_plane_z,
    look_rotation,
    pixel_rays_batch,
    project_batch,
    project_batch_jacobians,
    rotation_from_vector,
    vector_from_rotation,
)
from dronecal_field.core.synthetic import paper_camera, pole_camera

DIST = Distortion(k1=-0.25, k2=0.08, p1=-28e-5, p2=-5e-5, k3=-0.01)


def _camera() -> Camera:
    return pole_camera(1110.0, 1280, 960, (0.5, 0.2, 2.0), 30.0, azimuth_deg_from_x=7.0, distortion=DIST, cx=633.0, cy=488.0, fy=1104.0)


def _points(n=60, seed=0):
    return np.random.default_rng(seed).uniform([4, -3, 0], [8, 3, 1.5], (n, 3))


def test_project_matches_opencv_to_1e9_px():
    cam = _camera()
    X = _points()
    rvec, _ = cv2.Rodrigues(cam.pose.R_cam_from_world)
    ref, _ = cv2.projectPoints(X, rvec, cam.pose.t_cam_from_world, cam.intrinsics.matrix, cam.distortion.as_array())
    assert np.max(np.abs(cam.project(X) - ref[:, 0])) < 1e-9


def _fd_jacobian(cam: Camera, X: np.ndarray, eps: float = 1e-6):
    intr, dist, R, t = (a[0] for a in cam.batch_arrays())
    p = np.r_[intr, dist]

    def f(p_, w, t_, X_):
        return project_batch(p_[None, :4], p_[None, 4:9], (rotation_from_vector(w) @ R)[None], t_[None], X_[None])[0]

    z3 = np.zeros(3)
    J = np.zeros((len(X), 2, 15))
    Jx = np.zeros((len(X), 2, 3))
    for i in range(9):
        d = np.zeros(9)
        d[i] = eps * max(1.0, abs(p[i]))
        J[:, :, i] = (f(p + d, z3, t, X) - f(p - d, z3, t, X)) / (2 * d[i])
    for i in range(3):
        d = np.zeros(3)
        d[i] = eps
        J[:, :, 9 + i] = (f(p, d, t, X) - f(p, -d, t, X)) / (2 * eps)
        J[:, :, 12 + i] = (f(p, z3, t + d, X) - f(p, z3, t - d, X)) / (2 * eps)
        Jx[:, :, i] = (f(p, z3, t, X + d) - f(p, z3, t, X - d)) / (2 * eps)
    return J, Jx


def test_jacobians_match_finite_differences():
    cam = _camera()
    X = _points()
    _, J, Jx = project_batch_jacobians(*cam.batch_arrays(), X[None])
    J_fd, Jx_fd = _fd_jacobian(cam, X)
    scale = np.abs(J_fd).max(axis=(0, 1)) + 1e-12
    assert np.max(np.abs(J[0] - J_fd) / scale) < 1e-6
    assert np.max(np.abs(Jx[0] - Jx_fd)) < 1e-4 * np.abs(Jx_fd).max()


def test_compiled_normal_equations_match_numpy_jacobian():
    from dronecal_field.core.calibrate import BatchState, CalibrationModel, _free_columns
    from dronecal_field.core.kernels import normal_equations

    cam = _camera()
    X = _points()
    y = cam.project(X) + np.random.default_rng(1).normal(0, 2, (len(X), 2))
    for model in (CalibrationModel(), CalibrationModel(distortion="full", fix_aspect_ratio=True)):
        A = model.parameter_map(aspect=cam.intrinsics.fy / cam.intrinsics.fx)
        uv, J, _ = project_batch_jacobians(*cam.batch_arrays(), X[None])
        Jm = (J[0] @ A).reshape(-1, A.shape[1])
        r = (y - uv[0]).reshape(-1)
        st_ = BatchState.from_camera(cam)
        sel, fx_col, aspect = _free_columns(A)
        m = A.shape[1]
        JtJ, g, sq = np.empty((1, m, m)), np.empty((1, m)), np.empty((1, len(X)))
        normal_equations(st_.intrinsics, st_.distortion, st_.R, st_.t, X[None], y[None], np.ones((1, len(X))), sel, fx_col, aspect, JtJ, g, sq)
        assert np.allclose(JtJ[0], Jm.T @ Jm, rtol=1e-9, atol=1e-6)
        assert np.allclose(g[0], Jm.T @ r, rtol=1e-9, atol=1e-6)
        assert np.allclose(sq[0], np.sum((y - uv[0]) ** 2, axis=1))


@settings(max_examples=60, deadline=None)
@given(
    u=st.floats(20, 1260), v=st.floats(20, 940),
    depth=st.floats(1.0, 80.0),
    k1=st.floats(-0.3, 0.1), p1=st.floats(-1e-3, 1e-3),
)
def test_pixel_ray_round_trip(u, v, depth, k1, p1):
    """A pixel's ray, walked to any depth, projects back onto the pixel."""
    cam = paper_camera().with_(distortion=Distortion(k1=k1, k2=0.02, p1=p1, p2=-5e-5))
    arrays = cam.batch_arrays()
    uv = np.array([[[u, v]]])
    ray = pixel_rays_batch(*arrays[:3], uv)[0, 0]
    centre = cam.pose.position_world
    depth_along_axis = ray @ cam.pose.R_cam_from_world[2]
    X = centre + ray * depth / depth_along_axis
    assert np.allclose(cam.project(X[None])[0], [u, v], atol=1e-6)


@settings(max_examples=40, deadline=None)
@given(w=st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3))
def test_rotation_vector_round_trip(w):
    w = np.array(w)
    if np.linalg.norm(w) > np.pi - 1e-3:
        w = w / np.linalg.norm(w) * (np.pi - 1e-3)
    R = rotation_from_vector(w)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.allclose(vector_from_rotation(R), w, atol=1e-9)


def test_ground_intersection_lands_on_plane_and_projects_back():
    cam = paper_camera(distorted=True)
    uv = np.array([[[640.0, 700.0], [100.0, 900.0], [1200.0, 600.0]]])
    G = intersect_plane_z(*cam.batch_arrays(), uv, 0.0)[0]
    assert np.allclose(G[:, 2], 0.0, atol=1e-12)
    assert np.allclose(cam.project(G), uv[0], atol=1e-6)
    # above the horizon: no ground
    assert np.all(np.isnan(intersect_plane_z(*cam.batch_arrays(), np.array([[[640.0, 0.0]]]), 0.0 + 3.0)[0]))


def test_look_rotation_axes():
    R = look_rotation(np.array([1.0, 0.0, 0.0]))
    # camera x (right) = -Y world (Y is left), camera y (down) = -Z, z = +X
    assert np.allclose(R, [[0, -1, 0], [0, 0, -1], [1, 0, 0]])
