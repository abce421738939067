"""Model choice, measured-sigma covariance, uncertainty maps and the ground homography."""

from __future__ import annotations

import numpy as np

from contract_writer import pole_camera
from dronecal_field.core.calibrate import CalibrationModel, resolve_model
from dronecal_field.core.uncertainty import monte_carlo
from dronecal_field.core.uncertainty import parameter_covariance
from dronecal_field.pipeline.maps import choose_model, ground_homography, uncertainty_maps


def _grid_points(n_side=4):
    e, n, u = np.meshgrid(np.linspace(-3, 3, n_side), np.linspace(6, 12, n_side), [1.5, 3.5])
    return np.c_[e.ravel(), n.ravel(), u.ravel()]


def test_ground_homography_maps_ground_points_to_their_pixels():
    camera = pole_camera()
    g = np.c_[np.random.default_rng(0).uniform(-5, 5, 30), np.random.default_rng(1).uniform(5, 30, 30), np.zeros(30)]
    H = ground_homography(camera)
    q = np.c_[g[:, :2], np.ones(30)] @ H.T
    assert np.abs(q[:, :2] / q[:, 2:] - camera.project(g)).max() < 1e-8
    back = np.c_[camera.project(g), np.ones(30)] @ np.linalg.inv(H).T
    assert np.abs(back[:, :2] / back[:, 2:] - g[:, :2]).max() < 1e-8


def test_model_follows_count_and_spread():
    w, h = 640, 480
    centre = np.array([319.5, 239.5])
    rng = np.random.default_rng(0)
    near_centre = centre + rng.uniform(-60, 60, (30, 2))
    assert choose_model(near_centre, w, h)[0].distortion == "none"
    wide = np.c_[rng.uniform(0, w, 30), rng.uniform(0, h, 30)]
    # Points to the corners and enough of them: k3 may be tried too (the F-test decides).
    assert resolve_model("auto", 30) == CalibrationModel(distortion="k1k2p1p2")
    assert choose_model(wide, w, h)[0] == CalibrationModel(distortion="full")
    # Few points: the engine's count rule wins, with its fixed parameters.
    for n in (6, 10):
        assert choose_model(wide[:n], w, h)[0] == resolve_model("auto", n)
    middle = centre + np.c_[rng.uniform(-140, 140, 30), rng.uniform(-100, 100, 30)]
    model, reason = choose_model(middle, w, h)
    assert model.distortion == "k1" and "half-diagonal" in reason


def test_measured_sigma_covariance_agrees_with_the_monte_carlo():
    camera = pole_camera(distortion=(-0.1, 0.0, 0.0, 0.0, 0.0))
    X = _grid_points()
    s3 = np.tile([0.01, 0.01, 0.015], (len(X), 1))
    s2 = np.full(len(X), 0.5)
    cov = parameter_covariance(camera, X, s3, s2, "k1")
    mc = monte_carlo(camera, X, trials=300, sigma_3d=s3, sigma_2d=s2, seed=1, model="k1")
    for k, name in enumerate(("fx", "fy", "cx", "cy", "k1")):
        lin = np.sqrt(cov[k, k])
        assert 0.75 < mc.param_std[name] / lin < 1.33, (name, mc.param_std[name], lin)
    assert cov[5, 5] == 0.0  # k2 fixed by the model


def test_uncertainty_maps_grow_away_from_the_points_and_vanish_without_noise():
    camera = pole_camera()
    X = _grid_points()
    cov = parameter_covariance(camera, X, np.full((len(X), 3), 0.01), np.full(len(X), 0.5), "none")
    maps = uncertainty_maps(camera, cov, nu=16, nv=12)
    assert maps.projection_px.shape == (12, 16) and maps.samples == 0
    # The sky (top rows) has no ground; the bottom rows all do.
    assert maps.sky[0].all() and not maps.sky[-1].any()
    assert np.isnan(maps.ground_cm[0]).all() and np.isfinite(maps.ground_cm[-1]).all()
    # Extrapolating to the image corners is worse than in the sampled middle.
    assert maps.projection_px[-1, 0] > maps.projection_px[6, 8]
    s = maps.summary()
    assert 0 < s["ground_cm_median"] < 50 and 0.3 < s["ground_fraction_of_image"] < 0.9
    assert s["method"] == "linearised" and not s["with_model_extrapolation"]
    zero = uncertainty_maps(camera, np.zeros((15, 15)), nu=8, nv=6)
    assert np.nanmax(zero.projection_px) < 1e-9 and np.nanmax(zero.ground_cm) < 1e-9


