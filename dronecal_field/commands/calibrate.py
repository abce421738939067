"""``dronecal-field calibrate RUN.mcap``: calibrate the camera from a recorded flight.

Finds the hover windows, detects the marker in the frames around them,
aligns the camera and GNSS clocks, builds one robust 3D-2D point per
waypoint, calibrates, and estimates the confidence (Monte-Carlo with the
measured sigmas) and the region of validity: the part of the image (and of
the ground) the points support, beyond which the predicted error grows.
Writes camera.yaml (with validity_polygon_px), camera_info.yaml,
ground_homography.yaml, validity.geojson, detections.csv, report.json and
report.html into --out.

Many runs (a campus of cameras, one run each):
  calibrate a.mcap b.mcap ... --out DIR [--workers N | --scheduler tcp://HOST:8786]
calibrates them in parallel on Dask (local worker processes by default),
one folder per run (DIR/<run-stem>/), and writes DIR/summary.csv and
DIR/summary.json. A run that fails is listed with its error and does not
stop the others; the exit code is then 1. --workers or --scheduler with a
single run also takes this path.

The flights of one plan (a plan split into mission-1.plan, mission-2.plan,
... to fit the battery; fly attaches the same plan.json to each run):
  calibrate run-1.mcap run-2.mcap [--out DIR]
pools them into ONE camera (one camera.yaml and report in DIR, default
<first-run>-joint-calibration beside it): each run is paired on its own
camera clock, then one solve and one uncertainty on all the points. Runs of
different plans stay a batch. --joint pools runs that carry no common plan
(refused when their image sizes differ or their plans put the camera over
1 m apart); --separate calibrates each run alone (the batch) even when they
are flights of one plan.
"""

from __future__ import annotations

import argparse
from pathlib import Path

