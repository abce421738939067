"""The ``plan`` stage: options -> request -> evaluated candidates -> mission -> files.

:func:`make_plan` is pure (no files) and returns a :class:`PlanResult` whose
``summary`` is the machine-readable report; :func:`write_plan` writes the
folder atomically (a temporary folder renamed into place), so a failed run
never leaves a half-written plan.
"""

from __future__ import annotations

import math
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dronecal_field.core.camera import Camera, pixel_rays_batch
from dronecal_field.errors import InputError, PlanError
from dronecal_field.geodesy import enu_to_geodetic
from dronecal_field.plan import mission as msn
from dronecal_field.plan.route import FlightModel, Route, plan_route
from dronecal_field.plan.site import CameraSite, LensGuess, Marker, guess_camera, latlon_to_site, resolve_focal_px
from dronecal_field.plan.strategies import (
    PLAN_FOLD_MIN_SLOPE,
    Limits,
    StrategyScore,
    alternatives,
    fold_radius,
    paper_strategies,
    recommended_strategy,
    score_candidates,
)

MAX_PRACTICAL_MARKER_M = 1.0  # larger plates make a small copter a sail
FENCE_MARGIN_M = 3.0
FOOTPRINT_RANGE_M = 40.0
PLAN_FILES = ("mission.plan", "mission.waypoints", "mission.geojson", "preview.png", "plan.json", "camera_guess.yaml")


@dataclass(frozen=True)
class Evaluation:
    """Monte-Carlo settings of the prediction."""

    trials: int = 200
    seed: int = 0
    sigma_px: float = 2.0
    sigma_h_m: float = 0.01
    sigma_v_m: float = 0.015
    model: str = "default"
    optimize: bool = False
    max_flight_time_s: float | None = None

    def monte_carlo_settings(self):
        """The survey's ``MonteCarloSettings`` for these values (the candidates are scored by the survey's rows)."""
        from dronecal_field.survey.evaluate import MonteCarloSettings

        return MonteCarloSettings(trials=self.trials, sigma_3d=(self.sigma_h_m, self.sigma_h_m, self.sigma_v_m),
                                  sigma_2d=self.sigma_px, model=self.model, seed=self.seed)


@dataclass(frozen=True, eq=False)
class PlanRequest:
    """Everything ``make_plan`` needs, validated."""

    site: CameraSite
    lens: LensGuess
    marker: Marker
    limits: Limits
    flight: FlightModel
    evaluation: Evaluation
    takeoff_site: np.ndarray | None = None  # (3,) site frame, m
    geofence_latlon: tuple[tuple[float, float], ...] | None = None
    alt_frame: str = "relative"
    end: str = "land"
    yaw_mode: str = "roi"
    endurance_s: float = 1200.0
    name: str | None = None
    notes: tuple[str, ...] = ()  # warnings found while reading the inputs


def _need(opts: dict[str, Any], key: str, what: str) -> Any:
    if opts.get(key) is None:
        raise InputError(f"missing --{key.replace('_', '-')}: give {what} (flag or site-file key '{key}')")
    return opts[key]


