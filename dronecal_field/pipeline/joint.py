"""One camera from several runs: ``calibrate a.mcap b.mcap --joint`` (issue 10's split plans).

A plan that does not fit one battery is flown as flights (``mission-1.plan``,
``mission-2.plan``, ...), one run file each; each flight alone covers part of
the view only. This stage pools their points into one calibration (``pool_runs``; the
orchestration of runs x cameras is ``pipeline.run.calibrate_runs``)::

    per run: read track -> hover windows + legs -> detections -> time alignment   (stages.run_stages)
             -> points and solve at that run's own offset, legs timing, noise    (solve.solve_at_offset)
    points of every run -> the first run's ENU frame (geodesy, pyproj)
    -> one solve on all points -> one uncertainty (Monte-Carlo, linearised, region of validity) -> report

Each flight keeps its own camera clock: its time offset, rolling shutter and
per-fix noise come from its own solve. A run too small to calibrate alone
(DegenerateGeometryError: too few holds, coplanar points) still contributes:
its points are paired at its motion-based time offset (no refinement through a
camera), their marker centres taken again under the pooled camera's
distortion, and the pooled camera solved once more with them. That is the
simplest pairing that needs no camera in that run's own frame; its offset is
as good as the marker's motion makes it (report.json says which runs were
paired so).

No printing: the command prints; every number lands in report.json (``joint``).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dronecal_field.errors import DegenerateGeometryError, InputError
from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic, geodetic_to_enu
from dronecal_field.pipeline.confidence import uncertainty
from dronecal_field.pipeline.results import CalibrateOptions, CalibrationReport, FrameStats, Track
from dronecal_field.pipeline.solve import check_physical, check_supported, pair_points, solve_at_offset, solve_points
from dronecal_field.pipeline.stages import RunStages, StageClock, clock_jump_cost, damage_cost, offset_with_timing, with_camera

MAX_CAMERA_APART_M = 1.0  # plans whose cameras lie further apart are of different cameras


# --------------------------------------------------------------------------
# Which runs are flights of one plan


@dataclass(frozen=True)
class PlanOfRun:
    """What a run says about the plan it flew: the plan.json fly attached, and where that plan put the camera."""

    path: Path
    plan_hash: str | None  # sha256 of plan.json's content (None: no plan.json attached)
    flight: int | None  # which flight of the plan its mission.plan is (1-based), None when unknown
    camera_wgs84: tuple[float, float, float] | None  # lat_deg, lon_deg, h_m of the planned camera
    width: int
    height: int


def plan_of_run(path: str | Path) -> PlanOfRun:
    """Read a run's metadata and attachments (no frames) for the grouping and the checks."""
    from dronecal_field.runfile.reader import open_run

    path = Path(path)
    with open_run(path) as run:
        md = run.metadata
        plan_bytes, mission_bytes = run.attachment("plan.json"), run.attachment("mission.plan")
    plan = _json(plan_bytes)
    return PlanOfRun(
        path=path, plan_hash=_plan_hash(plan_bytes, plan), flight=_flight_number(plan, _json(mission_bytes)),
        camera_wgs84=_planned_camera(plan), width=int(md.width), height=int(md.height),
    )


def _json(data: bytes | None):
    if not data:
        return None
    try:
        return json.loads(data)
    except ValueError:
        return None


def _plan_hash(data: bytes | None, plan) -> str | None:
    """The same plan hashes the same: its JSON content (keys sorted, whitespace aside), else its bytes."""
    if not data:
        return None
    canonical = json.dumps(plan, sort_keys=True, separators=(",", ":")).encode() if plan is not None else bytes(data)
    return hashlib.sha256(canonical).hexdigest()


def _flight_number(plan, mission) -> int | None:
    """The flight of ``plan`` whose sampling points ``mission`` flies (plan.json's grid ``flight``), by position."""
    try:
        grid = [(float(g["lat_deg"]), float(g["lon_deg"]), int(g["flight"])) for g in plan["grid"]]
        items = mission["mission"]["items"]
    except (TypeError, KeyError, ValueError):
        return None
    if not grid:
        return None
    g = np.array([(a, b) for a, b, _ in grid])
    flights = np.array([f for _, _, f in grid])
    votes: dict[int, int] = {}
    for item in items:
        params = item.get("params") if isinstance(item, dict) else None
        if not params or len(params) < 6 or params[4] is None or params[5] is None:
            continue
        d = np.abs(g - [float(params[4]), float(params[5])]).max(axis=1)
        k = int(np.argmin(d))
        if d[k] < 3e-7:  # ~3 cm
            votes[int(flights[k])] = votes.get(int(flights[k]), 0) + 1
    return max(votes, key=votes.get) if votes else None


