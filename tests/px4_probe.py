"""One probe for PX4 1.16 SITL and for `sim vehicle --autopilot px4`: what a ground station meets, and how it flies.

:func:`probe` talks to a vehicle with `fly`'s own client code and returns
what it saw: boot mode and identity, GPS (fix type, h_acc, the time base,
the fix rate), SYS_STATUS health, MISSION_CURRENT with no mission, the
upload's request types, the read-back (frame 3 -> 6, float32 altitude, yaw
through float32 radians), DO_SET_ROI refused at start, the start
(MISSION_START arms and starts), then a flight (:data:`FULL`: take-off to
2.5 m, 2 m/s, a 3 s hold 4 m east facing the pole, a fly-through 6 m north,
1 m/s, a 2 s hold, LAND at home; :data:`SHORT`: the first hold only). From
the flight's GLOBAL_POSITION_INT track (vehicle clock) it measures the climb
and descent rates, each hold's still time, the legs' top speeds and
acceleration, the speed at the fly-through point, the yaw error to the pole
at the holds, the MISSION_ITEM_REACHED messages (which seqs, how often, when
against the hold), the modes, the landing and the disarm. :func:`rows` puts
SITL runs and a simulator probe side by side, each value with a tolerance.

Used by benchmarks/sim_px4_conformance.py (the full table) and
tests/test_px4_sim_conformance.py (the CI's short flight).
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic, geodetic_to_enu
from dronecal_field.mavlink import missionfile as mf
from dronecal_field.mavlink import px4
from dronecal_field.mavlink.control import arm_and_start_mission, request_telemetry
from dronecal_field.mavlink.link import MavLink, open_link
from dronecal_field.mavlink.mission import download_mission, send_mission, upload_and_verify
from dronecal_field.mavlink.missionfile import MissionItem
from dronecal_field.mavlink.preflight import VideoStatus, run_preflight

HOME = (-35.363261, 149.165230, 584.0)
ROI_EN = (0.0, -8.0)
HOLD_A = (4.0, 0.0, 2.5, 3.0)  # east, north, up (m), hold s
PASS_B = (4.0, 6.0, 3.0)
HOLD_C = (0.0, 6.0, 3.0, 2.0)
SPEED_1, SPEED_2 = 2.0, 1.0  # m/s: before B, after B


@dataclass(frozen=True)
class Scenario:
    """A probe flight: its holds (name -> east, north, up m, hold s; PX4 seq), whether it has the fly-through legs."""

    name: str
    holds: dict
    legs: bool


# take-off 2.5 m, 2 m/s, ROI, hold A 3 s, fly-through B, 1 m/s, hold C 2 s, LAND (about 55 s on the SITL)
FULL = Scenario("full", {"A": (HOLD_A, 3), "C": (HOLD_C, 6)}, legs=True)
# take-off 2.5 m, 2 m/s, ROI, hold A 3 s, LAND (about 30 s on the SITL): the CI's
SHORT = Scenario("short", {"A": (HOLD_A, 3)}, legs=False)


def _at(e: float, n: float) -> tuple[int, int]:
    lat, lon, _h = enu_to_geodetic([e, n, 0.0], EnuOrigin(*HOME))[0]
    return int(round(lat * 1e7)), int(round(lon * 1e7))


def mission(scenario: Scenario = FULL) -> list[MissionItem]:
    """The file's items (seq 0 = home), as `plan` writes them: fly converts them to PX4's mission."""
    hx, hy = _at(0, 0)
    rx, ry = _at(*ROI_EN)
    ax, ay = _at(HOLD_A[0], HOLD_A[1])
    bx, by = _at(PASS_B[0], PASS_B[1])
    cx, cy = _at(HOLD_C[0], HOLD_C[1])
    if not scenario.legs:
        return [
            MissionItem(seq=0, frame=0, command=16, x=hx, y=hy, z=HOME[2]),
            MissionItem(seq=1, frame=3, command=22, p4=math.nan, x=hx, y=hy, z=2.5),
            MissionItem(seq=2, frame=2, command=178, p1=1.0, p2=SPEED_1, p3=-1.0),
            MissionItem(seq=3, frame=3, command=201, p1=3.0, x=rx, y=ry, z=1.0),
            MissionItem(seq=4, frame=3, command=16, p1=HOLD_A[3], p4=236.57, x=ax, y=ay, z=HOLD_A[2]),
            MissionItem(seq=5, frame=3, command=21, p4=math.nan, x=hx, y=hy, z=0.0),
        ]
    return [
        MissionItem(seq=0, frame=0, command=16, x=hx, y=hy, z=HOME[2]),
        MissionItem(seq=1, frame=3, command=22, p4=math.nan, x=hx, y=hy, z=2.5),
        MissionItem(seq=2, frame=2, command=178, p1=1.0, p2=SPEED_1, p3=-1.0),
        MissionItem(seq=3, frame=3, command=201, p1=3.0, x=rx, y=ry, z=1.0),
        MissionItem(seq=4, frame=3, command=16, p1=HOLD_A[3], p4=236.57, x=ax, y=ay, z=HOLD_A[2]),
        MissionItem(seq=5, frame=3, command=16, p4=math.nan, x=bx, y=by, z=PASS_B[2]),
        MissionItem(seq=6, frame=2, command=178, p1=1.0, p2=SPEED_2, p3=-1.0),
        MissionItem(seq=7, frame=3, command=16, p1=HOLD_C[3], p4=math.nan, x=cx, y=cy, z=HOLD_C[2]),
        MissionItem(seq=8, frame=3, command=21, p4=math.nan, x=hx, y=hy, z=0.0),
    ]


# ----- the probe -----


class _Recorder:
    """Every message of interest with its arrival (monotonic s), for the vehicle clock and the events."""

    def __init__(self) -> None:
        self.track: list[tuple[float, ...]] = []  # (boot s, lat, lon, rel alt m, vn, ve, vd, hdg deg)
        self.clock: list[tuple[float, float]] = []  # (arrival s, boot s)
        self.reached: list[tuple[float, int]] = []  # (arrival s, seq)
        self.modes: list[tuple[float, str, bool]] = []  # (arrival s, mode, armed)
        self.stream_boot_s: dict[int, float] = {}  # id of a reached/heartbeat entry -> the vehicle time of the position before it
        self.last_boot_s: float | None = None
        self.gps: list[tuple[float, int]] = []  # (arrival s, time_usec)
        self.requests: list[str] = []
        self.texts: list[str] = []
        self.lock = threading.Lock()

    def __call__(self, direction: str, _stamp: int, msg: Any) -> None:
        if direction != "in":
            return
        now = time.monotonic()
        t = msg.get_type()
        with self.lock:
            if t == "GLOBAL_POSITION_INT":
                self.last_boot_s = msg.time_boot_ms * 1e-3
                self.clock.append((now, msg.time_boot_ms * 1e-3))
                self.track.append((msg.time_boot_ms * 1e-3, msg.lat * 1e-7, msg.lon * 1e-7, msg.relative_alt * 1e-3,
                                   msg.vx * 1e-2, msg.vy * 1e-2, msg.vz * 1e-2, msg.hdg * 1e-2))  # fmt: skip
            elif t == "MISSION_ITEM_REACHED":
                self.reached.append((now, int(msg.seq)))
                self.stream_boot_s[id(self.reached[-1])] = self.last_boot_s
            elif t == "HEARTBEAT" and msg.autopilot == 12:
                self.modes.append((now, px4.mode_name(int(msg.custom_mode)), bool(msg.base_mode & 128)))
                self.stream_boot_s[id(self.modes[-1])] = self.last_boot_s
            elif t == "GPS_RAW_INT":
                self.gps.append((now, int(msg.time_usec)))
            elif t.startswith("MISSION_REQUEST"):
                self.requests.append(t)
            elif t == "STATUSTEXT":
                self.texts.append(str(msg.text))

    def boot_s(self, arrival: np.ndarray) -> np.ndarray:
        """Arrival times -> vehicle seconds since boot (a line through GLOBAL_POSITION_INT's)."""
        c = np.array(self.clock)
        a, b = np.polyfit(c[:, 0], c[:, 1], 1)
        return a * np.asarray(arrival) + b


def probe(link: MavLink, *, rate: float = 1.0, scenario: Scenario = FULL, log=print) -> dict:
    """Everything the table compares, seen on ``link`` (vehicle time where it matters; ``rate`` = vehicle s per wall s)."""
    obs: dict[str, Any] = {}
    rec = _Recorder()
    link.add_listener(rec)
    hb = link.wait_heartbeat(30)
    obs["autopilot"], obs["type"] = int(hb.autopilot), int(hb.type)
    obs["boot_mode"] = px4.mode_name(int(hb.custom_mode))
    obs["boot_custom_mode"] = int(hb.custom_mode)
    obs["boot_base_mode"], obs["boot_system_status"] = int(hb.base_mode), int(hb.system_status)
    request_telemetry(link)
    link.command_long(511, (115, 1e5))  # HIL_STATE_QUATERNION, the truth the sim camera draws with
    obs["hil_state"] = link.wait_message({"HIL_STATE_QUATERNION"}, timeout_s=3.0) is not None
    time.sleep(3.0 / rate)
    cur = link.latest("MISSION_CURRENT")
    obs["mission_total_empty"] = None if cur is None else int(cur.total)
    video = VideoStatus(url="x", frames=30, fps=30, width=1280, height=720)
    checks = {r.name: r for r in run_preflight(link, mf.Mission(items=tuple(mission(scenario)), home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2]),
                                               video, min_fix="3d", wait_s=90)}  # fmt: skip
    obs["preflight"] = {k: bool(checks[k].ok) for k in ("ekf", "ready_to_arm", "home", "gnss") if k in checks}
    gps = link.latest("GPS_RAW_INT")
    gpi = link.latest("GLOBAL_POSITION_INT")
    obs["gps_fix_type"], obs["gps_h_acc_mm"], obs["gps_v_acc_mm"] = int(gps.fix_type), int(gps.h_acc), int(gps.v_acc)
    obs["gps_time_minus_boot_s"] = gps.time_usec * 1e-6 - gpi.time_boot_ms * 1e-3
    stamps = sorted({u for _a, u in rec.gps})
    span = (stamps[-1] - stamps[0]) * 1e-6 if len(stamps) > 1 else 0.0
    obs["gps_fix_hz"] = (len(stamps) - 1) / span if span > 0 else 0.0
    status = link.latest("SYS_STATUS")
    obs["sys_status_prearm_bit"] = bool(status.onboard_control_sensors_health & (1 << 28))
    obs["sys_status_health_ok"] = (status.onboard_control_sensors_present & status.onboard_control_sensors_enabled
                                   & ~status.onboard_control_sensors_health & ~(1 << 28)) == 0  # fmt: skip
    est = link.latest("ESTIMATOR_STATUS")
    obs["estimator_flags"] = None if est is None else int(est.flags)
    obs["ekf_status_report"] = link.latest("EKF_STATUS_REPORT") is not None
    # DO_SET_ROI (201) as ArduPilot takes it: PX4 stores mode 0 and refuses the start
    items = mission(scenario)
    raw = [MissionItem(seq=0, frame=3, command=22, p4=math.nan, x=items[1].x, y=items[1].y, z=2.5), replace(items[3], seq=1)]
    rec.requests.clear()
    send_mission(link, raw)
    obs["requests_first_upload"] = list(dict.fromkeys(rec.requests))
    back = download_mission(link)
    obs["roi201_p1_back"] = float(back[1].p1)
    time.sleep(1.5 / rate)  # PX4 checks a new mission's feasibility a moment after the upload
    obs["start_with_roi201"] = int(link.command_long(300, (0, 0)))
    if obs["start_with_roi201"] == 0:  # accepted (the SITL did, 1.5 s after the upload): it armed; disarm before the real mission
        link.command_long(400, (0, 21196))
        time.sleep(2.0 / rate)
    rec.requests.clear()
    report = upload_and_verify(link, items)
    obs["requests_next_upload"] = list(dict.fromkeys(rec.requests))
    obs["readback_identical"] = report.items == len(items)
    back = download_mission(link)
    obs["mission_seq0_command"] = int(back[0].command)
    obs["frame3_back"] = int(back[0].frame)
    obs["do_frame_back"] = int(back[1].frame)
    obs["z_back"] = float(back[3].z)
    obs["yaw_back"] = float(back[3].p4)
    obs["roi_command_back"] = int(back[2].command)
    time.sleep(1.0 / rate)
    cur = link.latest("MISSION_CURRENT")
    obs["mission_total"] = None if cur is None else int(cur.total)
    obs["scenario"] = scenario.name
    t_start = time.monotonic()
    arm_and_start_mission(link)
    obs["start_acks"] = 1  # MISSION_START alone, accepted (arm_and_start_mission raises otherwise)
    deadline = time.monotonic() + 200 / rate
    armed_seen = False
    while time.monotonic() < deadline:
        time.sleep(0.2 / rate)
        with rec.lock:
            last = rec.modes[-1] if rec.modes else None
        if last is not None and last[2]:
            armed_seen = True
        if armed_seen and last is not None and not last[2]:
            break
    time.sleep(2.0 / rate)
    link.remove_listener(rec)
    with rec.lock:
        obs.update(_flight(rec, t_start, scenario))
    obs["texts"] = rec.texts[-12:]
    log(f"probe done: {len(rec.track)} positions, {len(rec.reached)} reached messages")
    return obs


