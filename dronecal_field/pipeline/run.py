"""The offline stage: ``calibrate_run(path, options) -> CalibrationReport``.

The pipeline, one named stage each (see :func:`_calibrate_run`)::

    read track -> hover windows + legs -> detections -> time alignment
      -> points -> solve (-> timing refined through the camera -> points -> solve)
      -> uncertainty -> report

No printing: the command prints a summary; every number lands in report.json.

Memory is bounded: fixes and attitude (a few floats per sample) are held in
arrays, frames are streamed once through the hover windows and the legs and
only the detections are kept.
"""

from __future__ import annotations

import json
import math
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dronecal_field.errors import CalibrationError, ContractError, DegenerateGeometryError, DronecalError, InputError
from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu
from dronecal_field.pipeline.agreement import AGREES, merged
from dronecal_field.pipeline.asflown import correlated_noise, flight_against_plan, planned_speed, vehicle_clock_rate
from dronecal_field.pipeline.align import TimeOffset, Timing, estimate_time_offset, refine_timing
from dronecal_field.pipeline.detect import Detection, centres_under_distortion
from dronecal_field.pipeline.fixes import DistinctFixes, distinct_fixes
from dronecal_field.pipeline.hover import (
    HoverWindow,
    TrackThresholds,
    windows_from_intervals,
    windows_from_reached,
    windows_from_track,
)
from dronecal_field.pipeline.legs import Leg, LegOptions, leg_points, legs_from_intervals, legs_from_track, track_velocity
from dronecal_field.pipeline.points import (
    FIX_TYPES,
    FixNoise,
    PointOptions,
    WaypointPoint,
    attitude_at,
    drop_outlying_scatter,
    estimate_fix_noise,
    lever_arm_enu,
    marker_track_at,
    track_at,
    window_point,
)
from dronecal_field.pipeline.sampling import SamplingOptions

HOVER_SOURCES = ("auto", "events", "reached", "track")
LEG_SOURCES = ("auto", "events", "track", "none")
MIN_POINTS = 6


@dataclass(frozen=True)
class CalibrateOptions:
    """Everything ``dronecal-field calibrate`` can be told (see its --help)."""

    out_dir: Path | None = None
    min_fix: str = "rtk_fixed"
    model: str = "auto"
    loss: str = "huber"
    loss_scale_px: float = 2.0
    trials: int = 500
    seed: int = 0
    annotate: bool = False
    hover_source: str = "auto"
    leg_source: str = "auto"  # fly-through legs: "leg" events, else the GNSS track; "none": holds only
    max_offset_s: float = 1.0
    max_readout_s: float = 0.06  # rolling-shutter readouts searched (0: assume a global shutter)
    recentre: bool = True  # marker centres again under the first calibration's distortion
    points: PointOptions = field(default_factory=PointOptions)
    legs: LegOptions = field(default_factory=LegOptions)
    sampling: SamplingOptions = field(default_factory=SamplingOptions)
    track: TrackThresholds = field(default_factory=TrackThresholds)

    def __post_init__(self) -> None:
        if self.min_fix not in FIX_TYPES:
            raise InputError(f"--min-fix {self.min_fix!r} is not a fix type: use one of {', '.join(FIX_TYPES)}")
        if self.hover_source not in HOVER_SOURCES:
            raise InputError(f"--hover-source {self.hover_source!r}: use one of {', '.join(HOVER_SOURCES)}")
        if self.leg_source not in LEG_SOURCES:
            raise InputError(f"--leg-source {self.leg_source!r}: use one of {', '.join(LEG_SOURCES)}")
        if self.trials < 0 or self.trials == 1:
            raise InputError(f"--trials {self.trials}: use 0 to skip the Monte-Carlo, or at least 2 (the paper uses 500)")
        if not (math.isfinite(self.loss_scale_px) and self.loss_scale_px > 0):
            raise InputError(f"--loss-scale-px {self.loss_scale_px:g}: give the robust loss scale in pixels, e.g. 2")
        if not (math.isfinite(self.max_readout_s) and 0 <= self.max_readout_s <= 0.2):
            raise InputError(f"--max-readout-s {self.max_readout_s:g}: give a rolling-shutter readout of 0-0.2 s (0 for a global shutter)")
        if not (math.isfinite(self.points.settle_s) and self.points.settle_s >= 0):
            raise InputError(f"--settle-s {self.points.settle_s:g}: give the seconds left out at the start of each hold, 0 or more")
        if self.sampling.max_frames_per_window < 1:
            raise InputError(f"--max-frames-per-window {self.sampling.max_frames_per_window}: give at least 1 (24 is the default)")


@dataclass(frozen=True, eq=False)
class FrameStats:
    """What the detection pass saw."""

    frames_read: int
    frames_decoded: int
    frames_corrupt: int
    frames_with_marker: int
    other_ids: tuple[int, ...]
    transitions_dense: int
    formats: tuple[str, ...]
    video_units_decoded: int | None = None  # /camera/video: access units the decoder ran through (the real cost), None for images
    frames_from_live: int = 0  # of frames_decoded, those whose outcome came from fly's live pass (not decoded again)

    def to_dict(self) -> dict:
        return {
            "frames_read": self.frames_read,
            "frames_decoded": self.frames_decoded,
            "frames_corrupt_skipped": self.frames_corrupt,
            "frames_with_marker": self.frames_with_marker,
            "other_marker_ids_seen": list(self.other_ids),
            "transitions_decoded_densely": self.transitions_dense,
            "formats": list(self.formats),
            "video_units_decoded": self.video_units_decoded,
            "frames_from_live_pass": self.frames_from_live,
        }


