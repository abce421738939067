"""Pre-flight checks: is this vehicle, this GNSS fix and this video good enough to fly the mission?

Pure evaluation (:func:`evaluate_preflight` on a :class:`VehicleSnapshot`)
plus the I/O around it (:func:`snapshot_from_link`, :func:`run_preflight`,
which waits for a booting vehicle to become ready). Nothing here commands
the vehicle.

Checks, in order: ``heartbeat`` (an ArduPilot autopilot), ``disarmed``,
``gnss`` (fix at least ``min_fix``; RTK float or 3D pass with a loud warning
when allowed), ``gnss_rate`` (new fixes per second when measured: under 8
warns, each hold's point averages its fixes), ``ekf`` (EKF3 healthy, as
0x033f in the recording), ``battery``, ``ready_to_arm`` (SYS_STATUS pre-arm
bit), ``home`` (within ``max_home_distance_m`` of the mission's first
position), ``mission`` (every item it will upload: see :func:`check_mission_items`)
and ``video`` (opened and producing frames).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from typing import Any

from dronecal_field.errors import InputError, PreflightError
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import px4
from dronecal_field.mavlink.link import MavLink
from dronecal_field.mavlink.missionfile import GLOBAL_FRAMES, STORED_IN_LOCATION, Mission

# ArduPilot reports no mission capacity over MAVLink (it answers a too long upload with
# MISSION_ACK NO_SPACE, after the upload began). ArduCopter SITL holds about 700 items on
# its storage; boards with less storage hold fewer. The count is checked against this.
DEFAULT_MAX_MISSION_ITEMS = 700
# Sanity bounds on a waypoint's height above home (metres): nothing this tool plans flies
# near them; a mission beyond them is a typo or a unit error. The vehicle's own fence
# (FENCE_ALT_MAX) still applies in flight.
MIN_ALT_ABOVE_HOME_M = -10.0
MAX_ALT_ABOVE_HOME_M = 500.0
# The frames ArduPilot accepts in a mission (global, relative, terrain, and MISSION for DO items).
MISSION_FRAMES = frozenset({0, 2, 3, 5, 6, 10, 11})
# The MAV_CMDs ArduCopter runs from a mission (AP_Mission, Copter mode AUTO), ArduPilot 4.x.
ARDUCOPTER_MISSION_COMMANDS = frozenset({
    16, 17, 18, 19, 20, 21, 22, 31, 82, 83, 84, 85, 92, 93, 94,  # NAV
    112, 113, 114, 115,  # CONDITION
    177, 178, 179, 181, 182, 183, 184, 189, 195, 197, 200, 201, 202, 203, 205, 206, 207, 208, 211, 212, 214, 215,
    216, 217, 218, 222, 223, 1000, 2000, 2001, 2500, 2501, 42006, 42600,  # DO
})
MIN_FIX_CHOICES = ("rtk_fixed", "rtk_float", "3d")
MIN_GNSS_RATE_HZ = 8.0  # fly asks for 10 Hz; a 5 Hz receiver (ArduPilot's default GPS_RATE_MS) warns


@dataclass(frozen=True)
class CheckResult:
    """One line of the pre-flight checklist.

    Attributes
    ----------
    name : str
        Check name (``gnss``, ``ekf``, ...).
    ok : bool
        Passed.
    detail : str
        What was seen, and for a failure what to do.
    warning : bool
        Passed, but the operator must know (e.g. only RTK float).
    """

    name: str
    ok: bool
    detail: str
    warning: bool = False


@dataclass(frozen=True)
class VehicleSnapshot:
    """What the vehicle last reported (``None`` = not received).

    Attributes
    ----------
    autopilot, vehicle_type : int or None
        HEARTBEAT.autopilot / type.
    armed : bool or None
        HEARTBEAT armed flag.
    mode_name : str or None
        ArduCopter mode.
    fix_type : int or None
        GPS_RAW_INT.fix_type (6 = RTK fixed).
    satellites : int or None
        Satellites used.
    h_acc_m : float or None
        Reported horizontal accuracy, metres.
    ekf_flags : int or None
        EKF_STATUS_REPORT.flags.
    ekf_max_variance : float or None
        Largest of the velocity/position/compass variances.
    battery_pct : int or None
        Remaining charge, percent (``None`` or -1 unknown).
    voltage_v : float or None
        Battery voltage.
    ready_to_arm : bool or None
        SYS_STATUS pre-arm bit healthy.
    home_lat_deg, home_lon_deg : float or None
        HOME_POSITION.
    last_text : str or None
        Latest STATUSTEXT (often the PreArm reason).
    gnss_rate_hz : float or None
        New GNSS fixes per vehicle second (:class:`GnssRateMeter`), None if not measured.
    """

    autopilot: int | None = None
    vehicle_type: int | None = None
    armed: bool | None = None
    mode_name: str | None = None
    fix_type: int | None = None
    satellites: int | None = None
    h_acc_m: float | None = None
    ekf_flags: int | None = None
    ekf_max_variance: float | None = None
    battery_pct: int | None = None
    voltage_v: float | None = None
    ready_to_arm: bool | None = None
    home_lat_deg: float | None = None
    home_lon_deg: float | None = None
    last_text: str | None = None
    gnss_rate_hz: float | None = None


class GnssRateMeter:
    """New fixes per second in a GPS_RAW_INT stream, over the vehicle's own clock.

    A message is a new fix when its ``time_usec`` (the fix's own time)
    differs from the previous one's: a stream asked for faster than the
    receiver makes fixes repeats the last fix, time and all (ArduPilot 4.7,
    recorded in fly-calib-t1.tlog; GPS_RATE_MS sets the receiver's rate).
    Not its position: in a still hover a third of the new fixes repeat the
    position before them exactly (1e-7 deg quantisation). Seconds are the
    fixes' times, so a simulator running faster than real time reads the same.
    """

    def __init__(self, window_s: float = 2.0) -> None:
        self.window_s = window_s
        self._samples: list[tuple[float, bool]] = []  # (fix time s, new)
        self._last_key: tuple | None = None
        self._lock = threading.Lock()

    def feed(self, msg: Any) -> None:
        """One GPS_RAW_INT message (other types are ignored)."""
        if msg.get_type() != "GPS_RAW_INT" or not msg.time_usec or msg.fix_type < 2:
            return
        key = int(msg.time_usec)
        with self._lock:
            self._samples.append((msg.time_usec * 1e-6, key != self._last_key))
            self._last_key = key
            t_end = self._samples[-1][0]
            while self._samples and self._samples[0][0] < t_end - self.window_s:
                self._samples.pop(0)

    def rate_hz(self, min_span_s: float = 1.0) -> float | None:
        """New fixes per second over the last ``window_s``, or None with under ``min_span_s`` of stream."""
        with self._lock:
            if len(self._samples) < 2:
                return None
            span = self._samples[-1][0] - self._samples[0][0]
            if span < min_span_s:
                return None
            return sum(new for _t, new in self._samples[1:]) / span


@dataclass(frozen=True)
class VideoStatus:
    """The video source as probed before flight.

    Attributes
    ----------
    url : str
        The source.
    frames : int
        Frames received during the probe.
    fps : float
        Frames per second during the probe.
    width, height : int or None
        Image size of the first frame, pixels.
    error : str or None
        Why it could not be opened.
    warning : str or None
        What is wrong with a stream that works (keyframes that do not decode).
    """

    url: str
    frames: int = 0
    fps: float = 0.0
    width: int | None = None
    height: int | None = None
    error: str | None = None
    warning: str | None = None


def _distance_m(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Great-circle distance on a 6371 km sphere (plenty for a 500 m sanity check)."""
    p1, p2 = math.radians(lat1), math.radians(lat2)
    dp, dl = p2 - p1, math.radians(lon2 - lon1)
    a = math.sin(dp / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(dl / 2) ** 2
    return 2 * 6371008.8 * math.asin(math.sqrt(min(1.0, a)))


def first_position(mission: Mission) -> tuple[float, float] | None:
    """(lat, lon) of the first item after home with a position, else ``None``."""
    for item in mission.items[1:]:
        if item.frame in GLOBAL_FRAMES and (item.x != 0 or item.y != 0):
            return item.x * 1e-7, item.y * 1e-7
    return None


def check_mission_items(mission: Mission, *, max_items: int = DEFAULT_MAX_MISSION_ITEMS) -> list[str]:
    """Problems with the items ``fly`` would upload (empty: all good). Pure.

    Every item: an integer command ArduCopter runs from a mission, a frame it
    accepts, finite params; for items stored with a location, latitude and
    longitude in range and not (0, 0) where the command flies there, a finite
    altitude within [MIN_ALT_ABOVE_HOME_M, MAX_ALT_ABOVE_HOME_M] of home.
    And no more items than the vehicle holds (``max_items``, with home).
    """
    problems: list[str] = []
    if len(mission.items) > max_items:
        problems.append(f"{len(mission.items)} items, more than the vehicle holds ({max_items} on ArduCopter SITL's storage): split the mission (plan --max-flight-time)")
    for item in mission.items:
        where = f"item {item.seq}"
        if isinstance(item.command, bool) or not isinstance(item.command, int) or item.command not in ARDUCOPTER_MISSION_COMMANDS:
            problems.append(f"{where}: command {item.command!r} is not one ArduCopter runs in a mission")
            continue
        if item.frame not in MISSION_FRAMES:
            problems.append(f"{where}: frame {item.frame!r} is not one ArduPilot accepts in a mission (0, 2, 3, 5, 6, 10, 11)")
            continue
        if not all(math.isfinite(v) or math.isnan(v) for v in (item.p1, item.p2, item.p3, item.p4)) or not math.isfinite(item.z):
            problems.append(f"{where}: a parameter is infinite or the altitude is not a finite number")
            continue
        if item.command not in STORED_IN_LOCATION or item.frame not in GLOBAL_FRAMES:
            continue
        lat, lon = item.x * 1e-7, item.y * 1e-7
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            problems.append(f"{where}: latitude {lat:g}, longitude {lon:g} out of range")
            continue
        if item.seq > 0 and item.command in (16, 17, 18, 19, 82) and item.x == 0 and item.y == 0:
            problems.append(f"{where}: waypoint at latitude 0, longitude 0 (a missing position?)")
            continue
        if item.seq == 0:
            continue
        above_home = item.z - mission.home_alt_m if item.frame in (0, 5) else item.z
        if not MIN_ALT_ABOVE_HOME_M <= above_home <= MAX_ALT_ABOVE_HOME_M:
            problems.append(f"{where}: altitude {above_home:g} m above home is outside {MIN_ALT_ABOVE_HOME_M:g}..{MAX_ALT_ABOVE_HOME_M:g} m")
    return problems


def evaluate_preflight(
    vehicle: VehicleSnapshot,
    mission: Mission,
    video: VideoStatus,
    *,
    min_fix: str = "rtk_fixed",
    min_battery_pct: int = 30,
    max_home_distance_m: float = 500.0,
    max_mission_items: int = DEFAULT_MAX_MISSION_ITEMS,
) -> list[CheckResult]:
    """The checklist for this vehicle, mission and video (pure).

    Parameters
    ----------
    vehicle : VehicleSnapshot
        Latest telemetry.
    mission : Mission
        The mission to fly.
    video : VideoStatus
        The video probe.
    min_fix : str
        Weakest acceptable fix: ``rtk_fixed`` (default), ``rtk_float`` or ``3d``.
    min_battery_pct : int
        Smallest remaining charge, percent.
    max_home_distance_m : float
        Largest distance between the vehicle's home and the mission's first position, metres.
    max_mission_items : int
        Most items the vehicle holds, home included.

    Returns
    -------
    list of CheckResult
    """
    if min_fix not in MIN_FIX_CHOICES:
        raise InputError(f"--min-fix {min_fix!r} unknown; use one of {', '.join(MIN_FIX_CHOICES)}")
    out: list[CheckResult] = []

    is_px4 = px4.is_px4(vehicle.autopilot)
    if vehicle.autopilot is None:
        out.append(CheckResult("heartbeat", False, "no HEARTBEAT from a vehicle; check --connect"))
    elif is_px4:
        kind = "quadrotor" if vehicle.vehicle_type == ap.MAV_TYPE_QUADROTOR else f"MAV_TYPE {vehicle.vehicle_type}"
        out.append(CheckResult("heartbeat", True, f"PX4 {kind}, mode {vehicle.mode_name}"))
    elif vehicle.autopilot != ap.MAV_AUTOPILOT_ARDUPILOTMEGA:
        out.append(CheckResult("heartbeat", False, f"autopilot {vehicle.autopilot} is neither ArduPilot nor PX4; this tool flies ArduCopter and PX4 missions"))
    else:
        kind = "quadrotor" if vehicle.vehicle_type == ap.MAV_TYPE_QUADROTOR else f"MAV_TYPE {vehicle.vehicle_type}"
        out.append(CheckResult("heartbeat", True, f"ArduPilot {kind}, mode {vehicle.mode_name}"))

    if vehicle.armed:
        out.append(CheckResult("disarmed", False, "vehicle is armed; land and disarm before uploading a mission"))
    else:
        out.append(CheckResult("disarmed", vehicle.armed is not None, "disarmed" if vehicle.armed is not None else "arming state unknown"))

    if vehicle.fix_type is None:
        out.append(CheckResult("gnss", False, "no GPS_RAW_INT received; check the GNSS receiver and telemetry rates"))
    else:
        name = ap.FIX_TYPE_NAMES.get(vehicle.fix_type, "no_fix")
        rank = ap.FIX_TYPE_RANK[name]
        acc = f", h_acc {vehicle.h_acc_m * 100:.1f} cm" if vehicle.h_acc_m else ""
        seen = f"{name}, {vehicle.satellites or 0} satellites{acc}"
        if rank >= ap.FIX_TYPE_RANK["rtk_fixed"]:
            out.append(CheckResult("gnss", True, seen))
        elif is_px4 and rank >= ap.FIX_TYPE_RANK[min_fix] and rank < ap.FIX_TYPE_RANK["dgps"] and vehicle.h_acc_m and vehicle.h_acc_m >= 0.5:
            out.append(CheckResult("gnss", True, f"WARNING: only {seen}: {gnss_accuracy_meaning(vehicle.h_acc_m)}", warning=True))
        elif rank >= ap.FIX_TYPE_RANK[min_fix]:
            out.append(
                CheckResult("gnss", True, f"WARNING: only {seen}: positions may be off by decimetres and the calibration will be worse; wait for RTK fixed if you can", warning=True)
            )
        else:
            out.append(CheckResult("gnss", False, f"{seen}, need {min_fix}; wait for the RTK base/corrections or pass --min-fix"))

    if vehicle.gnss_rate_hz is not None:
        rate = vehicle.gnss_rate_hz
        if rate < MIN_GNSS_RATE_HZ and is_px4:
            out.append(CheckResult(
                "gnss_rate", True,
                f"WARNING: {rate:.1f} new fixes/s: each hold averages fewer fixes (the calibration is worse); {px4.Px4Advice().gps_rate}",
                warning=True,
            ))
        elif rate < MIN_GNSS_RATE_HZ:
            out.append(CheckResult(
                "gnss_rate", True,
                f"WARNING: {rate:.1f} new fixes/s: each hold averages fewer fixes (the calibration is worse); "
                "set GPS_RATE_MS (GPS1_RATE_MS) to 100 if the receiver does 10 Hz, or fly longer holds (plan --hover)",
                warning=True,
            ))
        else:
            out.append(CheckResult("gnss_rate", True, f"{rate:.1f} new fixes/s"))

    if vehicle.ekf_flags is None:
        what = "ESTIMATOR_STATUS" if is_px4 else "EKF_STATUS_REPORT"
        out.append(CheckResult("ekf", False, f"no {what} received; wait for the EKF to start"))
    elif is_px4:
        # PX4's ESTIMATOR_STATUS: healthy EKF2 with GPS reports 1023 (its const-pos bit 128 set too); ratios < 1 pass
        missing = px4.ESTIMATOR_HEALTHY_FLAGS & ~vehicle.ekf_flags
        bad = vehicle.ekf_flags & (ap.EKF_UNINITIALIZED | ap.EKF_GPS_GLITCH)
        ratio = vehicle.ekf_max_variance or 0.0
        if missing or bad or ratio >= 0.8:
            out.append(CheckResult("ekf", False, f"EKF2 not healthy (ESTIMATOR_STATUS flags 0x{vehicle.ekf_flags:04x}, max test ratio {ratio:.2f}); wait for GPS lock and alignment"))
        else:
            out.append(CheckResult("ekf", True, f"EKF2 healthy (ESTIMATOR_STATUS flags 0x{vehicle.ekf_flags:04x}, max test ratio {ratio:.2f})"))
    else:
        missing = ap.EKF_HEALTHY_FLAGS & ~vehicle.ekf_flags
        bad = vehicle.ekf_flags & ap.EKF_BAD_FLAGS
        variance = vehicle.ekf_max_variance or 0.0
        if missing or bad or variance >= 0.8:
            out.append(CheckResult("ekf", False, f"EKF not healthy (flags 0x{vehicle.ekf_flags:04x}, max variance {variance:.2f}); wait for GPS lock and EKF alignment"))
        else:
            out.append(CheckResult("ekf", True, f"healthy (flags 0x{vehicle.ekf_flags:04x}, max variance {variance:.2f})"))

    if vehicle.battery_pct is None or vehicle.battery_pct < 0:
        volts = f"{vehicle.voltage_v:.1f} V, " if vehicle.voltage_v else ""
        out.append(CheckResult("battery", True, f"{volts}remaining charge unknown: check the battery yourself", warning=True))
    elif vehicle.battery_pct < min_battery_pct:
        out.append(CheckResult("battery", False, f"{vehicle.battery_pct} % left, need {min_battery_pct} %; fit a charged battery"))
    else:
        volts = f", {vehicle.voltage_v:.1f} V" if vehicle.voltage_v else ""
        out.append(CheckResult("battery", True, f"{vehicle.battery_pct} %{volts}"))

    if vehicle.ready_to_arm:
        out.append(CheckResult("ready_to_arm", True, "pre-arm checks pass"))
    else:
        reason = f" ({vehicle.last_text})" if vehicle.last_text and "PreArm" in vehicle.last_text else ""
        out.append(CheckResult("ready_to_arm", False, f"vehicle reports pre-arm checks failing{reason}; fix them on the vehicle"))

    target = first_position(mission)
    if vehicle.home_lat_deg is None:
        out.append(CheckResult("home", False, "no HOME_POSITION yet; wait for a GPS lock on the vehicle"))
    elif target is None:
        out.append(CheckResult("home", True, "mission has no positions to compare with"))
    else:
        d = _distance_m(vehicle.home_lat_deg, vehicle.home_lon_deg or 0.0, *target)
        if d > max_home_distance_m:
            out.append(CheckResult("home", False, f"home is {d:.0f} m from the mission's first point (limit {max_home_distance_m:.0f} m); wrong site or wrong mission"))
        else:
            out.append(CheckResult("home", True, f"{d:.1f} m from the mission's first point"))

    problems = check_mission_items(mission, max_items=max_mission_items)
    if problems:
        more = f" (+{len(problems) - 3} more)" if len(problems) > 3 else ""
        out.append(CheckResult("mission", False, "; ".join(problems[:3]) + more + "; fix the mission file (or re-plan) before flying"))
    else:
        flier = "PX4" if is_px4 else "ArduCopter"
        out.append(CheckResult("mission", True, f"{len(mission.items)} items, each a command, frame, position and altitude {flier} flies"))

    if video.error:
        out.append(CheckResult("video", False, video.error if video.url in video.error else f"{video.url}: {video.error}"))
    elif video.frames == 0:
        out.append(CheckResult("video", False, f"{video.url} opened but sent no frame; check the camera stream"))
    else:
        seen = f"{video.width}x{video.height}, {video.fps:.1f} fps"
        if video.warning:
            out.append(CheckResult("video", True, f"WARNING: {seen}, but {video.warning}", warning=True))
        else:
            out.append(CheckResult("video", True, seen))
    return out


def snapshot_from_link(link: MavLink, gnss_meter: GnssRateMeter | None = None) -> VehicleSnapshot:
    """The latest telemetry the link has seen, as a snapshot (with the GNSS rate when a meter is fed)."""
    hb = link.vehicle_heartbeat
    gps = link.latest("GPS_RAW_INT")
    ekf = link.latest("EKF_STATUS_REPORT")
    is_px4 = hb is not None and px4.is_px4(int(hb.autopilot))
    estimator = link.latest("ESTIMATOR_STATUS") if is_px4 else None
    status = link.latest("SYS_STATUS")
    battery = link.latest("BATTERY_STATUS")
    home = link.latest("HOME_POSITION")
    text = link.latest("STATUSTEXT")
    battery_pct = None
    if battery is not None and battery.battery_remaining >= 0:
        battery_pct = int(battery.battery_remaining)
    elif status is not None and status.battery_remaining >= 0:
        battery_pct = int(status.battery_remaining)
    return VehicleSnapshot(
        autopilot=None if hb is None else int(hb.autopilot),
        vehicle_type=None if hb is None else int(hb.type),
        armed=None if hb is None else bool(hb.base_mode & ap.MAV_MODE_FLAG_SAFETY_ARMED),
        mode_name=None if hb is None else (px4.mode_name(int(hb.custom_mode)) if is_px4 else ap.MODE_NAMES.get(int(hb.custom_mode), f"MODE{hb.custom_mode}")),
        fix_type=None if gps is None else int(gps.fix_type),
        satellites=None if gps is None else int(gps.satellites_visible),
        h_acc_m=None if gps is None or not getattr(gps, "h_acc", 0) else gps.h_acc / 1000.0,
        ekf_flags=int(estimator.flags) if estimator is not None else (None if ekf is None else int(ekf.flags)),
        ekf_max_variance=_estimator_ratio(estimator) if estimator is not None else (
            None if ekf is None else float(max(ekf.velocity_variance, ekf.pos_horiz_variance, ekf.pos_vert_variance, ekf.compass_variance))),
        battery_pct=battery_pct,
        voltage_v=None if status is None or status.voltage_battery in (0, 65535) else status.voltage_battery / 1000.0,
        ready_to_arm=None if status is None else bool(status.onboard_control_sensors_health & ap.MAV_SYS_STATUS_PREARM_CHECK),
        home_lat_deg=None if home is None else home.latitude * 1e-7,
        home_lon_deg=None if home is None else home.longitude * 1e-7,
        last_text=None if text is None else str(text.text),
        gnss_rate_hz=None if gnss_meter is None else gnss_meter.rate_hz(),
    )


def _estimator_ratio(msg: Any) -> float:
    """Largest of ESTIMATOR_STATUS's velocity, position and magnetometer test ratios (NaN = not used)."""
    ratios = [float(v) for v in (msg.vel_ratio, msg.pos_horiz_ratio, msg.pos_vert_ratio, msg.mag_ratio) if math.isfinite(v)]
    return max(ratios, default=0.0)


def gnss_accuracy_meaning(h_acc_m: float, distance_m: float = 10.0, focal_px: float = 1000.0) -> str:
    """What a reported horizontal accuracy means for the calibration, in one clause.

    A hold's point is the mean of its fixes, but GNSS error drifts over
    seconds, so a 3 s hold averages little of it: each point may be off by
    about ``h_acc_m``. Seen from the camera ``distance_m`` away that is an
    angle of h_acc/distance, i.e. ``focal_px * h_acc / distance`` pixels of
    disagreement between where the marker is drawn and where the fix says.
    """
    deg = math.degrees(math.atan2(h_acc_m, distance_m))
    px = focal_px * h_acc_m / distance_m
    return (f"the receiver claims {h_acc_m:.1f} m horizontal accuracy (no RTK): each hold's point may be off by that much, "
            f"{deg:.1f} deg or ~{px:.0f} px seen from {distance_m:.0f} m at f={focal_px:.0f} px, against ~1 px with RTK; "
            "the camera's position comes out to decimetres and its focal to percents at best. Fly with RTK for a metric calibration")


def run_preflight(
    link: MavLink,
    mission: Mission,
    video: VideoStatus,
    *,
    min_fix: str = "rtk_fixed",
    min_battery_pct: int = 30,
    max_home_distance_m: float = 500.0,
    wait_s: float = 60.0,
    gnss_meter: GnssRateMeter | None = None,
) -> list[CheckResult]:
    """Evaluate the checklist, waiting up to ``wait_s`` seconds for a booting vehicle to pass.

    Only vehicle checks are waited for; a failed video probe or an armed
    vehicle is reported at once. Asks for HOME_POSITION if none came (a
    request, not a command).
    """
    deadline = time.monotonic() + wait_s
    asked_home = False
    while True:
        results = evaluate_preflight(
            snapshot_from_link(link, gnss_meter), mission, video, min_fix=min_fix, min_battery_pct=min_battery_pct, max_home_distance_m=max_home_distance_m
        )
        failing = {r.name for r in results if not r.ok}
        if not failing or failing & {"video", "disarmed", "heartbeat", "mission"} or time.monotonic() >= deadline:
            return results
        if "home" in failing and not asked_home and link.latest("HOME_POSITION") is None:
            link.send(link.dialect.MAVLink_command_long_message(link.target_system, link.target_component, ap.CMD_REQUEST_MESSAGE, 0, 242, 0, 0, 0, 0, 0, 0))
            asked_home = True
        time.sleep(0.2)


def require_preflight(results: list[CheckResult]) -> None:
    """Raise PreflightError naming every failed check (one line)."""
    failed = [r for r in results if not r.ok]
    if failed:
        raise PreflightError("pre-flight failed: " + "; ".join(f"{r.name}: {r.detail}" for r in failed))


def format_checklist(results: list[CheckResult]) -> str:
    """The checklist as aligned text lines (``[ OK ]``, ``[WARN]``, ``[FAIL]``)."""
    width = max((len(r.name) for r in results), default=0)
    lines = []
    for r in results:
        tag = "FAIL" if not r.ok else ("WARN" if r.warning else " OK ")
        lines.append(f"[{tag}] {r.name.ljust(width)}  {r.detail}")
    return "\n".join(lines)
