"""Stages 5-6: 3D-2D points from the holds and legs at a time offset, the camera solved from them, and the
refinements through the calibrated camera (lever arm facing it without attitude, centres under its distortion,
the legs' offset and rolling shutter, legs that disagree with the holds left out, the per-fix noise measured
on its residuals).

Pure functions of the earlier stages' values; no file is read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from dronecal_field.errors import CalibrationError, DegenerateGeometryError, DronecalError
from dronecal_field.pipeline.agreement import AGREES, merged
from dronecal_field.core.camera import undistort_normalised
from dronecal_field.pipeline.align import TimeOffset, Timing, estimate_time_offset, refine_timing
from dronecal_field.pipeline.detect import centres_under_distortion
from dronecal_field.pipeline.hover import HoverWindow
from dronecal_field.pipeline.legs import Leg, leg_points, track_velocity
from dronecal_field.pipeline.points import (
    FixNoise,
    WaypointPoint,
    drop_outlying_scatter,
    estimate_fix_noise,
    lever_arm_enu,
    marker_track_at,
    track_at,
    window_point,
)
from dronecal_field.pipeline.results import CalibrateOptions, Detections, MIN_POINTS, Solved, Track, TrackRead
from dronecal_field.pipeline.validity import convex_hull, polygon_area


def pair_points(
    track: Track,
    attitude: tuple,
    offset_frd: np.ndarray,
    windows: list[HoverWindow],
    legs: list[Leg],
    dets: Detections,
    centres_px: np.ndarray,
    timing: Timing,
    marker_size_m: float | None,
    options: CalibrateOptions,
    noise: FixNoise | None = None,
) -> list[WaypointPoint]:
    """Stage 5: one 3D-2D point per hover window (averaged over its settled part) and one per fix on the legs.

    With ``noise`` (measured after a first solve) each point's sigma follows it.
    """
    po = replace(options.points, min_fix=options.min_fix)
    if dets.stats.video_units_decoded is not None and options.sampling.video_bursts:
        po = replace(po, pair_across_gaps=True)  # keyframe bursts leave 1-4 s between a hold's frames (pipeline.sampling)
    # Each detection at the instant its marker row was read out.
    det_t = dets.t_ns + np.round(centres_px[:, 1] * timing.line_time_s * 1e9).astype(np.int64) if len(dets.t_ns) else dets.t_ns
    det_marker = None  # pairing at the fixes interpolates the image track instead
    if po.paired and po.pair_at == "detections":
        det_marker, bracketed = marker_track_at(
            det_t - timing.offset_ns, track.t_ns, track.antenna_enu_m, offset_frd, *attitude, max_gap_s=po.pair_max_gap_s
        )
        det_marker[~bracketed] = np.nan
    hover = [
        window_point(
            w, w.stable(po.settle_s, po.tail_s), track.t_ns, track.marker_enu_m, track.sigma_enu_m, track.fix_types,
            det_t, centres_px, timing.offset_ns, po, dets.size_px, marker_size_m, det_marker, noise,
        )
        for w in windows
    ]
    hover = drop_outlying_scatter(hover, po)
    if not legs:
        return hover
    readout_std = (timing.line_time_std_s or 0.0) * 0.5 * float(np.ptp(centres_px[:, 1])) if len(centres_px) else 0.0
    time_std = float(np.hypot(timing.offset_std_s if timing.offset_std_s is not None else 0.02, readout_std))
    moving = leg_points(
        legs, track.t_ns, track.marker_enu_m, track.velocity_enu_mps, track.sigma_enu_m, track.fix_types,
        dets.t_ns, centres_px, timing.offset_ns, timing.line_time_s, time_std, options.min_fix,
        first_index=len(windows), options=options.legs, noise=noise,
    )
    return hover + moving


def _fix_residuals(
    points: list[WaypointPoint], track: Track, dets: Detections, centres_px: np.ndarray, timing: Timing, camera, max_gap_s: float
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per-fix residuals (metres at the marker) through the calibrated camera, one series per hold and per leg.

    A hold's fixes in its settled part are paired with the image track
    interpolated at each (as its point was made); a leg's points are its fixes.
    """
    used = [p for p in points if p.used]
    if not used:
        return []
    det_t = dets.t_ns + np.round(centres_px[:, 1] * timing.line_time_s * 1e9).astype(np.int64) - timing.offset_ns
    f = 0.5 * (camera.intrinsics.fx + camera.intrinsics.fy)
    segments: list[tuple[np.ndarray, np.ndarray]] = []

    def metres(X: np.ndarray, uv: np.ndarray) -> np.ndarray:
        return (camera.project(X) - uv) * (camera.depth(X) / f)[:, None]

    for p in used:
        if p.window.source == "leg":
            continue
        a, b = p.stable_ns
        k = np.flatnonzero((track.t_ns >= a) & (track.t_ns <= b))
        if len(k) < 2:
            continue
        uv, ok = track_at(track.t_ns[k], det_t, centres_px, max_gap_s)
        if ok.sum() >= 2:
            segments.append((track.t_ns[k][ok], metres(track.marker_enu_m[k][ok], uv[ok])))
    legs: dict[int, list[WaypointPoint]] = {}
    for p in used:
        if p.window.source == "leg":
            legs.setdefault(int(p.window.seq), []).append(p)
    for pts in legs.values():
        X = np.array([p.marker_enu_m for p in pts])
        uv = np.array([p.uv_px for p in pts])
        segments.append((np.array([p.window.start_ns for p in pts], np.int64), metres(X, uv)))
    return segments


