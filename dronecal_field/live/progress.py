"""The live core: each flown waypoint's detections and point, the running calibration, coverage, the verdict.

Pure functions over arrays and records (no threads, no sockets), built from
the offline stage's own parts so that the live numbers mean what
``calibrate``'s do: the same detector (pipeline/detect.py), the same
per-hold point (pipeline/points.window_point over HoverWindow.stable), the
same solver (core/calibrate.py) and linearised uncertainty
(core/uncertainty.py). What differs is the amount of work: a few frames per
hold instead of every frame, legs thinned in the solve, no Monte-Carlo.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dronecal_field.core.camera import Camera
from dronecal_field.pipeline.detect import Detection
from dronecal_field.pipeline.hover import HoverWindow
from dronecal_field.pipeline.points import PointOptions, WaypointPoint, marker_track_at, window_point
from dronecal_field.pipeline.sampling import SamplingOptions

MIN_SOLVE_POINTS = 6  # as calibrate (pipeline.run.MIN_POINTS)
NOT_DETECTED = "marker not detected"
NO_FRAMES = "no video frames recorded there"


@dataclass(frozen=True)
class LiveOptions:
    """How much work the live pipeline does per waypoint (defaults: a few frames, well under a second of CPU)."""

    frames_per_hold: int = 10  # frames decoded per hold (calibrate decodes up to 24)
    frames_per_leg: int = 16
    min_fix: str = "rtk_fixed"
    summary_every: int = 3  # a summary line every N waypoints
    points: PointOptions = field(default_factory=PointOptions)
    sampling: SamplingOptions = field(default_factory=SamplingOptions)  # the frame cache's zones: calibrate's read windows
    frame_cache: bool = True  # detect every ring frame around holds and legs for calibrate after landing (JPEG/PNG)


@dataclass(frozen=True, eq=False)
class FixTrack:
    """The GNSS track so far in the live ENU frame.

    ``t_ns`` (N,) int64 fix times; ``marker_enu_m`` (N, 3) the marker (lever
    arm applied with the attitude); ``sigma_enu_m`` (N, 3) receiver std;
    ``fix_types`` (N,) names.
    """

    t_ns: np.ndarray
    marker_enu_m: np.ndarray
    sigma_enu_m: np.ndarray
    fix_types: list[str | None]


@dataclass(frozen=True, eq=False)
class WaypointOutcome:
    """What one flown waypoint gave.

    ``kind`` is ``hold`` (a hover window) or ``leg`` (the leg flown into a
    fly-through waypoint); ``point`` the hold's 3D-2D point (None for a leg);
    ``uv_px`` (K, 2) the marker centres seen; ``problem`` None when the
    waypoint is good, else why it must be flown again.
    """

    seq: int
    kind: str
    end_ns: int
    frames: int
    detections: list[Detection]
    point: WaypointPoint | None
    problem: str | None

    @property
    def good(self) -> bool:
        return self.problem is None

    @property
    def uv_px(self) -> np.ndarray:
        return np.array([[d.u_px, d.v_px] for d in self.detections], float).reshape(-1, 2)


@dataclass(frozen=True, eq=False)
class LiveEstimate:
    """The running calibration after some waypoints.

    ``ground_error_15m_cm`` is the linearised prediction of the ground
    position error 15 m out (as calibrate's report gives it); ``focal_std_px``
    the linearised standard deviation of the mean focal length.
    """

    waypoints: int
    n_points: int
    camera: Camera
    model: str
    rms_px: float
    focal_px: float
    focal_std_px: float
    ground_error_15m_cm: float

    def to_dict(self) -> dict:
        i = self.camera.intrinsics
        return {
            "waypoints": self.waypoints, "n_points": self.n_points, "model": self.model, "rms_px": self.rms_px,
            "focal_px": self.focal_px, "focal_std_px": self.focal_std_px, "ground_error_15m_cm": self.ground_error_15m_cm,
            "fx": i.fx, "fy": i.fy, "cx": i.cx, "cy": i.cy, "distortion": self.camera.distortion.as_array().tolist(),
            "position_enu_m": self.camera.pose.position_world.tolist(),
            "R_cam_from_enu": np.asarray(self.camera.pose.R_cam_from_world).tolist(),
        }


# ----------------------------------------------------------------------------
# frames and detections


def pick_frames(frames: list[Any], start_ns: int, end_ns: int, n: int) -> list[Any]:
    """Up to ``n`` frames (with ``timestamp_ns``) of [start_ns, end_ns], spread evenly over the span."""
    inside = [f for f in frames if start_ns <= f.timestamp_ns <= end_ns]
    if len(inside) <= n:
        return inside
    idx = np.unique(np.round(np.linspace(0, len(inside) - 1, n)).astype(int))
    return [inside[k] for k in idx]


COMPRESSED = ("h264", "h265")


def gray_images(picked: list[Any], stream: list[Any] | None = None) -> list[tuple[int, np.ndarray | None]]:
    """(timestamp_ns, (H, W) uint8 or None) of the ``picked`` frames, in time order.

    JPEG/PNG frames decode on their own. H.264/H.265 access units (a
    ``/camera/video`` stream) decode from the keyframe before the first picked
    one, through ``stream`` (every access unit around them, in order), with the
    offline stage's ``video.decode.VideoFrameDecoder``.
    """
    from dronecal_field.pipeline.detect import decode_gray

    picked = sorted(picked, key=lambda f: f.timestamp_ns)
    if not picked:
        return []
    if picked[0].format not in COMPRESSED:
        return [(f.timestamp_ns, decode_gray(f.data)) for f in picked]
    from dronecal_field.video.decode import VideoFrameDecoder
    from dronecal_field.video.nal import video_frame_of

    units = sorted(stream if stream is not None else picked, key=lambda f: f.timestamp_ns)
    wanted = {f.timestamp_ns for f in picked}
    first, last = min(wanted), max(wanted)
    start = 0
    for k, unit in enumerate(units):
        if unit.timestamp_ns > first:
            break
        if video_frame_of(unit).keyframe:
            start = k
    decoder = VideoFrameDecoder(picked[0].format, threads=1)
    out: list[tuple[int, np.ndarray | None]] = []
    for unit in units[start:]:
        if unit.timestamp_ns > last:
            break
        decoder.push(video_frame_of(unit))
        if unit.timestamp_ns in wanted:
            out.append((unit.timestamp_ns, decoder.gray()))
    return out


def detect_in_frames(frames: list[Any], marker: Any, detector: Any, stream: list[Any] | None = None) -> list[Detection]:
    """The marker in each frame, calibrate's detector; the frames in time order.

    ``marker`` is the run's MarkerSpec; ``detector`` from
    ``detect.make_aruco_detector`` (None for an LED marker); ``stream`` every
    access unit around the frames when they are H.264/H.265 (:func:`gray_images`).
    """
    from dronecal_field.pipeline.detect import detect_marker, roi_around

    found: list[Detection] = []
    last: Detection | None = None
    for timestamp_ns, image in gray_images(frames, stream):
        if image is None:
            continue
        res = detect_marker(image, marker, detector, timestamp_ns, roi_around(last, image.shape) if last is not None else None)
        if res.detection is not None:
            found.append(res.detection)
            last = res.detection
    return found


# ----------------------------------------------------------------------------
# points


def fix_track(
    fixes: list[Any], attitudes: list[Any], origin: Any, offset_frd_m: np.ndarray
) -> FixTrack:
    """The marker's ENU track from GnssFix and Attitude records (any order), at ``origin`` (EnuOrigin)."""
    from dronecal_field.geodesy import geodetic_to_enu

    fixes = sorted((f for f in fixes if f.fix_type != "no_fix"), key=lambda f: f.timestamp_ns)
    if not fixes:
        return FixTrack(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3)), [])
    t = np.array([f.timestamp_ns for f in fixes], np.int64)
    lla = np.array([(f.lat_deg, f.lon_deg, f.alt_m) for f in fixes], float)
    antenna = geodetic_to_enu(lla[:, 0], lla[:, 1], lla[:, 2], origin)
    sigma = np.array(
        [np.sqrt(np.clip(np.diag(f.covariance_enu), 0, None)) if f.covariance_enu is not None else (np.nan,) * 3 for f in fixes], float
    )
    att_t = att_rpy = None
    if attitudes:
        att = sorted(attitudes, key=lambda a: a.timestamp_ns)
        att_t = np.array([a.timestamp_ns for a in att], np.int64)
        att_rpy = np.array([(a.roll_rad, a.pitch_rad, a.yaw_rad) for a in att], float)
    # At the fixes' own instants: the lever arm turned by the attitude then (no pairing gap applies).
    marker, _ = marker_track_at(t, t, antenna, np.asarray(offset_frd_m, float), att_t, att_rpy)
    return FixTrack(t_ns=t, marker_enu_m=marker, sigma_enu_m=sigma, fix_types=[f.fix_type for f in fixes])


