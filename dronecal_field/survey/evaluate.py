"""One (camera, strategy) of the survey: sample its points, run the engine's Monte-Carlo, make a row.

Pure computation (no files, no cluster): ``evaluate_case`` is what a Dask
worker runs, ``evaluate_batch`` a list of them in one task.
``evaluate_strategy_row`` scores a strategy on any known camera; ``plan``
scores its candidates with it through ``runner.score_strategies`` (same
rows, same Dask machinery: ``plan.strategies.score_candidates``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from dronecal_field.core.camera import Camera
from dronecal_field.errors import CalibrationError, DegenerateGeometryError, DronecalError
from dronecal_field.sampling.lattice import Strategy
from dronecal_field.survey.catalogue import PaperLattice, Sampler
from dronecal_field.survey.design import SurveyCamera

MIN_THICKNESS_M = 0.05  # as the uncertainty command: points within 5 cm of one plane are coplanar

STATUS_OK = "ok"
STATUS_DEGENERATE = "degenerate"  # too few points seen, or all on one plane / line
STATUS_FAILED = "failed"  # the engine could not calibrate the reference data


@dataclass(frozen=True)
class MonteCarloSettings:
    """The noise model and solver of every Monte-Carlo (paper section III.B by default)."""

    trials: int = 500
    sigma_3d: tuple[float, float, float] = (0.01, 0.01, 0.015)  # m, RTK X, Y and altimeter Z
    sigma_2d: float = 2.0  # px per axis, the marker detector (paper section IV.A)
    model: str = "default"  # fx, fy, cx, cy, k1, k2, p1, p2 free (OpenCV CALIB_FIX_K3)
    seed: int = 0

    def case_seed(self, camera_id: int) -> int:
        """Monte-Carlo seed of a camera: fixed by (seed, camera_id), shared by its strategies.

        Every strategy of one camera draws from the same stream (common random
        numbers), which sharpens the paired comparisons; the seed does not
        depend on which worker runs the case or when.
        """
        return int(np.random.SeedSequence([self.seed, camera_id]).generate_state(1)[0])


@dataclass(frozen=True)
class Case:
    """One unit of survey work: a design camera and a strategy, sampled by ``sampler``."""

    camera: SurveyCamera
    strategy: Strategy
    sampler: Sampler = PaperLattice()

    @property
    def key(self) -> tuple[int, str]:
        return (self.camera.camera_id, self.strategy.name)


def evaluate_camera(camera: Camera, points: np.ndarray, settings: MonteCarloSettings, seed: int, details: bool = False) -> dict:
    """Monte-Carlo statistics of one camera and its sampled points, as flat row fields.

    Parameters
    ----------
    camera : the reference camera (truth)
    points : (N, 3) sampled 3D points in the camera's world frame, m
    settings : noise model, trials, calibration model
    seed : the Monte-Carlo seed
    details : also return ``ground_error_15m_cm_p95`` and the whole result as
        ``monte_carlo`` (``UncertaintyResult.to_dict()``): what ``plan``
        reports for its chosen candidate; the survey's stored rows leave them out

    Returns
    -------
    dict with ``status`` ('ok', 'degenerate' or 'failed'), ``message`` and,
    when ok, the RMS reprojection error statistics (px), projection errors
    (px) and the ground errors 15 m out (cm, km/h). Degenerate geometry is a
    result, not an exception: the survey records it.
    """
    from dronecal_field.core.calibrate import check_correspondences, resolve_model
    from dronecal_field.core.uncertainty import monte_carlo

    row: dict = {"status": STATUS_OK, "message": None, "n_points": int(len(points))}
    try:
        model = resolve_model(settings.model, len(points))
        check_correspondences(points, camera.project(points), model.n_free, MIN_THICKNESS_M)
    except DegenerateGeometryError as exc:
        row.update(status=STATUS_DEGENERATE, message=str(exc))
        return row
    try:
        mc = monte_carlo(
            camera, points, trials=settings.trials, sigma_3d=settings.sigma_3d,
            sigma_2d=settings.sigma_2d, seed=seed, model=model,
        )
    except (CalibrationError, DegenerateGeometryError) as exc:
        row.update(status=STATUS_FAILED, message=str(exc))
        return row
    row.update(
        rms_mean=mc.rms_mean,
        rms_std=math.sqrt(mc.rms_var) if math.isfinite(mc.rms_var) else float("nan"),
        rms_max=mc.rms_max,
        rms_p5=mc.rms_percentiles[5],
        rms_p50=mc.rms_percentiles[50],
        rms_p95=mc.rms_percentiles[95],
        rms_p99=mc.rms_percentiles[99],
        projection_error_px=mc.projection_error_px,
        ground_projection_error_px=mc.ground_projection_error_px,
        ground_error_15m_cm=mc.ground_error_15m_cm,
        speed_error_15m_kmh=mc.speed_error_15m_kmh,
        failed_trials=mc.failed_trials,
    )
    if details:
        row.update(ground_error_15m_cm_p95=mc.ground_error_15m_cm_p95, monte_carlo=mc.to_dict())
    if mc.failed_trials == mc.trials:
        row.update(status=STATUS_FAILED, message=f"all {mc.trials} trials failed to converge")
    return row


def evaluate_strategy_row(
    camera: Camera, strategy: Strategy, sampler: Sampler, settings: MonteCarloSettings, seed: int | None = None, details: bool = False
) -> dict:
    """Row of one strategy on a known camera (the survey's cases and ``plan``'s candidates): points, heights, statistics.

    ``camera`` is in the frame the sampler works in (the site frame); the
    Monte-Carlo seed defaults to ``settings.seed`` so all strategies share
    their noise draws; ``details`` as in :func:`evaluate_camera`.
    """
    row: dict = {"strategy": strategy.name, "x_min_m": strategy.x_min_m, "x_max_m": strategy.x_max_m,
                 "y_step_m": strategy.y_step_m, "n_heights": strategy.n_heights, "trials": settings.trials}
    try:
        points = sampler.points(strategy, camera)
    except DronecalError as exc:
        row.update(status=STATUS_DEGENERATE, message=str(exc), n_points=0, heights_m="")
        return row
    row["heights_m"] = ",".join(f"{z:g}" for z in sorted(set(np.round(points[:, 2], 3)))) if len(points) else ""
    row.update(evaluate_camera(camera, points, settings, settings.seed if seed is None else seed, details))
    return row


def evaluate_case(case: Case, settings: MonteCarloSettings) -> dict:
    """The survey row of one (camera, strategy): design factors, strategy, points and statistics."""
    t0 = time.perf_counter()
    cam, strat = case.camera, case.strategy
    row: dict = {
        "camera_id": cam.camera_id,
        "strategy": strat.name,
        "focal_mm": cam.focal_mm,
        "focal_px": cam.focal_px,
        "width_px": cam.width_px,
        "height_px": cam.height_px,
        "hfov_deg": cam.hfov_deg,
        "elevation_m": cam.elevation_m,
        "tilt_deg": cam.tilt_deg,
        "distorted": cam.distorted,
    }
    row.update(evaluate_strategy_row(cam.camera(), strat, case.sampler, settings, settings.case_seed(cam.camera_id)))
    row["compute_s"] = time.perf_counter() - t0
    return row


def evaluate_batch(cases: list[Case], settings: MonteCarloSettings) -> list[dict]:
    """Rows of several cases, in order (one Dask task: amortises scheduling over ~1 s of work)."""
    _limit_threads()
    return [evaluate_case(c, settings) for c in cases]


def _limit_threads() -> None:
    """One numba thread in a Dask worker thread, whatever the worker was started with (see cluster.py).

    Outside a worker (the in-process runner) numba keeps its default threads.
    """
    try:
        from distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return
    try:
        import numba

        if numba.get_num_threads() != 1:
            numba.set_num_threads(1)
    except (ImportError, ValueError):
        pass


def warm_up() -> None:
    """Compile (or load from cache) the engine's kernels in this process: a small Monte-Carlo."""
    from dronecal_field.core.synthetic import paper_camera, paper_grid
    from dronecal_field.core.uncertainty import monte_carlo

    _limit_threads()
    camera = paper_camera()
    monte_carlo(camera, paper_grid(camera), trials=4, seed=0)