@dataclass(frozen=True, eq=False)
class Track:
    """The run's GNSS track in the report's ENU frame (arrays, for plots and the report)."""

    t_ns: np.ndarray  # (N,) int64
    antenna_enu_m: np.ndarray  # (N, 3)
    marker_enu_m: np.ndarray  # (N, 3)
    sigma_enu_m: np.ndarray  # (N, 3) receiver-reported std
    fix_types: list[str | None]
    velocity_enu_mps: np.ndarray | None = None  # (N, 3) the marker's velocity at each fix


@dataclass(frozen=True, eq=False)
class CalibrationReport:
    """Everything the offline stage measured and decided (report.json is its ``to_dict``)."""

    run_path: Path
    truncated: bool
    run_warnings: list[str]
    metadata: object  # runfile.RunMetadata
    origin: EnuOrigin
    origin_source: str
    altitude_datum: str
    windows: list[HoverWindow]
    window_source: str
    frames: FrameStats
    detections: list[Detection]
    detection_groups: list[int]
    offset: TimeOffset
    points: list[WaypointPoint]
    attitude_source: str
    model_reason: str
    result: object  # core.calibrate.CalibrationResult
    monte_carlo: object | None  # core.uncertainty.UncertaintyResult
    linearised: object | None
    covariance_measured: np.ndarray
    maps: object  # maps.UncertaintyMaps
    homography: np.ndarray
    track: Track
    timings_s: dict[str, float]
    warnings: list[str]
    options: CalibrateOptions
    background: np.ndarray | None = field(default=None, repr=False)  # (H, W) a frame with the marker
    outputs: dict[str, str] = field(default_factory=dict)
    fixes_repeated: int = 0  # messages left out as repeats of the fix before (see ``fix_identity``)
    centres: str = "diagonals' crossing"  # how marker centres were taken (report.json "points")
    legs: list[Leg] = field(default_factory=list)
    leg_source: str = "none"
    timing: Timing | None = None  # offset and rolling shutter refined through the calibrated camera
    fix_identity: DistinctFixes | None = None  # how fixes were told apart (rule, counts)
    gnss_latency_s: float | None = None  # subtracted from arrival-stamped fixes (metadata gnss.latency_s)
    validity: object | None = None  # the region of validity (filled by the uncertainty stage when available)
    noise: FixNoise | None = None  # the per-fix noise measured on the residuals (sets the points' sigmas)
    sigma_scale: float = 1.0  # the points' sigmas were scaled by this for every uncertainty figure (see sigma_scale)
    agreement: object | None = None  # agreement.Agreement: whether the legs agreed with the holds, what was left out
    notices: list[str] = field(default_factory=list)  # what the first printed line must name: sets left out, a flight not as planned

    @property
    def hover_points(self) -> list[WaypointPoint]:
        return [p for p in self.points if p.window.source != "leg"]

    @property
    def leg_points(self) -> list[WaypointPoint]:
        return [p for p in self.points if p.window.source == "leg"]

    @property
    def camera(self):
        return self.result.camera

    @property
    def used_points(self) -> list[WaypointPoint]:
        return [p for p in self.points if p.used]


# --------------------------------------------------------------------------
# Reading the run




@dataclass(frozen=True, eq=False)
class TrackRead:
    """What the read-track stage returns: the usable fixes, the ENU frame, the marker's track."""

    track: Track
    identity: DistinctFixes
    gnss_latency_s: float | None
    origin: EnuOrigin
    origin_source: str
    attitude: tuple  # (att_t_ns (K,), att_rpy_rad (K, 3)) or (None, None)
    attitude_source: str
    offset_frd_m: np.ndarray  # (3,)
    holds: dict[int, float] | None
    warnings: list[str]
    plan_roi: object | None = None  # validity.PlanRoi of the plan.json attached to the run, in this ENU frame
    planned_speed_mps: float | None = None  # the mission.plan's DO_CHANGE_SPEED (the slowest, where it changes)
    vehicle_clock_rate: float = 1.0  # vehicle seconds per run second (a sped-up simulator's; 1 for a real vehicle)


@dataclass(frozen=True, eq=False)
class Detections:
    """What the detection stage returns (arrays over the M detections, camera clock)."""

    items: list[Detection]
    groups: list[int]
    t_ns: np.ndarray  # (M,) int64
    uv_px: np.ndarray  # (M, 2)
    size_px: np.ndarray  # (M,)
    stats: FrameStats
    size_mismatch: bool
    background: np.ndarray | None


@dataclass(frozen=True, eq=False)
class Solved:
    """What the points-and-solve stage returns."""

    points: list[WaypointPoint]
    result: object  # core.calibrate.CalibrationResult
    model_reason: str
    track: Track  # with the marker track finally used (lever arm)
    attitude_source: str
    centres: str
    timing: Timing
    warnings: list[str]
    noise: FixNoise | None = None
    legs: list[Leg] | None = None  # the legs paired (None: all found); a leg that disagreed with the holds is not
    agreement: object | None = None  # agreement.Agreement: the holds against each leg


@dataclass(frozen=True, eq=False)
class Uncertainty:
    """What the uncertainty stage returns."""

    monte_carlo: object | None
    linearised: object | None
    covariance: np.ndarray
    maps: object
    homography: np.ndarray
    validity: object | None = None
    sigma_scale: float = 1.0


