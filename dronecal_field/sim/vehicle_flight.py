"""The simulated copter's flight logic: modes, arming, mission execution, kinematics.

Pure state machine, no sockets: :class:`CopterModel` advances in fixed steps
of vehicle time and collects what a real ArduCopter would say (STATUSTEXT,
MISSION_ITEM_REACHED) in outboxes the MAVLink shell drains. Positions are
ENU metres relative to home on the ground; headings are degrees clockwise
from north (MAVLink's convention).

The behaviours copied from ArduCopter 4.7 SITL (shared/replays/arducopter-sitl
README, "Quirks seen") are marked ``# ArduCopter:`` where they happen.

AUTO waypoints are flown on leg profiles (:class:`Leg`): a NAV_WAYPOINT with
hold 0 followed by another waypoint is flown through as ArduCopter's SCurve
blends two legs (docs/simulators.md, "Fly-through waypoints").
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import missionfile as mf
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
        Effective acceleration and braking on legs. ArduCopter's S-curve is
        jerk-limited [WPNAV_JERK 1 m/s^3, WPNAV_ACCEL 2.5 m/s^2], so short legs
        never reach WPNAV_ACCEL: fitted to the recorded ArduCopter 4.7 flight
        (shared/replays/arducopter-sitl: a 1 m leg peaks at 0.57 m/s, a 5 m leg
        at 1.36 m/s), the same value as ``plan.route.FlightModel.accel_m_s2``.
    wp_settle_s : float
        Time from the leg's end to the start of the hold timer (the vehicle
        lags the S-curve target; 0.5 s makes a 1 m leg + 3 s hold cycle 7.0 s,
        recorded 6.9-7.2 s).
    wp_radius_m : float
        Largest distance of a rounded corner's apex from a pass-through
        waypoint [WPNAV_RADIUS, 4.7: WP_RADIUS_M].
    corner_accel_mps2 : float or None
        Largest acceleration through a rounded corner [WPNAV_ACCEL_C]; None
        = 2 x ``wp_accel_mps2`` (ArduCopter's default for WPNAV_ACCEL_C 0).
    descent_mps : float
        Descent rate on sloping legs [WPNAV_SPEED_DN].
    takeoff_climb_mps : float
        Climb rate during NAV_TAKEOFF (about 1 m/s in the recording).
    climb_mps : float
        Climb rate for RTL and climbing legs [WPNAV_SPEED_UP].
    land_speed_mps, land_speed_high_mps : float
        Final and high descent rates [LAND_SPEED, LAND_SPEED_HIGH].
    land_alt_low_m : float
        Height where the final descent rate starts [LAND_ALT_LOW].
    rtl_alt_m, rtl_alt_min_m, rtl_cone_slope, rtl_loiter_s : float
        RTL climb target, its floor, cone slope and loiter above home [RTL_*].
    spool_up_s : float
        Motor spool-up before the climb; with the 1 m/s climb the copter passes
        0.1 m 3.4 s after MISSION_START, as recorded.
    disarm_delay_s : float
        Armed on the ground without throttle -> disarm after this [DISARM_DELAY].
    landed_disarm_s : float
        Touchdown to "Disarming motors" (2 s in the recording).
    yaw_rate_dps : float
        Yaw rate limit, degrees/second.
    hover_drift_m : float
        Standard deviation of the wind-free hover wander per horizontal axis, metres.
    drift_tau_s : float
        Correlation time of the wander, seconds.
    """

    wp_speed_mps: float = 5.0
    wp_accel_mps2: float = 0.33
    wp_settle_s: float = 0.5
    wp_radius_m: float = 2.0
    corner_accel_mps2: float | None = None
    descent_mps: float = 1.5
    takeoff_climb_mps: float = 1.0
    climb_mps: float = 2.5
    land_speed_mps: float = 0.5
    land_speed_high_mps: float = 1.5
    land_alt_low_m: float = 10.0
    rtl_alt_m: float = 15.0
    rtl_alt_min_m: float = 2.0
    rtl_cone_slope: float = 3.0
    rtl_loiter_s: float = 5.0
    spool_up_s: float = 3.3
    disarm_delay_s: float = 10.0
    landed_disarm_s: float = 2.0
    yaw_rate_dps: float = 90.0
    hover_drift_m: float = 0.007
    drift_tau_s: float = 2.0


def _wrap_deg(a: float) -> float:
    """Angle wrapped to [-180, 180) degrees."""
    return (a + 180.0) % 360.0 - 180.0