def _planned_camera(plan) -> tuple[float, float, float] | None:
    """WGS84 position of the camera a plan.json was made for (its ENU origin plus the guessed camera's position)."""
    try:
        o = plan["enu_origin"]
        origin = EnuOrigin(float(o["lat_deg"]), float(o["lon_deg"]), float(o["h_m"]))
        pos = np.asarray(plan["camera_guess"]["position_enu_m"], float).reshape(1, 3)
    except (TypeError, KeyError, ValueError):
        return None
    lat, lon, h = enu_to_geodetic(pos, origin)[0]
    return float(lat), float(lon), float(h)


def flights_of_one_plan(runs: list[PlanOfRun]) -> bool:
    """True when every run carries the same plan.json (the flights of one split plan)."""
    return len(runs) > 1 and runs[0].plan_hash is not None and all(r.plan_hash == runs[0].plan_hash for r in runs)


def check_one_camera(runs: list[PlanOfRun]) -> None:
    """Refuse to pool runs whose metadata contradict one camera (image size, the planned camera's place).

    Raises
    ------
    InputError : one line naming the two runs, what differs and what to do
    """
    first = runs[0]
    for r in runs[1:]:
        if (r.width, r.height) != (first.width, first.height):
            raise InputError(
                f"--joint: {first.path.name} is {first.width}x{first.height} and {r.path.name} is {r.width}x{r.height} "
                "(camera.width/height): they are not one camera; calibrate them as a batch (drop --joint)"
            )
        if first.camera_wgs84 is not None and r.camera_wgs84 is not None:
            o = EnuOrigin(*first.camera_wgs84)
            apart = float(np.linalg.norm(geodetic_to_enu(*r.camera_wgs84, o)[0]))
            if apart > MAX_CAMERA_APART_M:
                raise InputError(
                    f"--joint: the plans of {first.path.name} and {r.path.name} put the camera {apart:.1f} m apart (more than "
                    f"{MAX_CAMERA_APART_M:g} m): they are not one camera; calibrate them as a batch (drop --joint)"
                )


# --------------------------------------------------------------------------
# The joint calibration


@dataclass(frozen=True, eq=False)
class JointRun:
    """One run's part of a joint calibration (its points re-numbered and in the joint ENU frame).

    ``offset``, ``points`` and ``detections`` are on this run's own clock, so
    report.detections_csv reads a JointRun as it reads a single run's report.
    """

    path: Path
    flight: int | None
    alone: bool  # calibrated alone first (its own offset refinement and noise); False: paired at its motion offset
    alone_reason: str | None  # why not alone (the DegenerateGeometryError's message)
    offset: object  # align.TimeOffset as report.json shows it
    points: list  # WaypointPoint, re-indexed, marker_enu_m in the joint frame
    detections: list
    windows: list
    window_source: str
    legs: list
    leg_source: str
    frames: FrameStats
    origin: EnuOrigin
    origin_moved_m: float  # how far this run's ENU origin lies from the joint one (0: same frame, no transform)
    alone_rms_px: float | None = None
    noise_px: dict = field(default_factory=dict)  # {"holds": px, "legs": px}: the noise its points were weighted by

    @property
    def used(self) -> int:
        return sum(1 for p in self.points if p.used)

    def to_dict(self) -> dict:
        hover = [p for p in self.points if p.window.source != "leg"]
        on_legs = [p for p in self.points if p.window.source == "leg"]
        return {
            "path": str(self.path),
            "flight": self.flight,
            "calibrated_alone_first": self.alone,
            "why_not_alone": self.alone_reason,
            "rms_px_alone": self.alone_rms_px,
            "noise_px_weighted_by": self.noise_px or None,
            "points_used": self.used,
            "hover_points_used": sum(1 for p in hover if p.used),
            "hover_windows": len(self.windows),
            "window_source": self.window_source,
            "leg_pairs_used": sum(1 for p in on_legs if p.used),
            "legs": len(self.legs),
            "leg_source": self.leg_source,
            "window_index_range": [min((p.window.index for p in self.points), default=None),
                                   max((p.window.index for p in self.points), default=None)],
            "time_offset": self.offset.to_dict(),
            "frames": self.frames.to_dict(),
            "enu_origin": self.origin.as_list(),
            "enu_origin_from_joint_m": self.origin_moved_m,
        }