def _read_fixes(run) -> tuple[np.ndarray, np.ndarray, np.ndarray, list, DistinctFixes, float | None]:
    """(t_ns (N,), lat/lon/alt (N, 3), sigma_enu (N, 3), fix types, DistinctFixes, latency applied) of every message of /gnss/fix, time-sorted."""
    t, lla, sig, types = [], [], [], []
    for fix in run.iter_fixes():
        if not (np.isfinite(fix.lat_deg) and np.isfinite(fix.lon_deg) and np.isfinite(fix.alt_m)):
            continue
        t.append(fix.timestamp_ns)
        lla.append((fix.lat_deg, fix.lon_deg, fix.alt_m))
        cov = fix.covariance_enu
        sig.append(np.sqrt(np.clip(np.diag(cov), 0, None)) if cov is not None else (np.nan, np.nan, np.nan))
        types.append(fix.fix_type)
    t_ns = np.asarray(t, np.int64)
    order = np.argsort(t_ns, kind="stable")
    lla_a = np.asarray(lla, float).reshape(-1, 3)[order]
    sig_a = np.asarray(sig, float).reshape(-1, 3)[order]
    types = [types[i] for i in order]
    t_ns = t_ns[order]
    stamping, latency = run.gnss_stamping
    # The raw messages only matter where a position repeats (reading them can mean a pass over every frame chunk).
    repeats = len(t_ns) > 1 and bool(np.any(np.all(np.diff(lla_a, axis=0) == 0.0, axis=1) & (np.diff(t_ns) > 0)))
    raw = _raw_fix_times(run, t_ns) if repeats else None
    identity = distinct_fixes(t_ns, lla_a, raw, arrival_stamped=stamping == "arrival")
    if stamping == "arrival" and latency is not None:
        t_ns = t_ns - int(round(latency * 1e9))  # the fix is older than its arrival
    return t_ns, lla_a, sig_a, types, identity, (latency if stamping == "arrival" else None)


def _raw_fix_times(run, t_ns: np.ndarray) -> np.ndarray | None:
    """(N,) GPS_RAW_INT.time_usec of the raw message each fix was stamped with, when the fixes carry
    those messages' arrival stamps (an arrival-stamping writer); None otherwise."""
    if "/mavlink/GPS_RAW_INT" not in run.topics or len(t_ns) == 0:
        return None
    raw: dict[int, int] = {}
    for _, t, fields in run.iter_mavlink({"GPS_RAW_INT"}):
        try:
            raw[int(t)] = int(fields.get("time_usec", 0))
        except (TypeError, ValueError):
            continue
    matched = np.array([raw.get(int(t), -1) for t in t_ns], np.int64)
    if np.mean(matched >= 0) < 0.9:
        return None  # fixes stamped at their own time (the contract): time tells them apart
    return np.where(matched >= 0, matched, 0)


def _read_track(run, path: Path, options: CalibrateOptions) -> TrackRead:
    """Stage 1: the usable fixes (one per fix time), the ENU frame, the marker's track and attitude."""
    md = run.metadata
    warnings: list[str] = []
    holds, roi = _plan_info(run)
    fix_t, lla, fix_sigma, fix_types, identity, latency = _read_fixes(run)
    usable = np.array([ty != "no_fix" for ty in fix_types], bool) & identity.keep
    if not usable.any():
        seen = sorted({str(t) for t in fix_types}) if fix_types else []
        raise InputError(
            f"{path.name}: no usable GNSS fix ({len(fix_types)} fixes"
            + (f", types {', '.join(seen)}" if seen else "")
            + "): fly with a working GNSS receiver and record /gnss/fix"
        )
    if identity.rule != "fix time" and identity.n_repeats > 0.1 * len(lla):
        warnings.append(
            f"{identity.n_repeats} of {len(lla)} GNSS messages repeat the fix before (left out, rule: {identity.rule}): the "
            "receiver is slower than the telemetry stream; set ArduPilot's GPS_RATE_MS to 100 for 10 Hz fixes if the receiver supports it"
        )
    fix_t, lla, fix_sigma = fix_t[usable], lla[usable], fix_sigma[usable]
    fix_types = [t for t, u in zip(fix_types, usable) if u]
    if md.site_origin is not None:
        origin, origin_source = md.site_origin, "dronecal.site metadata"
    elif roi is not None:
        origin, origin_source = EnuOrigin(lat_deg=roi[0], lon_deg=roi[1], h_m=float(lla[0, 2])), "camera (ROI) in mission.plan, height of the first fix"
    else:
        origin, origin_source = EnuOrigin(lat_deg=float(lla[0, 0]), lon_deg=float(lla[0, 1]), h_m=float(lla[0, 2])), "first GNSS fix"
    antenna = geodetic_to_enu(lla[:, 0], lla[:, 1], lla[:, 2], origin)
    att = [(a.timestamp_ns, a.roll_rad, a.pitch_rad, a.yaw_rad) for a in run.iter_attitude()]
    offset_frd = np.asarray(md.marker.offset_frd_m, float)
    if att:
        arr = np.asarray(att, float)
        att_t = arr[:, 0].astype(np.int64)
        order = np.argsort(att_t, kind="stable")
        attitude = (att_t[order], arr[order, 1:])
        marker = antenna + lever_arm_enu(offset_frd, attitude_at(fix_t, *attitude))
        attitude_source = f"vehicle attitude ({len(att)} samples)"
    else:
        attitude = (None, None)
        marker = antenna.copy()
        attitude_source = "none in the run"
    track = Track(
        t_ns=fix_t, antenna_enu_m=antenna, marker_enu_m=marker, sigma_enu_m=fix_sigma, fix_types=fix_types,
        velocity_enu_mps=track_velocity(fix_t, marker),
    )
    plan_roi = _plan_roi(run, origin, warnings)
    return TrackRead(
        track=track, identity=identity, gnss_latency_s=latency, origin=origin, origin_source=origin_source,
        attitude=attitude, attitude_source=attitude_source, offset_frd_m=offset_frd, holds=holds, warnings=warnings,
        plan_roi=plan_roi, planned_speed_mps=planned_speed(run), vehicle_clock_rate=vehicle_clock_rate(run),
    )


