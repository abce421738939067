"""The scout flight (issue 23): a short generic mission the camera sees whatever its lens and tilt.

A user often knows where the pole is and how high the camera sits, and not
much else. The scout flies rows across the camera's expected view, each a
straight fly-through leg perpendicular to the azimuth (start hold 1 s, a
pass-through point in the middle so ``fly`` records a leg, end hold 1 s), at
*depression levels* (the angle below the camera's horizon of the row's middle)
from a little above the horizon down to as steep as the keep-out allows, every
:data:`LEVEL_STEP_DEG` (under half the vertical field of view of the
narrowest camera, 16:9 at 30 deg HFOV: 17 deg, so any tilt sees two levels).
Rows alternate between a near and a far distance, so the levels a camera sees
lie at different depths, and each row spans the azimuth +- (tolerance + half
the narrowest HFOV), so a camera turned up to the tolerance still sees part of
every row in its vertical band. Without an azimuth the rows become rings round
the pole (fewer levels: a ring is 4x a row).

Pure: the rows and the route in the site frame; ``write_scout`` writes the
folder. ``plan --from-run`` (``plan.fromrun``) turns the recorded scout into a
camera estimate and the main plan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dronecal_field.errors import InputError, PlanError
from dronecal_field.plan import mission as msn
from dronecal_field.plan.route import FlightModel, Route, plan_route
from dronecal_field.plan.site import CameraSite
from dronecal_field.sampling.lattice import Limits

LEVEL_STEP_DEG = 8.0  # depression step between rows: 2 rows inside the narrowest 17 deg vertical field of view
SCOUT_STEPS_DEG = (4.0, 5.0, 6.0, 7.0, LEVEL_STEP_DEG)  # finest first: the finest that fits MAX_SCOUT_S is flown
MAX_SCOUT_S = 120.0  # the scout's budget: two minutes of flight
SCOUT_FILES = ("mission.plan", "mission.waypoints", "mission.geojson", "plan.json")


@dataclass(frozen=True)
class ScoutSpec:
    """The cameras the scout must be seen by, and how it flies.

    Horizontal field of view ``hfov_deg`` (min, max), ``tilt_deg`` (min, max) below the horizon, the azimuth
    within +- ``azimuth_tolerance_deg`` of the given one (None: unknown, rings), the narrowest image aspect
    ``aspect`` (width / height). Rows at ``near_m`` and ``far_m`` from the pole, flown at ``speed_m_s``.
    """

    hfov_deg: tuple[float, float] = (30.0, 110.0)
    tilt_deg: tuple[float, float] = (0.0, 60.0)
    azimuth_tolerance_deg: float = 30.0
    aspect: float = 16.0 / 9.0
    near_m: float = 3.5
    far_m: float = 5.5
    speed_m_s: float = 2.5
    marker_size_m: float = 0.4

    @property
    def min_vfov_deg(self) -> float:
        return 2.0 * math.degrees(math.atan(math.tan(math.radians(self.hfov_deg[0]) / 2.0) / self.aspect))


@dataclass(frozen=True)
class ScoutRow:
    """One row, a straight line at one ``depression_deg`` below the camera's horizon: the marker from (``x_m``, ``y_from_m``,
    ``z_m``) to (``x_to_m``, ``y_to_m``, ``z_to_m``), site frame (X along the azimuth). A row runs from far to near (or near to
    far), so its markers lie at several depths along the same image row. A ring (no azimuth) has ``ring`` True: ``x_m`` is
    its radius and ``z_m`` its height."""

    x_m: float
    z_m: float
    y_from_m: float
    y_to_m: float
    depression_deg: float
    ring: bool = False
    x_to_m: float | None = None
    z_to_m: float | None = None

    @property
    def start(self) -> np.ndarray:
        return np.array([self.x_m, self.y_from_m, self.z_m])

    @property
    def end(self) -> np.ndarray:
        return np.array([self.x_m if self.x_to_m is None else self.x_to_m, self.y_to_m, self.z_m if self.z_to_m is None else self.z_to_m])


def scout_levels(spec: ScoutSpec, step_deg: float) -> np.ndarray:
    """Depressions (deg) of the rows, near the horizon first: from just above what the least tilted narrowest lens sees at
    the top of its image to just below what the most tilted one sees at the bottom, every ``step_deg``."""
    half_v = spec.min_vfov_deg / 2.0
    lo = spec.tilt_deg[0] - half_v + 3.0
    hi = spec.tilt_deg[1] + half_v - 1.0
    return np.arange(lo, hi + 1e-9, step_deg)


def scout_rows(mount_height_m: float, spec: ScoutSpec, limits: Limits, azimuth_known: bool = True,
               step_deg: float = LEVEL_STEP_DEG) -> tuple[tuple[ScoutRow, ...], list[str]]:
    """The rows (or rings) of the scout, near the horizon first, and what it cannot reach (in words).

    Each row keeps its depression from its far end (at most ``spec.far_m``, above ``--min-agl``) to its near end (just
    outside the keep-out), spanning the azimuth +- (tolerance + half the narrowest HFOV). Rows alternate which side is
    far, so two rows a camera sees are never in one plane (parallel rows at one depth were: a 2 m pole's scout was
    refused by calibrate as coplanar) and every row gives depth along one image row.
    """
    H = mount_height_m
    levels = scout_levels(spec, step_deg if azimuth_known else 2.0 * step_deg)
    z_top = (limits.max_agl_m if limits.max_agl_m is not None else H + 2.0)
    z_low = limits.min_agl_m + max(0.0, limits.marker_offset_frd_m[2])
    T = math.tan(math.radians(min(80.0, spec.azimuth_tolerance_deg + spec.hfov_deg[0] / 2.0 + 2.0)))
    # nearest the drone may carry the marker: the keep-out, the marker's offset from the drone and a margin
    r_near = limits.keep_out_m + 0.3 + math.hypot(*limits.marker_offset_frd_m[:2])
    rows, notes = [], []
    for k, d in enumerate(levels):
        t = math.tan(math.radians(d))
        # the distances at which depression d keeps the marker between the lowest and the highest allowed height
        r_hi = spec.far_m if t <= 0 else min(spec.far_m, (H - z_low) / t)
        if t < 0:
            r_hi = min(r_hi, (z_top - H) / -t)
        r_lo = r_near if t <= 0 or H <= z_top else max(r_near, (H - z_top) / t)
        if r_hi < r_lo:
            notes.append(f"depression {d:.0f} deg (tilts near {d:.0f} deg with the narrowest lens) needs the marker "
                         f"{max(r_hi, 0.0):.1f} m from the pole, inside --keep-out {limits.keep_out_m:g} m")
            continue
        if not azimuth_known:
            r = r_hi if k % 2 == 0 else max(r_lo, min(r_hi, spec.near_m))
            rows.append(ScoutRow(x_m=round(r, 3), z_m=round(H - r * t, 3), y_from_m=0.0, y_to_m=0.0, depression_deg=float(d), ring=True))
            continue
        # far end on -Y for even rows, on +Y for odd ones; flown -Y -> +Y, then back, so the pass stays continuous
        far = np.array([r_hi, -r_hi * T, H - r_hi * t])
        near = np.array([r_lo, r_lo * T, H - r_lo * t])
        if k % 2:
            far[1], near[1] = -far[1], -near[1]
        a, b = (far, near) if far[1] < near[1] else (near, far)
        if len(rows) % 2:
            a, b = b, a
        rows.append(ScoutRow(x_m=round(float(a[0]), 3), z_m=round(float(a[2]), 3), y_from_m=round(float(a[1]), 3), y_to_m=round(float(b[1]), 3),
                             depression_deg=float(d), x_to_m=round(float(b[0]), 3), z_to_m=round(float(b[2]), 3)))
    if not rows:
        raise PlanError(f"no scout row is reachable from a {H:g} m camera with --min-agl {limits.min_agl_m:g} and --keep-out {limits.keep_out_m:g}")
    return tuple(rows), notes


def row_points(row: ScoutRow, ring_sides: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Marker positions (K, 3) site frame and holds (K,) s of one row: start (1 s), middle (0), end (1 s);
    a ring: ``ring_sides`` corners round the pole, flown through, 1 s holds where it starts and closes."""
    if row.ring:
        ang = np.linspace(0.0, 2.0 * np.pi, ring_sides + 1)
        pts = np.column_stack([row.x_m * np.cos(ang), row.x_m * np.sin(ang), np.full(len(ang), row.z_m)])
        hold = np.zeros(len(ang))
        hold[0] = hold[-1] = 1.0
        return pts, hold
    a, b = row.start, row.end
    return np.vstack([a, 0.5 * (a + b), b]), np.array([1.0, 0.0, 1.0])