@dataclass(frozen=True, eq=False)
class JointReport(CalibrationReport):
    """A CalibrationReport of several runs pooled: ``runs`` has each run's part; the rest is the pooled camera's.

    ``run_path``, ``metadata``, ``origin`` and ``offset`` are the first run's (its ENU frame is the joint one).
    """

    runs: tuple[JointRun, ...] = field(default_factory=tuple)


def check_runs(paths: list[Path]) -> None:
    """Refuse fewer than two runs, or one run file given twice (InputError, one line)."""
    if len(paths) < 2:
        raise InputError("--joint needs two or more run files: pass the runs of every flight of the plan")
    seen: dict[Path, Path] = {}
    for p in paths:
        if p.resolve() in seen:
            raise InputError(f"{seen[p.resolve()]} and {p} are the same run file: give each flight's run once")
        seen[p.resolve()] = p


def pool_runs(stages: list[RunStages], plans: list[PlanOfRun], options: CalibrateOptions, clock: StageClock) -> "JointReport":
    """One camera from the points of every run (flights of one plan); outputs into ``options.out_dir`` when set.

    Parameters
    ----------
    stages : stages 1-4 of each run, for this camera (``stages.run_stages``), the first run's ENU frame the joint one
    plans : what each run says about its plan (``plan_of_run``), in the same order
    clock : the stage clock the timings land in

    Raises
    ------
    InputError : runs that are not one camera (image size, planned camera place)
    DegenerateGeometryError, CalibrationError : the pooled points give no camera
    """
    plans = [replace(p, width=int(st.md.width), height=int(st.md.height)) for p, st in zip(plans, stages)]
    if stages[0].camera is not None:
        plans = [replace(p, camera_wgs84=None) for p in plans]  # a site's plan guesses one camera, not this one
    check_one_camera(plans)
    origin = stages[0].read.origin
    parts = [clock("calibration_s", _alone, st, options) for st in stages]
    points, runs, tracks = _pool(stages, parts, plans, origin)
    md = stages[0].md
    result, reason = clock("calibration_s", solve_points, points, md, options)
    if options.recentre and any(s is None for s, _, _, _ in parts) and np.any(result.camera.distortion.as_array() != 0.0):
        # runs paired without a camera of their own: their centres again under the pooled distortion, and solve once more
        i = result.camera.intrinsics
        K_dist = (np.array([i.fx, i.fy, i.cx, i.cy]), result.camera.distortion.as_array())
        parts = [p if p[0] is not None else _paired_at_motion(st, options, K_dist, reason=p[3]) for st, p in zip(stages, parts)]
        points, runs, tracks = _pool(stages, parts, plans, origin)
        result, reason = clock("calibration_s", solve_points, points, md, options, (result, reason))
    run_of_point = [i for i, r in enumerate(runs) for p in r.points if p.used]  # _pool: runs' points one after another
    alone_models = [None if s is None else s.result.model for s, _, _, _ in parts]
    result, noise = clock("calibration_s", noise_weighted, points, result, md, options, run_of_point, alone_models)
    if noise is not None:
        runs = [replace(r, noise_px=noise.get(i, {})) for i, r in enumerate(runs)]
        reason += f" (each run's holds and legs weighted by their own noise: {_noise_text(noise, runs)})"
    noise0 = parts[0][0].noise if parts[0][0] is not None else None
    check_physical(result, points, md, noise0)
    camera = result.camera.with_(enu_origin=tuple(origin.as_list()))
    result = with_camera(result, camera)
    unc = clock("uncertainty_s", uncertainty, camera, points, result, options, origin, stages[0].read.plan_roi)
    check_supported(unc.monte_carlo, result, noise0)
    warnings = _warnings(stages, parts, runs)
    if options.annotate:
        warnings.append("--annotate is not done for a joint calibration (one annotated copy per run would need the camera "
                        "in each run's frame): calibrate a run alone with --annotate for its copy")
    first = stages[0]
    report = JointReport(
        run_path=first.path, truncated=any(st.truncated for st in stages), run_warnings=[w for st in stages for w in st.run_warnings],
        metadata=md, origin=origin, origin_source=first.read.origin_source, altitude_datum=md.altitude_datum,
        windows=[w for r in runs for w in r.windows], window_source=", ".join(dict.fromkeys(r.window_source for r in runs)),
        frames=_sum_frames([r.frames for r in runs]), detections=[d for r in runs for d in r.detections],
        detection_groups=[g for st in stages for g in st.dets.groups], offset=runs[0].offset, points=points,
        attitude_source="; ".join(dict.fromkeys(st.read.attitude_source for st in stages)),
        model_reason=reason + f" (joint: {len(runs)} runs pooled)", result=result, monte_carlo=unc.monte_carlo,
        linearised=unc.linearised, covariance_measured=unc.covariance, maps=unc.maps, homography=unc.homography,
        track=_concat_tracks(tracks), timings_s=clock.timings, warnings=warnings, options=replace(options, annotate=False),
        background=first.dets.background, fixes_repeated=sum(st.read.identity.n_repeats for st in stages),
        centres=(parts[0][0].centres if parts[0][0] is not None else "diagonals' crossing"),
        legs=[g for r in runs for g in r.legs], leg_source=", ".join(dict.fromkeys(r.leg_source for r in runs)),
        timing=parts[0][0].timing if parts[0][0] is not None else None, fix_identity=first.read.identity,
        gnss_latency_s=first.read.gnss_latency_s, validity=unc.validity,
        noise=noise0, sigma_scale=unc.sigma_scale, runs=tuple(runs),
    )
    if options.out_dir is not None:
        from dronecal_field.pipeline.report import write_outputs

        report.outputs.update(clock("outputs_s", write_outputs, report, Path(options.out_dir)))
    return report


