"""Calibration from 3D-2D pairs: recovery, agreement with OpenCV, degenerate input."""

import cv2
import numpy as np
import pytest

from dronecal_field.core.calibrate import CalibrationModel, calibrate, resolve_model
from dronecal_field.core.camera import Distortion
from dronecal_field.core.synthetic import paper_camera, paper_grid, pole_camera, sampling_grid, visible
from dronecal_field.errors import DegenerateGeometryError, InputError


def _rel(a, b):
    return np.max(np.abs(np.asarray(a) - np.asarray(b)) / np.maximum(np.abs(np.asarray(b)), 1e-300))


@pytest.mark.parametrize("distorted", [False, True])
def test_recovers_known_camera_from_noise_free_points(distorted):
    truth = paper_camera(distorted)
    X = paper_grid(truth)
    uv = truth.project(X)
    model = "default" if distorted else "none"
    res = calibrate(X, uv, truth.width, truth.height, model=model)
    cam = res.camera
    assert _rel(cam.intrinsics.as_array(), truth.intrinsics.as_array()) < 1e-6
    assert np.max(np.abs(cam.distortion.as_array() - truth.distortion.as_array())) < 1e-6
    assert np.max(np.abs(cam.pose.position_world - truth.pose.position_world)) < 1e-6
    assert res.rms_px < 1e-6


def test_strongly_distorted_camera_converges_from_dlt_alone():
    truth = pole_camera(900.0, 1920, 1080, (0.0, 0.0, 4.0), 25.0, distortion=Distortion(k1=-0.35, k2=0.12, p1=1e-3, p2=-5e-4))
    X = sampling_grid(np.arange(4, 9.0), np.arange(-4, 4.1, 0.5), [1.0, 2.0, 3.0])
    from dronecal_field.core.synthetic import visible

    X = X[visible(truth, X)]
    res = calibrate(X, truth.project(X), truth.width, truth.height, model="k1k2p1p2")
    assert _rel(res.camera.intrinsics.as_array(), truth.intrinsics.as_array()) < 1e-6
    assert res.rms_px < 1e-6


def _noisy_table1(seed=1):
    truth = paper_camera(distorted=True)
    X = paper_grid(truth)
    rng = np.random.default_rng(seed)
    Q = (X + rng.normal(size=X.shape) * [0.01, 0.01, 0.015]).astype(np.float32).astype(float)
    q = (truth.project(X) + rng.normal(size=(len(X), 2)) * 2.0).astype(np.float32).astype(float)
    return truth, Q, q


def test_same_solution_as_opencv_calibrate_camera():
    truth, Q, q = _noisy_table1()
    res = calibrate(Q, q, truth.width, truth.height, model="default")
    criteria = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 1000, 1e-16)
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
    rms, K, d, rvecs, tvecs = cv2.calibrateCamera(
        [Q.astype(np.float32)], [q.astype(np.float32)], (truth.width, truth.height),
        res.camera.intrinsics.matrix * np.array([[1.02, 1, 0.98], [1, 1.02, 1.01], [1, 1, 1]]), np.zeros(5), flags=flags, criteria=criteria,
    )
    ours = res.camera
    assert _rel([ours.intrinsics.fx, ours.intrinsics.fy, ours.intrinsics.cx, ours.intrinsics.cy], [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]) < 1e-6
    assert np.max(np.abs(ours.distortion.as_array()[:4] - d.ravel()[:4]) / np.abs(d.ravel()[:4])) < 1e-5
    R_cv, _ = cv2.Rodrigues(rvecs[0])
    assert np.max(np.abs(ours.pose.position_world - (-R_cv.T @ tvecs[0].ravel()))) < 1e-6
    assert abs(res.rms_px - rms) / rms < 1e-6


def test_opencv_needs_a_guess_for_non_planar_points_we_do_not():
    truth, Q, q = _noisy_table1()
    with pytest.raises(cv2.error):
        cv2.calibrateCamera([Q.astype(np.float32)], [q.astype(np.float32)], (truth.width, truth.height), None, None)
    res = calibrate(Q, q, truth.width, truth.height, model="default")
    assert abs(res.camera.intrinsics.fx - truth.intrinsics.fx) / truth.intrinsics.fx < 0.05
    assert res.rms_px < 4.0