def _plan_roi(run, origin: EnuOrigin, warnings: list[str]):
    """The region of interest of the plan.json that ``fly`` attached to the run (None without one)."""
    from dronecal_field.pipeline.validity import roi_from_plan

    data = run.attachment("plan.json")
    if not data:
        return None
    try:
        return roi_from_plan(json.loads(data), origin)
    except (ValueError, TypeError, KeyError) as exc:
        warnings.append(f"the plan.json attached to the run has no usable region of interest ({exc}): checked against the visible ground only")
        return None
def _plan_info(run) -> tuple[dict[int, float] | None, tuple[float, float] | None]:
    """Hold seconds by mission seq and the camera (ROI) lat/lon from an attached QGC plan, if any."""
    data = run.attachment("mission.plan")
    if not data:
        return None, None
    try:
        plan = json.loads(data)
        items = plan["mission"]["items"]
    except (ValueError, KeyError, TypeError):
        return None, None
    holds: dict[int, float] = {}
    roi = None
    for k, item in enumerate(items, start=1):
        if not isinstance(item, dict):
            continue
        seq = int(item.get("doJumpId", k))
        params = item.get("params") or []
        cmd = item.get("command")
        if cmd == 16 and params:  # NAV_WAYPOINT: param1 is the hold time
            holds[seq] = float(params[0] or 0.0)
        elif cmd == 201 and len(params) >= 6 and roi is None:  # DO_SET_ROI at the camera
            lat, lon = params[4], params[5]
            if lat and lon:
                roi = (float(lat), float(lon))
    return holds or None, roi


def _damage_cost(span: tuple[int, int, int], points: list[WaypointPoint], fix_t_ns: np.ndarray) -> str:
    """What a skipped chunk cost: its span of the run and the hover windows and leg pairs it overlapped, used or not."""
    offset, a, b = span
    t0 = int(fix_t_ns[0]) if len(fix_t_ns) else a
    hit = [p for p in points if p.window.start_ns <= b and a <= p.window.end_ns]
    holds = [p for p in hit if p.window.source != "leg"]
    lost = [p for p in holds if not p.used]
    legs = [p for p in hit if p.window.source == "leg"]
    names = ", ".join(str(p.window.seq if p.window.seq is not None else p.window.index) for p in holds)
    if len(holds) == 1:
        what = f"hover window {names} ({'dropped' if lost else 'still used'})"
    else:
        what = f"hover windows {names} ({len(lost)} of them dropped)" if holds else "no hover window"
    return (f"the damaged chunk at byte {offset} held {(b - a) / 1e9:.1f} s of the run ({(a - t0) / 1e9:+.1f} to {(b - t0) / 1e9:+.1f} s "
            f"from the first fix): it overlapped {what}" + (f" and {len(legs)} leg pairs" if legs else "")
            + "; the frames and fixes in it are lost")


def _clock_jump_cost(event, points: list[WaypointPoint], fix_t_ns: np.ndarray) -> str:
    """What a clock jump the recorder saw may have cost: the holds and leg pairs within a few seconds of it."""
    t0 = int(fix_t_ns[0]) if len(fix_t_ns) else event.timestamp_ns
    near = [p for p in points if abs(p.window.start_ns - event.timestamp_ns) < 5e9 or p.window.start_ns <= event.timestamp_ns <= p.window.end_ns]
    holds = [p for p in near if p.window.source != "leg"]
    used = sum(p.used for p in near)
    return (f"the recorder's clock jumped {event.metadata.get('jump_s', '?')} s against the vehicle's at "
            f"{(event.timestamp_ns - t0) / 1e9:+.1f} s: frames and fixes across it may not line up; "
            f"{len(holds)} hover windows and {len(near) - len(holds)} leg pairs lie within 5 s of it ({used} of them used): "
            "keep the recording computer's clock from stepping during a flight (NTP slewing, not stepping)")


def _seq(event, key: str) -> int | None:
    try:
        return int(event.metadata.get(key, ""))
    except ValueError:
        return None


def _planned_sample_seqs(run) -> set[int] | None:
    """Mission seqs of the attached mission.plan that are sampling points of the attached plan.json (its ``grid``),
    matched by position (each flight of a split plan has its own seqs); None when the run carries no plan."""
    plan_json, mission = run.attachment("plan.json"), run.attachment("mission.plan")
    if not plan_json or not mission:
        return None
    try:
        grid = json.loads(plan_json)["grid"]
        points = np.array([[float(g["lat_deg"]), float(g["lon_deg"])] for g in grid])
        items = json.loads(mission)["mission"]["items"]
    except (ValueError, KeyError, TypeError):
        return None
    seqs = set()
    for k, item in enumerate(items, start=1):
        params = item.get("params") if isinstance(item, dict) else None
        if item.get("command") != 16 or not params or len(params) < 6 or params[4] is None or params[5] is None:
            continue
        if len(points) and np.min(np.abs(points - [float(params[4]), float(params[5])]).max(axis=1)) < 3e-7:  # ~3 cm
            seqs.add(int(item.get("doJumpId", k)))
    return seqs