def request_from_options(opts: dict[str, Any]) -> PlanRequest:
    """Validate resolved options (``plan.site.resolve_options``) into a :class:`PlanRequest`."""
    notes: list[str] = []
    lat = _need(opts, "lat", "the camera pole's latitude in degrees")
    lon = _need(opts, "lon", "the camera pole's longitude in degrees")
    if not (-90 < lat < 90 and -180 <= lon <= 360):
        raise InputError(f"--lat {lat} --lon {lon} is not a WGS84 position: give decimal degrees")
    g_h, g_amsl, n_geoid = opts.get("ground_alt"), opts.get("ground_amsl"), opts.get("geoid_separation")
    if g_h is None and g_amsl is None:
        raise InputError("missing ground height: give --ground-alt (ellipsoidal, m) or --ground-amsl with --geoid-separation")
    if g_h is None:
        if n_geoid is None:
            raise InputError("--ground-amsl needs --geoid-separation N (h = AMSL + N; a survey receiver or EGM96 table gives N): or give --ground-alt (ellipsoidal)")
        g_h = g_amsl + n_geoid
    elif g_amsl is not None:
        implied = g_h - g_amsl
        if n_geoid is not None and abs(implied - n_geoid) > 0.5:
            raise InputError(f"--ground-alt {g_h:g} - --ground-amsl {g_amsl:g} = {implied:.2f} m disagrees with --geoid-separation {n_geoid:g}: drop one")
        n_geoid = implied if n_geoid is None else n_geoid
    mount = _need(opts, "mount_height", "the camera height above the ground in metres")
    if not 0.3 <= mount <= 100:
        raise InputError(f"--mount-height {mount:g} m is outside 0.3-100 m: give the camera height above the ground")
    site = CameraSite(
        lat_deg=lat, lon_deg=lon, ground_h_m=float(g_h), mount_height_m=mount,
        azimuth_deg=float(_need(opts, "azimuth", "the optical axis azimuth in degrees from true north")) % 360.0,
        tilt_deg=float(_need(opts, "tilt", "the optical axis angle below horizontal in degrees")),
        roll_deg=float(opts.get("roll") or 0.0), geoid_separation_m=n_geoid,
    )
    w, h = _need(opts, "image_size", "the image size as WIDTHxHEIGHT")
    f_px, how = resolve_focal_px(w, h, opts.get("focal_px"), opts.get("focal_mm"), opts.get("sensor_width"),
                                 opts.get("sensor_format"), opts.get("pixel_pitch"), opts.get("hfov"))
    fps = float(opts.get("fps") or 25.0)
    if fps <= 0:
        raise InputError(f"--fps {fps:g} must be positive")
    lens = LensGuess(width=w, height=h, focal_px=f_px, distortion_level=opts.get("distortion") or "medium", focal_source=how, fps=fps)

    size = float(opts.get("marker_size") or 0.3)
    if not 0.02 <= size <= MAX_PRACTICAL_MARKER_M:
        raise InputError(f"--marker-size {size:g} m is outside 0.02-{MAX_PRACTICAL_MARKER_M:g} m: give the printed marker side in metres")
    marker = Marker(size_m=size, dictionary=opts.get("aruco_dict") or "DICT_4X4_50", marker_id=int(opts.get("marker_id") or 0),
                    offset_frd_m=tuple(opts.get("marker_offset") or (0.0, 0.0, 0.0)), min_px=float(opts.get("min_marker_px") or 20.0))

    min_agl = float(opts["min_agl"]) if opts.get("min_agl") is not None else 1.0
    max_agl, max_range = opts.get("max_agl"), opts.get("max_range")
    keep_out = float(opts["keep_out"]) if opts.get("keep_out") is not None else 2.0
    if min_agl <= 0.05:
        raise InputError(f"--min-agl {min_agl:g} m: the drone must fly above the ground (ArduPilot reads altitude 0 as 'here'): give at least 0.3")
    if max_agl is not None and max_agl <= min_agl:
        raise InputError(f"--max-agl {max_agl:g} m is not above --min-agl {min_agl:g} m: raise --max-agl or lower --min-agl")
    if keep_out < 0:
        raise InputError(f"--keep-out {keep_out:g} m is negative: give the no-fly radius around the pole")
    if max_range is not None and max_range <= keep_out:
        raise InputError(f"--max-range {max_range:g} m is inside --keep-out {keep_out:g} m: nowhere is left to fly; raise --max-range or lower --keep-out")
    speed = float(opts.get("speed") or 1.5)
    if not 0.1 <= speed <= 10.0:
        raise InputError(f"--speed {speed:g} m/s is outside 0.1-10 m/s: calibration legs are 1 m long, 1-2 m/s is plenty")
    if opts.get("hover") is None:
        hover = float(max(2, math.ceil(1.0 + 40.0 / fps)))  # 1 s to settle + 40 frames to average
    else:
        hover = float(opts["hover"])
        if hover <= 0:
            raise InputError(f"--hover {hover:g} s must be positive: the marker is detected while the drone holds still")
        if hover != math.ceil(hover):
            notes.append(f"hover {hover:g} s rounded up to {math.ceil(hover)} s: ArduCopter holds whole seconds")
            hover = float(math.ceil(hover))
    endurance_min = float(opts.get("endurance") or 20.0)
    if endurance_min <= 0:
        raise InputError(f"--endurance {endurance_min:g} min must be positive")

    geofence_xy = None
    if opts.get("geofence") is not None:
        fence = np.asarray(opts["geofence"], float)
        geofence_xy = tuple(tuple(map(float, p)) for p in latlon_to_site(site, fence)[:, :2])
    limits = Limits(
        min_agl_m=min_agl, max_agl_m=max_agl, max_range_m=max_range, keep_out_m=keep_out, marker_size_m=size,
        min_marker_px=marker.min_px, marker_offset_frd_m=marker.offset_frd_m, geofence_xy=geofence_xy,
        # without --max-agl, fly no higher than 3 m above the camera: above that a pole camera sees sky
        max_search_height_m=mount + 3.0,
    )
    takeoff_site = None
    if opts.get("takeoff") is not None:
        t = opts["takeoff"]
        h_t = t[2] if len(t) > 2 else site.ground_h_m
        takeoff_site = latlon_to_site(site, np.array([[t[0], t[1]]]), h_t)[0]
        r = float(np.hypot(takeoff_site[0], takeoff_site[1]))
        if r < keep_out:
            raise PlanError(f"--takeoff is {r:.1f} m from the pole, inside --keep-out {keep_out:g} m: take off away from the pole")
        if r > 300:
            raise InputError(f"--takeoff is {r:.0f} m from the pole: check the coordinates (lat,lon in degrees)")
    budget = opts.get("max_flight_time")
    evaluation = Evaluation(
        trials=int(opts.get("trials") or 200), seed=int(opts.get("seed") or 0), sigma_px=float(opts.get("sigma_px") or 2.0),
        sigma_h_m=float(opts["sigma_h"]) if opts.get("sigma_h") is not None else 0.01,
        sigma_v_m=float(opts["sigma_v"]) if opts.get("sigma_v") is not None else 0.015,
        model=str(opts.get("model") or "default"), optimize=bool(opts.get("optimize")),
        max_flight_time_s=None if budget is None else float(budget) * 60.0,
    )
    if evaluation.trials < 2:
        raise InputError(f"--trials {evaluation.trials} is too few: use at least 20 (200 is the default)")
    if (opts.get("alt_frame") or "relative") == "amsl" and n_geoid is None:
        raise InputError("--alt-frame amsl needs the geoid separation: add --geoid-separation N (m) or --ground-amsl with --ground-alt")
    return PlanRequest(
        site=site, lens=lens, marker=marker, limits=limits, flight=FlightModel(speed_m_s=speed, hover_s=hover),
        evaluation=evaluation, takeoff_site=takeoff_site, geofence_latlon=opts.get("geofence"),
        alt_frame=opts.get("alt_frame") or "relative", end=opts.get("end") or "land", yaw_mode=opts.get("yaw_mode") or "roi",
        endurance_s=endurance_min * 60.0, name=opts.get("name"), notes=tuple(notes),
    )


