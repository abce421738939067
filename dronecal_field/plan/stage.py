"""The ``plan`` stage: options -> request -> evaluated candidates -> mission -> files.

:func:`make_plan` is pure (no files) and returns a :class:`PlanResult` whose
``summary`` is the machine-readable report; :func:`write_plan` writes the
folder atomically (a temporary folder renamed into place), so a failed run
never leaves a half-written plan.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from dronecal_field.core.camera import Camera, pixel_rays_batch
from dronecal_field.errors import InputError, PlanError
from dronecal_field.geodesy import enu_to_geodetic
from dronecal_field.plan import mission as msn
from dronecal_field.outfolder import replace_folder, staged_folder
from dronecal_field.plan.route import FlightModel, Route, plan_route, split_into_flights
from dronecal_field.plan.site import CameraSite, LensGuess, Marker, guess_camera, latlon_to_site, resolve_focal_px
from dronecal_field.plan.strategies import (
    PLAN_FOLD_MIN_SLOPE,
    ImageCandidate,
    Limits,
    StrategyScore,
    alternatives,
    fold_radius,
    image_candidate_params,
    make_strategy,
    paper_strategies,
    predict_points_on_roi,
    recommended_strategy,
    score_candidates,
    score_image_candidates,
    screen_grid,
)
from dronecal_field.sampling.band import GuessBand, band_cost, band_report, quiet_zone_fraction, scaled_distortion, screen_cameras
from dronecal_field.sampling.design import SAMPLINGS, LegTiming
from dronecal_field.sampling.predict import NoiseModel, lens_draws, normalised_radius
from dronecal_field.sampling.roi import Roi, RoiSpec, build_roi

MAX_PRACTICAL_MARKER_M = 1.0  # larger plates make a small copter a sail
FENCE_MARGIN_M = 3.0
FOOTPRINT_RANGE_M = 40.0
PLAN_FILES = ("mission.plan", "mission.waypoints", "mission.geojson", "preview.png", "plan.json", "camera_guess.yaml")
STRATEGIES = ("image", "paper-far", "paper-near", "paper-full")
BATTERY_RESERVE = 0.25  # a flight uses at most 75 % of --endurance
MAX_MC_POINTS = 800  # the Monte-Carlo of the chosen layout thins its leg samples to this many points
EQUIVALENT_ERROR = 1.10  # candidates within 10 % of the lowest predicted ROI error count as equal: the shortest flight wins
DEFAULT_DISTORTION_RANGE = ("0.5", "1")  # the lens may have half to all of the guessed level's distortion
COVERAGE_SLACK = 0.02  # a smaller marker is chosen when its coverage is within this of the best
LAYOUT_COVERAGE_SLACK = 0.05  # layouts covering within this of the marker's best count as covering; the predicted error decides
# among them (fly-through legs cover a few % more cells than holds, yet the paper's Table 1 camera's 2.4-min legs predicted
# 9.9 px over the ROI and measured 5.9 px on the ground, its 6.5-min holds 4.5 px predicted, 0.6 px measured)


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
    strategy: str = "image"
    sampling: str = "auto"  # 'auto' = the lower predicted ROI error within the battery
    marker_sizes_m: tuple[float, ...] = (0.3, 0.6)
    roi: RoiSpec = RoiSpec()
    timing: LegTiming = LegTiming()
    reserve: float = BATTERY_RESERVE
    band: GuessBand = GuessBand()  # how far the camera may be from the guess (``sampling.band``)
    camera_enu: Camera | None = None  # an estimated camera (ENU at the site's origin) used instead of the guess (``plan --from-run``)

    @property
    def battery_budget_s(self) -> float:
        """Longest flight allowed, s: ``endurance_s`` less the reserve."""
        return (1.0 - self.reserve) * self.endurance_s

    @property
    def choice_budget_s(self) -> float:
        """Flight time the image layouts are chosen within, s: the battery budget, or ``--max-flight-time`` if shorter."""
        cap = self.evaluation.max_flight_time_s
        return self.battery_budget_s if cap is None else min(cap, self.battery_budget_s)


def _opt(opts: dict[str, Any], key: str) -> Any:
    """The option's value, or its documented default when unset (None); a given 0 stays 0."""
    from dronecal_field.plan.site import OPTION_BY_KEY

    v = opts.get(key)
    return OPTION_BY_KEY[key].default if v is None else v


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
        roll_deg=float(_opt(opts, "roll")), geoid_separation_m=n_geoid,
    )
    w, h = _need(opts, "image_size", "the image size as WIDTHxHEIGHT")
    f_px, how = resolve_focal_px(w, h, opts.get("focal_px"), opts.get("focal_mm"), opts.get("sensor_width"),
                                 opts.get("sensor_format"), opts.get("pixel_pitch"), opts.get("hfov"))
    fps = float(_opt(opts, "fps"))
    if fps <= 0:
        raise InputError(f"--fps {fps:g} must be positive")
    lens = LensGuess(width=w, height=h, focal_px=f_px, distortion_level=_opt(opts, "distortion"), focal_source=how, fps=fps)

    if opts.get("marker_size") is not None:  # one marker given: that one
        sizes: tuple[float, ...] = (float(opts["marker_size"]),)
    else:
        sizes = tuple(sorted(set(float(v) for v in _opt(opts, "marker_sizes"))))
    for v in sizes:
        if not 0.02 <= v <= MAX_PRACTICAL_MARKER_M:
            flag = "--marker-size" if opts.get("marker_size") is not None else "--marker-sizes"
            raise InputError(f"{flag} {v:g} m is outside 0.02-{MAX_PRACTICAL_MARKER_M:g} m: give the printed marker side in metres")
    size = sizes[0]
    min_px = float(_opt(opts, "min_marker_px"))
    if min_px <= 0:
        raise InputError(f"--min-marker-px {min_px:g} must be positive: give the smallest marker side the detector reads, px")
    marker = Marker(size_m=size, dictionary=_opt(opts, "aruco_dict"), marker_id=int(_opt(opts, "marker_id")),
                    offset_frd_m=tuple(_opt(opts, "marker_offset")), min_px=min_px)

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
    speed = float(_opt(opts, "speed"))
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
    endurance_min = float(_opt(opts, "endurance"))
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
        max_search_height_m=mount + 3.0, quiet_zone_frac=quiet_zone_fraction(marker.dictionary),
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
        trials=int(_opt(opts, "trials")), seed=int(_opt(opts, "seed")), sigma_px=float(_opt(opts, "sigma_px")),
        sigma_h_m=float(_opt(opts, "sigma_h")), sigma_v_m=float(_opt(opts, "sigma_v")),
        model=str(_opt(opts, "model")), optimize=bool(opts.get("optimize")),
        max_flight_time_s=None if budget is None else float(budget) * 60.0,
    )
    if evaluation.trials < 2:
        raise InputError(f"--trials {evaluation.trials} is too few: use at least 20 (200 is the default)")
    if evaluation.sigma_px < 0 or evaluation.sigma_h_m < 0 or evaluation.sigma_v_m < 0:
        raise InputError("--sigma-px/--sigma-h/--sigma-v must not be negative: give the noise std (px, m)")
    if budget is not None and budget <= 0:
        raise InputError(f"--max-flight-time {budget:g} min must be positive")
    alt_frame = _opt(opts, "alt_frame")
    if alt_frame == "amsl" and n_geoid is None:
        raise InputError("--alt-frame amsl needs the geoid separation: add --geoid-separation N (m) or --ground-amsl with --ground-alt")
    strategy = _opt(opts, "strategy")
    if evaluation.optimize and strategy == "image":
        strategy = "paper-far"  # --optimize chooses among the paper's 18 alternatives
    sampling = _opt(opts, "sampling")
    exposure_s, gnss_hz = float(_opt(opts, "exposure_s")), float(_opt(opts, "gnss_hz"))
    if exposure_s <= 0:
        raise InputError(f"--exposure-s {exposure_s:g} must be positive: give the shutter time in seconds (0.004 is a daylight guess)")
    if gnss_hz <= 0:
        raise InputError(f"--gnss-hz {gnss_hz:g} must be positive: give the receiver's fix rate in Hz (GPS_RATE_MS 100 = 10 Hz)")
    roi = roi_spec_from_options(opts, site)
    band = band_from_options(opts, lens.distortion_level)
    return PlanRequest(
        site=site, lens=lens, marker=marker, limits=limits, flight=FlightModel(speed_m_s=speed, hover_s=hover),
        evaluation=evaluation, takeoff_site=takeoff_site, geofence_latlon=opts.get("geofence"),
        alt_frame=alt_frame, end=_opt(opts, "end"), yaw_mode=_opt(opts, "yaw_mode"),
        endurance_s=endurance_min * 60.0, name=opts.get("name"), notes=tuple(notes), strategy=strategy, sampling=sampling,
        marker_sizes_m=sizes, roi=roi, timing=LegTiming(fps=fps, exposure_s=exposure_s, gnss_hz=gnss_hz), band=band,
    )


