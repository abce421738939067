"""The simulated vehicle as PX4 1.16 (SIH) behaves: ``sim vehicle --autopilot px4``.

:class:`Px4Vehicle` is :class:`~dronecal_field.sim.vehicle.SimVehicle` with
PX4's personality; ``SimVehicle(VehicleConfig(..., autopilot="px4"))``
builds one. Everything here was measured on PX4 1.16 SITL with SIH
(``../shared/sitl/px4-1.16``) by ``benchmarks/sim_px4_conformance.py``,
which runs the same probe on both and prints them side by side:

* HEARTBEAT: autopilot 12 (PX4), type 2, base_mode 29 (+128 armed),
  ``custom_mode`` = main << 16 | sub << 24; boot AUTO.LOITER, a mission
  AUTO.MISSION (kept after the landing, disarmed), RTL AUTO.RTL, LAND
  AUTO.LAND. Modes are asked with DO_SET_MODE(1, main, sub) or SET_MODE.
* Mission: seq 0 is the first item (no home item); a session's first upload
  is asked with MISSION_REQUEST, later ones with MISSION_REQUEST_INT (PX4's
  ``_int_mode``, set by the ground station's ``_INT`` messages); storage as
  PX4's ``format_mavlink_mission_item`` (:func:`px4_stored`): frame 3 reads
  back as 6 in int mode, altitude and params float32, a NAV item's yaw
  through float32 radians, DO items in frame 2, DO_SET_ROI (201) stored with
  mode 0 (ROI none: flown, it turns nothing). MISSION_START is DENIED ("Mission
  start denied! No valid mission") until the navigator has checked a new
  upload (1 s here; the SITL denied at once and accepted 1.5 s later).
  MISSION_CURRENT.total is 65535 with no mission.
* MISSION_START arms and starts in one command; arming in AUTO.MISSION
  starts the mission too. DO items run in sequence after the NAV item
  before them is reached (ArduCopter runs them as that item starts), so a
  DO_CHANGE_SPEED after a fly-through waypoint slows the next leg only.
* MISSION_ITEM_REACHED: for every item, NAV and DO, at the end of a hold,
  the last of a tick's items only (a hold followed by a DO_CHANGE_SPEED is
  never reported), repeated every second for 10 s or until the next; the
  LAND item when its descent starts.
* GPS_RAW_INT: fix type 3, h_acc 900 mm, v_acc 1780 mm, ``time_usec`` since
  boot, ~7.5 new fixes/s when asked for 10 Hz, white noise 0.2 m per
  horizontal axis and 0.5 m vertical (SIH's SensorGpsSim); with
  ``gnss="rtk"`` an RTK-fixed receiver instead (fix 6, the config's
  centimetre noise, h_acc 14 mm). ESTIMATOR_STATUS (flags 1023) instead of
  EKF_STATUS_REPORT; HIL_STATE_QUATERNION (SIH's truth) when asked.
* Flight (:class:`Px4Model`): take-off spool and climb, jerk-limited
  acceleration on legs, a corner speed at fly-through waypoints, the hold
  time as planned, the land speeds, "Disarmed by landing" 3.2 s after
  touchdown. Not modelled: in one SITL run of three the vehicle lingered ~7 s
  within 0.5 m of a fly-through waypoint before the next leg (53 s against 46).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from dronecal_field.geodesy import enu_to_geodetic
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import missionfile as mf
from dronecal_field.mavlink import px4
from dronecal_field.mavlink.missionfile import MissionItem, item_from_message
from dronecal_field.sim.vehicle import SimVehicle, VehicleConfig
from dronecal_field.sim.vehicle_flight import CopterModel, CopterParams, _Nav
from dronecal_field.sim.vehicle_mission import MissionServer

PX4_BOOT_S = 12.0  # SITL: GPS, home and a healthy EKF2 about 10-15 s after start
PX4_BASE_MODE = ap.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | 4 | 8 | 16  # custom, auto, guided, stabilize: 29 (SITL)
REACHED_REPEAT_S = 1.0  # measured 1.006 s
REACHED_REPEAT_FOR_S = 10.0  # 10-11 messages per item when nothing follows
MISSION_VALID_AFTER_S = 1.0  # navigator's feasibility check after an upload: DENIED until then (SITL: DENIED at once, ACCEPTED 1.5 s later)
PX4_GPS_RATE_MS = 133.0  # 7.5 new fixes/s when asked for 10 Hz (SITL)
SITL_GNSS = dict(gnss_sigma_h_m=0.2, gnss_sigma_v_m=0.5)  # SensorGpsSim: generate_wgn() * 0.2 / 0.5
SITL_ACC_MM = (900, 1780)  # GPS_RAW_INT h_acc, v_acc on the SITL (eph 0.9, epv 1.78)
RTK_ACC_MM = (14, 10)  # what a u-blox F9P reports in RTK fixed, for the rtk option
POSITION_COMMANDS = frozenset({16, 17, 18, 19, 21, 22, 195, 201})
_F32 = np.float32

# Streams PX4 sends on a GCS link without being asked (MAV_0_MODE normal; the SITL's faster rates
# for ATTITUDE and LOCAL_POSITION_NED, ~50 Hz, are capped at the simulator's 20 Hz tick)
DEFAULT_STREAMS_HZ: tuple[tuple[str, float], ...] = (
    ("SYS_STATUS", 1.0), ("GPS_RAW_INT", 1.0), ("GLOBAL_POSITION_INT", 20.0), ("ATTITUDE", 20.0),
    ("LOCAL_POSITION_NED", 20.0), ("HOME_POSITION", 0.5), ("BATTERY_STATUS", 0.5), ("ESTIMATOR_STATUS", 0.5),
    ("MISSION_CURRENT", 1.0), ("SYSTEM_TIME", 1.0),
)  # fmt: skip


def px4_params(speed_mps: float = 5.0) -> CopterParams:
    """PX4 1.16 SIH quad's flight, fitted to the SITL (benchmarks/sim_px4_conformance.py).

    Take-off: airborne 4.9 s after MISSION_START, climbing at 0.67-0.84 m/s;
    holds: the still time matches the plan; landing at 0.64-0.69 m/s, the
    last 0.5 m at 0.35 m/s, disarmed 3.2 s after touchdown (3.6-4.4 s seen, 1 Hz HEARTBEAT) (the land
    detector, then COM_DISARM_LAND 2 s); yaw up to ~60 deg/s (MPC_YAWRAUTO_MAX).
    """
    return CopterParams(wp_speed_mps=speed_mps, wp_accel_mps2=1.8, wp_settle_s=0.0, takeoff_climb_mps=0.77, climb_mps=3.0,
                        descent_mps=1.5, land_speed_mps=0.35, land_speed_high_mps=0.7, land_alt_low_m=0.5, spool_up_s=4.4,
                        disarm_delay_s=10.0, landed_disarm_s=3.2, yaw_rate_dps=60.0, hover_drift_m=0.05, drift_tau_s=3.0)  # fmt: skip


# ----- storage -----


def _yaw_back(deg: float) -> float:
    """A NAV item's yaw as PX4 keeps it: float32 radians wrapped to [0, 2 pi), read back in degrees (236.57 -> 236.56997680664062)."""
    if math.isnan(deg):
        return deg
    r = _F32(_F32(deg) * _F32(math.pi / 180.0))
    two_pi = _F32(2.0 * math.pi)
    while r < 0:
        r = _F32(r + two_pi)
    while r >= two_pi:
        r = _F32(r - two_pi)
    return float(_F32(r * _F32(_F32(180.0) / _F32(math.pi))))