def test_linearised_maps_match_sampled_cameras():
    # mrcal's check, on the maps: the first-order propagation against the
    # spread of cameras drawn from the same covariance (400 draws: the RMS of
    # a sampled std is within ~7 % of the truth at 2 sigma).
    camera = pole_camera(distortion=(-0.1, 0.0, 0.0, 0.0, 0.0))
    X = _grid_points()
    cov = parameter_covariance(camera, X, np.full((len(X), 3), 0.01), np.full(len(X), 0.5), "k1")
    lin = uncertainty_maps(camera, cov, nu=16, nv=12)
    mc = uncertainty_maps(camera, cov, nu=16, nv=12, samples=2000, seed=3)
    ratio = mc.projection_px / lin.projection_px
    assert 0.9 < np.median(ratio) < 1.1 and np.percentile(ratio, 95) < 1.25, np.percentile(ratio, [5, 50, 95])
    ground = np.isfinite(lin.ground_cm) & np.isfinite(mc.ground_cm) & (lin.ground_cm < 100)
    g_ratio = mc.ground_cm[ground] / lin.ground_cm[ground]
    assert 0.85 < np.median(g_ratio) < 1.15, np.percentile(g_ratio, [5, 50, 95])


def test_maps_add_the_model_extrapolation_term():
    # A k1 camera fitted to points in the middle of a k1k2 lens: the richer
    # fit departs from it towards the corners, never in the middle.
    from dronecal_field.core.calibrate import calibrate
    from dronecal_field.pipeline.validity import fit_richer

    truth = pole_camera(width=1280, height=720, f_px=700.0, distortion=(-0.3, 0.08, 0.0, 0.0, 0.0))
    X = _grid_points(5)
    from dronecal_field.core.synthetic import visible

    X = X[visible(truth, X, 20.0)]
    uv = truth.project(X) + np.random.default_rng(0).normal(0, 0.2, (len(X), 2))
    res = calibrate(X, uv, 1280, 720, model=CalibrationModel(distortion="k1", fix_aspect_ratio=True))
    richer = fit_richer(res)
    assert richer is not None and richer.model.distortion == "k1k2"
    s3, s2 = np.full((len(X), 3), 0.005), np.full(len(X), 0.2)
    cov = parameter_covariance(res.camera, X, s3, s2, res.model)
    rcov = parameter_covariance(richer.camera, X, s3, s2, richer.model)
    plain = uncertainty_maps(res.camera, cov, nu=32)
    both = uncertainty_maps(res.camera, cov, nu=32, richer=richer.camera, richer_covariance=rcov)
    assert both.summary()["with_model_extrapolation"]
    assert np.all(both.projection_px >= plain.projection_px - 1e-9)
    centre = both.extrapolation_px[both.extrapolation_px.shape[0] // 2, 16]
    corner = both.extrapolation_px[-1, 0]
    assert centre < 1.0 < 10 * centre < corner, (centre, corner)


def test_tangential_terms_are_refused_when_they_inflate_the_principal_points_std():
    # A camera with real tangential distortion, seen at well-spread points with 0.2 px noise: the
    # F-test wants p1, p2; they are then kept only if the principal point's std (with p1, p2 over
    # without) grows by at most max_pp_inflation. Thresholds just above and below the measured ratio.
    from dronecal_field.core.synthetic import visible
    from dronecal_field.pipeline.maps import select_model

    camera = pole_camera(width=1920, height=1080, f_px=1400.0, position_enu=(0.0, 0.0, 4.0), tilt_deg=15.0,
                         distortion=(-0.2, 0.05, 2e-3, -1.5e-3, 0.0))
    e, n, u = np.meshgrid(np.linspace(-3.5, 3.5, 6), np.linspace(4.5, 12, 5), [0.8, 2.5, 4.5])
    X = np.c_[e.ravel(), n.ravel(), u.ravel()]
    X = X[visible(camera, X, 20.0)]
    uv = camera.project(X) + np.random.default_rng(2).normal(0, 0.2, (len(X), 2))
    from dronecal_field.core.calibrate import calibrate
    from dronecal_field.pipeline.maps import _pp_std

    # select_model fits square pixels first (fx = fy), so the ratio is measured that way too.
    without = calibrate(X, uv, 1920, 1080, model=CalibrationModel(distortion="k1k2", fix_aspect_ratio=True), loss="huber")
    with_p = calibrate(X, uv, 1920, 1080, model=CalibrationModel(distortion="k1k2p1p2", fix_aspect_ratio=True), loss="huber")
    inflation = _pp_std(with_p) / _pp_std(without)
    taken, reason = select_model(X, uv, 1920, 1080, max_pp_inflation=1.05 * inflation)
    assert taken.model.distortion == "k1k2p1p2", reason
    assert abs(taken.camera.distortion.p1 - 2e-3) < 5e-4
    refused, reason = select_model(X, uv, 1920, 1080, max_pp_inflation=0.95 * inflation)
    assert refused.model.distortion == "k1k2"
    assert "principal point's std grows" in reason


def test_sigma_consistency_says_which_way_the_fit_departs_from_the_measured_sigmas():
    from dronecal_field.pipeline.report import sigma_consistency

    assert "conservative" in sigma_consistency(0.9, 3.0)["note"]
    assert "lever arm" in sigma_consistency(4.0, 2.0)["note"]
    assert sigma_consistency(1.0, 1.1)["note"].endswith("consistent")
    assert sigma_consistency(1.0, None) is None


def test_sigmas_are_scaled_up_to_explain_the_fit_never_down():
    # 1 px of image noise, sigmas that claim 0.5 px: the uncertainty must use twice them (the fit says so);
    # sigmas that claim 2 px stay (conservative). Outliers do not count.
    from dronecal_field.core.calibrate import calibrate
    from dronecal_field.core.synthetic import visible
    from dronecal_field.core.uncertainty import linearised
    from dronecal_field.pipeline.report import sigma_consistency
    from dronecal_field.pipeline.run import sigma_scale

    camera = pole_camera(width=1920, height=1080, f_px=1400.0, position_enu=(0.0, 0.0, 4.0), tilt_deg=15.0, distortion=(-0.2, 0.05, 0.0, 0.0, 0.0))
    e, n, u = np.meshgrid(np.linspace(-3.5, 3.5, 6), np.linspace(4.5, 12, 5), [0.8, 2.5, 4.5])
    X = np.c_[e.ravel(), n.ravel(), u.ravel()]
    X = X[visible(camera, X, 20.0)]
    uv = camera.project(X) + np.random.default_rng(5).normal(0, 1.0 / np.sqrt(2), (len(X), 2))
    uv[3] += 40.0  # one wild pair: the robust fit's outlier
    model = CalibrationModel(distortion="k1k2", fix_aspect_ratio=True)
    result = calibrate(X, uv, 1920, 1080, model=model, loss="huber")
    assert 3 in result.outliers
    tight = linearised(result.camera, X, sigma_3d=np.zeros(3), sigma_2d=0.5 / np.sqrt(2), model=model).rms_mean
    scale = sigma_scale(result, tight)
    assert 1.7 < scale < 2.3  # the fit's inliers are 1 px RMS, twice what 0.5 px predicts (less the fitted dof)
    loose = linearised(result.camera, X, sigma_3d=np.zeros(3), sigma_2d=2.0 / np.sqrt(2), model=model).rms_mean
    assert sigma_scale(result, loose) == 1.0
    assert "scaled 2.00x" in sigma_consistency(2.0, 1.0, 2.0)["note"]
    assert "close, but above; every uncertainty figure uses the sigmas scaled 1.20x" in sigma_consistency(1.2, 1.0, 1.2)["note"]
    assert sigma_consistency(2.0, 1.0, 2.0)["sigma_scale"] == 2.0


def test_k3_is_tested_at_5_percent_only_when_the_points_reach_the_outer_ring():
    """k3 acts in the image's outer ring: points that sample it interpolate k3 (a spurious one costs little), points
    that do not would extrapolate it. The F-test level for k3 is 0.05 from a 90th-percentile radius of 0.8 of the
    half-diagonal on, the caller's elsewhere."""
    from dronecal_field.pipeline.maps import k3_significance

    w, h = 3840, 2160
    centre, half = np.array([(w - 1) / 2, (h - 1) / 2]), 0.5 * np.hypot(w, h)
    angles = np.linspace(0, 2 * np.pi, 200, endpoint=False)
    uv_at = lambda r: centre + r * half * np.c_[np.cos(angles), np.sin(angles)]  # noqa: E731
    assert k3_significance(uv_at(0.85), w, h, 0.01) == 0.05
    assert k3_significance(uv_at(0.74), w, h, 0.01) == 0.01  # the 4K run without its last quarter reached 0.74
    assert k3_significance(uv_at(0.85), w, h, 0.1) == 0.1  # never stricter than asked
    assert k3_significance(np.empty((0, 2)), w, h, 0.01) == 0.01
