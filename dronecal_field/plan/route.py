"""Point order, take-off point, keep-out detours and the flight-time model (pure, site frame).

Order: level by level from the lowest (one climb per level), back and forth
along Y within a level, rows along X; each level starts where the previous
one ended (the replayed SITL mission, shared/replays/arducopter-sitl).

Flight time is ArduCopter 4.7's own waypoint navigation, flown by
``dronecal_field.motion`` (the module the simulated vehicle flies with, so
planned and simulated times agree by construction): every leg a jerk-limited
S-curve (WPNAV_JERK 1 m/s^3, WPNAV_ACCEL, the DO_CHANGE_SPEED speed), its clock
slowed while the vehicle lags its target, as AC_WPNav does; a 1 m leg takes
3.8 s from rest and 3.9 s after a 3 s hold, so a 3 s hold cycle takes 6.9 s
(recorded 6.9-7.2 s); a pass-through
point (hold 0: NAV_WAYPOINT param 1 = 0 followed by another waypoint) starts
the next leg while this one brakes, once the turn's apex lies within
WPNAV_RADIUS and the corner needs less than WPNAV_ACCEL_C, so a straight run
of pass-through points is flown at constant cruise and only the points where
the drone holds cost an acceleration and a braking. Lift-off comes 3.4 s
after arming; NAV_LAND descends at LAND_SPEED 0.5 m/s below 10 m.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from dronecal_field.errors import PlanError
from dronecal_field.motion import WpnavParams, path_timing
from dronecal_field.sampling.design import through_speed_m_s  # noqa: F401  (the leg speed rule lives with the design)

if TYPE_CHECKING:  # strategies imports this module
    from dronecal_field.sampling.lattice import Limits


@dataclass(frozen=True)
class FlightModel:
    """ArduCopter timing: its parameters (defaults = ArduCopter 4.7's) and what the SITL replay measured; speeds m/s, times s."""

    speed_m_s: float = 1.5  # DO_CHANGE_SPEED
    accel_m_s2: float = 2.5  # WPNAV_ACCEL (short legs never reach it: the jerk binds)
    jerk_m_s3: float = 1.0  # WPNAV_JERK
    input_tc_s: float = 0.15  # ATC_INPUT_TC: the S-curve's snap and the vehicle's lag behind its target
    accel_z_m_s2: float = 1.0  # WPNAV_ACCEL_Z
    leg_overhead_s: float = 0.0  # extra time per stop before the hold timer starts (the firmware has none)
    hover_s: float = 3.0  # hold at every grid point (whole seconds)
    spool_up_s: float = 3.4  # arming (MISSION_START) to lift-off
    takeoff_climb_m_s: float = 0.8  # the firmware's shaped climb: 2 m in 2.7 s from lift-off (peak 1.2 m/s)
    land_speed_m_s: float = 0.5  # LAND_SPEED below LAND_ALT_LOW
    land_high_speed_m_s: float = 1.5  # WPNAV_SPEED_DN above LAND_ALT_LOW (10 m)
    land_detect_s: float = 2.0  # touchdown to disarm
    rtl_alt_m: float = 15.0  # RTL_ALT
    rtl_climb_m_s: float = 2.5  # WPNAV_SPEED_UP
    rtl_loiter_s: float = 5.0  # RTL_LOIT_TIME
    wp_radius_m: float = 2.0  # WPNAV_RADIUS: the farthest a rounded corner's apex lies from its point
    corner_accel_m_s2: float | None = None  # WPNAV_ACCEL_C; None = 2 x accel_m_s2 (ArduCopter's default)
    climb_m_s: float = 2.5  # WPNAV_SPEED_UP on sloping legs
    descent_m_s: float = 1.5  # WPNAV_SPEED_DN on sloping legs

    @property
    def wpnav(self) -> WpnavParams:
        """The navigation parameters ``dronecal_field.motion`` flies with."""
        return WpnavParams(speed_mps=self.speed_m_s, speed_up_mps=self.climb_m_s, speed_down_mps=self.descent_m_s,
                           accel_mps2=self.accel_m_s2, accel_z_mps2=self.accel_z_m_s2, accel_c_mps2=self.corner_accel_m_s2 or 0.0,
                           jerk_mps3=self.jerk_m_s3, input_tc_s=self.input_tc_s, radius_m=self.wp_radius_m)  # fmt: skip


@functools.lru_cache(maxsize=4096)
def _rest_to_rest_s(length_m: float, speed_m_s: float, hold_s: float, wpnav: WpnavParams) -> float:
    """A level leg between two holds of ``hold_s``, in a row of such legs (the S-curve clock then runs as it does on a grid)."""
    path = np.stack([np.arange(4) * length_m, np.zeros(4), np.zeros(4)], 1)
    reached, _total = path_timing(path, np.ones(4, bool), np.full(3, speed_m_s), wpnav, np.full(4, hold_s))
    return float(reached[3] - reached[2] - hold_s)


def leg_time_s(distance_m: np.ndarray | float, flight: FlightModel) -> np.ndarray:
    """Time (s) of level rest-to-rest legs (m) as ArduCopter flies them (``motion.WaypointTracker``), ``leg_overhead_s`` added; 0 for 0 m.

    Each leg is one of a row of such legs with ``flight.hover_s`` holds between
    them (a grid): after a short hold the S-curve clock still runs a little
    slow (a 1 m leg: 3.9 s here, 3.8 s from a long rest).
    """
    d = np.asarray(distance_m, float)
    wp = flight.wpnav
    hold = float(flight.hover_s)
    t = np.vectorize(lambda x: _rest_to_rest_s(round(float(x), 4), float(flight.speed_m_s), hold, wp) if x > 1e-6 else 0.0, otypes=[float])(d)
    return np.where(d > 1e-6, t + flight.leg_overhead_s, 0.0)


def path_reached_s(path: np.ndarray, stop: np.ndarray, speeds_m_s: np.ndarray, flight: FlightModel, hold_s: np.ndarray | None = None) -> np.ndarray:
    """When the drone reaches each point of a polyline flown from rest (M,), s; at a stop, when its hold timer starts.

    ``hold_s`` (M,) are the holds at the stops; ``flight.leg_overhead_s`` is
    added before every stop's hold timer. Flown by ``motion.path_timing``.
    """
    P = np.asarray(path, float)
    if len(P) < 2:
        return np.zeros(len(P))
    stops = np.asarray(stop, bool).copy()
    stops[-1] = True
    at_stop = stops & (np.arange(len(P)) > 0)
    holds = np.zeros(len(P)) if hold_s is None else np.where(stops, np.asarray(hold_s, float), 0.0)
    overhead = flight.leg_overhead_s * at_stop
    reached, _total = path_timing(P, stops, np.asarray(speeds_m_s, float), flight.wpnav, holds + overhead)
    return reached + overhead


def path_time_s(path: np.ndarray, stop: np.ndarray, speeds_m_s: np.ndarray, flight: FlightModel, hold_s: np.ndarray | None = None) -> float:
    """Time (s) to fly a polyline from rest, stopping only where ``stop`` says (holds excluded).

    Parameters
    ----------
    path : (M, 3) positions, m; the drone is at rest at ``path[0]``
    stop : (M,) bool; True where the drone stops (``stop[-1]`` is always taken as True)
    speeds_m_s : (M-1,) horizontal cruise commanded on each leg, m/s
    flight : timing model
    hold_s : (M,) holds at the stops, s, or None: they are not counted, but
        they let the S-curve clock recover between legs as it does in flight

    Flown by ``dronecal_field.motion`` (ArduCopter's AC_WPNav + SCurve), the
    same code as the simulated vehicle's legs.
    """
    P = np.asarray(path, float)
    if len(P) < 2:
        return 0.0
    stops = np.asarray(stop, bool).copy()
    stops[-1] = True
    reached = path_reached_s(P, stops, speeds_m_s, flight, hold_s)
    holds = 0.0 if hold_s is None else float(np.where(stops, np.asarray(hold_s, float), 0.0)[1:-1].sum())  # flown between the first and last point
    return float(reached[-1]) - holds


def takeoff_time_s(alt_m: float, flight: FlightModel) -> float:
    """Arming to the take-off altitude, s."""
    return flight.spool_up_s + alt_m / flight.takeoff_climb_m_s + 0.3


def descent_time_s(alt_m: float, flight: FlightModel) -> float:
    """Vertical landing from ``alt_m`` to disarm, s."""
    high = max(alt_m - 10.0, 0.0)
    return high / flight.land_high_speed_m_s + min(alt_m, 10.0) / flight.land_speed_m_s + flight.land_detect_s


def order_points(points: np.ndarray, start_corner: tuple[int, int] = (1, 1)) -> np.ndarray:
    """Flight order (indices) of site-frame points (N, 3): per level, rows along X, back and forth along Y.

    ``start_corner`` = (x_dir, y_dir): +1 starts the first level at the smallest
    X row / smallest Y, -1 at the largest. Levels go from low to high; each level
    reverses the X direction so it starts above where the last one ended.
    """
    pts = np.asarray(points, float)
    if len(pts) == 0:
        return np.zeros(0, int)
    x_dir, y_dir = start_corner
    z_key = np.round(pts[:, 2], 3)
    x_key = np.round(pts[:, 0], 3)
    order: list[int] = []
    for z in np.unique(z_key):
        level = np.nonzero(z_key == z)[0]
        rows = np.unique(x_key[level])[:: x_dir]
        for x in rows:
            row = level[x_key[level] == x]
            row = row[np.argsort(pts[row, 1] * y_dir, kind="stable")]
            order.extend(row.tolist())
            y_dir = -y_dir
        x_dir = -x_dir
    return np.asarray(order, int)


def _segment_clearance(a: np.ndarray, b: np.ndarray) -> tuple[float, np.ndarray]:
    """Horizontal distance of the origin from segment a-b (2D), and the closest point."""
    ab = b - a
    L2 = float(ab @ ab)
    s = 0.0 if L2 < 1e-12 else float(np.clip(-(a @ ab) / L2, 0.0, 1.0))
    c = a + s * ab
    return float(np.linalg.norm(c)), c


def detour(a: np.ndarray, b: np.ndarray, radius_m: float) -> list[np.ndarray]:
    """Intermediate points (each (3,)) that take the leg a -> b (site frame) around the keep-out circle.

    Empty when the straight leg stays ``radius_m`` from the pole. Otherwise the
    leg follows a polygon outside the circle on the side the leg passed, with
    heights interpolated between a and b.
    """
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    clearance, closest = _segment_clearance(a[:2], b[:2])
    if clearance >= radius_m - 1e-9 or radius_m <= 0:
        return []
    tha, thb = math.atan2(a[1], a[0]), math.atan2(b[1], b[0])
    sweep = (thb - tha + math.pi) % (2 * math.pi) - math.pi  # shortest way round
    mid = tha + sweep / 2.0
    if clearance > 1e-6:
        # go round on the side where the straight leg passed
        side = math.atan2(closest[1], closest[0])
        if math.cos(side - mid) < 0:
            sweep = sweep - math.copysign(2 * math.pi, sweep)
    n = max(2, int(math.ceil(abs(sweep) / math.radians(40.0))) + 1)
    step = sweep / (n - 1)
    r = radius_m / math.cos(abs(step) / 2.0) + 0.3  # chords stay outside the circle
    out = []
    for k in range(n):
        th = tha + k * step
        f = k / (n - 1)
        out.append(np.array([r * math.cos(th), r * math.sin(th), a[2] + f * (b[2] - a[2])]))
    return out


@dataclass(frozen=True, eq=False)
class Route:
    """The drone's path in the site frame, from take-off to landing.

    ``points`` (K, 3) are every position the mission commands after take-off (grid
    holds, detours, the point above the take-off point); ``kind`` (K,) is
    'grid' | 'detour' | 'home'; ``grid_index`` (K,) the index into the planned
    grid points (-1 for others); ``hold_s`` (K,) the holds in whole seconds
    (0 = flown through when another waypoint follows); ``speed_m_s`` (K,) the
    horizontal cruise commanded on the leg that arrives at each point;
    ``through`` (K,) True where the drone passes without stopping;
    ``reached_s`` (K,) when the drone gets to each point, s after arming.
    """

    takeoff_site: np.ndarray  # (3,) on the ground
    takeoff_alt_m: float  # above the take-off point
    points: np.ndarray  # (K, 3)
    kind: tuple[str, ...]
    grid_index: np.ndarray  # (K,)
    hold_s: np.ndarray  # (K,)
    end: str  # 'land' | 'rtl'
    flight_time_s: float
    path_length_m: float
    speed_m_s: np.ndarray | None = None  # (K,)
    through: np.ndarray | None = None  # (K,) bool
    reached_s: np.ndarray | None = None  # (K,) s after arming the drone reaches each point (a hold's timer starts then)

    @property
    def grid_order(self) -> np.ndarray:
        """Indices of the grid points in flight order."""
        return self.grid_index[self.grid_index >= 0]


def default_takeoff(vehicle: np.ndarray, order: np.ndarray, limits: Limits, clearance_m: float = 3.0) -> np.ndarray:
    """A take-off / landing point on the ground beside the grid, away from the pole (site frame (3,)).

    Tried in turn: beyond the first point along its row (so the first leg is a
    short sideways move with the camera's bearing well defined), then beyond
    the last point, then behind the far end of the grid; the first that is
    outside the keep-out, within the range and geofence wins.
    """
    v = np.asarray(vehicle, float)
    first, last = v[order[0]], v[order[-1]]
    y_lo, y_hi = v[:, 1].min(), v[:, 1].max()
    x_hi = v[:, 0].max()

    def beside(p: np.ndarray) -> np.ndarray:
        side = -1.0 if p[1] <= (y_lo + y_hi) / 2.0 else 1.0
        y = (y_lo - clearance_m) if side < 0 else (y_hi + clearance_m)
        return np.array([p[0], y, 0.0])

    candidates = [beside(first), beside(last), np.array([x_hi + clearance_m, 0.0, 0.0]), np.array([x_hi + clearance_m, y_lo, 0.0])]
    for c in candidates:
        if _allowed_ground(c, limits):
            return c
    raise PlanError("no take-off point beside the grid is outside the keep-out and inside the range/geofence: give --takeoff LAT,LON")


def _allowed_ground(p: np.ndarray, limits: Limits) -> bool:
    r = float(np.hypot(p[0], p[1]))
    if r < limits.keep_out_m:
        return False
    if limits.max_range_m is not None and r > limits.max_range_m:
        return False
    if limits.geofence_xy is not None:
        from matplotlib.path import Path as MplPath

        if not MplPath(np.asarray(limits.geofence_xy, float)).contains_point(p[:2]):
            return False
    return True


def plan_route(
    vehicle: np.ndarray,
    marker: np.ndarray,
    limits: Limits,
    flight: FlightModel,
    takeoff_site: np.ndarray | None = None,
    end: str = "land",
    hold_s: np.ndarray | None = None,
    ordered: bool = False,
    takeoff_alt_m: float | None = None,
    leg_speed_m_s: float | None = None,
) -> Route:
    """Order the points, add the take-off point and keep-out detours, and time the flight.

    Parameters
    ----------
    vehicle : (N, 3) drone positions of the points, site frame, m
    marker : (N, 3) marker centres (only for grouping into levels), m
    limits : ``sampling.lattice.Limits`` (keep-out, range, geofence)
    flight : timing model
    takeoff_site : (3,) take-off point on the ground, site frame; default beside the points
    end : 'land' (fly above the take-off point, NAV_LAND) or 'rtl'
    hold_s : (N,) hold per point, s, rounded to whole seconds (ArduCopter's
        NAV_WAYPOINT param 1); 0 = fly through without stopping (when another
        waypoint follows). None = ``flight.hover_s`` everywhere.
    ordered : True keeps the given order (designed legs); False orders the
        points level by level (``order_points``), starting nearest the take-off point
    takeoff_alt_m : NAV_TAKEOFF altitude above the take-off point; default max(2 m, first point)
    leg_speed_m_s : horizontal speed on the legs into, between and out of
        pass-through points (DO_CHANGE_SPEED at each stop where it changes);
        None = ``flight.speed_m_s`` everywhere

    Notes
    -----
    A run of pass-through points should start at a point where the drone
    holds (or at the take-off climb): the drone accelerates from there and
    keeps the leg speed through the run. Detours round the keep-out are
    flown through as well (hold 0), as ArduCopter does.
    """
    vehicle = np.asarray(vehicle, float)
    marker = np.asarray(marker, float)
    n = len(vehicle)
    holds_in = np.full(n, float(flight.hover_s)) if hold_s is None else np.asarray(hold_s, float).reshape(-1)
    if len(holds_in) != n:
        raise PlanError(f"hold_s has {len(holds_in)} values for {n} points: give one hold (s) per point")
    if np.any(holds_in < 0) or not np.all(np.isfinite(holds_in)):
        raise PlanError("hold_s has negative or non-finite holds: give 0 (fly through) or a hold in seconds per point")
    holds_in = np.round(holds_in)  # ArduCopter stores the hold as whole seconds
    if ordered:
        order = np.arange(n)
        takeoff = default_takeoff(vehicle, order, limits) if takeoff_site is None else np.asarray(takeoff_site, float).copy()
    elif takeoff_site is None:
        order = order_points(marker)
        takeoff = default_takeoff(vehicle, order, limits)
    else:
        takeoff = np.asarray(takeoff_site, float).copy()
        # start at the corner of the lowest level nearest the take-off point
        best = None
        for corner in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
            o = order_points(marker, corner)
            d = float(np.hypot(*(vehicle[o[0], :2] - takeoff[:2])))
            if best is None or d < best[0] - 1e-9:
                best = (d, o)
        order = best[1]
    if takeoff_alt_m is None:
        takeoff_alt_m = max(2.0, float(vehicle[order[0], 2]) - float(takeoff[2]))
    pts: list[np.ndarray] = []
    kinds: list[str] = []
    gidx: list[int] = []
    holds: list[float] = []

    def add_leg(to: np.ndarray, kind: str, index: int, hold: float) -> None:
        prev = pts[-1] if pts else np.array([takeoff[0], takeoff[1], takeoff[2] + takeoff_alt_m])
        for q in detour(prev, to, limits.keep_out_m):
            pts.append(q)
            kinds.append("detour")
            gidx.append(-1)
            holds.append(0.0)
        pts.append(np.asarray(to, float))
        kinds.append(kind)
        gidx.append(index)
        holds.append(hold)

    for i in order:
        add_leg(vehicle[i], "grid", int(i), float(holds_in[i]))
    if end == "land":
        add_leg(np.array([takeoff[0], takeoff[1], pts[-1][2]]), "home", -1, 0.0)
    P = np.asarray(pts)
    H = np.asarray(holds, float)
    G = np.asarray(gidx, int)
    start = np.array([takeoff[0], takeoff[1], takeoff[2] + takeoff_alt_m])
    path = np.concatenate([start[None], P])
    legs = np.linalg.norm(np.diff(path, axis=0), axis=1)
    # the drone flies through a hold-0 point when a waypoint with some length follows (the last one precedes LAND/RTL)
    next_len = np.append(legs[1:], 0.0)
    through = (H <= 0.0) & (next_len > 0.01)
    through[-1] = False
    # leg speed on the legs that arrive at or leave a pass-through grid point
    speeds = np.full(len(P), float(flight.speed_m_s))
    if leg_speed_m_s is not None:
        in_run = through & (G >= 0)
        arrive = in_run | np.concatenate([[False], in_run[:-1]])
        speeds[arrive] = float(leg_speed_m_s)
    stop = np.concatenate([[True], ~through])
    t_takeoff = takeoff_time_s(takeoff_alt_m, flight)
    reached = t_takeoff + path_reached_s(path, stop, speeds, flight, np.concatenate([[0.0], H]))[1:]
    t = float(reached[-1]) + float(H[-1])
    if end == "land":
        t += descent_time_s(float(P[-1, 2] - takeoff[2]), flight)
    else:
        z = float(P[-1, 2] - takeoff[2])
        climb = max(flight.rtl_alt_m - z, 0.0)
        home_leg = float(np.hypot(*(P[-1, :2] - takeoff[:2])))
        t += climb / flight.rtl_climb_m_s + float(leg_time_s(home_leg, flight)) + flight.rtl_loiter_s + descent_time_s(max(z, flight.rtl_alt_m), flight)
    return Route(
        takeoff_site=takeoff,
        takeoff_alt_m=float(takeoff_alt_m),
        points=P,
        kind=tuple(kinds),
        grid_index=G,
        hold_s=H,
        end=end,
        flight_time_s=float(t),
        path_length_m=float(legs.sum()),
        speed_m_s=speeds,
        through=through,
        reached_s=reached,
    )


def leg_units(hold_s: np.ndarray) -> list[tuple[int, int]]:
    """Consecutive index ranges [start, stop) that a flight may not cut: a run of hold-0 points and the hold that ends it.

    ``hold_s`` (N,) in flight order; a unit ends after every point with a hold
    (> 0 after rounding to whole seconds) and after the last point.
    """
    h = np.round(np.asarray(hold_s, float))
    units = []
    start = 0
    for i in range(len(h)):
        if h[i] > 0 or i == len(h) - 1:
            units.append((start, i + 1))
            start = i + 1
    return units


def split_into_flights(
    vehicle: np.ndarray,
    markers: np.ndarray,
    hold_s: np.ndarray,
    limits: Limits,
    flight: FlightModel,
    endurance_s: float,
    reserve: float = 0.25,
    takeoff_site: np.ndarray | None = None,
    end: str = "land",
    ordered: bool = True,
    leg_speed_m_s: float | None = None,
) -> list[Route]:
    """Cut the points into consecutive flights that each fit one battery.

    Every flight takes off from and lands at the same take-off point and lasts
    at most ``(1 - reserve) * endurance_s`` (take-off, transit, holds and
    landing included, as ``plan_route`` times them). Cuts fall only after a
    point with a hold (``leg_units``): a leg of pass-through points is never
    cut. When the unit after a cut starts with pass-through points, the next
    flight first returns to the hold point that ended the previous flight, so
    the leg again starts from rest there (that point, and its ``grid_index``,
    appears in both flights). Flights are filled greedily in order.

    Parameters
    ----------
    vehicle, markers : (N, 3) drone positions and marker centres, site frame, m
    hold_s : (N,) holds, s (0 = fly through)
    limits, flight : as for ``plan_route``
    endurance_s : battery endurance, s
    reserve : fraction of the endurance kept in reserve
    takeoff_site : (3,) take-off point; default beside the whole set of points
    end : 'land' | 'rtl'
    ordered : True keeps the given order; False orders all points first (``order_points``)
    leg_speed_m_s : speed on the legs (``plan_route``)

    Raises
    ------
    PlanError
        When one leg alone (with take-off and landing) does not fit the budget.
    """
    vehicle = np.asarray(vehicle, float)
    markers = np.asarray(markers, float)
    hold = np.asarray(hold_s, float).reshape(-1)
    if len(hold) != len(vehicle):
        raise PlanError(f"hold_s has {len(hold)} values for {len(vehicle)} points: give one hold (s) per point")
    if not (endurance_s > 0 and 0.0 <= reserve < 1.0):
        raise PlanError(f"endurance {endurance_s!r} s with reserve {reserve!r}: give a positive --endurance and a reserve in [0, 1)")
    order = np.arange(len(vehicle)) if ordered else order_points(markers)
    if takeoff_site is None:
        takeoff_site = default_takeoff(vehicle, order, limits)
    budget_s = (1.0 - reserve) * float(endurance_s)
    units = leg_units(hold[order])

    def route_of(idx: list[int]) -> Route:
        sel = order[np.asarray(idx, int)]
        return plan_route(vehicle[sel], markers[sel], limits, flight, takeoff_site=takeoff_site, end=end,
                          hold_s=hold[sel], ordered=True, leg_speed_m_s=leg_speed_m_s)

    def remap(route: Route, idx: list[int]) -> Route:
        sel = order[np.asarray(idx, int)]
        g = np.where(route.grid_index >= 0, sel[np.maximum(route.grid_index, 0)], -1)
        return replace(route, grid_index=g)

    flights: list[Route] = []
    current: list[int] = []
    current_route: Route | None = None
    for u, (a, b) in enumerate(units):
        unit = list(range(a, b))
        trial = current + unit
        r = route_of(trial)
        if r.flight_time_s <= budget_s:
            current, current_route = trial, r
            continue
        if current_route is not None:
            flights.append(remap(current_route, current))
        # re-enter a leg at the hold that ended the previous flight
        lead = [a - 1] if (a > 0 and np.round(hold[order[a]]) <= 0 and b - a > 1) else []
        current = lead + unit
        r = route_of(current)
        if r.flight_time_s > budget_s:
            raise PlanError(
                f"points {a}-{b - 1} (one leg) need {r.flight_time_s / 60:.1f} min with take-off and landing, more than "
                f"{budget_s / 60:.1f} min ({100 * (1 - reserve):.0f} % of the endurance): shorten that leg, lower its holds or give a longer --endurance"
            )
        current_route = r
    if current_route is not None:
        flights.append(remap(current_route, current))
    return flights