def solve_points(points: list[WaypointPoint], md, options: CalibrateOptions, previous=None):
    """Stage 6: the camera from the used points: (CalibrationResult, why this model).

    ``previous`` (result, reason): an intermediate solve of nearly the same
    points keeps its model and starts from its camera (one fit instead of the
    model ladder); the final solve chooses the model again.
    """
    from dronecal_field.core.calibrate import calibrate
    from dronecal_field.pipeline import maps

    used = [p for p in points if p.used]
    if len(used) < MIN_POINTS:
        raise DegenerateGeometryError(_too_few_message(points, len(used)))
    X = np.array([p.marker_enu_m for p in used])
    uv = np.array([p.uv_px for p in used])
    if previous is not None:
        result, reason = previous
        fit = calibrate(X, uv, md.width, md.height, model=result.model, loss=options.loss, loss_scale_px=options.loss_scale_px, initial=result.camera)
        return fit, reason
    if options.model == "auto":
        return maps.select_model(X, uv, md.width, md.height, options.loss, options.loss_scale_px, n_effective=_n_effective(used))
    result = calibrate(X, uv, md.width, md.height, model=options.model, loss=options.loss, loss_scale_px=options.loss_scale_px)
    return result, "--model given"


MAX_PRINCIPAL_OFFSET = 0.5  # principal point this far outside the image centre, in image sizes: no lens does that
MIN_FOCAL_PER_SIDE, MAX_FOCAL_PER_SIDE = 0.05, 25.0
NOISY_GNSS_M = 0.1  # fixes this noisy are no RTK's: the likely reason few points could not pin a camera  # fx / image width: a 169-2.3 degree horizontal field of view