def _flight(rec: _Recorder, t_start: float, scenario: Scenario) -> dict:
    """The flight's numbers from the recorded track (vehicle seconds)."""
    out: dict[str, Any] = {}
    tr = np.array(sorted(set(rec.track)))
    t = tr[:, 0]
    enu = geodetic_to_enu(tr[:, 1], tr[:, 2], HOME[2], EnuOrigin(*HOME))
    e, n, u = enu[:, 0], enu[:, 1], tr[:, 3]
    speed = np.hypot(tr[:, 4], tr[:, 5])
    vz = -tr[:, 6]
    hdg = tr[:, 7]
    start_s = float(rec.boot_s([t_start])[0])
    after = t >= start_s
    air = np.nonzero(after & (u > 0.3))[0]
    out["airborne_after_start_s"] = float(t[air[0]] - start_s) if len(air) else None
    out["climb_rate_mps"] = float(np.percentile(vz[after & (u < 2.0) & (u > 0.5)], 90)) if np.any(after & (u < 2.0) & (u > 0.5)) else None
    # holds: the longest still stretch near the point. Still by the speed's median over a second: the SITL's EKF speed
    # jitters with its 0.5 m GNSS noise, and the raw gate cut one CI run's 3 s hold to 1.7 s of stillness
    from scipy.ndimage import median_filter

    per_s = max(1, int(round(1.0 / float(np.median(np.diff(t)))))) if len(t) > 1 else 1
    calm = median_filter(speed, size=per_s, mode="nearest")
    holds = {}
    for name, ((he, hn, hu, hs), _seq) in scenario.holds.items():
        near = (np.hypot(e - he, n - hn) < 0.5) & (np.abs(u - hu) < 0.6) & (calm < 0.3)
        best, best_span, start = 0.0, None, None
        for i, ok in enumerate(near):
            if ok and start is None:
                start = i
            if (not ok or i == len(near) - 1) and start is not None:
                end = i if ok else i - 1
                if t[end] - t[start] > best:
                    best, best_span = t[end] - t[start], (t[start], t[end])
                start = None
        at = np.hypot(e - he, n - hn) < 0.5
        arrive = float(t[np.nonzero(at)[0][0]]) if at.any() else None
        bearing = math.degrees(math.atan2(ROI_EN[0] - he, ROI_EN[1] - hn)) % 360
        yaw_err = float(np.median(np.abs((hdg[near] - bearing + 180) % 360 - 180))) if near.any() else None
        holds[name] = dict(planned_s=hs, still_s=float(best), span=best_span, arrive_s=arrive, yaw_err_deg=yaw_err)
    out["holds"] = holds
    # legs: A -> B at SPEED_1, B -> C at SPEED_2
    a_end = holds["A"]["span"][1] if holds["A"]["span"] else None
    last = holds[list(holds)[-1]]
    c_start = last["span"][0] if last["span"] else None
    if scenario.legs and a_end is not None and c_start is not None:
        near_b = np.hypot(e - PASS_B[0], n - PASS_B[1])
        leg = (t > a_end) & (t < c_start)
        ib = np.nonzero(leg)[0][np.argmin(near_b[leg])]
        t_b = t[ib]
        leg1 = (t > a_end) & (t < t_b)
        leg2 = (t > t_b) & (t < c_start)
        out["leg1_top_mps"] = float(speed[leg1].max())
        out["leg2_top_mps"] = float(speed[leg2].max())
        out["pass_b_miss_m"] = float(near_b[ib])
        out["pass_b_speed_mps"] = float(speed[ib])
        out["leg1_s"] = float(t_b - a_end)
        # acceleration out of the hold: 10 % to 90 % of the leg's top speed
        top = out["leg1_top_mps"]
        i10 = np.nonzero(leg1 & (speed > 0.1 * top))[0]
        i90 = np.nonzero(leg1 & (speed > 0.9 * top))[0]
        out["leg1_accel_mps2"] = float(0.8 * top / max(t[i90[0]] - t[i10[0]], 1e-3)) if len(i10) and len(i90) else None
    # yaw rate while turning
    dh = np.abs((np.diff(hdg) + 180) % 360 - 180)
    dt = np.diff(t)
    ok = dt > 0.02
    out["max_yaw_rate_dps"] = float(np.percentile(dh[ok] / dt[ok], 99)) if ok.any() else None
    # reached: which, how often, when
    # event times on the stream's order (the vehicle time of the position before each): arrival times blur on a busy machine
    seqs = [s for _a, s in rec.reached]
    boot = np.array([rec.stream_boot_s.get(id(r)) or 0.0 for r in rec.reached])
    out["reached_seqs"] = sorted(set(seqs))
    out["reached_counts"] = {str(s): seqs.count(s) for s in sorted(set(seqs))}
    period = []
    for s in set(seqs):
        ts = sorted(boot[[i for i, q in enumerate(seqs) if q == s]])
        period += list(np.diff(ts))
    out["reached_repeat_period_s"] = float(np.median(period)) if period else None
    first = {}
    for b, s in zip(boot, seqs):
        first.setdefault(s, float(b))
    for name, (_hold, px4_seq) in scenario.holds.items():
        span = holds[name]["span"]
        first_any = first.get(px4_seq, first.get(px4_seq + 1))
        holds[name]["reached_minus_hold_end_s"] = None if span is None or first_any is None else float(first_any - span[1])
    # landing
    ground = float(np.median(u[-10:]))  # PX4's relative altitude on the ground after landing is not 0 (baro)
    land_i = np.nonzero(after & (t > (c_start or 0)) & (u < ground + 0.15) & (np.abs(vz) < 0.1))[0]
    if len(land_i):
        out["land_miss_m"] = float(np.hypot(e[land_i[0]], n[land_i[0]]))
        t_touch = t[land_i[0]]
        desc = after & (t > (c_start or 0)) & (vz < -0.05) & (u > 0.5)
        out["descent_rate_mps"] = float(-np.percentile(vz[desc], 10)) if desc.any() else None
        disarm = [rec.stream_boot_s.get(id(x)) for x in rec.modes if not x[2] and x[0] > t_start + 5]
        out["disarm_after_touchdown_s"] = float(disarm[0] - t_touch) if disarm and disarm[0] is not None else None
    modes = []
    for _a, m, armed in rec.modes:
        label = f"{m}{'*' if armed else ''}"
        if not modes or modes[-1] != label:
            modes.append(label)
    out["modes"] = modes
    flown: list[str] = []
    for a, m, armed in rec.modes:
        label = f"{m}{'*' if armed else ''}"
        if a >= t_start and (not flown or flown[-1] != label):
            flown.append(label)
    out["modes_flown"] = flown
    out["flight_s"] = float(t[after][-1] - start_s)
    out["track"] = [[round(float(v), 3) for v in row] for row in np.column_stack([t, e, n, u, speed, vz, hdg])[after][::2]]
    return out


