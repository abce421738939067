"""The paper's sampling strategies and the point screen, as pure functions (used by ``plan`` and the survey).

A :class:`Strategy` is a lattice in the *site frame* (X along the camera
azimuth, Y left, Z up, origin at the pole's foot): X rows every ``x_step_m``
between ``x_min_m`` and ``x_max_m``, Y every ``y_step_m`` within
``±y_half_width_m``, and ``n_heights`` flight levels. The paper (section
IV.B) recommends 1 m along X and Y, two heights, X from 4 to 8 m, 3 m each
side; 0.5 m along Y for short focal lengths / wide fields of view; nearer
sampling for extreme fields of view.

The heights are not fixed numbers: they depend on what the camera sees. The
levels are spread over the band of heights where the lattice is well seen
(see :func:`choose_heights`). All functions take the camera *in the site
frame* (``plan.site.guess_camera(..., frame="site")``; the survey's synthetic
cameras already are). This module imports neither ``plan`` nor ``survey``:
both import it.

Points are *marker centres* (what the camera sees). The drone's own position
(the waypoint) is the marker minus its body offset turned to face the camera;
height, keep-out, range and geofence limits apply to the drone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from dronecal_field.core.camera import Camera

# The paper's X ranges (section IV.B): near 0-4 m, far 4-8 m, full 0-8 m.
X_RANGES_M: dict[str, tuple[float, float]] = {"far": (4.0, 8.0), "near": (0.0, 4.0), "full": (0.0, 8.0)}
MIN_POINTS = 12  # below this the 'default' model (up to 15 unknowns) has little redundancy
MIN_POINTS_PER_LEVEL = 3


@dataclass(frozen=True)
class Strategy:
    """One sampling strategy: a site-frame lattice (metres) and a number of flight levels."""

    name: str
    x_min_m: float = 4.0
    x_max_m: float = 8.0
    x_step_m: float = 1.0
    y_half_width_m: float = 3.0
    y_step_m: float = 1.0
    n_heights: int = 2

    @property
    def x_range_name(self) -> str:
        for name, (a, b) in X_RANGES_M.items():
            if (a, b) == (self.x_min_m, self.x_max_m):
                return name
        return f"{self.x_min_m:g}-{self.x_max_m:g}m"

    def describe(self) -> str:
        """e.g. 'far X 4-8 m, Y step 1 m, 2 heights'."""
        return f"{self.x_range_name} X {self.x_min_m:g}-{self.x_max_m:g} m, Y step {self.y_step_m:g} m, {self.n_heights} heights"


def make_strategy(x_range: str = "far", y_step_m: float = 1.0, n_heights: int = 2) -> Strategy:
    """A paper strategy by its three factors; the name is ``'<range>-y<step>-z<n>'``."""
    x0, x1 = X_RANGES_M[x_range]
    return Strategy(name=f"{x_range}-y{y_step_m:g}-z{n_heights}", x_min_m=x0, x_max_m=x1, y_step_m=y_step_m, n_heights=n_heights)


def paper_strategies() -> tuple[Strategy, ...]:
    """The paper's 18 alternatives: Y step {1, 0.5} m x {2, 3, 4} heights x X range {far, near, full}."""
    return tuple(
        make_strategy(x_range, y_step, n_z)
        for x_range in ("far", "near", "full")
        for y_step in (1.0, 0.5)
        for n_z in (2, 3, 4)
    )


def horizontal_fov_deg(camera: Camera) -> float:
    """Pinhole horizontal field of view of a camera, deg."""
    return 2.0 * math.degrees(math.atan(camera.width / 2.0 / camera.intrinsics.fx))


def recommended_strategy(camera: Camera) -> Strategy:
    """The paper's recommendation for this camera.

    1 m along Y unless the horizontal field of view is 90 deg or more (short
    focal length: 0.5 m, paper Fig. 8); X 4-8 m unless the field of view is
    extreme (above 110 deg or below 25 deg), where the paper's 21 % exception
    samples nearer (0-4 m).
    """
    hfov = horizontal_fov_deg(camera)
    y_step = 0.5 if hfov >= 90.0 else 1.0
    x_range = "near" if (hfov > 110.0 or hfov < 25.0) else "far"
    return make_strategy(x_range, y_step, 2)