def check_physical(result, points: list[WaypointPoint], md, noise: FixNoise | None = None) -> None:
    """Refuse a final camera whose intrinsics are no camera's: a fit that wandered off because the points did not pin it.

    Intermediate solves may wander and be pulled back by the refined timing; only the camera to be written is checked.

    Such a camera reprojects the sampled points well and everything else absurdly (seen: fx 78006, principal
    point (54914, -37649) px for a 1280x720 image from a PX4 flight whose holds lay in a strip of the image).
    """
    i = result.camera.intrinsics
    w, h = md.width, md.height
    off_x, off_y = abs(i.cx - 0.5 * w) / w, abs(i.cy - 0.5 * h) / h
    fov_ok = MIN_FOCAL_PER_SIDE * w <= min(i.fx, i.fy) and max(i.fx, i.fy) <= MAX_FOCAL_PER_SIDE * w
    if fov_ok and off_x <= MAX_PRINCIPAL_OFFSET and off_y <= MAX_PRINCIPAL_OFFSET:
        return
    uv = np.array([p.uv_px for p in points if p.used]).reshape(-1, 2)
    span = 100.0 * polygon_area(convex_hull(uv)) / float(w * h)  # as the report's geometry warning counts it
    gnss = 0.0 if noise is None else math.hypot(noise.sigma_white_m, noise.sigma_corr_m)
    noisy = f" with GNSS noise of {gnss:.2f} m per fix" if gnss > NOISY_GNSS_M else ""
    raise DegenerateGeometryError(
        f"the solved camera is not physical (fx {i.fx:.0f}, fy {i.fy:.0f} px, principal point ({i.cx:.0f}, {i.cy:.0f}) px "
        f"for a {w}x{h} image): its {len(uv)} points span {span:.0f} % of the image{noisy}, too little to pin the intrinsics; "
        "re-fly so the marker is seen across the whole image" + (", with RTK GNSS" if noisy else "")
    )


UNSUPPORTED_FOCAL_STD = 0.5  # a focal length known no better than this fraction of itself is a guess, not a calibration


def check_supported(mc, result, noise: FixNoise | None, causes: list[str] | tuple[str, ...] = ()) -> None:
    """Refuse a camera the flight's own noise leaves undetermined: a written camera.yaml is taken for a calibration.

    Seen on PX4 SITL (GNSS 0.65 m, 17 holds in a strip of the image): the fit landed 12 % off in focal and 5 m off
    in position, and every Monte-Carlo trial ran off to the affine limit (focal std 10^8 px).
    """
    f = 0.5 * (result.camera.intrinsics.fx + result.camera.intrinsics.fy)
    std = mc.param_std.get("fx") if mc is not None else None
    if std is None or (math.isfinite(std) and std <= UNSUPPORTED_FOCAL_STD * f):  # NaN: no trial converged
        return
    spread = f"{100 * std / f:.0f} %" if math.isfinite(std) and std < 10 * f else "beyond 1000 %"
    sigma = None if noise is None else math.hypot(noise.sigma_white_m, noise.sigma_corr_m)
    gnss = "" if sigma is None else f" (GNSS noise measured through the fit: {sigma:.2f} m per fix)"
    advice = "fly with RTK GNSS, and more holds across the whole image" if sigma is None or sigma > NOISY_GNSS_M else \
        "fly more holds across the whole image, at more heights"
    flown = f"{'; '.join(causes)}; " if causes else ""
    raise CalibrationError(
        f"{flown}this flight cannot pin the camera: with the noise it carries{gnss} the Monte-Carlo spreads the focal length "
        f"by {spread} over {mc.n_points} points; {advice}"
    )


LEG_PAIRS_PER_EFFECTIVE_POINT = 10  # pairs along a leg worth one independent point (1 s of 10 Hz fixes)


def _n_effective(used: list[WaypointPoint]) -> float:
    """How many independent points the used points are worth: a hold is one; a leg's pairs share its timing error
    and RTK noise correlated over seconds, so ``LEG_PAIRS_PER_EFFECTIVE_POINT`` of them count as one (at least 2 a leg)."""
    holds = sum(1 for p in used if p.window.source != "leg")
    legs: dict[int, int] = {}
    for p in used:
        if p.window.source == "leg":
            legs[int(p.window.seq)] = legs.get(int(p.window.seq), 0) + 1
    return float(holds + sum(max(min(n, 2), n / LEG_PAIRS_PER_EFFECTIVE_POINT) for n in legs.values()))


