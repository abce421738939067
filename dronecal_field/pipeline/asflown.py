"""The flight as flown against its plan, and the noise as measured: what a calibration's first line must name (issue 20).

Pure functions on what the read stage found: the attached mission.plan's
speed and holds against the GNSS track's legs and hover windows, and the
measured per-fix noise. A refusal starts with the cause they name ("the legs
were flown at 1.5 m/s where the plan said 0.18 m/s: ..."), never only a
downstream symptom; a calibration that succeeds names them in its first
printed line (``CalibrationReport.notices``).
"""

from __future__ import annotations

import json

import numpy as np

from dronecal_field.pipeline.hover import HoverWindow
from dronecal_field.pipeline.legs import Leg, chord_speed
from dronecal_field.pipeline.points import FixNoise


def planned_speed(run) -> float | None:
    """The slowest DO_CHANGE_SPEED (m/s) of the attached mission.plan, None without one."""
    data = run.attachment("mission.plan")
    if not data:
        return None
    try:
        items = json.loads(data)["mission"]["items"]
        speeds = [float(it["params"][1]) for it in items if isinstance(it, dict) and it.get("command") == 178 and float(it["params"][1]) > 0]
    except (ValueError, KeyError, TypeError, IndexError):
        return None
    return min(speeds) if speeds else None


def vehicle_clock_rate(run) -> float:
    """Vehicle seconds per run second, from the recorder's events (``vehicle_clock_rate``): a sped-up simulator's
    rate, so that its 1 s holds and 0.5 m/s legs are not taken for 0.3 s and 1.5 m/s; 1 when no event says."""
    rates = []
    for event in run.iter_events():
        try:
            rate = float(event.metadata.get("vehicle_clock_rate", "nan"))
        except (TypeError, ValueError):
            continue
        if np.isfinite(rate) and 0.01 < rate < 1000:
            rates.append(rate)
    return float(np.median(rates)) if rates else 1.0


def flight_against_plan(read, windows: list[HoverWindow], legs: list[Leg]) -> list[str]:
    """How the flight differs from its plan where that costs points: legs flown faster, holds cut short.

    ``read``: run.TrackRead (the track, the mission.plan's holds by seq and its speed). Each item a phrase for a
    refusal or a warning, e.g. "the legs were flown at 1.5 m/s where the plan said 0.18 m/s".
    """
    out: list[str] = []
    track = read.track
    if legs and read.planned_speed_mps:
        flown = _leg_speed(track, legs, read.vehicle_clock_rate)
        if flown is not None and flown > 1.5 * read.planned_speed_mps:
            out.append(f"the legs were flown at {flown:.2g} m/s where the plan said {read.planned_speed_mps:.2g} m/s")
    if read.holds and windows:
        planned = np.array([read.holds[w.seq] for w in windows if w.seq in read.holds and read.holds[w.seq] > 0])
        flown = np.array([w.duration_s * read.vehicle_clock_rate for w in windows if w.seq in read.holds and read.holds[w.seq] > 0])
        if len(planned) and np.median(flown) < 0.6 * np.median(planned):
            out.append(f"the holds lasted {np.median(flown):.1f} s where the plan said {np.median(planned):.1f} s")
    missing = unflown_holds(read.holds, windows)
    if missing:
        out.append(missing)
    return out


UNFLOWN_SHARE = 0.1  # a plan this much of whose holds (and at least 2) the run lacks is named first


def unflown_holds(holds: dict[int, float] | None, windows: list[HoverWindow]) -> str | None:
    """"3 of the plan's 16 holds are missing from the run (seq 17-19)" when the run has no hold window (by the
    autopilot's reached events) for them: a flight cut short or started late samples less of the image than planned
    (the 4K suite's last quarter: 3 of 16 holds, its bottom row, and the ground error 3.7x). "Missing from the run",
    not "not flown": a loaded PX4 may fold a reached event. None when the windows carry no mission seq (found in the
    GNSS track) or the plan says no holds."""
    planned = sorted(seq for seq, hold_s in (holds or {}).items() if hold_s > 0)
    reached = {w.seq for w in windows if w.seq is not None}
    if not planned or not reached:
        return None
    missing = [seq for seq in planned if seq not in reached]
    if len(missing) < 2 or len(missing) < UNFLOWN_SHARE * len(planned):
        return None
    return f"{len(missing)} of the plan's {len(planned)} holds are missing from the run (seq {_ranges(missing)})"


def _ranges(seqs: list[int]) -> str:
    """'4-9, 12' for [4, 5, 6, 7, 8, 9, 12]."""
    out: list[str] = []
    start = prev = seqs[0]
    for s in [*seqs[1:], None]:
        if s is not None and s == prev + 1:
            prev = s
            continue
        out.append(f"{start}-{prev}" if prev > start else f"{start}")
        if s is not None:
            start = prev = s
    return ", ".join(out)


def _leg_speed(track, legs: list[Leg], clock_rate: float) -> float | None:
    """Median over the legs of each leg's chord speed (m/s on the vehicle's clock; legs.chord_speed says why)."""
    speeds = []
    for g in legs:
        on = (track.t_ns >= g.start_ns) & (track.t_ns <= g.end_ns)
        v = chord_speed(track.t_ns[on], track.marker_enu_m[on])
        if v is not None:
            speeds.append(v / clock_rate)
    return float(np.median(speeds)) if speeds else None


CORRELATED_TAU_S = 2.0  # RTK noise correlated over this long or more, and dominating the white part, is named first


def correlated_noise(noise: FixNoise | None) -> str | None:
    """A first-line notice when the measured fix noise is mostly correlated over seconds: the holds share their
    errors, so the camera is worse than their number suggests. Measured (contract writer, RTK noise correlated over
    10 s): white 0 mm, correlated 8-9 mm over 5 s, and the ground 3-30 m error 1.9-4.8x the white-noise run's;
    white-noise runs measure 10 mm white, at most 3 mm correlated over under 1 s."""
    if noise is None or noise.tau_s is None or noise.tau_s < CORRELATED_TAU_S or noise.sigma_corr_m < noise.sigma_white_m:
        return None
    return (f"RTK noise correlated over {noise.tau_s:.0f} s ({1000 * noise.sigma_corr_m:.0f} mm, white {1000 * noise.sigma_white_m:.0f} mm): "
            "the points share their errors and say less than their number; expect a larger error than a white-noise flight: "
            "hold longer, or fly again in better sky")