FIX_CHOICES = ("no_fix", "2d", "unknown", "3d", "dgps", "rtk_float", "rtk_fixed")
MODEL_CHOICES = ("auto", "default", "none", "k1", "k1k2", "k1k2p1p2", "full")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "calibrate",
        help="calibrate the camera from a run file (MCAP)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("run", type=Path, nargs="+", help="the run file (.mcap), complete or cut off; several for a batch")
    parser.add_argument("--out", type=Path, default=None,
                        help="output directory (default: <run>-calibration beside the run); for a batch the folder "
                             "of the summary and of one folder per run (required)")
    parser.add_argument("--min-fix", choices=FIX_CHOICES, default="rtk_fixed", help="drop hover windows with a worse GNSS fix (default rtk_fixed)")
    parser.add_argument("--model", choices=MODEL_CHOICES, default="auto",
                        help="distortion model; auto suits it to the number and spread of the points (default)")
    parser.add_argument("--loss", choices=("linear", "huber", "cauchy"), default="huber", help="robust loss of the fit (default huber)")
    parser.add_argument("--loss-scale-px", type=float, default=2.0, help="robust loss scale, pixels (default 2)")
    parser.add_argument("--trials", type=int, default=500, help="Monte-Carlo trials (default 500; 0 skips)")
    parser.add_argument("--seed", type=int, default=0, help="Monte-Carlo seed (default 0)")
    parser.add_argument("--hover-source", choices=("auto", "events", "reached", "track"), default="auto",
                        help="where hover windows come from (default: events, else MISSION_ITEM_REACHED, else the GNSS track)")
    parser.add_argument("--settle-s", type=float, default=1.0, help="seconds ignored at the start of each hold (default 1)")
    parser.add_argument("--max-frames-per-window", type=int, default=24,
                        help="frames decoded per hover window (default 24; a hold shorter than 2 s decodes every frame)")
    parser.add_argument("--leg-source", choices=("auto", "events", "track", "none"), default="auto",
                        help="fly-through legs: leg events, else straight constant-speed stretches of the GNSS track (auto, the default); none: holds only")
    parser.add_argument("--max-readout-s", type=float, default=0.06, metavar="S",
                        help="longest rolling-shutter readout searched, seconds (default 0.06; 0 for a global shutter)")
    parser.add_argument("--annotate", action="store_true", help="also write a copy of the run with the calibration and detections for Foxglove")
    pooled = parser.add_argument_group("several runs of one camera")
    how = pooled.add_mutually_exclusive_group()
    how.add_argument("--joint", action="store_true",
                     help="one camera from the points of all the runs (the default for the flights of one plan)")
    how.add_argument("--separate", action="store_true",
                     help="calibrate each run alone (a batch) even when the runs are flights of one plan")
    batch = parser.add_argument_group("many runs (Dask)")
    batch.add_argument("--workers", type=int, default=None, metavar="N",
                       help="local worker processes for a batch (default: one per core; 0 runs them one by one in this process)")
    batch.add_argument("--scheduler", default=None, metavar="tcp://HOST:8786",
                       help="run the batch on this Dask scheduler's workers (run files and --out must be on a folder they share)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    _check_flags(args)
    if getattr(args, "joint", False):
        return run_joint(args)
    if len(args.run) > 1 and not getattr(args, "separate", False):
        pooled, notes = _flights_of_one_plan(args.run)
        for line in notes:
            print(line)
        if pooled:
            return run_joint(args)
    if len(args.run) > 1 or args.workers is not None or args.scheduler is not None:
        return run_batch(args)
    return run_single(args, args.run[0])


def _flights_of_one_plan(runs: list[Path]) -> tuple[bool, list[str]]:
    """(whether the runs are the flights of one plan: the same plan.json attached, the lines saying so).

    Runs of several plans stay a batch; a plan flown in several of them is named, with how to pool it.
    """
    from dronecal_field.errors import DronecalError
    from dronecal_field.pipeline.joint import flights_of_one_plan, plan_of_run

    try:
        plans = [plan_of_run(p) for p in runs]
    except DronecalError:
        return False, []  # a run that does not open: the batch lists it with its error
    if flights_of_one_plan(plans):
        return True, [f"runs {_names(plans)} are {_which(plans)} of one plan: calibrated together; --separate to calibrate each alone"]
    groups: dict[str, list] = {}
    for p in plans:
        if p.plan_hash is not None:
            groups.setdefault(p.plan_hash, []).append(p)
    return False, [
        f"runs {_names(g)} are {_which(g)} of one plan, calibrated here each alone (a batch): "
        f"calibrate them together with dronecal-field calibrate {' '.join(str(p.path) for p in g)}"
        for g in groups.values() if len(g) > 1
    ]


def _names(plans) -> str:
    return ", ".join(p.path.name for p in plans)


def _which(plans) -> str:
    numbers = [p.flight for p in plans]
    if None in numbers:
        return "flights"
    return "flights " + ", ".join(str(n) for n in numbers[:-1]) + f" and {numbers[-1]}"


def _check_flags(args: argparse.Namespace) -> None:
    """The flags the pipeline's options do not bound, checked before any run is read."""
    from dronecal_field.cli import check_address, check_number, check_out_dir, check_seed
    from dronecal_field.errors import InputError

    check_seed("--seed", args.seed)
    check_number("--settle-s", args.settle_s, 0, 60, hint="give the seconds left out at the start of each hold, e.g. 1")
    check_number("--trials", args.trials, 0, 100_000, hint="give the Monte-Carlo trials, e.g. 500 (the paper's k), or 0 to skip it")
    if args.workers is not None and args.workers < 0:
        raise InputError(f"--workers {args.workers} is negative: give a number of worker processes (0 runs them in this process)")
    if args.scheduler is not None:
        check_address("--scheduler", args.scheduler, ("tcp", "tls", "inproc", "ucx"))
    if args.out is not None:
        check_out_dir("--out", args.out)
    if getattr(args, "joint", False) and len(args.run) < 2:
        raise InputError("--joint needs two or more run files: pass the runs of every flight of the plan")


def _options(args: argparse.Namespace, out: Path | None):
    from dataclasses import replace

    from dronecal_field.pipeline.points import PointOptions
    from dronecal_field.pipeline.run import CalibrateOptions
    from dronecal_field.pipeline.sampling import SamplingOptions

    return CalibrateOptions(
        out_dir=out,
        min_fix=args.min_fix,
        model=args.model,
        loss=args.loss,
        loss_scale_px=args.loss_scale_px,
        trials=args.trials,
        seed=args.seed,
        annotate=args.annotate,
        hover_source=args.hover_source,
        leg_source=args.leg_source,
        max_readout_s=args.max_readout_s,
        points=replace(PointOptions(), settle_s=args.settle_s, min_fix=args.min_fix),
        sampling=replace(SamplingOptions(), max_frames_per_window=args.max_frames_per_window),
    )


def run_single(args: argparse.Namespace, run_path: Path, live=None) -> int:
    """One run, in this process: the report's summary on stdout.

    ``live``: pipeline.framecache.FrameResults of fly's live pass over this run (``fly --calibrate``), or None.
    """
    from dronecal_field.cli import announce_first_compile
    from dronecal_field.pipeline.run import calibrate_runs

    out = args.out if args.out is not None else run_path.with_name(run_path.stem + "-calibration")
    announce_first_compile()
    site = calibrate_runs([run_path], _options(args, out), live=live)
    if site.several:
        return _print_site(site, run_path.name, out)
    print("\n".join(_summary_lines(site.cameras[None], run_path.name, out)))
    return 0


def _print_site(site, title: str, out: Path) -> int:
    """What calibrate prints about a site: each camera's summary, then every pair; 1 when a camera failed."""
    import sys

    names = [n for n in (*site.cameras, *site.failed)]
    lines = [f"calibrated site {title}: {len(site.cameras)} of {len(names)} cameras ({', '.join(names)}) in one ENU frame"]
    for name, report in site.cameras.items():
        own = _summary_lines(report, f"camera {name}", out / name)
        # a hold of another camera's view is not a loss of this one: counted, not listed
        unseen = sum(1 for p in getattr(report, "hover_points", []) if not p.used and p.dropped.startswith("0 marker detections"))
        own = [line for line in own[:-1] if not ("dropped window" in line and ": 0 marker detections" in line)]
        if unseen:
            own.insert(1, f"  {unseen} holds outside its view (no marker detection)")
        lines += ["  " + line for line in own]
        if getattr(report, "runs", None):
            lines += [f"    {r.path.name}: {r.used} points used, time offset {r.offset.offset_s:+.3f} s" for r in report.runs]
    for pair in site.pairs:
        lines.append(
            f"  {pair.b} from {pair.a}: {pair.distance_m:.3f} m apart (\u00b1 {1000 * pair.translation_std_m:.1f} mm), turned "
            f"{pair.rotation_deg:.2f}\u00b0 (\u00b1 {pair.rotation_std_deg:.3f}\u00b0); "
            + (f"{pair.shared_ground_m2:.0f} m\u00b2 of ground 3-30 m seen by both" if pair.shares_ground else "no ground seen by both")
        )
    lines.append(f"report: {site.outputs.get('report_html', out)}")
    print("\n".join(lines))
    for name, error in site.failed.items():
        print(f"dronecal-field calibrate: camera {name}: {error}", file=sys.stderr)
    return 1 if site.failed else 0


def run_joint(args: argparse.Namespace) -> int:
    """The runs of one camera pooled into one calibration, in this process: the summary on stdout."""
    from dronecal_field.cli import announce_first_compile
    from dronecal_field.errors import InputError
    from dronecal_field.pipeline.run import calibrate_runs

    first = args.run[0]
    out = args.out if args.out is not None else first.with_name(first.stem + "-joint-calibration")
    if len(args.run) < 2:
        raise InputError("--joint needs two or more run files: pass the runs of every flight of the plan")
    announce_first_compile()
    site = calibrate_runs(args.run, _options(args, out))
    if site.several:
        return _print_site(site, " + ".join(p.name for p in args.run) + " jointly", out)
    report = site.cameras[None]
    lines = _summary_lines(report, " + ".join(p.name for p in args.run) + " jointly", out)
    per_run = [
        f"  {r.path.name}" + (f" (flight {r.flight})" if r.flight is not None else "") + f": {r.used} points used, "
        f"time offset {r.offset.offset_s:+.3f} s" + ("" if r.alone else " (too small alone: paired at its motion offset)")
        for r in report.runs
    ]
    print("\n".join(lines[:1] + per_run + lines[1:]))
    return 0


def _summary_lines(report, title: str, out: Path) -> list[str]:
    """What calibrate prints about a calibration (one run, or several pooled)."""
    from dronecal_field.pipeline.report import all_warnings, offset_text

    cam = report.camera
    i = cam.intrinsics
    mc = report.monte_carlo or report.linearised
    off = report.offset
    hover = getattr(report, "hover_points", report.points)
    on_legs = getattr(report, "leg_points", [])
    dropped = [p for p in hover if not p.used]
    at15 = getattr(getattr(report, "validity", None), "at_15m", None)  # pipeline.ground15: the lens extrapolated 15 m out
    at15_note = f" ({at15.line()})" if at15 is not None and at15.line() else ""
    legs_text = (f" and {sum(1 for p in on_legs if p.used)} fix-by-fix pairs on {len(report.legs)} legs (from {report.leg_source})"
                 if getattr(report, "legs", None) else "")
    lines = [
        f"calibrated {title}: {sum(1 for p in hover if p.used)} of {len(report.windows)} waypoints "
        f"(windows from {report.window_source}){legs_text}, model {report.result.model.name}" + _caution(report),
        f"  fx {i.fx:.2f}  fy {i.fy:.2f}  cx {i.cx:.2f}  cy {i.cy:.2f} px;  distortion "
        + " ".join(f"{v:.4g}" for v in cam.distortion.as_array()),
        "  camera at ENU " + " ".join(f"{v:.3f}" for v in cam.pose.position_world) + " m",
        f"  RMS reprojection {report.result.rms_px:.3f} px; {len(report.result.outliers)} outliers",
        f"  camera time offset {offset_text(off.offset_s, off.std_s)} ({off.method})" + (f", of {report.runs[0].path.name}" if getattr(report, "runs", None) else ""),
        f"  confidence ({mc.method}): RMS mean {mc.rms_mean:.3f} px; at 15 m: {mc.ground_error_15m_cm:.1f} cm{at15_note}, "
        f"{mc.speed_error_15m_kmh:.2f} km/h at 50 km/h",
    ]
    if report.frames.frames_from_live:
        lines.append(f"  detections: {report.frames.frames_from_live} of {report.frames.frames_decoded} frames from the live pass")
    for p in dropped[:5]:
        lines.append(f"  dropped window {p.window.index}" + (f" (seq {p.window.seq})" if p.window.seq is not None else "") + f": {p.dropped}")
    if len(dropped) > 5:
        lines.append(f"  ... {len(dropped) - 5} more dropped windows in report.json")
    validity = getattr(report, "validity", None)
    if validity is not None:
        frac = validity.visible_ground_fraction
        lines.append(
            f"  region of validity: {validity.image_fraction:.0%} of the image"
            + (f", {frac:.0%} of the visible ground 3-30 m" if frac is not None else "")
            + (f"; predicted ground error there {validity.inside_cm_rms:.1f} cm RMS (max {validity.inside_cm_max:.1f} cm)"
               if validity.inside_cm_rms is not None else "")
        )
    if getattr(report, "track", None) is not None:  # what the receiver's reported accuracy means (pipeline/gnss_quality.py)
        from dronecal_field.pipeline.gnss_quality import gnss_quality_of_report
        lines.append("  gnss: " + gnss_quality_of_report(report).headline)
    for w in all_warnings(report):
        lines.append(f"  warning: {w}")
    lines.append(f"report: {report.outputs.get('report_html', out)}")
    return lines


POOR_FIT = 3.0  # a fit this many times worse than the points' measured sigmas predict is named in the first line


def _caution(report) -> str:
    """What the first printed line must add: a set left out, a fit far worse than the noise predicts."""
    out = []
    agreement = getattr(report, "agreement", None)
    if agreement is not None and agreement.left_out:
        n = len(agreement.left_out)
        out.append(f"{n} leg{'s' if n > 1 else ''} left out (disagree with the holds, below)")
    flown = [n.split(": the calibration used")[0] for n in getattr(report, "notices", []) if ": the calibration used" in n]
    if flown:
        out.append("flown other than planned: " + "; ".join(flown))
    out += [n.split(": the points share")[0] + ": expect a larger error" for n in getattr(report, "notices", []) if n.startswith("RTK noise correlated")]
    scale = float(getattr(report, "sigma_scale", 1.0) or 1.0)
    if scale >= POOR_FIT:
        out.append(f"CAUTION: the fit is {scale:.0f}x worse than the measured noise predicts (every uncertainty scaled up by it)")
    return "; " + "; ".join(out) if out else ""


def run_batch(args: argparse.Namespace) -> int:
    """Several runs on Dask: one folder each, the summary table on stdout; 1 if any run failed."""
    import sys

    from dronecal_field.cluster import dask_client
    from dronecal_field.errors import InputError
    from dronecal_field.pipeline.batch import calibrate_many, plan_tasks, summary_table

    if args.out is None:
        raise InputError("several runs need --out DIR: the folder of summary.csv, summary.json and one folder per run")
    options = _options(args, None)
    plan_tasks(args.run, args.out, options)  # colliding run names fail here, before a cluster starts
    with dask_client(args.scheduler, args.workers) as client:
        report = calibrate_many(args.run, args.out, options, client=client, scheduler=args.scheduler, progress=sys.stderr.isatty())
    print(summary_table(report))
    n_bad = len(report.failed)
    # a several-camera run gives a row per camera: count cameras then, runs otherwise
    what = "cameras" if any(getattr(r, "camera", None) for r in report.rows) else "runs"
    print(f"{len(report.rows) - n_bad} of {len(report.rows)} {what} calibrated on {report.workers} worker(s) in {report.wall_s:.1f} s; "
          f"wrote {', '.join(Path(p).name for p in report.outputs.values())} and one folder per run to {args.out}")
    if n_bad:
        print(f"dronecal-field calibrate: {n_bad} of {len(report.rows)} {what} failed (see {report.outputs['summary_csv']})", file=sys.stderr)
        return 1
    return 0