@dataclass(frozen=True, eq=False)
class PairingInputs:
    """What every re-pairing uses unchanged: the windows, the legs, the detections and the options."""

    windows: list[HoverWindow]
    legs: list[Leg]
    dets: Detections
    offset_frd_m: np.ndarray  # (3,)
    marker_size_m: float | None
    md: object  # runfile.RunMetadata
    options: CalibrateOptions


def _pair_and_solve(inp: PairingInputs, track: Track, attitude: tuple, centres: np.ndarray, timing: Timing, previous=None):
    """Stages 5 and 6 once: (points, CalibrationResult, model reason)."""
    points = pair_points(track, attitude, inp.offset_frd_m, inp.windows, inp.legs, inp.dets, centres, timing, inp.marker_size_m, inp.options)
    return (points, *solve_points(points, inp.md, inp.options, previous))


def _level_towards(track: Track, offset_frd_m: np.ndarray, camera_position: np.ndarray) -> tuple[Track, tuple]:
    """Without attitude: the marker track for level flight with the nose at the camera (what DO_SET_ROI does)."""
    ant = track.antenna_enu_m
    yaw = np.arctan2(camera_position[0] - ant[:, 0], camera_position[1] - ant[:, 1])
    rpy = np.c_[np.zeros(len(yaw)), np.zeros(len(yaw)), yaw]
    marker = ant + lever_arm_enu(offset_frd_m, rpy)
    return replace(track, marker_enu_m=marker, velocity_enu_mps=track_velocity(track.t_ns, marker)), (track.t_ns, rpy)


def _measured_noise(points: list[WaypointPoint], track: Track, dets: Detections, centres: np.ndarray, timing: Timing, result, options) -> FixNoise | None:
    """The per-fix noise from the residuals through the final camera, scaled for the parameters the fit spent on them."""
    noise = estimate_fix_noise(_fix_residuals(points, track, dets, centres, timing, result.camera, options.points.pair_max_gap_s))
    if noise is None:
        return None
    n_eq = 2 * len([p for p in points if p.used])
    scale = float(np.sqrt(n_eq / max(n_eq - result.model.n_free, 1)))
    return replace(noise, sigma_white_m=noise.sigma_white_m * scale, sigma_corr_m=noise.sigma_corr_m * scale)


