"""Build a contract run from a flight log (.tlog or DataFlash .BIN) and a video file.

The run clock (docs/runfile.md, "Import"):

* A tlog's 8-byte record stamps are the recording host's wall clock. They
  can run at a different speed from the vehicle (SITL with ``--speedup 5``
  compresses a 3 s hold into 0.6 s of record time), so they are never used for
  durations. Vehicle time comes from the messages: ``time_boot_ms`` (and the
  boot-based ``GPS_RAW_INT.time_usec``), mapped to UTC by a straight-line fit
  of the vehicle's ``SYSTEM_TIME.time_unix_usec`` against its ``time_boot_ms``
  (per boot, when the vehicle rebooted). A vehicle message without its own time
  field takes the last ``time_boot_ms`` seen from the vehicle (it left in the
  same scheduler tick); a message from the ground station is placed by
  interpolating the host stamps against the vehicle-stamped messages around it.
* Without any SYSTEM_TIME, the host stamp of the first vehicle message anchors
  the clock and the vehicle clock gives every duration (a warning says so).
* A DataFlash log's ``TimeUS`` is boot time; UTC comes from the GPS week and
  milliseconds (GPS time minus the 18 leap seconds) fitted the same way.

Hover windows: ArduCopter sends MISSION_ITEM_REACHED (and the DataFlash
message "Reached command #n") when a waypoint's hold *ends*, so the window is
``[reached - hold_s, reached]`` with ``hold_s`` = param1 of that mission item.
The mission comes from the MISSION_ITEM_INT messages the ground station sent
(the last upload), else from the vehicle's read-back, else from DataFlash CMD.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from dronecal_field.errors import InputError
from dronecal_field.runfile.records import (
    FORMAT_VERSION,
    Attitude,
    GnssFix,
    MarkerSpec,
    RunEvent,
    RunMetadata,
    fix_type_from_mavlink,
)

GPS_EPOCH_UNIX_S = 315_964_800  # 1980-01-06T00:00:00Z
GPS_LEAP_SECONDS = 18  # GPS - UTC since 2017-01-01
NAV_WAYPOINT = 16
NAV_LOITER_TIME = 19
HOLD_COMMANDS = (NAV_WAYPOINT, NAV_LOITER_TIME)
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6
_UINT16_MAX = 65535


# --- domain values ------------------------------------------------------------


@dataclass(frozen=True)
class ClockMap:
    """Vehicle boot clock -> run clock: ``utc_ns = utc_at_boot_ns + rate * boot_ns``.

    Attributes
    ----------
    utc_at_boot_ns : UTC ns at vehicle boot time 0.
    rate : run-clock seconds per vehicle second (1 + drift).
    method : ``"system_time"``, ``"gps_time"`` or ``"host_clock"``.
    samples : number of time pairs fitted.
    residual_ms : RMS of the fit residuals, milliseconds.
    """

    utc_at_boot_ns: int
    rate: float = 1.0
    method: str = "system_time"
    samples: int = 0
    residual_ms: float = 0.0

    def to_utc_ns(self, boot_ns: float | np.ndarray) -> Any:
        """UTC ns of vehicle boot-clock ns (scalar -> int, array -> int64 array)."""
        value = self.utc_at_boot_ns + self.rate * np.asarray(boot_ns, dtype=float)
        if np.ndim(value) == 0:
            return int(round(float(value)))
        return np.round(value).astype(np.int64)

    def to_boot_s(self, utc_ns: int) -> float:
        """Vehicle boot-clock seconds of a run-clock time."""
        return (utc_ns - self.utc_at_boot_ns) / self.rate / 1e9


@dataclass(frozen=True)
class MissionItem:
    """One mission item as flown (MISSION_ITEM_INT or DataFlash CMD)."""

    seq: int
    command: int
    frame: int
    param1: float
    lat_deg: float
    lon_deg: float
    alt_m: float


@dataclass(frozen=True)
class LogMessage:
    """One telemetry message on the run clock."""

    name: str
    time_ns: int
    src_system: int
    src_component: int
    fields: dict[str, Any]


@dataclass(frozen=True, eq=False)
class FlightLog:
    """What a flight log gives a run: every message, fixes, attitude, hover windows.

    Attributes
    ----------
    path : the log file.
    kind : ``"tlog"`` or ``"dataflash"``.
    messages : every message, run clock, in log order (topic ``/mavlink/<NAME>``
        for tlogs, ``/dataflash/<NAME>`` for DataFlash).
    fixes : GNSS fixes with a position (fix_type 2d or better).
    altitude_datum : ``"ellipsoid"`` or ``"msl"`` for every fix.
    attitudes : vehicle attitude (ATTITUDE / ATT).
    hovers : hover windows (RunEvent type ``"hover"``).
    mission : the mission items by seq.
    clocks : the boot -> UTC map of each vehicle boot seen.
    position_source : message the fixes come from.
    warnings : things the user should know.
    """

    path: str
    kind: str
    messages: list[LogMessage]
    fixes: list[GnssFix]
    altitude_datum: str
    attitudes: list[Attitude]
    hovers: list[RunEvent]
    mission: dict[int, MissionItem]
    clocks: list[ClockMap]
    position_source: str
    vehicle_system: int | None = None
    host_seconds_per_vehicle_second: float | None = None
    skipped_no_fix: int = 0
    warnings: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class ImportReport:
    """Machine-readable summary of one import (also attached to the run as import_report.json)."""

    out: str
    log: str
    log_kind: str
    video: str | None
    video_start_ns: int | None
    video_start_source: str | None
    width: int
    height: int
    frames: int
    fixes: int
    skipped_no_fix: int
    attitudes: int
    telemetry_messages: int
    hovers: int
    altitude_datum: str
    position_source: str
    clocks: list[dict[str, Any]]
    host_seconds_per_vehicle_second: float | None
    time_range_ns: tuple[int, int] | None
    warnings: list[str]

    def to_dict(self) -> dict[str, Any]:
        from dataclasses import asdict

        return asdict(self)


# --- pure helpers -------------------------------------------------------------


def fit_clock(boot_ns: np.ndarray, utc_ns: np.ndarray, method: str, outlier_ms: float = 50.0) -> ClockMap:
    """Straight-line fit of UTC against boot time, robust to a few bad pairs.

    Parameters
    ----------
    boot_ns : (N,) vehicle boot-clock times, ns.
    utc_ns : (N,) matching UTC times, ns.
    method : label stored in the ClockMap.
    outlier_ms : pairs further than this from the first fit are dropped.

    A single pair (or pairs spanning under 10 s) gives an offset with rate 1,
    because a rate fitted over a short span is mostly noise.
    """
    boot = np.asarray(boot_ns, dtype=np.int64)
    utc = np.asarray(utc_ns, dtype=np.int64)
    if boot.size == 0:
        raise InputError("no time pairs to fit a clock; the log has no SYSTEM_TIME or GPS time")
    offsets = (utc - boot).astype(np.float64)
    base = float(np.median(offsets))
    keep = np.abs(offsets - base) <= outlier_ms * 1e6
    boot_k, off_k = boot[keep], offsets[keep]
    span_s = (boot_k.max() - boot_k.min()) / 1e9 if boot_k.size else 0.0
    if boot_k.size < 3 or span_s < 10.0:
        residual = float(np.sqrt(np.mean((off_k - base) ** 2))) / 1e6 if off_k.size else 0.0
        return ClockMap(utc_at_boot_ns=int(round(base)), rate=1.0, method=method, samples=int(boot_k.size), residual_ms=residual)
    # Fit offset = a + d * boot (d = drift) in centred coordinates to keep precision.
    t0 = float(boot_k.mean())
    x = (boot_k - t0) / 1e9
    d, a = np.polyfit(x, off_k - base, 1)
    residual = float(np.sqrt(np.mean((off_k - base - (a + d * x)) ** 2))) / 1e6
    rate = 1.0 + d / 1e9
    utc_at_boot = base + a - d * t0 / 1e9
    return ClockMap(
        utc_at_boot_ns=int(round(utc_at_boot)), rate=float(rate), method=method, samples=int(boot_k.size), residual_ms=residual
    )


def boot_segments(boot_ms: np.ndarray, reboot_drop_ms: float = 10_000.0) -> np.ndarray:
    """(N,) boot index of each sample: a new boot starts where time_boot_ms drops by more than reboot_drop_ms."""
    b = np.asarray(boot_ms, dtype=float)
    if b.size == 0:
        return np.zeros(0, dtype=int)
    drops = np.zeros(b.size, dtype=int)
    # A drop is measured against the largest time of the current boot so far.
    seg = 0
    top = b[0]
    for i in range(1, b.size):
        if b[i] < top - reboot_drop_ms:
            seg += 1
            top = b[i]
        else:
            top = max(top, b[i])
        drops[i] = seg
    return drops


def hover_windows(
    reached: Iterable[tuple[int, int]],
    mission: dict[int, MissionItem],
) -> list[RunEvent]:
    """Hover events of MISSION_ITEM_REACHED times, one per waypoint with a hold.

    Parameters
    ----------
    reached : (seq, time_ns) of each "reached" report, run clock; repeats of a
        seq keep the first.
    mission : the mission items by seq.

    Returns
    -------
    list of RunEvent type ``"hover"``: ``[t - hold_s, t]`` with metadata
    ``seq``, ``hold_s``, ``command``, ``lat``, ``lon``, ``alt`` and ``frame``
    (MAV_FRAME of the commanded altitude).
    """
    out: list[RunEvent] = []
    seen: set[int] = set()
    for seq, t_ns in reached:
        if seq in seen:
            continue
        seen.add(seq)
        item = mission.get(seq)
        if item is None or item.command not in HOLD_COMMANDS or not item.param1 > 0:
            continue
        hold_ns = int(round(item.param1 * 1e9))
        out.append(
            RunEvent(
                timestamp_ns=int(t_ns) - hold_ns,
                duration_ns=hold_ns,
                type="hover",
                metadata={
                    "seq": str(seq),
                    "hold_s": repr(float(item.param1)),
                    "command": str(item.command),
                    "lat": repr(float(item.lat_deg)),
                    "lon": repr(float(item.lon_deg)),
                    "alt": repr(float(item.alt_m)),
                    "frame": str(item.frame),
                },
            )
        )
    return out


def gnss_covariance(
    h_acc_m: float | None,
    v_acc_m: float | None,
    hdop: float | None = None,
    vdop: float | None = None,
    fix_type: str | None = None,
) -> np.ndarray | None:
    """(3, 3) ENU covariance, m^2, from the receiver's accuracy, else from DOPs.

    The receiver's horizontal accuracy is used as the 1-sigma of each of east
    and north (conservative: it is often a 2D radius), its vertical accuracy
    for up. Without accuracies, DOP times a per-fix-type range error (UERE)
    gives an approximation; None when neither is known.
    """
    if h_acc_m and h_acc_m > 0 and v_acc_m and v_acc_m > 0:
        return np.diag([h_acc_m**2, h_acc_m**2, v_acc_m**2])
    uere = {"rtk_fixed": 0.02, "rtk_float": 0.3, "dgps": 0.7}.get(fix_type or "", 3.0)
    if hdop and hdop > 0:
        v = vdop if vdop and vdop > 0 else 1.5 * hdop
        return np.diag([(hdop * uere) ** 2, (hdop * uere) ** 2, (v * uere) ** 2])
    return None


def parse_iso8601_ns(text: str) -> int:
    """UTC ns of an ISO 8601 time with a zone (``2025-07-21T10:00:00.5Z``, ``...+02:00``).

    Raises InputError for a malformed time or one without a zone (ambiguous).
    """
    from datetime import datetime

    try:
        dt = datetime.fromisoformat(text.strip().replace("z", "Z"))
    except ValueError:
        raise InputError(f"--video-start {text!r} is not ISO 8601; write e.g. 2025-07-21T10:00:00.000Z") from None
    if dt.tzinfo is None:
        raise InputError(f"--video-start {text!r} has no time zone; add 'Z' for UTC or an offset like +02:00")
    return int(dt.timestamp()) * 1_000_000_000 + dt.microsecond * 1000


# --- tlog ------------------------------------------------------------------------


def read_tlog(path: str | os.PathLike, position_source: str = "auto") -> FlightLog:
    """Read a MAVLink telemetry log (.tlog) onto the run clock.

    Parameters
    ----------
    path : the .tlog file (both link directions, 8-byte µs stamps).
    position_source : ``"auto"`` (GPS_RAW_INT when it has fixes, else
        GLOBAL_POSITION_INT), ``"gps_raw"`` or ``"global_position"``.

    Raises
    ------
    InputError
        when the file cannot be read or holds no vehicle messages.
    """
    from pymavlink import mavutil

    path = Path(path)
    if not path.is_file():
        raise InputError(f"tlog {path} does not exist; give the ground station's .tlog")
    if position_source not in ("auto", "gps_raw", "global_position"):
        raise InputError(f"position source {position_source!r} unknown; use auto, gps_raw or global_position")
    conn = mavutil.mavlink_connection(str(path), robust_parsing=True, dialect="ardupilotmega")
    raw: list[tuple[int, str, int, int, dict[str, Any]]] = []  # (host_us, name, sys, comp, fields)
    try:
        while True:
            msg = conn.recv_msg()
            if msg is None:
                break
            name = msg.get_type()
            if name == "BAD_DATA":
                continue
            fields = msg.to_dict()
            fields.pop("mavpackettype", None)
            raw.append((int(round(msg._timestamp * 1e6)), name, msg.get_srcSystem(), msg.get_srcComponent(), fields))
    finally:
        conn.close()
    if not raw:
        raise InputError(f"tlog {path} holds no MAVLink messages; is it a .tlog?")
    warnings: list[str] = []
    vehicle = _vehicle_system(raw)
    if vehicle is None:
        raise InputError(f"tlog {path}: no vehicle messages with time_boot_ms; cannot place them on a clock")

    # 1. Vehicle boot time of each vehicle message that carries one, split into boots.
    stamped_idx = [i for i, r in enumerate(raw) if r[2] == vehicle and "time_boot_ms" in r[4]]
    stamped_boot_ms = np.array([raw[i][4]["time_boot_ms"] for i in stamped_idx], dtype=np.int64)
    segments = boot_segments(stamped_boot_ms)
    n_boots = int(segments.max()) + 1 if segments.size else 1
    if n_boots > 1:
        warnings.append(f"the vehicle rebooted {n_boots - 1} time(s) during the log; each boot has its own clock fit")

    # 2. One boot -> UTC map per boot, from the vehicle's SYSTEM_TIME.
    clocks: list[ClockMap] = []
    for seg in range(n_boots):
        idx = [stamped_idx[k] for k in np.flatnonzero(segments == seg)]
        pairs = [
            (raw[i][4]["time_boot_ms"] * 1_000_000, raw[i][4]["time_unix_usec"] * 1000)
            for i in idx
            if raw[i][1] == "SYSTEM_TIME" and raw[i][4].get("time_unix_usec", 0) > 0
        ]
        if pairs:
            b, u = np.array(pairs, dtype=np.int64).T
            clocks.append(fit_clock(b, u, "system_time"))
        else:
            first = idx[0]
            host_ns = raw[first][0] * 1000
            clocks.append(
                ClockMap(utc_at_boot_ns=host_ns - raw[first][4]["time_boot_ms"] * 1_000_000, method="host_clock", samples=1)
            )
            warnings.append(
                f"boot {seg}: no SYSTEM_TIME with UTC; the run clock is anchored at the tlog's host clock "
                "and only durations come from the vehicle"
            )

    # 3. Run-clock time of every message.
    seg_of = np.zeros(len(raw), dtype=int)
    stamped_utc = np.empty(len(stamped_idx), dtype=np.int64)
    for seg in range(n_boots):
        sel = segments == seg
        stamped_utc[sel] = clocks[seg].to_utc_ns(stamped_boot_ms[sel] * 1_000_000)
    stamped_host = np.array([raw[i][0] for i in stamped_idx], dtype=np.float64)
    host_to_utc = _monotone_interp(stamped_host, stamped_utc)
    times = np.empty(len(raw), dtype=np.int64)
    last_utc: int | None = None
    last_seg = 0
    k = 0
    for i, (host_us, name, sysid, _comp, fields) in enumerate(raw):
        if k < len(stamped_idx) and stamped_idx[k] == i:
            last_utc = int(stamped_utc[k])
            last_seg = int(segments[k])
            k += 1
            times[i] = last_utc
        elif sysid == vehicle and last_utc is not None:
            times[i] = last_utc
            seg_of[i] = last_seg
        else:
            times[i] = host_to_utc(host_us)
            seg_of[i] = last_seg
    messages = [
        LogMessage(name=r[1], time_ns=int(times[i]), src_system=r[2], src_component=r[3], fields=r[4])
        for i, r in enumerate(raw)
    ]
    host_rate = _host_rate(stamped_host, stamped_boot_ms, segments)

    # 4. Mission, hover windows, fixes, attitude.
    mission = _mission_from_mavlink(messages, vehicle)
    reached = [(int(m.fields["seq"]), m.time_ns) for m in messages if m.name == "MISSION_ITEM_REACHED" and m.src_system == vehicle]
    if reached and not mission:
        warnings.append("MISSION_ITEM_REACHED seen but no mission items in the log: no hover windows (hold times unknown)")
    hovers = hover_windows(reached, mission)
    fixes, datum, source, skipped = _fixes_from_mavlink(messages, vehicle, clocks, seg_of, position_source, warnings)
    attitudes = [
        Attitude(timestamp_ns=m.time_ns, roll_rad=float(m.fields["roll"]), pitch_rad=float(m.fields["pitch"]), yaw_rad=float(m.fields["yaw"]))
        for m in messages
        if m.name == "ATTITUDE" and m.src_system == vehicle
    ]
    return FlightLog(
        path=str(path),
        kind="tlog",
        messages=messages,
        fixes=fixes,
        altitude_datum=datum,
        attitudes=attitudes,
        hovers=hovers,
        mission=mission,
        clocks=clocks,
        position_source=source,
        vehicle_system=vehicle,
        host_seconds_per_vehicle_second=host_rate,
        skipped_no_fix=skipped,
        warnings=warnings,
    )


def _vehicle_system(raw: list[tuple[int, str, int, int, dict[str, Any]]]) -> int | None:
    """System id of the vehicle: an autopilot HEARTBEAT's source, else the most frequent time_boot_ms source."""
    counts: dict[int, int] = {}
    for _, name, sysid, _, fields in raw:
        if name == "HEARTBEAT" and fields.get("autopilot") != MAV_AUTOPILOT_INVALID and fields.get("type") != MAV_TYPE_GCS:
            counts[sysid] = counts.get(sysid, 0) + 1000
        elif "time_boot_ms" in fields:
            counts[sysid] = counts.get(sysid, 0) + 1
    stamped = {s for _, _, s, _, f in raw if "time_boot_ms" in f}
    ranked = sorted((c, s) for s, c in counts.items() if s in stamped)
    return ranked[-1][1] if ranked else None