# --------------------------------------------------------------------------
# Each run's points weighted by that run's own noise

MIN_GROUP_POINTS = 6  # fewer points than this give no noise of their own: they take their run's (or the pool's)
EQUAL_NOISE_RATIO = 1.25  # noises this close are one noise: the plain (unweighted, compiled) fit stands
NOISE_FLOOR_PX = 0.05  # no group is trusted beyond this (a near-perfect group would take every weight)
MAX_REWEIGHTS = 6


def noise_weighted(points: list, result, md, options: CalibrateOptions, run_of_point: list[int], alone_models: list | None = None):
    """The pooled camera with each run's holds and each run's legs weighted by their own measured noise.

    Runs flown differently do not share one noise: a scout's fast legs (motion
    blur, rolling shutter, timing) scatter by pixels where a main flight's
    holds scatter by tenths, and the same weight for both lets the noisy run
    pull the camera away from what the quiet run alone would give. Each group's
    noise is its robust residual scale about the pooled camera (median of the
    squared residuals over that of chi-square with 2 degrees of freedom, so a few
    bad points do not set it), every point is weighted by 1 / noise^2 and the
    camera solved again, until the noises settle (variance components). The
    pixel residual carries every noise of a point: the detector's, the GNSS
    fixes' seen through the camera, and the timing's along a leg.

    The model (``options.model`` auto) is the one the run carrying most of the
    weight (sum of 1 / noise^2 over its points) chose alone (``alone_models``,
    by run; None for a run paired at its motion offset): the model ladder ran
    on the unweighted pool, where the noisy run's points decided it (the
    Table 1 simulator: k1k2p1p2 from the pool where the main run alone
    supports k1, 1.66 px on the ground against 0.67 alone), and the weighted
    pool is that run's data to first order.

    ``run_of_point``: the run (0-based) of each used point, in order.
    Returns (result, {run: {"holds"|"legs": noise px}}), or (result, None) when
    the groups' noises are one noise (within EQUAL_NOISE_RATIO): then nothing changes.
    """
    from dronecal_field.core.calibrate import calibrate

    used = [p for p in points if p.used]
    groups = [(r, "legs" if p.window.source == "leg" else "holds") for p, r in zip(used, run_of_point)]
    X = np.array([p.marker_enu_m for p in used])
    uv = np.array([p.uv_px for p in used])
    noise = _group_noise(result.residuals_px, groups)
    if noise is None or max(noise.values()) < EQUAL_NOISE_RATIO * min(noise.values()):
        return result, None
    model = result.model
    share: dict[int, float] = {}
    for g in groups:
        share[g[0]] = share.get(g[0], 0.0) + 1.0 / noise[g] ** 2
    heaviest = max(share, key=share.get)
    if options.model == "auto" and alone_models and heaviest < len(alone_models) and alone_models[heaviest] is not None:
        model = alone_models[heaviest]
    for _ in range(MAX_REWEIGHTS):
        sigma = np.array([noise[g] for g in groups])
        result = calibrate(X, uv, md.width, md.height, model=model, loss=options.loss, loss_scale_px=options.loss_scale_px,
                           initial=result.camera, sigma_px=sigma)
        new = _group_noise(result.residuals_px, groups)
        settled = all(abs(new[g] / noise[g] - 1.0) < 0.02 for g in noise)
        noise = new
        if settled:
            break
    result, noise = _consistent_with_heaviest(X, uv, md, model, options, result, groups, noise, heaviest)
    out: dict[int, dict[str, float]] = {}
    for (r, kind), v in noise.items():
        out.setdefault(r, {})[kind] = round(float(v), 3)
    return result, out