def band_from_options(opts: dict[str, Any], level: str) -> GuessBand:
    """The guess band of ``--focal-tolerance``, ``--tilt-tolerance``, ``--azimuth-tolerance``, ``--distortion-range``."""
    from dronecal_field.plan.site import DISTORTION_LEVELS

    f_tol = float(_opt(opts, "focal_tolerance"))
    t_tol, a_tol = float(_opt(opts, "tilt_tolerance")), float(_opt(opts, "azimuth_tolerance"))
    for flag, v, hi in (("--focal-tolerance", f_tol, 60.0), ("--tilt-tolerance", t_tol, 30.0), ("--azimuth-tolerance", a_tol, 60.0)):
        if not 0.0 <= v <= hi:
            raise InputError(f"{flag} {v:g} is outside 0-{hi:g}: give how far the real camera may be from the guess (0: exactly as given)")
    raw = opts.get("distortion_range") or DEFAULT_DISTORTION_RANGE
    if len(raw) not in (1, 2):
        raise InputError(f"--distortion-range {','.join(map(str, raw))} needs LOW,HIGH: levels (none, medium, strong) or shares of the --distortion level (0.5,1)")
    guess = DISTORTION_LEVELS[level]
    names, dists = [], []
    for v in raw:
        if str(v) in DISTORTION_LEVELS:
            names.append(str(v))
            dists.append(DISTORTION_LEVELS[str(v)])
        else:
            try:
                k = float(v)
            except ValueError:
                raise InputError(f"--distortion-range {v!r} is neither a level (none, medium, strong) nor a share of the --distortion level (e.g. 0.5)") from None
            if not 0.0 <= k <= 3.0:
                raise InputError(f"--distortion-range {k:g} is outside 0-3 (shares of the --distortion level)")
            names.append(f"{k:g}x {level}")
            dists.append(scaled_distortion(guess, k))
    return GuessBand(focal_tolerance=f_tol / 100.0, tilt_tolerance_deg=t_tol, azimuth_tolerance_deg=a_tol,
                     distortions=tuple(dists), distortion_names=tuple(names))

def roi_spec_from_options(opts: dict[str, Any], site: CameraSite) -> RoiSpec:
    """The region of interest of ``--roi`` / ``--roi-range`` (see ``sampling.roi``)."""
    r_min, r_max = (float(v) for v in _opt(opts, "roi_range"))
    if not 0 <= r_min < r_max:
        raise InputError(f"--roi-range {r_min:g},{r_max:g} is not MIN,MAX metres with 0 <= MIN < MAX: e.g. --roi-range 3,40")
    if r_max > 500:
        raise InputError(f"--roi-range max {r_max:g} m is beyond 500 m: a marker is not seen that far; give the range you measure in")
    roi = opts.get("roi")
    if roi is None:
        return RoiSpec(kind="range", range_m=(r_min, r_max), source="--roi-range" if opts.get("roi_range") is not None else "default")
    if str(roi).strip() == "image":
        return RoiSpec(kind="image", range_m=(r_min, r_max), source="--roi image")
    lat_lon = read_roi_polygon(str(roi))
    xy = latlon_to_site(site, lat_lon)[:, :2]
    return RoiSpec(kind="polygon", range_m=(0.0, max(r_max, float(np.hypot(xy[:, 0], xy[:, 1]).max()) + 1.0)),
                   polygon_site=tuple(tuple(map(float, p)) for p in xy), source=Path(str(roi)).name)


def read_roi_polygon(path: str) -> np.ndarray:
    """(K, 2) lat, lon (deg) of the first Polygon in a GeoJSON file (WGS84, [lon, lat] order as GeoJSON says)."""
    import json

    p = Path(path)
    if not p.is_file():
        raise InputError(f"--roi {path}: no such file; give a GeoJSON polygon (WGS84), 'image' for the whole image, or leave it out")
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"--roi {path} is not JSON ({exc}): export the polygon as GeoJSON") from None
    geoms: list[dict] = []
    if isinstance(data, dict) and data.get("type") == "FeatureCollection":
        geoms = [f.get("geometry") or {} for f in data.get("features", []) if isinstance(f, dict)]
    elif isinstance(data, dict) and data.get("type") == "Feature":
        geoms = [data.get("geometry") or {}]
    elif isinstance(data, dict):
        geoms = [data]
    for g in geoms:
        coords = None
        if g.get("type") == "Polygon" and g.get("coordinates"):
            coords = g["coordinates"][0]
        elif g.get("type") == "MultiPolygon" and g.get("coordinates"):
            coords = g["coordinates"][0][0]
        if coords is None:
            continue
        try:
            ll = np.asarray([[float(c[1]), float(c[0])] for c in coords], float)
        except (TypeError, ValueError, IndexError):
            raise InputError(f"--roi {path}: the polygon's coordinates are not [lon, lat] numbers") from None
        if len(ll) >= 4 and np.allclose(ll[0], ll[-1]):
            ll = ll[:-1]
        if len(ll) < 3 or not np.all(np.abs(ll[:, 0]) <= 90) or not np.all(np.abs(ll[:, 1]) <= 360):
            raise InputError(f"--roi {path}: the polygon needs 3+ vertices as [lon, lat] degrees (GeoJSON order)")
        return ll
    raise InputError(f"--roi {path} holds no Polygon: draw the road or car park as a polygon and export GeoJSON (WGS84)")


