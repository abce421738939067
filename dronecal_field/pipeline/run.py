"""The offline stage: ``calibrate_run(path, options) -> CalibrationReport``.

Ties the steps together (hover windows -> detections -> time alignment ->
per-waypoint points -> calibration -> uncertainty -> outputs) and returns
everything it measured. No printing: the command prints a summary; every
number lands in report.json.

Memory is bounded: fixes and attitude (a few floats per sample) are held in
arrays, frames are streamed once through the hover windows and only the
detections are kept.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dronecal_field.errors import ContractError, DegenerateGeometryError, DronecalError, InputError
from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu
from dronecal_field.pipeline.align import TimeOffset, estimate_time_offset
from dronecal_field.pipeline.detect import Detection, centres_under_distortion
from dronecal_field.pipeline.hover import (
    HoverWindow,
    TrackThresholds,
    windows_from_intervals,
    windows_from_reached,
    windows_from_track,
)
from dronecal_field.pipeline.points import (
    FIX_TYPES,
    PointOptions,
    WaypointPoint,
    attitude_at,
    drop_outlying_scatter,
    lever_arm_enu,
    marker_track_at,
    window_point,
)
from dronecal_field.pipeline.sampling import SamplingOptions

HOVER_SOURCES = ("auto", "events", "reached", "track")
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
    max_offset_s: float = 1.0
    recentre: bool = True  # marker centres again under the first calibration's distortion
    points: PointOptions = field(default_factory=PointOptions)
    sampling: SamplingOptions = field(default_factory=SamplingOptions)
    track: TrackThresholds = field(default_factory=TrackThresholds)

    def __post_init__(self) -> None:
        if self.min_fix not in FIX_TYPES:
            raise InputError(f"--min-fix {self.min_fix!r} is not a fix type: use one of {', '.join(FIX_TYPES)}")
        if self.hover_source not in HOVER_SOURCES:
            raise InputError(f"--hover-source {self.hover_source!r}: use one of {', '.join(HOVER_SOURCES)}")
        if self.trials < 0 or self.trials == 1:
            raise InputError(f"--trials {self.trials}: use 0 to skip the Monte-Carlo, or at least 2 (the paper uses 500)")


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

    def to_dict(self) -> dict:
        return {
            "frames_read": self.frames_read,
            "frames_decoded": self.frames_decoded,
            "frames_corrupt_skipped": self.frames_corrupt,
            "frames_with_marker": self.frames_with_marker,
            "other_marker_ids_seen": list(self.other_ids),
            "transitions_decoded_densely": self.transitions_dense,
            "formats": list(self.formats),
        }


@dataclass(frozen=True, eq=False)
class Track:
    """The run's GNSS track in the report's ENU frame (arrays, for plots and the report)."""

    t_ns: np.ndarray  # (N,) int64
    antenna_enu_m: np.ndarray  # (N, 3)
    marker_enu_m: np.ndarray  # (N, 3)
    sigma_enu_m: np.ndarray  # (N, 3) receiver-reported std
    fix_types: list[str | None]


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
    fixes_repeated: int = 0  # fixes left out as bit-for-bit repeats of the previous one
    centres: str = "diagonals' crossing"  # how marker centres were taken (report.json "points")

    @property
    def camera(self):
        return self.result.camera

    @property
    def used_points(self) -> list[WaypointPoint]:
        return [p for p in self.points if p.used]


# --------------------------------------------------------------------------
# Reading the run


def _read_track(run) -> tuple[np.ndarray, np.ndarray, np.ndarray, list, np.ndarray, int]:
    """(t_ns, lat/lon/alt (N, 3), sigma_enu (N, 3), fix types, all-usable mask, repeated fixes) of every fix."""
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
    # Duplicated stamps would break interpolation. A fix repeated bit for bit
    # under a later stamp comes from a logger or stream faster than the
    # receiver (new fixes come at ArduPilot's GPS_RATE_MS): the repeat is
    # stale, so the first one is kept.
    keep = np.r_[True, np.diff(t_ns) > 0] if len(t_ns) else np.zeros(0, bool)
    repeated = np.r_[False, np.all(np.diff(lla_a, axis=0) == 0.0, axis=1)] if len(t_ns) else np.zeros(0, bool)
    usable = np.array([ty != "no_fix" for ty in types], bool) & keep & ~repeated
    return t_ns, lla_a, sig_a, types, usable, int(repeated.sum())


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


def _detect_frames(run, windows: list[HoverWindow], marker, width: int, height: int, sampling: SamplingOptions):
    """One pass over the frames in the windows: (detections, groups, FrameStats)."""
    from dronecal_field.pipeline.detect import decode_gray, detect_aruco, detect_led, make_aruco_detector, roi_around
    from dronecal_field.pipeline.sampling import FrameSelector

    selector = FrameSelector(windows, sampling)
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
    read = decoded = corrupt = found = 0
    others: set[int] = set()
    formats: set[str] = set()
    last: Detection | None = None
    background = None  # one frame showing the marker, for the report's figure
    size_warned = False
    for frame in run.iter_frames(selector.read_windows()):
        read += 1
        decode, group = selector.wants(frame.timestamp_ns)
        if not decode:
            continue
        decoded += 1
        formats.add(frame.format)
        image = decode_gray(frame.data)
        if image is None:
            corrupt += 1
            continue
        if image.shape[:2] != (height, width) and not size_warned:
            size_warned = True
        roi = None
        if last is not None and abs(frame.timestamp_ns - last.timestamp_ns) < 500_000_000:
            roi = roi_around(last, image.shape)
        while True:
            if marker.kind == "aruco":
                res = detect_aruco(image, detector, int(marker.marker_id), frame.timestamp_ns, roi)
            else:
                res = detect_led(image, frame.timestamp_ns, roi)
            if res.detection is not None or roi is None:
                break
            roi = None  # lost in the tracking box: search the whole frame
        others.update(res.other_ids)
        selector.record(group, res.detection is not None)
        if res.detection is not None:
            found += 1
            detections.append(res.detection)
            groups.append(int(group))
            last = res.detection
            background = image
    stats = FrameStats(
        frames_read=read,
        frames_decoded=decoded,
        frames_corrupt=corrupt,
        frames_with_marker=found,
        other_ids=tuple(sorted(others)),
        transitions_dense=len(selector.transitions_taken),
        formats=tuple(sorted(formats)),
    )
    return detections, groups, stats, size_warned, background


# --------------------------------------------------------------------------
# The stage


def calibrate_run(path: str | os.PathLike, options: CalibrateOptions = CalibrateOptions()) -> CalibrationReport:
    """Calibrate the camera seen in one run file; write the outputs when ``options.out_dir`` is set.

    When a cut-off run cannot be calibrated, the error says where it is cut:
    the missing part is the likely reason (e.g. a second height never flown).

    Parameters
    ----------
    path : a run file following shared/contracts/run-format.md (also cut off)
    options : see CalibrateOptions

    Returns
    -------
    CalibrationReport

    Raises
    ------
    ContractError : the file breaks the contract (names what is missing)
    InputError : no usable fix, no hover window, no marker found
    DegenerateGeometryError : too few good waypoints, coplanar points
    CalibrationError : the solver found no trustworthy camera
    """
    try:
        return _calibrate_run(Path(path), options)
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


def _calibrate_run(path: Path, options: CalibrateOptions) -> CalibrationReport:
    from dataclasses import replace

    from dronecal_field.core.calibrate import calibrate
    from dronecal_field.pipeline import maps
    from dronecal_field.runfile.reader import open_run

    point_options = replace(options.points, min_fix=options.min_fix)
    timings: dict[str, float] = {}
    warnings: list[str] = []
    tick = time.perf_counter()
    with open_run(path) as run:
        md = run.metadata
        run_warnings = list(run.warnings)
        if run.truncated:
            warnings.append(f"the run is cut off at byte {run.truncated_at}: using the complete part")
        holds, roi = _plan_info(run)
        fix_t, lla, fix_sigma, fix_types, usable, n_repeated = _read_track(run)
        if not usable.any():
            seen = sorted({str(t) for t in fix_types}) if fix_types else []
            raise InputError(
                f"{path.name}: no usable GNSS fix ({len(fix_types)} fixes"
                + (f", types {', '.join(seen)}" if seen else "")
                + "): fly with a working GNSS receiver and record /gnss/fix"
            )
        if n_repeated > 0.1 * len(lla):
            warnings.append(
                f"{n_repeated} of {len(lla)} GNSS fixes repeat the previous one exactly (left out): the receiver is slower than "
                "the telemetry stream; set ArduPilot's GPS_RATE_MS to 100 for 10 Hz fixes if the receiver supports it"
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
            att_track = (att_t[order], arr[order, 1:])
            rpy = attitude_at(fix_t, *att_track)
            marker = antenna + lever_arm_enu(offset_frd, rpy)
            attitude_source = f"vehicle attitude ({len(att)} samples)"
        else:
            att_track = (None, None)
            marker = antenna.copy()
            attitude_source = "none in the run"
        timings["read_track_s"] = time.perf_counter() - tick

        tick = time.perf_counter()
        windows, window_source, notes = _hover_windows(run, fix_t, antenna, options, holds)
        warnings += notes
        if not windows:
            raise InputError(
                f"{path.name}: no hover window found (no hover events, no MISSION_ITEM_REACHED, and the GNSS track "
                f"never stays within {options.track.max_spread_m * 100:.0f} cm for {options.track.min_duration_s:g} s): "
                "fly holds of a few seconds at each waypoint"
            )
        timings["hover_windows_s"] = time.perf_counter() - tick

        tick = time.perf_counter()
        detections, groups, frame_stats, size_mismatch, background = _detect_frames(run, windows, md.marker, md.width, md.height, options.sampling)
        timings["detection_s"] = time.perf_counter() - tick
    if size_mismatch:
        warnings.append(f"frames are not {md.width}x{md.height} as camera.width/height say")
    if frame_stats.frames_corrupt:
        warnings.append(f"{frame_stats.frames_corrupt} corrupt frames skipped")
    if not detections:
        raise InputError(_no_marker_message(path, md.marker, windows, frame_stats))

    det_t = np.array([d.timestamp_ns for d in detections], np.int64)
    det_uv = np.array([[d.u_px, d.v_px] for d in detections], float)
    det_size = np.array([d.size_px for d in detections], float)
    marker_size_m = md.marker.size_m if md.marker.kind == "aruco" else None
    tick = time.perf_counter()
    offset = estimate_time_offset(det_t, det_uv, fix_t, marker, groups=np.asarray(groups), max_offset_s=options.max_offset_s)
    if offset.method == "none":
        if md.camera_latency_s is not None:
            offset = TimeOffset(offset_s=float(md.camera_latency_s), std_s=None, method="declared", n_points=offset.n_points, n_moving=offset.n_moving)
            warnings.append("the time offset is not observable from the data (no marker motion seen): using camera.latency_s")
        else:
            warnings.append("the time offset is not observable from the data (no marker motion seen) and camera.latency_s is unknown: assuming 0")
    elif offset.std_s is None:
        warnings.append(f"the time offset {offset.offset_s:+.3f} s is at the edge of the search range or unbounded: check camera.latency_s")
    timings["time_alignment_s"] = time.perf_counter() - tick

    tick = time.perf_counter()

    def build_points(marker_enu: np.ndarray, attitude: tuple, centres_px: np.ndarray) -> list[WaypointPoint]:
        det_marker = None  # pairing at the fixes interpolates the image track instead
        if point_options.paired and point_options.pair_at == "detections":
            # The marker at each detection's capture time, to pair 3D with 2D through the hover drift.
            det_marker, bracketed = marker_track_at(
                det_t - offset.offset_ns, fix_t, antenna, offset_frd, *attitude, max_gap_s=point_options.pair_max_gap_s
            )
            det_marker[~bracketed] = np.nan
        pts = [
            window_point(
                w, w.stable(point_options.settle_s, point_options.tail_s), fix_t, marker_enu, fix_sigma, fix_types,
                det_t, centres_px, offset.offset_ns, point_options, det_size, marker_size_m, det_marker,
            )
            for w in windows
        ]
        return drop_outlying_scatter(pts, point_options)

    def solve(pts: list[WaypointPoint]):
        used = [p for p in pts if p.used]
        if len(used) < MIN_POINTS:
            raise DegenerateGeometryError(_too_few_message(pts, len(used)))
        X = np.array([p.marker_enu_m for p in used])
        uv = np.array([p.uv_px for p in used])
        if options.model == "auto":
            result, reason = maps.select_model(X, uv, md.width, md.height, options.loss, options.loss_scale_px)
        else:
            reason = "--model given"
            result = calibrate(X, uv, md.width, md.height, model=options.model, loss=options.loss, loss_scale_px=options.loss_scale_px)
        return result, reason

    attitude_used = att_track
    points = build_points(marker, attitude_used, det_uv)
    result, model_reason = solve(points)
    if not att and np.linalg.norm(offset_frd) > 0:
        # No attitude: assume level flight with the nose at the camera (the
        # mission's DO_SET_ROI), which the first calibration has located.
        centre = result.camera.pose.position_world
        yaw = np.arctan2(centre[0] - antenna[:, 0], centre[1] - antenna[:, 1])
        rpy = np.c_[np.zeros(len(yaw)), np.zeros(len(yaw)), yaw]
        marker = antenna + lever_arm_enu(offset_frd, rpy)
        attitude_used = (fix_t, rpy)
        points = build_points(marker, attitude_used, det_uv)
        result, model_reason = solve(points)
        attitude_source = "none in the run: assumed level with the nose towards the calibrated camera"
        warnings.append("no attitude in the run: the marker lever arm assumes level flight facing the camera")
    centres_method = "diagonals' crossing" if md.marker.kind == "aruco" else "blob centroid"
    corners = [d.corners_px for d in detections]
    if options.recentre and np.any(result.camera.distortion.as_array() != 0.0) and all(c is not None for c in corners):
        # Distortion bends the marker's diagonals: take the centres again under the calibrated distortion.
        i = result.camera.intrinsics
        centres = centres_under_distortion(np.array(corners), np.array([i.fx, i.fy, i.cx, i.cy]), result.camera.distortion.as_array())
        points = build_points(marker, attitude_used, centres)
        result, model_reason = solve(points)
        centres_method = "diagonals' crossing under the first calibration's distortion"
    camera = result.camera.with_(enu_origin=tuple(origin.as_list()))
    result = _with_camera(result, camera)
    timings["calibration_s"] = time.perf_counter() - tick

    used = [p for p in points if p.used]
    X = np.array([p.marker_enu_m for p in used])
    s3 = np.array([p.sigma_enu_m for p in used])
    s2 = np.array([p.sigma_px for p in used])
    tick = time.perf_counter()
    from dronecal_field.core.uncertainty import linearised, monte_carlo, parameter_covariance

    mc = monte_carlo(camera, X, trials=options.trials, sigma_3d=s3, sigma_2d=s2, seed=options.seed, model=result.model) if options.trials >= 2 else None
    lin = linearised(camera, X, sigma_3d=s3, sigma_2d=s2, model=result.model)
    cov = parameter_covariance(camera, X, s3, s2, result.model)
    umaps = maps.uncertainty_maps(camera, cov, seed=options.seed)
    H = maps.ground_homography(camera)
    timings["uncertainty_s"] = time.perf_counter() - tick

    report = CalibrationReport(
        run_path=path,
        truncated=bool(run.truncated),
        run_warnings=run_warnings,
        metadata=md,
        origin=origin,
        origin_source=origin_source,
        altitude_datum=md.altitude_datum,
        windows=windows,
        window_source=window_source,
        frames=frame_stats,
        detections=detections,
        detection_groups=groups,
        offset=offset,
        points=points,
        attitude_source=attitude_source,
        model_reason=model_reason,
        result=result,
        monte_carlo=mc,
        linearised=lin,
        covariance_measured=cov,
        maps=umaps,
        homography=H,
        track=Track(t_ns=fix_t, antenna_enu_m=antenna, marker_enu_m=marker, sigma_enu_m=fix_sigma, fix_types=fix_types),
        timings_s=timings,
        warnings=warnings,
        options=options,
        background=background,
        fixes_repeated=n_repeated,
        centres=centres_method,
    )
    if options.out_dir is not None:
        from dronecal_field.pipeline.report import write_outputs

        tick = time.perf_counter()
        outputs = write_outputs(report, Path(options.out_dir))
        report.outputs.update(outputs)
        timings["outputs_s"] = time.perf_counter() - tick
    return report


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


def _too_few_message(points: list[WaypointPoint], n_used: int) -> str:
    reasons: dict[str, int] = {}
    for p in points:
        if not p.used:
            key = p.dropped.split(" (")[0] if "worse than" not in p.dropped else p.dropped
            reasons[key] = reasons.get(key, 0) + 1
    top = "; ".join(f"{n}x {r}" for r, n in sorted(reasons.items(), key=lambda kv: -kv[1])[:3])
    return (
        f"too few good waypoints: {n_used} of {len(points)} hover windows are usable, {MIN_POINTS} needed"
        + (f" (dropped: {top})" if top else "")
        + ": fly more waypoints in view of the camera, or relax --min-fix"
    )