def hold_outcome(
    seq: int, index: int, start_ns: int, end_ns: int, frames: int, detections: list[Detection], track: FixTrack,
    camera_offset_ns: int, marker_size_m: float | None, options: LiveOptions,
) -> WaypointOutcome:
    """One hold's outcome: its point as calibrate makes it (``window_point`` over the settled part)."""
    from dataclasses import replace

    po = replace(options.points, min_fix=options.min_fix)
    window = HoverWindow(index=index, start_ns=int(start_ns), end_ns=int(end_ns), source="event", seq=int(seq))
    # Live, only a few frames are decoded: a hold needs 3 detections, like calibrate's minimum.
    po = replace(po, min_detections=min(po.min_detections, max(1, frames)))
    det_t = np.array([d.timestamp_ns for d in detections], np.int64)
    det_uv = np.array([[d.u_px, d.v_px] for d in detections], float).reshape(-1, 2)
    det_size = np.array([d.size_px for d in detections], float)
    point = window_point(
        window, window.stable(po.settle_s, po.tail_s), track.t_ns, track.marker_enu_m, track.sigma_enu_m, track.fix_types,
        det_t, det_uv, int(camera_offset_ns), po, det_size, marker_size_m,
    )
    problem = None
    if not detections:
        problem = NOT_DETECTED
    elif not point.used:
        problem = NOT_DETECTED if "marker detections" in (point.dropped or "") else point.dropped
    return WaypointOutcome(seq=int(seq), kind="hold", end_ns=int(end_ns), frames=frames, detections=detections, point=point, problem=problem)