@dataclass(frozen=True, eq=False)
class Chosen:
    """The layout the plan flies, whichever strategy made it.

    Hold points in the order given to the route: ``marker_site`` /
    ``vehicle_site`` (N, 3) site metres, ``marker_px`` (N,), ``hold_s`` (N,)
    seconds (0 = fly through), ``leg`` (N,) leg number; ``leg_speed_m_s`` the
    constant speed of fly-through legs (None when hovering everywhere).
    ``samples_site`` (S, 3) are all the positions the prediction counts
    (holds and fixes along legs). ``image`` or ``paper`` is the scored candidate.
    """

    name: str
    text: str
    strategy: str
    marker_size_m: float
    marker_site: np.ndarray
    vehicle_site: np.ndarray
    marker_px: np.ndarray
    hold_s: np.ndarray
    leg: np.ndarray
    ordered: bool
    leg_speed_m_s: float | None  # pass-through legs (``through``)
    cruise_m_s: float | None  # every leg (``mixed``: fixes between holds need the leg speed); None = --speed
    samples_site: np.ndarray
    samples_sigma_h_m: np.ndarray
    samples_rtk_factor: np.ndarray
    heights_m: tuple[float, ...] = ()
    image: ImageCandidate | None = None
    paper: StrategyScore | None = None

    @property
    def sampling(self) -> str:
        return self.image.design.params.sampling if self.image is not None else "hover"

    @classmethod
    def from_image(cls, c: ImageCandidate) -> "Chosen":
        d = c.design
        return cls(name=c.name, text=d.params.describe(), strategy="image", marker_size_m=d.params.marker_size_m,
                   marker_site=d.marker_site, vehicle_site=d.vehicle_site, marker_px=d.marker_px, hold_s=d.hold_s, leg=d.leg,
                   ordered=True, leg_speed_m_s=d.speed_m_s if d.params.sampling == "through" else None,
                   cruise_m_s=d.speed_m_s if d.params.sampling == "mixed" else None,
                   samples_site=d.samples_site, samples_sigma_h_m=d.samples_sigma_h_m, samples_rtk_factor=d.samples_rtk_factor, image=c)

    @classmethod
    def from_paper(cls, s: StrategyScore, hover_s: float, marker_size_m: float) -> "Chosen":
        pts = s.screen.points
        n = len(pts)
        return cls(name=s.strategy.name, text=s.strategy.describe(), strategy="paper", marker_size_m=marker_size_m,
                   marker_site=pts, vehicle_site=s.screen.vehicle_points, marker_px=s.screen.marker_px[s.screen.keep],
                   hold_s=np.full(n, float(hover_s)), leg=np.arange(n), ordered=False, leg_speed_m_s=None, cruise_m_s=None,
                   samples_site=pts, samples_sigma_h_m=np.zeros(n), samples_rtk_factor=np.ones(n), heights_m=s.screen.heights_m, paper=s)


@dataclass(frozen=True, eq=False)
class PlanResult:
    """A finished plan: the chosen layout, its flights (routes and missions) and the report."""

    request: PlanRequest
    camera_enu: Camera
    camera_site: Camera
    chosen: Chosen
    candidates: tuple
    routes: tuple[Route, ...]
    missions: tuple[msn.Mission, ...]
    point_flight: np.ndarray  # (N,) flight number (0-based) of each hold point
    fence_site: np.ndarray  # (M, 2) inclusion polygon, site XY
    footprint_site: np.ndarray  # (K, 2) ground footprint of the image, site XY
    roi: Roi | None
    roi_prediction: Any  # sampling.predict.RoiPrediction of the chosen layout, or None
    summary: dict
    warnings: tuple[str, ...] = field(default_factory=tuple)

    @property
    def route(self) -> Route:
        """The first flight's route (the only one unless the plan was split)."""
        return self.routes[0]

    @property
    def mission(self) -> msn.Mission:
        return self.missions[0]

    @property
    def grid_site(self) -> np.ndarray:
        """(N, 3) marker centres of the plan, site frame."""
        return self.chosen.marker_site

    def mission_names(self) -> list[str]:
        """File stems: 'mission' for one flight, 'mission-1', 'mission-2', ... when split."""
        return ["mission"] if len(self.missions) == 1 else [f"mission-{k + 1}" for k in range(len(self.missions))]


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


