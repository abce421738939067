"""``plan``'s scoring of the paper's strategies (the lattice itself lives in ``dronecal_field.sampling.lattice``).

The names of ``sampling.lattice`` are re-exported here so older imports keep
working; new code imports them from ``dronecal_field.sampling``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from dronecal_field.core.camera import Camera
from dronecal_field.plan.route import FlightModel, plan_route
from dronecal_field.sampling.lattice import (  # noqa: F401  (re-exported)
    MIN_POINTS,
    MIN_POINTS_PER_LEVEL,
    PLAN_FOLD_FRACTION,
    PLAN_FOLD_MIN_SLOPE,
    X_RANGES_M,
    GridScreen,
    Limits,
    Strategy,
    alternatives,
    choose_heights,
    fold_radius,
    geometry_problem,
    horizontal_fov_deg,
    make_strategy,
    marker_corners,
    paper_strategies,
    recommended_strategy,
    sample_grid,
    screen_grid,
    screen_points,
    xy_lattice,
)

if TYPE_CHECKING:  # the survey imports sampling, not this module; its settings are only named here
    from dronecal_field.survey.evaluate import MonteCarloSettings


@dataclass(frozen=True, eq=False)
class StrategyScore:
    """A strategy evaluated on a camera: its points, flight time and predicted uncertainty."""

    strategy: Strategy
    screen: GridScreen
    n_points: int
    flight_time_s: float | None
    rms_mean_px: float | None = None
    rms_p95_px: float | None = None
    ground_error_15m_cm: float | None = None
    ground_error_15m_cm_p95: float | None = None
    uncertainty: dict | None = None  # MonteCarloResult.to_dict()
    problem: str | None = None  # why it cannot be flown / predicted

    @property
    def usable(self) -> bool:
        return self.problem is None and self.rms_mean_px is not None

    def row(self) -> dict:
        """JSON-ready table row."""
        return {
            "candidate": self.strategy.name,
            "strategy": self.strategy.describe(),
            "heights_m": list(self.screen.heights_m),
            "points": self.n_points,
            "flight_time_s": None if self.flight_time_s is None else round(self.flight_time_s, 1),
            "rms_mean_px": self.rms_mean_px,
            "rms_p95_px": self.rms_p95_px,
            "ground_error_15m_cm": self.ground_error_15m_cm,
            "ground_error_15m_cm_p95": self.ground_error_15m_cm_p95,
            "problem": self.problem,
        }


def score_candidates(
    camera: Camera,
    strategies: Sequence[Strategy],
    limits: Limits,
    settings: MonteCarloSettings | None = None,
    flight: FlightModel | None = None,
    client: Any = None,
) -> tuple[StrategyScore, ...]:
    """Score candidate strategies on one camera: points and flight time here, Monte-Carlo through the survey.

    Each strategy is screened and its route timed in this process (plan's
    own rules: :func:`geometry_problem`, ``plan.route``); those that can
    calibrate are then scored by ``survey.runner.score_strategies`` with
    ``PlanLattice(limits)``, the very row function the survey runs, on Dask
    when ``client`` is given. All candidates share ``settings.seed`` (common
    random numbers), so their differences are not noise.

    Parameters
    ----------
    camera : the (guessed) camera, world = site frame
    strategies : the candidates, in the order of the result
    limits : where the drone may go and what the detector reads
    settings : ``survey.evaluate.MonteCarloSettings`` (noise, trials, model, seed);
        None gives the plan defaults (200 trials, RTK 1 / 1.5 cm, 2 px)
    flight : ``plan.route.FlightModel`` for the flight time (default one if None)
    client : ``distributed.Client`` to score on a cluster, None for this process

    Returns
    -------
    tuple of StrategyScore, one per strategy; ``problem`` says why one cannot calibrate.
    """
    from dronecal_field.survey.catalogue import PlanLattice
    from dronecal_field.survey.evaluate import STATUS_OK, MonteCarloSettings
    from dronecal_field.survey.runner import score_strategies

    if settings is None:
        settings = MonteCarloSettings(trials=200)
    screens = [screen_grid(s, camera, limits) for s in strategies]
    flight_times: list[float | None] = []
    problems: list[str | None] = []
    for screen in screens:
        points = screen.points
        problems.append(geometry_problem(points) if len(points) else "no point is both seen and allowed")
        if len(points):
            route = plan_route(screen.vehicle_points, points, limits, flight or FlightModel())
            flight_times.append(route.flight_time_s)
        else:
            flight_times.append(None)
    todo = [i for i, problem in enumerate(problems) if problem is None]
    rows = score_strategies(camera, tuple(strategies[i] for i in todo), PlanLattice(limits), settings, client=client, details=True)
    row_of = dict(zip(todo, rows))
    scores = []
    for i, (strategy, screen) in enumerate(zip(strategies, screens)):
        base = dict(strategy=strategy, screen=screen, n_points=len(screen.points), flight_time_s=flight_times[i])
        row = row_of.get(i)
        if row is None:
            scores.append(StrategyScore(**base, problem=problems[i]))
        elif row["status"] != STATUS_OK:
            scores.append(StrategyScore(**base, problem=row["message"]))
        else:
            if row["n_points"] != base["n_points"]:
                raise RuntimeError(f"{strategy.name}: the survey sampled {row['n_points']} points, plan {base['n_points']}: the samplers disagree")
            scores.append(StrategyScore(
                **base,
                rms_mean_px=_finite(row["rms_mean"]),
                rms_p95_px=_finite(row["rms_p95"]),
                ground_error_15m_cm=_finite(row["ground_error_15m_cm"]),
                ground_error_15m_cm_p95=_finite(row["ground_error_15m_cm_p95"]),
                uncertainty=row["monte_carlo"],
            ))
    return tuple(scores)


def evaluate_strategy(
    camera: Camera,
    strategy: Strategy,
    limits: Limits,
    trials: int = 200,
    sigma_3d: tuple[float, float, float] = (0.01, 0.01, 0.015),
    sigma_2d: float = 2.0,
    seed: int = 0,
    model: str = "default",
    flight: FlightModel | None = None,
) -> StrategyScore:
    """One candidate of :func:`score_candidates`, in this process.

    Parameters
    ----------
    camera : the (guessed) camera, world = site frame
    strategy, limits : what to sample and where the drone may go
    trials : Monte-Carlo trials (the paper uses 500; ~200 ranks candidates)
    sigma_3d : position noise std (x, y, z), m (paper: RTK 1 cm, 1.5 cm vertical)
    sigma_2d : detection noise std, px (paper: 2)
    seed : Monte-Carlo seed
    model : calibration model of the prediction
    flight : ``plan.route.FlightModel`` for the flight time (default one if None)

    Returns
    -------
    StrategyScore; ``problem`` says why when the points cannot calibrate.
    """
    from dronecal_field.survey.evaluate import MonteCarloSettings

    settings = MonteCarloSettings(trials=trials, sigma_3d=tuple(sigma_3d), sigma_2d=sigma_2d, model=model, seed=seed)
    return score_candidates(camera, [strategy], limits, settings, flight)[0]


def _finite(v: object) -> float | None:
    try:
        f = float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


# --------------------------------------------------------------------------
# The image-space design (``--strategy image``): candidates scored by the predicted ROI error

DEFAULT_LATTICES: tuple[tuple[int, int], ...] = ((5, 4), (7, 5), (8, 5), (9, 6))
# (depths per ray, far / near ratio or None for the widest, nearest distance from the camera or None)
DEFAULT_DEPTHS: tuple[tuple[int, float | None, float | None], ...] = ((2, None, None), (2, 2.0, None), (3, None, None), (2, None, 4.0), (3, None, 4.0))


@dataclass(frozen=True, eq=False)
class ImageCandidate:
    """One image-space layout on one camera: its design, predicted ROI error and flight time."""

    design: Any  # sampling.design.Design
    prediction: Any  # sampling.predict.RoiPrediction | None
    flight_time_s: float | None
    problem: str | None = None

    @property
    def name(self) -> str:
        return self.design.params.name

    @property
    def usable(self) -> bool:
        return self.problem is None and self.prediction is not None

    @property
    def objective(self) -> float:
        """Lower is better: combined (noise + extrapolation) projection RMS over the ROI, px."""
        return self.prediction.combined_rms_px if self.usable else math.inf

    def row(self) -> dict:
        """JSON-ready table row."""
        p = self.design.params
        s = self.prediction.summary() if self.prediction is not None else None
        return {
            "candidate": self.name, "strategy": p.describe(), "lattice": [p.n_u, p.n_v], "depths": p.n_depths,
            "depth_ratio": p.depth_ratio, "marker_size_m": p.marker_size_m, "sampling": p.sampling,
            "holds": self.design.n_points, "leg_samples": self.design.n_leg_samples,
            "leg_speed_m_s": round(self.design.speed_m_s, 3) if p.sampling != "hover" else None,
            "coverage_pct": round(100.0 * self.design.coverage, 1),
            "flight_time_s": None if self.flight_time_s is None else round(self.flight_time_s, 1),
            "roi_lin_rms_px": None if s is None else s["linearised_px"]["rms"],
            "roi_extrap_rms_px": None if s is None else s["extrapolation_px"]["rms"],
            "roi_combined_rms_px": None if s is None else s["combined_px"]["rms"],
            "roi_combined_max_px": None if s is None else s["combined_px"]["max"],
            "ground_combined_rms_cm": None if s is None else s["ground_combined_cm"]["rms"],
            "model": None if s is None else s["model"],
            "problem": self.problem,
        }


def image_candidate_params(marker_sizes: Sequence[float], samplings: Sequence[str],
                           lattices: Sequence[tuple[int, int]] = DEFAULT_LATTICES,
                           depths: Sequence[tuple[int, float | None, float | None]] = DEFAULT_DEPTHS) -> list:
    """Every layout to score: lattice x depths x marker size x sampling (``sampling.design.DesignParams``)."""
    from dronecal_field.sampling.design import DesignParams

    return [DesignParams(n_u=nu, n_v=nv, n_depths=nd, depth_ratio=ratio, min_depth_m=near, marker_size_m=float(m), sampling=smp)
            for m in marker_sizes for (nu, nv) in lattices for (nd, ratio, near) in depths for smp in samplings]


def design_problem(points: np.ndarray) -> str | None:
    """Why a designed point set cannot give a non-coplanar calibration, or None."""
    if len(points) < MIN_POINTS:
        return f"{len(points)} points (need {MIN_POINTS})"
    centred = points - points.mean(axis=0)
    thickness = float(np.linalg.svd(centred, compute_uv=False)[-1] / math.sqrt(len(points)))
    if thickness < 0.05:
        return f"the points lie within {thickness * 100:.0f} mm of one plane (need depth spread for a non-coplanar calibration)"
    return None


def score_image_candidates(
    camera: Camera,
    roi: Any,
    params: Sequence[Any],
    limits: Limits,
    flight: FlightModel,
    timing: Any,
    noise: Any,
    draws: np.ndarray,
    takeoff_site: np.ndarray | None = None,
    end: str = "land",
) -> tuple[ImageCandidate, ...]:
    """Design, time and predict every layout of ``params`` (see ``sampling.design`` and ``sampling.predict``).

    Parameters
    ----------
    camera : the guessed camera, site frame
    roi : ``sampling.roi.Roi`` of that camera
    params : the layouts (``sampling.design.DesignParams``)
    limits : where the drone may go; the marker size comes from each layout
    flight : timing model (hover, speed) of ``plan.route``
    timing : ``sampling.design.LegTiming`` (frame rate, exposure, GNSS rate)
    noise : ``sampling.predict.NoiseModel``
    draws : (D, 6) lens draws for the extrapolation term (``sampling.predict.lens_draws``)
    takeoff_site : (3,) site frame, or None for beside the points
    end : 'land' or 'rtl'

    Returns
    -------
    tuple of ImageCandidate in the order of ``params``; ``problem`` says why one cannot be flown.
    Lattices are screened once per (lattice, marker size) and shared.
    """
    from dronecal_field.errors import PlanError
    from dronecal_field.sampling.design import design_sampling, screen_targets
    from dronecal_field.sampling.predict import predict_roi
    from dronecal_field.sampling.roi import evaluation_points

    roi_pts, roi_ground = evaluation_points(roi)
    cache: dict[tuple[int, int, float], Any] = {}
    legs_cache: dict = {}
    extrap_cache: dict = {}
    out = []
    for p in params:
        key = (p.n_u, p.n_v, p.marker_size_m)
        lim = replace(limits, marker_size_m=p.marker_size_m)
        if key not in cache:
            cache[key] = screen_targets(camera, roi, p.n_u, p.n_v, lim)
        d = design_sampling(camera, roi, p, lim, timing, hover_s=flight.hover_s, screened=cache[key], legs_cache=legs_cache)
        problem = design_problem(d.marker_site) if d.n_points else "no target pixel has an allowed point along its ray"
        ft = None
        if d.n_points:
            try:
                # mixed: the fixes between holds are only sharp if every leg is flown at the leg speed
                fl = replace(flight, speed_m_s=min(flight.speed_m_s, d.speed_m_s)) if p.sampling == "mixed" else flight
                route = plan_route(d.vehicle_site, d.marker_site, lim, fl, takeoff_site=takeoff_site, end=end, hold_s=d.hold_s,
                                   ordered=True, leg_speed_m_s=d.speed_m_s if p.sampling == "through" else None)
                ft = route.flight_time_s
            except PlanError as exc:
                problem = problem or str(exc)
        pred = None
        if problem is None:
            same_samples = (p.n_u, p.n_v, p.n_depths, p.depth_ratio, p.min_depth_m, p.marker_size_m, p.sampling == "hover")
            pred = predict_roi(camera, d.samples_site, d.samples_sigma_h_m, roi_pts, roi_ground, noise, draws, d.samples_rtk_factor,
                               extrap_cache=extrap_cache, cache_key=same_samples)
        out.append(ImageCandidate(design=d, prediction=pred, flight_time_s=ft, problem=problem))
    return tuple(out)


def predict_points_on_roi(camera: Camera, points: np.ndarray, roi: Any, noise: Any, draws: np.ndarray,
                          sigma_h_extra_m: np.ndarray | None = None, rtk_factor: np.ndarray | None = None) -> Any:
    """The ROI prediction (``sampling.predict.RoiPrediction``) of samples (N, 3); hover points unless
    ``sigma_h_extra_m`` (N,) adds a timing term per sample (the paper's grid is scored the same way)."""
    from dronecal_field.sampling.predict import predict_roi
    from dronecal_field.sampling.roi import evaluation_points

    roi_pts, roi_ground = evaluation_points(roi)
    extra = np.zeros(len(points)) if sigma_h_extra_m is None else np.asarray(sigma_h_extra_m, float)
    return predict_roi(camera, points, extra, roi_pts, roi_ground, noise, draws, rtk_factor)