@dataclass(frozen=True, eq=False)
class PlanResult:
    """A finished plan: the chosen candidate, the route, the mission and the report."""

    request: PlanRequest
    camera_enu: Camera
    camera_site: Camera
    chosen: StrategyScore
    candidates: tuple[StrategyScore, ...]
    route: Route
    mission: msn.Mission
    fence_site: np.ndarray  # (M, 2) inclusion polygon, site XY
    footprint_site: np.ndarray  # (K, 2) ground footprint of the image, site XY
    summary: dict
    warnings: tuple[str, ...] = field(default_factory=tuple)

    @property
    def grid_site(self) -> np.ndarray:
        """(N, 3) marker centres of the plan, site frame."""
        return self.chosen.screen.points


def _objective(score: StrategyScore) -> float:
    """Lower is better: predicted ground error at 15 m (the RMS residual alone rewards overfitting)."""
    if score.ground_error_15m_cm is not None:
        return score.ground_error_15m_cm
    return score.rms_mean_px if score.rms_mean_px is not None else math.inf


def _no_plan_error(req: PlanRequest, scores: tuple[StrategyScore, ...]) -> PlanError:
    """The most useful message when no candidate can be flown."""
    best = max(scores, key=lambda s: s.n_points)
    screen = best.screen
    seen = screen.in_view.sum() if len(screen.in_view) else 0
    seen_reach = (screen.in_view & screen.reachable).sum() if len(screen.in_view) else 0
    if req.site.tilt_deg < 0 and seen == 0:
        return PlanError(f"the camera is tilted {-req.site.tilt_deg:g} deg up and sees no point it can be calibrated from: check --tilt (deg below horizontal)")
    if seen == 0:
        return PlanError(
            "the camera sees no reachable volume within 8 m of the pole (looking at a wall, or too steep/high for the limits): "
            "check --tilt/--azimuth, lower --min-agl or raise --max-agl"
        )
    if seen_reach == 0:
        reasons = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in screen.reasons.items())
        return PlanError(f"every point the camera sees is out of bounds ({reasons}): relax --min-agl/--max-agl/--max-range/--keep-out/--geofence")
    needed = max((s.screen.needed_marker_size_m(req.limits) or 0.0) for s in scores)
    if needed > 0:
        if needed > MAX_PRACTICAL_MARKER_M:
            return PlanError(
                f"a marker {req.limits.min_marker_px:g} px wide from this camera needs {needed:.2f} m, more than a drone can carry "
                f"({MAX_PRACTICAL_MARKER_M:g} m): the camera is too wide-angle/far for marker calibration at 4-8 m; lower --min-marker-px only if your detector reads smaller markers"
            )
        return PlanError(
            f"the {req.marker.size_m:g} m marker is under {req.limits.min_marker_px:g} px at most points: print a marker of at least "
            f"{math.ceil(needed * 20) / 20:.2f} m (--marker-size)"
        )
    return PlanError(
        f"too few usable points for a non-coplanar calibration: best candidate {best.strategy.name} has {best.problem}; "
        "relax --min-agl/--max-agl/--keep-out, or use a larger marker"
    )