def _points_and_solve(read: TrackRead, windows, legs, dets: Detections, offset: TimeOffset, md, options: CalibrateOptions) -> Solved:
    """Stages 5-6 with their refinements: points -> solve; without attitude the lever arm facing the
    camera; centres again under the distortion; on legs the offset and rolling shutter refined
    through the camera (twice); the noise measured on the residuals sets the points' sigmas."""
    inp = PairingInputs(windows, legs, dets, read.offset_frd_m, md.marker.size_m if md.marker.kind == "aruco" else None, md, options)
    warnings: list[str] = []
    track, attitude, attitude_source = read.track, read.attitude, read.attitude_source
    timing = Timing(offset.offset_s, offset.std_s, 0.0, None, 0.0, "not estimated", n_points=offset.n_points)
    centres = dets.uv_px
    points, result, reason = _pair_and_solve(inp, track, attitude, centres, timing)
    if attitude[0] is None and np.linalg.norm(read.offset_frd_m) > 0:
        # The first calibration located the camera the nose pointed at.
        track, attitude = _level_towards(track, read.offset_frd_m, result.camera.pose.position_world)
        points, result, reason = _pair_and_solve(inp, track, attitude, centres, timing)
        attitude_source = "none in the run: assumed level with the nose towards the calibrated camera"
        warnings.append("no attitude in the run: the marker lever arm assumes level flight facing the camera")
    method = "diagonals' crossing" if md.marker.kind == "aruco" else "blob centroid"
    corners = [d.corners_px for d in dets.items]
    if options.recentre and np.any(result.camera.distortion.as_array() != 0.0) and all(c is not None for c in corners):
        # Distortion bends the marker's diagonals: take the centres again under the calibrated distortion.
        i = result.camera.intrinsics
        centres = centres_under_distortion(np.array(corners), np.array([i.fx, i.fy, i.cx, i.cy]), result.camera.distortion.as_array())
        method = "diagonals' crossing under the first calibration's distortion"
        if not legs:
            points, result, reason = _pair_and_solve(inp, track, attitude, centres, timing)
    if legs:
        speed = float(np.nanmax(np.linalg.norm(track.velocity_enu_mps, axis=1), initial=0.0)) if len(track.t_ns) else 0.0
        for final in (False, True):  # the camera absorbed part of the timing error: refine, solve, once more
            timing = refine_timing(
                result.camera.project, dets.t_ns, centres, track.t_ns, track.marker_enu_m, timing.offset_s, md.height,
                max_readout_s=options.max_readout_s, speed_mps=speed,
            )
            if timing.offset_std_s is None:
                timing = replace(timing, offset_std_s=offset.std_s)
            points, result, reason = _pair_and_solve(inp, track, attitude, centres, timing, None if final else (result, reason))
        timing = _profiled_offset(inp, track, attitude, centres, timing, result, reason)
        points, result, reason = _pair_and_solve(inp, track, attitude, centres, timing)
        if timing.rolling_shutter != "estimated" and timing.bound_m is not None and options.max_readout_s > 0:
            warnings.append(
                f"rolling shutter not observable from these legs: a readout up to {options.max_readout_s * 1000:.0f} ms would move "
                f"the marker by up to {100 * timing.bound_m:.1f} cm between the top and bottom rows; fly legs at several image rows "
                "in both directions to estimate it"
            )
    agreement = None
    if legs:
        # after the legs' timing: a leg paired at the wrong instant also steers the offset the holds are paired at
        agreement = _agreement(points, result, md, options, legs)
        richer = _richer_fit(points, result, md, options) if agreement.left_out else None
        if richer is not None:
            # the legs may reach where the chosen model cannot follow (the edge of a wide lens): a richer model that
            # fits holds and legs alike keeps them
            again = _agreement(points, richer, md, options, legs)
            if again.line is None and again.reason == AGREES:
                reason += (f"; {richer.model.name} instead: under {result.model.name} the legs pulled the holds to "
                           f"{agreement.holds_pooled_rms_px:.2f} px (alone {agreement.holds_alone_rms_px:.2f} px), under "
                           f"{richer.model.name} to {again.holds_pooled_rms_px:.2f} px")
                result, agreement = richer, again
        if agreement.left_out:
            kept = [g for g in legs if g.index not in agreement.left_out]
            again = _points_and_solve(read, windows, kept, dets, offset, md, options)
            return replace(again, legs=again.legs, agreement=merged(agreement, again.agreement))
    noise = _measured_noise(points, track, dets, centres, timing, result, options)
    if noise is not None:  # same points, honest sigmas: no new solve
        points = pair_points(track, attitude, read.offset_frd_m, windows, legs, dets, centres, timing, inp.marker_size_m, options, noise)
    return Solved(
        points=points, result=result, model_reason=reason, track=track, attitude_source=attitude_source,
        centres=method, timing=timing, warnings=warnings, noise=noise, legs=legs, agreement=agreement,
    )


def _agreement(points: list[WaypointPoint], result, md, options: CalibrateOptions, legs: list[Leg]):
    """Do the legs agree with the holds (pipeline/agreement.py)? With ``--leg-source auto`` a leg that does not is left out."""
    from dronecal_field.pipeline import maps
    from dronecal_field.pipeline.agreement import AgreementOptions, check_sets

    source = legs[0].source if legs else "event"
    flag = "`--leg-source track`" if source == "gnss_track" else "`--leg-source events`"

    def fit(X: np.ndarray, uv: np.ndarray):
        if options.model == "auto":
            return maps.select_model(X, uv, md.width, md.height, options.loss, options.loss_scale_px)[0]
        from dronecal_field.core.calibrate import calibrate

        return calibrate(X, uv, md.width, md.height, model=options.model, loss=options.loss, loss_scale_px=options.loss_scale_px)

    return check_sets(points, result, fit, AgreementOptions(keep=options.leg_source != "auto", flag=flag, leg_source_name=source))