@dataclass(frozen=True, eq=False)
class Scout:
    """The scout's route and mission, and its report (``summary``, plan.json)."""

    site: CameraSite
    spec: ScoutSpec
    rows: tuple[ScoutRow, ...]
    marker_site: np.ndarray  # (N, 3) planned marker centres (row starts, middles, ends), site frame
    leg: np.ndarray  # (N,) row index
    route: Route
    mission: msn.Mission
    notes: tuple[str, ...]
    summary: dict


def _scout_route(site: CameraSite, spec: ScoutSpec, limits: Limits, flight: FlightModel, azimuth_known: bool,
                 takeoff_site: np.ndarray | None, step_deg: float):
    """The rows at ``step_deg`` and their route: (rows, notes, marker (N, 3), hold (N,), leg (N,), vehicle (N, 3), route)."""
    from dronecal_field.sampling.lattice import _facing_vehicle

    rows, notes = scout_rows(site.mount_height_m, spec, limits, azimuth_known, step_deg)
    pts, holds, legs = [], [], []
    for k, row in enumerate(rows):
        p, h = row_points(row)
        pts.append(p)
        holds.append(h)
        legs.append(np.full(len(p), k))
    marker = np.concatenate(pts)
    hold = np.concatenate(holds)
    leg = np.concatenate(legs)
    # one continuous pass: the drone stops only where the scout starts and ends (the rows' turns slow it down anyway)
    hold[1:-1] = 0.0
    vehicle, _ = _facing_vehicle(marker, limits.marker_offset_frd_m, np.zeros(2))
    lim = replace(limits, marker_size_m=spec.marker_size_m)
    route = plan_route(vehicle, marker, lim, replace(flight, speed_m_s=max(flight.speed_m_s, spec.speed_m_s)), takeoff_site=takeoff_site,
                       hold_s=hold, ordered=True, leg_speed_m_s=spec.speed_m_s, takeoff_alt_m=float(max(2.0, vehicle[0, 2])))
    return rows, list(notes), marker, hold, leg, vehicle, route


