"""ArduCopter's waypoint motion profile (AC_WPNav + SCurve, Copter 4.1 to 4.7), pure.

One implementation for the two places that need it: the simulated vehicle
(``sim.vehicle_flight``) flies its AUTO legs on it, and the planner
(``plan.route``) times routes with it, so planned and simulated flight times
agree by construction, and both follow the firmware (tests/test_sitl_conformance.py
compares with ArduCopter 4.7 SITL).

The firmware, as read from ArduPilot's ``libraries/AP_Math/SCurve.cpp`` and
``libraries/AC_WPNav/AC_WPNav.cpp`` (GPLv3; this is a re-statement of the
algorithm, not a copy of the code):

- Every straight leg is planned from rest to rest as a 23-segment S-curve:
  jerk rises and falls as a raised cosine (duration ``tj = J pi / (2 S)``),
  acceleration is bounded by WPNAV_ACCEL, speed by WPNAV_SPEED (or
  DO_CHANGE_SPEED), the vertical part by WPNAV_SPEED_UP / _DN and
  WPNAV_ACCEL_Z (``kinematic_limit``). The jerk is WPNAV_JERK (1 m/s^3) and
  the snap ``J pi / (2 ATC_INPUT_TC) / 2`` (AC_WPNav::calc_scurve_jerk_and_snap).
  With these defaults a 1 m leg's S-curve takes 3.6 s and peaks at 0.55 m/s:
  short legs never reach WPNAV_ACCEL.
- A fly-through ("fast") waypoint starts the next leg while this one brakes,
  at the first 400 Hz tick where the turn's mid point would be within
  WPNAV_RADIUS of the waypoint, slower than both legs' cruise, and need less
  than WPNAV_ACCEL_C (0 = 2 x WPNAV_ACCEL) horizontally and WPNAV_ACCEL_Z
  vertically (SCurve::advance_target_along_track); the waypoint counts as
  reached half way through that overlap.
- A waypoint with a hold is reached when its S-curve ends (the vehicle then
  within WPNAV_RADIUS), and the hold timer (NAV_WAYPOINT param 1, whole
  seconds) starts there: MISSION_ITEM_REACHED comes when it runs out.
- DO_CHANGE_SPEED re-plans the legs (SCurve::set_speed_max): a leg not yet
  started is planned afresh at the new speed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

LOOP_DT_S = 0.0025  # ArduCopter's main loop (400 Hz): the fly-through test runs once a tick

_SEG_ACCEL_END = 7
_SEG_SPEED_CHANGE_END = 14
_SEG_CONST = 15
_SEG_DECEL_END = 22
_N_SEGS = 23
_CONST, _INCR, _DECR = 0, 1, 2  # segment types: constant jerk, raised-cosine rise, raised-cosine fall


@dataclass(frozen=True)
class WpnavParams:
    """ArduCopter 4.7's waypoint-navigation parameters (defaults = the firmware's, read from SITL).

    Attributes
    ----------
    speed_mps : float
        Horizontal speed [WPNAV_SPEED 1000 cm/s]; DO_CHANGE_SPEED overrides it.
    speed_up_mps, speed_down_mps : float
        Climb and descent limits [WPNAV_SPEED_UP 250, WPNAV_SPEED_DN 150 cm/s].
    accel_mps2 : float
        Horizontal acceleration limit [WPNAV_ACCEL 250 cm/s^2].
    accel_z_mps2 : float
        Vertical acceleration limit [WPNAV_ACCEL_Z 100 cm/s^2].
    accel_c_mps2 : float
        Corner acceleration [WPNAV_ACCEL_C]; 0 = 2 x ``accel_mps2``.
    jerk_mps3 : float
        [WPNAV_JERK 1 m/s^3] (ATC_RATE_R_MAX / _P_MAX 0 leave it unlimited by the attitude rates).
    input_tc_s : float
        Attitude input time constant [ATC_INPUT_TC 0.15 s]: sets the snap.
    radius_m : float
        Waypoint radius [WPNAV_RADIUS 200 cm].
    """

    speed_mps: float = 10.0
    speed_up_mps: float = 2.5
    speed_down_mps: float = 1.5
    accel_mps2: float = 2.5
    accel_z_mps2: float = 1.0
    accel_c_mps2: float = 0.0
    jerk_mps3: float = 1.0
    input_tc_s: float = 0.15
    radius_m: float = 2.0

    @property
    def snap_mps4(self) -> float:
        """AC_WPNav::calc_scurve_jerk_and_snap: jerk x pi / (2 x input TC), halved (the angular-accel cap, 188 m/s^4, never binds)."""
        return 0.5 * self.jerk_mps3 * math.pi / (2.0 * max(self.input_tc_s, 0.1))

    @property
    def corner_accel_mps2(self) -> float:
        return self.accel_c_mps2 if self.accel_c_mps2 > 0 else 2.0 * self.accel_mps2


def kinematic_limit(unit: np.ndarray, max_xy: float, max_up: float, max_down: float) -> float:
    """The largest magnitude along direction ``unit`` (3,) ENU within a horizontal and an up/down limit (AP_Math)."""
    u = np.asarray(unit, float)
    n = float(np.linalg.norm(u))
    if n <= 0 or max_xy <= 0 or max_up <= 0 or max_down <= 0:
        return 0.0
    u = u / n
    xy = float(math.hypot(u[0], u[1]))
    if xy <= 1e-12:
        return max_up if u[2] > 0 else max_down
    if abs(u[2]) <= 1e-12:
        return max_xy
    slope = u[2] / xy
    limit_z = max_up if slope > 0 else max_down
    if abs(slope) < limit_z / max_xy:
        return max_xy / xy
    return abs(limit_z / u[2])


def _calculate_path(Sm: float, Jm: float, V0: float, Am: float, Vm: float, L: float) -> tuple[float, float, float, float, float]:
    """SCurve::calculate_path: (Jm, tj, t2, t4, t6) of one speed change from V0 towards Vm within length L."""
    zero = (0.0, 0.0, 0.0, 0.0, 0.0)
    if not (Sm > 0 and Jm > 0 and Am > 0 and Vm > 0 and L > 0) or V0 >= Vm:
        return zero
    tj = Jm * math.pi / (2.0 * Sm)
    At = min(Am, (Vm - V0) / (2.0 * tj), (L - 4.0 * V0 * tj) / (4.0 * tj * tj))
    if At <= 0:
        return zero
    sqrt = lambda x: math.sqrt(x) if x > 0 else 0.0  # noqa: E731 - AP's safe_sqrt

    def t4_of(Am: float, Jm: float, tj: float) -> float:
        root = sqrt(Am**4 / 4.0 + Jm * Jm * V0 * V0 + Am * Am * Jm * Jm * tj * tj / 4.0 + Am * Jm * Jm * L * 2.0
                    - Am * Am * Jm * V0 + Am**3 * Jm * tj / 2.0 - Am * Jm * Jm * V0 * tj)  # fmt: skip
        a = (Am * Am * -1.5 + root - Jm * V0 - Am * Jm * tj * 1.5) / (Am * Jm)
        b = (Am * Am * -1.5 - root - Jm * V0 - Am * Jm * tj * 1.5) / (Am * Jm)
        return max(min(-(V0 - Vm + Am * tj + Am * Am / Jm) / Am, max(a, b)), 0.0)

    if abs(At) < Jm * tj:
        if V0 == 0.0:
            tj = min(tj, ((L * math.pi) / (8.0 * Sm)) ** 0.25, ((Vm * math.pi) / (4.0 * Sm)) ** (1.0 / 3.0), sqrt((Am * math.pi) / (2.0 * Sm)))
            Jm = 2.0 * Sm * tj / math.pi
            Am = Jm * tj
        else:
            Am = At
            Jm = Am / tj
        if Vm <= V0 + 2.0 * Am * tj or L <= 4.0 * V0 * tj + 4.0 * Am * tj * tj:
            t2 = t4 = t6 = 0.0
        else:
            t2, t4, t6 = 0.0, t4_of(Am, Jm, tj), 0.0
    else:
        if Vm < V0 + Am * tj + Am * Am / Jm or L < 1.0 / (Jm * Jm) * (Am**3 + Am * Jm * (V0 * 2.0 + Am * tj * 2.0)) + V0 * tj * 2.0 + Am * tj * tj:
            q = Jm * Jm * tj * tj / 9.0 - Jm * V0 * 2.0 / 3.0
            p = -(Jm * Jm) * L / 2.0 + Jm**3 * tj**3 * 8.0 / 27.0 - Jm * tj * (Jm * Jm * tj * tj + Jm * V0 * 2.0) / 3.0 + Jm * Jm * V0 * tj
            r = sqrt(p * p - q**3)
            cube = lambda x: math.copysign(abs(x) ** (1.0 / 3.0), x) if x >= 0 else float("nan")  # noqa: E731 - powf of a negative is NaN
            c = cube(r - p)
            am_cubic = Jm * tj * (-2.0 / 3.0) + q / c + c if c and math.isfinite(c) else float("nan")
            s = sqrt((V0 * -4.0 + Vm * 4.0 + Jm * tj * tj) / Jm)
            Am = min(Am, max(Jm * (tj + s) * -0.5, Jm * (tj - s) * -0.5), am_cubic if math.isfinite(am_cubic) else Am)
            t2 = Am / Jm - tj
            t4 = 0.0
            t6 = t2
        else:
            t2 = Am / Jm - tj
            t4 = t4_of(Am, Jm, tj)
            t6 = t2
    out = (Jm, tj, t2, t4, t6)
    if not all(math.isfinite(v) and v >= -1e-12 for v in out):
        return (0.0, tj, 0.0, 0.0, 0.0)
    return (Jm, tj, max(t2, 0.0), max(t4, 0.0), max(t6, 0.0))


class SCurve:
    """One straight leg's jerk-limited speed profile (SCurve), along-track: time -> (distance, speed, acceleration).

    Build with :meth:`track`. ``t_s`` is the leg's own clock (0 = not started).
    """

    def __init__(self) -> None:
        self.t = np.zeros(_N_SEGS)  # segment end times, s
        self.kind = np.zeros(_N_SEGS, int)
        self.jerk = np.zeros(_N_SEGS)
        self.acc = np.zeros(_N_SEGS)
        self.vel = np.zeros(_N_SEGS)
        self.pos = np.zeros(_N_SEGS)
        self.n = 1
        self.snap_max = self.jerk_max = self.accel_max = self.vel_max = self.accel_z_max = 0.0
        self.length_m = 0.0
        self.origin = np.zeros(3)
        self.dest = np.zeros(3)
        self.unit = np.zeros(3)
        self.t_s = 0.0

    # ----- construction -----
    @classmethod
    def track(cls, origin: np.ndarray, dest: np.ndarray, speed_mps: float, p: WpnavParams) -> SCurve:
        """SCurve::calculate_track: a rest-to-rest leg from ``origin`` to ``dest`` (ENU m) at horizontal ``speed_mps``."""
        s = cls()
        s.origin = np.asarray(origin, float).copy()
        s.dest = np.asarray(dest, float).copy()
        delta = s.dest - s.origin
        length = float(np.linalg.norm(delta))
        if length <= 1e-9:
            return s
        s.unit = delta / length
        s.length_m = length
        s.snap_max, s.jerk_max = p.snap_mps4, p.jerk_mps3
        s.vel_max = kinematic_limit(delta, speed_mps, p.speed_up_mps, p.speed_down_mps)
        s.accel_max = kinematic_limit(delta, p.accel_mps2, p.accel_z_mps2, p.accel_z_mps2)
        s.accel_z_max = p.accel_z_mps2
        s._add_segments(length)
        return s

    def _set(self, i: int, t: float, kind: int, jerk: float, acc: float, vel: float, pos: float) -> int:
        self.t[i], self.kind[i], self.jerk[i], self.acc[i], self.vel[i], self.pos[i] = t, kind, jerk, acc, vel, pos
        return i + 1

    def _const_jerk(self, i: int, tj: float, J: float) -> int:
        T0, A0, V0, P0 = self.t[i - 1], self.acc[i - 1], self.vel[i - 1], self.pos[i - 1]
        if tj <= 0:
            return self._set(i, T0, _CONST, J, A0, V0, P0)
        return self._set(i, T0 + tj, _CONST, J, A0 + J * tj, V0 + A0 * tj + 0.5 * J * tj * tj, P0 + V0 * tj + 0.5 * A0 * tj * tj + J * tj**3 / 6.0)

    def _incr_jerk(self, i: int, tj: float, Jm: float) -> int:
        T0, A0, V0, P0 = self.t[i - 1], self.acc[i - 1], self.vel[i - 1], self.pos[i - 1]
        if tj <= 0:
            return self._set(i, T0, _CONST, 0.0, A0, V0, P0)
        beta, alpha = math.pi / tj, Jm * 0.5
        AT = alpha * tj
        VT = alpha * (tj * tj * 0.5 - 2.0 / beta**2)
        PT = alpha * (-tj / beta**2 + tj**3 / 6.0)
        return self._set(i, T0 + tj, _INCR, Jm, A0 + AT, V0 + A0 * tj + VT, P0 + V0 * tj + 0.5 * A0 * tj * tj + PT)

    def _decr_jerk(self, i: int, tj: float, Jm: float) -> int:
        T0, A0, V0, P0 = self.t[i - 1], self.acc[i - 1], self.vel[i - 1], self.pos[i - 1]
        if tj <= 0:
            return self._set(i, T0, _CONST, 0.0, A0, V0, P0)
        beta, alpha = math.pi / tj, Jm * 0.5
        AT = alpha * tj
        VT = alpha * (tj * tj * 0.5 - 2.0 / beta**2)
        PT = alpha * (-tj / beta**2 + tj**3 / 6.0)
        A2T, V2T = Jm * tj, Jm * tj * tj
        P2T = alpha * (-2.0 * tj / beta**2 + 4.0 / 3.0 * tj**3)
        return self._set(i, T0 + tj, _DECR, Jm, (A0 - AT) + A2T, (V0 - VT) + (A0 - AT) * tj + V2T,
                         (P0 - PT) + (V0 - VT) * tj + 0.5 * (A0 - AT) * tj * tj + P2T)  # fmt: skip

    def _jerk3(self, i: int, tj: float, Jm: float, tcj: float) -> int:
        i = self._incr_jerk(i, tj, Jm)
        i = self._const_jerk(i, tcj, Jm)
        return self._decr_jerk(i, tj, Jm)

    def _fill(self, first: int, last: int, src: int) -> None:
        for i in range(first, last + 1):
            self._set(i, self.t[src], _CONST, 0.0, 0.0, self.vel[src], self.pos[src])

    def _extend_const_vel_to(self, target: float) -> None:
        dP = max(0.0, target - self.pos[_SEG_DECEL_END])
        v = self.vel[_SEG_CONST]
        dt = dP / v if v > 0 else 0.0
        self.t[_SEG_CONST:] += dt
        self.pos[_SEG_CONST:] += dP

    def _add_segments(self, L: float) -> None:
        """SCurve::add_segments: accelerate, (no speed change), cruise, brake."""
        Jm, tj, t2, t4, t6 = _calculate_path(self.snap_max, self.jerk_max, 0.0, self.accel_max, self.vel_max, L * 0.5)
        i = self._set(0, 0.0, _CONST, 0.0, 0.0, 0.0, 0.0)
        i = self._jerk3(i, tj, Jm, t2)
        i = self._const_jerk(i, t4, 0.0)
        i = self._jerk3(i, tj, -Jm, t6)
        self.acc[_SEG_ACCEL_END] = 0.0
        for _ in range(_SEG_ACCEL_END + 1, _SEG_SPEED_CHANGE_END + 1):
            i = self._const_jerk(i, 0.0, 0.0)
        v = self.vel[_SEG_SPEED_CHANGE_END]
        t15 = max(0.0, (L - 2.0 * self.pos[_SEG_SPEED_CHANGE_END]) / v) if v > 0 else 0.0
        i = self._const_jerk(i, t15, 0.0)
        i = self._jerk3(i, tj, -Jm, t6)
        i = self._const_jerk(i, t4, 0.0)
        i = self._jerk3(i, tj, Jm, t2)
        self.acc[_SEG_DECEL_END] = 0.0
        self.vel[_SEG_DECEL_END] = 0.0
        self.n = i

    def set_speed(self, speed_mps: float, p: WpnavParams) -> None:
        """DO_CHANGE_SPEED on this leg (SCurve::set_speed_max).

        A leg not yet started is planned afresh. One under way keeps its
        course: ArduCopter rebuilds its speed-change segments, which this
        simplification leaves to the next leg (our missions change speed only
        at a stop, where the next leg has not started).
        """
        if self.length_m <= 0 or self.t_s > 0.0:
            return
        t_s = self.t_s
        fresh = SCurve.track(self.origin, self.dest, speed_mps, p)
        self.__dict__.update(fresh.__dict__)
        self.t_s = t_s

    # ----- reading -----
    @property
    def end_s(self) -> float:
        return self._lists()[0][_SEG_DECEL_END] if self.length_m > 0 else 0.0

    @property
    def accel_end_s(self) -> float:
        """SCurve::time_accel_end: when the acceleration to cruise ends."""
        return float(self.t[_SEG_ACCEL_END]) if self.length_m > 0 else 0.0

    @property
    def decel_start_s(self) -> float:
        """SCurve::time_decel_start: when the braking starts."""
        return float(self.t[_SEG_CONST]) if self.length_m > 0 else 0.0

    @property
    def peak_mps(self) -> float:
        return float(self.vel[_SEG_CONST]) if self.length_m > 0 else 0.0

    @property
    def unit_t(self) -> tuple[float, float, float]:
        if getattr(self, "_unit_src", None) is not self.unit:
            self._unit_src, self._unit_t = self.unit, tuple(float(c) for c in self.unit)
        return self._unit_t

    @property
    def origin_t(self) -> tuple[float, float, float]:
        if getattr(self, "_origin_src", None) is not self.origin:
            self._origin_src, self._origin_t = self.origin, tuple(float(c) for c in self.origin)
        return self._origin_t


    @property
    def remaining_s(self) -> float:
        return max(0.0, self.end_s - self.t_s)

    @property
    def finished(self) -> bool:
        return self.t_s >= self.end_s - 1e-9

    def advance(self, dt: float) -> None:
        self.t_s = min(self.t_s + dt, self.end_s)

    def _lists(self) -> tuple[list[float], ...]:
        if getattr(self, "_cache_n", -1) != self.n or self._cache_t0 is not self.t:
            self._py = (self.t.tolist(), self.kind.tolist(), self.jerk.tolist(), self.acc.tolist(), self.vel.tolist(), self.pos.tolist())
            self._cache_n, self._cache_t0 = self.n, self.t
        return self._py

    def state1(self, t_s: float) -> tuple[float, float, float]:
        """:meth:`state_at` for one time, in plain floats (the simulator and the planner call it every step)."""
        if self.length_m <= 0:
            return 0.0, 0.0, 0.0
        T, KIND, JERK, ACC, VEL, POS = self._lists()
        n = self.n
        t = min(max(float(t_s), 0.0), T[22])
        if t >= T[n - 1]:
            return self.length_m, 0.0, 0.0
        k = self._k if 1 <= getattr(self, "_k", 0) < n and T[self._k - 1] <= t else 1  # time moves forward: start from the last segment
        while k < n - 1 and T[k] <= t:
            k += 1
        self._k = k
        T0, A0, V0, P0 = T[k - 1], ACC[k - 1], VEL[k - 1], POS[k - 1]
        tj = T[k] - T0
        J = JERK[k]
        kind = KIND[k]
        x = t - T0
        if kind == _CONST or tj <= 0:
            A = A0 + J * x
            V = V0 + A0 * x + 0.5 * J * x * x
            P = P0 + V0 * x + 0.5 * A0 * x * x + J * x * x * x / 6.0
        else:
            alpha, beta = 0.5 * J, math.pi / tj
            b2 = beta * beta
            b3 = b2 * beta
            if kind == _INCR:
                sb, cb = math.sin(beta * x), math.cos(beta * x)
                A = A0 + alpha * x - alpha / beta * sb
                V = V0 + A0 * x + alpha * 0.5 * x * x + alpha / b2 * cb - alpha / b2
                P = P0 + V0 * x + 0.5 * A0 * x * x - alpha / b2 * x + alpha * x * x * x / 6.0 + alpha / b3 * sb
            else:
                AT = alpha * tj
                VT = alpha * (tj * tj * 0.5 - 2.0 / b2)
                PT = alpha * (-tj / b2 + tj * tj * tj / 6.0)
                y = x + tj
                sb, cb = math.sin(beta * y), math.cos(beta * y)
                A = (A0 - AT) + alpha * y - alpha / beta * sb
                V = (V0 - VT) + (A0 - AT) * x + 0.5 * alpha * y * y + alpha / b2 * cb - alpha / b2
                P = (P0 - PT) + (V0 - VT) * x + 0.5 * (A0 - AT) * x * x - alpha / b2 * y + alpha / 6.0 * y * y * y + alpha / b3 * sb
        return min(max(P, 0.0), self.length_m), max(V, 0.0), A

    def state_at(self, t_s: np.ndarray | float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(distance m, speed m/s, acceleration m/s^2) along the track at leg time(s) ``t_s`` (SCurve::get_jerk_accel_vel_pos_at_time)."""
        t = np.atleast_1d(np.asarray(t_s, float))
        if self.length_m <= 0:
            z = np.zeros_like(t)
            return z, z.copy(), z.copy()
        t = np.clip(t, 0.0, self.end_s)
        k = np.searchsorted(self.t[: self.n], t, side="right")  # first segment ending after t
        k = np.clip(k, 1, self.n - 1)
        after_end = t >= self.t[self.n - 1]
        T0, A0, V0, P0 = self.t[k - 1], self.acc[k - 1], self.vel[k - 1], self.pos[k - 1]
        tj = self.t[k] - T0
        J = self.jerk[k]
        kind = self.kind[k]
        x = t - T0
        # constant jerk
        A = A0 + J * x
        V = V0 + A0 * x + 0.5 * J * x * x
        P = P0 + V0 * x + 0.5 * A0 * x * x + J * x**3 / 6.0
        with np.errstate(divide="ignore", invalid="ignore"):
            alpha = 0.5 * J
            beta = np.where(tj > 0, math.pi / np.where(tj > 0, tj, 1.0), 0.0)
            b2 = np.where(beta > 0, beta * beta, 1.0)
            b3 = np.where(beta > 0, beta**3, 1.0)
            # raised-cosine rise
            Ai = A0 + alpha * x - alpha / np.where(beta > 0, beta, 1.0) * np.sin(beta * x)
            Vi = V0 + A0 * x + alpha * 0.5 * x * x + alpha / b2 * np.cos(beta * x) - alpha / b2
            Pi = P0 + V0 * x + 0.5 * A0 * x * x - alpha / b2 * x + alpha * x**3 / 6.0 + alpha / b3 * np.sin(beta * x)
            # raised-cosine fall
            AT = alpha * tj
            VT = alpha * (tj * tj * 0.5 - 2.0 / b2)
            PT = alpha * (-tj / b2 + tj**3 / 6.0)
            y = x + tj
            Ad = (A0 - AT) + alpha * y - alpha / np.where(beta > 0, beta, 1.0) * np.sin(beta * y)
            Vd = (V0 - VT) + (A0 - AT) * x + 0.5 * alpha * y * y + alpha / b2 * np.cos(beta * y) - alpha / b2
            Pd = (P0 - PT) + (V0 - VT) * x + 0.5 * (A0 - AT) * x * x - alpha / b2 * y + alpha / 6.0 * y**3 + alpha / b3 * np.sin(beta * y)
        incr = (kind == _INCR) & (tj > 0)
        decr = (kind == _DECR) & (tj > 0)
        A = np.where(incr, Ai, np.where(decr, Ad, A))
        V = np.where(incr, Vi, np.where(decr, Vd, V))
        P = np.where(incr, Pi, np.where(decr, Pd, P))
        P = np.where(after_end, self.length_m, np.clip(P, 0.0, self.length_m))
        V = np.where(after_end, 0.0, np.maximum(V, 0.0))
        A = np.where(after_end, 0.0, A)
        return P, V, A