def alternatives(base: Strategy) -> tuple[Strategy, ...]:
    """``base`` and its one-factor-at-a-time variants, as the paper compares them.

    Y step 0.5 / 1 m, 2 / 3 / 4 heights, near / far / full X range; each
    variant changes one factor of ``base``.
    """
    out = [base]
    other_y = 0.5 if base.y_step_m == 1.0 else 1.0
    out.append(replace(base, y_step_m=other_y))
    for n in (2, 3, 4):
        if n != base.n_heights:
            out.append(replace(base, n_heights=n))
    for name, (a, b) in X_RANGES_M.items():
        if (a, b) != (base.x_min_m, base.x_max_m):
            out.append(replace(base, x_min_m=a, x_max_m=b))
    return tuple(
        replace(s, name=f"{s.x_range_name}-y{s.y_step_m:g}-z{s.n_heights}") for s in out
    )


@dataclass(frozen=True)
class Limits:
    """What the flight and the detector allow. Distances in metres, site frame.

    ``marker_size_m`` and ``min_marker_px`` live here because they limit where
    points may be (the marker must be at least ``min_marker_px`` across).
    ``geofence_xy`` is a site-frame polygon ((x, y), ...) the drone must stay in.
    """

    min_agl_m: float = 1.0
    max_agl_m: float | None = None
    max_range_m: float | None = None
    keep_out_m: float = 2.0
    marker_size_m: float = 0.3
    min_marker_px: float = 20.0
    marker_offset_frd_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    margin_px: float = 10.0
    geofence_xy: tuple[tuple[float, float], ...] | None = None
    height_step_m: float = 0.1  # resolution of the height levels
    max_search_height_m: float = 30.0  # top of the height search when max_agl_m is unset
    # the white quiet zone round the marker (one cell each side), as a fraction of the marker side: it must be in the image too
    quiet_zone_frac: float = 0.0
    # the guess band's corner cameras (``sampling.band.corner_cameras``, same world frame): a point is in view only when
    # the whole marker is in the image of the camera screened AND of every one of these
    band: tuple = ()


@dataclass(frozen=True, eq=False)
class GridScreen:
    """Every lattice point of a strategy and why it was kept or dropped.

    All arrays are (M,) or (M, k) over the full lattice (all levels).
    """

    strategy: Strategy
    heights_m: tuple[float, ...]  # marker-centre heights of the levels, m
    marker_site: np.ndarray  # (M, 3) marker centres, site frame, m
    vehicle_site: np.ndarray  # (M, 3) drone positions (waypoints), site frame, m
    uv: np.ndarray  # (M, 2) marker centre pixels (NaN behind the camera)
    marker_px: np.ndarray  # (M,) smallest projected marker side, px
    in_view: np.ndarray  # (M,) bool: whole marker in the image with the margin, in front, before the distortion fold
    reachable: np.ndarray  # (M,) bool: height, keep-out, range, geofence all allowed
    big_enough: np.ndarray  # (M,) bool: marker_px >= min_marker_px
    reasons: dict[str, int] = field(default_factory=dict)  # counts of dropped points per first reason

    @property
    def keep(self) -> np.ndarray:
        """(M,) bool: the points of the plan."""
        return self.in_view & self.reachable & self.big_enough

    @property
    def points(self) -> np.ndarray:
        """(N, 3) kept marker centres, site frame, m."""
        return self.marker_site[self.keep]

    @property
    def vehicle_points(self) -> np.ndarray:
        """(N, 3) kept drone positions, site frame, m."""
        return self.vehicle_site[self.keep]

    def needed_marker_size_m(self, limits: Limits) -> float | None:
        """Marker side (m) that would make every seen, reachable point at least ``min_marker_px``; None if none is short."""
        short = self.in_view & self.reachable & ~self.big_enough
        if not short.any():
            return None
        return float(np.max(limits.marker_size_m * limits.min_marker_px / self.marker_px[short]))