def test_covariance_matches_spread_of_repeated_calibrations():
    truth = paper_camera()
    X = paper_grid(truth)
    rng = np.random.default_rng(7)
    fx, std = [], []
    for _ in range(150):
        res = calibrate(X, truth.project(X) + rng.normal(0, 1.0, (len(X), 2)), 1280, 960, model="none")
        fx.append(res.camera.intrinsics.fx)
        std.append(res.parameter_std["fx"])
    assert np.std(fx) == pytest.approx(np.mean(std), rel=0.2)


def test_robust_loss_reports_outliers_and_ignores_them():
    truth = paper_camera()
    X = paper_grid(truth)
    rng = np.random.default_rng(3)
    uv = truth.project(X) + rng.normal(0, 0.5, (len(X), 2))
    bad = [3, 17, 40]
    uv[bad] += [[60.0, -45.0], [-80.0, 30.0], [50.0, 70.0]]
    plain = calibrate(X, uv, 1280, 960, model="none")
    robust = calibrate(X, uv, 1280, 960, model="none", loss="cauchy", loss_scale_px=1.0)
    assert set(bad) <= set(robust.outliers)
    assert len(robust.outliers) <= len(bad) + 2
    err_plain = abs(plain.camera.intrinsics.fx - 1110.0)
    err_robust = abs(robust.camera.intrinsics.fx - 1110.0)
    assert err_robust < 5.0 < err_plain


def test_fixed_aspect_and_principal_point_are_kept():
    truth = paper_camera()
    X = paper_grid(truth)
    uv = truth.project(X) + np.random.default_rng(0).normal(0, 1.0, (len(X), 2))
    res = calibrate(X, uv, 1280, 960, model=CalibrationModel(distortion="k1", fix_aspect_ratio=True, fix_principal_point=True))
    c = res.camera.intrinsics
    assert c.cx == pytest.approx(639.5) and c.cy == pytest.approx(479.5)
    assert c.fx == pytest.approx(c.fy, rel=1e-12)
    assert res.parameter_std["cx"] == 0.0


def test_auto_model_follows_point_count():
    assert resolve_model("auto", 60).distortion == "k1k2p1p2"
    assert resolve_model("auto", 13).distortion == "k1k2"
    assert resolve_model("auto", 11).distortion == "k1"
    assert resolve_model("auto", 8).distortion == "none"
    assert resolve_model("auto", 8).fix_principal_point


# ---- degenerate input: a clear error, not a wrong camera

def _xu(n=40):
    truth = paper_camera()
    X = paper_grid(truth)[:n]
    return truth, X, truth.project(X)


def test_too_few_points():
    truth, X, uv = _xu()
    with pytest.raises(DegenerateGeometryError, match="cannot determine 14 parameters"):
        calibrate(X[:6], uv[:6], 1280, 960, model="default")


def test_coplanar_points():
    truth = paper_camera()
    X = sampling_grid(np.arange(4, 9.0), np.arange(-3, 3.1), [0.5])
    with pytest.raises(DegenerateGeometryError, match="coplanar"):
        calibrate(X, truth.project(X), 1280, 960)


def test_one_point_off_a_plane_is_still_coplanar():
    truth = paper_camera()
    X = sampling_grid(np.arange(4, 9.0), np.arange(-3, 3.1), [0.5])
    X = X[visible(truth, X)]
    X = np.vstack([X, [[6.0, 0.0, 1.2]]])
    with pytest.raises(DegenerateGeometryError, match="only 1 off it"):
        calibrate(X, truth.project(X), 1280, 960)


def test_collinear_points():
    truth = paper_camera()
    X = np.stack([np.linspace(4, 8, 20), np.zeros(20), np.full(20, 0.5)], 1)
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        calibrate(X, truth.project(X), 1280, 960)