def _f32(v: float) -> float:
    return float(_F32(v))


def px4_stored(item: MissionItem) -> MissionItem | None:
    """``item`` as PX4 1.16 stores it (read back in int mode), or None for a command it does not take.

    Position items keep lat/lon (1e-7 degree integers), a float32 altitude and
    only their command's params (WAYPOINT: hold, acceptance radius, yaw;
    TAKEOFF: yaw; LAND: precision, yaw); frame 3 becomes 6 and 0 becomes 5.
    DO items keep all seven params as float32 in frame 2. DO_SET_ROI (201)
    is stored with its ROI mode as 0 (measured).
    """
    cmd = int(item.command)
    if cmd in POSITION_COMMANDS and item.frame in mf.GLOBAL_FRAMES:
        relative = item.frame in (mf.FRAME_GLOBAL_RELATIVE_ALT, mf.FRAME_GLOBAL_RELATIVE_ALT_INT)
        p = [0.0, 0.0, 0.0, 0.0]
        if cmd == mf.CMD_NAV_WAYPOINT:
            p = [_f32(item.p1), _f32(item.p2), 0.0, _yaw_back(item.p4)]
        elif cmd == mf.CMD_NAV_TAKEOFF:
            p[3] = _yaw_back(item.p4)
        elif cmd == mf.CMD_NAV_LAND:
            p = [0.0, _f32(item.p2), 0.0, _yaw_back(item.p4)]
        elif cmd in (17, 19):
            p = [_f32(item.p1), _f32(item.p2), _f32(item.p3), _f32(item.p4) if cmd == 19 else _yaw_back(item.p4)]
        frame = mf.FRAME_GLOBAL_RELATIVE_ALT_INT if relative else mf.FRAME_GLOBAL_INT
        return replace(item, frame=frame, p1=p[0], p2=p[1], p3=p[2], p4=p[3], z=_f32(item.z))
    if cmd in POSITION_COMMANDS:
        return None  # a position command without a global frame: PX4 answers UNSUPPORTED_FRAME
    return replace(item, frame=2, p1=_f32(item.p1), p2=_f32(item.p2), p3=_f32(item.p3), p4=_f32(item.p4),
                   x=int(round(item.x)), y=int(round(item.y)), z=_f32(item.z))  # fmt: skip