def leg_outcome(seq: int, end_ns: int, frames: int, detections: list[Detection], min_detections: int = 3) -> WaypointOutcome:
    """A fly-through waypoint: the leg into it showed the marker (``min_detections`` frames) or not."""
    problem = None if len(detections) >= min(min_detections, max(1, frames)) else NOT_DETECTED
    return WaypointOutcome(seq=int(seq), kind="leg", end_ns=int(end_ns), frames=frames, detections=detections, point=None, problem=problem)


def live_leg_points(start_ns: int, end_ns: int, detections: list[Detection], track: FixTrack, offset_ns: int, min_fix: str,
                    index: int = 0, time_std_s: float = 0.03) -> list[WaypointPoint]:
    """One leg's 3D-2D pairs as calibrate makes them (``pipeline.legs.leg_points``: a pair per GNSS fix, the image
    track interpolated at its instant), at camera offset ``offset_ns``; [start_ns, end_ns] on the GNSS (run) clock."""
    from dronecal_field.pipeline.legs import Leg, leg_points, track_velocity

    det_t = np.array([d.timestamp_ns for d in detections], np.int64)
    det_uv = np.array([[d.u_px, d.v_px] for d in detections], float).reshape(-1, 2)
    inside = (track.t_ns >= start_ns - 2_000_000_000) & (track.t_ns <= end_ns + 2_000_000_000)
    t, X = track.t_ns[inside], track.marker_enu_m[inside]
    if len(t) < 4:
        return []
    velocity = track_velocity(t, X)
    sigma = np.nan_to_num(track.sigma_enu_m[inside], nan=0.02)
    types = [f for f, keep in zip(track.fix_types, inside) if keep]
    leg = Leg(index=int(index), start_ns=int(start_ns), end_ns=int(end_ns), source="event")
    return leg_points([leg], t, X, velocity, sigma, types, det_t, det_uv, int(offset_ns), 0.0, time_std_s, min_fix, first_index=0)