def _no_image_plan_error(req: PlanRequest, cands: tuple[ImageCandidate, ...]) -> PlanError:
    """The most useful message when no image-space layout can be flown: the rule that blocks most target rays."""
    from collections import Counter

    from dronecal_field.sampling.design import REASON_TEXT

    best = max(cands, key=lambda c: c.design.n_points)
    needed = [c.design.needed_marker_m for c in cands if c.design.needed_marker_m]
    reasons = Counter(r for c in cands for r in c.design.target_reason if r is not None)
    if best.design.n_points == 0 and req.site.tilt_deg < 0:
        return PlanError(f"the camera is tilted {-req.site.tilt_deg:g} deg up and sees no point it can be calibrated from: check --tilt (deg below horizontal)")
    if needed and reasons and reasons.most_common(1)[0][0] == "marker_too_small":
        need = max(needed)
        if need > MAX_PRACTICAL_MARKER_M:
            return PlanError(
                f"a marker {req.limits.min_marker_px:g} px wide where this camera sees the ROI needs {need:.2f} m, more than a drone can carry "
                f"({MAX_PRACTICAL_MARKER_M:g} m): lower --min-marker-px only if your detector reads smaller markers, or narrow --roi-range"
            )
        return PlanError(f"the {max(req.marker_sizes_m):g} m marker is under {req.limits.min_marker_px:g} px where the ROI is: print a marker of at least "
                         f"{math.ceil(need * 20) / 20:.2f} m (--marker-sizes)")
    if best.design.n_points == 0:
        why, _ = reasons.most_common(1)[0] if reasons else ("behind_camera", 0)
        fmt = {"min_agl": req.limits.min_agl_m, "max_agl": "unset" if req.limits.max_agl_m is None else f"{req.limits.max_agl_m:g} m",
               "keep_out": req.limits.keep_out_m, "max_range": "unset" if req.limits.max_range_m is None else f"{req.limits.max_range_m:g} m",
               "size": max(req.marker_sizes_m), "min_px": req.limits.min_marker_px, "margin": req.limits.margin_px, "ratio": 1.5}
        return PlanError(
            f"the camera sees no reachable point along the rays of its region of interest ({REASON_TEXT.get(why, why).format(**fmt)}): "
            "check --tilt/--azimuth, lower --min-agl or raise --max-agl/--max-range"
        )
    return PlanError(f"too few usable points for a non-coplanar calibration: best layout {best.name} has {best.problem}; "
                     "relax --min-agl/--max-agl/--keep-out/--max-range, or widen --roi-range")


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
    """Design or pick the sampling for this camera, split it into flights, build the missions and the report.

    ``--strategy image`` (default): candidates from ``sampling.design`` scored by
    the predicted ROI error (``sampling.predict``, linearised + extrapolation);
    the chosen one also gets the paper's Monte-Carlo. ``paper-*``: the paper's
    strategies scored by ``plan.strategies.score_candidates`` (the survey's row
    function; on a Dask cluster when ``client`` is given). Either way the
    chosen layout is scored on the ROI, and compared with paper-far.

    Raises ``PlanError`` (with what to change) when no safe, useful mission exists.
    """
    cam_site = guess_camera(req.site, req.lens, frame="site")
    cam_enu = guess_camera(req.site, req.lens, frame="enu")
    if req.camera_enu is not None:  # the scout's estimate: its lens, principal point and pose
        cam_enu = req.camera_enu
        R_site = np.asarray(cam_enu.pose.R_cam_from_world) @ req.site.R_enu_from_site
        cam_site = cam_enu.with_(pose=type(cam_enu.pose).from_position(R_site, req.site.R_enu_from_site.T @ cam_enu.pose.position_world),
                                 enu_origin=None)
    _check_sees_ground(req, cam_site)
    # every point the plan keeps is screened through the guess and each factor of the band at its full tolerance alone
    req = replace(req, limits=replace(req.limits, band=screen_cameras(cam_site, req.band)))
    warnings = list(req.notes)
    roi = build_roi(cam_site, req.roi)
    from dronecal_field.sampling.roi import evaluation_points

    roi_pts, _ = evaluation_points(roi)
    draws = lens_draws(cam_site, cam_site.distortion.as_array(), float(normalised_radius(cam_site, roi_pts).max()), seed=req.evaluation.seed)
    noise = NoiseModel(sigma_px=req.evaluation.sigma_px, sigma_h_m=req.evaluation.sigma_h_m, sigma_v_m=req.evaluation.sigma_v_m,
                       model="auto" if req.evaluation.model == "default" else req.evaluation.model)
    if req.strategy == "image":
        chosen, candidates, rows = _choose_image(req, cam_site, roi, noise, draws, warnings)
    else:
        chosen, candidates, rows = _choose_paper(req, cam_site, client, warnings)
    prediction = predict_points_on_roi(cam_site, chosen.samples_site, roi, noise, draws, chosen.samples_sigma_h_m, chosen.samples_rtk_factor)
    cost = band_cost(cam_site, req.band, chosen.samples_site, replace(req.limits, marker_size_m=chosen.marker_size_m), lambda keep: predict_points_on_roi(
        cam_site, chosen.samples_site[keep], roi, noise, draws, chosen.samples_sigma_h_m[keep], chosen.samples_rtk_factor[keep]).summary()["combined_px"]["rms"])
    warnings += [cost["text"]] if cost else []
    limits = replace(req.limits, marker_size_m=chosen.marker_size_m)
    if chosen.cruise_m_s is not None:
        req = replace(req, flight=replace(req.flight, speed_m_s=min(req.flight.speed_m_s, chosen.cruise_m_s)))
    routes, flight_of = _flights(req, chosen, limits)
    if len(routes) > 1:
        warnings.append(f"the plan takes {sum(r.flight_time_s for r in routes) / 60:.1f} min: split into {len(routes)} flights "
                        f"(mission-1 ... mission-{len(routes)}), each within "
                        + (f"--max-flight-time {req.choice_budget_s / 60:g} min, " if req.choice_budget_s < req.battery_budget_s else
                           f"75 % of the {req.endurance_s / 60:g} min battery, ") +
                        "each starting and ending at the take-off point")
    missions = tuple(
        msn.build_mission(r, req.site.R_enu_from_site, req.site.origin, req.site.mount_height_m, req.flight.speed_m_s,
                          alt_frame=req.alt_frame, yaw_mode=req.yaw_mode, geoid_separation_m=req.site.geoid_separation_m)
        for r in routes
    )
    datum = msn.home_datum_warning(missions[0])
    if datum is not None:
        warnings.append(datum)
    fence = msn.fence_polygon(np.vstack([r.points for r in routes] + [routes[0].takeoff_site[None]]), FENCE_MARGIN_M)
    footprint = footprint_site(cam_site)
    longest = max(r.flight_time_s for r in routes)
    battery_pct = 100.0 * longest / req.endurance_s
    if battery_pct > 100.0 * (1.0 - req.reserve) + 1e-6:
        warnings.append(f"a flight takes {battery_pct:.0f} % of a {req.endurance_s / 60:g} min battery (more than the 75 % allowed): shorten --hover or add flights")
    if req.geofence_latlon is not None:
        from matplotlib.path import Path as MplPath

        gf = MplPath(np.asarray(req.limits.geofence_xy))
        if not gf.contains_point(routes[0].takeoff_site[:2]):
            warnings.append("the take-off point is outside --geofence")
    monte_carlo = _monte_carlo(req, cam_site, chosen, prediction.model)
    comparison = _paper_far_comparison(req, cam_site, roi, noise, draws, chosen, prediction)
    result = PlanResult(
        request=req, camera_enu=cam_enu, camera_site=cam_site, chosen=chosen, candidates=candidates, routes=routes, missions=missions,
        point_flight=flight_of, fence_site=fence, footprint_site=footprint, roi=roi, roi_prediction=prediction,
        summary={}, warnings=tuple(warnings),
    )
    summary = _json_safe(_summary(result, rows, battery_pct, monte_carlo, comparison))
    return replace(result, summary=summary)