def footprint_site(camera_site: Camera, n_side: int = 24, range_m: float = FOOTPRINT_RANGE_M) -> np.ndarray:
    """(K, 2) ground footprint of the image border in site XY (rays above the horizon cut at ``range_m``)."""
    w, h = camera_site.width, camera_site.height
    t = np.linspace(0.0, 1.0, n_side, endpoint=False)
    border = np.concatenate([
        np.stack([t * (w - 1), np.zeros_like(t)], 1), np.stack([np.full_like(t, w - 1), t * (h - 1)], 1),
        np.stack([(1 - t) * (w - 1), np.full_like(t, h - 1)], 1), np.stack([np.zeros_like(t), (1 - t) * (h - 1)], 1),
    ])
    K, D, R, _ = camera_site.batch_arrays()
    rays = pixel_rays_batch(K, D, R, border[None])[0]
    c = camera_site.pose.position_world
    # pixels beyond the distortion model's fold have no ray: drop those whose ray does not project back
    # (beyond the fold Newton may also land on the far branch, which projects back fine)
    back = camera_site.project(c[None] + rays)
    d_cam = rays @ camera_site.pose.R_cam_from_world.T
    r_norm = np.hypot(d_cam[:, 0], d_cam[:, 1]) / np.maximum(d_cam[:, 2], 1e-9)
    ok = (np.linalg.norm(back - border, axis=1) < 1.0) & (d_cam[:, 2] > 0) & (r_norm < fold_radius(camera_site.distortion.as_array(), PLAN_FOLD_MIN_SLOPE))
    out = []
    for d in rays[ok]:
        horiz = float(np.hypot(d[0], d[1]))
        if d[2] < -1e-9:
            p = c + (-c[2] / d[2]) * d
            r = float(np.hypot(p[0], p[1]))
            if r > range_m:
                p = c + d * (range_m / max(horiz, 1e-9))
        else:
            p = c + d * (range_m / max(horiz, 1e-9))
        out.append(p[:2])
    return np.asarray(out)


def _check_sees_ground(req: PlanRequest, cam_site: Camera) -> None:
    """A camera whose lowest image row is at or above the horizon looks at the sky: no ground, no plan."""
    w, h = cam_site.width, cam_site.height
    bottom = np.array([[[0.0, h - 1.0], [(w - 1) / 2.0, h - 1.0], [w - 1.0, h - 1.0]]])
    K, D, R, _ = cam_site.batch_arrays()
    rays = pixel_rays_batch(K, D, R, bottom)[0]
    if np.all(rays[:, 2] >= -1e-3):
        up = -req.site.tilt_deg
        raise PlanError(
            f"the camera is tilted {up:g} deg up and its image holds no ground: the marker must be flown in front of a camera "
            "that sees the ground; check --tilt (degrees BELOW horizontal, positive looking down)"
        )