def test_points_behind_the_camera():
    truth, X, uv = _xu()
    c = truth.pose.position_world
    behind = 2 * c - X[:5]  # mirrored through the camera centre
    X2 = np.vstack([X, behind])
    # the pinhole algebra maps a point behind the camera to a pixel too; only the depth tells
    uv2 = np.vstack([uv, truth.project(behind)])
    with pytest.raises(DegenerateGeometryError, match="5 of 45 points lie behind the camera"):
        calibrate(X2, uv2, 1280, 960, model="none")


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_nan_and_inf(bad):
    truth, X, uv = _xu()
    uv = uv.copy()
    uv[4, 1] = bad
    with pytest.raises(InputError, match="NaN or inf"):
        calibrate(X, uv, 1280, 960)


def test_mismatched_shapes():
    truth, X, uv = _xu()
    with pytest.raises(InputError, match="matching arrays"):
        calibrate(X, uv[:-1], 1280, 960)


def test_unknown_model_name():
    truth, X, uv = _xu()
    with pytest.raises(InputError, match="unknown distortion model"):
        calibrate(X, uv, 1280, 960, model="fisheye")


# --------------------------------------------------------------------------
# A weight per point (pooled runs of different noise, pipeline/joint.py)


def test_equal_sigmas_give_the_unweighted_solution():
    truth, Q, q = _noisy_table1()
    plain = calibrate(Q, q, truth.width, truth.height, model="default")
    same = calibrate(Q, q, truth.width, truth.height, model="default", sigma_px=np.full(len(Q), 3.0))
    assert _rel(same.camera.intrinsics.as_array(), plain.camera.intrinsics.as_array()) < 1e-7
    assert np.max(np.abs(same.camera.distortion.as_array() - plain.camera.distortion.as_array())) < 1e-7
    assert abs(same.rms_px - plain.rms_px) < 1e-9
    # one point scale: the covariance does not depend on the sigmas' unit
    assert _rel(np.diag(same.camera.covariance)[:4], np.diag(plain.camera.covariance)[:4]) < 1e-5


def test_weighted_fit_is_the_whitened_least_squares_minimum():
    """Two runs, 0.3 px and 6 px: our weighted fit equals scipy's least_squares on the whitened residuals."""
    from scipy.optimize import least_squares

    from dronecal_field.core.camera import Camera

    truth = paper_camera(distorted=True)
    X = paper_grid(truth)
    rng = np.random.default_rng(7)
    sigma = np.where(np.arange(len(X)) % 2 == 0, 0.3, 6.0)
    q = truth.project(X) + rng.normal(size=(len(X), 2)) * sigma[:, None]
    res = calibrate(X, q, truth.width, truth.height, model="k1", sigma_px=sigma)
    plain = calibrate(X, q, truth.width, truth.height, model="k1")

    c0 = res.camera
    rvec0 = cv2.Rodrigues(c0.pose.R_cam_from_world)[0].ravel()

    def whitened(p):
        R = cv2.Rodrigues(p[5:8])[0]
        cam = Camera.from_arrays(p[:4], np.r_[p[4], 0, 0, 0, 0], R, p[8:11], truth.width, truth.height)
        return ((q - cam.project(X)) / sigma[:, None]).ravel()

    i = c0.intrinsics
    p0 = np.r_[i.fx * 1.01, i.fy * 0.99, i.cx + 3, i.cy - 2, c0.distortion.k1, rvec0, c0.pose.t_cam_from_world]
    ref = least_squares(whitened, p0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=20000)
    assert _rel([i.fx, i.fy, i.cx, i.cy], ref.x[:4]) < 1e-6
    assert abs(c0.distortion.k1 - ref.x[4]) < 1e-6
    # the weights matter here: the quiet half alone sets the focal length far better than all points alike
    err_w = abs(res.camera.intrinsics.fx - truth.intrinsics.fx)
    err_u = abs(plain.camera.intrinsics.fx - truth.intrinsics.fx)
    assert err_w < 0.5 * err_u, (err_w, err_u)


def test_bad_sigmas_are_refused():
    truth, X, uv = _xu()
    with pytest.raises(InputError, match="sigma_px must be a positive"):
        calibrate(X, uv, 1280, 960, sigma_px=np.r_[np.ones(len(X) - 1), 0.0])