def _hover_windows(run, fix_t, antenna, options: CalibrateOptions, holds) -> tuple[list[HoverWindow], str, list[str]]:
    notes: list[str] = []
    want = options.hover_source
    if want in ("auto", "events"):
        events = [e for e in run.iter_events() if e.type == "hover" and e.duration_ns > 0]
        if events:
            intervals = []
            for e in events:
                try:
                    seq = int(e.metadata.get("seq")) if e.metadata.get("seq") not in (None, "") else None
                except ValueError:
                    seq = None
                intervals.append((e.timestamp_ns, e.end_ns, seq))
            return windows_from_intervals(intervals, "event"), "event", notes
        if want == "events":
            raise InputError("--hover-source events: the run has no hover events on /events; use --hover-source auto")
    if want in ("auto", "reached"):
        reached = []
        for _, t_ns, fields in run.iter_mavlink({"MISSION_ITEM_REACHED"}):
            try:
                reached.append((int(t_ns), int(fields["seq"])))
            except (KeyError, TypeError, ValueError):
                continue
        if reached:
            windows = windows_from_reached(reached, fix_t, antenna, holds, options.track)
            if windows:
                return windows, "mission_item_reached", notes
            notes.append(f"{len(reached)} MISSION_ITEM_REACHED messages matched no still part of the GNSS track")
        if want == "reached":
            raise InputError("--hover-source reached: no MISSION_ITEM_REACHED marks a hold in this run; use --hover-source auto")
    return windows_from_track(fix_t, antenna, options.track), "gnss_track", notes



def _find_legs(run, track: Track, windows: list[HoverWindow], options: CalibrateOptions) -> tuple[list[Leg], str]:
    """Stage 2b: the fly-through legs, from ``leg`` events, else from the GNSS track (outside the hover windows)."""
    want = options.leg_source
    if want == "none":
        return [], "none"
    if want in ("auto", "events"):
        events = [e for e in run.iter_events() if e.type == "leg" and e.duration_ns > 0]
        designed = _planned_sample_seqs(run)
        if designed is not None:
            # only legs between two of the plan's sampling points: a detour round the pole or the way home passes
            # close under the camera, where its pairs pulled a calibration from 0.74 to 12.99 px over the ground
            events = [e for e in events if _seq(e, "seq_from") in designed and _seq(e, "seq_to") in designed]
        if events:
            return legs_from_intervals([(e.timestamp_ns, e.end_ns) for e in events], "event"), "event"
        if designed is not None and want == "auto":
            return [], "none"  # a hover plan: its legs are transits, and the track would find them again
        if want == "events":
            raise InputError("--leg-source events: the run has no leg events on /events; use --leg-source auto")
    legs = legs_from_track(track.t_ns, track.antenna_enu_m, options.legs)
    # A stretch overlapping a hold is the hold's drift or its approach, not a leg.
    legs = [g for g in legs if not any(w.start_ns < g.end_ns and g.start_ns < w.end_ns for w in windows)]
    legs = [replace(g, index=k) for k, g in enumerate(legs)]
    return legs, ("gnss_track" if legs else "none")


def _one_image(run, t_ns: int):
    """(H, W) grey image of the frame stamped ``t_ns`` (an access unit decoded from its keyframe), or None."""
    from dronecal_field.pipeline.detect import FrameDecoder, decode_gray

    if not run.video:
        return next((decode_gray(f.data) for f in run.iter_frames([(t_ns, t_ns)])), None)
    decoder = FrameDecoder()
    for frame in run.iter_frames([(t_ns, t_ns)]):
        decoder.push(frame)
    return decoder.gray()