def thin(points: list, n: int) -> list:
    """At most ``n`` of ``points``, evenly spread over the list."""
    if len(points) <= n:
        return list(points)
    idx = np.unique(np.round(np.linspace(0, len(points) - 1, n)).astype(int))
    return [points[k] for k in idx]


# ----------------------------------------------------------------------------
# the running calibration


def solve(points: list[WaypointPoint], width: int, height: int, waypoints: int, previous: LiveEstimate | None = None,
          prior: Camera | None = None) -> LiveEstimate | None:
    """The camera from the used hold points (None below 6 points or on degenerate geometry), with its linearised uncertainty.

    The model is chosen as calibrate chooses it (``maps.select_model``: the
    richest the points support, by F-test), so a handful of points never
    gets a 14-parameter lens. The uncertainty is taken from the fit's own
    residuals (sigma_2d = the residual sigma corrected for the free
    parameters, sigma_3d = 0): the receiver's reported accuracy is often far
    from the RTK noise (the simulator reports 30 cm), and calibrate too
    replaces it by the noise it measures on the residuals.
    ``previous`` is returned when the new solve fails. ``prior`` (the plan's
    guessed camera, same ENU frame) is a second start for the chosen model:
    the lower-RMS fit is kept (on the first, nearly one-layer holds the DLT
    start can land in a basin at twice the focal length).
    """
    from dronecal_field.core.uncertainty import linearised
    from dronecal_field.errors import DronecalError
    from dronecal_field.pipeline.maps import select_model

    used = [p for p in points if p.used]
    if len(used) < MIN_SOLVE_POINTS:
        return None
    X = np.array([p.marker_enu_m for p in used])  # (N, 3) ENU metres
    uv = np.array([p.uv_px for p in used])  # (N, 2) px
    try:
        result, _reason = select_model(X, uv, width, height, loss="huber", loss_scale_px=2.0)
        if prior is not None:
            from dronecal_field.core.calibrate import calibrate

            try:
                alt = calibrate(X, uv, width, height, model=result.model, loss="huber", loss_scale_px=2.0, initial=prior)
                if alt.rms_px < result.rms_px:
                    result = alt
            except (DronecalError, ValueError, np.linalg.LinAlgError):
                pass
        n_eq = 2 * len(used)
        sigma_px = max(float(result.residual_sigma_px) * float(np.sqrt(n_eq / max(n_eq - result.model.n_free, 1))), 0.05)
        lin = linearised(result.camera, X, sigma_3d=0.0, sigma_2d=sigma_px, model=result.model)
    except (DronecalError, ValueError, np.linalg.LinAlgError):
        return previous  # coplanar so far, or a failed fit: keep what we had
    i = result.camera.intrinsics
    focal_std = 0.5 * float(np.hypot(lin.param_std.get("fx", np.nan), lin.param_std.get("fy", np.nan)))
    return LiveEstimate(
        waypoints=int(waypoints), n_points=len(used), camera=result.camera, model=result.model.name, rms_px=float(result.rms_px),
        focal_px=0.5 * (i.fx + i.fy), focal_std_px=focal_std, ground_error_15m_cm=float(lin.ground_error_15m_cm),
    )