def _json_safe(x: Any) -> Any:
    """NaN/inf -> None, numpy scalars -> Python, recursively (JSON has no NaN)."""
    if isinstance(x, dict):
        return {str(k): _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(float(x)) else None
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.ndarray):
        return _json_safe(x.tolist())
    return x


def make_plan(req: PlanRequest, client: Any = None) -> PlanResult:
    """Evaluate the candidates for this camera, pick one, and build the mission and the report.

    The candidates are scored by ``plan.strategies.score_candidates`` (the
    survey's row function): in this process, or on a Dask cluster when
    ``client`` (a ``distributed.Client``, see ``dronecal_field.cluster.dask_client``)
    is given; the plan is the same either way.

    Raises ``PlanError`` (with what to change) when no safe, useful mission exists.
    """
    cam_site = guess_camera(req.site, req.lens, frame="site")
    cam_enu = guess_camera(req.site, req.lens, frame="enu")
    _check_sees_ground(req, cam_site)
    ev = req.evaluation
    base = recommended_strategy(cam_site)
    strategies = list(alternatives(base))
    if ev.optimize:
        names = {s.name for s in strategies}
        strategies += [s for s in paper_strategies() if s.name not in names]
    scores = score_candidates(cam_site, strategies, req.limits, ev.monte_carlo_settings(), req.flight, client)
    usable = [s for s in scores if s.usable]
    warnings = list(req.notes)
    if not usable:
        raise _no_plan_error(req, scores)
    if ev.optimize:
        budget = ev.max_flight_time_s if ev.max_flight_time_s is not None else 0.8 * req.endurance_s
        fit = [s for s in usable if s.flight_time_s is not None and s.flight_time_s <= budget]
        if not fit:
            shortest = min(usable, key=lambda s: s.flight_time_s or math.inf)
            raise PlanError(
                f"no candidate fits in {budget / 60:.1f} min: the shortest usable one, {shortest.strategy.name}, takes "
                f"{(shortest.flight_time_s or 0) / 60:.1f} min: raise --max-flight-time or shorten --hover"
            )
        chosen = min(fit, key=_objective)
    else:
        chosen = scores[0]
        if not chosen.usable:
            chosen = min(usable, key=_objective)
            warnings.append(f"the paper's recommendation {scores[0].strategy.name} cannot be used here ({scores[0].problem}); using {chosen.strategy.name}")
    screen = chosen.screen
    dropped_small = screen.reasons.get("marker_too_small", 0)
    if dropped_small:
        need = screen.needed_marker_size_m(req.limits)
        warnings.append(f"{dropped_small} grid points dropped because the {req.marker.size_m:g} m marker is under {req.limits.min_marker_px:g} px there; a {math.ceil((need or 0) * 20) / 20:.2f} m marker keeps them")

    route = plan_route(screen.vehicle_points, screen.points, req.limits, req.flight, takeoff_site=req.takeoff_site, end=req.end)
    mission = msn.build_mission(route, req.site.R_enu_from_site, req.site.origin, req.site.mount_height_m, req.flight.speed_m_s,
                                alt_frame=req.alt_frame, yaw_mode=req.yaw_mode, geoid_separation_m=req.site.geoid_separation_m)
    fence = msn.fence_polygon(np.vstack([route.points, route.takeoff_site[None]]), FENCE_MARGIN_M)
    footprint = footprint_site(cam_site)
    battery_pct = 100.0 * route.flight_time_s / req.endurance_s
    if battery_pct > 80.0:
        warnings.append(f"the flight takes {battery_pct:.0f} % of a {req.endurance_s / 60:g} min battery: split it or use --optimize --max-flight-time")
    if req.geofence_latlon is not None:
        from matplotlib.path import Path as MplPath

        gf = MplPath(np.asarray(req.limits.geofence_xy))
        if not gf.contains_point(route.takeoff_site[:2]):
            warnings.append("the take-off point is outside --geofence")
    summary = _json_safe(_summary(req, cam_enu, cam_site, chosen, scores, route, mission, fence, warnings, battery_pct))
    return PlanResult(request=req, camera_enu=cam_enu, camera_site=cam_site, chosen=chosen, candidates=scores, route=route,
                      mission=mission, fence_site=fence, footprint_site=footprint, summary=summary, warnings=tuple(warnings))