def _richer_fit(points: list[WaypointPoint], result, md, options: CalibrateOptions):
    """The used points fitted with the next richer distortion model than ``result``'s (from its camera), or None."""
    from dronecal_field.core.calibrate import calibrate

    order = ("none", "k1", "k1k2", "k1k2p1p2", "full")
    k = order.index(result.model.distortion) if result.model.distortion in order else len(order) - 1
    if options.model != "auto" or k + 1 >= len(order):
        return None
    used = [p for p in points if p.used]
    X = np.array([p.marker_enu_m for p in used])
    uv = np.array([p.uv_px for p in used])
    try:
        return calibrate(X, uv, md.width, md.height, model=replace(result.model, distortion=order[k + 1]), loss=options.loss,
                         loss_scale_px=options.loss_scale_px, initial=result.camera)
    except DronecalError:
        return None


PROFILE_STEP_S = 0.004  # the offset profile's step, s


PROFILE_REACH_S = 0.06  # how far from the refined offset the profile may walk, s


def _inlier_ss(result) -> float:
    """Sum of squared residuals of a fit's inliers, px^2 (its outliers left out: a late frame must not steer the offset)."""
    res = np.asarray(result.residuals_px, float)
    keep = np.ones(len(res), bool)
    keep[list(result.outliers)] = False
    return float(np.sum(res[keep] ** 2))


def _profiled_offset(inp: "PairingInputs", track: Track, attitude: tuple, centres: np.ndarray, timing: Timing, result, reason) -> Timing:
    """The time offset that minimises the calibration's own residuals, the camera refitted at each (a profile).

    Refining the offset through a fixed camera and then the camera at that
    offset converges slowly: the camera absorbs part of a timing error (a
    marker late along a row looks like a principal point moved). Measured on
    the 4K sim-chain fly-through run: two such rounds stopped 28 ms short; the
    profile's minimum there took the principal point error from 6.7 to about
    1 px and the ground 3-30 m error from 0.54 to about 0.15 px. The std comes
    from the profile's curvature with the fit's own residual variance.
    """
    ss0 = _inlier_ss(result)
    dof = max(2 * len(result.residuals_px) - result.model.n_free, 1)

    def cost(offset_s: float) -> float:
        try:
            _, fit, _ = _pair_and_solve(inp, track, attitude, centres, replace(timing, offset_s=offset_s), (result, reason))
        except DronecalError:
            return math.inf
        return _inlier_ss(fit)

    h = PROFILE_STEP_S
    centre, c0 = timing.offset_s, ss0
    lo, hi = cost(centre - h), cost(centre + h)
    for _ in range(int(PROFILE_REACH_S / h)):  # walk downhill until the minimum is bracketed
        if lo < c0 and lo <= hi:
            centre, hi, c0, lo = centre - h, c0, lo, cost(centre - 2 * h)
        elif hi < c0:
            centre, lo, c0, hi = centre + h, c0, hi, cost(centre + 2 * h)
        else:
            break
    curvature = (lo - 2 * c0 + hi) / h**2
    if not (np.isfinite(curvature) and curvature > 0):
        return timing
    step = float(np.clip(0.5 * (lo - hi) / (lo - 2 * c0 + hi) * h, -h, h))
    sigma2 = c0 / dof
    return replace(timing, offset_s=centre + step, offset_std_s=float(np.sqrt(2.0 * sigma2 / curvature)))


UNCERTAIN_OFFSET_S = 0.02  # an offset from the marker's motion this uncertain may be tried against its neighbours


