"""Mission items from a route, and the three mission files: QGC ``.plan``, ``QGC WPL 110``, GeoJSON.

The item sequence copies the real, accepted SITL mission
(shared/replays/arducopter-sitl/calib-grid.waypoints):

    [home]  NAV_TAKEOFF  DO_CHANGE_SPEED  DO_SET_ROI(camera)  NAV_WAYPOINT x N  (NAV_WAYPOINT above take-off, NAV_LAND) | RTL

Fly-through legs: a point the route passes (hold 0) is a NAV_WAYPOINT with
param 1 = 0; ArduCopter then flies through it into the next waypoint without
stopping (param 2, the acceptance radius, is not stored by Copter: WPNAV_RADIUS
applies). Where the route's leg speed changes, a DO_CHANGE_SPEED follows the
NAV_WAYPOINT the new speed leads to (DO items run when the NAV item before
them starts).

ArduPilot rules kept: home is slot 0 of the uploaded mission (the ``.plan``
keeps it in ``plannedHomePosition``, QGC inserts it on upload); holds are whole
seconds (NAV_WAYPOINT param 1 is an integer in ArduCopter); no commanded
position has altitude 0 (0 means 'current altitude'); NAV_WAYPOINT's yaw is
ignored by ArduCopter, so the nose faces the camera through DO_SET_ROI, or a
CONDITION_YAW per point (``yaw_mode='condition-yaw'``).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from dronecal_field.geodesy import EGM96_GRID, EnuOrigin, enu_to_geodetic
from dronecal_field.geodesy import geoid_separation_m as geoid_separation_m_at

# MAV_CMD and MAV_FRAME values used here (common.xml)
MAV_CMD_NAV_WAYPOINT = 16
MAV_CMD_NAV_RETURN_TO_LAUNCH = 20
MAV_CMD_NAV_LAND = 21
MAV_CMD_NAV_TAKEOFF = 22
MAV_CMD_CONDITION_YAW = 115
MAV_CMD_DO_CHANGE_SPEED = 178
MAV_CMD_DO_SET_ROI = 201
MAV_FRAME_GLOBAL = 0  # altitude AMSL
MAV_FRAME_MISSION = 2  # no position
MAV_FRAME_GLOBAL_RELATIVE_ALT = 3  # altitude relative to home
MAV_ROI_LOCATION = 3
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_TYPE_QUADROTOR = 2
QGC_ALT_MODE = {"relative": 1, "amsl": 2}  # QGC AltMode: 1 relative to launch, 2 AMSL

ALT_FRAME_TEXT = {
    "relative": "altitudes in metres relative to home = the take-off point's ground (MAV_FRAME_GLOBAL_RELATIVE_ALT, 3)",
    "amsl": "altitudes in metres above mean sea level (MAV_FRAME_GLOBAL, 0)",
}


@dataclass(frozen=True)
class MissionItem:
    """One MAVLink mission item (after home). ``x``/``y`` lat/lon deg, ``z`` altitude m in ``frame``."""

    command: int
    frame: int
    param1: float = 0.0
    param2: float = 0.0
    param3: float = 0.0
    param4: float = 0.0
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    label: str = ""  # 'takeoff', 'grid 12', 'detour', 'speed', 'roi', 'yaw', 'home', 'land', 'rtl'
    grid_index: int = -1  # index into the plan's grid points, -1 for others

    @property
    def params(self) -> list[float]:
        return [self.param1, self.param2, self.param3, self.param4, self.x, self.y, self.z]


@dataclass(frozen=True)
class Mission:
    """Home and the items after it. Heights: ``home_h_m`` ellipsoidal, ``home_alt_m`` as written for home."""

    home_lat_deg: float
    home_lon_deg: float
    home_h_m: float  # WGS84 ellipsoidal height of the take-off point's ground
    home_alt_m: float  # the altitude written for home: AMSL when the geoid separation is known, else ellipsoidal
    home_alt_is_amsl: bool
    alt_frame: str  # 'relative' | 'amsl'
    items: tuple[MissionItem, ...]
    speed_m_s: float
    geoid_separation_m: float | None = None
    home_datum: str = "AMSL (the site's geoid separation)"  # what home_alt_m is, in words (stated in the .plan)

    @property
    def alt_frame_text(self) -> str:
        return ALT_FRAME_TEXT[self.alt_frame]


def bearing_deg(from_xy_enu: np.ndarray, to_xy_enu: np.ndarray) -> np.ndarray:
    """Bearings (deg clockwise from north, [0, 360)) from (N, 2) ENU points to (2,) or (N, 2) points."""
    d = np.asarray(to_xy_enu, float) - np.asarray(from_xy_enu, float)
    return np.degrees(np.arctan2(d[..., 0], d[..., 1])) % 360.0


def build_mission(
    route,
    R_enu_from_site: np.ndarray,
    origin: EnuOrigin,
    camera_height_m: float,
    speed_m_s: float,
    alt_frame: str = "relative",
    yaw_mode: str = "roi",
    geoid_separation_m: float | None = None,
) -> Mission:
    """Mission items for a ``plan.route.Route``.

    Parameters
    ----------
    route : the route in the site frame (take-off point, points, holds)
    R_enu_from_site : (3, 3) site -> ENU rotation
    origin : ENU origin (the pole's foot)
    camera_height_m : camera centre above the pole's foot (the ROI), m
    speed_m_s : DO_CHANGE_SPEED ground speed (when the route carries no per-leg speeds)
    alt_frame : 'relative' (to home, frame 3) or 'amsl' (frame 0; needs ``geoid_separation_m``)
    yaw_mode : 'roi' (one DO_SET_ROI at the camera) or 'condition-yaw' (CONDITION_YAW after each waypoint)
    geoid_separation_m : N (h = AMSL + N); None if unknown
    """
    if alt_frame == "amsl" and geoid_separation_m is None:
        from dronecal_field.errors import InputError

        raise InputError("--alt-frame amsl needs the geoid separation: add --geoid-separation N (m) or use --alt-frame relative")
    to_enu = lambda p: np.atleast_2d(np.asarray(p, float)) @ R_enu_from_site.T  # noqa: E731
    home_geo = enu_to_geodetic(to_enu(route.takeoff_site), origin)[0]
    home_h = float(home_geo[2])
    frame = MAV_FRAME_GLOBAL_RELATIVE_ALT if alt_frame == "relative" else MAV_FRAME_GLOBAL

    def alt_of(h: np.ndarray) -> np.ndarray:
        # millimetres: the curvature between home and a point 10 m away is ~0.01 mm
        h = np.asarray(h, float)
        return np.round(h - home_h if alt_frame == "relative" else h - geoid_separation_m, 3)

    cam_enu = np.array([0.0, 0.0, camera_height_m])
    cam_geo = enu_to_geodetic(cam_enu, origin)[0]
    items: list[MissionItem] = []
    # NAV_TAKEOFF: ArduCopter climbs vertically from where it is; lat/lon are
    # informative (the take-off point) and the altitude is never 0.
    takeoff_top = route.takeoff_site + np.array([0.0, 0.0, route.takeoff_alt_m])
    t_geo = enu_to_geodetic(to_enu(takeoff_top), origin)[0]
    items.append(MissionItem(MAV_CMD_NAV_TAKEOFF, frame, x=float(home_geo[0]), y=float(home_geo[1]), z=float(alt_of(t_geo[2])), label="takeoff"))
    speeds = None if route.speed_m_s is None else [round(float(v), 3) for v in route.speed_m_s]
    current_speed = float(speed_m_s) if not speeds else speeds[0]
    items.append(MissionItem(MAV_CMD_DO_CHANGE_SPEED, MAV_FRAME_MISSION, param1=1.0, param2=current_speed, param3=-1.0, label="speed"))
    if yaw_mode == "roi":
        items.append(MissionItem(MAV_CMD_DO_SET_ROI, frame, param1=MAV_ROI_LOCATION, x=float(cam_geo[0]), y=float(cam_geo[1]), z=float(alt_of(cam_geo[2])), label="roi"))
    enu = to_enu(route.points)
    geo = enu_to_geodetic(enu, origin)
    yaw = bearing_deg(enu[:, :2], cam_enu[:2])
    for k in range(len(route.points)):
        kind = route.kind[k]
        hold = float(int(round(route.hold_s[k])))
        gi = int(route.grid_index[k])
        label = f"grid {gi}" if kind == "grid" else kind
        items.append(MissionItem(MAV_CMD_NAV_WAYPOINT, frame, param1=hold, param4=round(float(yaw[k]), 2),
                                 x=float(geo[k, 0]), y=float(geo[k, 1]), z=float(alt_of(geo[k, 2])), label=label, grid_index=gi))
        if yaw_mode == "condition-yaw" and kind == "grid":
            # runs while this waypoint is the active one: turn (shortest way) to face the camera
            items.append(MissionItem(MAV_CMD_CONDITION_YAW, MAV_FRAME_MISSION, param1=round(float(yaw[k]), 2), param2=0.0, param3=0.0, param4=0.0, label="yaw", grid_index=gi))
        if speeds and speeds[k] != current_speed:
            # a DO item after NAV_WAYPOINT k runs when the vehicle sets off towards k: it sets the speed of the leg into k
            current_speed = speeds[k]
            items.append(MissionItem(MAV_CMD_DO_CHANGE_SPEED, MAV_FRAME_MISSION, param1=1.0, param2=current_speed, param3=-1.0, label="speed", grid_index=gi))
    if route.end == "land":
        items.append(MissionItem(MAV_CMD_NAV_LAND, frame, x=float(home_geo[0]), y=float(home_geo[1]), z=0.0, label="land"))
    else:
        items.append(MissionItem(MAV_CMD_NAV_RETURN_TO_LAUNCH, frame, label="rtl"))
    for it in items:
        if it.command in (MAV_CMD_NAV_WAYPOINT, MAV_CMD_NAV_TAKEOFF) and not it.z > 0.05:
            from dronecal_field.errors import PlanError

            raise PlanError(f"item '{it.label}' would fly at altitude {it.z:.2f} m ({alt_frame}); ArduPilot reads 0 as 'here': raise --min-agl")
    home_sep = geoid_separation_m
    home_datum = "AMSL (the site's geoid separation)"
    if home_sep is None:
        # QGC, Mission Planner and MAVSDK read home's height as AMSL: convert it with PROJ's geoid if installed
        home_sep = geoid_separation_m_at(float(home_geo[0]), float(home_geo[1]))
        home_datum = "AMSL (EGM96, PROJ grid)" if home_sep is not None else "WGS84 ellipsoidal (no geoid known: not AMSL)"
    return Mission(
        home_lat_deg=float(home_geo[0]),
        home_lon_deg=float(home_geo[1]),
        home_h_m=home_h,
        home_alt_m=round(home_h - home_sep if home_sep is not None else home_h, 3),
        home_alt_is_amsl=home_sep is not None,
        alt_frame=alt_frame,
        items=tuple(items),
        speed_m_s=float(speed_m_s),
        geoid_separation_m=geoid_separation_m,
        home_datum=home_datum,
    )


def home_datum_warning(mission: Mission) -> str | None:
    """The warning for a home height written in the wrong datum, or None when it is AMSL.

    QGroundControl, Mission Planner and MAVSDK read the ``.plan``'s
    ``plannedHomePosition`` and the ``.waypoints`` home line (frame 0) as
    heights above mean sea level.
    """
    if mission.home_alt_is_amsl:
        return None
    return (
        f"the home height in mission.plan (plannedHomePosition) and the .waypoints home line is ellipsoidal ({mission.home_alt_m:.2f} m, WGS84): "
        "QGroundControl, Mission Planner and MAVSDK read it as AMSL; no geoid separation was given and PROJ's EGM96 grid "
        f"({EGM96_GRID}) is not installed: give --geoid-separation N (m) or --ground-amsl to write AMSL"
    )


def item_heights_m(mission: Mission, item: MissionItem) -> float:
    """WGS84 ellipsoidal height (m) of an item's position."""
    if item.frame == MAV_FRAME_GLOBAL_RELATIVE_ALT:
        return mission.home_h_m + item.z
    return item.z + (mission.geoid_separation_m or 0.0)


# --------------------------------------------------------------------------
# QGroundControl .plan


def fence_polygon(points_site: np.ndarray, margin_m: float) -> np.ndarray:
    """(M, 2) convex polygon (site XY, counter-clockwise) around (N, 2|3) points grown by ``margin_m``."""
    from scipy.spatial import ConvexHull

    xy = np.asarray(points_site, float)[:, :2]
    n = 16
    # a 16-gon of radius margin/cos(pi/n) contains the margin circle around each point
    ang = np.arange(n) * 2 * np.pi / n
    ring = (margin_m / math.cos(math.pi / n)) * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    cloud = (xy[:, None, :] + ring[None, :, :]).reshape(-1, 2)
    hull = ConvexHull(cloud)
    return cloud[hull.vertices]  # scipy gives 2D hull vertices counter-clockwise


def qgc_plan(mission: Mission, fence_latlon: np.ndarray | None, keep_out: tuple[float, float, float] | None, cruise_speed_m_s: float) -> dict:
    """The QGroundControl plan (fileType Plan, version 1) as a dict.

    ``fence_latlon`` (M, 2) is an inclusion polygon; ``keep_out`` = (lat, lon,
    radius_m) an exclusion circle around the pole.
    """
    alt_mode = QGC_ALT_MODE[mission.alt_frame]
    items = []
    for seq, it in enumerate(mission.items, start=1):
        d: dict = {
            "autoContinue": True,
            "command": it.command,
            "doJumpId": seq,
            "frame": it.frame,
            "params": [float(v) for v in it.params],
            "type": "SimpleItem",
        }
        if it.frame in (MAV_FRAME_GLOBAL, MAV_FRAME_GLOBAL_RELATIVE_ALT):
            d["Altitude"] = float(it.z)
            d["AltitudeMode"] = alt_mode
            d["AMSLAltAboveTerrain"] = None
        items.append(d)
    polygons = []
    if fence_latlon is not None:
        polygons.append({"inclusion": True, "polygon": [[float(a), float(b)] for a, b in fence_latlon], "version": 1})
    circles = []
    if keep_out is not None and keep_out[2] > 0:
        circles.append({"circle": {"center": [float(keep_out[0]), float(keep_out[1])], "radius": float(keep_out[2])}, "inclusion": False, "version": 1})
    return {
        "fileType": "Plan",
        "geoFence": {"circles": circles, "polygons": polygons, "version": 2},
        "groundStation": "dronecal-field",
        "mission": {
            "cruiseSpeed": float(cruise_speed_m_s),
            "firmwareType": MAV_AUTOPILOT_ARDUPILOTMEGA,
            "globalPlanAltitudeMode": alt_mode,
            "hoverSpeed": float(cruise_speed_m_s),
            "items": items,
            "plannedHomePosition": [mission.home_lat_deg, mission.home_lon_deg, float(mission.home_alt_m)],
            "vehicleType": MAV_TYPE_QUADROTOR,
            "version": 2,
        },
        # a foreign member (ignored by QGC and MAVSDK): which height plannedHomePosition carries
        "dronecal": {"plannedHomePositionHeight": mission.home_datum},
        "rallyPoints": {"points": [], "version": 2},
        "version": 1,
    }


# --------------------------------------------------------------------------
# Mission Planner QGC WPL 110


def waypoints_text(mission: Mission) -> str:
    """``QGC WPL 110`` text: home as item 0 (frame 0, its altitude), then the items; tab separated.

    Relative altitudes use frame 3 (GLOBAL_RELATIVE_ALT) as GCS files do; the
    frame column is what states the altitude reference of each line.
    """
    lines = ["QGC WPL 110"]
    lines.append(_wpl_line(0, 1, MAV_FRAME_GLOBAL, MAV_CMD_NAV_WAYPOINT, [0, 0, 0, 0, mission.home_lat_deg, mission.home_lon_deg, mission.home_alt_m]))
    for seq, it in enumerate(mission.items, start=1):
        lines.append(_wpl_line(seq, 0, it.frame, it.command, it.params))
    return "\n".join(lines) + "\n"


def _wpl_line(seq: int, current: int, frame: int, command: int, p: list[float]) -> str:
    return "\t".join(
        [str(seq), str(current), str(frame), str(command)]
        + [f"{float(v):.6f}" for v in p[:4]]
        + [f"{float(p[4]):.7f}", f"{float(p[5]):.7f}", f"{float(p[6]):.6f}", "1"]
    )


def parse_waypoints(text: str) -> list[dict]:
    """Rows of a ``QGC WPL 110`` file as dicts (seq, current, frame, command, params (7,), autocontinue)."""
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if not lines or not lines[0].startswith("QGC WPL 110"):
        from dronecal_field.errors import InputError

        raise InputError("not a QGC WPL 110 file: the first line must be 'QGC WPL 110'")
    rows = []
    for ln in lines[1:]:
        f = ln.split("\t")
        rows.append({
            "seq": int(f[0]), "current": int(f[1]), "frame": int(f[2]), "command": int(f[3]),
            "params": [float(v) for v in f[4:11]], "autocontinue": int(f[11]),
        })
    return rows


# --------------------------------------------------------------------------
# GeoJSON


def geojson(features: list[dict], description: str) -> dict:
    """A FeatureCollection; ``description`` states the height reference (a foreign member)."""
    return {"type": "FeatureCollection", "description": description, "features": features}


def point_feature(lon: float, lat: float, h: float | None, props: dict) -> dict:
    coords = [float(lon), float(lat)] + ([round(float(h), 3)] if h is not None else [])
    return {"type": "Feature", "geometry": {"type": "Point", "coordinates": coords}, "properties": props}


def line_feature(coords: np.ndarray, props: dict) -> dict:
    """LineString from (K, 2|3) lon, lat[, h] rows."""
    rows = [[float(c) if i < 2 else round(float(c), 3) for i, c in enumerate(r)] for r in np.asarray(coords, float)]
    return {"type": "Feature", "geometry": {"type": "LineString", "coordinates": rows}, "properties": props}


def _crossing(a, b, c, d) -> tuple[float, float] | None:
    """Where segments a-b and c-d cross each other properly (not at an end), or None."""
    def orient(p, q, r) -> float:
        return (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])

    o1, o2, o3, o4 = orient(a, b, c), orient(a, b, d), orient(c, d, a), orient(c, d, b)
    if o1 * o2 >= 0 or o3 * o4 >= 0:
        return None
    t = o3 / (o3 - o4)
    return (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]))


