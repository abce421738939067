"""Point order, take-off point, keep-out detours and the flight-time model (pure, site frame).

Order: level by level from the lowest (one climb per level), back and forth
along Y within a level, rows along X; each level starts where the previous
one ended (the replayed SITL mission, shared/replays/arducopter-sitl).

Flight time is fitted to that real ArduCopter flight: WPNAV's jerk-limited
S-curve makes a 1 m leg peak at 0.57 m/s and take ~4 s, so a 3 s hold cycle
takes 6.9-7.2 s; lift-off comes 3.4 s after arming; NAV_LAND descends at
LAND_SPEED 0.5 m/s below 10 m.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from dronecal_field.errors import PlanError

if TYPE_CHECKING:  # strategies imports this module
    from dronecal_field.plan.strategies import Limits


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


def leg_time_s(distance_m: np.ndarray | float, flight: FlightModel) -> np.ndarray:
    """Time (s) of straight legs (m) under a trapezoidal fit of ArduCopter's S-curve; 0 for 0 m."""
    d = np.asarray(distance_m, float)
    a, v = flight.accel_m_s2, flight.speed_m_s
    d_ramp = v * v / a  # accelerate + brake distance
    t = np.where(d < d_ramp, 2.0 * np.sqrt(np.maximum(d, 0.0) / a), d / v + v / a)
    return np.where(d > 1e-6, t + flight.leg_overhead_s, 0.0)


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
    grid points (-1 for others); ``hold_s`` (K,) the holds.
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
    takeoff_alt_m: float | None = None,
) -> Route:
    """Order the grid, add the take-off point and keep-out detours, and time the flight.

    Parameters
    ----------
    vehicle : (N, 3) drone positions of the grid points, site frame, m
    marker : (N, 3) marker centres (only for grouping into levels), m
    limits : ``plan.strategies.Limits`` (keep-out, range, geofence)
    flight : timing model
    takeoff_site : (3,) take-off point on the ground, site frame; default beside the grid
    end : 'land' (fly above the take-off point, NAV_LAND) or 'rtl'
    takeoff_alt_m : NAV_TAKEOFF altitude above the take-off point; default max(2 m, first point)
    """
    vehicle = np.asarray(vehicle, float)
    marker = np.asarray(marker, float)
    if takeoff_site is None:
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
        add_leg(vehicle[i], "grid", int(i), flight.hover_s)
    if end == "land":
        add_leg(np.array([takeoff[0], takeoff[1], pts[-1][2]]), "home", -1, 0.0)
    P = np.asarray(pts)
    start = np.array([takeoff[0], takeoff[1], takeoff[2] + takeoff_alt_m])
    path = np.concatenate([start[None], P])
    legs = np.linalg.norm(np.diff(path, axis=0), axis=1)
    t = takeoff_time_s(takeoff_alt_m, flight) + float(leg_time_s(legs, flight).sum()) + float(np.sum(holds))
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
        grid_index=np.asarray(gidx, int),
        hold_s=np.asarray(holds, float),
        end=end,
        flight_time_s=float(t),
        path_length_m=float(legs.sum()),
    )