def _monotone_interp(x: np.ndarray, y: np.ndarray) -> Callable[[float], int]:
    """Interpolator x -> y over nondecreasing copies of x and y, extrapolating with the end slopes."""
    if x.size == 0:
        return lambda v: int(v * 1000)
    xs = np.maximum.accumulate(x)
    ys = np.maximum.accumulate(y.astype(np.float64))
    # Keep strictly increasing x for np.interp.
    keep = np.concatenate([[True], np.diff(xs) > 0])
    xs, ys = xs[keep], ys[keep]
    if xs.size == 1:
        return lambda v: int(round(ys[0] + (v - xs[0]) * 1000))
    slope_lo = (ys[min(10, xs.size - 1)] - ys[0]) / (xs[min(10, xs.size - 1)] - xs[0])
    slope_hi = (ys[-1] - ys[max(0, xs.size - 11)]) / (xs[-1] - xs[max(0, xs.size - 11)])

    def f(v: float) -> int:
        if v < xs[0]:
            return int(round(ys[0] + (v - xs[0]) * slope_lo))
        if v > xs[-1]:
            return int(round(ys[-1] + (v - xs[-1]) * slope_hi))
        return int(round(float(np.interp(v, xs, ys))))

    return f


def _host_rate(host_us: np.ndarray, boot_ms: np.ndarray, segments: np.ndarray) -> float | None:
    """Host (record) seconds per vehicle second over the longest boot: ~0.2 for SITL at speedup 5."""
    if host_us.size < 2:
        return None
    best = np.bincount(segments).argmax()
    sel = segments == best
    h, b = host_us[sel] / 1e6, boot_ms[sel] / 1e3
    if b.max() - b.min() < 1.0:
        return None
    return float((h.max() - h.min()) / (b.max() - b.min()))