def _site_to_geo(req: PlanRequest, pts_site: np.ndarray) -> np.ndarray:
    """(N, 3) lat, lon, h of site-frame points."""
    return enu_to_geodetic(np.atleast_2d(pts_site) @ req.site.R_enu_from_site.T, req.site.origin)


def _summary(req, cam_enu, cam_site, chosen, scores, route, mission, fence, warnings, battery_pct) -> dict:
    from dronecal_field import __version__

    screen = chosen.screen
    pts = screen.points
    veh = screen.vehicle_points
    geo = _site_to_geo(req, veh)
    uv = cam_site.project(pts)
    seq_of: dict[int, int] = {it.grid_index: seq for seq, it in enumerate(mission.items, start=1) if it.label.startswith("grid")}
    order = route.grid_order
    rank = {int(g): k for k, g in enumerate(order)}
    marker_px = screen.marker_px[screen.keep]
    alt_written = (geo[:, 2] - mission.home_h_m) if req.alt_frame == "relative" else geo[:, 2] - (req.site.geoid_separation_m or 0.0)
    grid = [
        {
            "index": i,
            "order": rank[i],
            "mission_seq": seq_of.get(i),
            "marker_site_m": [round(float(v), 4) for v in pts[i]],
            "drone_site_m": [round(float(v), 4) for v in veh[i]],
            "drone_enu_m": [round(float(v), 4) for v in (req.site.R_enu_from_site @ veh[i])],
            "lat_deg": float(geo[i, 0]), "lon_deg": float(geo[i, 1]), "h_m": round(float(geo[i, 2]), 4),
            "alt_m": round(float(alt_written[i]), 3),
            "pixel": [round(float(uv[i, 0]), 1), round(float(uv[i, 1]), 1)],
            "marker_px": round(float(marker_px[i]), 1),
        }
        for i in range(len(pts))
    ]
    fence_geo = _site_to_geo(req, np.column_stack([fence, np.zeros(len(fence))]))
    takeoff_geo = _site_to_geo(req, route.takeoff_site)[0]
    max_alt = float(np.max(route.points[:, 2] - route.takeoff_site[2]))
    lens = req.lens
    d = cam_enu.distortion
    ev = req.evaluation
    return {
        "format": "dronecal-field plan summary, version 1",
        "created_by": f"dronecal-field {__version__} plan",
        "name": req.name,
        "altitude_frame": req.alt_frame,
        "altitude_frame_text": mission.alt_frame_text,
        "heights_text": "h_m values are WGS84 ellipsoidal heights; alt_m values are the mission altitudes in altitude_frame",
        "enu_origin": {"lat_deg": req.site.lat_deg, "lon_deg": req.site.lon_deg, "h_m": req.site.ground_h_m,
                        "text": "ENU frame (east, north, up, m) at the pole's foot; h is ellipsoidal"},
        "site_frame": {"azimuth_deg": req.site.azimuth_deg, "R_enu_from_site": np.round(req.site.R_enu_from_site, 12).tolist(),
                        "text": "site frame: X along the camera azimuth (horizontal), Y left, Z up, origin at the pole's foot"},
        "geoid_separation_m": req.site.geoid_separation_m,
        "home": {"lat_deg": mission.home_lat_deg, "lon_deg": mission.home_lon_deg, "h_m": round(mission.home_h_m, 3),
                 "alt_written_m": round(mission.home_alt_m, 3), "alt_written_is_amsl": mission.home_alt_is_amsl,
                 "text": "home = take-off and landing point, away from the pole; the vehicle replaces it with where it arms"},
        "camera_guess": {
            "file": "camera_guess.yaml", "width": lens.width, "height": lens.height, "focal_px": round(lens.focal_px, 2),
            "focal_source": lens.focal_source, "cx": lens.width / 2.0, "cy": lens.height / 2.0,
            "hfov_deg": round(lens.hfov_deg, 2), "vfov_deg": round(lens.vfov_deg, 2),
            "distortion_level": lens.distortion_level, "distortion_k1_k2_p1_p2_k3": d.as_array().tolist(),
            "mount_height_m": req.site.mount_height_m, "azimuth_deg": req.site.azimuth_deg, "tilt_deg": req.site.tilt_deg,
            "roll_deg": req.site.roll_deg, "position_enu_m": cam_enu.pose.position_world.tolist(),
            "rotation_world_to_camera": np.round(cam_enu.pose.R_cam_from_world, 12).tolist(), "fps": lens.fps,
        },
        "marker": {"size_m": req.marker.size_m, "dictionary": req.marker.dictionary, "id": req.marker.marker_id,
                   "offset_frd_m": list(req.marker.offset_frd_m), "min_px": req.marker.min_px,
                   "mounting": "upright on the drone's nose, facing forward: the nose (and marker) faces the camera at every point",
                   "px_min": round(float(screen.marker_px[screen.keep].min()), 1), "px_max": round(float(screen.marker_px[screen.keep].max()), 1)},
        "limits": {"min_agl_m": req.limits.min_agl_m, "max_agl_m": req.limits.max_agl_m, "max_range_m": req.limits.max_range_m,
                   "keep_out_m": req.limits.keep_out_m, "geofence": None if req.geofence_latlon is None else [list(p) for p in req.geofence_latlon]},
        "strategy": {**chosen.row(), "recommended": scores[0].strategy.name, "optimized": ev.optimize, "dropped": screen.reasons},
        "points": len(pts),
        "grid": grid,
        "flight": {
            "flight_time_s": round(route.flight_time_s, 1), "path_length_m": round(route.path_length_m, 1),
            "battery_pct": round(battery_pct, 1), "endurance_min": req.endurance_s / 60.0,
            "hover_s": req.flight.hover_s, "speed_m_s": req.flight.speed_m_s, "end": req.end, "yaw_mode": req.yaw_mode,
            "takeoff": {"lat_deg": float(takeoff_geo[0]), "lon_deg": float(takeoff_geo[1]), "h_m": round(float(takeoff_geo[2]), 3),
                        "site_m": [round(float(v), 3) for v in route.takeoff_site], "alt_m": route.takeoff_alt_m},
            "mission_items": len(mission.items) + 1,
            "max_alt_m": round(max_alt, 2),
        },
        "uncertainty": {
            "trials": ev.trials, "seed": ev.seed, "sigma_px": ev.sigma_px, "sigma_3d_m": [ev.sigma_h_m, ev.sigma_h_m, ev.sigma_v_m],
            "model": ev.model, "rms_mean_px": chosen.rms_mean_px, "rms_p95_px": chosen.rms_p95_px,
            "ground_error_15m_cm": chosen.ground_error_15m_cm, "ground_error_15m_cm_p95": chosen.ground_error_15m_cm_p95,
            "monte_carlo": chosen.uncertainty,
        },
        "candidates": [s.row() for s in scores],
        "fence": {"inclusion_polygon_latlon": fence_geo[:, :2].tolist(), "margin_m": FENCE_MARGIN_M,
                  "exclusion_circle": {"lat_deg": req.site.lat_deg, "lon_deg": req.site.lon_deg, "radius_m": req.limits.keep_out_m}},
        "ardupilot_advice": {
            "RTL_ALT_cm": int(max(200, math.ceil(req.site.mount_height_m + 2.0) * 100)),
            "FENCE_ENABLE": 1, "FENCE_TYPE": 7, "FENCE_ALT_MAX_m": math.ceil(max_alt + 5.0),
            "text": "set RTL_ALT to clear the pole top (mount height + 2 m) but not the default 15 m climb; "
                    "the fence polygon and keep-out circle are in mission.plan (QGC uploads them)",
        },
        "warnings": list(warnings),
        "files": {
            "mission.plan": "QGroundControl plan (upload with QGC or dronecal-field fly)",
            "mission.waypoints": "Mission Planner QGC WPL 110, home as item 0",
            "mission.geojson": "map features; coordinates [lon, lat, h ellipsoidal]",
            "preview.png": "top view and predicted image",
            "plan.json": "this summary",
            "camera_guess.yaml": "the guessed camera (OpenCV FileStorage, world = ENU at the pole's foot)",
        },
    }


