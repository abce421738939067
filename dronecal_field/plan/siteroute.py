"""The route and missions of a site plan (``plan.multiplan``): the first camera's site frame, every pole detoured, and the
nose turned to the camera each point serves.

Pure functions over ``plan.multiplan``'s ``SiteCamera`` and ``MergedPoints`` (duck-typed here: that module imports
this one).
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from dronecal_field.geodesy import enu_to_geodetic, geodetic_to_enu
from dronecal_field.plan import mission as msn
from dronecal_field.plan.route import Route, plan_route
from dronecal_field.plan.stage import PlanRequest

if TYPE_CHECKING:
    from dronecal_field.plan.multiplan import MergedPoints, SiteCamera


def route_request(base: PlanRequest, size: float, budget_s: float, cruise_m_s: float | None) -> PlanRequest:
    """The first camera's request as the route's: its site frame, keep-out at its pole, no per-pole range, the site's budget."""
    limits = replace(base.limits, marker_size_m=size, max_range_m=None, band=())
    flight = base.flight if cruise_m_s is None else replace(base.flight, speed_m_s=min(base.flight.speed_m_s, cruise_m_s))
    return replace(base, limits=limits, flight=flight, evaluation=replace(base.evaluation, max_flight_time_s=budget_s))


def _other_poles(cams: tuple[SiteCamera, ...]) -> list[tuple[np.ndarray, float]]:
    """(centre (3,) on the ground, keep-out m) of every pole but the first (``plan.route`` detours round the first)."""
    out, seen = [], {cams[0].pole}
    for cam in cams:
        if cam.pole not in seen:
            seen.add(cam.pole)
            out.append((np.array([cam.t_ref_from_own[0], cam.t_ref_from_own[1], 0.0]), cam.request.limits.keep_out_m))
    return out