def _mission_from_mavlink(messages: list[LogMessage], vehicle: int) -> dict[int, MissionItem]:
    """Mission items of the last upload by the ground station, else the vehicle's read-back."""
    uploaded: dict[int, MissionItem] = {}
    readback: dict[int, MissionItem] = {}
    for m in messages:
        f = m.fields
        if m.name == "MISSION_COUNT" and m.src_system != vehicle and f.get("mission_type", 0) == 0:
            uploaded = {}  # a new upload replaces the mission
        elif m.name in ("MISSION_ITEM_INT", "MISSION_ITEM") and f.get("mission_type", 0) == 0:
            scale = 1e-7 if m.name == "MISSION_ITEM_INT" else 1.0
            item = MissionItem(
                seq=int(f["seq"]),
                command=int(f["command"]),
                frame=int(f["frame"]),
                param1=float(f["param1"]),
                lat_deg=float(f["x"]) * scale,
                lon_deg=float(f["y"]) * scale,
                alt_m=float(f["z"]),
            )
            (readback if m.src_system == vehicle else uploaded)[item.seq] = item
    return uploaded or readback


def _fixes_from_mavlink(
    messages: list[LogMessage],
    vehicle: int,
    clocks: list[ClockMap],
    seg_of: np.ndarray,
    position_source: str,
    warnings: list[str],
) -> tuple[list[GnssFix], str, str, int]:
    """GNSS fixes, their altitude datum, the source message and the count of no-fix messages skipped."""
    gps = [(i, m) for i, m in enumerate(messages) if m.name == "GPS_RAW_INT" and m.src_system == vehicle]
    gps_good = [(i, m) for i, m in gps if m.fields.get("fix_type", 0) >= 2 and (m.fields["lat"] or m.fields["lon"])]
    if position_source == "gps_raw" or (position_source == "auto" and gps_good):
        if not gps_good:
            warnings.append("no GPS_RAW_INT with a position fix in the log: the run has no GNSS fixes")
        ellipsoid = bool(gps_good) and all(m.fields.get("alt_ellipsoid", 0) != 0 for _, m in gps_good)
        if gps_good and not ellipsoid:
            warnings.append("GPS_RAW_INT has no alt_ellipsoid: heights are above mean sea level (gnss.altitude_datum msl)")
        fixes = []
        for i, m in gps_good:
            f = m.fields
            fix_type = fix_type_from_mavlink(f["fix_type"])
            t_ns = _gps_time_ns(f.get("time_usec", 0), m.time_ns, clocks[seg_of[i]])
            h_acc = f.get("h_acc", 0) / 1000.0
            v_acc = f.get("v_acc", 0) / 1000.0
            eph, epv = f.get("eph", _UINT16_MAX), f.get("epv", _UINT16_MAX)
            cov = gnss_covariance(
                h_acc,
                v_acc,
                eph / 100.0 if eph != _UINT16_MAX else None,
                epv / 100.0 if epv != _UINT16_MAX else None,
                fix_type,
            )
            alt_mm = f["alt_ellipsoid"] if ellipsoid else f["alt"]
            fixes.append(
                GnssFix(
                    timestamp_ns=t_ns,
                    lat_deg=f["lat"] * 1e-7,
                    lon_deg=f["lon"] * 1e-7,
                    alt_m=alt_mm / 1000.0,
                    covariance_enu=cov,
                    fix_type=fix_type,
                )
            )
        return fixes, ("ellipsoid" if ellipsoid else "msl"), "GPS_RAW_INT", len(gps) - len(gps_good)
    # GLOBAL_POSITION_INT: the EKF's fused position, heights above MSL, no accuracy.
    fix_type: str | None = None
    fixes = []
    skipped = 0
    for m in messages:
        if m.src_system != vehicle:
            continue
        if m.name == "GPS_RAW_INT":
            fix_type = fix_type_from_mavlink(m.fields.get("fix_type", 0))
        elif m.name == "GLOBAL_POSITION_INT":
            f = m.fields
            if not (f["lat"] or f["lon"]):
                skipped += 1
                continue
            fixes.append(
                GnssFix(
                    timestamp_ns=m.time_ns,
                    lat_deg=f["lat"] * 1e-7,
                    lon_deg=f["lon"] * 1e-7,
                    alt_m=f["alt"] / 1000.0,
                    covariance_enu=None,
                    fix_type=fix_type,
                )
            )
    if not fixes:
        warnings.append("no GLOBAL_POSITION_INT with a position in the log: the run has no GNSS fixes")
    warnings.append("positions from GLOBAL_POSITION_INT (EKF estimate, no accuracy, heights above MSL)")
    return fixes, "msl", "GLOBAL_POSITION_INT", skipped