def mission_valid(items: list[MissionItem]) -> bool:
    """PX4's feasibility as the simulator checks it: a mission (a DO_SET_ROI stored with mode 0 passes and flies without its ROI)."""
    return bool(items)


class Px4MissionServer(MissionServer):
    """PX4's side of the mission protocol: items from seq 0, ``_int_mode`` per link, PX4's storage.

    ``on_mission`` gets the model's view (a home item at 0, then the items
    shifted by one), so the flight model keeps ArduPilot's numbering inside.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._int_mode: dict[int, bool] = {}
        self.valid_from_s: float | None = None

    def stored_items(self) -> list[MissionItem]:
        return list(self.items)

    @property
    def count(self) -> int:
        return len(self.items)

    def _request(self, up: Any, now_s: float) -> None:
        if self._int_mode.get(id(up.link), False):
            self.send(up.link, self.enc.mission_request_int_encode(up.sysid, up.compid, up.next_seq, 0))
        else:
            self.send(up.link, self.enc.mission_request_encode(up.sysid, up.compid, up.next_seq, 0))
        up.last_request_s = now_s

    def _store(self, items: list[MissionItem], now_s: float) -> None:
        self.items = items
        self.valid_from_s = now_s + MISSION_VALID_AFTER_S
        self.on_mission([self.home_item(), *(replace(it, seq=it.seq + px4.SEQ_OFFSET) for it in items)])

    def handle(self, link: Any, msg: Any, now_s: float) -> bool:
        mtype = msg.get_type()
        if mtype in ("MISSION_ITEM_INT", "MISSION_REQUEST_INT"):
            self._int_mode[id(link)] = True
        elif mtype in ("MISSION_ITEM", "MISSION_REQUEST"):
            self._int_mode[id(link)] = False
        sysid, compid = msg.get_srcSystem(), msg.get_srcComponent()
        mission_type = getattr(msg, "mission_type", 0)
        if mtype == "MISSION_COUNT" and mission_type == 0:
            if self.upload is not None and self.upload.link is not link:
                self._ack(link, sysid, compid, ap.MAV_MISSION_DENIED)
            elif msg.count > self.max_items:
                self._ack(link, sysid, compid, ap.MAV_MISSION_NO_SPACE)
            elif msg.count == 0:
                self._store([], now_s)
                self._ack(link, sysid, compid, ap.MAV_MISSION_ACCEPTED)
            else:
                from dronecal_field.sim.vehicle_mission import _Upload

                self.upload = _Upload(link, sysid, compid, msg.count, 0, [], now_s, now_s)
                self._request(self.upload, now_s)
            return True
        if mtype in ("MISSION_ITEM_INT", "MISSION_ITEM") and mission_type == 0:
            up = self.upload
            if up is None or up.link is not link:
                if self._last_upload is not None and self._last_upload[0] is link and msg.seq == self._last_upload[1] - 1:
                    self._ack(link, sysid, compid, ap.MAV_MISSION_ACCEPTED)
                return True
            up.last_receive_s = now_s
            if msg.seq != up.next_seq:
                return True
            stored = px4_stored(item_from_message(msg))
            if stored is None:
                self.upload = None
                self._ack(link, sysid, compid, ap.MAV_MISSION_UNSUPPORTED_FRAME)
                return True
            up.items.append(stored)
            up.next_seq += 1
            if up.next_seq < up.count:
                self._request(up, now_s)
                return True
            self.upload = None
            self._last_upload = (link, up.count)
            self._store(up.items, now_s)
            self._ack(link, sysid, compid, ap.MAV_MISSION_ACCEPTED)
            return True
        if mtype in ("MISSION_REQUEST_INT", "MISSION_REQUEST") and mission_type == 0:
            if not 0 <= msg.seq < len(self.items):
                self._ack(link, sysid, compid, ap.MAV_MISSION_INVALID_SEQUENCE)
                return True
            it = self.items[msg.seq]
            if mtype == "MISSION_REQUEST_INT":
                out = self.enc.mission_item_int_encode(sysid, compid, it.seq, it.frame, it.command, 0, int(it.autocontinue),
                                                       it.p1, it.p2, it.p3, it.p4, it.x, it.y, it.z, 0)  # fmt: skip
            else:
                frame = {mf.FRAME_GLOBAL_RELATIVE_ALT_INT: mf.FRAME_GLOBAL_RELATIVE_ALT, mf.FRAME_GLOBAL_INT: mf.FRAME_GLOBAL}.get(it.frame, it.frame)
                x, y = (it.x * 1e-7, it.y * 1e-7) if it.frame in mf.GLOBAL_FRAMES else (float(it.x), float(it.y))
                out = self.enc.mission_item_encode(sysid, compid, it.seq, frame, it.command, 0, int(it.autocontinue),
                                                   it.p1, it.p2, it.p3, it.p4, x, y, it.z, 0)  # fmt: skip
            self.send(link, out)
            return True
        if mtype == "MISSION_CLEAR_ALL" and mission_type == 0:
            self._store([], now_s)
            self._ack(link, sysid, compid, ap.MAV_MISSION_ACCEPTED)
            return True
        return super().handle(link, msg, now_s)


# ----- flight -----


class Px4Model(CopterModel):
    """ArduCopter's model flown as PX4 flies a mission (file numbering inside; the shell shifts by one)."""

    corner_k_m2ps2 = 0.55  # v_corner^2 = k * tan(alpha / 2): 0.74 m/s through the SITL's 90 deg corner
    jerk_mps3 = 4.0  # MPC_JERK_AUTO
    speed_factor = 0.8  # legs topped at 0.8 of DO_CHANGE_SPEED on the SITL (1.57-1.60 of 2 m/s, 0.72-0.87 of 1 m/s)

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._accel_now = 0.0
        self._land_reported: int | None = None
        self.px4_texts: list[str] = []

    def say(self, text: str, severity: int = ap.SEVERITY_INFO) -> None:
        """ArduPilot's words are not PX4's: the shell says PX4's own (:attr:`px4_texts`)."""

    def step(self, dt: float) -> None:
        self._deferred_texts.clear()  # ArduCopter's second "Mission: 1 Takeoff"
        super().step(dt)

    def px4_say(self, text: str, severity: int = ap.SEVERITY_INFO) -> None:
        self.texts.append((severity, text))

    def _run_from(self, index: int) -> None:
        """PX4: DO items run in turn until a NAV item, which starts; the DO items after it wait until it is reached."""
        while index < len(self.items):
            item = self.items[index]
            if item.command == mf.CMD_DO_JUMP:
                index = self._jump(index)
                continue
            if item.is_nav:
                self._next_index = index + 1
                self._start_nav(index)
                return
            self._run_do(index)
            index += 1
        self._mission_complete()

    def _nav_complete(self) -> None:
        seq = self.nav.seq
        if seq is None:
            self._hover_here()
            return
        if self.nav.kind == "takeoff":
            self.px4_say("Takeoff detected")
        self.reached.append(seq)
        self._run_from(seq + 1)

    def _start_nav(self, index: int) -> None:
        item = self.items[index]
        if item.command == mf.CMD_NAV_WAYPOINT and (item.x != 0 or item.y != 0):
            self.current_seq = index
            target = self._item_target(item)
            exit_mps = self._corner_speed(index, target) if item.hold_s <= 0 else 0.0
            accept = float(item.p2) if item.p2 > 0 else 0.3
            self.nav = _Nav(phase="goto", target=target, hold_s=item.hold_s, seq=index, kind="px4wp")
            self.nav.timer_s = 0.0
            self._exit_mps, self._accept_m = exit_mps, accept
            return
        super()._start_nav(index)

    def _corner_speed(self, index: int, here: np.ndarray) -> float:
        """Speed through a fly-through waypoint: from the turn into the next position item (0 if none)."""
        j = index + 1
        while j < len(self.items) and not self.items[j].is_nav:
            j += 1
        if j >= len(self.items) or self.items[j].command not in (mf.CMD_NAV_WAYPOINT, mf.CMD_NAV_LAND):
            return 0.0
        nxt = self._item_target(self.items[j])
        a, b = here[:2] - self.pos[:2], nxt[:2] - here[:2]
        if np.linalg.norm(a) < 1e-3 or np.linalg.norm(b) < 1e-3:
            return 0.0
        turn = math.acos(max(-1.0, min(1.0, float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b))))))
        alpha = math.pi - turn  # the angle between the legs at the waypoint
        if alpha <= 1e-3:
            return 0.0
        return min(self.speed_mps, math.sqrt(self.corner_k_m2ps2 * math.tan(min(alpha, math.pi - 1e-3) / 2.0)))

    def _px4_goto(self, dt: float) -> None:
        """A leg towards ``nav.target``: jerk-limited acceleration, braking to the exit speed, the hold timer inside the acceptance radius."""
        nav = self.nav
        delta = nav.target - self.pos
        dist = float(np.linalg.norm(delta))
        hold = nav.hold_s > 0 or self._exit_mps <= 0
        if hold and dist <= 0.05:
            nav.timer_s += dt  # the still time at a hold matched the plan (SITL 3.0 s of 3, 2.7 of 2 after a slow creep in)
        if dist > 1e-3:
            direction = delta / dist
            v_now = float(np.linalg.norm(self.vel))
            self._accel_now = min(self.p.wp_accel_mps2, self._accel_now + self.jerk_mps3 * dt)
            brake = math.sqrt(self._exit_mps**2 + 2.0 * self.p.wp_accel_mps2 * 0.6 * dist)
            v = min(self.speed_mps * self.speed_factor, brake, v_now + self._accel_now * dt)
            if v < v_now:
                self._accel_now = 0.0
            step = v * dt
            if step < dist:
                self.pos = self.pos + direction * step
                self.vel = direction * v
                return
            self.pos = nav.target.copy()
        if not hold:
            self.vel = self.vel  # keep the speed through the corner: the next leg starts from it
            self._nav_complete()
            return
        self.vel[:] = 0.0
        self._accel_now = 0.0
        if nav.timer_s >= nav.hold_s - 1e-9:
            self._nav_complete()

    def _step_nav(self, dt: float) -> None:
        nav = self.nav
        if nav.kind == "px4wp" and nav.phase == "goto":
            self._px4_goto(dt)
            return
        was_armed, seq, kind = self.armed, nav.seq, nav.kind
        super()._step_nav(dt)
        if kind == "land" and self.nav.phase == "descend" and seq is not None and self._land_reported != seq:
            self._land_reported = seq  # PX4: the LAND item is "reached" when the descent starts
            self.reached.append(seq)
        if self.nav.phase == "touchdown" and self.nav.timer_s <= dt + 1e-9 and was_armed:
            self.px4_say("Landing detected")
        if was_armed and not self.armed and kind in ("land", "rtl"):
            self.current_seq = seq if seq is not None else self.current_seq  # PX4 keeps the last item current
            self.px4_say("Mission finished, landed")
            self.px4_say("Disarmed by landing")
            self._land_reported = None

    def _step_yaw(self, dt: float) -> None:
        if self.nav.kind == "px4wp" and self.roi is None and self.yaw_fixed_deg is None and not self.landed:
            if float(np.hypot(*(self.nav.target[:2] - self.pos[:2]))) > 1.0:  # MPC_YAW_MODE 0: towards the waypoint
                from dronecal_field.sim.vehicle_flight import _wrap_deg, bearing_deg

                err = _wrap_deg(bearing_deg(self.pos, self.nav.target) - self.heading_deg)
                limit = self.p.yaw_rate_dps * dt
                self.heading_deg = (self.heading_deg + max(-limit, min(limit, err))) % 360.0
            return
        super()._step_yaw(dt)