def with_detours(cams: tuple[SiteCamera, ...], pts: MergedPoints) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The holds with pass-through waypoints round the other poles' keep-outs (``plan.route.detour`` moved to each pole)
    between holds whose straight leg would cross one. Returns vehicle (K, 3), marker (K, 3), hold_s (K,) and (K,) index
    of the hold each row is (-1 for a detour waypoint)."""
    from dronecal_field.plan.route import detour

    V, M, H = [], [], []
    real: list[int] = []
    others = _other_poles(cams)
    for k in range(len(pts.vehicle)):
        if k > 0 and others:
            chain = [pts.vehicle[k - 1], pts.vehicle[k]]
            for c, r in others:
                out = [chain[0]]
                for a, b in zip(chain[:-1], chain[1:]):
                    out += [q + c for q in detour(a - c, b - c, r)] + [b]
                chain = out
            for q in chain[1:-1]:
                V.append(q)
                M.append(q)
                H.append(0.0)
                real.append(-1)
        V.append(pts.vehicle[k])
        M.append(pts.marker[k])
        H.append(pts.hold_s[k])
        real.append(k)
    return np.asarray(V), np.asarray(M), np.asarray(H), np.asarray(real)


def _as_detours(route: Route, real: np.ndarray) -> Route:
    """The route with the rows of ``with_detours`` mapped back: hold indices, detour waypoints as 'detour'."""
    g = np.where(route.grid_index >= 0, real[np.maximum(route.grid_index, 0)], -1)
    kind = tuple("detour" if (k == "grid" and gi < 0) else k for k, gi in zip(route.kind, g))
    return replace(route, grid_index=g, kind=kind)


def site_flights(cams: tuple[SiteCamera, ...], req: PlanRequest, pts: MergedPoints) -> tuple[tuple[Route, ...], np.ndarray]:
    """One route, or consecutive flights within ``req.choice_budget_s`` (``plan.route.split_into_flights``), with every pole
    detoured; and per hold (N,) the flight (0-based) that flies it first."""
    from dronecal_field.plan.route import split_into_flights

    V, M, H, real = with_detours(cams, pts)
    one = plan_route(V, M, req.limits, req.flight, takeoff_site=req.takeoff_site, end=req.end, hold_s=H, ordered=True,
                     leg_speed_m_s=pts.leg_speed_m_s)
    routes = [one]
    if one.flight_time_s > req.choice_budget_s:
        endurance_s = req.choice_budget_s / (1.0 - req.reserve)
        routes = split_into_flights(V, M, H, req.limits, req.flight, endurance_s, reserve=req.reserve, takeoff_site=one.takeoff_site,
                                    end=req.end, ordered=True, leg_speed_m_s=pts.leg_speed_m_s)
    routes = [_as_detours(r, real) for r in routes]
    flight_of = np.full(len(pts.vehicle), -1)
    for k, r in enumerate(routes):
        g = r.grid_order
        flight_of[g[flight_of[g] < 0]] = k
    return tuple(routes), flight_of


def one_route(cams: tuple[SiteCamera, ...], base: PlanRequest, pts: MergedPoints, size: float) -> Route:
    """The merged holds as one flight (for the budget)."""
    req = route_request(base, size, math.inf, pts.cruise_m_s)
    V, M, H, real = with_detours(cams, pts)
    return plan_route(V, M, req.limits, req.flight, takeoff_site=req.takeoff_site, end=req.end, hold_s=H, ordered=True,
                      leg_speed_m_s=pts.leg_speed_m_s)


def pole_clearance(cams: tuple[SiteCamera, ...], route: Route) -> list[tuple[str, float]]:
    """(pole, closest approach m) of every pole other than the first that a leg passes within its keep-out."""
    from dronecal_field.plan.route import _segment_clearance

    out: dict[str, float] = {}
    path = np.vstack([route.takeoff_site[None], route.takeoff_site[None] + [0, 0, route.takeoff_alt_m], route.points])
    for cam in cams[1:]:
        c = cam.t_ref_from_own[:2]
        if np.linalg.norm(c) < 0.5 or cam.pole in out:
            continue
        ko = cam.request.limits.keep_out_m
        d = min(_segment_clearance(a[:2] - c, b[:2] - c)[0] for a, b in zip(path[:-1], path[1:]))
        if d < ko - 1e-6:
            out[cam.pole] = d
    return list(out.items())


def retarget_yaw(mission: msn.Mission, route: Route, cams: tuple[SiteCamera, ...], owner: np.ndarray, base: PlanRequest,
                 yaw_mode: str) -> msn.Mission:
    """The mission with the nose facing each point's owner camera: yaw of every waypoint (and CONDITION_YAW), and one
    DO_SET_ROI at the owner camera wherever the owner changes (a DO item after a NAV item runs as the drone sets off to it)."""
    R = base.site.R_enu_from_site
    origin = base.site.origin
    home_h = mission.home_h_m
    cam_enu = np.array([R @ cam.camera_ref.pose.position_world for cam in cams])  # (C, 3) ENU at the site origin
    cam_geo = enu_to_geodetic(cam_enu, origin)

    def alt_of(h: float) -> float:
        return round(h - home_h if mission.alt_frame == "relative" else h - (base.site.geoid_separation_m or 0.0), 3)

    def roi_item(i: int, gi: int) -> msn.MissionItem:
        return msn.MissionItem(msn.MAV_CMD_DO_SET_ROI, msn.MAV_FRAME_GLOBAL_RELATIVE_ALT if mission.alt_frame == "relative" else msn.MAV_FRAME_GLOBAL,
                               param1=msn.MAV_ROI_LOCATION, x=float(cam_geo[i, 0]), y=float(cam_geo[i, 1]), z=alt_of(float(cam_geo[i, 2])),
                               label=f"roi {cams[i].name}", grid_index=gi)

    # the owner of every NAV item: its grid point's; a detour takes the next grid point's, the way home the last one's
    nav = [k for k, it in enumerate(mission.items) if it.command == msn.MAV_CMD_NAV_WAYPOINT]
    owners: list[int] = []
    nxt = int(owner[route.grid_order[-1]]) if len(route.grid_order) else 0
    for k in reversed(nav):
        gi = mission.items[k].grid_index
        if gi >= 0:
            nxt = int(owner[gi])
        owners.append(nxt)
    owner_of = dict(zip(nav, owners[::-1]))
    items: list[msn.MissionItem] = []
    current = None
    for k, it in enumerate(mission.items):
        if it.label == "roi":
            if yaw_mode == "roi" and nav:  # where the single-camera mission sets its ROI: the first camera's, before the first waypoint
                current = owner_of[nav[0]]
                items.append(roi_item(current, -1))
            continue
        if it.command == msn.MAV_CMD_NAV_WAYPOINT:
            i = owner_of[k]
            p_enu = geodetic_to_enu(it.x, it.y, 0.0, origin)[0]
            yaw = float(msn.bearing_deg(p_enu[None, :2], cam_enu[i, :2])[0])
            items.append(replace(it, param4=round(yaw, 2)))
            if yaw_mode == "roi" and i != current:
                items.append(roi_item(i, it.grid_index))  # runs as the drone sets off to this waypoint
                current = i
            continue
        if it.command == msn.MAV_CMD_CONDITION_YAW:
            items.append(replace(it, param1=items[-1].param4 if items and items[-1].command == msn.MAV_CMD_NAV_WAYPOINT else it.param1))
            continue
        items.append(it)
    return replace(mission, items=tuple(items))
