"""Pure pieces of the recorder: MAVLink -> run records, the vehicle clock, the status line.

No threads, no files: everything here is a function of its arguments so it can
be tested on its own and reused on replays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink.missionfile import CMD_DO_CHANGE_SPEED, CMD_NAV_WAYPOINT, Mission
from dronecal_field.recording.feed import CameraStatus
from dronecal_field.runfile.records import Attitude, GnssFix, RunEvent


def fix_from_gps_raw(msg: Any, timestamp_ns: int, altitude_datum: str = "ellipsoid") -> GnssFix | None:
    """A GnssFix from GPS_RAW_INT, or ``None`` without a position (no fix, or no height in the run's datum).

    Covariance is diagonal ENU from the receiver's ``h_acc``/``v_acc`` (mm,
    one sigma); ``None`` when the receiver does not report them.
    """
    if msg.fix_type < 2 or (msg.lat == 0 and msg.lon == 0):
        return None
    if altitude_datum == "ellipsoid":
        if not msg.alt_ellipsoid:
            return None
        alt_m = msg.alt_ellipsoid / 1000.0
    else:
        alt_m = msg.alt / 1000.0
    h_acc = getattr(msg, "h_acc", 0) / 1000.0
    v_acc = getattr(msg, "v_acc", 0) / 1000.0
    cov = np.diag([h_acc**2, h_acc**2, v_acc**2]) if h_acc > 0 and v_acc > 0 else None
    return GnssFix(
        timestamp_ns=int(timestamp_ns),
        lat_deg=msg.lat * 1e-7,
        lon_deg=msg.lon * 1e-7,
        alt_m=alt_m,
        covariance_enu=cov,
        fix_type=ap.FIX_TYPE_NAMES.get(int(msg.fix_type)),
    )


def attitude_from_mavlink(msg: Any, timestamp_ns: int) -> Attitude:
    """An Attitude record from ATTITUDE (radians, FRD relative to NED)."""
    return Attitude(timestamp_ns=int(timestamp_ns), roll_rad=float(msg.roll), pitch_rad=float(msg.pitch), yaw_rad=float(msg.yaw))


class VehicleClock:
    """Vehicle seconds per host second, estimated from ``time_boot_ms`` against the host clock.

    A real autopilot runs at 1.0; a simulator with ``--speedup N`` at N. Hold
    times in the mission are vehicle seconds, so hover windows on the host
    clock are ``hold_s / rate`` long. Rates within 5 % of 1 are taken as 1.
    """

    def __init__(self) -> None:
        self._first: tuple[int, int] | None = None  # (host ns, boot ms)
        self._last: tuple[int, int] | None = None

    def update(self, host_ns: int, boot_ms: int) -> None:
        """Add one (host UTC ns at arrival, vehicle time_boot_ms) pair, in arrival order."""
        if self._last is not None and boot_ms < self._last[1] - 1000:
            self._first = None  # the vehicle rebooted
        if self._first is None:
            self._first = (host_ns, boot_ms)
        self._last = (host_ns, boot_ms)

    @property
    def rate(self) -> float:
        if self._first is None or self._last is None:
            return 1.0
        host_s = (self._last[0] - self._first[0]) / 1e9
        if host_s < 1.0:
            return 1.0  # arrival jitter dominates shorter spans
        rate = (self._last[1] - self._first[1]) / 1000.0 / host_s
        return 1.0 if abs(rate - 1.0) < 0.05 or rate <= 0 else rate


class ClockJumpMonitor:
    """Finds steps of this computer's clock against the vehicle's boot clock (an NTP step, a hand-set clock).

    Each vehicle message gives ``host - boot / rate``: its link delay plus the
    clocks' offset. The smallest value over a block of ``block`` messages is
    the offset (delays are never negative). A step of that floor by more than
    ``threshold_s`` between two steady pairs of blocks is a clock jump; a
    block delayed as a whole (a stalled link) is not, since the next one comes back.
    A vehicle reboot (its boot clock going back) starts afresh.
    """

    def __init__(self, block: int = 40, threshold_s: float = 0.5) -> None:
        self.block = block
        self.threshold_s = threshold_s
        self._floors: list[tuple[float, int, float]] = []  # (floor s, host ns at the block's start, rate used)
        self._min: float | None = None
        self._start_ns = 0
        self._n = 0
        self._last_boot_ms: int | None = None
        self._rate = 1.0

    def observe(self, host_ns: int, boot_ms: int, rate: float = 1.0) -> tuple[int, float] | None:
        """One vehicle message, in arrival order; returns (host ns where the jump happened, jump s) once per jump."""
        if self._last_boot_ms is not None and boot_ms < self._last_boot_ms - 1000:
            self._floors, self._min, self._n = [], None, 0  # the vehicle rebooted
        self._last_boot_ms = int(boot_ms)
        e = host_ns / 1e9 - boot_ms / 1000.0 / max(rate, 1e-6)
        if self._n == 0:
            self._start_ns = int(host_ns)
            self._rate = float(rate)
        elif abs(rate - self._rate) > 1e-3 * self._rate:
            self._floors, self._min, self._n = [], None, 0  # the vehicle-clock rate estimate moved: offsets restart
            return None
        self._min = e if self._min is None else min(self._min, e)
        self._n += 1
        if self._n < self.block:
            return None
        self._floors.append((self._min, self._start_ns, self._rate))
        self._min, self._n = None, 0
        del self._floors[:-4]
        if len(self._floors) < 4:
            return None
        # steady before, a step, steady after: a block held up by the link is neither steady nor a step
        (fa, _, ra), (fb, _, _), (fc, at_ns, _), (fd, _, rd) = self._floors
        if abs(rd - ra) > 1e-3 * ra:
            return None  # offsets under different rate estimates do not compare
        steady = self.threshold_s / 2
        if abs(fb - fa) < steady and abs(fd - fc) < steady and abs(fc - fb) > self.threshold_s:
            return at_ns, fc - fb
        return None


def hover_event(mission: Mission, seq: int, reached_ns: int, clock_rate: float) -> RunEvent | None:
    """The hover window that ends with MISSION_ITEM_REACHED ``seq`` (ArduCopter reports at the END of a hold)."""
    if not 0 <= seq < len(mission.items):
        return None
    item = mission.items[seq]
    if item.command != CMD_NAV_WAYPOINT or item.hold_s <= 0:
        return None
    duration_ns = int(round(item.hold_s / max(clock_rate, 1e-6) * 1e9))
    # hold_s is vehicle time; the window is host time: hold_s / vehicle_clock_rate (1 for a real vehicle)
    meta = {
        "seq": str(seq),
        "hold_s": repr(float(item.hold_s)),
        "vehicle_clock_rate": repr(float(clock_rate)),
        "lat": repr(item.x * 1e-7),
        "lon": repr(item.y * 1e-7),
        "alt": repr(float(item.z)),
        "alt_frame": str(item.frame),
    }
    return RunEvent(timestamp_ns=int(reached_ns) - duration_ns, duration_ns=duration_ns, type="hover", metadata=meta)


def remaining_s(mission: Mission, current_seq: int, position: tuple[float, float, float] | None = None) -> float:
    """Rough vehicle seconds left: holds plus legs at the mission speed from ``current_seq`` on.

    Parameters
    ----------
    mission : Mission
        The mission.
    current_seq : int
        MISSION_CURRENT.seq.
    position : (lat_deg, lon_deg, rel_alt_m) or None
        Where the vehicle is, for the first leg.
    """
    speed = 5.0
    for item in mission.items[1 : max(1, current_seq) + 1]:
        if item.command == CMD_DO_CHANGE_SPEED and item.p2 > 0:
            speed = float(item.p2)
    total = 0.0
    prev = position
    for item in mission.items[max(1, current_seq) :]:
        if item.command == CMD_DO_CHANGE_SPEED and item.p2 > 0:
            speed = float(item.p2)
        if item.command != CMD_NAV_WAYPOINT:
            continue
        here = (item.x * 1e-7, item.y * 1e-7, float(item.z))
        if prev is not None:
            north = (here[0] - prev[0]) * 111_320.0
            east = (here[1] - prev[1]) * 111_320.0 * math.cos(math.radians(here[0]))
            total += math.sqrt(north**2 + east**2 + (here[2] - prev[2]) ** 2) / speed
        total += item.hold_s
        prev = here
    return total


@dataclass(frozen=True)
class RecorderStatus:
    """One status line's worth of the recording.

    Attributes
    ----------
    waypoint, waypoints : int
        Current NAV_WAYPOINT (1-based; 0 before the first) and how many there are.
    mode : str
        Vehicle mode (``AUTO``...), ``?`` unknown.
    armed : bool
        Motors armed.
    fix : str
        Fix type name.
    satellites : int
        Satellites used.
    fps : float
        Frames recorded per second over the last second.
    frames : int
        Frames written.
    dropped : int
        Frames dropped (slow disk + slow reader).
    marker_seen : bool or None
        ArUco marker found in the last checked frame (``None`` not checked yet).
    link_ok : bool
        Telemetry arriving.
    video_ok : bool
        Frames arriving.
    elapsed_s : float
        Wall seconds since the recording started.
    remaining_s : float or None
        Estimated wall seconds left in the mission.
    video_lag_s : float or None
        How far the recorder lags the stream's own clock (H.264/H.265), seconds.
    video_lagging : bool
        The lag is more than a frame (sustained over a second).
    video_lost : int
        Frames lost in the stream plus corrupt packets.
    recording_stopped : str or None
        Why the run file stopped taking data (a full disk); None while it records.
    cameras : tuple of CameraStatus
        Each named camera of a several-camera run (its own line); () for a single camera.
        The fields above then sum (fps, frames, dropped, video_lost) or join (video_ok: all) them.
    """

    waypoint: int
    waypoints: int
    mode: str
    armed: bool
    fix: str
    satellites: int
    fps: float
    frames: int
    dropped: int
    marker_seen: bool | None
    link_ok: bool
    video_ok: bool
    elapsed_s: float
    remaining_s: float | None
    video_lag_s: float | None = None
    video_lagging: bool = False
    video_lost: int = 0
    recording_stopped: str | None = None
    cameras: tuple[CameraStatus, ...] = ()


def _mmss(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    return f"{seconds // 60:02d}:{seconds % 60:02d}"


def status_alarm(s: RecorderStatus) -> bool:
    """True when the status line must be red: link or video lost, video behind, frames lost."""
    return not s.link_ok or not s.video_ok or s.video_lagging or s.video_lost > 0 or s.dropped > 0 or s.recording_stopped is not None


def _marker(seen: bool | None) -> str:
    return "?" if seen is None else ("yes" if seen else "no")


def format_status(s: RecorderStatus, color: bool = False) -> str:
    """``wp 3/12 AUTO armed | rtk_fixed 18 sats | 29.8 fps 0 dropped | marker yes | 01:02 / ~03:10 left``.

    With several cameras the video part is ``4 cameras (1 NO VIDEO: east)`` and each camera has its own
    line (:func:`format_camera_status`).
    """
    link = "" if s.link_ok else " | LINK LOST"
    left = "" if s.remaining_s is None else f" / ~{_mmss(s.remaining_s)} left"
    if s.cameras:
        lost = [c.name for c in s.cameras if not c.video_ok]
        video_part = f"{len(s.cameras)} cameras {s.dropped} dropped"
        video = f" | NO VIDEO from {len(lost)} of {len(s.cameras)}: {', '.join(map(str, lost))}" if lost else ""
    else:
        video_part = f"{s.fps:4.1f} fps {s.dropped} dropped | marker {_marker(s.marker_seen)}"
        video = "" if s.video_ok else " | NO VIDEO"
        if s.video_lagging:
            video += f" | VIDEO BEHIND {s.video_lag_s or 0.0:.2f} s"
        if s.video_lost:
            video += f" | {s.video_lost} VIDEO LOST"
    if s.recording_stopped is not None:
        video += f" | RECORDING STOPPED: {s.recording_stopped.split(':', 1)[0].upper()}"
    line = (
        f"wp {s.waypoint}/{s.waypoints} {s.mode} {'armed' if s.armed else 'disarmed'} | {s.fix} {s.satellites} sats | "
        f"{video_part} | {_mmss(s.elapsed_s)}{left}{link}{video}"
    )
    # ``color``: a terminal gets the line in red (ANSI) while anything is wrong.
    return f"\x1b[31m{line}\x1b[0m" if color and status_alarm(s) else line


def camera_alarm(c: CameraStatus) -> bool:
    """True when a camera's line must be red: no video, behind, frames lost or dropped."""
    return not c.video_ok or c.video_lagging or c.video_lost > 0 or c.dropped > 0


def format_camera_status(c: CameraStatus, color: bool = False, live: str = "") -> str:
    """``  cam north: 29.8 fps 1204 frames 0 dropped 0 gaps | marker yes`` (+ `` | live ...``), one camera of several."""
    line = f"  cam {c.name}: {c.fps:4.1f} fps {c.frames} frames {c.dropped} dropped {c.gaps} gaps | marker {_marker(c.marker_seen)}"
    if not c.video_ok:
        line += " | NO VIDEO"
    if c.video_lagging:
        line += f" | VIDEO BEHIND {c.video_lag_s or 0.0:.2f} s"
    if c.video_lost:
        line += f" | {c.video_lost} VIDEO LOST"
    if live:
        line += " | " + live
    return f"\x1b[31m{line}\x1b[0m" if color and camera_alarm(c) else line