def constrained(estimate: LiveEstimate | None, prior: Camera | None = None, max_focal_rel_std: float = 0.02, max_shift_m: float = 2.0) -> bool:
    """The running calibration means something yet: its focal length known to ``max_focal_rel_std`` (1 sigma) and,
    with the plan's guessed camera ``prior``, the camera within ``max_shift_m`` of where the plan put it (the pole
    is surveyed to a metre or two; a camera metres away is a wrong solution whatever its sigma says)."""
    if estimate is None or not (np.isfinite(estimate.focal_std_px) and np.isfinite(estimate.ground_error_15m_cm)):
        return False
    if estimate.focal_std_px > max_focal_rel_std * estimate.focal_px:
        return False
    if prior is not None and np.linalg.norm(estimate.camera.pose.position_world - prior.pose.position_world) > max_shift_m:
        return False
    return True


def guessed_camera(plan: dict | None) -> Camera | None:
    """The plan's guessed camera in its ENU frame (``plan.json`` ``camera_guess``), None without one."""
    try:
        g = plan["camera_guess"]
        R = np.asarray(g["rotation_world_to_camera"], float)
        c = np.asarray(g["position_enu_m"], float)
        f = float(g["focal_px"])
        return Camera.from_arrays([f, f, float(g["cx"]), float(g["cy"])], g.get("distortion_k1_k2_p1_p2_k3") or [0.0] * 5, R, -R @ c,
                                  int(g["width"]), int(g["height"]))
    except (KeyError, TypeError, ValueError):
        return None


# ----------------------------------------------------------------------------
# coverage and the verdict


def image_roi(plan: dict | None):
    """The plan's ROI in the image of its guessed camera (sampling.roi.Roi), None without a plan.json or ROI.

    Rebuilt from plan.json's ``camera_guess`` and ``roi`` exactly as ``plan``
    built it, so coverage here is the same figure as plan's ``coverage.pct``.
    """
    from dronecal_field.sampling.roi import RoiSpec, build_roi

    try:
        g, r = plan["camera_guess"], plan["roi"]
        R_enu_from_site = np.asarray(plan["site_frame"]["R_enu_from_site"], float)
        R_cam_from_enu = np.asarray(g["rotation_world_to_camera"], float)
        R = R_cam_from_enu @ R_enu_from_site  # camera from site
        c = R_enu_from_site.T @ np.asarray(g["position_enu_m"], float)
        f = float(g["focal_px"])
        camera = Camera.from_arrays(
            [f, f, float(g["cx"]), float(g["cy"])], g.get("distortion_k1_k2_p1_p2_k3") or [0.0] * 5, R, -R @ c,
            int(g["width"]), int(g["height"]),
        )
        poly = r.get("polygon_site_m")
        spec = RoiSpec(
            kind=str(r.get("kind", "range")), range_m=tuple(float(v) for v in r["range_m"]),
            polygon_site=tuple(tuple(float(v) for v in p[:2]) for p in poly) if poly else None,
            layer_heights_m=tuple(float(v) for v in r.get("layer_heights_m") or (0.0,)), source=str(r.get("source", "plan.json")),
        )
        cells = r.get("cells")
        return build_roi(camera, spec, cells_across=int(cells[0]) if cells else 16)
    except Exception:  # noqa: BLE001 - no ROI is a valid answer (no plan.json, an older format): coverage is then not shown
        return None


def coverage(roi: Any, outcomes: list[WaypointOutcome]) -> float | None:
    """Share of the ROI's image cells within one cell of a marker seen so far (plan's coverage rule); None without an ROI."""
    if roi is None:
        return None
    uv = [o.uv_px for o in outcomes if len(o.detections)]
    return float(roi.coverage(np.concatenate(uv) if uv else np.zeros((0, 2))))