CONSISTENCY_LEVEL = 0.999  # chi-square quantile the heaviest run's own fit may worsen by when the others join
ROBUST_SIGMAS = 2.0  # the consistency cost is quadratic to 2 sigmas of a point, then robust as the fit's loss
MAX_INFLATION = 1000.0  # beyond this the other runs weigh nothing: the heaviest run alone, in effect


def _consistent_with_heaviest(X, uv, md, model, options: CalibrateOptions, result, groups, noise: dict, heaviest: int):
    """(result, noise): the other runs' noise inflated until the heaviest run's own points agree with the pool.

    A run whose points are biased (a scout's leg timing, its fast legs' rolling
    shutter) and not only noisy is not cured by its noise weight: it pulls the
    camera by its bias. Joined by consistent runs, the heaviest run's own
    weighted cost rises by about a chi-square of the free parameters' count; a
    larger rise (above its CONSISTENCY_LEVEL quantile) means the others
    disagree, and their sigmas are multiplied by 3 until it does not: the pool
    then never fits the heaviest run worse than chance allows, so it is no
    worse than that run alone (the Table 1 and wide simulators' scouts, 13-19 px).
    """
    from scipy.stats import chi2

    from dronecal_field.core.calibrate import calibrate
    from dronecal_field.errors import DronecalError

    mine = np.array([g[0] == heaviest for g in groups])
    if mine.all() or mine.sum() < model.n_free:
        return result, noise
    sig = np.array([noise[g] for g in groups])
    try:
        own = calibrate(X[mine], uv[mine], md.width, md.height, model=model, loss=options.loss, loss_scale_px=options.loss_scale_px,
                        initial=result.camera, sigma_px=sig[mine])
    except DronecalError:
        return result, noise

    def chi(res) -> float:
        """The heaviest run's cost in its own sigmas, robust as the fit's loss (outliers of a leg would swamp squares)."""
        r2 = np.sum(np.asarray(res) ** 2, axis=1) / sig[mine] ** 2
        if options.loss == "huber":
            r = np.sqrt(r2)
            r2 = np.where(r <= ROBUST_SIGMAS, r2, 2.0 * ROBUST_SIGMAS * r - ROBUST_SIGMAS ** 2)
        elif options.loss == "cauchy":
            r2 = ROBUST_SIGMAS ** 2 * np.log1p(r2 / ROBUST_SIGMAS ** 2)
        return float(np.sum(r2))

    bound = float(chi2.ppf(CONSISTENCY_LEVEL, model.n_free))
    base = chi(own.residuals_px)
    factor = 1.0
    while chi(result.residuals_px[mine]) - base > bound and factor < MAX_INFLATION:
        factor *= 3.0
        noise = {g: (v if g[0] == heaviest else v * 3.0) for g, v in noise.items()}
        sigma = np.array([noise[g] for g in groups])
        result = calibrate(X, uv, md.width, md.height, model=model, loss=options.loss, loss_scale_px=options.loss_scale_px,
                           initial=result.camera, sigma_px=sigma)
    return result, noise