def solve_at_offset(read: TrackRead, windows, legs, dets: Detections, offset: TimeOffset, md,
                     options: CalibrateOptions) -> tuple[Solved, TimeOffset]:
    """Stages 5-6 at the estimated offset; when that leaves too few usable holds and the estimate was uncertain,
    at the candidates around it (and 0, and camera.latency_s) instead: the one whose calibration uses the most holds.

    The motion-based estimate fits a projective map, which a distorted lens bends: with few moving detections
    (a short or cut run) its minimum can sit 0.2 s off, where each hold's settled part loses its frames.
    """
    try:
        solved = _points_and_solve(read, windows, legs, dets, offset, md, options)
    except DegenerateGeometryError as exc:
        if offset.std_s is not None and offset.std_s < UNCERTAIN_OFFSET_S:
            raise
        if clear_minimum(offset):
            # the marker's motion says where the clocks meet: other offsets would pair the holds with the wrong frames
            raise DegenerateGeometryError(
                f"{exc} (at the time offset from the marker's motion, {offset.offset_s:+.3f} \u00b1 {offset.std_s:.3f} s, a clear "
                f"minimum: its cost {offset.cost_min_px:.2f} against {offset.cost_zero_px:.2f} at 0 s)"
            ) from None
        first = exc
    else:
        return _through_the_lens(read, windows, legs, dets, offset, md, options, solved)
    spread = offset.std_s if offset.std_s is not None else options.max_offset_s / 4
    candidates = [offset.offset_s + k * spread for k in (-2, -1, 1, 2)] + [0.0]
    if md.camera_latency_s is not None:
        candidates.append(float(md.camera_latency_s))
    best = None
    trials: list[tuple] = []
    other: tuple[float, DegenerateGeometryError] | None = None
    for c in candidates:
        if abs(c) > options.max_offset_s:
            continue
        trial = replace(offset, offset_s=float(c), std_s=spread, method="image-vs-gnss, then calibration")
        try:
            solved = _points_and_solve(read, windows, legs, dets, trial, md, options)
        except DegenerateGeometryError as exc:
            if other is None and not str(exc).startswith(TOO_FEW):
                other = (float(c), exc)  # enough holds at this offset, but their geometry says why no camera
            continue
        n_used = sum(p.used for p in solved.points)
        trials.append((n_used, _robust_rms(solved.result), solved, trial))
    n_most = max((t[0] for t in trials), default=0)
    for n_used, cost, solved, trial in trials:  # the full fit's robust cost, among the candidates that keep most points
        if n_used >= 0.8 * n_most and (best is None or cost < best[0][1]):
            best = ((n_used, cost), solved, trial)
    if best is None:
        if other is None:
            raise first
        raise DegenerateGeometryError(
            f"{other[1]} (at a time offset of {other[0]:+.3f} s: the one from the marker's motion, {offset.offset_s:+.3f} "
            f"\u00b1 {spread:.3f} s, left too few usable holds)"
        ) from None
    _, solved, trial = best
    note = (f"the time offset from the marker's motion ({offset.offset_s:+.3f} \u00b1 {spread:.3f} s) left too few usable holds; "
            f"{trial.offset_s:+.3f} s, the candidate near it whose calibration fits best ({best[0][1]:.2f} px robust RMS over "
            f"{best[0][0]} points), was taken")
    return replace(solved, warnings=[*solved.warnings, note]), trial


LENS_SHIFT_S = 0.02  # a rescan through the lens this far from the first offset is solved at and compared


def undistorted_pixels(uv_px: np.ndarray, camera) -> np.ndarray:
    """(N, 2) pixels of the camera's pinhole part: ``uv_px`` with its distortion taken out (cv2.undistortPoints(P=K))."""
    i = camera.intrinsics
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    x, y = undistort_normalised(((uv[:, 0] - i.cx) / i.fx)[None], ((uv[:, 1] - i.cy) / i.fy)[None],
                                camera.distortion.as_array()[None].astype(float))
    return np.c_[x[0] * i.fx + i.cx, y[0] * i.fy + i.cy]