def _choose_image(req: PlanRequest, cam_site: Camera, roi: Roi, noise: NoiseModel, draws: np.ndarray,
                  warnings: list[str]) -> tuple[Chosen, tuple, list[dict]]:
    """Score the image-space candidates and pick: the smallest marker that covers the ROI; among the layouts that
    cover it, the lowest ROI error within one battery, or, when none fits, within the fewest flights."""
    samplings = SAMPLINGS if req.sampling == "auto" else (req.sampling,)
    params = image_candidate_params(req.marker_sizes_m, samplings)
    cands = score_image_candidates(cam_site, roi, params, req.limits, req.flight, req.timing, noise, draws,
                                   takeoff_site=req.takeoff_site, end=req.end)
    usable = [c for c in cands if c.usable]
    if not usable:
        raise _no_image_plan_error(req, cands)
    best_cov = {m: max((c.design.coverage for c in usable if c.design.params.marker_size_m == m), default=-1.0) for m in req.marker_sizes_m}
    top = max(best_cov.values())
    size = min(m for m, v in best_cov.items() if v >= top - COVERAGE_SLACK)
    # only layouts that cover the ROI (within LAYOUT_COVERAGE_SLACK of the best): one battery if one of them fits, else flights
    pool = [c for c in usable if c.design.params.marker_size_m == size and c.design.coverage >= best_cov[size] - LAYOUT_COVERAGE_SLACK]
    budget = req.choice_budget_s
    fit = [c for c in pool if c.flight_time_s is not None and c.flight_time_s <= budget]
    if not fit and req.evaluation.max_flight_time_s is not None:
        # the user's --max-flight-time is a cap, not a wish: the layouts within it that cover the most of the ROI
        within = [c for c in usable if c.design.params.marker_size_m == size and c.flight_time_s is not None and c.flight_time_s <= budget]
        if within:
            most = max(c.design.coverage for c in within)
            fit = [c for c in within if c.design.coverage >= most - LAYOUT_COVERAGE_SLACK]
            shortest = min(pool, key=lambda c: c.flight_time_s or math.inf)
            warnings.append(f"no layout covering the whole ROI fits --max-flight-time {budget / 60:g} min (the shortest, {shortest.name}, "
                            f"covers {100 * shortest.design.coverage:.0f} % in {(shortest.flight_time_s or 0) / 60:.1f} min): this plan covers "
                            f"{100 * most:.0f} %; --max-flight-time {math.ceil((shortest.flight_time_s or 0) / 60):g} covers it all")
    if not fit:  # nothing that covers the ROI fits one battery: the layouts needing the fewest flights
        n_flights = {id(c): math.ceil((c.flight_time_s or math.inf) / budget) for c in pool}
        fewest = min(n_flights.values())
        fit = [c for c in pool if n_flights[id(c)] <= fewest]
    # the lowest predicted ROI error; within EQUIVALENT_ERROR of it, the shortest flight
    best = min(c.objective for c in fit)
    chosen = min((c for c in fit if c.objective <= EQUIVALENT_ERROR * best), key=lambda c: (c.flight_time_s, c.objective))
    needed = [c.design.needed_marker_m for c in cands if c.design.needed_marker_m]
    if needed and top < 0.98:
        warnings.append(f"a {math.ceil(max(needed) * 20) / 20:.2f} m marker would reach more of the ROI (the {max(req.marker_sizes_m):g} m marker is under "
                        f"{req.limits.min_marker_px:g} px there): add it to --marker-sizes")
    for part in chosen.design.unreachable:
        if part["reason"] != "between_samples" and part["share_pct"] >= 2.0:
            warnings.append(f"not reached: {part['text']}")
    return Chosen.from_image(chosen), cands, [c.row() for c in cands]


def _choose_paper(req: PlanRequest, cam_site: Camera, client: Any, warnings: list[str]) -> tuple[Chosen, tuple, list[dict]]:
    """The paper's strategies (``--strategy paper-*``, ``--optimize``), scored by the survey's Monte-Carlo rows."""
    ev = req.evaluation
    base = recommended_strategy(cam_site)
    x_range = req.strategy.split("-", 1)[1]
    if x_range != base.x_range_name:
        base = make_strategy(x_range, base.y_step_m, base.n_heights)
    strategies = list(alternatives(base))
    if ev.optimize:
        names = {s.name for s in strategies}
        strategies += [s for s in paper_strategies() if s.name not in names]
    limits = replace(req.limits, marker_size_m=req.marker.size_m)
    scores = score_candidates(cam_site, strategies, limits, ev.monte_carlo_settings(), req.flight, client)
    usable = [s for s in scores if s.usable]
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
    dropped_small = chosen.screen.reasons.get("marker_too_small", 0)
    if dropped_small:
        need = chosen.screen.needed_marker_size_m(limits)
        warnings.append(f"{dropped_small} grid points dropped because the {req.marker.size_m:g} m marker is under {req.limits.min_marker_px:g} px there; a {math.ceil((need or 0) * 20) / 20:.2f} m marker keeps them")
    return Chosen.from_paper(chosen, req.flight.hover_s, req.marker.size_m), scores, [s.row() for s in scores]


def _flights(req: PlanRequest, chosen: Chosen, limits: Limits) -> tuple[tuple[Route, ...], np.ndarray]:
    """The chosen points as one route, or as several flights when one exceeds the battery budget.

    Returns the routes (their ``grid_index`` are the plan's point indices) and
    per point (N,) the (first) flight that flies it. Flights are cut between legs only.
    """
    n = len(chosen.marker_site)
    one = plan_route(chosen.vehicle_site, chosen.marker_site, limits, req.flight, takeoff_site=req.takeoff_site, end=req.end,
                     hold_s=chosen.hold_s, ordered=chosen.ordered, leg_speed_m_s=chosen.leg_speed_m_s)
    if one.flight_time_s <= req.choice_budget_s:
        return (one,), np.zeros(n, int)
    # every flight starts and ends where the one-flight plan would take off
    takeoff = one.takeoff_site
    if not chosen.ordered:  # fly the route's own order, cut into flights
        order = one.grid_order
    else:
        order = np.arange(n)
    # each flight within the battery, and within --max-flight-time when the user set a shorter one
    endurance_s = req.endurance_s * req.choice_budget_s / req.battery_budget_s
    routes = split_into_flights(chosen.vehicle_site[order], chosen.marker_site[order], chosen.hold_s[order], limits, req.flight,
                                endurance_s, reserve=req.reserve, takeoff_site=takeoff, end=req.end, ordered=True,
                                leg_speed_m_s=chosen.leg_speed_m_s)
    # grid indices of every flight refer to the points as given to the split: map them back to the plan's points
    routes = [replace(r, grid_index=np.where(r.grid_index >= 0, order[np.maximum(r.grid_index, 0)], -1)) for r in routes]
    flight_of = np.full(n, -1)
    for k, r in enumerate(routes):
        g = r.grid_order
        flight_of[g[flight_of[g] < 0]] = k  # a point flown twice (a leg re-entered) belongs to its first flight
    return tuple(routes), flight_of