def bearing_deg(from_en: np.ndarray, to_en: np.ndarray) -> float:
    """Heading (deg clockwise from north) from one ENU point to another (first two components)."""
    d = np.asarray(to_en[:2], float) - np.asarray(from_en[:2], float)
    return math.degrees(math.atan2(d[0], d[1])) % 360.0


@dataclass
class Leg:
    """One straight mission leg flown on a time-symmetric speed profile.

    ArduCopter (AC_WPNav + SCurve, Copter 4.1+) plans every leg from rest to
    rest; a pass-through ("fast") waypoint is flown by starting the next leg's
    profile while this one brakes, the target being the sum of the two: on a
    straight continuation the braking and the accelerating halves add up to
    constant speed, at a turn of angle theta the apex speed is cruise x
    cos(theta / 2) and the corner is cut by at most WPNAV_RADIUS. The jerk-limited
    S-curve is modelled as a trapezoid (acceleration ``accel_mps2``).

    Attributes
    ----------
    origin, dest : (3,) ENU metres
    speed_mps : float
        Cruise along the track (m/s): the horizontal speed, or the climb /
        descent limit on steep legs, whichever binds.
    accel_mps2 : float
        Acceleration and braking along the track, m/s^2.
    t_s : float
        Time since the leg started, s (0 = not started).
    """

    origin: np.ndarray
    dest: np.ndarray
    speed_mps: float
    accel_mps2: float
    t_s: float = 0.0

    @classmethod
    def plan(cls, origin: np.ndarray, dest: np.ndarray, speed_h_mps: float, accel_mps2: float, climb_mps: float, descent_mps: float) -> "Leg":
        """A leg from ``origin`` to ``dest`` (ENU m) with ArduCopter's horizontal and vertical speed limits."""
        origin = np.asarray(origin, float).copy()
        dest = np.asarray(dest, float).copy()
        delta = dest - origin
        length = float(np.linalg.norm(delta))
        speed = speed_h_mps
        if length > 1e-9:
            u = delta / length
            h = float(np.hypot(u[0], u[1]))
            limits = [speed_h_mps / h] if h > 1e-9 else []
            vz = climb_mps if u[2] > 0 else descent_mps
            if abs(u[2]) > 1e-9:
                limits.append(vz / abs(u[2]))
            speed = min(limits)
        return cls(origin=origin, dest=dest, speed_mps=float(speed), accel_mps2=float(accel_mps2))

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(self.dest - self.origin))

    @property
    def unit(self) -> np.ndarray:
        L = self.length_m
        return (self.dest - self.origin) / L if L > 1e-9 else np.zeros(3)

    @property
    def peak_mps(self) -> float:
        """Speed reached: cruise, or less on a leg too short to reach it."""
        return min(self.speed_mps, math.sqrt(self.accel_mps2 * self.length_m))

    @property
    def ramp_s(self) -> float:
        """Duration of the acceleration (= the braking), s."""
        return self.peak_mps / self.accel_mps2

    @property
    def end_s(self) -> float:
        v = self.peak_mps
        if v <= 0.0:
            return 0.0
        return 2.0 * self.ramp_s + (self.length_m - v * v / self.accel_mps2) / v

    @property
    def decel_start_s(self) -> float:
        return self.end_s - self.ramp_s

    @property
    def remaining_s(self) -> float:
        return max(0.0, self.end_s - self.t_s)

    @property
    def finished(self) -> bool:
        return self.t_s >= self.end_s - 1e-9

    def state_at(self, t_s: float) -> tuple[float, float, float]:
        """(distance m, speed m/s, acceleration m/s^2) along the track at leg time ``t_s``."""
        a, v, L = self.accel_mps2, self.peak_mps, self.length_m
        tr, te = self.ramp_s, self.end_s
        if v <= 0.0 or t_s >= te:
            return L, 0.0, 0.0
        if t_s <= 0.0:
            return 0.0, 0.0, 0.0
        if t_s < tr:
            return 0.5 * a * t_s * t_s, a * t_s, a
        if t_s <= te - tr:
            return 0.5 * v * tr + v * (t_s - tr), v, 0.0
        tau = te - t_s
        return L - 0.5 * a * tau * tau, a * tau, -a