# ----- the shell -----


def _px4_mode_of(model: CopterModel) -> int:
    """HEARTBEAT.custom_mode PX4 shows for the model's mode."""
    main_sub = {ap.MODE_AUTO: "AUTO.MISSION", ap.MODE_RTL: "AUTO.RTL", ap.MODE_LAND: "AUTO.LAND"}.get(model.mode, "AUTO.LOITER")
    return px4.custom_mode(*px4.MODES[main_sub])


class Px4Vehicle(SimVehicle):
    """:class:`SimVehicle` speaking and flying as PX4 1.16 (module docstring)."""

    def __init__(self, config: VehicleConfig, listen: list[str], out: list[str] | None = None) -> None:
        rtk = getattr(config, "gnss", "auto") == "rtk"
        changes: dict[str, Any] = {} if rtk else dict(SITL_GNSS)
        if config.boot_s == VehicleConfig.boot_s:
            changes["boot_s"] = PX4_BOOT_S
        if config.gps_rate_ms == VehicleConfig.gps_rate_ms:
            changes["gps_rate_ms"] = PX4_GPS_RATE_MS
        if config.params == CopterParams():
            changes["params"] = px4_params()
        config = replace(config, **changes)
        super().__init__(config, listen, out)
        self.rtk = rtk
        self.acc_mm = RTK_ACC_MM if rtk else SITL_ACC_MM
        self.model = Px4Model(self._item_enu, config.params, self.rng)
        self.model.heading_deg = config.heading_deg
        self.mission = Px4MissionServer(self.enc, self._send_to, self._home_item, lambda: True, self.model.set_mission, self.model.say, config.max_items)
        self._heartbeat_mode = self.model.mode
        self._reached_pending: list[int] = []
        self._reached_last: tuple[int, float, float] | None = None  # (PX4 seq, first sent s, next repeat s)
        for conn in self.links:
            streams = self.streams[id(conn)]
            for name, hz in DEFAULT_STREAMS_HZ:
                streams.interval_s[name] = 1.0 / hz
                streams.next_due_s[name] = 0.0

    # ----- boot -----
    def _boot_sequence(self) -> list[tuple[float, str]]:
        b = self.config.boot_s
        return [(0.0, "banner"), (0.1 * b, "gps"), (0.3 * b, "origin"), (1.0 * b, "ready")]

    def _boot(self, now_s: float) -> None:
        while self._boot_steps and self._boot_steps[0][0] <= now_s:
            _, step = self._boot_steps.pop(0)
            if step == "banner":
                self.ekf_flags = 0
            elif step == "gps":
                self.fix_type = ap.GPS_FIX_TYPE_RTK_FIXED if getattr(self, "rtk", False) else 3
                self.ekf_flags = 0x0007
            elif step == "origin":
                self.home_set = True
            elif step == "ready":
                self.ekf_flags = 1023
                self.prearm_bit = True
                self.model.ready = True

    # ----- commands -----
    def _handle(self, link: Any, msg: Any) -> None:
        if msg.get_type() == "SET_MODE" and getattr(msg, "target_system", 0) in (0, self.config.sysid):
            self._active.add(id(link))
            main, sub = px4.split_mode(int(msg.custom_mode))
            result = self._set_px4_mode(main, sub)
            self._send_to(link, self.enc.command_ack_encode(11, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
            return
        super()._handle(link, msg)

    def _start_mission(self) -> int:
        m = self.model
        valid = mission_valid(self.mission.items) and self.mission.valid_from_s is not None and m.time_s >= self.mission.valid_from_s
        if not valid or not m.ready:
            m.px4_say("Mission start denied! No valid mission", ap.SEVERITY_CRITICAL)
            return ap.MAV_RESULT_DENIED
        if not m.armed:
            if m.mode == ap.MODE_AUTO:
                m.mode = ap.MODE_LOITER  # the ArduCopter model refuses arming in AUTO; PX4 arms in any auto mode
            if m.arm() != ap.MAV_RESULT_ACCEPTED:
                return ap.MAV_RESULT_DENIED
            m.px4_say("Armed by mission start")
        result = m.mission_start()
        if result == ap.MAV_RESULT_ACCEPTED:
            m.px4_say("Executing Mission")
            if m.landed and self.mission.items and self.mission.items[0].command == mf.CMD_NAV_TAKEOFF:
                m.px4_say(f"Climb to {self.mission.items[0].z:.1f} meters above home")
        return result

    def _set_px4_mode(self, main: int, sub: int) -> int:
        m = self.model
        if (main, sub) == px4.MODES["AUTO.MISSION"]:
            if not self.mission.items:
                return ap.MAV_RESULT_DENIED
            if m.armed:
                return self._start_mission() if m.landed else m.set_mode(ap.MODE_AUTO)
            m.mode = ap.MODE_AUTO  # disarmed: PX4 switches; arming then starts the mission
            return ap.MAV_RESULT_ACCEPTED
        target = {px4.MODES["AUTO.LOITER"]: ap.MODE_LOITER, px4.MODES["AUTO.RTL"]: ap.MODE_RTL, px4.MODES["AUTO.LAND"]: ap.MODE_LAND,
                  px4.MODES["POSCTL"]: ap.MODE_LOITER}.get((main, sub))  # fmt: skip
        if target is None:
            return ap.MAV_RESULT_DENIED
        if not m.armed and target in (ap.MODE_RTL, ap.MODE_LAND):
            return ap.MAV_RESULT_DENIED
        return m.set_mode(target)

    def _command(self, link: Any, msg: Any) -> int:
        cmd = int(msg.command)
        m = self.model
        if cmd == ap.CMD_MISSION_START:
            return self._start_mission()
        if cmd == ap.CMD_DO_SET_MODE:
            return self._set_px4_mode(int(msg.param2), int(msg.param3))
        if cmd == ap.CMD_COMPONENT_ARM_DISARM and msg.param1 >= 0.5 and not m.armed:
            if m.mode == ap.MODE_AUTO:
                return self._start_mission()  # PX4: armed in AUTO.MISSION, it takes off and flies the mission
            if not m.ready:
                return ap.MAV_RESULT_DENIED
            return m.arm()
        return super()._command(link, msg)

    # ----- GPS -----
    def _gps_step(self, now: float) -> None:
        """SIH's receiver: a fix every ``gps_rate_ms``, stamped when measured (the SITL's time_usec sat -0.05..+0.06 s
        from the boot clock of the position beside it; ArduPilot's u-blox is 104 ms late)."""
        self._history.append((now, self.model.position.copy()))
        del self._history[:-20]
        if now + 1e-9 < self._next_fix_s:
            return
        period = self.config.gps_rate_ms * 1e-3
        self._next_fix_s = math.ceil(now / period + 0.5) * period
        c = self.config
        noise = self.rng.standard_normal(3) * np.array([c.gnss_sigma_h_m, c.gnss_sigma_h_m, c.gnss_sigma_v_m])
        self._last_fix = (now, self.model.position.copy() + noise)

    # ----- reached messages -----
    def _broadcast_active(self, msg: Any) -> None:
        if msg.get_type() == "MISSION_ITEM_REACHED":
            self._reached_pending.append(int(msg.seq))
            return
        super()._broadcast_active(msg)

    def _tick(self, dt: float) -> None:
        super()._tick(dt)
        now = self.model.time_s
        if self._reached_pending:
            seq = self._reached_pending[-1] - px4.SEQ_OFFSET  # one mission_result per cycle: the tick's last item
            self._reached_pending.clear()
            self._reached_last = (seq, now, now)
        last = self._reached_last
        if last is not None and now + 1e-9 >= last[2]:
            seq, first, _due = last
            if now - first <= REACHED_REPEAT_FOR_S + 1e-9:
                super()._broadcast_active(self.enc.mission_item_reached_encode(seq))
                self._reached_last = (seq, first, last[2] + REACHED_REPEAT_S)
            else:
                self._reached_last = None

    # ----- messages -----
    def _build(self, name: str) -> Any | None:
        m = self.model
        c = self.config
        enc = self.enc
        if name == "HEARTBEAT":
            state = ap.MAV_STATE_ACTIVE if m.armed else ap.MAV_STATE_STANDBY
            base = PX4_BASE_MODE | (ap.MAV_MODE_FLAG_SAFETY_ARMED if m.armed else 0)
            return enc.heartbeat_encode(ap.MAV_TYPE_QUADROTOR, px4.MAV_AUTOPILOT_PX4, base, _px4_mode_of(m), state, 3)
        if name in ("SIMSTATE", "EKF_STATUS_REPORT"):
            return None  # PX4 has neither: HIL_STATE_QUATERNION and ESTIMATOR_STATUS instead
        if name == "MISSION_CURRENT":
            items = self.mission.items
            total = len(items) if items else 65535
            seq = max(0, m.current_seq - px4.SEQ_OFFSET) if items else 0
            return enc.mission_current_encode(seq, total, m.mission_state, 1 if m.mode == ap.MODE_AUTO else 0)
        if name == "GPS_RAW_INT":
            msg = super()._build(name)
            if msg is not None and self.fix_type >= 2:
                msg.h_acc, msg.v_acc = self.acc_mm
                msg.eph, msg.epv = (90, 178) if not self.rtk else (1, 1)
            return msg
        if name == "ESTIMATOR_STATUS":
            ok = self.ekf_flags == 1023
            ratio = 0.05 if ok else float("nan")
            return enc.estimator_status_encode(int(m.time_s * 1e6), self.ekf_flags, ratio, ratio, ratio, ratio, 0.0, 0.0,
                                               self.acc_mm[0] * 1e-3, self.acc_mm[1] * 1e-3)  # fmt: skip
        if name == "HIL_STATE_QUATERNION":
            if not self.home_set:
                return None
            pos = m.position
            lat, lon, h = enu_to_geodetic(pos, self.origin)[0]
            roll, pitch = self._roll_pitch_rad()
            yaw = math.radians(m.heading_deg)
            cr, sr, cp, sp, cy, sy = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2), math.cos(yaw / 2), math.sin(yaw / 2)
            q = [cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy]
            v = m.vel
            return enc.hil_state_quaternion_encode(
                int(m.time_s * 1e6), q, 0.0, 0.0, 0.0, int(round(lat * 1e7)), int(round(lon * 1e7)), int(round((h - c.geoid_sep_m) * 1000)),
                int(round(v[1] * 100)), int(round(v[0] * 100)), int(round(-v[2] * 100)), 0, 0, 0, 0, -1000,
            )  # fmt: skip
        if name == "AUTOPILOT_VERSION":
            return enc.autopilot_version_encode(0xFFFF, (1 << 24) | (16 << 16), 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, c.sysid, [0] * 18)
        return super()._build(name)