def fold_radius(distortion: np.ndarray, min_slope: float = 0.0) -> float:
    """Normalised radius where the radial distortion stops increasing (inf if it never does within 10).

    The radial map ``r -> r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` of a barrel
    model turns back beyond this radius, so points past it project back
    *into* the image although a real lens never shows them. One definition
    for ``plan`` and the survey.

    Parameters
    ----------
    distortion : (5,) k1, k2, p1, p2, k3 (OpenCV order)
    min_slope : the fold is where d(r')/dr first drops to this; ``plan`` asks
        0.05 to stay clear of the squeezed rim, the survey 0 (the fold itself)

    Returns
    -------
    float : normalised radius (x^2 + y^2)^0.5 on the z = 1 plane (exact: the
        smallest positive root, in x = r^2, of 1 - min_slope + 3 k1 x + 5 k2 x^2 + 7 k3 x^3)
    """
    k1, k2, _, _, k3 = np.asarray(distortion, float)
    if min_slope >= 1.0:
        return 0.0
    if k1 >= 0 and k2 >= 0 and k3 >= 0:
        return math.inf
    # coefficients too small to bend the map within r <= 10 (x <= 100) are zero (a denormal leading one breaks np.roots)
    coeffs = np.array([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0 - min_slope])
    coeffs[np.abs(coeffs) * np.array([1e6, 1e4, 1e2, 1.0]) < 1e-9] = 0.0
    coeffs = np.trim_zeros(coeffs, "f")
    if len(coeffs) <= 1 or not np.all(np.isfinite(coeffs)):
        return math.inf
    x = np.roots(coeffs)
    x = x.real[(np.abs(x.imag) <= 1e-9 * np.maximum(1.0, np.abs(x.real))) & (x.real > 0.0) & (x.real <= 100.0)]
    return float(math.sqrt(x.min())) if x.size else math.inf


# plan keeps lattice points inside 97 % of the radius where the slope falls to 5 %
PLAN_FOLD_MIN_SLOPE = 0.05
PLAN_FOLD_FRACTION = 0.97