# ----- the table -----


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.2f}"
    return str(v)


def rows(sitls: list[dict], sim: dict) -> list[tuple[str, str, str, bool]]:
    """(item, SITL, sim, agree?) for every probe value, each with its own tolerance.

    ``sitls`` holds one or more SITL probes: the SITL column shows each run
    (``a / b``), and a value agrees when it is within the tolerance of one of
    them or between them (the firmware's own run-to-run spread).
    """
    out: list[tuple[str, str, str, bool]] = []

    def col(values: list) -> str:
        texts = [_fmt(v) for v in values]
        return texts[0] if len(set(texts)) == 1 else " / ".join(texts)

    def pick(src: dict, key: str | tuple) -> Any:
        if isinstance(key, tuple):
            return tuple(src.get(k) for k in key)
        return src.get(key)

    def same(name: str, a: Any, b: Any) -> None:
        values = [pick(x, a) for x in sitls]
        mine = pick(sim, b if b is not None else a)
        out.append((name, col(values), _fmt(mine), mine in values))

    def near(name: str, key: Any, tol: float, rel: bool = False, get=None) -> None:
        getter = get or (lambda src: src.get(key))
        values = [getter(x) for x in sitls]
        mine = getter(sim)
        known = [v for v in values if v is not None]
        ok = mine is not None and bool(known) and (
            min(known) <= mine <= max(known) or any(abs(mine - v) <= (tol * abs(v) if rel else tol) for v in known))
        out.append((name, col(values), _fmt(mine), bool(ok)))

    same("HEARTBEAT autopilot, type", ("autopilot", "type"), None)
    same("HEARTBEAT base_mode, boot", "boot_base_mode", None)
    same("boot mode", "boot_mode", None)
    same("HIL_STATE_QUATERNION (truth) when asked", "hil_state", None)
    same("MISSION_CURRENT.total, no mission", "mission_total_empty", None)
    same("pre-flight (ekf, ready_to_arm, home, gnss) with --min-fix 3d", "preflight", None)
    same("GPS fix type, h_acc, v_acc mm", ("gps_fix_type", "gps_h_acc_mm", "gps_v_acc_mm"), None)
    near("GPS time_usec minus boot clock, s", "gps_time_minus_boot_s", 0.3)  # two latest messages: a fix interval apart at most
    near("GPS new fixes/s (asked 10 Hz)", "gps_fix_hz", 1.0)
    same("SYS_STATUS pre-arm bit, sensors healthy", ("sys_status_prearm_bit", "sys_status_health_ok"), None)
    same("ESTIMATOR_STATUS flags; EKF_STATUS_REPORT sent", ("estimator_flags", "ekf_status_report"), None)
    same("requests, first upload of the session", "requests_first_upload", None)
    same("DO_SET_ROI(201) mode 3 stored as", "roi201_p1_back", None)
    same("MISSION_START 1.5 s after uploading DO_SET_ROI (0 = ACCEPTED)", "start_with_roi201", None)
    same("requests, next upload", "requests_next_upload", None)
    same("read back identical by fly's PX4 rules", "readback_identical", None)
    same("seq 0 is the first item (command)", "mission_seq0_command", None)
    same("frame 3 read back as; DO item frame", ("frame3_back", "do_frame_back"), None)
    same("z 2.5 read back", "z_back", None)
    same("yaw 236.57 read back (float32 radians)", "yaw_back", None)
    same("ROI command stored", "roi_command_back", None)
    same("MISSION_CURRENT.total (items uploaded)", "mission_total", None)
    same("modes from MISSION_START (* armed)", "modes_flown", None)
    # tolerances: the SITL's own spread over its runs (hold still 2.7-4.0 s for 3 s, descent 0.64-0.83 m/s, disarm 2.5-4.4 s
    # after touchdown, seen on a 1 Hz HEARTBEAT)
    near("airborne after MISSION_START, s", "airborne_after_start_s", 1.0)
    near("climb rate, m/s", "climb_rate_mps", 0.15, rel=True)
    for name in sitls[0]["holds"]:
        planned = sitls[0]["holds"][name]["planned_s"]
        # the SITL's own spread, still by the 1 s median speed: 3.0 s idle, 5.4 s beside two CPU hogs (a 3 s hold)
        near(f"hold {name} ({planned:g} s planned): still s", None, 2.0, get=lambda x, n=name: x["holds"][n]["still_s"])
        near(f"hold {name}: yaw error to the pole, deg", None, 3.0, get=lambda x, n=name: x["holds"][n]["yaw_err_deg"])
        near(f"hold {name}: first reached minus hold end, s", None, 0.5, get=lambda x, n=name: x["holds"][n].get("reached_minus_hold_end_s"))
    if sitls[0].get("leg1_top_mps") is not None:  # the full flight's legs
        near(f"leg 1 top speed ({SPEED_1:g} m/s planned)", "leg1_top_mps", 0.1, rel=True)
        near("leg 1 acceleration out of the hold, m/s^2", "leg1_accel_mps2", 0.25, rel=True)
        near("leg 1 duration (hold A end to B), s", "leg1_s", 0.2, rel=True)
        near("fly-through B: closest, m", "pass_b_miss_m", 0.3)
        near("fly-through B: speed there, m/s", "pass_b_speed_mps", 0.3)
        near(f"leg 2 top speed ({SPEED_2:g} m/s planned)", "leg2_top_mps", 0.1, rel=True)
    near("yaw rate (99th pct), deg/s", "max_yaw_rate_dps", 0.2, rel=True)
    same("MISSION_ITEM_REACHED seqs", "reached_seqs", None)
    near("reached repeats, period s", "reached_repeat_period_s", 0.1)
    near("reached repeats of the LAND item", None, 1.0, get=lambda x: x["reached_counts"].get(str(max(map(int, x["reached_counts"])))) if x["reached_counts"] else None)
    near("descent rate, m/s", "descent_rate_mps", 0.2, rel=True)
    near("landed from the LAND point, m", "land_miss_m", 1.0)
    near("disarm after touchdown, s", "disarm_after_touchdown_s", 1.5)
    near("flight, MISSION_START to disarm + 2 s, s", "flight_s", 0.1, rel=True)
    return out


def probe_sitl(scenario: Scenario = FULL, log=print) -> dict:
    from px4_sitl import Px4Sitl

    with Px4Sitl.start(HOME) as sitl:
        with sitl.netns():
            link = open_link(sitl.gcs_url)
        with link:
            return probe(link, scenario=scenario, log=log)


def probe_sim(speedup: float = 4.0, *, seed: int = 0, scenario: Scenario = FULL, log=print) -> dict:
    from dronecal_field.sim.vehicle import SimVehicle, VehicleConfig

    config = VehicleConfig(home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2], speedup=speedup, seed=seed, autopilot="px4")
    with SimVehicle(config, listen=["udp:127.0.0.1:0"]) as sim:
        url = sim.addresses()[0].replace("udp:", "udpout:")
        with open_link(url) as link:
            return probe(link, rate=speedup, scenario=scenario, log=log)