def make_scout(site: CameraSite, spec: ScoutSpec, limits: Limits, flight: FlightModel, azimuth_known: bool = True,
               takeoff_site: np.ndarray | None = None) -> Scout:
    """The scout for a camera at ``site`` (its azimuth only orients the rows when ``azimuth_known``)."""
    # the finest depression step whose scout still fits the two minutes: a low pole reaches few levels (the rest of the
    # view is ground inside the keep-out), so it gets more rows across the part it can reach; a tall pole's rows come
    # nearer (shorter) until the coarsest step fits
    tries = [(step, spec.far_m) for step in SCOUT_STEPS_DEG] + [(SCOUT_STEPS_DEG[-1], f) for f in (5.0, 4.5, 4.0) if f < spec.far_m]
    for step, far in tries:
        rows, notes, marker, hold, leg, vehicle, route = _scout_route(site, replace(spec, far_m=far), limits, flight, azimuth_known,
                                                                      takeoff_site, step)
        if route.flight_time_s <= MAX_SCOUT_S:
            break
    spec = replace(spec, far_m=far)
    if route.flight_time_s > MAX_SCOUT_S * 1.25:
        notes.append(f"the scout takes {route.flight_time_s:.0f} s, more than the {MAX_SCOUT_S:.0f} s aimed at: give --azimuth (rows instead of rings)")
    mission = msn.build_mission(route, site.R_enu_from_site, site.origin, site.mount_height_m, spec.speed_m_s,
                                geoid_separation_m=site.geoid_separation_m)
    summary = _summary(site, spec, rows, marker, vehicle, hold, leg, route, mission, notes, azimuth_known)
    return Scout(site=site, spec=spec, rows=rows, marker_site=marker, leg=leg, route=route, mission=mission, notes=tuple(notes), summary=summary)