def _monte_carlo(req: PlanRequest, cam_site: Camera, chosen: Chosen, model: str) -> dict | None:
    """The paper's Monte-Carlo (``core.uncertainty.monte_carlo``) of the chosen layout, leg samples thinned."""
    if chosen.paper is not None and chosen.paper.uncertainty is not None:
        return {**chosen.paper.uncertainty, "points_used": len(chosen.samples_site), "thinned_from": None}
    from dronecal_field.core.uncertainty import monte_carlo
    from dronecal_field.sampling.predict import sample_sigmas

    ev = req.evaluation
    S, sig = chosen.samples_site, chosen.samples_sigma_h_m
    idx = np.arange(len(S))
    if len(S) > MAX_MC_POINTS:
        is_hold = sig == 0
        holds = idx[is_hold]
        rest = idx[~is_hold]
        k = max(MAX_MC_POINTS - len(holds), 0)
        idx = np.concatenate([holds, rest[np.linspace(0, len(rest) - 1, k).round().astype(int)] if k and len(rest) else rest[:0]])
    s3 = sample_sigmas(sig[idx], NoiseModel(sigma_px=ev.sigma_px, sigma_h_m=ev.sigma_h_m, sigma_v_m=ev.sigma_v_m), chosen.samples_rtk_factor[idx])
    try:
        mc = monte_carlo(cam_site, S[idx], trials=ev.trials, sigma_3d=s3, sigma_2d=ev.sigma_px, seed=ev.seed, model=model)
    except Exception as exc:  # a degenerate trial set must not sink the plan: the linearised figures stand
        return {"error": str(exc)}
    return {**mc.to_dict(), "points_used": int(len(idx)), "thinned_from": int(len(S)) if len(idx) < len(S) else None}


def _paper_far_comparison(req: PlanRequest, cam_site: Camera, roi: Roi, noise: NoiseModel, draws: np.ndarray, chosen: Chosen,
                          prediction: Any) -> dict:
    """paper-far (the paper's recommendation) scored by the same ROI prediction, beside the chosen layout."""
    base = recommended_strategy(cam_site)
    far = make_strategy("far", base.y_step_m, base.n_heights)
    limits = replace(req.limits, marker_size_m=chosen.marker_size_m)
    screen = screen_grid(far, cam_site, limits)
    row: dict[str, Any] = {"strategy": far.name, "marker_size_m": chosen.marker_size_m, "points": int(len(screen.points))}
    if len(screen.points) >= 12:
        p = predict_points_on_roi(cam_site, screen.points, roi, noise, draws)
        try:
            r = plan_route(screen.vehicle_points, screen.points, limits, req.flight, takeoff_site=req.takeoff_site, end=req.end)
            row["flight_time_s"] = round(r.flight_time_s, 1)
        except PlanError as exc:
            row["flight_time_s"] = None
            row["problem"] = str(exc)
        row["coverage_pct"] = round(100.0 * roi.coverage(cam_site.project(screen.points)), 1)
        row["prediction"] = p.summary()
    else:
        row["problem"] = f"{len(screen.points)} points: too few to calibrate"
    s = prediction.summary()
    pf = row.get("prediction")
    row["text"] = (f"chosen {chosen.name}: ROI {s['combined_px']['rms']:.2f} px RMS combined; paper-far: "
                   + (f"{pf['combined_px']['rms']:.2f} px" if pf else row.get("problem", "n/a")))
    return row


def _site_to_geo(req: PlanRequest, pts_site: np.ndarray) -> np.ndarray:
    """(N, 3) lat, lon, h of site-frame points."""
    return enu_to_geodetic(np.atleast_2d(pts_site) @ req.site.R_enu_from_site.T, req.site.origin)