def _flies_here(item: Any, point: dict) -> bool:
    """True when mission ``item`` is at plan.json grid ``point``'s drone position (within ~5 cm; a grid without positions: True)."""
    if item is None:
        return False
    if point.get("lat_deg") is None or point.get("lon_deg") is None:
        return True
    return abs(item.x - float(point["lat_deg"]) * 1e7) <= 5 and abs(item.y - float(point["lon_deg"]) * 1e7) <= 5


def _grid_here(mission: Any, plan: dict | None) -> list[dict]:
    """plan.json's grid points this mission flies: a split plan's grid holds every flight's points, each numbered in
    its own mission, so a point counts where this mission's NAV_WAYPOINT at its seq stands at its position."""
    from dronecal_field.mavlink.missionfile import CMD_NAV_WAYPOINT

    grid = (plan or {}).get("grid") if isinstance(plan, dict) else None
    if not isinstance(grid, list):
        return []
    nav = {item.seq: item for item in mission.items if item.command == CMD_NAV_WAYPOINT}
    return [g for g in grid if isinstance(g, dict) and g.get("mission_seq") is not None and _flies_here(nav.get(int(g["mission_seq"])), g)]


def expected_seqs(mission: Any, plan: dict | None) -> list[int]:
    """The mission seqs that are measurement points: plan.json's grid, else every NAV_WAYPOINT with a hold.

    A scout flight (plan.json ``kind: scout``) has none: its rows sweep wider than any camera sees, so the waypoints
    a camera does not see are expected and never re-fly material."""
    from dronecal_field.mavlink.missionfile import CMD_NAV_WAYPOINT

    if isinstance(plan, dict) and plan.get("kind") == "scout":
        return []

    seqs = sorted({int(g["mission_seq"]) for g in _grid_here(mission, plan)})
    if seqs:
        return seqs
    return [item.seq for item in mission.items[1:] if item.command == CMD_NAV_WAYPOINT and item.hold_s > 0]


def plan_flight(mission: Any, plan: dict | None) -> tuple[int, int] | None:
    """(k, n) when ``mission`` is flight k of a plan split into n > 1 flights (plan.json's grid), else None."""
    grid = (plan or {}).get("grid") if isinstance(plan, dict) else None
    flights = {int(g["flight"]) for g in grid if isinstance(g, dict) and g.get("flight") is not None} if isinstance(grid, list) else set()
    here = [int(g["flight"]) for g in _grid_here(mission, plan) if g.get("flight") is not None]
    if len(flights) < 2 or not here:
        return None
    return max(set(here), key=here.count), max(flights)


@dataclass(frozen=True)
class Verdict:
    """The end of the mission: good, or which waypoints to fly again and why."""

    good: bool
    text: str
    refly_seqs: tuple[int, ...]