def _summary(site, spec, rows, marker, vehicle, hold, leg, route, mission, notes, azimuth_known) -> dict:
    from dronecal_field import __version__
    from dronecal_field.geodesy import enu_to_geodetic

    enu = vehicle @ site.R_enu_from_site.T
    geo = enu_to_geodetic(enu, site.origin)
    seq = {it.grid_index: s for s, it in enumerate(mission.items, start=1) if it.label.startswith("grid")}
    home_h = mission.home_h_m
    grid = [{"index": i, "flight": 1, "order": int(np.flatnonzero(route.grid_order == i)[0]) if np.any(route.grid_order == i) else i,
             "mission_seq": seq.get(i), "marker_site_m": [round(float(v), 4) for v in marker[i]],
             "drone_site_m": [round(float(v), 4) for v in vehicle[i]], "drone_enu_m": [round(float(v), 4) for v in enu[i]],
             "lat_deg": float(geo[i, 0]), "lon_deg": float(geo[i, 1]), "h_m": round(float(geo[i, 2]), 4),
             "alt_m": round(float(geo[i, 2] - home_h), 3), "hold_s": float(hold[i]), "leg": int(leg[i])} for i in range(len(marker))]
    return {
        "format": "dronecal-field plan summary, version 2",
        "created_by": f"dronecal-field {__version__} plan --scout",
        "kind": "scout",
        "scout": {
            "text": (f"rows across the view of any camera with HFOV {spec.hfov_deg[0]:g}-{spec.hfov_deg[1]:g} deg, tilt "
                     f"{spec.tilt_deg[0]:g}-{spec.tilt_deg[1]:g} deg" + (f", azimuth {site.azimuth_deg:g} +- {spec.azimuth_tolerance_deg:g} deg"
                                                                      if azimuth_known else ", any azimuth (rings round the pole)")),
            "hfov_deg": list(spec.hfov_deg), "tilt_deg": list(spec.tilt_deg), "azimuth_deg": site.azimuth_deg if azimuth_known else None,
            "azimuth_tolerance_deg": spec.azimuth_tolerance_deg if azimuth_known else 180.0, "marker_size_m": spec.marker_size_m,
            "rows": [{"x_m": r.x_m, "z_m": r.z_m, "y_from_m": r.y_from_m, "y_to_m": r.y_to_m, "x_to_m": r.x_to_m, "z_to_m": r.z_to_m,
                      "depression_deg": round(r.depression_deg, 1), "ring": r.ring} for r in rows],
            "not_reached": list(notes), "then": "fly it, then: dronecal-field plan --from-run RUN.mcap --out DIR",
        },
        "altitude_frame": mission.alt_frame, "altitude_frame_text": mission.alt_frame_text,
        "enu_origin": {"lat_deg": site.lat_deg, "lon_deg": site.lon_deg, "h_m": site.ground_h_m},
        "site_frame": {"azimuth_deg": site.azimuth_deg, "R_enu_from_site": np.round(site.R_enu_from_site, 12).tolist()},
        "geoid_separation_m": site.geoid_separation_m,
        "camera_site": {"mount_height_m": site.mount_height_m, "azimuth_deg": site.azimuth_deg if azimuth_known else None,
                        "position_enu_m": [0.0, 0.0, site.mount_height_m]},
        "marker": {"size_m": spec.marker_size_m},
        "points": len(marker),
        "grid": grid,
        "flight": {"flight_time_s": round(route.flight_time_s, 1), "path_length_m": round(route.path_length_m, 1),
                   "leg_speed_m_s": spec.speed_m_s, "n_flights": 1,
                   "takeoff": {"lat_deg": mission.home_lat_deg, "lon_deg": mission.home_lon_deg}},
    }