def _detect_frames(run, windows: list[HoverWindow], legs: list[Leg], md, sampling: SamplingOptions, live=None) -> Detections:
    """Stage 3: one pass over the frames of the windows and the legs: the marker's detections.

    ``live`` (framecache.FrameResults, the live pass of ``fly``): inside its covered intervals its
    frames are the candidates and their stored outcomes are taken (no read, no decode); the rest
    is read from the file. The selector decides on the merged stream, in time order, as without.
    """
    import heapq

    from dronecal_field.pipeline.detect import TRACK_NS, FrameDecoder, decode_gray, detect_marker, make_aruco_detector, predicted, roi_around
    from dronecal_field.pipeline.sampling import FrameSelector

    marker = md.marker
    selector = FrameSelector(windows, sampling, legs=[(g.start_ns, g.end_ns) for g in legs], video=run.video)
    detector = None
    if marker.kind == "aruco":
        try:
            detector = make_aruco_detector(marker.dictionary)
        except ValueError:
            raise ContractError(
                f"marker.dictionary {marker.dictionary!r} is not an OpenCV ArUco dictionary: use a name like DICT_4X4_50"
            ) from None
    detections: list[Detection] = []
    groups: list[int] = []
    read = decoded = corrupt = found = from_live = 0
    others: set[int] = set()
    formats: set[str] = set()
    last: Detection | None = None
    before_last: Detection | None = None
    background = None  # one frame showing the marker, for the report's figure
    size_warned = False
    decoder = FrameDecoder()  # /camera/video: access units kept from the keyframe on, decoded only up to a wanted frame
    # /camera/video holds are decoded in keyframe bursts seconds apart: the last detection still boxes the search.
    track_ns = int(max(0.5, sampling.video_max_period_s) * 1e9) if run.video else TRACK_NS
    wanted = selector.read_windows()
    if live is not None:
        cached = (_CachedFrame(t, res) for t, res in live.items_in(wanted))
        frames = heapq.merge(cached, run.iter_frames(live.uncovered(wanted)), key=lambda f: f.timestamp_ns)
    else:
        frames = run.iter_frames(wanted)
    for frame in frames:
        read += 1
        stored = isinstance(frame, _CachedFrame)
        if not stored:
            decoder.push(frame)
        # Decisions use what was detected so far (a transition is decoded once its hold showed the marker).
        decode, group = selector.wants(frame.timestamp_ns, keyframe=bool(getattr(frame, "keyframe", False)))
        if not decode:
            continue
        decoded += 1
        if not stored and live is not None:
            stored, res = live.lookup(frame.timestamp_ns)  # a frame the live pass detected outside its covered spans
            frame = _CachedFrame(frame.timestamp_ns, res) if stored else frame
        if stored:
            from_live += 1
            formats.update(live.formats)
            res = frame.result
            if res is None:
                corrupt += 1
                continue
        else:
            formats.add(frame.format)
            image = decoder.gray()
            if image is None:
                corrupt += 1
                continue
            if image.shape[:2] != (md.height, md.width) and not size_warned:
                size_warned = True
            roi = None
            if last is not None and abs(frame.timestamp_ns - last.timestamp_ns) < TRACK_NS:
                roi = roi_around(predicted(last, before_last, frame.timestamp_ns), image.shape)
            elif last is not None and abs(frame.timestamp_ns - last.timestamp_ns) < track_ns:
                roi = roi_around(last, image.shape)  # keyframe bursts seconds apart: a still hold's marker is where it was
            res = detect_marker(image, marker, detector, frame.timestamp_ns, roi)
        others.update(res.other_ids)
        selector.record(group, res.detection is not None)
        if res.detection is not None:
            found += 1
            detections.append(res.detection)
            groups.append(int(group))
            before_last, last = last, res.detection
            if not stored:
                background = image
    if background is None and live is not None and detections:
        # every detection came from the live pass: the report's figure still needs one frame with the marker
        t = detections[-1].timestamp_ns
        background = _one_image(run, t)
    stats = FrameStats(
        frames_read=read,
        frames_decoded=decoded,
        frames_corrupt=corrupt,
        frames_with_marker=found,
        other_ids=tuple(sorted(others)),
        transitions_dense=len(selector.transitions_taken),
        formats=tuple(sorted(formats)),
        video_units_decoded=decoder.video_stats[0] if decoder.video_stats is not None else None,
        frames_from_live=from_live,
    )
    return Detections(
        items=detections,
        groups=groups,
        t_ns=np.array([d.timestamp_ns for d in detections], np.int64),
        uv_px=np.array([[d.u_px, d.v_px] for d in detections], float).reshape(-1, 2),
        size_px=np.array([d.size_px for d in detections], float),
        stats=stats,
        size_mismatch=size_warned,
        background=background,
    )


@dataclass(frozen=True)
class _CachedFrame:
    """A frame the live pass already ran the detector on (stamp and outcome; None: it did not decode)."""

    timestamp_ns: int
    result: object  # detect.FrameResult | None


def _align(dets: Detections, track: Track, md, options: CalibrateOptions) -> tuple[TimeOffset, list[str]]:
    """Stage 4: the camera-GNSS offset from the marker's motion (legs and transitions)."""
    warnings: list[str] = []
    offset = estimate_time_offset(
        dets.t_ns, dets.uv_px, track.t_ns, track.marker_enu_m, groups=np.asarray(dets.groups), max_offset_s=options.max_offset_s
    )
    if offset.method == "none":
        if md.camera_latency_s is not None:
            offset = TimeOffset(offset_s=float(md.camera_latency_s), std_s=None, method="declared", n_points=offset.n_points, n_moving=offset.n_moving)
            warnings.append("the time offset is not observable from the data (no marker motion seen): using camera.latency_s")
        else:
            warnings.append("the time offset is not observable from the data (no marker motion seen) and camera.latency_s is unknown: assuming 0")
    elif offset.std_s is None:
        warnings.append(f"the time offset {offset.offset_s:+.3f} s is at the edge of the search range or unbounded: check camera.latency_s")
    return offset, warnings