def turn_start_s(this: SCurve, nxt: SCurve, p: WpnavParams) -> float | None:
    """Leg time of ``this`` at which ArduCopter starts ``nxt`` at a fly-through waypoint, or None (it stops there).

    The first 400 Hz tick, once this leg brakes and will end before the next
    one has finished accelerating, where the turn's mid point (both legs
    advanced half the remaining time) is within WPNAV_RADIUS of the waypoint,
    slower than both cruises, and under the corner and vertical acceleration
    limits (SCurve::advance_target_along_track).
    """
    if this.length_m <= 0 or nxt.length_m <= 0:
        return None
    first = max(this.decel_start_s, this.end_s - nxt.accel_end_s)
    if first >= this.end_s:
        return None
    t = np.arange(math.ceil(first / LOOP_DT_S - 1e-9), math.floor(this.end_s / LOOP_DT_S) + 1) * LOOP_DT_S
    t = t[(t >= first - 1e-12) & (t < this.end_s)]
    if len(t) == 0:
        return None
    half = 0.5 * (this.end_s - t)
    s1, v1, a1 = this.state_at(t + half)
    s2, v2, a2 = nxt.state_at(half)
    u1, u2 = this.unit, nxt.unit
    pos = (s1 - this.length_m)[:, None] * u1 + s2[:, None] * u2
    vel = v1[:, None] * u1 + v2[:, None] * u2
    acc = a1[:, None] * u1 + a2[:, None] * u2
    speed_min = min(this.vel_max, nxt.vel_max)
    ok = (
        (np.linalg.norm(pos, axis=1) < p.radius_m)
        & (np.linalg.norm(vel, axis=1) < speed_min)
        & (np.hypot(acc[:, 0], acc[:, 1]) < p.corner_accel_mps2)
        & (np.abs(acc[:, 2]) < min(this.accel_z_max, nxt.accel_z_max))
    )
    idx = np.flatnonzero(ok)
    return float(t[idx[0]]) if len(idx) else None


