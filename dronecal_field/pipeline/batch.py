"""Many runs at once (issue 6, "a campus of cameras, one run each"): ``calibrate_many`` on Dask.

Each run is calibrated by :func:`calibrate_one` (module-level, so Dask
workers import it by name), which calls ``pipeline.run.calibrate_run`` and
returns one :class:`BatchRow`: the few numbers a summary needs, not the
whole report (that stays on disk, in the run's own folder). A run that fails
is a row with its error message, never an exception, so one bad file does
not stop the campus.

A several-camera run (``/cameras/<name>/...``, issue 24) is calibrated as
``calibrate run.mcap`` does it (``pipeline.run.calibrate_runs``): every camera,
one row each, and the run's site.json beside their folders.

Layout of ``out_dir``::

    <run-stem>/      camera.yaml, report.json, report.html, ... of that run
    <run-stem>/<camera>/  the same per camera of a several-camera run (site.json, report.html in <run-stem>/)
    summary.csv      one line per run, or per camera of a several-camera run (the order given)
    summary.json     the same rows plus counts, workers, timings and options

Workers read the run files and write the run folders themselves: with a
remote scheduler the paths must mean the same on every worker (a shared
folder).
"""

from __future__ import annotations

import csv
import io
import json
import os
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import IO, Any

from dronecal_field.errors import DronecalError, InputError
from dronecal_field.pipeline.run import CalibrateOptions

SUMMARY_CSV = "summary.csv"
SUMMARY_JSON = "summary.json"
STATUS_OK = "ok"
STATUS_FAILED = "failed"  # a DronecalError: the run itself is the problem (the message says what to do)
STATUS_ERROR = "error"  # anything else: a bug or a lost worker; the message names the exception


@dataclass(frozen=True)
class BatchTask:
    """One run to calibrate: its file and where its outputs go (paths as the workers see them)."""

    run_path: str
    out_dir: str
    options: CalibrateOptions


@dataclass(frozen=True)
class BatchRow:
    """The summary line of one run. Numbers are None when the run failed.

    ``position_enu_m`` is in the run's own ENU frame (each run has its own
    origin: see ``enu_origin``); ``lat_deg``, ``lon_deg``, ``h_m`` place the
    camera on the campus (h ellipsoidal, or as the run's altitude datum).
    """

    run: str  # the run file's stem (its output folder's name)
    run_path: str
    status: str
    out_dir: str
    camera: str | None = None  # the camera of a several-camera run (its folder under the run's); None: a one-camera run
    waypoints_used: int | None = None
    waypoints: int | None = None  # hover windows found
    model: str | None = None
    rms_px: float | None = None
    fx_px: float | None = None
    fy_px: float | None = None
    cx_px: float | None = None
    cy_px: float | None = None
    position_e_m: float | None = None
    position_n_m: float | None = None
    position_u_m: float | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    h_m: float | None = None
    ground_error_15m_cm: float | None = None
    confidence_method: str | None = None  # monte_carlo, or linearised with --trials 0
    time_offset_s: float | None = None
    warnings: int = 0
    wall_s: float = 0.0
    message: str | None = None  # why the run failed

    def to_dict(self) -> dict:
        return asdict(self)


COLUMNS: tuple[str, ...] = tuple(f.name for f in fields(BatchRow))


@dataclass(frozen=True)
class BatchReport:
    """What ``calibrate_many`` did: the rows (in the order given), counts and timings (s)."""

    out_dir: str
    rows: tuple[BatchRow, ...]
    workers: int
    scheduler: str | None
    wall_s: float
    outputs: dict[str, str]

    @property
    def failed(self) -> tuple[BatchRow, ...]:
        return tuple(r for r in self.rows if r.status != STATUS_OK)

    def to_dict(self) -> dict:
        counts: dict[str, int] = {}
        for r in self.rows:
            counts[r.status] = counts.get(r.status, 0) + 1
        return {
            "runs": len(self.rows),
            "counts": counts,
            "workers": self.workers,
            "scheduler": self.scheduler,
            "wall_s": self.wall_s,
            "rows": [r.to_dict() for r in self.rows],
        }


