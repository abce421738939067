"""The simulated copter's flight logic: modes, arming, mission execution, kinematics.

Pure state machine, no sockets: :class:`CopterModel` advances in fixed steps
of vehicle time and collects what a real ArduCopter would say (STATUSTEXT,
MISSION_ITEM_REACHED) in outboxes the MAVLink shell drains. Positions are
ENU metres relative to home on the ground; headings are degrees clockwise
from north (MAVLink's convention).

The behaviours copied from ArduCopter 4.7 SITL (shared/replays/arducopter-sitl
README, "Quirks seen") are marked ``# ArduCopter:`` where they happen.

AUTO waypoints are flown by :class:`dronecal_field.motion.WaypointTracker`,
ArduCopter's AC_WPNav + SCurve (jerk-limited legs, fly-through blending,
the S-curve clock slowed while the vehicle lags its target): the same code
``plan.route`` times flights with (docs/simulators.md, "Legs and holds").
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import missionfile as mf
from dronecal_field.motion import WaypointTracker, WpnavParams
from dronecal_field.mavlink.missionfile import MissionItem

GRAVITY_MPS2 = 9.80665


@dataclass(frozen=True)
class CopterParams:
    """Flight parameters (ArduCopter parameter names in brackets).

    Attributes
    ----------
    wp_speed_mps : float
        Horizontal waypoint speed [WPNAV_SPEED]; DO_CHANGE_SPEED overrides it.
    wp_accel_mps2 : float
        Horizontal acceleration limit of the S-curve legs [WPNAV_ACCEL 2.5 m/s^2];
        the jerk (below) keeps short legs far under it.
    wp_jerk_mps3 : float
        Jerk of the S-curve legs [WPNAV_JERK 1 m/s^3].
    input_tc_s : float
        Attitude input time constant [ATC_INPUT_TC 0.15 s]: the S-curve's snap.
    accel_z_mps2 : float
        Vertical acceleration limit on legs [WPNAV_ACCEL_Z 1 m/s^2].
    wp_settle_s : float
        Extra wait before the hold timer starts, s (0: ArduCopter starts it as
        the S-curve ends, the vehicle within WPNAV_RADIUS).
    wp_radius_m : float
        Waypoint radius: a corner's apex at most this far from a fly-through
        waypoint [WPNAV_RADIUS].
    corner_accel_mps2 : float or None
        Largest horizontal acceleration through a corner [WPNAV_ACCEL_C]; None
        = 2 x ``wp_accel_mps2`` (ArduCopter's default for WPNAV_ACCEL_C 0).
    descent_mps : float
        Descent rate on sloping legs [WPNAV_SPEED_DN].
    takeoff_climb_mps : float
        Mean climb rate during NAV_TAKEOFF (ArduCopter 4.7 SITL: 2 m in 2.7 s
        from lift-off, peaking at 1.2 m/s; complete 6.2 s after MISSION_START).
    climb_mps : float
        Climb rate for RTL and climbing legs [WPNAV_SPEED_UP].
    land_speed_mps, land_speed_high_mps : float
        Final and high descent rates [LAND_SPEED, LAND_SPEED_HIGH].
    land_alt_low_m : float
        Height where the final descent rate starts [LAND_ALT_LOW].
    rtl_alt_m, rtl_alt_min_m, rtl_cone_slope, rtl_loiter_s : float
        RTL climb target, its floor, cone slope and loiter above home [RTL_*].
    takeoff_approach_s : float
        Time constant of the take-off's slow-down into its altitude (recorded:
        1.9 m at +5.3 s, complete at +5.6 s after arming).
    spool_up_s : float
        Motor spool-up before the climb; with the 1 m/s climb the copter passes
        0.1 m 3.4 s after MISSION_START, as recorded.
    disarm_delay_s : float
        Armed on the ground without throttle -> disarm after this [DISARM_DELAY].
    landed_disarm_s : float
        Touchdown to "Disarming motors" (2 s in the recording).
    yaw_rate_dps : float
        Yaw rate limit in AUTO, degrees/second [ATC_SLEW_YAW 6000 cdeg/s].
    hover_drift_m : float
        Standard deviation of the wind-free hover wander per horizontal axis, metres.
    drift_tau_s : float
        Correlation time of the wander, seconds.
    """

    wp_speed_mps: float = 5.0
    wp_accel_mps2: float = 2.5
    wp_jerk_mps3: float = 1.0
    input_tc_s: float = 0.15
    accel_z_mps2: float = 1.0
    wp_settle_s: float = 0.0
    wp_radius_m: float = 2.0
    corner_accel_mps2: float | None = None
    descent_mps: float = 1.5
    takeoff_climb_mps: float = 0.8
    climb_mps: float = 2.5
    land_speed_mps: float = 0.5
    land_speed_high_mps: float = 1.5
    land_alt_low_m: float = 10.0
    rtl_alt_m: float = 15.0
    rtl_alt_min_m: float = 2.0
    rtl_cone_slope: float = 3.0
    rtl_loiter_s: float = 5.0
    takeoff_approach_s: float = 0.15
    spool_up_s: float = 3.3
    disarm_delay_s: float = 10.0
    landed_disarm_s: float = 2.0
    yaw_rate_dps: float = 60.0
    hover_drift_m: float = 0.007
    drift_tau_s: float = 2.0

    @property
    def wpnav(self) -> WpnavParams:
        """The waypoint-navigation parameters the legs are flown with (``dronecal_field.motion``)."""
        return WpnavParams(speed_mps=self.wp_speed_mps, speed_up_mps=self.climb_mps, speed_down_mps=self.descent_mps,
                           accel_mps2=self.wp_accel_mps2, accel_z_mps2=self.accel_z_mps2,
                           accel_c_mps2=self.corner_accel_mps2 or 0.0, jerk_mps3=self.wp_jerk_mps3,
                           input_tc_s=self.input_tc_s, radius_m=self.wp_radius_m)  # fmt: skip


def _wrap_deg(a: float) -> float:
    """Angle wrapped to [-180, 180) degrees."""
    return (a + 180.0) % 360.0 - 180.0


def bearing_deg(from_en: np.ndarray, to_en: np.ndarray) -> float:
    """Heading (deg clockwise from north) from one ENU point to another (first two components)."""
    d = np.asarray(to_en[:2], float) - np.asarray(from_en[:2], float)
    return math.degrees(math.atan2(d[0], d[1])) % 360.0


@dataclass
class _Nav:
    """The active navigation task."""

    phase: str = "idle"  # idle | spool | climb | goto | leg | hold | hover | rtl_climb | rtl_return | rtl_loiter | descend | touchdown
    target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    timer_s: float = 0.0
    hold_s: float = 0.0
    seq: int | None = None  # mission seq this task belongs to (AUTO), else None
    kind: str = ""  # takeoff | waypoint | rtl | land | guided
    fast: bool = False  # phase "leg": a fly-through waypoint (the tracker has the next leg)


class CopterModel:
    """An ArduCopter-like quadcopter for the simulator.

    Parameters
    ----------
    to_enu : callable
        ``to_enu(item) -> (3,) ENU metres or None`` for a mission item's
        position (``None`` = "here"); the shell binds it to the home position.
    params : CopterParams
        Flight parameters.
    rng : numpy.random.Generator
        Seeded noise source (hover wander).
    """

    def __init__(self, to_enu: Callable[[MissionItem], np.ndarray | None], params: CopterParams, rng: np.random.Generator) -> None:
        self.to_enu = to_enu
        self.p = params
        self.rng = rng
        self.time_s = 0.0
        self.pos = np.zeros(3)  # controller position (the "true" one without wander), ENU m
        self.vel = np.zeros(3)  # ENU m/s
        self.accel = np.zeros(3)
        self.drift = np.zeros(3)  # hover wander added to the reported position
        self.heading_deg = 353.0  # SITL's CMAC initial heading
        self.armed = False
        self.auto_armed = False  # ArduCopter: set by MISSION_START / guided takeoff, never by a bare mode change
        self.landed = True
        self.mode = ap.MODE_STABILIZE
        self.ready = False  # pre-arm checks pass (the shell sets it after boot)
        self.speed_mps = params.wp_speed_mps
        self.roi: np.ndarray | None = None
        self.yaw_fixed_deg: float | None = None  # CONDITION_YAW target, until the next waypoint starts
        self.items: list[MissionItem] = []
        self.current_seq = 0
        self.mission_state = ap.MISSION_STATE_NO_MISSION
        self._next_index = 1
        self._jumps_done: dict[int, int] = {}
        self._armed_ground_s = 0.0
        self.nav = _Nav()
        self.tracker: WaypointTracker | None = None  # AUTO waypoint legs (AC_WPNav), while flying them
        self.texts: list[tuple[int, str]] = []  # (severity, text) waiting to go out
        self.reached: list[int] = []  # MISSION_ITEM_REACHED seqs waiting to go out
        self._deferred_texts: list[tuple[int, str]] = []

    # ----- reported state -----
    @property
    def position(self) -> np.ndarray:
        """Reported ENU position (controller position plus hover wander), metres."""
        return self.pos + self.drift

    def say(self, text: str, severity: int = ap.SEVERITY_INFO) -> None:
        self.texts.append((severity, text))

    # ----- mission store -----
    def set_mission(self, items: list[MissionItem]) -> None:
        """Replace the stored mission (item 0 = home). A running mission keeps its place."""
        self.items = list(items)
        self._jumps_done.clear()
        if self.mode != ap.MODE_AUTO or self.nav.seq is None:
            self.current_seq = 0
            self.mission_state = ap.MISSION_STATE_NOT_STARTED if len(items) > 1 else ap.MISSION_STATE_NO_MISSION

    # ----- commands (return a MAV_RESULT) -----
    def arm(self) -> int:
        if self.armed:
            return ap.MAV_RESULT_ACCEPTED
        if not self.ready:
            self.say("PreArm: Need Position Estimate", ap.SEVERITY_CRITICAL)  # ArduCopter 4.7 before the EKF has a position
            return ap.MAV_RESULT_FAILED
        if self.mode == ap.MODE_AUTO:
            # ArduCopter: AUTO_OPTIONS 0 -> arming in AUTO is refused
            self.say("Arm: AUTO mode not armable", ap.SEVERITY_CRITICAL)
            return ap.MAV_RESULT_FAILED
        if self.mode in (ap.MODE_RTL, ap.MODE_LAND):
            self.say("Arm: Mode not armable", ap.SEVERITY_CRITICAL)
            return ap.MAV_RESULT_FAILED
        self.armed = True
        self.auto_armed = False
        self._armed_ground_s = 0.0
        self.say("Arming motors")
        return ap.MAV_RESULT_ACCEPTED

    def disarm(self, force: bool = False) -> int:
        if not self.armed:
            return ap.MAV_RESULT_ACCEPTED
        if not self.landed and not force:
            self.say("Disarm: not landed", ap.SEVERITY_CRITICAL)
            return ap.MAV_RESULT_FAILED
        self._do_disarm()
        if not self.landed:  # forced in the air: it falls
            self.pos[2] = 0.0
            self.vel[:] = 0.0
            self.landed = True
        return ap.MAV_RESULT_ACCEPTED

    def _do_disarm(self) -> None:
        self.armed = False
        self.auto_armed = False
        self.nav = _Nav()
        self.say("Disarming motors")

    def set_mode(self, mode: int) -> int:
        if mode not in ap.MODE_NAMES:
            return ap.MAV_RESULT_FAILED
        if mode == self.mode:
            return ap.MAV_RESULT_ACCEPTED
        if mode == ap.MODE_AUTO and len(self.items) <= 1:
            self.say("Mode change failed: no mission", ap.SEVERITY_WARNING)
            return ap.MAV_RESULT_FAILED
        self.mode = mode  # leaving AUTO keeps the mission's place; re-entering AUTO resumes it
        self._enter_mode(mode)
        return ap.MAV_RESULT_ACCEPTED

    def _enter_mode(self, mode: int) -> None:
        if mode == ap.MODE_AUTO:
            # ArduCopter: on the ground with zero throttle, AUTO does not take off (auto_armed stays
            # false) and the copter disarms itself after DISARM_DELAY; in the air it resumes.
            if not self.landed:
                self._resume_mission()
        elif mode in (ap.MODE_GUIDED, ap.MODE_LOITER, ap.MODE_STABILIZE):
            if not self.landed:
                self._hover_here()
        elif mode == ap.MODE_RTL:
            self._start_rtl(seq=None)
        elif mode == ap.MODE_LAND:
            self._start_land(None, seq=None)

    def mission_start(self) -> int:
        """MAV_CMD_MISSION_START: armed -> AUTO, auto_armed, start (or resume) the mission."""
        if not self.armed or len(self.items) <= 1:
            return ap.MAV_RESULT_FAILED
        if self.mode != ap.MODE_AUTO:
            self.mode = ap.MODE_AUTO
        self.auto_armed = True
        if self.mission_state != ap.MISSION_STATE_ACTIVE:
            self._start_mission()
        return ap.MAV_RESULT_ACCEPTED

    def guided_takeoff(self, alt_m: float) -> int:
        """MAV_CMD_NAV_TAKEOFF as a command: only armed, landed, in GUIDED."""
        if self.mode != ap.MODE_GUIDED or not self.armed or not self.landed:
            return ap.MAV_RESULT_FAILED
        self.auto_armed = True
        self._start_takeoff(max(alt_m, 0.5), seq=None)
        return ap.MAV_RESULT_ACCEPTED

    def guided_goto(self, target_enu: np.ndarray) -> bool:
        """SET_POSITION_TARGET_GLOBAL_INT in GUIDED while flying."""
        if self.mode != ap.MODE_GUIDED or self.landed or not self.armed:
            return False
        self.nav = _Nav(phase="goto", target=np.asarray(target_enu, float).copy(), kind="guided")
        return True

    # ----- mission execution -----
    def _start_mission(self) -> None:
        self._jumps_done.clear()
        self.mission_state = ap.MISSION_STATE_ACTIVE
        self._run_from(1)

    def _resume_mission(self) -> None:
        if self.mission_state == ap.MISSION_STATE_ACTIVE and 0 < self.current_seq < len(self.items):
            self._start_nav(self.current_seq)
        else:
            self._start_mission()

    def _run_from(self, index: int) -> None:
        """Start the next NAV item at or after ``index``, running DO items on the way."""
        while index < len(self.items):
            item = self.items[index]
            if item.command == mf.CMD_DO_JUMP:
                index = self._jump(index)
                continue
            if item.is_nav:
                self._start_nav(index)
                if item.command == mf.CMD_NAV_TAKEOFF:
                    # ArduCopter: DO items after a takeoff run only when the takeoff completes
                    self._next_index = index + 1
                else:
                    # DO items after a NAV item run as soon as it starts
                    j = index + 1
                    while j < len(self.items) and not self.items[j].is_nav and self.items[j].command != mf.CMD_DO_JUMP:
                        self._run_do(j)
                        j += 1
                    self._next_index = j
                return
            self._run_do(index)
            index += 1
        self._mission_complete()

    def _jump(self, index: int) -> int:
        item = self.items[index]
        target, repeat = int(item.p1), int(item.p2)
        done = self._jumps_done.get(index, 0)
        if (repeat < 0 or done < repeat) and 0 < target < len(self.items):
            self._jumps_done[index] = done + 1
            return target
        return index + 1

    def _name(self, item: MissionItem) -> str:
        return mf.COMMAND_NAMES.get(item.command, f"Cmd{item.command}")

    def _run_do(self, index: int) -> None:
        item = self.items[index]
        self.say(f"Mission: {index} {self._name(item)}")
        if item.command == mf.CMD_DO_CHANGE_SPEED:
            if item.p2 > 0:
                self.speed_mps = float(item.p2)
                self._replan_unstarted_legs()
        elif item.command in (mf.CMD_DO_SET_ROI, mf.CMD_DO_SET_ROI_LOCATION):
            target = self.to_enu(item)
            self.roi = None if target is None else np.asarray(target, float)
            self.yaw_fixed_deg = None
        elif item.command == mf.CMD_DO_SET_ROI_NONE:
            self.roi = None
        elif item.command == mf.CMD_CONDITION_YAW:
            base = self.heading_deg if item.p4 >= 1 else 0.0
            self.yaw_fixed_deg = (base + float(item.p1)) % 360.0
            self.roi = None
        self.reached.append(index)  # DO items are reported (README: seq 2 and 3 at 49.56 s)

    def _start_nav(self, index: int) -> None:
        item = self.items[index]
        self.current_seq = index
        self.say(f"Mission: {index} {self._name(item)}")
        if item.command == mf.CMD_NAV_TAKEOFF:
            self._deferred_texts.append((ap.SEVERITY_INFO, f"Mission: {index} {self._name(item)}"))  # ArduCopter prints it twice
            self._start_takeoff(self._item_alt(item), seq=index)
        elif item.command in (mf.CMD_NAV_WAYPOINT, mf.CMD_NAV_LOITER_TIME):
            self.yaw_fixed_deg = None  # ArduCopter resets a fixed yaw at each waypoint (an ROI stays)
            hold = item.hold_s if item.command == mf.CMD_NAV_WAYPOINT else max(0.0, item.p1)
            self.nav = self._waypoint_nav(index, self._item_target(item), hold)
        elif item.command == mf.CMD_NAV_RETURN_TO_LAUNCH:
            self._start_rtl(seq=index)
        elif item.command == mf.CMD_NAV_LAND:
            target = self.to_enu(item)
            self._start_land(None if target is None else target[:2], seq=index)
        else:  # NAV_DELAY and friends: nothing to fly
            self.nav = _Nav(phase="hover", target=self.pos.copy(), seq=index, kind="waypoint")
            self._nav_complete()

    def _waypoint_nav(self, index: int, target: np.ndarray, hold_s: float) -> _Nav:
        """The leg task for a NAV_WAYPOINT (AC_WPNav::set_wp_destination, and _next for a fly-through one).

        A waypoint that follows another waypoint keeps the tracker (the leg
        before may still be braking, a fly-through's next leg is already
        under way); after a take-off, hover or RTL the controller starts
        afresh where the vehicle is (wp_and_spline_init).
        """
        old = self.nav
        if self.tracker is None or old.kind != "waypoint" or old.phase not in ("leg", "hold"):
            self.tracker = WaypointTracker(self.p.wpnav, self.pos)
        self.tracker.start_leg(target, self.speed_mps)
        fast = False
        if hold_s <= 0.0:
            # ArduCopter (ModeAuto::do_nav_wp): no delay and a next NAV item with a position -> "fast" waypoint
            after = self._next_fast_target(index)
            if after is not None:
                self.tracker.set_next(after, self.speed_mps)
                fast = self.tracker.next is not None
        return _Nav(phase="leg", target=np.asarray(target, float).copy(), hold_s=hold_s, seq=index, kind="waypoint", fast=fast)

    def _next_fast_target(self, index: int) -> np.ndarray | None:
        """Position of the next NAV item if ArduCopter would fly through item ``index`` into it, else None.

        ArduCopter also flies through into a NAV_LAND with a position and into
        RTL; this simulator stops there (our missions put the last waypoint
        straight above the landing point, so that leg has no length anyway),
        and it stops before a DO_JUMP.
        """
        j = index + 1
        while j < len(self.items):
            item = self.items[j]
            if item.command == mf.CMD_DO_JUMP:
                return None
            if item.is_nav:
                if item.command in (mf.CMD_NAV_WAYPOINT, mf.CMD_NAV_LOITER_TIME) and (item.x != 0 or item.y != 0):
                    return self._item_target(item)
                return None
            j += 1
        return None

    def _replan_unstarted_legs(self) -> None:
        """A new speed (DO_CHANGE_SPEED) for the legs not yet under way."""
        if self.nav.phase == "leg" and self.tracker is not None:
            self.tracker.set_speed(self.speed_mps)

    def _item_alt(self, item: MissionItem) -> float:
        target = self.to_enu(item)
        return float(item.z) if target is None else float(target[2])

    def _item_target(self, item: MissionItem) -> np.ndarray:
        target = self.to_enu(item)
        if target is None:  # lat/lon 0: here, at the item's altitude
            return np.array([self.pos[0], self.pos[1], float(item.z)])
        return np.asarray(target, float)

    def _nav_complete(self) -> None:
        seq = self.nav.seq
        kind = self.nav.kind
        if seq is None:  # a GUIDED/RTL/LAND task outside the mission
            self._hover_here()
            return
        if kind == "takeoff":
            j = seq + 1
            dos = []
            while j < len(self.items) and not self.items[j].is_nav and self.items[j].command != mf.CMD_DO_JUMP:
                dos.append(j)
                j += 1
            if not dos:
                self.reached.append(seq)
            # ArduCopter: with DO items in the same tick only they are reported; the takeoff's
            # MISSION_ITEM_REACHED is overwritten (one pending "reached" per link)
            for k in dos:
                self._run_do(k)
            self._run_from(j)
            return
        self.reached.append(seq)
        self.say(f"Reached command #{seq}")
        self._run_from(self._next_index)

    def _mission_complete(self) -> None:
        self.mission_state = ap.MISSION_STATE_COMPLETE
        # ArduCopter: after the last item it hovers in AUTO until the mode changes
        if not self.landed:
            self._hover_here()
        else:
            self.nav = _Nav()

    # ----- navigation tasks -----
    def _hover_here(self) -> None:
        self.tracker = None
        self.nav = _Nav(phase="hover", target=self.pos.copy(), kind="guided")

    def _start_takeoff(self, alt_m: float, seq: int | None) -> None:
        self.tracker = None
        target = np.array([self.pos[0], self.pos[1], alt_m])
        if self.landed:
            self.nav = _Nav(phase="spool", target=target, seq=seq, kind="takeoff")
        elif self.pos[2] >= alt_m - 0.1:
            self.nav = _Nav(phase="climb", target=self.pos.copy(), seq=seq, kind="takeoff")
        else:
            self.nav = _Nav(phase="climb", target=target, seq=seq, kind="takeoff")

    def _start_rtl(self, seq: int | None) -> None:
        self.tracker = None
        if self.landed:
            self.nav = _Nav(phase="touchdown", target=self.pos.copy(), seq=seq, kind="rtl")
            return
        dist = float(np.hypot(self.pos[0], self.pos[1]))
        alt = max(self.p.rtl_alt_m, self.pos[2])
        if self.p.rtl_cone_slope > 0:
            alt = min(alt, max(dist * self.p.rtl_cone_slope, self.p.rtl_alt_min_m))
        alt = max(alt, float(self.pos[2]))
        self.nav = _Nav(phase="rtl_climb", target=np.array([self.pos[0], self.pos[1], alt]), seq=seq, kind="rtl")

    def _start_land(self, target_en: np.ndarray | None, seq: int | None) -> None:
        self.tracker = None
        if target_en is not None and float(np.hypot(*(np.asarray(target_en) - self.pos[:2]))) > 0.05:
            self.nav = _Nav(phase="goto", target=np.array([target_en[0], target_en[1], self.pos[2]]), seq=seq, kind="land")
        else:
            self.nav = _Nav(phase="descend", target=np.array([self.pos[0], self.pos[1], 0.0]), seq=seq, kind="land")

    # ----- time step -----
    def step(self, dt: float) -> None:
        """Advance vehicle time by ``dt`` seconds."""
        self.time_s += dt
        if self._deferred_texts:
            self.texts.extend(self._deferred_texts)
            self._deferred_texts.clear()
        vel_before = self.vel.copy()
        if self.armed:
            self._step_nav(dt)
        else:
            self.vel[:] = 0.0
        if self.armed and self.landed and not self.auto_armed:
            # ArduCopter: armed on the ground with zero throttle disarms after DISARM_DELAY
            self._armed_ground_s += dt
            if self._armed_ground_s >= self.p.disarm_delay_s:
                self._do_disarm()
        else:
            self._armed_ground_s = 0.0
        self.accel = (self.vel - vel_before) / dt
        self._step_drift(dt)
        self._step_yaw(dt)

    def _step_drift(self, dt: float) -> None:
        if self.landed:
            self.drift[:] = 0.0
            return
        tau = self.p.drift_tau_s
        sigma = np.array([self.p.hover_drift_m, self.p.hover_drift_m, self.p.hover_drift_m * 0.4])
        self.drift += -self.drift * (dt / tau) + sigma * math.sqrt(2.0 * dt / tau) * self.rng.standard_normal(3)

    def _step_yaw(self, dt: float) -> None:
        if self.landed:
            return
        here = self.position
        desired = None
        if self.yaw_fixed_deg is not None and self.nav.kind != "rtl":
            desired = self.yaw_fixed_deg
        elif self.roi is not None and self.nav.kind != "rtl":
            if float(np.hypot(*(self.roi[:2] - here[:2]))) > 0.3:
                desired = bearing_deg(here, self.roi)
        elif self.nav.phase in ("goto", "leg"):
            # WP_YAW_BEHAVIOR 2 (face the next waypoint, RTL aside): AC_PosControl points the nose along the
            # target velocity once it exceeds 5 % of the speed limit (calculate_yaw_and_rate_yaw)
            v = self.tracker.target_vel if (self.nav.phase == "leg" and self.tracker is not None) else self.vel
            if float(np.hypot(v[0], v[1])) > 0.05 * self.speed_mps:
                desired = math.degrees(math.atan2(v[0], v[1])) % 360.0
        if desired is None:
            return
        err = _wrap_deg(desired - self.heading_deg)
        limit = self.p.yaw_rate_dps * dt
        self.heading_deg = (self.heading_deg + max(-limit, min(limit, err))) % 360.0

    def _fly_to(self, target: np.ndarray, speed: float, dt: float) -> bool:
        """One S-curve leg to ``target`` from where the vehicle is (GUIDED goto, RTL's return, LAND's reposition); True on arrival."""
        tr = self.tracker
        if tr is None or not bool(np.allclose(tr.dest, target, atol=1e-6)):
            tr = self.tracker = WaypointTracker(self.p.wpnav, self.pos)
            tr.start_leg(target, speed)
        arrived = tr.step(dt)
        self.pos = tr.pos.copy()
        self.vel = tr.vel.copy()
        if arrived:
            self.tracker = None
        return arrived

    def _step_legs(self, dt: float) -> None:
        """Fly the AUTO waypoint legs: the tracker moves the target and the vehicle follows it."""
        nav = self.nav
        tr = self.tracker
        assert tr is not None
        reached = tr.step(dt)
        self.pos = tr.pos.copy()
        self.vel = tr.vel.copy()
        if nav.phase == "hold" or not reached:
            return
        if nav.fast:
            self._nav_complete()  # MISSION_ITEM_REACHED without stopping; the next waypoint takes the legs over
            return
        nav.phase = "hold"  # ArduCopter: the hold timer starts as the S-curve ends, the vehicle within WPNAV_RADIUS
        nav.timer_s = -self.p.wp_settle_s

    def _vertical(self, target_alt: float, rate: float, dt: float) -> bool:
        dz = target_alt - self.pos[2]
        if abs(dz) <= rate * dt:
            self.pos[2] = target_alt
            self.vel[:] = 0.0
            return True
        self.pos[2] += math.copysign(rate * dt, dz)
        self.vel = np.array([0.0, 0.0, math.copysign(rate, dz)])
        return False

    def _step_nav(self, dt: float) -> None:
        nav = self.nav
        p = self.p
        if nav.phase in ("idle",):
            self.vel[:] = 0.0
            return
        if nav.phase == "spool":
            nav.timer_s += dt
            self.vel[:] = 0.0
            if nav.timer_s >= p.spool_up_s:
                nav.phase = "climb"
                nav.timer_s = 0.0
                self.landed = False
            return
        if nav.phase == "climb":
            self.landed = False
            # ArduCopter's take-off slows into its altitude (recorded: 1.9 m at +5.3 s, complete at +5.6 s after arming)
            dz = float(nav.target[2]) - float(self.pos[2])
            rate = min(p.takeoff_climb_mps, max(0.05, abs(dz) / p.takeoff_approach_s))
            if abs(dz) < 0.01 or self._vertical(float(nav.target[2]), rate, dt):
                self.pos[2] = float(nav.target[2])
                self.vel[:] = 0.0
                self._nav_complete()
            return
        if nav.phase == "goto":
            speed = self.speed_mps if nav.kind != "guided" else p.wp_speed_mps
            if self._fly_to(nav.target, speed, dt):
                if nav.kind == "land":
                    nav.phase = "descend"
                    nav.target = np.array([self.pos[0], self.pos[1], 0.0])
                elif nav.kind == "waypoint":
                    nav.phase = "hold"  # ArduCopter: the hold timer starts when the target reaches the point
                    nav.timer_s = -p.wp_settle_s
                    self.tracker = None
                else:
                    self._hover_here()
            return
        if nav.phase == "leg":
            self._step_legs(dt)
            return
        if nav.phase == "hold":
            if self.tracker is not None and nav.kind == "waypoint" and bool(np.allclose(self.tracker.dest, nav.target, atol=1e-6)):
                self._step_legs(dt)  # the vehicle settles on the point as the timer runs
            else:
                self.vel[:] = 0.0
            nav.timer_s += dt
            if nav.timer_s >= nav.hold_s - 1e-9:
                self._nav_complete()  # ArduCopter: MISSION_ITEM_REACHED when the hold ENDS
            return
        if nav.phase == "hover":
            self.vel[:] = 0.0
            return
        if nav.phase == "rtl_climb":
            if self._vertical(float(nav.target[2]), p.climb_mps, dt):
                nav.phase = "rtl_return"
                nav.target = np.array([0.0, 0.0, self.pos[2]])
            return
        if nav.phase == "rtl_return":
            if self._fly_to(nav.target, p.wp_speed_mps, dt):
                nav.phase = "rtl_loiter"
                nav.timer_s = 0.0
            return
        if nav.phase == "rtl_loiter":
            self.vel[:] = 0.0
            nav.timer_s += dt
            if nav.timer_s >= p.rtl_loiter_s:
                nav.phase = "descend"
                nav.target = np.array([self.pos[0], self.pos[1], 0.0])
            return
        if nav.phase == "descend":
            rate = p.land_speed_high_mps if self.pos[2] > p.land_alt_low_m else p.land_speed_mps
            # the descent speeds up at WPNAV_ACCEL_Z (0.25 s to LAND_SPEED from a hover, as the replayed landings show)
            rate = min(rate, max(0.0, -float(self.vel[2])) + p.accel_z_mps2 * dt)
            if self._vertical(0.0, rate, dt):
                self.landed = True
                self.drift[:] = 0.0
                nav.phase = "touchdown"
                nav.timer_s = 0.0
                self.say(f"SIM Hit ground at {rate:.2f} m/s")
            return
        if nav.phase == "touchdown":
            self.vel[:] = 0.0
            nav.timer_s += dt
            if nav.timer_s >= p.landed_disarm_s:
                seq, kind = nav.seq, nav.kind
                # ArduCopter: the landing item completes, the copter disarms itself and stays in its mode.
                # An RTL item is reported reached and MISSION_CURRENT goes back to 0 (calib-grid-rtk.tlog);
                # a NAV_LAND is never reported: 4.7 disarms, rewinds the mission to item 1 ("Mission: 1
                # Takeoff", MISSION_CURRENT 1), as ArduCopter 4.7 SITL does (tests/test_sitl_conformance.py).
                if seq is not None and kind == "rtl":
                    self.reached.append(seq)
                    self.say(f"Reached command #{seq}")
                    self._do_disarm()
                    self.mission_state = ap.MISSION_STATE_COMPLETE
                    self.current_seq = 0
                elif seq is not None and kind == "land":
                    self._do_disarm()
                    self.mission_state = ap.MISSION_STATE_COMPLETE
                    if len(self.items) > 1:
                        self.say(f"Mission: 1 {mf.COMMAND_NAMES.get(self.items[1].command, self.items[1].command)}")
                    self.current_seq = 1
                else:
                    self._do_disarm()
            return