def _summary(result: PlanResult, rows: list[dict], battery_pct: float, monte_carlo: dict | None, comparison: dict) -> dict:
    from dronecal_field import __version__

    req, cam_enu, cam_site, chosen = result.request, result.camera_enu, result.camera_site, result.chosen
    pts, veh = chosen.marker_site, chosen.vehicle_site
    geo = _site_to_geo(req, veh)
    uv = cam_site.project(pts)
    names = result.mission_names()
    home_h = result.missions[0].home_h_m
    alt_written = (geo[:, 2] - home_h) if req.alt_frame == "relative" else geo[:, 2] - (req.site.geoid_separation_m or 0.0)
    # mission items and routes carry the plan's point indices (a point flown twice belongs to its first flight)
    seq_by_flight = [{it.grid_index: seq for seq, it in enumerate(m.items, start=1) if it.label.startswith("grid")} for m in result.missions]
    order_by_flight = [{int(g): k for k, g in enumerate(r.grid_order)} for r in result.routes]
    offsets = np.cumsum([0] + [len(r.grid_order) for r in result.routes])
    grid = []
    for i in range(len(pts)):
        k = int(result.point_flight[i])
        grid.append({
            "index": i,
            "flight": k + 1,
            "order": int(offsets[k] + order_by_flight[k][i]),
            "mission_seq": seq_by_flight[k].get(i),
            "marker_site_m": [round(float(v), 4) for v in pts[i]],
            "drone_site_m": [round(float(v), 4) for v in veh[i]],
            "drone_enu_m": [round(float(v), 4) for v in (req.site.R_enu_from_site @ veh[i])],
            "lat_deg": float(geo[i, 0]), "lon_deg": float(geo[i, 1]), "h_m": round(float(geo[i, 2]), 4),
            "alt_m": round(float(alt_written[i]), 3),
            "pixel": [round(float(uv[i, 0]), 1), round(float(uv[i, 1]), 1)],
            "marker_px": round(float(chosen.marker_px[i]), 1),
            "hold_s": float(np.round(chosen.hold_s[i])),
            "leg": int(chosen.leg[i]),
        })
    fence_geo = _site_to_geo(req, np.column_stack([result.fence_site, np.zeros(len(result.fence_site))]))
    takeoff_geo = _site_to_geo(req, result.routes[0].takeoff_site)[0]
    max_alt = float(max(np.max(r.points[:, 2] - r.takeoff_site[2]) for r in result.routes))
    lens = req.lens
    d = cam_enu.distortion
    ev = req.evaluation
    keep_px = chosen.marker_px
    flights = [
        {"file": f"{n}.plan", "flight_time_s": round(r.flight_time_s, 1), "path_length_m": round(r.path_length_m, 1),
         "points": int(len(r.grid_order)), "battery_pct": round(100.0 * r.flight_time_s / req.endurance_s, 1),
         "mission_items": len(m.items) + 1}
        for n, r, m in zip(names, result.routes, result.missions)
    ]
    pred = result.roi_prediction.summary() if result.roi_prediction is not None else None
    design = chosen.image.design if chosen.image is not None else None
    coverage = design.coverage if design is not None else (result.roi.coverage(cam_site.project(chosen.samples_site)) if result.roi is not None else None)
    strategy_row = dict(chosen.image.row()) if chosen.image is not None else dict(chosen.paper.row())
    strategy_row.update({"name": chosen.name, "kind": chosen.strategy, "text": chosen.text, "sampling": chosen.sampling,
                         "optimized": ev.optimize, "requested": req.strategy, "sampling_requested": req.sampling})
    if chosen.paper is not None:
        strategy_row.update({"recommended": result.candidates[0].strategy.name, "dropped": chosen.paper.screen.reasons,
                             "heights_m": list(chosen.heights_m)})
    total_time = sum(r.flight_time_s for r in result.routes)
    return {
        "format": "dronecal-field plan summary, version 2",
        "created_by": f"dronecal-field {__version__} plan",
        "name": req.name,
        "altitude_frame": req.alt_frame,
        "altitude_frame_text": result.missions[0].alt_frame_text,
        "heights_text": "h_m values are WGS84 ellipsoidal heights; alt_m values are the mission altitudes in altitude_frame",
        "enu_origin": {"lat_deg": req.site.lat_deg, "lon_deg": req.site.lon_deg, "h_m": req.site.ground_h_m,
                        "text": "ENU frame (east, north, up, m) at the pole's foot; h is ellipsoidal"},
        "site_frame": {"azimuth_deg": req.site.azimuth_deg, "R_enu_from_site": np.round(req.site.R_enu_from_site, 12).tolist(),
                        "text": "site frame: X along the camera azimuth (horizontal), Y left, Z up, origin at the pole's foot"},
        "geoid_separation_m": req.site.geoid_separation_m,
        "home": {"lat_deg": result.missions[0].home_lat_deg, "lon_deg": result.missions[0].home_lon_deg, "h_m": round(home_h, 3),
                 "alt_written_m": round(result.missions[0].home_alt_m, 3), "alt_written_is_amsl": result.missions[0].home_alt_is_amsl,
                 "text": "home = take-off and landing point, away from the pole; the vehicle replaces it with where it arms"},
        "camera_guess": {
            "file": "camera_guess.yaml", "width": lens.width, "height": lens.height, "focal_px": round(lens.focal_px, 2),
            "focal_source": lens.focal_source, "cx": lens.width / 2.0, "cy": lens.height / 2.0,
            "hfov_deg": round(lens.hfov_deg, 2), "vfov_deg": round(lens.vfov_deg, 2),
            "distortion_level": lens.distortion_level, "distortion_k1_k2_p1_p2_k3": d.as_array().tolist(),
            "mount_height_m": req.site.mount_height_m, "azimuth_deg": req.site.azimuth_deg, "tilt_deg": req.site.tilt_deg,
            "roll_deg": req.site.roll_deg, "position_enu_m": cam_enu.pose.position_world.tolist(),
            "rotation_world_to_camera": np.round(cam_enu.pose.R_cam_from_world, 12).tolist(), "fps": lens.fps,
            "exposure_s": req.timing.exposure_s,
        },
        "marker": {"size_m": chosen.marker_size_m, "sizes_offered_m": list(req.marker_sizes_m), "dictionary": req.marker.dictionary,
                   "id": req.marker.marker_id, "offset_frd_m": list(req.marker.offset_frd_m), "min_px": req.marker.min_px,
                   "needed_m": None if design is None or design.needed_marker_m is None else round(design.needed_marker_m, 3),
                   "mounting": "upright on the drone's nose, facing forward: the nose (and marker) faces the camera at every point",
                   "px_min": round(float(keep_px.min()), 1), "px_max": round(float(keep_px.max()), 1)},
        "limits": {"min_agl_m": req.limits.min_agl_m, "max_agl_m": req.limits.max_agl_m, "max_range_m": req.limits.max_range_m,
                   "keep_out_m": req.limits.keep_out_m, "geofence": None if req.geofence_latlon is None else [list(p) for p in req.geofence_latlon]},
        "roi": None if result.roi is None else result.roi.to_dict(),
        "coverage": {
            "pct": None if coverage is None else round(100.0 * coverage, 1),
            "text": "share of the ROI's image cells (a 16-column grid) within one cell of a sample pixel (holds and fixes along legs)",
            "unreachable": [] if design is None else list(design.unreachable),
        },
        "guess_band": band_report(cam_site, req.band, pts, replace(req.limits, marker_size_m=chosen.marker_size_m)),
        "strategy": strategy_row,
        "points": len(pts),
        "samples": {"holds": int(np.sum(chosen.hold_s > 0)), "pass_through_points": int(np.sum(chosen.hold_s <= 0)),
                    "leg_samples": int(len(chosen.samples_site) - len(pts)) if chosen.image is not None else 0,
                    "leg_speed_m_s": None if chosen.leg_speed_m_s is None else round(chosen.leg_speed_m_s, 3),
                    "gnss_hz": req.timing.gnss_hz, "exposure_s": req.timing.exposure_s},
        "grid": grid,
        "flight": {
            "flight_time_s": round(total_time, 1), "path_length_m": round(sum(r.path_length_m for r in result.routes), 1),
            "battery_pct": round(battery_pct, 1), "endurance_min": req.endurance_s / 60.0, "reserve_pct": round(100 * req.reserve),
            "flights": flights, "n_flights": len(flights),
            "hover_s": req.flight.hover_s, "speed_m_s": req.flight.speed_m_s, "end": req.end, "yaw_mode": req.yaw_mode,
            "takeoff": {"lat_deg": float(takeoff_geo[0]), "lon_deg": float(takeoff_geo[1]), "h_m": round(float(takeoff_geo[2]), 3),
                        "site_m": [round(float(v), 3) for v in result.routes[0].takeoff_site], "alt_m": result.routes[0].takeoff_alt_m},
            "mission_items": sum(f["mission_items"] for f in flights),
            "max_alt_m": round(max_alt, 2),
        },
        "prediction": pred,
        "uncertainty": {
            "trials": ev.trials, "seed": ev.seed, "sigma_px": ev.sigma_px, "sigma_3d_m": [ev.sigma_h_m, ev.sigma_h_m, ev.sigma_v_m],
            "timing_sigma_s": 0.01, "model": None if pred is None else pred["model"],
            "rms_mean_px": None if not monte_carlo else monte_carlo.get("rms_mean"),
            "rms_p95_px": None if not monte_carlo else (monte_carlo.get("rms_percentiles") or {}).get("95"),
            "ground_error_15m_cm": None if not monte_carlo else monte_carlo.get("ground_error_15m_cm"),
            "ground_error_15m_cm_p95": None if not monte_carlo else monte_carlo.get("ground_error_15m_cm_p95"),
            "monte_carlo": monte_carlo,
        },
        "comparison": comparison,
        "candidates": rows,
        "fence": {"inclusion_polygon_latlon": fence_geo[:, :2].tolist(), "margin_m": FENCE_MARGIN_M,
                  "exclusion_circle": {"lat_deg": req.site.lat_deg, "lon_deg": req.site.lon_deg, "radius_m": req.limits.keep_out_m}},
        "ardupilot_advice": {
            "RTL_ALT_cm": int(max(200, math.ceil(req.site.mount_height_m + 2.0) * 100)),
            "FENCE_ENABLE": 1, "FENCE_TYPE": 7, "FENCE_ALT_MAX_m": math.ceil(max_alt + 5.0),
            "text": "set RTL_ALT to clear the pole top (mount height + 2 m) but not the default 15 m climb; "
                    "the fence polygon and keep-out circle are in mission.plan (QGC uploads them)",
        },
        "warnings": list(result.warnings),
        "files": {
            **{f"{n}.plan": "QGroundControl plan (upload with QGC or dronecal-field fly)" for n in names},
            **{f"{n}.waypoints": "Mission Planner QGC WPL 110, home as item 0" for n in names},
            "mission.geojson": "map features; coordinates [lon, lat, h ellipsoidal]",
            "preview.png": "top view, predicted image with the ROI, and the predicted error over the ROI",
            "plan.json": "this summary",
            "camera_guess.yaml": "the guessed camera (OpenCV FileStorage, world = ENU at the pole's foot)",
        },
    }


