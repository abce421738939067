"""The offline stage, runs x cameras: ``calibrate_runs(paths, options) -> SiteReport``.

One orchestration for one run of one camera, the flights of one plan pooled
(``--joint``) and every camera of a site::

    per run, per camera: read track -> hover windows + legs -> detections -> time alignment   (stages.run_stages)
    per camera:  one run:      solve (-> timing refined through the camera -> points -> solve)  (solve)
                               -> uncertainty -> report                                       (confidence, report)
                 several runs: each alone, then pooled in the first run's ENU frame           (joint.pool_runs)
    several cameras: the relative pose of every pair in the run's one ENU frame              (site, site_page)

A run's track, hover windows and legs are read once and shared by its
cameras; each camera keeps its own clock offset, model, uncertainty and
region of validity. ``calibrate_run`` is the one-run, one-camera case and
returns its ``CalibrationReport`` as it always has.

No printing: the command prints a summary; every number lands in report.json
(and, for several cameras, site.json).

Memory is bounded: fixes and attitude (a few floats per sample) are held in
arrays, frames are streamed once per camera through the hover windows and the
legs and only the detections are kept.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

from dronecal_field.errors import CalibrationError, ContractError, DegenerateGeometryError, DronecalError, InputError
from dronecal_field.geodesy import EnuOrigin
from dronecal_field.pipeline.asflown import correlated_noise, flight_against_plan
from dronecal_field.pipeline.confidence import sigma_scale, uncertainty
from dronecal_field.pipeline.results import (  # noqa: F401 - the stage's public names, where callers have always found them
    HOVER_SOURCES,
    LEG_SOURCES,
    MIN_POINTS,
    CalibrateOptions,
    CalibrationReport,
    FrameStats,
    Track,
)
from dronecal_field.pipeline.solve import check_physical, check_supported, clear_minimum, solve_at_offset  # noqa: F401
from dronecal_field.pipeline.stages import (
    RunStages,
    StageClock,
    clock_jump_cost,
    cut_off_at,
    damage_cost,
    offset_with_timing,
    run_stages,
    with_camera,
)
from dronecal_field.pipeline.track import find_legs

# Older names of the stages (tests and tools import them from here).
_find_legs = find_legs
_clock_jump_cost = clock_jump_cost
__all__ = ["CalibrateOptions", "CalibrationReport", "SiteReport", "calibrate_run", "calibrate_runs", "sigma_scale"]


@dataclass(frozen=True, eq=False)
class SiteReport:
    """Every camera of the runs calibrated: one report each, and how they sit to each other.

    Attributes
    ----------
    run_paths : the runs, in the order given.
    cameras : camera name -> its CalibrationReport (a ``joint.JointReport`` when several runs were pooled);
        the name is None for the one camera of one-camera runs.
    failed : camera name -> why it could not be calibrated (the others still are).
    pairs : the relative pose of every pair of calibrated cameras (``site.RelativePose``).
    origin : the ENU frame every camera is in.
    timings_s : wall time of each stage, summed over the cameras.
    outputs : files written (site.json, report.html) when ``options.out_dir`` is set.
    """

    run_paths: tuple[Path, ...]
    cameras: dict
    failed: dict[str, str]
    pairs: list
    origin: EnuOrigin | None
    timings_s: dict[str, float]
    outputs: dict[str, str] = field(default_factory=dict)

    @property
    def several(self) -> bool:
        """True for a site (cameras named by the run), False for one-camera runs."""
        return any(name is not None for name in (*self.cameras, *self.failed))


def calibrate_run(path: str | os.PathLike, options: CalibrateOptions = CalibrateOptions(), live=None,
                  camera: str | None = None) -> CalibrationReport:
    """Calibrate the camera seen in one run file; write the outputs when ``options.out_dir`` is set.

    When a cut-off run cannot be calibrated, the error says where it is cut:
    the missing part is the likely reason (e.g. a second height never flown).

    Parameters
    ----------
    path : a run file following shared/contracts/run-format.md (also cut off)
    options : see CalibrateOptions
    live : pipeline.framecache.FrameResults of ``fly``'s live pass over this run (same process), or None:
        its detector outcomes stand in for the frames it covered (not decoded again); JPEG/PNG runs only
    camera : in a several-camera run, the camera to calibrate (None: the first); every camera at once is
        :func:`calibrate_runs`

    Returns
    -------
    CalibrationReport

    Raises
    ------
    ContractError : the file breaks the contract (names what is missing)
    InputError : no usable fix, no hover window or leg, no marker found
    DegenerateGeometryError : too few good waypoints, coplanar points
    CalibrationError : the solver found no trustworthy camera
    """
    path = Path(path)
    clock = StageClock()
    return _noting_cut([path], lambda: calibrate_stages([run_stages(path, options, live, clock, camera)], options, clock))


def calibrate_runs(paths: list[str | os.PathLike], options: CalibrateOptions = CalibrateOptions(), live=None) -> SiteReport:
    """Calibrate every camera of the runs, each camera pooled over the runs that have it.

    Parameters
    ----------
    paths : run files: one, or the flights of one plan (pooled per camera); several-camera runs
        (``/cameras/<name>/...``) and one-camera runs are not mixed
    options : see CalibrateOptions; ``out_dir`` gets one folder per camera (``<out>/<name>/``) plus
        site.json and the site's report.html for a several-camera run, or the one camera's outputs
    live : fly's live pass (pipeline.framecache.FrameResults), used for a one-camera run only

    Returns
    -------
    SiteReport

    Raises
    ------
    InputError : runs given twice, one-camera and several-camera runs mixed, or no camera calibrated (the
        first camera's error when it is the only one)
    """
    from dronecal_field.pipeline.joint import check_runs, plan_of_run

    paths = [Path(p) for p in paths]
    if len(paths) > 1:
        check_runs(paths)
    names = [_camera_names(p) for p in paths]
    cameras = list(dict.fromkeys(n for run in names for n in run))
    if None in cameras and len(cameras) > 1:
        one = next(p for p, run in zip(paths, names) if run == (None,))
        several = next(p for p, run in zip(paths, names) if run != (None,))
        raise InputError(f"{one.name} has one camera (/camera/...) and {several.name} several (/cameras/<name>/...): "
                         "calibrate them apart, or pool runs of the same cameras")
    plans = [plan_of_run(p) for p in paths] if len(paths) > 1 else []
    clock = StageClock()  # the site's own stages; each camera has its own clock (its report's timings_s)
    shared: dict[Path, RunStages] = {}  # each run's first stages: its track, windows and legs, for its other cameras
    reports: dict = {}
    failed: dict[str, str] = {}
    for cam in cameras:
        have = [k for k, run in enumerate(names) if cam in run]
        opts = options if cam is None or options.out_dir is None else replace(options, out_dir=Path(options.out_dir) / cam)
        try:
            reports[cam] = _noting_cut([paths[k] for k in have], lambda: _calibrate_camera(
                [paths[k] for k in have], [plans[k] for k in have] if plans else [], cam, opts, live if cam is None else None,
                StageClock(), shared))
        except DronecalError as exc:
            if cam is None or len(cameras) == 1 or isinstance(exc, ContractError):
                raise
            failed[cam] = str(exc)
    if not reports:
        raise CalibrationError("no camera calibrated: " + "; ".join(f"{n}: {e}" for n, e in failed.items()))
    pairs = []
    named = {n: r for n, r in reports.items() if n is not None}
    if len(named) > 1:
        from dronecal_field.pipeline.site import site_pairs

        pairs = clock("site_s", site_pairs, {n: r.camera for n, r in named.items()},
                      {n: r.covariance_measured for n, r in named.items()}, options.seed)
    first = next(iter(reports.values()))
    timings = dict(clock.timings)
    for r in reports.values():
        for k, v in r.timings_s.items():
            timings[k] = timings.get(k, 0.0) + v
    site = SiteReport(run_paths=tuple(paths), cameras=reports, failed=failed, pairs=pairs, origin=first.origin, timings_s=timings)
    if site.several and options.out_dir is not None:
        from dronecal_field.pipeline.site_page import write_site

        site.outputs.update(clock("outputs_s", write_site, site, Path(options.out_dir)))
    return site


def _camera_names(path: Path) -> tuple[str | None, ...]:
    """The cameras of a run: their names in a several-camera run, (None,) for a one-camera run."""
    from dronecal_field.runfile.reader import open_run

    with open_run(path) as run:
        return run.cameras or (None,)


def _calibrate_camera(paths: list[Path], plans: list, camera: str | None, options: CalibrateOptions, live, clock: StageClock,
                      shared: dict[Path, RunStages]) -> CalibrationReport:
    """One camera over the runs that have it: stages 1-4 per run (a run's track shared by its cameras), then alone or pooled."""
    stages = []
    for p in paths:
        st = run_stages(p, options, live, clock, camera, like=shared.get(p))
        shared.setdefault(p, st)
        stages.append(st)
    return calibrate_stages(stages, options, clock, plans)


def calibrate_stages(stages: list[RunStages], options: CalibrateOptions, clock: StageClock, plans: list | None = None) -> CalibrationReport:
    """Stages 5-8 of one camera: from one run's stages alone, from several runs' pooled (``joint.pool_runs``)."""
    if len(stages) > 1:
        from dronecal_field.pipeline.joint import plan_of_run, pool_runs

        return pool_runs(stages, plans or [plan_of_run(st.path) for st in stages], options, clock)
    return _finish(stages[0], options, clock)


def _noting_cut(paths: list[Path], calibrate):
    """``calibrate()``, with a cut-off run's byte offset added to its error: the missing part is the likely reason."""
    try:
        return calibrate()
    except ContractError:
        raise
    except DronecalError as exc:
        cuts = [(p, cut_off_at(p)) for p in paths]
        cuts = [(p, c) for p, c in cuts if c is not None]
        if not cuts:
            raise
        where = f"the run is cut off at byte {cuts[0][1]}" if len(paths) == 1 else f"{cuts[0][0].name} is cut off at byte {cuts[0][1]}"
        raise type(exc)(f"{exc} ({where}: only its complete part could be used)") from None


def _finish(st: RunStages, options: CalibrateOptions, clock: StageClock) -> CalibrationReport:
    """One run of one camera: solve at its offset, uncertainty, report (and its files)."""
    md, read, windows, legs, dets = st.md, st.read, st.windows, st.legs, st.dets
    causes = flight_against_plan(read, windows, legs)
    try:
        solved, offset = clock("calibration_s", solve_at_offset, read, windows, legs, dets, st.offset, md, options)
        check_physical(solved.result, solved.points, md, solved.noise)
    except (DegenerateGeometryError, CalibrationError) as exc:
        if not causes:
            raise
        raise type(exc)(f"{'; '.join(causes)}: {exc}") from None
    flown = [f"{c}: the calibration used what that flight gave" for c in causes]
    notices = ([solved.agreement.line] if solved.agreement is not None and solved.agreement.line else []) + flown
    correlated = correlated_noise(solved.noise)
    if correlated:
        notices.append(correlated)
    warnings = notices + list(st.warnings) + solved.warnings
    warnings += [damage_cost(span, solved.points, read.track.t_ns) for span in st.damaged]
    warnings += [clock_jump_cost(e, solved.points, read.track.t_ns) for e in st.jumps]
    camera = solved.result.camera.with_(enu_origin=tuple(read.origin.as_list()))
    result = with_camera(solved.result, camera)
    unc = clock("uncertainty_s", uncertainty, camera, solved.points, result, options, read.origin, read.plan_roi)
    check_supported(unc.monte_carlo, result, solved.noise, causes)
    report = CalibrationReport(
        run_path=st.path, truncated=st.truncated, run_warnings=st.run_warnings, metadata=md,
        origin=read.origin, origin_source=read.origin_source, altitude_datum=md.altitude_datum,
        windows=windows, window_source=st.window_source, frames=dets.stats, detections=dets.items, detection_groups=dets.groups,
        offset=offset_with_timing(offset, solved.timing, read, solved.noise), points=solved.points, attitude_source=solved.attitude_source,
        model_reason=solved.model_reason, result=result, monte_carlo=unc.monte_carlo, linearised=unc.linearised,
        covariance_measured=unc.covariance, maps=unc.maps, homography=unc.homography, track=solved.track,
        timings_s=clock.timings, warnings=warnings, options=options, background=dets.background,
        fixes_repeated=read.identity.n_repeats, centres=solved.centres, legs=legs, leg_source=st.leg_source,
        timing=solved.timing, fix_identity=read.identity, gnss_latency_s=read.gnss_latency_s, validity=unc.validity,
        noise=solved.noise, sigma_scale=unc.sigma_scale, agreement=solved.agreement, notices=notices,
    )
    if options.out_dir is not None:
        from dronecal_field.pipeline.report import write_outputs

        report.outputs.update(clock("outputs_s", write_outputs, report, Path(options.out_dir)))
    return report