def _points(
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


def _solve(points: list[WaypointPoint], md, options: CalibrateOptions, previous=None):
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
    points = _points(track, attitude, inp.offset_frd_m, inp.windows, inp.legs, inp.dets, centres, timing, inp.marker_size_m, inp.options)
    return (points, *_solve(points, inp.md, inp.options, previous))


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
        points = _points(track, attitude, read.offset_frd_m, windows, legs, dets, centres, timing, inp.marker_size_m, options, noise)
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


def _solve_at_offset(read: TrackRead, windows, legs, dets: Detections, offset: TimeOffset, md,
                     options: CalibrateOptions) -> tuple[Solved, TimeOffset]:
    """Stages 5-6 at the estimated offset; when that leaves too few usable holds and the estimate was uncertain,
    at the candidates around it (and 0, and camera.latency_s) instead: the one whose calibration uses the most holds.

    The motion-based estimate fits a projective map, which a distorted lens bends: with few moving detections
    (a short or cut run) its minimum can sit 0.2 s off, where each hold's settled part loses its frames.
    """
    try:
        return _points_and_solve(read, windows, legs, dets, offset, md, options), offset
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


def _uncertainty(camera, points: list[WaypointPoint], result, options: CalibrateOptions, origin: EnuOrigin | None = None,
                 plan_roi=None) -> Uncertainty:
    """Stage 7: Monte-Carlo and linearised uncertainty, the region of validity, the maps and the ground homography."""
    from dronecal_field.core.uncertainty import linearised, monte_carlo, parameter_covariance
    from dronecal_field.pipeline import maps
    from dronecal_field.pipeline.validity import assess_validity

    used = [p for p in points if p.used]
    X = np.array([p.marker_enu_m for p in used])
    s3 = np.array([p.sigma_enu_m for p in used])
    s2 = np.array([p.sigma_px for p in used])
    lin = linearised(camera, X, sigma_3d=s3, sigma_2d=s2, model=result.model)
    scale = sigma_scale(result, lin.rms_mean)
    if scale > 1.0:
        s3, s2 = scale * s3, scale * s2
        lin = linearised(camera, X, sigma_3d=s3, sigma_2d=s2, model=result.model)
    mc = monte_carlo(camera, X, trials=options.trials, sigma_3d=s3, sigma_2d=s2, seed=options.seed, model=result.model) if options.trials >= 2 else None
    cov = parameter_covariance(camera, X, s3, s2, result.model)
    region = assess_validity(result, cov, s3, s2, origin=origin, roi=plan_roi, loss_scale_px=options.loss_scale_px)
    return Uncertainty(
        monte_carlo=mc, linearised=lin, covariance=cov,
        maps=maps.uncertainty_maps(camera, cov, seed=options.seed, richer=region.richer_camera, richer_covariance=region.richer_covariance),
        homography=maps.ground_homography(camera), validity=region, sigma_scale=scale,
    )


# --------------------------------------------------------------------------
# The stage


def calibrate_run(path: str | os.PathLike, options: CalibrateOptions = CalibrateOptions(), live=None) -> CalibrationReport:
    """Calibrate the camera seen in one run file; write the outputs when ``options.out_dir`` is set.

    When a cut-off run cannot be calibrated, the error says where it is cut:
    the missing part is the likely reason (e.g. a second height never flown).

    Parameters
    ----------
    path : a run file following shared/contracts/run-format.md (also cut off)
    options : see CalibrateOptions
    live : pipeline.framecache.FrameResults of ``fly``'s live pass over this run (same process), or None:
        its detector outcomes stand in for the frames it covered (not decoded again); JPEG/PNG runs only

    Returns
    -------
    CalibrationReport

    Raises
    ------
    ContractError : the file breaks the contract (names what is missing)
    InputError : no usable fix, no hover window or leg, no marker found
    DegenerateGeometryError : too few good waypoints, coplanar points
    CalibrationError : the solver found no trustworthy camera
    """
    try:
        return _calibrate_run(Path(path), options, live)
    except ContractError:
        raise
    except DronecalError as exc:
        cut = _cut_off_at(Path(path))
        if cut is None:
            raise
        raise type(exc)(f"{exc} (the run is cut off at byte {cut}: only its complete part could be used)") from None


def _cut_off_at(path: Path) -> int | None:
    """Byte offset where a run file is cut off, None when it is complete or unreadable."""
    from dronecal_field.runfile.reader import open_run

    try:
        with open_run(path) as run:
            return int(run.truncated_at) if run.truncated and run.truncated_at is not None else None
    except DronecalError:
        return None


@dataclass(frozen=True, eq=False)
class RunStages:
    """One run through the stages that need only the run itself (read track to time alignment):
    what the solve starts from. ``calibrate --joint`` (pipeline/joint.py) pools several of these."""

    path: Path
    md: object  # runfile.RunMetadata
    read: TrackRead
    windows: list[HoverWindow]
    window_source: str
    legs: list[Leg]
    leg_source: str
    dets: Detections
    offset: TimeOffset  # from the marker's motion, before the solve refines it
    truncated: bool
    run_warnings: list[str]
    warnings: list[str]
    damaged: list  # (byte offset, start_ns, end_ns) of skipped chunks
    jumps: list  # the recorder's clock_jump events


def _run_stages(path: Path, options: CalibrateOptions, live, clock: "_Clock") -> RunStages:
    """Stages 1-4 of one run: track, hover windows and legs, detections, time alignment."""
    from dronecal_field.runfile.reader import open_run

    with open_run(path) as run:
        md = run.metadata
        read = clock("read_track_s", _read_track, run, path, options)
        windows, window_source, notes = clock("hover_windows_s", _hover_windows, run, read.track.t_ns, read.track.antenna_enu_m, options, read.holds)
        legs, leg_source = clock("legs_s", _find_legs, run, read.track, windows, options)
        if not windows and not legs:
            raise InputError(
                f"{path.name}: no hover window and no leg found (no hover or leg events, no MISSION_ITEM_REACHED, and the GNSS "
                f"track never stays within {options.track.max_spread_m * 100:.0f} cm for {options.track.min_duration_s:g} s "
                "nor flies straight for long): fly holds of a few seconds at each waypoint, or legs at constant speed"
            )
        dets = clock("detection_s", _detect_frames, run, windows, legs, md, options.sampling, live)
        # Damage is found while reading (a skipped chunk, a cut): take the reader's word after the frames, not at open.
        truncated, run_warnings = bool(run.truncated), list(dict.fromkeys(run.warnings))  # each pass over a bad chunk says so again
        warnings = [f"the run is cut off at byte {run.truncated_at}: using the complete part"] if truncated else []
        damaged = sorted(getattr(run, "damaged_spans", ()))
        jumps = [e for e in run.iter_events() if e.type == "clock_jump"]
    warnings += [f"run file: {w}" for w in run_warnings] + read.warnings + notes
    if dets.size_mismatch:
        warnings.append(f"frames are not {md.width}x{md.height} as camera.width/height say")
    if dets.stats.frames_corrupt:
        warnings.append(f"{dets.stats.frames_corrupt} corrupt frames skipped")
    if not dets.items:
        raise InputError(_no_marker_message(path, md.marker, windows, dets.stats))
    offset, notes = clock("time_alignment_s", _align, dets, read.track, md, options)
    return RunStages(
        path=path, md=md, read=read, windows=windows, window_source=window_source, legs=legs, leg_source=leg_source, dets=dets,
        offset=offset, truncated=truncated, run_warnings=run_warnings, warnings=warnings + notes, damaged=damaged, jumps=jumps,
    )


def _calibrate_run(path: Path, options: CalibrateOptions, live=None) -> CalibrationReport:
    """The pipeline: each stage a function of the ones before."""
    clock = _Clock()
    st = _run_stages(path, options, live, clock)
    md, read, windows, legs, dets = st.md, st.read, st.windows, st.legs, st.dets
    window_source, leg_source, truncated, run_warnings = st.window_source, st.leg_source, st.truncated, st.run_warnings
    damaged, jumps, offset = st.damaged, st.jumps, st.offset
    warnings = list(st.warnings)
    causes = flight_against_plan(read, windows, legs)
    try:
        solved, offset = clock("calibration_s", _solve_at_offset, read, windows, legs, dets, offset, md, options)
    except (DegenerateGeometryError, CalibrationError) as exc:
        if not causes:
            raise
        raise type(exc)(f"{'; '.join(causes)}: {exc}") from None
    flown = [f"{c}: the calibration used what that flight gave" for c in causes]
    notices = ([solved.agreement.line] if solved.agreement is not None and solved.agreement.line else []) + flown
    correlated = correlated_noise(solved.noise)
    if correlated:
        notices.append(correlated)
    warnings = notices + warnings + solved.warnings
    warnings += [_damage_cost(span, solved.points, read.track.t_ns) for span in damaged]
    warnings += [_clock_jump_cost(e, solved.points, read.track.t_ns) for e in jumps]
    camera = solved.result.camera.with_(enu_origin=tuple(read.origin.as_list()))
    result = _with_camera(solved.result, camera)
    unc = clock("uncertainty_s", _uncertainty, camera, solved.points, result, options, read.origin, read.plan_roi)
    report = CalibrationReport(
        run_path=path, truncated=truncated, run_warnings=run_warnings, metadata=md,
        origin=read.origin, origin_source=read.origin_source, altitude_datum=md.altitude_datum,
        windows=windows, window_source=window_source, frames=dets.stats, detections=dets.items, detection_groups=dets.groups,
        offset=_offset_with_timing(offset, solved.timing, read, solved.noise), points=solved.points, attitude_source=solved.attitude_source,
        model_reason=solved.model_reason, result=result, monte_carlo=unc.monte_carlo, linearised=unc.linearised,
        covariance_measured=unc.covariance, maps=unc.maps, homography=unc.homography, track=solved.track,
        timings_s=clock.timings, warnings=warnings, options=options, background=dets.background,
        fixes_repeated=read.identity.n_repeats, centres=solved.centres, legs=legs, leg_source=leg_source,
        timing=solved.timing, fix_identity=read.identity, gnss_latency_s=read.gnss_latency_s, validity=unc.validity,
        noise=solved.noise, sigma_scale=unc.sigma_scale, agreement=solved.agreement, notices=notices,
    )
    if options.out_dir is not None:
        from dronecal_field.pipeline.report import write_outputs

        report.outputs.update(clock("outputs_s", write_outputs, report, Path(options.out_dir)))
    return report


class _Clock:
    """Runs a stage and keeps its wall time under a name (report.json ``timings_s``)."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}

    def __call__(self, name: str, stage, *args):
        tick = time.perf_counter()
        try:
            return stage(*args)
        finally:
            self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - tick


def _offset_with_timing(offset: TimeOffset, timing: Timing, read: TrackRead, noise: FixNoise | None) -> TimeOffset:
    """The offset as report.json's ``time_offset`` shows it: the refined first-row offset when legs
    refined it, with the rolling shutter and how GNSS fixes were timed and told apart."""
    out = offset
    if timing.rolling_shutter != "not estimated" or timing.offset_s != offset.offset_s:
        out = replace(offset, offset_s=timing.offset_s, std_s=timing.offset_std_s if timing.offset_std_s is not None else offset.std_s)
    gnss = read.identity.to_dict() | {"latency_s_subtracted": read.gnss_latency_s, "noise": None if noise is None else noise.to_dict()}
    return replace(out, rolling_shutter=timing.to_dict(), gnss_times=gnss)


def _with_camera(result, camera):
    from dataclasses import replace

    return replace(result, camera=camera)


def _no_marker_message(path: Path, marker, windows: list[HoverWindow], stats: FrameStats) -> str:
    if marker.kind == "aruco":
        what = f"ArUco id {marker.marker_id} of {marker.dictionary} ({marker.size_m} m)"
        hint = "check marker.dictionary, marker.id and marker.size_m, and that the marker faces the camera"
        if stats.other_ids:
            hint = f"ids {', '.join(map(str, stats.other_ids))} were seen: is marker.id right? Else " + hint
    else:
        what = "an LED blob"
        hint = "fly at dusk or night with the LED on, or use an ArUco marker"
    if stats.frames_read == 0:
        return (
            f"{path.name}: no marker found: no frames lie in the {len(windows)} hover windows; "
            "check the camera clock (the frames' timestamps) against the GNSS clock"
        )
    return (
        f"{path.name}: no marker found: looked for {what} in {stats.frames_decoded} frames "
        f"({stats.frames_corrupt} corrupt) of {len(windows)} hover windows; {hint}"
    )


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