def corner_ok(this: Leg, nxt: Leg, wp_radius_m: float, corner_accel_mps2: float, accel_z_mps2: float) -> bool:
    """ArduCopter's test for starting the next leg now (SCurve::advance_target_along_track).

    The turn's mid point, if the next leg started now, must lie within
    ``wp_radius_m`` of the waypoint, be no faster than the slower leg's cruise
    and need no more than the corner acceleration (horizontal) and the
    vertical acceleration limit.
    """
    half = 0.5 * this.remaining_s
    s1, v1, a1 = this.state_at(this.t_s + half)
    s2, v2, a2 = nxt.state_at(half)
    u1, u2 = this.unit, nxt.unit
    pos = (s1 - this.length_m) * u1 + s2 * u2
    vel = v1 * u1 + v2 * u2
    acc = a1 * u1 + a2 * u2
    speed_min = min(this.speed_mps, nxt.speed_mps)
    return (
        float(np.linalg.norm(pos)) < wp_radius_m
        and float(np.linalg.norm(vel)) <= speed_min * (1.0 + 1e-6)
        and float(np.hypot(acc[0], acc[1])) < corner_accel_mps2
        and abs(float(acc[2])) < accel_z_mps2 * (1.0 + 1e-6)
    )


@dataclass
class _Nav:
    """The active navigation task."""

    phase: str = "idle"  # idle | spool | climb | goto | leg | hold | hover | rtl_climb | rtl_return | rtl_loiter | descend | touchdown
    target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    timer_s: float = 0.0
    hold_s: float = 0.0
    seq: int | None = None  # mission seq this task belongs to (AUTO), else None
    kind: str = ""  # takeoff | waypoint | rtl | land | guided
    # phase "leg" (AUTO waypoints): the leg being finished after a pass-through, this one, the next one
    prev_leg: Leg | None = None
    leg: Leg | None = None
    next_leg: Leg | None = None  # set when this waypoint is a pass-through ("fast") one


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

    def _plan_leg(self, origin: np.ndarray, dest: np.ndarray) -> Leg:
        p = self.p
        return Leg.plan(origin, dest, self.speed_mps, p.wp_accel_mps2, p.climb_mps, p.descent_mps)

    def _waypoint_nav(self, index: int, target: np.ndarray, hold_s: float) -> _Nav:
        """The leg task for a NAV_WAYPOINT: carries on a pass-through already under way, plans the next leg if this one is one."""
        old = self.nav
        if old.phase == "leg" and old.next_leg is not None and old.next_leg.t_s > 0.0 and bool(np.allclose(old.next_leg.dest, target, atol=1e-6)):
            # ArduCopter: past the apex of a pass-through the next leg becomes this leg, the old one finishes its braking
            prev, leg = old.leg, old.next_leg
        else:
            prev, leg = None, self._plan_leg(self.pos, target)
        nxt = None
        if hold_s <= 0.0:
            # ArduCopter (ModeAuto::do_nav_wp): no delay and a next NAV item with a position -> "fast" waypoint
            after = self._next_fast_target(index)
            if after is not None:
                candidate = self._plan_leg(target, after)
                if candidate.length_m > 0.01:
                    nxt = candidate
        return _Nav(phase="leg", target=np.asarray(target, float).copy(), hold_s=hold_s, seq=index, kind="waypoint", prev_leg=prev, leg=leg, next_leg=nxt)

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
        """A new speed (DO_CHANGE_SPEED) for the legs not yet under way (ArduCopter re-plans the current one too)."""
        nav = self.nav
        if nav.phase != "leg":
            return
        if nav.leg is not None and nav.leg.t_s == 0.0 and nav.prev_leg is None:
            nav.leg = self._plan_leg(nav.leg.origin, nav.leg.dest)
        if nav.next_leg is not None and nav.next_leg.t_s == 0.0:
            nav.next_leg = self._plan_leg(nav.next_leg.origin, nav.next_leg.dest)

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
        self.nav = _Nav(phase="hover", target=self.pos.copy(), kind="guided")

    def _start_takeoff(self, alt_m: float, seq: int | None) -> None:
        target = np.array([self.pos[0], self.pos[1], alt_m])
        if self.landed:
            self.nav = _Nav(phase="spool", target=target, seq=seq, kind="takeoff")
        elif self.pos[2] >= alt_m - 0.1:
            self.nav = _Nav(phase="climb", target=self.pos.copy(), seq=seq, kind="takeoff")
        else:
            self.nav = _Nav(phase="climb", target=target, seq=seq, kind="takeoff")

    def _start_rtl(self, seq: int | None) -> None:
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
        elif self.nav.phase in ("goto", "leg") and float(np.hypot(*(self.nav.target[:2] - self.pos[:2]))) > 1.0:
            desired = bearing_deg(self.pos, self.nav.target)  # WP_YAW_BEHAVIOR 2: face the next waypoint
        if desired is None:
            return
        err = _wrap_deg(desired - self.heading_deg)
        limit = self.p.yaw_rate_dps * dt
        self.heading_deg = (self.heading_deg + max(-limit, min(limit, err))) % 360.0

    def _move_towards(self, target: np.ndarray, speed: float, accel: float, dt: float) -> bool:
        """Straight-line move with accel/brake limits; True on arrival."""
        delta = target - self.pos
        dist = float(np.linalg.norm(delta))
        if dist < 1e-3:
            self.pos = target.copy()
            self.vel[:] = 0.0
            return True
        direction = delta / dist
        v_now = float(np.dot(self.vel, direction))
        v = min(speed, math.sqrt(2.0 * accel * dist), max(0.0, v_now) + accel * dt)
        step = v * dt
        if step >= dist:
            self.pos = target.copy()
            self.vel[:] = 0.0
            return True
        self.pos = self.pos + direction * step
        self.vel = direction * v
        return False

    def _step_legs(self, dt: float) -> None:
        """Advance the leg profiles of an AUTO waypoint; the target is the sum of the legs under way."""
        nav = self.nav
        p = self.p
        leg = nav.leg
        assert leg is not None
        prev, nxt = nav.prev_leg, nav.next_leg
        if prev is not None:
            prev.t_s += dt
            if prev.finished:
                nav.prev_leg = prev = None
        leg.t_s = min(leg.t_s + dt, leg.end_s)
        done = leg.finished
        if nxt is not None:
            if nxt.t_s > 0.0:
                nxt.t_s += dt
            elif not done and leg.t_s >= leg.decel_start_s - 1e-9 and leg.remaining_s <= nxt.ramp_s + 1e-9:
                corner = p.corner_accel_mps2 if p.corner_accel_mps2 is not None else 2.0 * p.wp_accel_mps2
                if corner_ok(leg, nxt, p.wp_radius_m, corner, p.wp_accel_mps2):
                    # start it when the condition first held inside this step (ArduCopter checks at 400 Hz, we step at 20 Hz)
                    first_s = max(leg.decel_start_s, leg.end_s - nxt.ramp_s)
                    nxt.t_s = max(1e-9, min(dt, leg.t_s - first_s))
            if nxt.t_s > 0.0 and nxt.t_s >= leg.remaining_s:
                done = True  # ArduCopter: a fast waypoint is reached half way through the turn (SCurve)
        s1, v1, _ = leg.state_at(leg.t_s)
        u1 = leg.unit
        pos = leg.origin + s1 * u1
        vel = v1 * u1
        if prev is not None:
            s0, v0, _ = prev.state_at(prev.t_s)
            pos = pos - (prev.length_m - s0) * prev.unit
            vel = vel + v0 * prev.unit
        if nxt is not None and nxt.t_s > 0.0:
            s2, v2, _ = nxt.state_at(nxt.t_s)
            pos = pos + s2 * nxt.unit
            vel = vel + v2 * nxt.unit
        self.pos = pos
        self.vel = vel
        if not done:
            return
        if nxt is not None and nxt.t_s > 0.0:
            self._nav_complete()  # MISSION_ITEM_REACHED without stopping; the next waypoint takes the legs over
            return
        if prev is not None:
            return  # a short leg can end before the braking of the one before it: wait for it
        self.pos = leg.dest.copy()
        self.vel[:] = 0.0
        nav.phase = "hold"  # ArduCopter: the hold timer starts when the target reaches the point, the vehicle settling behind it
        nav.timer_s = -p.wp_settle_s if leg.length_m > 1e-6 else 0.0

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
                self.landed = False
            return
        if nav.phase == "climb":
            self.landed = False
            if self._vertical(float(nav.target[2]), p.takeoff_climb_mps, dt):
                self._nav_complete()
            return
        if nav.phase == "goto":
            speed = self.speed_mps if nav.kind != "guided" else p.wp_speed_mps
            if self._move_towards(nav.target, speed, p.wp_accel_mps2, dt):
                if nav.kind == "land":
                    nav.phase = "descend"
                    nav.target = np.array([self.pos[0], self.pos[1], 0.0])
                elif nav.kind == "waypoint":
                    nav.phase = "hold"  # ArduCopter: the hold timer starts when the target reaches the point
                    nav.timer_s = -p.wp_settle_s
                else:
                    self._hover_here()
            return
        if nav.phase == "leg":
            self._step_legs(dt)
            return
        if nav.phase == "hold":
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
            if self._move_towards(nav.target, p.wp_speed_mps, p.wp_accel_mps2, dt):
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