def write_scout(scout: Scout, out_dir: str | Path, keep_out_m: float) -> list[Path]:
    """Write mission.plan, mission.waypoints, mission.geojson and plan.json atomically into ``out_dir``."""
    from dronecal_field.geodesy import enu_to_geodetic
    from dronecal_field.outfolder import replace_folder, staged_folder
    from dronecal_field.plan.schema import validate_plan

    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "plan.json").is_file())):
        raise InputError(f"--out {out} exists and is not a plan folder: choose a new folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    site = scout.site
    pts = np.vstack([scout.route.points, scout.route.takeoff_site[None]])
    fence_site = msn.fence_polygon(pts, 3.0)
    fence = enu_to_geodetic(np.column_stack([fence_site, np.zeros(len(fence_site))]) @ site.R_enu_from_site.T, site.origin)[:, :2]
    ko = (site.lat_deg, site.lon_deg, keep_out_m) if keep_out_m > 0 else None
    plan = msn.qgc_plan(scout.mission, fence, ko, scout.spec.speed_m_s)
    validate_plan(plan)
    feats = []
    g = scout.summary["grid"]
    for p in g:
        feats.append(msn.point_feature(p["lon_deg"], p["lat_deg"], p["h_m"], {"kind": "scout", "index": p["index"], "leg": p["leg"], "hold_s": p["hold_s"]}))
    with staged_folder(out) as tmp:
        (tmp / "mission.plan").write_text(msn.dumps(plan), encoding="utf-8")
        (tmp / "mission.waypoints").write_text(msn.waypoints_text(scout.mission), encoding="utf-8")
        (tmp / "mission.geojson").write_text(msn.dumps(msn.geojson(feats, "dronecal-field scout; [lon, lat, h] h ellipsoidal")), encoding="utf-8")
        (tmp / "plan.json").write_text(msn.dumps({**scout.summary, "fence": {"inclusion_polygon_latlon": fence.tolist()}}), encoding="utf-8")
        replace_folder(tmp, out, lambda name: name in SCOUT_FILES)
    return [out / f for f in SCOUT_FILES]


def scout_seen(camera, scout: Scout, limits: Limits, gnss_hz: float = 10.0) -> np.ndarray:
    """(S,) bool per marker position along the scout's legs (a fix every speed / gnss_hz m): the whole marker in ``camera``'s
    image (site frame). What a camera of the band records of the scout."""
    from dronecal_field.sampling.band import markers_in_view

    step = scout.spec.speed_m_s / gnss_hz
    samples = []
    m = scout.marker_site
    for a, b, la, lb in zip(m[:-1], m[1:], scout.leg[:-1], scout.leg[1:]):
        if la != lb:
            continue
        n = max(1, int(np.linalg.norm(b - a) // step))
        f = (np.arange(n + 1) / n)[:, None]
        samples.append(a + f * (b - a))
    S = np.concatenate(samples)
    return S, markers_in_view(camera, S, replace(limits, marker_size_m=scout.spec.marker_size_m))


def scout_from_options(opts: dict) -> tuple[Scout, float]:
    """The scout of resolved ``plan`` options (``--scout``): the pole, its height, the azimuth if known; returns it and the keep-out (m)."""
    from dronecal_field.plan.stage import _need, _opt

    lat = _need(opts, "lat", "the camera pole's latitude in degrees")
    lon = _need(opts, "lon", "the camera pole's longitude in degrees")
    g_h, g_amsl, n = opts.get("ground_alt"), opts.get("ground_amsl"), opts.get("geoid_separation")
    if g_h is None and g_amsl is None:
        raise InputError("missing ground height: give --ground-alt (ellipsoidal, m) or --ground-amsl with --geoid-separation")
    if g_h is None:
        if n is None:
            raise InputError("--ground-amsl needs --geoid-separation N: or give --ground-alt (ellipsoidal)")
        g_h = g_amsl + n
    mount = float(_need(opts, "mount_height", "the camera height above the ground in metres"))
    if not 1.0 <= mount <= 30.0:
        raise InputError(f"--mount-height {mount:g} m is outside 1-30 m: the scout flies rows a few metres from a pole camera")
    az = opts.get("azimuth")
    site = CameraSite(lat_deg=lat, lon_deg=lon, ground_h_m=float(g_h), mount_height_m=mount, azimuth_deg=float(az or 0.0) % 360.0,
                      tilt_deg=0.0, geoid_separation_m=n)
    keep_out = float(_opt(opts, "keep_out"))
    limits = Limits(min_agl_m=float(_opt(opts, "min_agl")), max_agl_m=opts.get("max_agl"), keep_out_m=keep_out,
                    marker_offset_frd_m=tuple(_opt(opts, "marker_offset")), max_search_height_m=mount + 3.0)
    spec = ScoutSpec(marker_size_m=float(opts.get("marker_size") or 0.4))
    takeoff = None
    if opts.get("takeoff") is not None:
        from dronecal_field.plan.site import latlon_to_site

        t = opts["takeoff"]
        takeoff = latlon_to_site(site, np.array([[t[0], t[1]]]), t[2] if len(t) > 2 else site.ground_h_m)[0]
    return make_scout(site, spec, limits, FlightModel(), azimuth_known=az is not None, takeoff_site=takeoff), keep_out


def format_scout(scout: Scout, out: str) -> str:
    """What ``plan --scout`` prints."""
    s = scout.summary
    lines = [f"scout: {s['scout']['text']}",
             f"{len(scout.rows)} {'rings' if scout.rows[0].ring else 'rows'} ({', '.join(f'{r.depression_deg:.0f}' for r in scout.rows)} deg below the "
             f"camera's horizon), {s['points']} waypoints, legs at {scout.spec.speed_m_s:g} m/s, marker {scout.spec.marker_size_m:g} m",
             f"flight: {scout.route.flight_time_s / 60:.1f} min ({scout.route.path_length_m:.0f} m)"]
    lines += [f"  not reached: {n}" for n in scout.notes]
    lines.append(f"next: fly it (dronecal-field fly --mission {out}/mission.plan ...), then dronecal-field plan --from-run RUN.mcap --out DIR")
    return "\n".join(lines)
