"""Run a survey: cameras x strategies, in batches on Dask, stored as they finish, resumable.

The stage between the command (flags, printing) and the pure pieces
(design, catalogue, evaluate, store). It returns a :class:`SurveyReport`.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import IO, Any

from dronecal_field.cluster import map_with_progress, run_on_every_worker, worker_count
from dronecal_field.errors import InputError
from dronecal_field.sampling.lattice import Strategy
from dronecal_field.survey.catalogue import PaperLattice, PlanLattice, Sampler
from dronecal_field.survey.design import DesignSpace, latin_hypercube
from dronecal_field.survey.evaluate import (
    STATUS_DEGENERATE,
    STATUS_FAILED,
    Case,
    MonteCarloSettings,
    _limit_threads,
    evaluate_batch,
    evaluate_strategy_row,
    warm_up,
)
from dronecal_field.survey.store import ResultStore


@dataclass(frozen=True)
class SurveyConfig:
    """Everything that defines the survey's rows (stored in the manifest, checked on resume)."""

    n_cameras: int = 5000
    design_seed: int = 0
    space: DesignSpace = DesignSpace()
    sampler: Sampler = PaperLattice()
    settings: MonteCarloSettings = MonteCarloSettings()

    def to_manifest(self) -> dict:
        """JSON-ready, comparable form (tuples as lists)."""
        sampler = {"name": self.sampler.name, **{k: v for k, v in asdict(self.sampler).items() if k != "name"}}
        if isinstance(self.sampler, PlanLattice):
            sampler["limits"] = asdict(self.sampler.limits)
        return _jsonable(
            {
                "n_cameras": self.n_cameras,
                "design_seed": self.design_seed,
                "space": asdict(self.space),
                "sampler": sampler,
                "monte_carlo": asdict(self.settings),
            }
        )


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    return obj


@dataclass(frozen=True)
class SurveyReport:
    """What a run did: counts (rows), timings (s) and where the rows are."""

    out: str
    total_rows: int
    already_done: int
    computed: int
    degenerate: int
    failed: int
    wall_s: float
    compute_s: float
    workers: int
    rows_per_s: float
    strategies: tuple[str, ...] = field(default=())

    def to_dict(self) -> dict:
        return asdict(self)


def plan_cases(config: SurveyConfig, strategies: tuple[Strategy, ...], done: set[tuple[int, str]]) -> list[Case]:
    """Every (camera, strategy) not yet in ``done``, camera by camera."""
    cameras = latin_hypercube(config.n_cameras, config.design_seed, config.space)
    return [
        Case(camera=cam, strategy=s, sampler=config.sampler)
        for cam in cameras
        for s in strategies
        if (cam.camera_id, s.name) not in done
    ]


def batches(cases: list[Case], size: int) -> list[list[Case]]:
    """Consecutive groups of ``size`` cases (the last may be shorter)."""
    if size < 1:
        raise InputError(f"--batch-size {size} must be at least 1")
    return [cases[i : i + size] for i in range(0, len(cases), size)]