def _facing_vehicle(marker: np.ndarray, offset_frd: tuple[float, float, float], camera_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drone positions (M, 3) and nose directions (M, 2) for markers (M, 3) when the nose faces the camera.

    The nose points (horizontally) from the drone at the camera; the marker is
    at drone + R(yaw) @ offset. Solved by fixed-point iteration (the offset is
    small against the distance).
    """
    f, r, d = offset_frd
    vehicle = marker.copy()
    for _ in range(6):
        to_cam = camera_xy[None, :] - vehicle[:, :2]
        norm = np.linalg.norm(to_cam, axis=1, keepdims=True)
        fwd = np.where(norm > 1e-6, to_cam / np.maximum(norm, 1e-9), np.array([[1.0, 0.0]]))
        right = np.stack([fwd[:, 1], -fwd[:, 0]], axis=1)  # Z up: right of forward is forward turned clockwise
        offset_world = np.concatenate([f * fwd + r * right, np.full((len(marker), 1), -d)], axis=1)
        vehicle = marker - offset_world
    return vehicle, fwd


def marker_corners(marker: np.ndarray, forward_xy: np.ndarray, size_m: float) -> np.ndarray:
    """(M, 4, 3) corners of upright square markers facing against ``forward_xy`` (M, 2)."""
    h = size_m / 2.0
    side = np.concatenate([np.stack([forward_xy[:, 1], -forward_xy[:, 0]], axis=1), np.zeros((len(marker), 1))], axis=1)
    up = np.array([0.0, 0.0, 1.0])
    signs = np.array([[-1, 1], [1, 1], [1, -1], [-1, -1]], float)
    return marker[:, None, :] + h * (signs[None, :, 0:1] * side[:, None, :] + signs[None, :, 1:2] * up[None, None, :])


def _marker_view(camera: Camera, marker_site: np.ndarray, fwd: np.ndarray, limits: Limits) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One camera's view of markers (M, 3) facing against ``fwd`` (M, 2): centre pixels (M, 2), marker side px (M,),
    in front (M,) and whole marker with its quiet zone inside the image with the margin, before the fold (M,)."""
    M = len(marker_site)
    corners = marker_corners(marker_site, fwd, limits.marker_size_m).reshape(-1, 3)
    parts = [marker_site, corners]
    if limits.quiet_zone_frac > 0:
        parts.append(marker_corners(marker_site, fwd, limits.marker_size_m * (1.0 + 2.0 * limits.quiet_zone_frac)).reshape(-1, 3))
    allp = np.concatenate(parts, axis=0)
    R, t = camera.pose.R_cam_from_world, camera.pose.t_cam_from_world
    Xc = allp @ R.T + t
    depth = Xc[:, 2]
    front = depth > 0.3
    safe = np.where(front, depth, 1.0)
    rn = np.hypot(Xc[:, 0] / safe, Xc[:, 1] / safe)
    before_fold = rn < PLAN_FOLD_FRACTION * fold_radius(camera.distortion.as_array(), PLAN_FOLD_MIN_SLOPE)
    with np.errstate(invalid="ignore", divide="ignore"):
        uv_all = camera.project(np.where(front[:, None], allp, np.nan))
    w, h, m = camera.width, camera.height, limits.margin_px
    inside = front & before_fold & (uv_all[:, 0] >= m) & (uv_all[:, 0] <= w - 1 - m) & (uv_all[:, 1] >= m) & (uv_all[:, 1] <= h - 1 - m)
    uv = uv_all[:M]
    cuv = uv_all[M:5 * M].reshape(M, 4, 2)
    sides = np.linalg.norm(cuv - np.roll(cuv, -1, axis=1), axis=2)
    marker_px = np.nan_to_num(np.min(sides, axis=1), nan=0.0)
    all_front = front[:M] & front[M:].reshape(-1, M, 4).transpose(1, 0, 2).reshape(M, -1).all(axis=1)
    in_view = inside[:M] & inside[M:].reshape(-1, M, 4).transpose(1, 0, 2).reshape(M, -1).all(axis=1)
    return uv, marker_px, all_front, in_view


def screen_points(camera: Camera, marker_site: np.ndarray, limits: Limits) -> dict[str, np.ndarray]:
    """Per-point visibility and limits for marker centres (M, 3) in the site frame.

    Returns arrays: ``vehicle`` (M, 3), ``uv`` (M, 2), ``marker_px`` (M,),
    ``in_view``, ``reachable``, ``big_enough`` (M,) bool, and one bool array
    per reason (``behind``, ``outside_image``, ``too_low``, ...). With
    ``limits.band`` a point is in view only if every band camera sees the whole
    marker too, and ``marker_px`` is the smallest over them.
    """
    marker_site = np.atleast_2d(np.asarray(marker_site, float))
    M = len(marker_site)
    cam_c = camera.pose.position_world
    vehicle, fwd = _facing_vehicle(marker_site, limits.marker_offset_frd_m, cam_c[:2])
    uv, marker_px, front, in_view = _marker_view(camera, marker_site, fwd, limits)
    behind = ~front
    for other in limits.band:
        _, px_o, front_o, in_view_o = _marker_view(other, marker_site, fwd, limits)
        in_view &= in_view_o & front_o
        marker_px = np.minimum(marker_px, px_o)

    horiz = np.hypot(vehicle[:, 0], vehicle[:, 1])
    too_low = (vehicle[:, 2] < limits.min_agl_m - 1e-9) | (marker_site[:, 2] < 0.2)
    too_high = np.zeros(M, bool) if limits.max_agl_m is None else vehicle[:, 2] > limits.max_agl_m + 1e-9
    in_keep_out = horiz < limits.keep_out_m
    out_of_range = np.zeros(M, bool) if limits.max_range_m is None else horiz > limits.max_range_m + 1e-9
    if limits.geofence_xy is not None:
        from matplotlib.path import Path as MplPath

        outside_fence = ~MplPath(np.asarray(limits.geofence_xy, float)).contains_points(vehicle[:, :2])
    else:
        outside_fence = np.zeros(M, bool)
    reachable = ~(too_low | too_high | in_keep_out | out_of_range | outside_fence)
    big_enough = marker_px >= limits.min_marker_px
    return {
        "vehicle": vehicle,
        "uv": uv,
        "marker_px": marker_px,
        "in_view": in_view,
        "reachable": reachable,
        "big_enough": big_enough,
        "behind_camera": behind,
        "outside_image": ~behind & ~in_view,
        "too_low": too_low,
        "too_high": too_high,
        "keep_out": in_keep_out,
        "out_of_range": out_of_range,
        "outside_geofence": outside_fence,
        "marker_too_small": ~big_enough,
    }


def xy_lattice(strategy: Strategy) -> np.ndarray:
    """(K, 2) lattice X, Y (m) of a strategy: X rows outer, Y inner (the order of every sampler)."""
    xs = np.arange(strategy.x_min_m, strategy.x_max_m + 1e-9, strategy.x_step_m)
    n_y = int(round(strategy.y_half_width_m / strategy.y_step_m))
    ys = np.arange(-n_y, n_y + 1) * strategy.y_step_m
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    return np.stack([X.ravel(), Y.ravel()], axis=1)


def choose_heights(strategy: Strategy, camera: Camera, limits: Limits) -> tuple[float, ...]:
    """Marker-centre heights (m) of the strategy's levels for this camera.

    Every height on a ``height_step_m`` lattice from the lowest allowed to
    ``max_agl_m`` (or ``max_search_height_m``) is scored by how many lattice
    points it keeps; the levels are spread evenly between the lowest and the
    highest heights that keep at least 25 % of the best count (and 3 points),
    so they cover the visible band without flying where little is seen.
    Returns fewer levels when the band is thinner than the levels need.
    """
    xy = xy_lattice(strategy)
    d = limits.marker_offset_frd_m[2]
    z_lo = max(limits.min_agl_m - d, 0.2)
    z_top = (limits.max_agl_m if limits.max_agl_m is not None else limits.max_search_height_m) - d
    if z_top < z_lo:
        return ()
    zs = np.round(np.arange(z_lo, z_top + 1e-9, limits.height_step_m), 3)
    pts = np.concatenate([np.column_stack([xy, np.full(len(xy), z)]) for z in zs])
    s = screen_points(camera, pts, limits)
    # the marker-size rule is left out here so a too-small marker is reported as such, not as "nothing seen"
    counts = (s["in_view"] & s["reachable"]).reshape(len(zs), len(xy)).sum(axis=1)
    if counts.max() == 0:
        return ()
    good = np.nonzero(counts >= max(MIN_POINTS_PER_LEVEL, 0.25 * counts.max()))[0]
    if good.size == 0:
        good = np.array([int(np.argmax(counts))])
    za, zb = float(zs[good[0]]), float(zs[good[-1]])
    step = limits.height_step_m
    # snap to the search lattice (which starts at z_lo, so no level falls below it)
    levels = za + np.round((np.linspace(za, zb, strategy.n_heights) - za) / step) * step
    # keep levels at least 0.2 m apart (closer ones add no depth to the lattice)
    out: list[float] = []
    for z in levels:
        if not out or z - out[-1] >= 0.2 - 1e-9:
            out.append(round(float(z), 3))
    return tuple(out)


def screen_grid(strategy: Strategy, camera: Camera, limits: Limits) -> GridScreen:
    """The strategy's lattice for this camera with every point's verdict (see :class:`GridScreen`)."""
    heights = choose_heights(strategy, camera, limits)
    xy = xy_lattice(strategy)
    if not heights:
        pts = np.zeros((0, 3))
    else:
        pts = np.concatenate([np.column_stack([xy, np.full(len(xy), z)]) for z in heights])
    s = screen_points(camera, pts, limits) if len(pts) else None
    if s is None:
        empty = np.zeros(0, bool)
        return GridScreen(strategy=strategy, heights_m=(), marker_site=pts, vehicle_site=pts.copy(), uv=np.zeros((0, 2)),
                          marker_px=np.zeros(0), in_view=empty, reachable=empty, big_enough=empty, reasons={})
    reasons: dict[str, int] = {}
    dropped = np.zeros(len(pts), bool)
    for name in ("behind_camera", "outside_image", "too_low", "too_high", "keep_out", "out_of_range", "outside_geofence", "marker_too_small"):
        first = s[name] & ~dropped
        if first.any():
            reasons[name] = int(first.sum())
        dropped |= s[name]
    return GridScreen(
        strategy=strategy, heights_m=heights, marker_site=pts, vehicle_site=s["vehicle"], uv=s["uv"],
        marker_px=s["marker_px"], in_view=s["in_view"], reachable=s["reachable"], big_enough=s["big_enough"], reasons=reasons,
    )


def sample_grid(strategy: Strategy, camera: Camera, limits: Limits) -> np.ndarray:
    """(N, 3) site-frame marker centres (m) of ``strategy`` that ``camera`` sees and ``limits`` allow.

    ``camera`` is in the site frame. Points are ordered level by level, X then Y
    (not the flight order: see ``plan.route.order_points``).
    """
    return screen_grid(strategy, camera, limits).points


def geometry_problem(points: np.ndarray) -> str | None:
    """Why a point set cannot give a non-coplanar calibration, or None if it can."""
    if len(points) < MIN_POINTS:
        return f"{len(points)} points (need {MIN_POINTS})"
    levels, counts = np.unique(np.round(points[:, 2], 3), return_counts=True)
    if (counts >= MIN_POINTS_PER_LEVEL).sum() < 2:
        return f"points on {len(levels)} height(s) with {MIN_POINTS_PER_LEVEL}+ points each (need 2 for a non-coplanar calibration)"
    return None