def plan_tasks(runs: list[str | os.PathLike], out_dir: str | os.PathLike, options: CalibrateOptions) -> list[BatchTask]:
    """One task per run, writing to ``out_dir/<run-stem>/``.

    Raises
    ------
    InputError : two runs share a stem (their folders would collide), or ``out_dir`` is a file
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError(f"--out {out} is a file: give a folder for the summary and one folder per run")
    by_stem: dict[str, Path] = {}
    for r in runs:
        p = Path(r)
        if p.stem in by_stem:
            raise InputError(
                f"{by_stem[p.stem]} and {p} both have the stem {p.stem!r}, so their output folders collide: rename one of the runs"
            )
        by_stem[p.stem] = p
    return [
        BatchTask(run_path=str(p.resolve()), out_dir=str((out / stem).resolve()), options=replace(options, out_dir=(out / stem).resolve()))
        for stem, p in by_stem.items()
    ]


def calibrate_one(task: BatchTask) -> tuple[BatchRow, ...]:
    """Calibrate one run and summarise it: one row, or one per camera of a several-camera run (every camera, not
    only the first). Failures become rows with the message (never raised): a camera the run could not calibrate is
    its own failed row beside the others.

    Runs in a Dask worker (or in this process): module-level and
    self-contained, it returns only the summary numbers.
    """
    from dronecal_field.pipeline.run import calibrate_run, calibrate_runs
    from dronecal_field.runfile.reader import open_run

    t0 = time.perf_counter()
    stem = Path(task.run_path).stem
    base = dict(run=stem, run_path=task.run_path, out_dir=task.out_dir)
    try:
        with open_run(task.run_path) as run:
            names = tuple(run.cameras)  # () for a one-camera run
        if names:
            site = calibrate_runs([task.run_path], task.options)
            rows = []
            for name in names:
                where = dict(base, out_dir=str(Path(task.out_dir) / name), camera=name)
                if name in site.cameras:
                    report = site.cameras[name]
                    rows.append(_row_of(report, where, float(sum(report.timings_s.values()))))
                else:  # this camera alone could not be calibrated; the others still are
                    rows.append(BatchRow(**where, status=STATUS_FAILED, message=_one_line(site.failed.get(name, "not calibrated"))))
            return tuple(rows)
        report = calibrate_run(task.run_path, task.options)
        return (_row_of(report, base, time.perf_counter() - t0),)
    except DronecalError as exc:
        return (BatchRow(**base, status=STATUS_FAILED, wall_s=time.perf_counter() - t0, message=_one_line(str(exc))),)
    except Exception as exc:  # noqa: BLE001 - one broken run must not stop the campus; the row names the exception
        return (BatchRow(**base, status=STATUS_ERROR, wall_s=time.perf_counter() - t0, message=_one_line(f"{type(exc).__name__}: {exc}")),)


def _row_of(report: Any, base: dict, wall_s: float) -> BatchRow:
    from dronecal_field.geodesy import enu_to_geodetic

    cam = report.camera
    i = cam.intrinsics
    pos = cam.pose.position_world
    geo = enu_to_geodetic(pos[None], report.origin)[0]
    conf = report.monte_carlo or report.linearised
    return BatchRow(
        **base,
        status=STATUS_OK,
        waypoints_used=len(report.used_points),
        waypoints=len(report.windows),
        model=report.result.model.name,
        rms_px=float(report.result.rms_px),
        fx_px=float(i.fx),
        fy_px=float(i.fy),
        cx_px=float(i.cx),
        cy_px=float(i.cy),
        position_e_m=float(pos[0]),
        position_n_m=float(pos[1]),
        position_u_m=float(pos[2]),
        lat_deg=float(geo[0]),
        lon_deg=float(geo[1]),
        h_m=float(geo[2]),
        ground_error_15m_cm=float(conf.ground_error_15m_cm),
        confidence_method=conf.method,
        time_offset_s=float(report.offset.offset_s),
        warnings=len(report.warnings),
        wall_s=wall_s,
    )


def _one_line(text: str) -> str:
    return " ".join(text.split())


def calibrate_many(
    runs: list[str | os.PathLike],
    out_dir: str | os.PathLike,
    options: CalibrateOptions = CalibrateOptions(),
    client: Any = None,
    scheduler: str | None = None,
    progress: bool | IO[str] = False,
) -> BatchReport:
    """Calibrate every run (one folder each under ``out_dir``) and write summary.csv and summary.json.

    Parameters
    ----------
    runs : run files (.mcap); their stems must differ
    out_dir : folder for the summary and the per-run folders (created)
    options : calibration options for every run (``out_dir`` is set per run)
    client : ``distributed.Client`` (``cluster.dask_client``), or None for this process
    scheduler : the scheduler address, recorded in the summary only
    progress : False, True (tqdm bar on stderr) or a stream

    Returns
    -------
    BatchReport with one row per run in the order given (one per camera of a several-camera run). Failed runs are
    rows (``status`` 'failed' or 'error', ``message``); a worker lost
    mid-way marks the runs it left unfinished as 'error' and the summary is
    still written.
    """
    from dronecal_field.cluster import map_with_progress, worker_count

    if not runs:
        raise InputError("no run files given: pass one or more .mcap files")
    t0 = time.perf_counter()
    tasks = plan_tasks(runs, out_dir, options)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[tuple[BatchRow, ...] | None] = [None] * len(tasks)
    try:
        for index, done in map_with_progress(client, calibrate_one, tasks, desc="calibrate", unit="run", progress=progress):
            rows[index] = done
    except Exception as exc:  # noqa: BLE001 - a lost worker (KilledWorker, connection) stops the map: keep what finished
        if isinstance(exc, DronecalError):
            raise
        reason = _one_line(f"not finished: {type(exc).__name__}: {exc}")
        for k, task in enumerate(tasks):
            if rows[k] is None:
                rows[k] = (BatchRow(run=Path(task.run_path).stem, run_path=task.run_path, out_dir=task.out_dir, status=STATUS_ERROR, message=reason),)
    report = BatchReport(
        out_dir=str(out),
        rows=tuple(r for done in rows if done is not None for r in done),
        workers=worker_count(client),
        scheduler=scheduler,
        wall_s=time.perf_counter() - t0,
        outputs={"summary_csv": str(out / SUMMARY_CSV), "summary_json": str(out / SUMMARY_JSON)},
    )
    write_summary(report, options)
    return report


def write_summary(report: BatchReport, options: CalibrateOptions) -> None:
    """summary.csv (one line per run, ``COLUMNS``) and summary.json (rows + counts + options), atomically."""
    from dronecal_field import __version__

    out = Path(report.out_dir)
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(COLUMNS), lineterminator="\n")
    writer.writeheader()
    for r in report.rows:
        writer.writerow({k: ("" if v is None else v) for k, v in r.to_dict().items()})
    _atomic_write(out / SUMMARY_CSV, buf.getvalue())
    doc = {
        "format": "dronecal-field calibrate batch summary, version 1",
        "created_by": f"dronecal-field {__version__} calibrate",
        **report.to_dict(),
        "options": {
            "min_fix": options.min_fix, "model": options.model, "loss": options.loss, "loss_scale_px": options.loss_scale_px,
            "trials": options.trials, "seed": options.seed, "hover_source": options.hover_source, "annotate": options.annotate,
            "settle_s": options.points.settle_s, "max_frames_per_window": options.sampling.max_frames_per_window,
        },
        "text": "one row per run in the order given (per camera of a several-camera run, its name in camera); position_enu_m is in each run's own ENU frame, lat/lon/h place the camera; "
                "status failed = the run cannot be calibrated (message says why), error = an unexpected exception",
    }
    _atomic_write(out / SUMMARY_JSON, json.dumps(doc, indent=2, allow_nan=False) + "\n")


def _atomic_write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def summary_table(report: BatchReport) -> str:
    """The summary as the command prints it: one line per run, failures with their message."""

    def num(v: float | None, f: str) -> str:
        return format("-", f">{f.split('.')[0]}") if v is None else format(v, f)

    def label(r: BatchRow) -> str:
        return r.run if r.camera is None else f"{r.run}/{r.camera}"

    width = max([len("run")] + [len(label(r)) for r in report.rows])
    lines = [
        f"{'run':<{width}} {'status':<7} {'used':>7} {'RMS px':>7} {'fx px':>9} {'fy px':>9} "
        f"{'E m':>8} {'N m':>8} {'U m':>7} {'gnd@15m cm':>10}",
    ]
    for r in report.rows:
        used = "-" if r.waypoints_used is None else f"{r.waypoints_used}/{r.waypoints}"
        line = (
            f"{label(r):<{width}} {r.status:<7} {used:>7} {num(r.rms_px, '7.3f')} {num(r.fx_px, '9.2f')} {num(r.fy_px, '9.2f')} "
            f"{num(r.position_e_m, '8.3f')} {num(r.position_n_m, '8.3f')} {num(r.position_u_m, '7.3f')} {num(r.ground_error_15m_cm, '10.1f')}"
        )
        if r.message:
            line += f"  {r.message}"
        lines.append(line)
    return "\n".join(lines)
