"""Stages 1-4 of one run for one camera (``run_stages``): what a solve starts from, whether the run is
calibrated alone, pooled with other flights (``pipeline.joint``) or beside other cameras (``pipeline.run``);
with the stage clock and the notes a run's damage and clock jumps leave in the report.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dronecal_field.errors import DronecalError, InputError
from dronecal_field.pipeline.align import TimeOffset, Timing
from dronecal_field.pipeline.frames import align_offset, detect_frames
from dronecal_field.pipeline.hover import HoverWindow
from dronecal_field.pipeline.legs import Leg
from dronecal_field.pipeline.points import FixNoise, WaypointPoint
from dronecal_field.pipeline.results import CalibrateOptions, Detections, FrameStats, TrackRead
from dronecal_field.pipeline.track import find_legs, hover_windows, read_track


def damage_cost(span: tuple[int, int, int], points: list[WaypointPoint], fix_t_ns: np.ndarray) -> str:
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


def clock_jump_cost(event, points: list[WaypointPoint], fix_t_ns: np.ndarray) -> str:
    """What a clock jump the recorder saw may have cost: the holds and leg pairs within a few seconds of it."""
    t0 = int(fix_t_ns[0]) if len(fix_t_ns) else event.timestamp_ns
    near = [p for p in points if abs(p.window.start_ns - event.timestamp_ns) < 5e9 or p.window.start_ns <= event.timestamp_ns <= p.window.end_ns]
    holds = [p for p in near if p.window.source != "leg"]
    used = sum(p.used for p in near)
    return (f"the recorder's clock jumped {event.metadata.get('jump_s', '?')} s against the vehicle's at "
            f"{(event.timestamp_ns - t0) / 1e9:+.1f} s: frames and fixes across it may not line up; "
            f"{len(holds)} hover windows and {len(near) - len(holds)} leg pairs lie within 5 s of it ({used} of them used): "
            "keep the recording computer's clock from stepping during a flight (NTP slewing, not stepping)")


def cut_off_at(path: Path) -> int | None:
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
    camera: str | None = None  # the camera of a several-camera run these stages are of; None: the run's one camera
    track_notes: list = field(default_factory=list)  # what finding the hover windows noted (shared by the run's cameras)


def run_stages(path: Path, options: CalibrateOptions, live, clock: "StageClock", camera: str | None = None,
               like: "RunStages | None" = None) -> RunStages:
    """Stages 1-4 of one run (of one of its cameras): track, hover windows and legs, detections, time alignment.

    ``like``: the stages of another camera of the same run, whose track and hover windows (the flight's, shared by
    every camera) are taken instead of being read again; the legs are each camera's own.
    """
    from dronecal_field.runfile.reader import open_run

    with open_run(path, camera) as run:
        md = run.metadata
        if like is not None:
            read, windows, window_source, notes = like.read, like.windows, like.window_source, like.track_notes
            # the legs per camera: a site plan's legs each serve their own camera (pipeline.track._planned_sample_seqs)
            legs, leg_source = clock("legs_s", find_legs, run, read.track, windows, options)
        else:
            read = clock("read_track_s", read_track, run, path, options)
            windows, window_source, notes = clock("hover_windows_s", hover_windows, run, read.track.t_ns, read.track.antenna_enu_m, options, read.holds)
            legs, leg_source = clock("legs_s", find_legs, run, read.track, windows, options)
        if not windows and not legs:
            raise InputError(
                f"{path.name}: no hover window and no leg found (no hover or leg events, no MISSION_ITEM_REACHED, and the GNSS "
                f"track never stays within {options.track.max_spread_m * 100:.0f} cm for {options.track.min_duration_s:g} s "
                "nor flies straight for long): fly holds of a few seconds at each waypoint, or legs at constant speed"
            )
        dets = clock("detection_s", detect_frames, run, windows, legs, md, options.sampling, live)
        # Damage is found while reading (a skipped chunk, a cut): take the reader's word after the frames, not at open.
        truncated, run_warnings = bool(run.truncated), list(dict.fromkeys(run.warnings))  # each pass over a bad chunk says so again
        warnings = [f"the run is cut off at byte {run.truncated_at}: using the complete part"] if truncated else []
        damaged = sorted(getattr(run, "damaged_spans", ()))
        jumps = [e for e in run.iter_events() if e.type == "clock_jump"]
    warnings += [f"run file: {w}" for w in run_warnings] + read.warnings + notes
    if dets.size_mismatch:
        key = "camera.width/height" if camera is None else f"camera.{camera}.width/height"
        warnings.append(f"frames are not {md.width}x{md.height} as {key} say")
    if dets.stats.frames_corrupt:
        warnings.append(f"{dets.stats.frames_corrupt} corrupt frames skipped")
    if not dets.items:
        raise InputError(_no_marker_message(path, md.marker, windows, dets.stats, camera))
    offset, align_notes = clock("time_alignment_s", align_offset, dets, read.track, md, options)
    return RunStages(
        path=path, md=md, read=read, windows=windows, window_source=window_source, legs=legs, leg_source=leg_source, dets=dets,
        offset=offset, truncated=truncated, run_warnings=run_warnings, warnings=warnings + align_notes, damaged=damaged, jumps=jumps,
        camera=camera, track_notes=notes,
    )


class StageClock:
    """Runs a stage and keeps its wall time under a name (report.json ``timings_s``)."""

    def __init__(self) -> None:
        self.timings: dict[str, float] = {}

    def __call__(self, name: str, stage, *args):
        tick = time.perf_counter()
        try:
            return stage(*args)
        finally:
            self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - tick


def offset_with_timing(offset: TimeOffset, timing: Timing, read: TrackRead, noise: FixNoise | None) -> TimeOffset:
    """The offset as report.json's ``time_offset`` shows it: the refined first-row offset when legs
    refined it, with the rolling shutter and how GNSS fixes were timed and told apart."""
    out = offset
    if timing.rolling_shutter != "not estimated" or timing.offset_s != offset.offset_s:
        out = replace(offset, offset_s=timing.offset_s, std_s=timing.offset_std_s if timing.offset_std_s is not None else offset.std_s)
    gnss = read.identity.to_dict() | {"latency_s_subtracted": read.gnss_latency_s, "noise": None if noise is None else noise.to_dict()}
    return replace(out, rolling_shutter=timing.to_dict(), gnss_times=gnss)


def with_camera(result, camera):
    """A CalibrationResult with its camera replaced (e.g. by the same camera carrying its ENU origin)."""
    return replace(result, camera=camera)


def _no_marker_message(path: Path, marker, windows: list[HoverWindow], stats: FrameStats, camera: str | None = None) -> str:
    name = path.name if camera is None else f"{path.name} camera {camera}"
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
            f"{name}: no marker found: no frames lie in the {len(windows)} hover windows; "
            "check the camera clock (the frames' timestamps) against the GNSS clock"
        )
    return (
        f"{name}: no marker found: looked for {what} in {stats.frames_decoded} frames "
        f"({stats.frames_corrupt} corrupt) of {len(windows)} hover windows; {hint}"
    )
