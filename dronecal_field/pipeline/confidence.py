"""Stage 7: the calibration's uncertainty (Monte-Carlo and linearised), scaled to the fit it has to explain,
the region of validity, the uncertainty maps and the ground homography (``core.uncertainty``,
``pipeline.validity``, ``pipeline.maps``).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from dronecal_field.geodesy import EnuOrigin
from dronecal_field.pipeline.points import WaypointPoint
from dronecal_field.pipeline.results import CalibrateOptions, Uncertainty

if TYPE_CHECKING:  # the engine (numba) is imported where it runs, not when this module loads
    from dronecal_field.core.uncertainty import UncertaintyResult

# A leg point's pixel is a cubic through the 4 detections around its fix (pipeline.legs): at 10 fps they span 0.3 s,
# and a fix 0.1 s on shares 3 of them, so the detector's error (inside the measured "white" noise) is common to the
# fixes of about 0.4 s. Measured on the 4K fly-through run (bench_uncertainty_cover, 960x540): leg points taken as
# independent reported the principal point and position 2.0x too tight; their sigmas x2 (= sqrt(0.4 s / 0.1 s)) gave
# 1.00 and 1.03.
PAIRING_CORRELATION_S = 0.4


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


def leg_sigma_factors(t_s: np.ndarray, leg: np.ndarray, correlation_s: float = PAIRING_CORRELATION_S) -> np.ndarray:
    """(N,) factors on the sigmas (3D and 2D) of fly-through leg points so that, taken as independent, a leg carries
    the information it really holds: sqrt(N / N_eff), N_eff = the leg's duration / ``correlation_s``.

    t_s (N,) fix times, seconds; leg (N,) the leg of each point, -1 for a hold (factor 1). A leg's N points,
    ``dt`` apart, share each error with ``g = min(N, correlation_s / dt)`` of their neighbours, so their mean has the
    variance of N / g independent points.

    Two shared errors are left to others: a GNSS error correlated over seconds was already inflated by
    pipeline.legs with the measured noise (``FixNoise.rho``); and the time offset's error, common to every leg, is
    not a per-leg inflation: measured on the 4K fly-through runs (960x540, 11 legs of 105-216 points), treating a
    0.02 s offset std as common to each leg's points reported the principal point and position 2.5-6x too loose
    (true/reported 0.15-0.40), as alternating legs' shifts cancel in the fit.
    """
    t = np.asarray(t_s, float)
    leg = np.asarray(leg)
    f = np.ones(len(t))
    for k in np.unique(leg[leg >= 0]):
        idx = np.flatnonzero(leg == k)
        if len(idx) < 2:
            continue
        dt = float(np.median(np.diff(np.sort(t[idx]))))
        g = float(np.clip(correlation_s / dt, 1.0, len(idx))) if dt > 0 else float(len(idx))
        f[idx] = np.sqrt(g)
    return f


FOCAL_KEYS = ("fx", "fy")


def focal_from(shared: UncertaintyResult, white: UncertaintyResult, reference: UncertaintyResult | None = None) -> UncertaintyResult:
    """``shared`` (an UncertaintyResult under the legs' factors) with the focal length's std of ``white`` (the same
    points taken as independent), never larger than ``shared``'s.

    The legs' factors are a measured correction, not a model of the shared
    error: over the 16 4K fly-through runs of benchmarks/bench_uncertainty_cover.py
    (960x540, median true error / reported 1-sigma) the points taken as
    independent reported the principal point and position 2x too tight
    (1.99, 2.04) and the focal length right (0.68, the 0.67 expected of one
    axis); x sqrt(N / N_eff) on every sigma fixed the first two (0.99, 1.02)
    and halved the focal ratio to 0.35 (its std 2.9x the true error). What
    the leg points share moves where the camera is and looks more than its
    scale (a shift common to all points is taken up by the position alone),
    so the focal length keeps the independent points' std. ``reference`` (default
    ``shared``): the result whose focal std ``white``'s was paired with, when
    ``shared`` is a Monte-Carlo (its focal std is scaled by white / reference).
    """
    from dataclasses import replace

    reference = shared if reference is None else reference
    std = dict(shared.param_std)
    for key in FOCAL_KEYS:
        w, r = white.param_std.get(key), reference.param_std.get(key)
        if key in std and w is not None and r is not None and np.isfinite(w) and r > 0:
            std[key] = float(std[key] * min(w / r, 1.0))
    return replace(shared, param_std=std)


def _leg_factors(points: list[WaypointPoint]) -> np.ndarray:
    """leg_sigma_factors for the used points (a leg point's window is one instant of source "leg", seq its leg)."""
    t = np.array([p.window.start_ns * 1e-9 for p in points])
    leg = np.array([p.window.seq if p.window.source == "leg" else -1 for p in points])
    return leg_sigma_factors(t, leg)


def uncertainty(camera, points: list[WaypointPoint], result, options: CalibrateOptions, origin: EnuOrigin | None = None,
                 plan_roi=None) -> Uncertainty:
    """Stage 7: Monte-Carlo and linearised uncertainty, the region of validity, the maps and the ground homography."""
    from dronecal_field.core.uncertainty import linearised, monte_carlo, parameter_covariance
    from dataclasses import replace

    from dronecal_field.pipeline import maps
    from dronecal_field.pipeline.ground15 import at_15m, honest
    from dronecal_field.pipeline.validity import assess_validity

    used = [p for p in points if p.used]
    X = np.array([p.marker_enu_m for p in used])
    s3 = np.array([p.sigma_enu_m for p in used])
    s2 = np.array([p.sigma_px for p in used])
    # the pixels the camera was fitted to let the model term add the richer model's departure (its bias),
    # not only its extra covariance; only when they are the same points as X
    fitted = result.pixels if result.points_world.shape == X.shape and np.allclose(result.points_world, X) else None
    lin = linearised(camera, X, sigma_3d=s3, sigma_2d=s2, model=result.model, fitted_pixels=fitted)
    # the scale explains the fit's residuals, which each point's own sigma predicts; the legs' factors come after it
    # (they say how many of the points' errors are shared, not how large each is)
    scale = sigma_scale(result, lin.rms_mean)
    legs = _leg_factors(used)
    if scale > 1.0:
        s3, s2 = scale * s3, scale * s2
        lin = linearised(camera, X, sigma_3d=s3, sigma_2d=s2, model=result.model, fitted_pixels=fitted)
    white = lin
    if np.any(legs != 1.0):
        s3, s2 = legs[:, None] * s3, legs * s2
        lin = focal_from(linearised(camera, X, sigma_3d=s3, sigma_2d=s2, model=result.model, fitted_pixels=fitted), white)
    mc = monte_carlo(camera, X, trials=options.trials, sigma_3d=s3, sigma_2d=s2, seed=options.seed, model=result.model,
                     fitted_pixels=fitted) if options.trials >= 2 else None
    if mc is not None and lin is not white:
        mc = focal_from(mc, white, lin)
    cov = parameter_covariance(camera, X, s3, s2, result.model)
    region = assess_validity(result, cov, s3, s2, origin=origin, roi=plan_roi, loss_scale_px=options.loss_scale_px)
    # the figures 15 m out: where the heading point lies outside the region, the lens's extrapolation joins them
    headline = mc if mc is not None else lin
    at = at_15m(camera, cov, region, headline.ground_error_15m_cm, headline.ground_error_15m_cm_p95)
    lin, mc, region = honest(lin, at), honest(mc, at), replace(region, at_15m=at)
    return Uncertainty(
        monte_carlo=mc, linearised=lin, covariance=cov,
        maps=maps.uncertainty_maps(camera, cov, seed=options.seed, richer=region.richer_camera, richer_covariance=region.richer_covariance),
        homography=maps.ground_homography(camera), validity=region, sigma_scale=scale,
    )