def run_survey(
    config: SurveyConfig,
    strategies: tuple[Strategy, ...],
    out: str | os.PathLike,
    client: Any = None,
    batch_size: int = 10,
    progress: bool | IO[str] = False,
    stop_after_batches: int | None = None,
) -> SurveyReport:
    """Compute every missing row of the survey and store it in ``out``.

    Parameters
    ----------
    config : cameras, sampler and noise (must match what ``out`` already holds)
    strategies : the strategies to run on every camera
    out : results directory (created, or resumed when it exists)
    client : ``distributed.Client``, or None to compute in this process
    batch_size : cases per task and per stored part (~0.15 s each at 500 trials)
    progress : False, True (tqdm bar on stderr with rate and ETA) or a stream
    stop_after_batches : stop after storing this many parts (tests, benchmarks)

    Returns
    -------
    SurveyReport with counts and timings; the rows are in ``out``.
    """
    store = ResultStore(out)
    store.open(config.to_manifest(), [s.name for s in strategies])
    store.clean_temporary()
    done = store.done_keys()
    cases = plan_cases(config, strategies, done)
    total = config.n_cameras * len(strategies)
    already = total - len(cases)
    groups = batches(cases, batch_size)
    if stop_after_batches is not None:
        groups = groups[:stop_after_batches]

    t0 = time.perf_counter()
    computed = degenerate = failed = 0
    compute_s = 0.0
    if groups:
        run_on_every_worker(client, warm_up)
    t_start = time.perf_counter()
    items = [(g, config.settings) for g in groups]
    for _, rows in map_with_progress(
        client, _evaluate_item, items, initial=already, desc="survey", unit="row",
        weight=_item_rows, progress=progress,
    ):
        # a batch is stored whole or not at all; keys are re-checked so a resubmitted task cannot duplicate
        rows = [r for r in rows if (r["camera_id"], r["strategy"]) not in done]
        if rows:
            store.write_part(rows)
            done.update((r["camera_id"], r["strategy"]) for r in rows)
        computed += len(rows)
        degenerate += sum(r["status"] == STATUS_DEGENERATE for r in rows)
        failed += sum(r["status"] == STATUS_FAILED for r in rows)
        compute_s += sum(r["compute_s"] for r in rows)
    elapsed = time.perf_counter() - t_start
    return SurveyReport(
        out=str(Path(out)),
        total_rows=total,
        already_done=already,
        computed=computed,
        degenerate=degenerate,
        failed=failed,
        wall_s=time.perf_counter() - t0,
        compute_s=compute_s,
        workers=worker_count(client),
        rows_per_s=computed / elapsed if elapsed > 0 and computed else 0.0,
        strategies=tuple(s.name for s in strategies),
    )


def _item_rows(item: tuple[list[Case], MonteCarloSettings]) -> int:
    return len(item[0])


def _evaluate_item(item: tuple[list[Case], MonteCarloSettings]) -> list[dict]:
    cases, settings = item
    return evaluate_batch(cases, settings)


def score_strategies(
    camera: Any,
    strategies: tuple[Strategy, ...],
    sampler: Sampler,
    settings: MonteCarloSettings = MonteCarloSettings(),
    client: Any = None,
    progress: bool | IO[str] = False,
    details: bool = False,
) -> list[dict]:
    """Rows of several strategies on one known camera, in the order given: what ``plan`` ranks.

    The survey's row function on the survey's Dask machinery: with a
    ``client`` the strategies run in parallel on the cluster, without one in
    this process. ``sampler`` is usually ``PlanLattice(limits)`` (what plan
    flies); every strategy shares ``settings.seed`` (common random numbers).

    Parameters
    ----------
    camera : core.camera.Camera in the site frame
    strategies : candidates (sampling.lattice.Strategy)
    sampler : how a strategy becomes points for this camera
    settings : noise model and trials
    client : ``distributed.Client``, or None to compute in this process
    progress : False, True (tqdm bar on stderr) or a stream
    details : add ``ground_error_15m_cm_p95`` and the whole Monte-Carlo result
        (``monte_carlo``) to ok rows (see ``evaluate.evaluate_camera``)

    Returns
    -------
    list of row dicts (status, n_points, heights_m, rms_mean, ..., see ``evaluate_camera``)
    """
    items = [(camera, s, sampler, settings, details) for s in strategies]
    rows: list[dict] = [{} for _ in items]
    for index, row in map_with_progress(client, _score_item, items, desc="candidates", unit="strategy", progress=progress):
        rows[index] = row
    return rows


def _score_item(item: tuple[Any, Strategy, Sampler, MonteCarloSettings, bool]) -> dict:
    camera, strategy, sampler, settings, details = item
    _limit_threads()
    return evaluate_strategy_row(camera, strategy, sampler, settings, details=details)