def mission_geojson(result: PlanResult) -> dict:
    """GeoJSON of the plan: camera, take-off, grid points, path, fence, keep-out, footprint."""
    req, mission = result.request, result.mission
    feats: list[dict] = []
    cam_geo = _site_to_geo(req, np.array([0.0, 0.0, req.site.mount_height_m]))[0]
    feats.append(msn.point_feature(cam_geo[1], cam_geo[0], cam_geo[2], {
        "kind": "camera", "azimuth_deg": req.site.azimuth_deg, "tilt_deg": req.site.tilt_deg, "mount_height_m": req.site.mount_height_m}))
    t_geo = _site_to_geo(req, result.route.takeoff_site)[0]
    feats.append(msn.point_feature(t_geo[1], t_geo[0], t_geo[2], {"kind": "takeoff", "text": "home: take-off and landing"}))
    for g in result.summary["grid"]:
        feats.append(msn.point_feature(g["lon_deg"], g["lat_deg"], g["h_m"], {
            "kind": "grid", "index": g["index"], "order": g["order"], "mission_seq": g["mission_seq"], "alt_m": g["alt_m"],
            "alt_frame": req.alt_frame, "hold_s": req.flight.hover_s, "pixel": g["pixel"], "marker_px": g["marker_px"]}))
    path_site = np.vstack([result.route.takeoff_site[None], result.route.takeoff_site[None] + [0, 0, result.route.takeoff_alt_m], result.route.points])
    if req.end == "land":
        path_site = np.vstack([path_site, result.route.takeoff_site[None]])
    pg = _site_to_geo(req, path_site)
    feats.append(msn.line_feature(pg[:, [1, 0, 2]], {"kind": "path", "length_m": round(result.route.path_length_m, 1)}))
    fg = _site_to_geo(req, np.column_stack([result.fence_site, np.zeros(len(result.fence_site))]))
    feats.append(msn.polygon_feature(fg[:, [1, 0]], {"kind": "geofence", "inclusion": True, "margin_m": FENCE_MARGIN_M}))
    ang = np.linspace(0, 2 * np.pi, 33)[:-1]
    ko = req.limits.keep_out_m * np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
    if req.limits.keep_out_m > 0:
        kg = _site_to_geo(req, ko)
        feats.append(msn.polygon_feature(kg[:, [1, 0]], {"kind": "keep_out", "radius_m": req.limits.keep_out_m}))
    fp = _site_to_geo(req, np.column_stack([result.footprint_site, np.zeros(len(result.footprint_site))]))
    feats.append(msn.polygon_feature(fp[:, [1, 0]], {"kind": "footprint", "text": f"ground seen by the guessed camera, cut at {FOOTPRINT_RANGE_M:g} m"}))
    return msn.geojson(feats, "dronecal-field plan; coordinates are [lon, lat, h] with h the WGS84 ellipsoidal height in metres; "
                              f"properties.alt_m are mission altitudes: {mission.alt_frame_text}")


