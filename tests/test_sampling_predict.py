"""Predicted ROI error (issue 10): the linearised noise term against a Monte-Carlo of the same ROI, and the extrapolation term."""

from __future__ import annotations

import numpy as np

from dronecal_field.core.calibrate import BatchState, levenberg_marquardt, resolve_model
from dronecal_field.core.camera import project_batch
from dronecal_field.plan.site import CameraSite, LensGuess, guess_camera
from dronecal_field.sampling.design import DesignParams, design_sampling
from dronecal_field.sampling.lattice import Limits
from dronecal_field.sampling.predict import (
    NoiseModel,
    extrapolation_roi,
    lens_draws,
    linearised_roi,
    normalised_radius,
    predict_roi,
    sample_sigmas,
)
from dronecal_field.sampling.roi import RoiSpec, build_roi, evaluation_points

CMAC = dict(lat_deg=-35.363261, lon_deg=149.165230, ground_h_m=584.0)


def paper_camera():
    site = CameraSite(**CMAC, mount_height_m=2.0, azimuth_deg=0.0, tilt_deg=30.0)
    lens = LensGuess(width=1280, height=960, focal_px=1110.0, distortion_level="medium", focal_source="test")
    return guess_camera(site, lens, frame="site")


def test_linearised_roi_error_matches_a_monte_carlo_of_the_roi_projection():
    """mrcal-style: the predicted per-point projection std over the ROI against the spread of 400 noisy solves."""
    cam = paper_camera()
    roi = build_roi(cam, RoiSpec())
    d = design_sampling(cam, roi, DesignParams(n_u=7, n_v=5), Limits(max_search_height_m=5.0))
    P, G = evaluation_points(roi)
    noise = NoiseModel(model="default")
    s3 = sample_sigmas(d.samples_sigma_h_m, noise)
    px, cm = linearised_roi(cam, d.samples_site, s3, P, G, noise)
    rng = np.random.default_rng(1)
    k = 400
    X = d.samples_site
    Q = X[None] + rng.standard_normal((k, len(X), 3)) * s3[None]
    q = cam.project(X)[None] + rng.standard_normal((k, len(X), 2)) * noise.sigma_px
    A = resolve_model("default", len(X)).parameter_map()
    state, _, _ = levenberg_marquardt(BatchState.from_camera(cam, k), Q, q, A, max_iterations=40, tolerance=1e-9)
    uv = project_batch(state.intrinsics, state.distortion, state.R, state.t, P[None])
    mc = np.sqrt(np.mean(np.sum((uv - cam.project(P)[None]) ** 2, axis=2), axis=0))
    ratio = np.sqrt(np.mean(px**2)) / np.sqrt(np.mean(mc**2))
    assert 0.85 < ratio < 1.15, ratio
    assert np.corrcoef(px, mc)[0, 1] > 0.95
    assert len(cm) == G.sum() and np.all(cm > 0)


def test_extrapolation_is_zero_for_a_lens_the_model_holds_and_grows_outside_the_samples():
    cam = paper_camera()
    roi = build_roi(cam, RoiSpec(kind="image", range_m=(3.0, 40.0)))
    P, G = evaluation_points(roi)
    d = design_sampling(cam, roi, DesignParams(n_u=7, n_v=5), Limits(max_search_height_m=5.0))
    # a lens inside the full model's family is fitted exactly: no extrapolation error anywhere
    exact = np.array([[-0.3, 0.1, 1e-4, -1e-4, 0.02, 0.0]])
    px, _ = extrapolation_roi(cam, d.samples_site, P, G, exact, "full")
    assert np.nanmax(px) < 1e-3
    # a lens with an eighth-order term: small where the samples are, larger where they are not
    draws = lens_draws(cam, cam.distortion.as_array(), float(normalised_radius(cam, P).max()), n=12, seed=3)
    assert draws.shape == (12, 6)
    # the lens is radial: "outside the samples" means beyond the samples' radius from the axis
    r_s = normalised_radius(cam, d.samples_site)
    inner = d.samples_site[r_s < 0.55 * r_s.max()]
    px, _ = extrapolation_roi(cam, inner, P, G, draws, "full")
    r_p = normalised_radius(cam, P)
    inside = r_p < 0.45 * r_s.max()
    outside = r_p > 0.9 * r_s.max()
    assert np.sqrt(np.mean(px[outside] ** 2)) > 5.0 * np.sqrt(np.mean(px[inside] ** 2))
    # with the samples out to the rim, the rim is no longer extrapolated
    px_all, _ = extrapolation_roi(cam, d.samples_site, P, G, draws, "full")
    assert np.sqrt(np.mean(px_all[outside] ** 2)) < 0.5 * np.sqrt(np.mean(px[outside] ** 2))


def test_combined_is_the_root_sum_square_and_the_paper_grid_scores_worse_on_the_roi():
    cam = paper_camera()
    roi = build_roi(cam, RoiSpec())
    P, G = evaluation_points(roi)
    draws = lens_draws(cam, cam.distortion.as_array(), float(normalised_radius(cam, P).max()), seed=0)
    lim = Limits(max_search_height_m=5.0)
    d = design_sampling(cam, roi, DesignParams(n_u=9, n_v=6), lim)
    pred = predict_roi(cam, d.samples_site, d.samples_sigma_h_m, P, G, NoiseModel(), draws, d.samples_rtk_factor)
    assert np.allclose(pred.px_combined, np.hypot(pred.px_lin, pred.px_extrap))
    s = pred.summary()
    assert s["combined_px"]["rms"] >= max(s["linearised_px"]["rms"], s["extrapolation_px"]["rms"])
    assert s["combined_px"]["p95"] <= s["combined_px"]["max"]
    from dronecal_field.sampling.lattice import recommended_strategy, screen_grid

    paper = screen_grid(recommended_strategy(cam), cam, lim).points
    pp = predict_roi(cam, paper, np.zeros(len(paper)), P, G, NoiseModel(), draws)
    assert pp.combined_rms_px > 1.3 * pred.combined_rms_px


def test_fast_covariance_is_the_engine_formula():
    """The noise term's sandwich (two BLAS products) equals core.uncertainty.parameter_covariance."""
    from dronecal_field.core.uncertainty import parameter_covariance
    from dronecal_field.sampling.predict import fast_parameter_covariance

    cam = paper_camera()
    roi = build_roi(cam, RoiSpec())
    d = design_sampling(cam, roi, DesignParams(sampling="through"), Limits(max_search_height_m=5.0))
    s3 = np.abs(np.random.default_rng(0).normal(0.01, 0.003, (len(d.samples_site), 3)))
    for model in ("default", "full"):
        ref = parameter_covariance(cam, d.samples_site, s3, 2.0, model)
        fast = fast_parameter_covariance(cam, d.samples_site, s3, 2.0, model)
        assert np.allclose(fast, ref, rtol=1e-5, atol=1e-6 * np.abs(ref).max())