def mission_geojson(result: PlanResult) -> dict:
    """GeoJSON of the plan: camera, take-off, points, paths (one per flight), fence, keep-out, footprint."""
    req = result.request
    feats: list[dict] = []
    cam_geo = _site_to_geo(req, np.array([0.0, 0.0, req.site.mount_height_m]))[0]
    feats.append(msn.point_feature(cam_geo[1], cam_geo[0], cam_geo[2], {
        "kind": "camera", "azimuth_deg": req.site.azimuth_deg, "tilt_deg": req.site.tilt_deg, "mount_height_m": req.site.mount_height_m}))
    t_geo = _site_to_geo(req, result.route.takeoff_site)[0]
    feats.append(msn.point_feature(t_geo[1], t_geo[0], t_geo[2], {"kind": "takeoff", "text": "home: take-off and landing"}))
    for g in result.summary["grid"]:
        feats.append(msn.point_feature(g["lon_deg"], g["lat_deg"], g["h_m"], {
            "kind": "grid", "index": g["index"], "order": g["order"], "flight": g["flight"], "mission_seq": g["mission_seq"], "alt_m": g["alt_m"],
            "alt_frame": req.alt_frame, "hold_s": g["hold_s"], "pixel": g["pixel"], "marker_px": g["marker_px"]}))
    for k, route in enumerate(result.routes):
        path_site = np.vstack([route.takeoff_site[None], route.takeoff_site[None] + [0, 0, route.takeoff_alt_m], route.points])
        if req.end == "land":
            path_site = np.vstack([path_site, route.takeoff_site[None]])
        pg = _site_to_geo(req, path_site)
        feats.append(msn.line_feature(pg[:, [1, 0, 2]], {"kind": "path", "flight": k + 1, "length_m": round(route.path_length_m, 1)}))
    fg = _site_to_geo(req, np.column_stack([result.fence_site, np.zeros(len(result.fence_site))]))
    feats.append(msn.polygon_feature(fg[:, [1, 0]], {"kind": "geofence", "inclusion": True, "margin_m": FENCE_MARGIN_M}))
    ang = np.linspace(0, 2 * np.pi, 33)[:-1]
    ko = req.limits.keep_out_m * np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], 1)
    if req.limits.keep_out_m > 0:
        kg = _site_to_geo(req, ko)
        feats.append(msn.polygon_feature(kg[:, [1, 0]], {"kind": "keep_out", "radius_m": req.limits.keep_out_m}))
    fp = _site_to_geo(req, np.column_stack([result.footprint_site, np.zeros(len(result.footprint_site))]))
    feats.append(msn.polygon_feature(fp[:, [1, 0]], {"kind": "footprint", "text": f"ground seen by the guessed camera, cut at {FOOTPRINT_RANGE_M:g} m"}))
    if req.roi.kind == "polygon" and req.roi.polygon_site:
        poly = np.asarray(req.roi.polygon_site, float)
        rg = _site_to_geo(req, np.column_stack([poly, np.zeros(len(poly))]))
        feats.append(msn.polygon_feature(rg[:, [1, 0]], {"kind": "roi", "text": req.roi.describe()}))
    return msn.geojson(feats, "dronecal-field plan; coordinates are [lon, lat, h] with h the WGS84 ellipsoidal height in metres; "
                              f"properties.alt_m are mission altitudes: {result.mission.alt_frame_text}")


_PLAN_OUTPUT = re.compile(r"^mission(-\d+)?(-px4)?\.(plan|waypoints)$|^(mission\.geojson|plan\.json|camera_guess\.yaml|preview\.png)$")


def write_plan(result: PlanResult, out_dir: str | os.PathLike) -> list[Path]:
    """Write the plan folder atomically; returns the written paths.

    The files go to a temporary sibling folder that is renamed to ``out_dir``; an
    existing ``out_dir`` is replaced only if it is empty or a previous plan (holds plan.json).
    """
    from dronecal_field.camerafile import write_camera
    from dronecal_field.plan.preview import render_preview
    from dronecal_field.plan.px4 import px4_plan, px4_plan_name
    from dronecal_field.plan.schema import validate_plan

    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "plan.json").is_file())):
        raise InputError(f"--out {out} exists and is not a plan folder: choose a new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    req = result.request
    ko = (req.site.lat_deg, req.site.lon_deg, req.limits.keep_out_m) if req.limits.keep_out_m > 0 else None
    fence = np.asarray(result.summary["fence"]["inclusion_polygon_latlon"])
    plans = []
    for mission in result.missions:
        plan = msn.qgc_plan(mission, fence, ko, req.flight.speed_m_s)
        validate_plan(plan)
        plans.append(plan)
    names = result.mission_names()
    with staged_folder(out) as tmp:
        for name, plan, mission in zip(names, plans, result.missions):
            (tmp / f"{name}.plan").write_text(msn.dumps(plan), encoding="utf-8")
            (tmp / f"{px4_plan_name(name)}.plan").write_text(msn.dumps(px4_plan(plan)), encoding="utf-8")  # QGC + PX4 (plan/px4.py)
            (tmp / f"{name}.waypoints").write_text(msn.waypoints_text(mission), encoding="utf-8")
        (tmp / "mission.geojson").write_text(msn.dumps(mission_geojson(result)), encoding="utf-8")
        (tmp / "plan.json").write_text(msn.dumps(result.summary), encoding="utf-8")
        write_camera(tmp / "camera_guess.yaml", result.camera_enu,
                     comment=f"dronecal-field plan: GUESSED camera (not calibrated): {req.lens.focal_source}, distortion {req.lens.distortion_level}")
        render_preview(result, tmp / "preview.png")
        replace_folder(tmp, out, lambda name: bool(_PLAN_OUTPUT.match(name)))
    files = [f"{n}.{ext}" for n in names for ext in ("plan", "waypoints")] + [f"{px4_plan_name(n)}.plan" for n in names] + list(PLAN_FILES[2:])
    return [out / f for f in files]