def _group_noise(residuals: np.ndarray, groups: list[tuple[int, str]]) -> dict | None:
    """Each group's per-axis noise (px) from its residuals; a group under MIN_GROUP_POINTS takes its run's, or the pool's."""
    sq = np.sum(np.asarray(residuals, float) ** 2, axis=1)
    chi2_median = 2.0 * np.log(2.0)  # median of chi-square, 2 degrees of freedom

    def scale(mask: np.ndarray) -> float:
        return max(float(np.sqrt(np.median(sq[mask]) / chi2_median)), NOISE_FLOOR_PX)

    keys = list(dict.fromkeys(groups))
    if len(keys) < 2:
        return None
    run_arr = np.array([g[0] for g in groups])
    kind_arr = np.array([g[1] for g in groups])
    pool = scale(np.ones(len(sq), bool))
    out = {}
    for r, kind in keys:
        mask = (run_arr == r) & (kind_arr == kind)
        if mask.sum() >= MIN_GROUP_POINTS:
            out[(r, kind)] = scale(mask)
        elif (run_arr == r).sum() >= MIN_GROUP_POINTS:
            out[(r, kind)] = scale(run_arr == r)
        else:
            out[(r, kind)] = pool
    return out


def _noise_text(noise: dict, runs: list) -> str:
    return "; ".join(f"{Path(runs[i].path).name} " + ", ".join(f"{k} {v:.2f} px" for k, v in sorted(d.items())) for i, d in sorted(noise.items()))


def _alone(st: RunStages, options: CalibrateOptions):
    """(Solved or None, points, offset as reported, why not alone) of one run: its own solve when it has enough
    points, else its points paired at the motion-based offset with the raw marker centres."""
    try:
        solved, offset = solve_at_offset(st.read, st.windows, st.legs, st.dets, st.offset, st.md, options)
    except DegenerateGeometryError as exc:
        return _paired_at_motion(st, options, None, reason=str(exc))
    return solved, solved.points, offset_with_timing(offset, solved.timing, st.read, solved.noise), None


def _paired_at_motion(st: RunStages, options: CalibrateOptions, K_dist, reason: str | None = None):
    """A run too small to calibrate alone: its points at its motion-based offset (global shutter), centres under
    ``K_dist`` ((fx, fy, cx, cy), distortion (5,)) when given, else the detector's."""
    from dronecal_field.pipeline.align import Timing
    from dronecal_field.pipeline.detect import centres_under_distortion

    centres = st.dets.uv_px
    corners = [d.corners_px for d in st.dets.items]
    if K_dist is not None and all(c is not None for c in corners) and corners:
        centres = centres_under_distortion(np.array(corners), *K_dist)
    timing = Timing(st.offset.offset_s, st.offset.std_s, 0.0, None, 0.0, "not estimated", n_points=st.offset.n_points)
    marker_size = st.md.marker.size_m if st.md.marker.kind == "aruco" else None
    pts = pair_points(st.read.track, st.read.attitude, st.read.offset_frd_m, st.windows, st.legs, st.dets, centres, timing, marker_size, options)
    return None, pts, offset_with_timing(st.offset, timing, st.read, None), reason


def _pool(stages: list[RunStages], parts: list, plans: list[PlanOfRun], origin: EnuOrigin):
    """Every run's points in the joint ENU frame, numbered one after another: (points, JointRuns, tracks)."""
    points, runs, tracks = [], [], []
    n_index = n_legs = 0
    for st, (solved, pts, offset, why), plan in zip(stages, parts, plans):
        moved = _frame_move(st.read.origin, origin)
        pts = [_renumbered(p, n_index, n_legs, moved) for p in pts]
        legs = [replace(g, index=g.index + n_legs) for g in st.legs]
        windows = [replace(w, index=w.index + n_index) for w in st.windows]
        track = solved.track if solved is not None else st.read.track
        tracks.append(replace(track, antenna_enu_m=moved(track.antenna_enu_m), marker_enu_m=moved(track.marker_enu_m)))
        runs.append(JointRun(
            path=st.path, flight=plan.flight, alone=solved is not None, alone_reason=why, offset=offset, points=pts,
            detections=st.dets.items, windows=windows, window_source=st.window_source, legs=legs, leg_source=st.leg_source,
            frames=st.dets.stats, origin=st.read.origin, origin_moved_m=_origin_distance(st.read.origin, origin),
            alone_rms_px=None if solved is None else float(solved.result.rms_px),
        ))
        points += pts
        n_index = max([n_index + len(st.windows)] + [p.window.index + 1 for p in pts])
        n_legs += len(st.legs)
    return points, runs, tracks


