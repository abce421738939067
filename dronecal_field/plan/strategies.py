"""``plan``'s scoring of the paper's strategies (the lattice itself lives in ``dronecal_field.sampling.lattice``).

The names of ``sampling.lattice`` are re-exported here so older imports keep
working; new code imports them from ``dronecal_field.sampling``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

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