def _gps_time_ns(time_usec: int, message_ns: int, clock: ClockMap) -> int:
    """Run-clock time of a GPS_RAW_INT fix: its time_usec is Unix time (> 2001) or boot time."""
    if time_usec >= 1_000_000_000_000_000:  # microseconds since 1970, i.e. after 2001-09
        return int(time_usec) * 1000
    if time_usec > 0:
        t = clock.to_utc_ns(int(time_usec) * 1000)
        # A boot-based fix time is never far from the message carrying it.
        if abs(t - message_ns) < 2_000_000_000:
            return t
    return message_ns


# --- DataFlash ---------------------------------------------------------------------

DATAFLASH_TYPES = ("GPS", "GPA", "ATT", "CMD", "MSG", "MODE", "EV", "ERR")


def read_dataflash(path: str | os.PathLike) -> FlightLog:
    """Read an ArduPilot DataFlash log (.BIN) onto the run clock.

    GPS (+GPA accuracies and ellipsoid height), ATT, CMD (mission), MSG
    ("Reached command #n"), MODE, EV and ERR are read; they become the fixes,
    attitude, hover windows and ``/dataflash/<TYPE>`` telemetry.
    """
    from pymavlink import DFReader

    path = Path(path)
    if not path.is_file():
        raise InputError(f"DataFlash log {path} does not exist; give the vehicle's .BIN log")
    try:
        reader = DFReader.DFReader_binary(str(path), zero_time_base=True)
    except Exception as exc:  # noqa: BLE001 - pymavlink raises assorted errors on a bad file
        raise InputError(f"DataFlash log {path} cannot be read ({exc}); is it a .BIN log?") from exc
    raw: list[tuple[str, int, dict[str, Any]]] = []  # (type, TimeUS, fields)
    while True:
        m = reader.recv_match(type=list(DATAFLASH_TYPES))
        if m is None:
            break
        fields = m.to_dict()
        name = fields.pop("mavpackettype", m.get_type())
        if "TimeUS" not in fields:
            continue
        raw.append((name, int(fields["TimeUS"]), fields))
    if not raw:
        raise InputError(f"DataFlash log {path} has none of {', '.join(DATAFLASH_TYPES)}; is it an ArduPilot log?")
    warnings: list[str] = []

    # Clock: GPS week/ms -> UTC against TimeUS (primary receiver, with a valid week).
    pairs = [
        (t * 1000, ((GPS_EPOCH_UNIX_S - GPS_LEAP_SECONDS) + f["GWk"] * 604_800) * 1_000_000_000 + f["GMS"] * 1_000_000)
        for name, t, f in raw
        if name == "GPS" and f.get("I", 0) == 0 and f.get("GWk", 0) > 0 and f.get("Status", 0) >= 3
    ]
    if pairs:
        b, u = np.array(pairs, dtype=np.int64).T
        clock = fit_clock(b, u, "gps_time")
    else:
        stat = path.stat()
        clock = ClockMap(utc_at_boot_ns=int(stat.st_mtime_ns) - raw[-1][1] * 1000, method="file_mtime", samples=0)
        warnings.append("no GPS time in the DataFlash log: the run clock is anchored at the file's modification time")
    messages = [
        LogMessage(name=name, time_ns=clock.to_utc_ns(t * 1000), src_system=0, src_component=0, fields=f)
        for name, t, f in raw
    ]

    # Fixes: GPS joined with the GPA of the same instance and TimeUS.
    gpa = {(f.get("I", 0), t): f for name, t, f in raw if name == "GPA"}
    good = [(t, f) for name, t, f in raw if name == "GPS" and f.get("I", 0) == 0 and f.get("Status", 0) >= 2]
    ellipsoid = bool(good) and all("AEl" in gpa.get((0, t), {}) for t, _ in good)
    if good and not ellipsoid:
        warnings.append("DataFlash GPA has no ellipsoid height (AEl): heights are above mean sea level")
    fixes = []
    for t, f in good:
        a = gpa.get((0, t), {})
        fix_type = fix_type_from_mavlink(f["Status"])
        cov = gnss_covariance(a.get("HAcc"), a.get("VAcc"), f.get("HDop"), a.get("VDop"), fix_type)
        fixes.append(
            GnssFix(
                timestamp_ns=clock.to_utc_ns(t * 1000),
                lat_deg=float(f["Lat"]),
                lon_deg=float(f["Lng"]),
                alt_m=float(a["AEl"] if ellipsoid else f["Alt"]),
                covariance_enu=cov,
                fix_type=fix_type,
            )
        )
    skipped = sum(1 for name, _, f in raw if name == "GPS" and f.get("I", 0) == 0 and f.get("Status", 0) < 2)
    attitudes = [
        Attitude(
            timestamp_ns=clock.to_utc_ns(t * 1000),
            roll_rad=float(np.radians(f["Roll"])),
            pitch_rad=float(np.radians(f["Pitch"])),
            yaw_rad=float(np.radians(f["Yaw"])),
        )
        for name, t, f in raw
        if name == "ATT"
    ]
    mission: dict[int, MissionItem] = {}
    for name, _, f in raw:
        if name == "CMD":
            mission[int(f["CNum"])] = MissionItem(
                seq=int(f["CNum"]),
                command=int(f["CId"]),
                frame=int(f.get("Frame", 0)),
                param1=float(f["Prm1"]),
                lat_deg=float(f["Lat"]),
                lon_deg=float(f["Lng"]),
                alt_m=float(f["Alt"]),
            )
    reached = []
    prefix = "Reached command #"
    for name, t, f in raw:
        text = str(f.get("Message", "")) if name == "MSG" else ""
        if text.startswith(prefix) and text[len(prefix):].strip().isdigit():
            reached.append((int(text[len(prefix):]), clock.to_utc_ns(t * 1000)))
    return FlightLog(
        path=str(path),
        kind="dataflash",
        messages=messages,
        fixes=fixes,
        altitude_datum="ellipsoid" if ellipsoid else "msl",
        attitudes=attitudes,
        hovers=hover_windows(reached, mission),
        mission=mission,
        clocks=[clock],
        position_source="GPS",
        skipped_no_fix=skipped,
        warnings=warnings,
    )


