"""The ``plan`` stage for a site: several cameras, one mission (issue 24).

Steps (each a function below):

1. :func:`prepare_camera`: each camera's own guess, ROI and image-space
   candidate layouts (``sampling.design`` via ``plan.strategies``), exactly
   as a single-camera plan scores them, in the camera's own site frame;
2. :func:`choose_marker`: one marker for every camera (one is carried);
3. :func:`select_layouts`: one layout per camera so the merged flight fits
   the budget: every camera starts with the layout a single-camera plan
   would fly; while the merged route is too long, the camera whose cheaper
   layout costs the least predicted error per second saved switches to it;
4. :func:`merge_points`: the layouts' holds in one frame (the first camera's
   site frame), camera after camera (each group entered from its end
   nearest the previous one), holds of two cameras on the same pole that
   lie within :data:`MERGE_RADIUS_M` of each other flown once;
5. :func:`cross_visibility`: every sample (hold or fix along a leg) is
   checked in every camera: screened as the camera's own design screens
   (whole marker in the image of its guess and its guess band's cameras),
   at least ``min_marker_px`` across after foreshortening, facing the
   camera within :data:`MAX_FACING_DEG`; a hold counts for every camera
   that reads it, a fix along a leg only for its own camera (its speed and
   timing noise were chosen for that camera's focal length and distance);
6. route, flights and missions (``plan.siteroute``) with the single-camera code (``plan.route``,
   ``plan.mission``; the other poles detoured like the first), then the yaw is retargeted:
   at every point the nose (and the marker on it) faces the pole of the
   camera the point was designed for (``DO_SET_ROI`` at that camera, one
   per camera group, or a ``CONDITION_YAW`` per point);
7. per camera: coverage of its ROI and the predicted error from all the
   samples it sees (``sampling.predict``), in plan.json and on stdout.

Pure: no files (``plan.sitefiles`` writes them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from dronecal_field.core.camera import Camera, CameraPose
from dronecal_field.errors import InputError, PlanError
from dronecal_field.geodesy import geodetic_to_enu
from dronecal_field.plan import mission as msn
from dronecal_field.plan.route import Route
from dronecal_field.plan.siteroute import one_route, pole_clearance, retarget_yaw, route_request, site_flights
from dronecal_field.plan.stage import (
    COVERAGE_SLACK,
    EQUIVALENT_ERROR,
    LAYOUT_COVERAGE_SLACK,
    PlanRequest,
    _check_sees_ground,
)
from dronecal_field.sampling.band import screen_cameras

# Candidate layouts of a site: lattices down to 3x3 (a site shares one battery), two depths per ray as far apart as the
# ray allows, none nearer than 4 m where it allows (the single-camera plans' usual pick). Few: each is timed by the route.
SITE_LATTICES: tuple[tuple[int, int], ...] = ((3, 3), (4, 3), (5, 4))
SITE_DEPTHS: tuple[tuple[int, float | None, float | None], ...] = ((2, None, 4.0),)
MAX_FACING_DEG = 60.0  # a marker turned further from a camera is read unreliably (ArUco corner refinement)
MERGE_RADIUS_M = 0.5  # holds of cameras on one pole this close are flown once
UPGRADE_TRIES = 6  # route timings spent giving back time the downgrades over-saved
COVERAGE_WEIGHT = 5.0  # a layout switch that loses 10 % of a camera's ROI costs as much as a 65 % larger error


@dataclass(frozen=True, eq=False)
class SiteCamera:
    """One camera of the site: its request, guess (own site frame, own ENU and the site's frame), ROI and candidates."""

    name: str
    pole: str
    request: PlanRequest
    camera_site: Camera  # world = its own site frame (X along its azimuth, origin at its pole's foot)
    camera_enu: Camera  # world = ENU at its pole's foot
    camera_ref: Camera  # world = the site's frame (the first camera's site frame)
    R_ref_from_own: np.ndarray  # (3, 3)
    t_ref_from_own: np.ndarray  # (3,) its pole's foot in the site's frame, m
    roi: Any
    noise: Any
    draws: np.ndarray
    candidates: tuple

    def to_ref(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) own site frame -> the site's frame."""
        return np.atleast_2d(np.asarray(p, float)) @ self.R_ref_from_own.T + self.t_ref_from_own

    def from_ref(self, p: np.ndarray) -> np.ndarray:
        """(N, 3) the site's frame -> own site frame."""
        return (np.atleast_2d(np.asarray(p, float)) - self.t_ref_from_own) @ self.R_ref_from_own


@dataclass(frozen=True, eq=False)
class SiteRequest:
    """A validated site: its cameras' requests (the first one's shared options fly the mission)."""

    cameras: tuple[tuple[str, str, PlanRequest], ...]  # (name, pole, request)
    name: str | None = None

    @property
    def base(self) -> PlanRequest:
        return self.cameras[0][2]


@dataclass(frozen=True, eq=False)
class MergedPoints:
    """The holds of every camera's layout in flight order, in the site's frame.

    ``marker`` / ``vehicle`` (N, 3) m, ``hold_s`` (N,), ``owner`` (N,) camera
    index whose pole the nose faces, ``also`` (N,) list of further camera indices
    whose layout had the same hold (merged), ``samples`` (S, 3) every
    prediction sample, ``samples_sigma_h_m``, ``samples_rtk_factor``,
    ``samples_owner`` (S,).
    """

    marker: np.ndarray
    vehicle: np.ndarray
    hold_s: np.ndarray
    leg: np.ndarray
    owner: np.ndarray
    also: tuple[tuple[int, ...], ...]
    marker_px: np.ndarray
    samples: np.ndarray
    samples_sigma_h_m: np.ndarray
    samples_rtk_factor: np.ndarray
    samples_owner: np.ndarray
    leg_speed_m_s: float | None
    cruise_m_s: float | None


@dataclass(frozen=True, eq=False)
class SitePlan:
    """A finished site plan."""

    request: SiteRequest
    cameras: tuple[SiteCamera, ...]
    chosen: tuple  # ImageCandidate per camera
    marker_size_m: float
    points: MergedPoints
    seen_samples: np.ndarray  # (C, S) bool
    seen_holds: np.ndarray  # (C, N) bool
    routes: tuple[Route, ...]
    missions: tuple[msn.Mission, ...]
    point_flight: np.ndarray
    fence_site: np.ndarray
    predictions: tuple  # RoiPrediction | None per camera
    coverage: tuple[float, ...]
    budget_s: float
    fits_budget: bool
    warnings: tuple[str, ...]
    summary: dict

    @property
    def base(self) -> PlanRequest:
        return self.request.base

    def mission_names(self) -> list[str]:
        return ["mission"] if len(self.missions) == 1 else [f"mission-{k + 1}" for k in range(len(self.missions))]


# --------------------------------------------------------------------------
# 1. each camera on its own


def _guess_cameras(req: PlanRequest, distortion) -> tuple[Camera, Camera]:
    """(own site frame, own ENU) guessed camera, with coefficients given in the site file or the scout's estimate."""
    from dronecal_field.plan.site import guess_camera

    cam_site = guess_camera(req.site, req.lens, frame="site")
    cam_enu = guess_camera(req.site, req.lens, frame="enu")
    if req.camera_enu is not None:
        cam_enu = req.camera_enu
        R_site = np.asarray(cam_enu.pose.R_cam_from_world) @ req.site.R_enu_from_site
        cam_site = cam_enu.with_(pose=CameraPose.from_position(R_site, req.site.R_enu_from_site.T @ cam_enu.pose.position_world), enu_origin=None)
    elif distortion is not None:
        cam_site, cam_enu = cam_site.with_(distortion=distortion), cam_enu.with_(distortion=distortion)
    return cam_site, cam_enu


def prepare_camera(name: str, pole: str, req: PlanRequest, ref: PlanRequest, distortion=None) -> SiteCamera:
    """The camera's guess in its own and the site's frames, its ROI, and its scored candidate layouts."""
    from dronecal_field.plan.strategies import image_candidate_params, score_image_candidates
    from dronecal_field.sampling.design import SAMPLINGS
    from dronecal_field.sampling.predict import NoiseModel, lens_draws, normalised_radius
    from dronecal_field.sampling.roi import build_roi, evaluation_points

    cam_site, cam_enu = _guess_cameras(req, distortion)
    try:
        _check_sees_ground(req, cam_site)
    except PlanError as exc:
        raise PlanError(f"camera {name!r}: {exc}") from None
    # own frame -> the site's frame: through ENU at each pole (poles tens of metres apart: the ENU axes agree to microradians)
    t_enu = geodetic_to_enu(req.site.lat_deg, req.site.lon_deg, req.site.ground_h_m, ref.site.origin)[0]
    R_ref_from_own = ref.site.R_enu_from_site.T @ req.site.R_enu_from_site
    t_ref = ref.site.R_enu_from_site.T @ t_enu
    R_cam_ref = np.asarray(cam_site.pose.R_cam_from_world) @ R_ref_from_own.T
    cam_ref = cam_site.with_(pose=CameraPose.from_position(R_cam_ref, R_ref_from_own @ cam_site.pose.position_world + t_ref))
    # the guess band's cameras a point must be in view of, as ``stage.make_plan`` screens a single camera: each factor
    # at its tolerance alone; points lost only at the band's combined extremes are kept (sampling.band.screen_cameras)
    req = replace(req, limits=replace(req.limits, band=screen_cameras(cam_site, req.band)))
    roi = build_roi(cam_site, req.roi)
    roi_pts, _ = evaluation_points(roi)
    draws = lens_draws(cam_site, cam_site.distortion.as_array(), float(normalised_radius(cam_site, roi_pts).max()), seed=req.evaluation.seed)
    noise = NoiseModel(sigma_px=req.evaluation.sigma_px, sigma_h_m=req.evaluation.sigma_h_m, sigma_v_m=req.evaluation.sigma_v_m,
                       model="auto" if req.evaluation.model == "default" else req.evaluation.model)
    samplings = SAMPLINGS if req.sampling == "auto" else (req.sampling,)
    params = image_candidate_params(req.marker_sizes_m, samplings, lattices=SITE_LATTICES, depths=SITE_DEPTHS)
    cands = score_image_candidates(cam_site, roi, params, req.limits, req.flight, req.timing, noise, draws, end=req.end)
    if not any(c.usable for c in cands):
        from dronecal_field.plan.stage import _no_image_plan_error

        raise PlanError(f"camera {name!r}: {_no_image_plan_error(req, cands)}")
    return SiteCamera(name=name, pole=pole, request=req, camera_site=cam_site, camera_enu=cam_enu, camera_ref=cam_ref,
                      R_ref_from_own=R_ref_from_own, t_ref_from_own=t_ref, roi=roi, noise=noise, draws=draws, candidates=cands)


# --------------------------------------------------------------------------
# 2.-3. one marker, one layout per camera


def choose_marker(cams: tuple[SiteCamera, ...], sizes: tuple[float, ...]) -> float:
    """The smallest marker every camera covers its ROI with (within COVERAGE_SLACK of its best), else the one covering most in sum."""
    cov = np.array([[max((c.design.coverage for c in cam.candidates if c.usable and c.design.params.marker_size_m == m), default=-1.0)
                     for m in sizes] for cam in cams])  # (C, M)
    good = np.all(cov >= cov.max(axis=1, keepdims=True) - COVERAGE_SLACK, axis=0)
    if good.any():
        return float(sizes[int(np.flatnonzero(good)[0])])
    return float(sizes[int(np.argmax(np.where(cov < 0, -10.0, cov).sum(axis=0)))])


def _pool(cam: SiteCamera, size: float) -> list:
    return [c for c in cam.candidates if c.usable and c.design.params.marker_size_m == size and c.flight_time_s is not None]


def _single_choice(pool: list) -> Any:
    """The layout a single-camera plan would fly (``stage._choose_image``'s rule without a budget)."""
    top = max(c.design.coverage for c in pool)
    cover = [c for c in pool if c.design.coverage >= top - LAYOUT_COVERAGE_SLACK]
    best = min(c.objective for c in cover)
    return min((c for c in cover if c.objective <= EQUIVALENT_ERROR * best), key=lambda c: (c.flight_time_s, c.objective))


def select_layouts(cams: tuple[SiteCamera, ...], size: float, budget_s: float, flight_time) -> tuple[list, float, bool]:
    """One layout per camera whose merged flight (``flight_time(layouts)`` s) fits ``budget_s``; greedy switches to
    cheaper layouts by predicted-error increase (and coverage loss) per second saved. Returns (layouts, time, fits)."""
    pools = [_pool(cam, size) for cam in cams]
    for cam, pool in zip(cams, pools):
        if not pool:
            raise PlanError(f"camera {cam.name!r}: no usable layout with the {size:g} m marker: add a marker size it can use (marker_sizes)")
    current = [_single_choice(p) for p in pools]
    t = flight_time(current)
    t_est = t
    for _ in range(200):
        if t_est <= budget_s:
            t = t_est = flight_time(current)  # the merged route, timed (an estimate steered here)
            if t <= budget_s:
                return _upgrade(pools, current, t, budget_s, flight_time)
        best = None
        for i, pool in enumerate(pools):
            cur = current[i]
            for c in pool:
                saved = cur.flight_time_s - c.flight_time_s
                if saved <= 1.0:
                    continue
                cost = (math.log(max(c.objective, 1e-9) / max(cur.objective, 1e-9))
                        + COVERAGE_WEIGHT * max(0.0, cur.design.coverage - c.design.coverage)) / saved
                if best is None or cost < best[0]:
                    best = (cost, i, c)
        if best is None:
            t = flight_time(current)
            return current, t, t <= budget_s
        # a switch saves about what the two layouts' own flights differ by (take-off and landing cancel out)
        t_est -= current[best[1]].flight_time_s - best[2].flight_time_s
        current[best[1]] = best[2]
    t = flight_time(current)
    return current, t, t <= budget_s


def _upgrade(pools: list, current: list, t: float, budget_s: float, flight_time, tries: int = UPGRADE_TRIES) -> tuple[list, float, bool]:
    """Give back time the downgrades over-saved: a switch can save more than the two layouts' own flights differ by
    (a slow fly-through layout sets the leg speed of every camera's legs). Better layouts, most error saved per second
    added first, each kept when the merged route still fits; at most ``tries`` route timings."""
    tried: set[tuple[int, int]] = set()
    for _ in range(tries):
        best = None
        for i, pool in enumerate(pools):
            cur = current[i]
            for c in pool:
                if (i, id(c)) in tried or c.objective >= cur.objective or c.design.coverage < cur.design.coverage - LAYOUT_COVERAGE_SLACK:
                    continue
                extra = c.flight_time_s - cur.flight_time_s
                if extra > budget_s - t:
                    continue
                gain = math.log(cur.objective / max(c.objective, 1e-9)) / max(extra, 1.0)
                if best is None or gain > best[0]:
                    best = (gain, i, c)
        if best is None:
            break
        _, i, c = best
        tried.add((i, id(c)))
        trial = list(current)
        trial[i] = c
        t_trial = flight_time(trial)
        if t_trial <= budget_s:
            current, t = trial, t_trial
    return current, t, True


# --------------------------------------------------------------------------
# 4. one sequence of holds


def merge_points(cams: tuple[SiteCamera, ...], layouts: list) -> MergedPoints:
    """The layouts' holds in the site's frame, one camera group after the other; near-equal holds of one pole flown once."""
    marker, vehicle, hold, leg, owner, px = [], [], [], [], [], []
    samples, s_sig, s_rtk, s_owner = [], [], [], []
    end = None
    leg_base = 0
    for i, (cam, c) in enumerate(zip(cams, layouts)):
        d = c.design
        m, v = cam.to_ref(d.marker_site), cam.to_ref(d.vehicle_site)
        idx = np.arange(len(m))
        if end is not None and np.linalg.norm(v[-1, :2] - end[:2]) < np.linalg.norm(v[0, :2] - end[:2]):
            idx = idx[::-1]  # legs are held at both ends: flown backwards they are the same legs
        marker.append(m[idx])
        vehicle.append(v[idx])
        hold.append(d.hold_s[idx])
        leg.append(d.leg[idx] + leg_base)
        leg_base += int(d.leg.max()) + 1 if len(d.leg) else 0
        owner.append(np.full(len(idx), i))
        px.append(d.marker_px[idx])
        end = v[idx][-1]
        samples.append(cam.to_ref(d.samples_site))
        s_sig.append(d.samples_sigma_h_m)
        s_rtk.append(d.samples_rtk_factor)
        s_owner.append(np.full(len(d.samples_site), i))
    M, V, H, L, O, P = (np.concatenate(x) for x in (marker, vehicle, hold, leg, owner, px))
    also: list[list[int]] = [[] for _ in range(len(M))]
    keep = np.ones(len(M), bool)
    for j in range(len(M)):
        if not keep[j] or H[j] <= 0:
            continue
        for k in range(j):  # an earlier hold of another camera on the same pole, facing the same way
            if keep[k] and H[k] > 0 and O[k] != O[j] and cams[O[k]].pole == cams[O[j]].pole \
                    and np.linalg.norm(V[k] - V[j]) < MERGE_RADIUS_M:
                keep[j] = False
                also[k].append(int(O[j]))
                H[k] = max(H[k], H[j])
                break
    through = [c.design.speed_m_s for c in layouts if c.design.params.sampling == "through"]
    mixed = [c.design.speed_m_s for c in layouts if c.design.params.sampling == "mixed"]
    return MergedPoints(marker=M[keep], vehicle=V[keep], hold_s=H[keep], leg=L[keep], owner=O[keep],
                        also=tuple(tuple(a) for a, k in zip(also, keep) if k), marker_px=P[keep],
                        samples=np.concatenate(samples), samples_sigma_h_m=np.concatenate(s_sig), samples_rtk_factor=np.concatenate(s_rtk),
                        samples_owner=np.concatenate(s_owner), leg_speed_m_s=min(through) if through else None,
                        cruise_m_s=min(mixed) if mixed else None)


# --------------------------------------------------------------------------
# 5. who sees what


def marker_seen(camera_ref: Camera, marker: np.ndarray, facing_xy: np.ndarray, size_m: float, min_px: float,
                margin_px: float = 10.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which markers a camera reads: in front, centre in the image (``margin_px`` in), at least ``min_px`` across
    after foreshortening, turned at most MAX_FACING_DEG from the camera.

    Parameters
    ----------
    camera_ref : the camera, world = the site's frame
    marker : (N, 3) marker centres, m
    facing_xy : (N, 2) unit horizontal normals of the markers (the nose direction)
    size_m, min_px : marker side, m; smallest side the detector reads, px

    Returns
    -------
    (N,) bool seen, (N, 2) pixels, (N,) marker side in px (foreshortened)
    """
    marker = np.atleast_2d(np.asarray(marker, float))
    depth = camera_ref.depth(marker)
    uv = camera_ref.project(marker)
    w, h = camera_ref.width, camera_ref.height
    inside = (depth > 0.3) & np.all(np.isfinite(uv), axis=1)
    inside &= (uv[:, 0] >= margin_px) & (uv[:, 0] <= w - 1 - margin_px) & (uv[:, 1] >= margin_px) & (uv[:, 1] <= h - 1 - margin_px)
    c = camera_ref.pose.position_world
    to_cam = c[None, :2] - marker[:, :2]
    horiz = np.linalg.norm(to_cam, axis=1)
    cos_a = np.einsum("ij,ij->i", facing_xy, to_cam) / np.maximum(horiz, 1e-9)
    dist = np.linalg.norm(c[None] - marker, axis=1)
    px = camera_ref.intrinsics.fx * size_m / np.maximum(dist, 1e-9) * np.clip(cos_a, 0.0, 1.0)
    ok = inside & (cos_a >= math.cos(math.radians(MAX_FACING_DEG))) & (px >= min_px)
    return ok, uv, px


def facing(cams: tuple[SiteCamera, ...], points: np.ndarray, owner: np.ndarray) -> np.ndarray:
    """(N, 2) unit horizontal directions from the points to their owner camera's pole (the nose, and the marker, face it)."""
    poles = np.array([cam.t_ref_from_own[:2] for cam in cams])[owner]
    d = poles - np.asarray(points, float)[:, :2]
    return d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)


def cross_visibility(cams: tuple[SiteCamera, ...], pts: MergedPoints, size_m: float, min_px: float) -> tuple[np.ndarray, np.ndarray]:
    """(C, S) samples and (C, N) holds each camera reads; a camera always keeps the samples of its own layout
    (screened with its guess band when designed)."""
    C = len(cams)
    fs, fh = facing(cams, pts.samples, pts.samples_owner), facing(cams, pts.marker, pts.owner)
    seen_s = np.zeros((C, len(pts.samples)), bool)
    seen_h = np.zeros((C, len(pts.marker)), bool)
    from dronecal_field.sampling.lattice import screen_points

    for i, cam in enumerate(cams):
        # as the camera's own design screens: the whole marker (quiet zone, margin) in the image of its guess and of
        # its guess band's cameras, so another camera's sample near the border, where the lens is least known, is not counted
        lim = replace(cam.request.limits, marker_size_m=size_m)
        band_s = screen_points(cam.camera_site, cam.from_ref(pts.samples), lim)["in_view"]
        band_h = screen_points(cam.camera_site, cam.from_ref(pts.marker), lim)["in_view"]
        # a fix along a leg counts for the camera it was designed for only: its speed, blur and timing noise were chosen
        # for that camera's focal length and distance (another camera's fixes raised the 4K's predicted noise 9 -> 17 px)
        sharp = pts.samples_sigma_h_m <= 0
        seen_s[i] = (marker_seen(cam.camera_ref, pts.samples, fs, size_m, min_px)[0] & band_s & sharp) | (pts.samples_owner == i)
        seen_h[i] = (marker_seen(cam.camera_ref, pts.marker, fh, size_m, min_px)[0] & band_h) | (pts.owner == i)
        seen_h[i] |= np.array([i in a for a in pts.also])
    return seen_s, seen_h


# --------------------------------------------------------------------------
# the stage


def make_site_plan(site: SiteRequest, distortions: dict | None = None) -> SitePlan:
    """Plan one mission (or the fewest flights) for every camera of ``site``; see the module docstring for the steps."""
    from dronecal_field.plan.sitereport import site_summary
    from dronecal_field.plan.strategies import predict_points_on_roi

    base = site.base
    distortions = distortions or {}
    cams = tuple(prepare_camera(n, p, r, base, distortions.get(n)) for n, p, r in site.cameras)
    sizes = tuple(sorted(set(base.marker_sizes_m)))
    size = choose_marker(cams, sizes)
    budget = base.choice_budget_s
    warnings = [f"camera {n!r}: {w}" for n, _, r in site.cameras for w in r.notes]

    def flight_time(layouts: list) -> float:
        return one_route(cams, base, merge_points(cams, layouts), size).flight_time_s

    layouts, t_one, fits = select_layouts(cams, size, budget, flight_time)
    pts = merge_points(cams, layouts)
    min_px = base.limits.min_marker_px
    seen_s, seen_h = cross_visibility(cams, pts, size, min_px)
    rreq = route_request(base, size, budget, pts.cruise_m_s)
    routes, flight_of = site_flights(cams, rreq, pts)
    if len(routes) > 1:
        warnings.append(f"the site's layouts take {t_one / 60:.1f} min even at the cheapest: split into {len(routes)} flights "
                        f"(mission-1 ... mission-{len(routes)}) within {budget / 60:g} min each")
    missions = []
    for r in routes:
        m = msn.build_mission(r, base.site.R_enu_from_site, base.site.origin, base.site.mount_height_m, rreq.flight.speed_m_s,
                              alt_frame=base.alt_frame, yaw_mode=base.yaw_mode, geoid_separation_m=base.site.geoid_separation_m)
        missions.append(retarget_yaw(m, r, cams, pts.owner, base, base.yaw_mode))
    datum = msn.home_datum_warning(missions[0])
    if datum is not None:
        warnings.append(datum)
    for r in routes:
        for pole, d in pole_clearance(cams, r):
            warnings.append(f"a leg passes {d:.1f} m from pole {pole!r}, inside its keep-out: fly that leg by hand or give --takeoff on the far side")
    for cam in cams[1:]:
        c = cam.t_ref_from_own[:2]
        if np.linalg.norm(routes[0].takeoff_site[:2] - c) < cam.request.limits.keep_out_m:
            raise PlanError(f"the take-off point is inside pole {cam.pole!r}'s keep-out: give takeoff = [lat, lon] away from the poles")
    fence = msn.fence_polygon(np.vstack([r.points for r in routes] + [routes[0].takeoff_site[None]]), 3.0)
    predictions, coverage = [], []
    for i, cam in enumerate(cams):
        S = cam.from_ref(pts.samples[seen_s[i]])
        coverage.append(float(cam.roi.coverage(cam.camera_site.project(S))))
        try:
            predictions.append(predict_points_on_roi(cam.camera_site, S, cam.roi, cam.noise, cam.draws,
                                                     pts.samples_sigma_h_m[seen_s[i]], pts.samples_rtk_factor[seen_s[i]]))
        except Exception as exc:  # a degenerate sample set must not sink the plan: say so per camera
            warnings.append(f"camera {cam.name!r}: no prediction ({exc})")
            predictions.append(None)
    plan = SitePlan(request=site, cameras=cams, chosen=tuple(layouts), marker_size_m=size, points=pts, seen_samples=seen_s,
                    seen_holds=seen_h, routes=tuple(routes), missions=tuple(missions), point_flight=flight_of, fence_site=fence,
                    predictions=tuple(predictions), coverage=tuple(coverage), budget_s=budget, fits_budget=fits and len(routes) == 1,
                    warnings=tuple(warnings), summary={})
    return replace(plan, summary=site_summary(plan))


def site_request(spec) -> tuple[SiteRequest, dict]:
    """The validated requests of a ``plan.multisite.SiteSpec`` (one per camera), and the coefficients given per camera."""
    from dronecal_field.plan.site import resolve_options
    from dronecal_field.plan.stage import request_from_options

    cams = []
    dists = {}
    for c in spec.cameras:
        where = f"site file {spec.path}: camera {c.name!r}"
        try:
            opts = resolve_options(c.values)
            if c.from_run is not None:
                from dronecal_field.plan.fromrun import estimate_from_run, request_from_estimate

                req = request_from_estimate(estimate_from_run(c.from_run), opts)
            else:
                req = request_from_options(opts)
        except InputError as exc:
            raise InputError(f"{where}: {exc}") from None
        except PlanError as exc:
            raise PlanError(f"{where}: {exc}") from None
        if c.distortion is not None:
            from dronecal_field.sampling.band import scaled_distortion

            from dronecal_field.plan.site import OPTION_BY_KEY

            raw = c.values.get("distortion_range")
            shares = OPTION_BY_KEY["distortion_range"].parse(raw) if raw is not None else ("0.5", "1")
            lo, hi = (float(shares[0]), float(shares[-1])) if all(_is_number(v) for v in shares) else (0.5, 1.0)
            band = replace(req.band, distortions=(scaled_distortion(c.distortion, lo), scaled_distortion(c.distortion, hi)),
                           distortion_names=(f"{lo:g}x given", f"{hi:g}x given"))
            req = replace(req, band=band)
            dists[c.name] = c.distortion
        cams.append((c.name, c.pole or c.name, req))
    return SiteRequest(cameras=tuple(cams), name=spec.name), dists


def _is_number(v: Any) -> bool:
    try:
        float(v)
        return True
    except (TypeError, ValueError):
        return False