def _through_the_lens(read: TrackRead, windows, legs, dets: Detections, offset: TimeOffset, md, options: CalibrateOptions,
                      solved: Solved) -> tuple[Solved, TimeOffset]:
    """The motion scan again on the detections undistorted by the first calibration; solved at when it moved.

    The first scan fits a distortion-free projective map, which a strong lens
    bends where the marker crosses the image's outer ring: on the independent
    writer's 4K run (k1 -0.32, k3, legs out to 88 % of the half-diagonal) it
    found +0.477 s for a true 0.350, and the refinements through the camera
    (+-0.06 s) stopped at +0.413; through the lens the same scan gives +0.317.
    The two calibrations are then judged by their full fit's robust cost.
    """
    camera = solved.result.camera
    if offset.method != "image-vs-gnss" or not np.any(camera.distortion.as_array() != 0.0):
        return solved, offset
    again = estimate_time_offset(dets.t_ns, undistorted_pixels(dets.uv_px, camera), solved.track.t_ns, solved.track.marker_enu_m,
                                 groups=np.asarray(dets.groups), max_offset_s=options.max_offset_s)
    if again.method != "image-vs-gnss" or again.std_s is None or abs(again.offset_s - solved.timing.offset_s) < LENS_SHIFT_S:
        return solved, offset
    again = replace(again, through_lens=True)
    try:
        other = _points_and_solve(read, windows, legs, dets, again, md, options)
    except DegenerateGeometryError:
        return solved, offset
    n0, n1 = (sum(p.used for p in s.points) for s in (solved, other))
    if n1 >= 0.8 * n0 and (_robust_rms(other.result) < _robust_rms(solved.result) or n0 < 0.8 * n1):
        return other, again
    return solved, offset


CLEAR_MINIMUM = 1.5  # the motion scan's cost at 0 s this many times its minimum's: the offset stands


def clear_minimum(offset: TimeOffset) -> bool:
    """Whether the marker's motion pinned the offset: a bounded minimum well below the cost at 0 s."""
    return (offset.method == "image-vs-gnss" and offset.std_s is not None and offset.cost_min_px is not None
            and offset.cost_zero_px is not None and offset.cost_zero_px > CLEAR_MINIMUM * offset.cost_min_px
            and abs(offset.offset_s) > 2 * offset.std_s)


def _robust_rms(result) -> float:
    """RMS of a fit's residuals within 3x their median norm, px: its cost, a few wild points aside."""
    r = np.linalg.norm(np.asarray(result.residuals_px, float), axis=1)
    keep = r <= 3.0 * max(float(np.median(r)), 1e-9)
    return float(np.sqrt(np.mean(r[keep] ** 2)))


TOO_FEW = "too few good waypoints"


def _too_few_message(points: list[WaypointPoint], n_used: int) -> str:
    reasons: dict[str, int] = {}
    for p in points:
        if not p.used:
            key = p.dropped.split(" (")[0] if "worse than" not in p.dropped else p.dropped
            reasons[key] = reasons.get(key, 0) + 1
    top = "; ".join(f"{n}x {r}" for r, n in sorted(reasons.items(), key=lambda kv: -kv[1])[:3])
    fix_drops = sum(n for r, n in reasons.items() if "worse than" in r or "GNSS fixes" in r)
    seen_drops = sum(n for r, n in reasons.items() if "marker detections" in r)
    if seen_drops > fix_drops:
        advice = "hold longer at each waypoint (plan --hover) or record more frames a second, and check the marker faces the camera"
    elif fix_drops:
        advice = "fly with a better GNSS fix, or relax --min-fix"
    else:
        advice = "fly more waypoints in view of the camera"
    return (
        f"{TOO_FEW}: {n_used} of {len(points)} hover windows are usable, {MIN_POINTS} needed"
        + (f" (dropped: {top})" if top else "")
        + f": {advice}"
    )
