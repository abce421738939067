"""Stages 1-2 of a run: the usable GNSS fixes in the run's ENU frame, the marker's track (lever arm through
the attitude), the hover windows and the fly-through legs, and what the attached plan says (holds, ROI).

Reads the run (``runfile.reader.Run``) but writes nothing; shared by every camera of the run.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from dronecal_field.errors import InputError
from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu
from dronecal_field.pipeline.asflown import planned_speed, vehicle_clock_rate
from dronecal_field.pipeline.fixes import DistinctFixes, distinct_fixes
from dronecal_field.pipeline.hover import HoverWindow, windows_from_intervals, windows_from_reached, windows_from_track
from dronecal_field.pipeline.legs import Leg, legs_from_intervals, legs_from_track, track_velocity
from dronecal_field.pipeline.points import attitude_at, lever_arm_enu
from dronecal_field.pipeline.results import CalibrateOptions, Track, TrackRead


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


def read_track(run, path: Path, options: CalibrateOptions) -> TrackRead:
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
        cam = getattr(run, "camera", None)
        if cam is not None and any("camera" in g for g in grid):
            # a site plan: a leg's speed and timing were chosen for the camera it was designed for, and the plan counts
            # its fixes for that camera only (plan.multiplan.cross_visibility); a-wide's legs took a-4k from 0.53 to 1.06 px
            grid = [g for g in grid if g.get("camera") == cam]
        points = np.array([[float(g["lat_deg"]), float(g["lon_deg"])] for g in grid]).reshape(-1, 2)
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


def hover_windows(run, fix_t, antenna, options: CalibrateOptions, holds) -> tuple[list[HoverWindow], str, list[str]]:
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


def find_legs(run, track: Track, windows: list[HoverWindow], options: CalibrateOptions) -> tuple[list[Leg], str]:
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