def verdict(outcomes: list[WaypointOutcome], expected: list[int], estimate: LiveEstimate | None, cover: float | None,
            prior: Camera | None = None, flight: tuple[int, int] | None = None) -> Verdict:
    """``good: ...`` or ``re-fly waypoints 12, 17, 31 (marker not detected)``; unflown expected waypoints are re-flown too.

    ``flight`` (k, n): this mission is flight k of a plan split into n; its coverage and points are a part of the
    plan's, and the verdict says the flights are calibrated together rather than that this one alone is too few.
    """
    by_seq: dict[int, WaypointOutcome] = {}
    for o in outcomes:
        if o.seq not in by_seq or (o.good and not by_seq[o.seq].good):
            by_seq[o.seq] = o
    reasons: dict[str, list[int]] = {}
    for seq in expected:
        o = by_seq.get(seq)
        why = "not flown" if o is None else o.problem
        if why is not None:
            reasons.setdefault(why, []).append(seq)
    for seq, o in by_seq.items():  # a waypoint outside the plan's grid that failed still counts
        if seq not in expected and o.problem is not None and o.kind == "hold":
            reasons.setdefault(o.problem, []).append(seq)
    refly = tuple(sorted({s for seqs in reasons.values() for s in seqs}))
    flown = sum(1 for s in expected if s in by_seq)
    detected = sum(1 for s in expected if s in by_seq and by_seq[s].good)
    tail = []
    if cover is not None:
        tail.append(f"coverage {100 * cover:.0f} % of the plan's ROI")
    if constrained(estimate, prior):
        tail.append(f"predicted ground error {estimate.ground_error_15m_cm:.1f} cm at 15 m ({estimate.n_points} points)")
    elif estimate is not None:
        tail.append(f"the calibration is not constrained yet (focal ± {100 * estimate.focal_std_px / estimate.focal_px:.0f} % from {estimate.n_points} points)")
    elif detected < MIN_SOLVE_POINTS and flight is None:
        tail.append(f"only {detected} points: calibrate needs {MIN_SOLVE_POINTS}")
    if flight is not None:
        tail.append(f"flight {flight[0]} of {flight[1]} of the plan: calibrate this run together with the other flights' runs "
                    "(calibrate run-1.mcap run-2.mcap ... pools them into one camera)")
    if not refly:
        return Verdict(True, f"good: {detected}/{len(expected)} waypoints detected" + ("; " + ", ".join(tail) if tail else ""), ())
    parts = [f"{', '.join(str(s) for s in seqs)} ({why})" for why, seqs in sorted(reasons.items(), key=lambda kv: min(kv[1]))]
    text = f"re-fly waypoints {'; '.join(parts)}" + f" — {detected}/{len(expected)} detected of {flown} flown" + ("; " + ", ".join(tail) if tail else "")
    return Verdict(False, text, refly)


def scout_verdict(outcomes: list[WaypointOutcome]) -> Verdict:
    """A scout flight's end: how many of its waypoints showed the marker, and what comes next (never a re-fly list)."""
    seen = sorted({o.seq for o in outcomes if o.good})
    if not seen:
        return Verdict(False, "scout: the marker was never seen: check the camera's position and azimuth, then fly the scout again", ())
    return Verdict(True, f"scout: the marker was seen at {len(seen)} of {len({o.seq for o in outcomes})} waypoints checked; "
                         "plan the main flight from it: dronecal-field plan --from-run RUN.mcap --out DIR", ())


def summary_line(outcomes: list[WaypointOutcome], expected: list[int], estimate: LiveEstimate | None, cover: float | None,
                 offset: Any | None, prior: Camera | None = None) -> str:
    """``live: 9/24 waypoints, 8 detected, 1 missed (seq 12) | coverage 41 % | ground 3.2 cm at 15 m | camera offset +0.12 s``.

    The counts are of the measurement waypoints (``expected``).
    """
    want = set(expected)
    good = {o.seq for o in outcomes if o.good and o.seq in want}
    flown = {o.seq for o in outcomes if o.seq in want}
    missed = sorted(flown - good)
    detected = len(good)
    parts = [f"live: {len(flown)}/{len(expected)} waypoints, {detected} detected, {len(missed)} missed"
             + (f" (seq {', '.join(map(str, missed[:8]))}{'...' if len(missed) > 8 else ''})" if missed else "")]
    if cover is not None:
        parts.append(f"coverage {100 * cover:.0f} %")
    if constrained(estimate, prior):
        parts.append(f"f {estimate.focal_px:.1f} ± {estimate.focal_std_px:.1f} px, ground {estimate.ground_error_15m_cm:.1f} cm at 15 m")
    elif estimate is not None:
        parts.append(f"calibration: not constrained yet ({estimate.n_points} points, model {estimate.model})")
    else:
        parts.append("calibration: waiting for 6 points")
    if offset is not None and offset.method != "none":
        parts.append(f"camera offset {offset.offset_s:+.3f} s" + (f" ± {offset.std_s:.3f}" if offset.std_s is not None else ""))
    else:
        parts.append("camera offset: not observable yet (needs the marker moving)")
    return " | ".join(parts)