def _frame_move(src: EnuOrigin, dst: EnuOrigin):
    """A function moving (N, 3) ENU points at ``src`` into the ENU frame at ``dst`` (identity when they are one).

    Through WGS84 with pyproj (geodesy.py). The sigmas stay as they are: two
    frames a few hundred metres apart turn by under 1e-4 rad.
    """
    if src == dst:
        return lambda X: X

    def move(X):
        X = np.asarray(X, float)
        if X.size == 0:
            return X
        llh = enu_to_geodetic(X.reshape(-1, 3), src)
        return geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2], dst).reshape(X.shape)

    return move


def _origin_distance(a: EnuOrigin, b: EnuOrigin) -> float:
    return 0.0 if a == b else float(np.linalg.norm(geodetic_to_enu(a.lat_deg, a.lon_deg, a.h_m, b)[0]))


def _renumbered(p, n_index: int, n_legs: int, moved):
    """A point with its window numbered after the runs before (a leg pair's seq is its leg) and in the joint frame."""
    w = p.window
    w = replace(w, index=w.index + n_index, seq=(w.seq + n_legs) if (w.source == "leg" and w.seq is not None) else w.seq)
    X = None if p.marker_enu_m is None else moved(np.asarray(p.marker_enu_m, float)[None])[0]
    return replace(p, window=w, marker_enu_m=X)


def _concat_tracks(tracks: list[Track]) -> Track:
    vel = [t.velocity_enu_mps for t in tracks]
    return Track(
        t_ns=np.concatenate([t.t_ns for t in tracks]),
        antenna_enu_m=np.concatenate([t.antenna_enu_m for t in tracks]),
        marker_enu_m=np.concatenate([t.marker_enu_m for t in tracks]),
        sigma_enu_m=np.concatenate([t.sigma_enu_m for t in tracks]),
        fix_types=[f for t in tracks for f in t.fix_types],
        velocity_enu_mps=None if any(v is None for v in vel) else np.concatenate(vel),
    )


def _sum_frames(stats: list[FrameStats]) -> FrameStats:
    units = [s.video_units_decoded for s in stats]
    return FrameStats(
        frames_read=sum(s.frames_read for s in stats), frames_decoded=sum(s.frames_decoded for s in stats),
        frames_corrupt=sum(s.frames_corrupt for s in stats), frames_with_marker=sum(s.frames_with_marker for s in stats),
        other_ids=tuple(sorted({i for s in stats for i in s.other_ids})), transitions_dense=sum(s.transitions_dense for s in stats),
        formats=tuple(sorted({f for s in stats for f in s.formats})),
        video_units_decoded=None if all(u is None for u in units) else sum(u or 0 for u in units),
        frames_from_live=sum(s.frames_from_live for s in stats),
    )


def _warnings(stages: list[RunStages], parts: list, runs: list[JointRun]) -> list[str]:
    """Each run's warnings, prefixed with its name, and what pooling decided."""
    out: list[str] = []
    for st, (solved, pts, _, why), run in zip(stages, parts, runs):
        name = st.path.name
        own = list(st.warnings) + (list(solved.warnings) if solved is not None else [])
        own += [damage_cost(span, pts, st.read.track.t_ns) for span in st.damaged]
        own += [clock_jump_cost(e, pts, st.read.track.t_ns) for e in st.jumps]
        out += [f"{name}: {w}" for w in own]
        if not run.alone:
            out.append(f"{name} does not calibrate alone ({why}); its points are paired at its time offset from the marker's "
                       f"motion ({st.offset.offset_s:+.3f} s, not refined through a camera) with the other runs' camera")
    return out
