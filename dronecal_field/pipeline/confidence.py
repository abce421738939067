"""Stage 7: the calibration's uncertainty (Monte-Carlo and linearised), scaled to the fit it has to explain,
the region of validity, the uncertainty maps and the ground homography (``core.uncertainty``,
``pipeline.validity``, ``pipeline.maps``).
"""

from __future__ import annotations

import numpy as np

from dronecal_field.geodesy import EnuOrigin
from dronecal_field.pipeline.points import WaypointPoint
from dronecal_field.pipeline.results import CalibrateOptions, Uncertainty


def sigma_scale(result, expected_rms_px: float) -> float:
    """The factor (>= 1) the points' measured sigmas are scaled by so that they explain the fit's inlier RMS.

    The variance factor of least squares, never below 1: a fit worse than its
    sigmas predict holds an error they do not (a lever arm, a time offset, a
    lens term), and its uncertainty must grow with it or the report claims
    less than the truth. Measured on the paper's grid for the Table 1 camera
    (sim chain): fit 1.23 px against 0.78 px predicted; unscaled, the 90 %
    bound covered the true ground error at 19 % of the pixels inside the
    region of validity. A fit better than predicted keeps the measured
    sigmas (conservative). Outliers (the robust fit's own) are left out: a
    few late frames must not inflate every claim.
    """
    res = np.asarray(result.residuals_px, float)
    keep = np.ones(len(res), bool)
    keep[list(result.outliers)] = False
    if not keep.any() or not (np.isfinite(expected_rms_px) and expected_rms_px > 0):
        return 1.0
    inlier_rms = float(np.sqrt(np.mean(np.sum(res[keep] ** 2, axis=1))))
    return max(1.0, inlier_rms / expected_rms_px)


def uncertainty(camera, points: list[WaypointPoint], result, options: CalibrateOptions, origin: EnuOrigin | None = None,
                 plan_roi=None) -> Uncertainty:
    """Stage 7: Monte-Carlo and linearised uncertainty, the region of validity, the maps and the ground homography."""
    from dronecal_field.core.uncertainty import linearised, monte_carlo, parameter_covariance
    from dronecal_field.pipeline import maps
    from dronecal_field.pipeline.validity import assess_validity

    used = [p for p in points if p.used]
    X = np.array([p.marker_enu_m for p in used])
    s3 = np.array([p.sigma_enu_m for p in used])
    s2 = np.array([p.sigma_px for p in used])
    # the pixels the camera was fitted to let the model term add the richer model's departure (its bias),
    # not only its extra covariance; only when they are the same points as X
    fitted = result.pixels if result.points_world.shape == X.shape and np.allclose(result.points_world, X) else None
    lin = linearised(camera, X, sigma_3d=s3, sigma_2d=s2, model=result.model, fitted_pixels=fitted)
    scale = sigma_scale(result, lin.rms_mean)
    if scale > 1.0:
        s3, s2 = scale * s3, scale * s2
        lin = linearised(camera, X, sigma_3d=s3, sigma_2d=s2, model=result.model, fitted_pixels=fitted)
    mc = monte_carlo(camera, X, trials=options.trials, sigma_3d=s3, sigma_2d=s2, seed=options.seed, model=result.model,
                     fitted_pixels=fitted) if options.trials >= 2 else None
    cov = parameter_covariance(camera, X, s3, s2, result.model)
    region = assess_validity(result, cov, s3, s2, origin=origin, roi=plan_roi, loss_scale_px=options.loss_scale_px)
    return Uncertainty(
        monte_carlo=mc, linearised=lin, covariance=cov,
        maps=maps.uncertainty_maps(camera, cov, seed=options.seed, richer=region.richer_camera, richer_covariance=region.richer_covariance),
        homography=maps.ground_homography(camera), validity=region, sigma_scale=scale,
    )