# --- the import stage ----------------------------------------------------------------


def mission_to_waypoints(mission: dict[int, MissionItem]) -> str:
    """QGC WPL 110 text of a mission (frame 6 written as 3, as ground stations do)."""
    lines = ["QGC WPL 110"]
    for seq in sorted(mission):
        it = mission[seq]
        frame = {6: 3, 5: 0}.get(it.frame, it.frame)
        lines.append(
            f"{seq}\t{1 if seq == 0 else 0}\t{frame}\t{it.command}\t{it.param1:.6f}\t0.000000\t0.000000\t0.000000\t"
            f"{it.lat_deg:.7f}\t{it.lon_deg:.7f}\t{it.alt_m:.6f}\t1"
        )
    return "\n".join(lines) + "\n"


def import_run(
    out: str | os.PathLike,
    log: FlightLog,
    marker: MarkerSpec,
    video: str | os.PathLike | None = None,
    video_start_ns: int | None = None,
    max_fps: float | None = None,
    jpeg_quality: int = 95,
    image_size: tuple[int, int] | None = None,
    compression: str = "zstd",
    reencode: bool = False,
) -> ImportReport:
    """Write a contract run from a flight log and a video file.

    Parameters
    ----------
    out : the .mcap to write.
    log : from :func:`read_tlog` or :func:`read_dataflash`.
    marker : the marker flown.
    video : video file; an H.264/H.265 one (an NVR's MP4/MKV export) goes to
        ``/camera/video`` as it is, access unit by access unit, never
        re-encoded; other codecs (or ``reencode``) to ``/camera/image`` as
        JPEG. None writes no frames (then ``image_size`` is required).
    video_start_ns : UTC ns of the video's first frame; None takes the MP4
        creation time, else the first GNSS fix (with a warning).
    max_fps : keep at most this many frames per second of video (JPEG only:
        a compressed stream keeps every frame, each refers to the one before).
    jpeg_quality : JPEG quality of the re-encoded frames.
    image_size : (width, height) when there is no video.
    compression : MCAP chunk compression.
    reencode : decode an H.264/H.265 file and write JPEG frames instead of passing it through.

    Returns
    -------
    ImportReport
        also attached to the run as ``import_report.json``.
    """
    from dronecal_field.video import read_video_file, video_creation_time_ns
    from dronecal_field.video.files import probe_video_format, read_video_packets

    warnings = list(log.warnings)
    start_source = None
    frames_iter: Iterator[tuple[int, Any, tuple[int, int]]] | None = None
    first = None
    if video is not None:
        if video_start_ns is not None:
            start_source = "--video-start"
        else:
            video_start_ns = video_creation_time_ns(video)
            start_source = "container creation time"
            if video_start_ns is None:
                if not log.fixes:
                    raise InputError(f"video {video}: no creation time and no GNSS fix to start at; pass --video-start")
                video_start_ns = log.fixes[0].timestamp_ns
                start_source = "first GNSS fix"
                warnings.append(
                    "the video has no creation time: its first frame is placed at the first GNSS fix; "
                    "pass --video-start for a real alignment"
                )
        passthrough = not reencode and probe_video_format(str(video)) is not None
        if passthrough:
            frames_iter = read_video_packets(str(video), video_start_ns)
            if max_fps:
                warnings.append(f"--max-fps {max_fps:g} ignored: an H.264/H.265 video is imported whole (each frame refers to the one before)")
        else:
            frames_iter = read_video_file(video, video_start_ns, jpeg_quality=jpeg_quality, max_fps=max_fps)
        first = next(frames_iter, None)
        if first is None:
            raise InputError(f"video {video} has no readable frame; check the file and its codec")
        width, height = first[2]
    elif image_size is not None:
        width, height = image_size
    else:
        raise InputError("no video and no image size: give --video (or the camera's width and height)")
    metadata = RunMetadata(
        format_version=FORMAT_VERSION,
        width=int(width),
        height=int(height),
        marker=marker,
        altitude_datum=log.altitude_datum,
        camera_latency_s=None,
        extra={"import.log": Path(log.path).name, "import.log_kind": log.kind},
    )
    camera = "video" if first is not None and first[1].format in ("h264", "h265") else "image"
    if camera == "video":
        from dataclasses import replace

        metadata = replace(metadata, extra={**metadata.extra, "camera.clock": "file"})
    seen = _TimeRange()
    # Written beside ``out`` under a temporary name and put in place whole at the end: an interrupted
    # import (Ctrl-C, SIGTERM, a full disk) leaves no half run that would block the retry.
    final = Path(out)
    tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
    from dronecal_field.errors import RecordingStoppedError

    try:
        try:
            report = _write_imported(tmp, metadata, compression, camera, log, frames_iter, first, seen, final, video, video_start_ns,
                                     start_source, width, height, warnings)
        except RecordingStoppedError as exc:
            raise InputError(f"--out {final}: writing failed ({str(exc).split(':', 1)[0]}); nothing was written: free some space and import again") from None
        try:
            os.link(tmp, final)  # never over a file that appeared meanwhile
        except FileExistsError:
            raise InputError(f"--out {final} appeared while importing (another process?); nothing was overwritten: choose a new name") from None
        except OSError:
            if final.exists():
                raise InputError(f"--out {final} appeared while importing (another process?); nothing was overwritten: choose a new name") from None
            os.rename(tmp, final)  # a file system without hard links
    finally:
        tmp.unlink(missing_ok=True)
    return report


