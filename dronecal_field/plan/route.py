"""Point order, take-off point, keep-out detours and the flight-time model (pure, site frame).

Order: level by level from the lowest (one climb per level), back and forth
along Y within a level, rows along X; each level starts where the previous
one ended (the replayed SITL mission, shared/replays/arducopter-sitl).

Flight time is fitted to that real ArduCopter flight: WPNAV's jerk-limited
S-curve makes a 1 m leg peak at 0.57 m/s and take ~4 s, so a 3 s hold cycle
takes 6.9-7.2 s; lift-off comes 3.4 s after arming; NAV_LAND descends at
LAND_SPEED 0.5 m/s below 10 m.

Pass-through points (hold 0: NAV_WAYPOINT param 1 = 0 followed by another
waypoint) are timed as ArduCopter flies them (SCurve, Copter 4.1+): each leg
is planned rest to rest, and the next leg starts while this one brakes, so a
straight run of pass-through points is flown at constant cruise and a turn
of angle theta is rounded at cruise x cos(theta / 2), its apex at most
WPNAV_RADIUS from the point (the overlap shrinks until it is). Only the
points where the drone holds cost an acceleration and a braking. The
simulated vehicle (``sim.vehicle_flight.Leg``) flies the same profiles.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from dronecal_field.errors import PlanError
from dronecal_field.sampling.design import through_speed_m_s  # noqa: F401  (the leg speed rule lives with the design)

if TYPE_CHECKING:  # strategies imports this module
    from dronecal_field.sampling.lattice import Limits


@dataclass(frozen=True)
class FlightModel:
    """ArduCopter timing (defaults fitted to the SITL replay; speeds m/s, times s)."""

    speed_m_s: float = 1.5  # DO_CHANGE_SPEED
    accel_m_s2: float = 0.33  # effective S-curve acceleration: 1 m leg peaks at sqrt(0.33) = 0.57 m/s
    leg_overhead_s: float = 0.5  # settle before the hold timer starts
    hover_s: float = 3.0  # hold at every grid point (whole seconds)
    spool_up_s: float = 3.4  # arming (MISSION_START) to lift-off
    takeoff_climb_m_s: float = 1.0
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


def leg_time_s(distance_m: np.ndarray | float, flight: FlightModel) -> np.ndarray:
    """Time (s) of straight legs (m) under a trapezoidal fit of ArduCopter's S-curve; 0 for 0 m."""
    d = np.asarray(distance_m, float)
    a, v = flight.accel_m_s2, flight.speed_m_s
    d_ramp = v * v / a  # accelerate + brake distance
    t = np.where(d < d_ramp, 2.0 * np.sqrt(np.maximum(d, 0.0) / a), d / v + v / a)
    return np.where(d > 1e-6, t + flight.leg_overhead_s, 0.0)


def _leg_cruise_m_s(unit: np.ndarray, speed_m_s: float, flight: FlightModel) -> float:
    """Cruise along a leg of direction ``unit`` (3,): the horizontal speed or the climb/descent limit."""
    h = float(np.hypot(unit[0], unit[1]))
    limits = [speed_m_s / h] if h > 1e-9 else []
    if abs(unit[2]) > 1e-9:
        limits.append((flight.climb_m_s if unit[2] > 0 else flight.descent_m_s) / abs(unit[2]))
    return min(limits) if limits else speed_m_s


def path_time_s(path: np.ndarray, stop: np.ndarray, speeds_m_s: np.ndarray, flight: FlightModel) -> float:
    """Time (s) to fly a polyline from rest, stopping only where ``stop`` says (holds excluded).

    Parameters
    ----------
    path : (M, 3) positions, m; the drone is at rest at ``path[0]``
    stop : (M,) bool; True where the drone stops (``stop[-1]`` is always taken as True)
    speeds_m_s : (M-1,) horizontal cruise commanded on each leg, m/s
    flight : timing model (``accel_m_s2``, ``leg_overhead_s`` per stop, ``wp_radius_m``, ``corner_accel_m_s2``)

    Each leg is a rest-to-rest trapezoid (``leg_time_s``); at a point flown
    through, the next leg starts when this one starts braking (ArduCopter's
    SCurve blend), which saves the overlap ``tau = min(ramp_in, ramp_out)``,
    shortened so the turn's apex stays within ``wp_radius_m`` (apex offset
    ``accel * tau^2 / 8 * |u_out - u_in|``); a turn needing more than the
    corner acceleration (a reversal) stops instead.
    """
    P = np.asarray(path, float)
    if len(P) < 2:
        return 0.0
    a = flight.accel_m_s2
    corner = flight.corner_accel_m_s2 if flight.corner_accel_m_s2 is not None else 2.0 * a
    d = np.diff(P, axis=0)
    lengths = np.linalg.norm(d, axis=1)
    units = np.where(lengths[:, None] > 1e-9, d / np.maximum(lengths, 1e-12)[:, None], 0.0)
    cruise = np.array([_leg_cruise_m_s(u, float(v), flight) for u, v in zip(units, np.asarray(speeds_m_s, float))])
    peak = np.minimum(cruise, np.sqrt(a * lengths))
    ramp = peak / a
    with np.errstate(divide="ignore", invalid="ignore"):
        ends = np.where(lengths > 1e-6, 2.0 * ramp + (lengths - peak * peak / a) / np.maximum(peak, 1e-12), 0.0)
    total = float(ends.sum())
    stops = np.asarray(stop, bool).copy()
    stops[-1] = True
    for j in range(1, len(P) - 1):
        through = not stops[j] and lengths[j - 1] > 1e-9 and lengths[j] > 0.01
        if through:
            du = units[j] - units[j - 1]
            if a * float(np.hypot(du[0], du[1])) >= corner or abs(a * du[2]) > a * (1 + 1e-6):
                through = False
        if not through:
            if lengths[j - 1] > 1e-6:
                total += flight.leg_overhead_s
            continue
        tau = min(ramp[j - 1], ramp[j])
        n = float(np.linalg.norm(du))
        if n > 1e-9:
            tau = min(tau, math.sqrt(8.0 * flight.wp_radius_m / (a * n)))
        total -= tau
    if lengths[-1] > 1e-6:
        total += flight.leg_overhead_s
    return total


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
    ``through`` (K,) True where the drone passes without stopping.
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
    t = takeoff_time_s(takeoff_alt_m, flight) + path_time_s(path, stop, speeds, flight) + float(H.sum())
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