def write_plan(result: PlanResult, out_dir: str | os.PathLike) -> list[Path]:
    """Write the plan folder atomically; returns the written paths.

    The files go to a temporary sibling folder that is renamed to ``out_dir``; an
    existing ``out_dir`` is replaced only if it is empty or a previous plan (holds plan.json).
    """
    from dronecal_field.camerafile import write_camera
    from dronecal_field.plan.preview import render_preview
    from dronecal_field.plan.schema import validate_plan

    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "plan.json").is_file())):
        raise InputError(f"--out {out} exists and is not a plan folder: choose a new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    req, mission = result.request, result.mission
    ko = (req.site.lat_deg, req.site.lon_deg, req.limits.keep_out_m) if req.limits.keep_out_m > 0 else None
    plan = msn.qgc_plan(mission, np.asarray(result.summary["fence"]["inclusion_polygon_latlon"]), ko, req.flight.speed_m_s)
    validate_plan(plan)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; the plan folder is an ordinary one
    try:
        (tmp / "mission.plan").write_text(msn.dumps(plan), encoding="utf-8")
        (tmp / "mission.waypoints").write_text(msn.waypoints_text(mission), encoding="utf-8")
        (tmp / "mission.geojson").write_text(msn.dumps(mission_geojson(result)), encoding="utf-8")
        (tmp / "plan.json").write_text(msn.dumps(result.summary), encoding="utf-8")
        write_camera(tmp / "camera_guess.yaml", result.camera_enu,
                     comment=f"dronecal-field plan: GUESSED camera (not calibrated): {req.lens.focal_source}, distortion {req.lens.distortion_level}")
        render_preview(result, tmp / "preview.png")
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            os.rename(out, old / out.name)
            os.rename(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return [out / f for f in PLAN_FILES]