def _write_imported(tmp, metadata, compression, camera, log, frames_iter, first, seen, out, video, video_start_ns, start_source,
                    width, height, warnings):
    """Write the imported run into ``tmp``; the report names ``out``."""
    import json
    from dataclasses import asdict

    from dronecal_field.runfile.writer import RunWriter

    n_frames = 0
    with RunWriter(tmp, metadata, compression=compression, background_flush=False, camera=camera) as writer:
        if log.mission:
            writer.attach("mission.waypoints", mission_to_waypoints(log.mission).encode(), "text/plain")
        for fix in log.fixes:
            writer.write_fix(fix)
            seen(fix.timestamp_ns)
        for att in log.attitudes:
            writer.write_attitude(att)
        for ev in log.hovers:
            writer.write_event(ev)
        for m in log.messages:
            if log.kind == "tlog":
                fields = dict(m.fields)
                fields["_sysid"] = m.src_system
                fields["_compid"] = m.src_component
                writer.write_mavlink(m.name, m.time_ns, fields)
            else:
                writer.write_json(f"/dataflash/{m.name}", f"dataflash.{m.name}", m.time_ns, m.fields)
        if frames_iter is not None and first is not None:
            for _, frame, _ in _chain([first], frames_iter):
                writer.write_frame(frame)
                seen(frame.timestamp_ns)
                n_frames += 1
        report = ImportReport(
            out=str(out),
            log=log.path,
            log_kind=log.kind,
            video=str(video) if video is not None else None,
            video_start_ns=video_start_ns,
            video_start_source=start_source,
            width=int(width),
            height=int(height),
            frames=n_frames,
            fixes=len(log.fixes),
            skipped_no_fix=log.skipped_no_fix,
            attitudes=len(log.attitudes),
            telemetry_messages=len(log.messages),
            hovers=len(log.hovers),
            altitude_datum=log.altitude_datum,
            position_source=log.position_source,
            clocks=[asdict(c) for c in log.clocks],
            host_seconds_per_vehicle_second=log.host_seconds_per_vehicle_second,
            time_range_ns=seen.range(),
            warnings=warnings,
        )
        writer.attach("import_report.json", json.dumps(report.to_dict(), indent=1).encode(), "application/json")
    return report


class _TimeRange:
    """The smallest and largest time seen, ns."""

    def __init__(self) -> None:
        self.t_min: int | None = None
        self.t_max: int | None = None

    def __call__(self, t: int) -> None:
        self.t_min = t if self.t_min is None else min(self.t_min, t)
        self.t_max = t if self.t_max is None else max(self.t_max, t)

    def range(self) -> tuple[int, int] | None:
        return (self.t_min, self.t_max) if self.t_min is not None else None


def _chain(head: list[Any], tail: Iterator[Any]) -> Iterator[Any]:
    yield from head
    yield from tail


__all__ = [
    "ClockMap",
    "FlightLog",
    "ImportReport",
    "LogMessage",
    "MissionItem",
    "boot_segments",
    "fit_clock",
    "gnss_covariance",
    "hover_windows",
    "import_run",
    "mission_to_waypoints",
    "parse_iso8601_ns",
    "read_dataflash",
    "read_tlog",
]