class WaypointTracker:
    """AC_WPNav's waypoint controller and the vehicle following it, stepped in time (mutable state).

    The target runs along the legs' S-curves (the leg before still braking,
    the next one started at a fly-through waypoint); the vehicle follows it
    through AC_PosControl's feedback (PSC_POSXY_P 1, PSC_VELXY_P 2) and a
    first-order lag of its acceleration (``LAG_XY_S``, the SITL airframe's
    lean response, fitted to the recorded 1 m legs: the vehicle peaks at
    0.53-0.56 m/s 1.8-1.9 s into the leg and is under 0.1 m/s for the last
    0.6-0.8 s before the hold starts). As in AC_WPNav::advance_wp_target_along_track,
    the S-curve clock runs slower while the vehicle lags its target: the rate
    ``clamp(0.05 + (v_along - kP x err_along) / |v_target|, 0, 1)``, low-passed
    with time constant WPNAV_ACCEL / WPNAV_JERK. That lag is what makes the
    firmware's legs 5-10 % longer than their bare S-curves (1 m: 3.8 s from
    rest, 3.9 s after a 3 s hold, as recorded, not 3.6 s; tests/test_sitl_conformance.py).

    Positions are ENU metres.
    """

    POS_P = 1.0  # PSC_POSXY_P (PSC_POSZ_P is 1 too)
    VEL_P = (2.0, 2.0, 5.0)  # PSC_VELXY_P, PSC_VELXY_P, PSC_VELZ_P
    # the firmware's velocity integrator (PSC_VELXY_I) pulls a vehicle that lags a stopped S-curve clock onto its
    # target; this follower has none, so the clock never stops entirely (a snappy WPNAV_JERK 10 copter stalled)
    MIN_RATE = 0.1
    LAG_XY_S = 0.1  # the horizontal acceleration's lag (leaning), s
    LAG_Z_S = 0.05  # thrust answers faster than a lean: the vertical lag, s
    MAX_STEP_S = 0.025  # the planner steps at this too: 2.5 % of a leg against 400 Hz, a third of the cost of 0.01 s

    def __init__(self, p: WpnavParams, pos: np.ndarray) -> None:
        self.p = p
        pos = np.asarray(pos, float)
        self.prev: SCurve | None = None
        self.leg: SCurve | None = None
        self.next: SCurve | None = None
        self.switch_s: float | None = None  # leg time of ``leg`` at which ``next`` starts
        self.dest = pos.copy()
        # plain-float state (the planner steps this a million times a plan); numpy views below
        self._tp, self._tv, self._ta = pos.tolist(), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]  # the target
        self._x, self._v, self._a = pos.tolist(), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]  # the vehicle
        self.scaler = 1.0  # AC_WPNav::_track_scalar_dt
        self._reported = True  # the current leg's arrival was reported (no leg yet: nothing to report)

    @property
    def pos(self) -> np.ndarray:
        """The vehicle's position (3,), ENU m."""
        return np.array(self._x)

    @property
    def vel(self) -> np.ndarray:
        return np.array(self._v)

    @property
    def target_pos(self) -> np.ndarray:
        return np.array(self._tp)

    @property
    def target_vel(self) -> np.ndarray:
        return np.array(self._tv)

    # ----- AC_WPNav::set_wp_destination / _next -----
    def start_leg(self, dest: np.ndarray, speed_mps: float) -> None:
        """Fly to ``dest``: continues the next leg if a fly-through already started it, else a new leg from the last destination."""
        dest = np.asarray(dest, float)
        if self.next is not None and self.next.t_s > 0.0 and bool(np.allclose(self.next.dest, dest, atol=1e-6)):
            self.prev, self.leg = self.leg, self.next
        else:
            self.prev = self.leg if self.leg is not None and not self.leg.finished else None
            self.leg = SCurve.track(self.dest, dest, speed_mps, self.p)
        self.dest = dest.copy()
        self._dest_t = dest.tolist()
        self.next, self.switch_s = None, None
        self._reported = False

    def set_next(self, dest: np.ndarray, speed_mps: float) -> None:
        """The waypoint after this one: this one becomes a fly-through ("fast") waypoint."""
        if self.leg is None:
            return
        nxt = SCurve.track(self.dest, np.asarray(dest, float), speed_mps, self.p)
        if nxt.length_m <= 0.01:
            return
        self.next, self.switch_s = nxt, turn_start_s(self.leg, nxt, self.p)

    def set_speed(self, speed_mps: float) -> None:
        """DO_CHANGE_SPEED: re-plans the legs not yet under way."""
        for leg in (self.leg, self.next):
            if leg is not None:
                leg.set_speed(speed_mps, self.p)
        if self.leg is not None and self.next is not None:
            self.switch_s = turn_start_s(self.leg, self.next, self.p)

    def hold_here(self) -> None:
        """Drop the legs: the target stays where the last one ended."""
        self.prev = self.leg = self.next = None
        self.switch_s = None

    # ----- stepping -----
    def step(self, dt: float) -> bool:
        """Advance ``dt`` seconds; True when the current leg's waypoint is reached (once per leg at most)."""
        reached = False
        n = max(1, math.ceil(dt / self.MAX_STEP_S - 1e-9))
        for _ in range(n):
            reached = self._substep(dt / n) or reached
        return reached

    def _substep(self, h: float) -> bool:
        p = self.p
        tp, tv = self._tp, self._tv
        x, v, a = self._x, self._v, self._a
        # the S-curve clock's rate from how well the vehicle keeps up (previous target)
        speed = math.sqrt(tv[0] * tv[0] + tv[1] * tv[1] + tv[2] * tv[2])
        rate = 1.0
        if speed > 0.0:
            err = ((tp[0] - x[0]) * tv[0] + (tp[1] - x[1]) * tv[1] + (tp[2] - x[2]) * tv[2]) / speed
            along = (v[0] * tv[0] + v[1] * tv[1] + v[2] * tv[2]) / speed
            rate = min(1.0, max(self.MIN_RATE, 0.05 + (along - self.POS_P * err) / speed))
        tc = p.accel_mps2 / p.jerk_mps3 if p.jerk_mps3 > 0 else 1.0
        self.scaler += (rate - self.scaler) * min(1.0, h / tc)
        reached = self._advance_target(self.scaler * h)
        tp, tv, ta = self._tp, self._tv, self._ta
        # the vehicle: position and velocity feedback, a lagged acceleration
        kp = self.POS_P
        for k in range(3):
            acc_cmd = ta[k] + self.VEL_P[k] * (tv[k] + kp * (tp[k] - x[k]) - v[k])
            lag = self.LAG_Z_S if k == 2 else self.LAG_XY_S
            a[k] += (acc_cmd - a[k]) * min(1.0, h / lag)
            v[k] += a[k] * h
            x[k] += v[k] * h
        return reached

    def _advance_target(self, dt: float) -> bool:
        leg = self.leg
        if leg is None:
            self._tp, self._tv, self._ta = self.dest.tolist(), [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
            return False
        o = leg.origin_t
        px, py, pz = o
        vx = vy = vz = ax = ay = az = 0.0
        prev = self.prev
        if prev is not None:
            prev.advance(dt)
            s, v, a = prev.state1(prev.t_s)
            s -= prev.length_m
            u = prev.unit_t
            px, py, pz = px + s * u[0], py + s * u[1], pz + s * u[2]
            vx, vy, vz = v * u[0], v * u[1], v * u[2]
            ax, ay, az = a * u[0], a * u[1], a * u[2]
            if prev.finished:
                self.prev = None
        before = leg.t_s
        leg.advance(dt)
        s, v, a = leg.state1(leg.t_s)
        u = leg.unit_t
        px, py, pz = px + s * u[0], py + s * u[1], pz + s * u[2]
        vx, vy, vz = vx + v * u[0], vy + v * u[1], vz + v * u[2]
        ax, ay, az = ax + a * u[0], ay + a * u[1], az + a * u[2]
        nxt = self.next
        if nxt is not None:
            if nxt.t_s > 0.0:
                nxt.advance(dt)
            elif self.switch_s is not None and leg.t_s >= self.switch_s - 1e-12:
                nxt.advance(max(1e-9, min(dt, leg.t_s - max(before, self.switch_s))))
            if nxt.t_s > 0.0:
                s, v, a = nxt.state1(nxt.t_s)
                u = nxt.unit_t
                px, py, pz = px + s * u[0], py + s * u[1], pz + s * u[2]
                vx, vy, vz = vx + v * u[0], vy + v * u[1], vz + v * u[2]
                ax, ay, az = ax + a * u[0], ay + a * u[1], az + a * u[2]
        self._tp, self._tv, self._ta = [px, py, pz], [vx, vy, vz], [ax, ay, az]
        if self._reported:
            return False
        if nxt is not None and nxt.t_s > 0.0:
            done = nxt.t_s >= leg.remaining_s  # a fly-through waypoint: reached half way through the turn
        else:  # a stop: the S-curve has ended and the vehicle is within WPNAV_RADIUS
            dst = self._dest_t
            d2 = (self._x[0] - dst[0]) ** 2 + (self._x[1] - dst[1]) ** 2 + (self._x[2] - dst[2]) ** 2
            done = leg.finished and d2 <= self.p.radius_m**2
        self._reported = done
        return done


_UNIT_CACHE: dict[tuple, tuple[tuple[float, ...], float]] = {}
_UNIT_CACHE_MAX = 20000


def _fly_unit(rel: np.ndarray, speeds: np.ndarray, p: WpnavParams, scaler: float, dt: float) -> tuple[tuple[float, ...], float]:
    """Fly from rest at the origin through ``rel`` (K, 3) (pass-through points, a stop at the last): reached times, end scaler."""
    key = (tuple(np.round(rel, 3).ravel()), tuple(np.round(speeds, 3)), round(scaler, 3), p, dt)
    hit = _UNIT_CACHE.get(key)
    if hit is not None:
        return hit
    tr = WaypointTracker(p, np.zeros(3))
    tr.scaler = scaler
    t = 0.0
    out = []
    K = len(rel)
    for j in range(K):
        tr.start_leg(rel[j], float(speeds[j]))
        if j < K - 1:
            tr.set_next(rel[j + 1], float(speeds[j + 1]))
        if tr.leg is None or tr.leg.length_m <= 1e-9:
            out.append(t)
            continue
        limit = t + 10.0 * tr.leg.end_s + 30.0
        while not tr.step(dt) and t < limit:
            t += dt
        t += dt
        out.append(t)
    result = (tuple(out), tr.scaler)
    if len(_UNIT_CACHE) >= _UNIT_CACHE_MAX:
        _UNIT_CACHE.clear()
    _UNIT_CACHE[key] = result
    return result


def path_timing(path: np.ndarray, stop: np.ndarray, speeds_mps: np.ndarray, p: WpnavParams, hold_s: np.ndarray | None = None,
                dt: float = 0.025) -> tuple[np.ndarray, float]:
    """When each point of a polyline is reached, flown from rest by :class:`WaypointTracker` (the simulator's flight).

    Parameters
    ----------
    path : (M, 3) ENU positions, m; at rest at ``path[0]``
    stop : (M,) bool; True where the vehicle stops (the last point always)
    speeds_mps : (M-1,) horizontal cruise commanded on each leg, m/s
    p : the navigation parameters
    hold_s : (M,) hold at each stop, s (None = 0); a hold's timer starts when its point is reached
    dt : time step, s

    Returns
    -------
    reached_s : (M,) time each point is reached (``reached_s[0]`` = 0): the
        end of its S-curve at a stop, the middle of the turn at a fly-through point
    total_s : time the last point is reached (its hold excluded)

    Each stretch from a stop to the next is flown from rest (the vehicle
    settles on a stop during its hold) and remembered: a grid of equal legs
    costs one simulation. During a hold the S-curve clock's rate relaxes
    back towards 1 (AC_WPNav keeps updating it with the target at rest).
    """
    P = np.asarray(path, float)
    M = len(P)
    reached = np.zeros(M)
    if M < 2:
        return reached, 0.0
    stops = np.asarray(stop, bool).copy()
    stops[-1] = True
    holds = np.zeros(M) if hold_s is None else np.asarray(hold_s, float)
    speeds = np.asarray(speeds_mps, float)
    tc = p.accel_mps2 / p.jerk_mps3 if p.jerk_mps3 > 0 else 1.0
    t, scaler, i = 0.0, 1.0, 0
    while i < M - 1:
        j = i + 1
        while not stops[j]:
            j += 1
        times, scaler = _fly_unit(P[i + 1 : j + 1] - P[i], speeds[i:j], p, scaler, dt)
        reached[i + 1 : j + 1] = t + np.asarray(times)
        t = float(reached[j])
        if j < M - 1 and holds[j] > 0:
            t += float(holds[j])
            scaler = 1.0 - (1.0 - scaler) * math.exp(-float(holds[j]) / tc)
        i = j
    return reached, float(reached[-1])