def _area(pts: list[tuple[float, float]]) -> float:
    """Unsigned shoelace area of a ring."""
    xy = np.asarray(pts, float)
    return 0.5 * abs(float(np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])))


def simple_ring(ring: np.ndarray) -> np.ndarray:
    """(K, 2) the ring without its self-crossings: each small loop cut off at its crossing point.

    A ring traced from an image border (the camera's ground footprint) folds
    into small bow-ties where distorted rays near a corner cross (the 4K plan
    had two), which GIS tools reject as an invalid polygon. Of the two rings
    either side of a crossing the larger (by area) is kept.

    Parameters
    ----------
    ring : (M, 2) open ring (first vertex not repeated), any planar or lon/lat units
    """
    pts = [tuple(map(float, p)) for p in np.asarray(ring, float)[:, :2]]
    changed = True
    while changed and len(pts) > 3:
        changed = False
        n = len(pts)
        for i in range(n):
            for j in range(i + 2, n):
                if i == 0 and j == n - 1:
                    continue  # the closing segment's neighbour
                p = _crossing(pts[i], pts[i + 1], pts[j], pts[(j + 1) % n])
                if p is None:
                    continue
                inner = [p] + pts[i + 1 : j + 1]
                outer = pts[: i + 1] + [p] + pts[j + 1 :]
                pts = outer if _area(outer) >= _area(inner) else inner
                changed = True
                break
            if changed:
                break
    return np.asarray(pts)


def polygon_feature(lonlat: np.ndarray, props: dict) -> dict:
    """Polygon from (M, 2) lon/lat vertices; the ring is closed, simple (no self-crossing) and
    counter-clockwise (RFC 7946)."""
    ring = simple_ring(np.asarray(lonlat, float)[:, :2])
    area2 = np.sum(ring[:, 0] * np.roll(ring[:, 1], -1) - np.roll(ring[:, 0], -1) * ring[:, 1])
    if area2 < 0:
        ring = ring[::-1]
    coords = [[float(a), float(b)] for a, b in ring] + [[float(ring[0, 0]), float(ring[0, 1])]]
    return {"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [coords]}, "properties": props}


def dumps(obj: dict) -> str:
    """JSON text with a trailing newline (stable key order as built)."""
    return json.dumps(obj, indent=2, allow_nan=False) + "\n"
