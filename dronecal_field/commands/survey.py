"""``dronecal-field survey``: the paper's camera-by-path study (section IV.B) on Dask.

Builds a seeded Latin Hypercube of cameras (focal 2-15 mm, width 700-4000 px,
height 3/4 of it, elevation 2-5 m, tilt 0-90 deg, distortion none or
medium), samples every strategy's 3D points each camera sees, runs the
engine's batched Monte-Carlo on each (camera, strategy) and stores one row
per pair in a parquet dataset directory (--out). A killed survey resumes
where it stopped when re-run with the same flags; no row is computed twice.

  dronecal-field survey --cameras 5000 --trials 500 --strategies paper --out results.parquet
  dronecal-field survey --scheduler tcp://10.0.0.5:8786 --out results.parquet   # same job, a cluster
  dronecal-field survey report results.parquet --report-dir survey-report

--strategies: paper (the six strategies of the paper's comparisons), all
(18), recommended (far-y1-z2), or names like far-y1-z2,near-y0.5-z3
(X range near 0-4 m / far 4-8 m / full 0-8 m, Y step in m, heights).
Assumptions the paper leaves open (pixel pitch, heights, "medium"
distortion) are flags here and explained in docs/survey.md.
"""

from __future__ import annotations

import argparse
import json
import sys


# A million cameras is two hundred times the paper's study; beyond it the design alone exhausts memory.
MAX_CAMERAS = 1_000_000


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "survey",
        help="the paper's camera-by-path study on Dask; 'survey report' for its findings and figures",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        add_help=False,
    )
    p.add_argument("-h", "--help", action=_ActionHelp, help="show this help (after report or export: that action's help) and exit")
    p.add_argument("action", nargs="?", choices=("run", "report", "export"), default="run",
                   help="run (default) the survey, report on results, or export results to one parquet file")
    p.add_argument("results", nargs="?", help="results directory or file (report, export)")
    g = p.add_argument_group("survey")
    g.add_argument("--cameras", type=int, default=5000, help="cameras in the Latin Hypercube (default 5000, as the paper)")
    g.add_argument("--trials", type=int, default=500, help="Monte-Carlo trials per (camera, strategy) (default 500)")
    g.add_argument("--strategies", default="paper", help="paper, all, recommended or comma-separated names (default paper)")
    g.add_argument("--out", default="results.parquet", help="results directory (parquet dataset; resumed if it exists)")
    g.add_argument("--seed", type=int, default=0, help="seed of the camera design and of the Monte-Carlo (default 0)")
    g.add_argument("--sigma-3d", default="0.01,0.01,0.015", help="GNSS/altimeter sigma X,Y,Z in m (default 0.01,0.01,0.015)")
    g.add_argument("--sigma-px", dest="sigma_2d", type=float, default=2.0, help="marker detection noise, pixels per axis (default 2, as plan's --sigma-px)")
    g.add_argument("--sigma-2d", dest="sigma_2d", type=float, help=argparse.SUPPRESS)  # the old name, for one release
    g.add_argument("--model", default="default", help="calibration model re-estimated per trial (default: k3 fixed)")
    g.add_argument("--pixel-pitch-um", type=float, default=7.5, help="sensor pixel size turning focal mm into px (default 7.5 um)")
    g.add_argument("--heights", default="paper", choices=("paper", "plan"),
                   help="paper: levels every 0.5 m from 0.5 m; plan: the levels `plan` would fly (default paper)")
    g.add_argument("--batch-size", type=int, default=10, help="(camera, strategy) pairs per task and per stored part (default 10)")
    g.add_argument("--scheduler", help="address of a running Dask scheduler (tcp://HOST:8786); default: a local cluster")
    g.add_argument("--workers", type=int, help="local worker processes (default: one per core; 0 = no Dask, this process)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    g.add_argument("--json", action="store_true", help="print the run report as one JSON object")
    r = p.add_argument_group("report")
    r.add_argument("--report-dir", help="where report writes figures and index.html (default: <results>-report)")
    r.add_argument("--fig10-trials", type=int, help="Monte-Carlo trials for Figure 10 (default: the survey's)")
    r.add_argument("--to", help="export: the single parquet file to write")
    p.set_defaults(func=run)


REPORT_HELP = """Read a survey's results (a results folder or an exported .parquet file),
print its findings and write the paper's figures 8-10 and index.html into
--report-dir (default: <results>-report)."""
EXPORT_HELP = """Write every row of a survey's results folder into one parquet file
(--to), with the survey's configuration in its metadata. An existing file
is never replaced."""


class _ActionHelp(argparse.Action):
    """-h: the help of the action given before it (`survey report --help`), else the survey's."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        action = getattr(namespace, "action", None)
        if action in ("report", "export"):
            parser = _action_parser(parser.prog, action)
        parser.print_help()
        parser.exit()


def _action_parser(prog: str, action: str) -> argparse.ArgumentParser:
    """A parser used only for the help text of `survey report` / `survey export`."""
    sub = argparse.ArgumentParser(prog=f"{prog} {action}", description=REPORT_HELP if action == "report" else EXPORT_HELP)
    sub.add_argument("results", help="the survey's results folder (its --out) or an exported .parquet file")
    if action == "report":
        sub.add_argument("--report-dir", metavar="DIR", help="where the figures and index.html go (default: <results>-report)")
        sub.add_argument("--fig10-trials", type=int, metavar="N", help="Monte-Carlo trials for Figure 10 (default: the survey's)")
        sub.add_argument("--json", action="store_true", help="print the findings as one JSON object")
    else:
        sub.add_argument("--to", required=True, metavar="FILE.parquet", help="the single parquet file to write (must not exist)")
    return sub


def run(args: argparse.Namespace) -> int:
    if args.action == "report":
        return _report(args)
    if args.action == "export":
        return _export(args)
    return _run(args)


def _run(args: argparse.Namespace) -> int:
    from dronecal_field.cluster import dask_client
    from dronecal_field.commands.uncertainty import parse_sigma_3d
    from dronecal_field.errors import InputError
    from dronecal_field.survey.catalogue import catalogue, sampler_from_name
    from dronecal_field.survey.design import DesignSpace
    from dronecal_field.survey.evaluate import MonteCarloSettings
    from dronecal_field.survey.runner import SurveyConfig, run_survey

    from dronecal_field.cli import check_address, check_number, check_out_dir, check_seed
    from dronecal_field.commands.uncertainty import MAX_TRIALS
    from dronecal_field.core.calibrate import resolve_model

    if args.results:
        raise InputError(f"unexpected argument {args.results!r}: the survey writes to --out; use `survey report {args.results}` to read results")
    # Every flag before the results folder is created: a refused survey leaves nothing behind.
    if not 1 <= args.cameras <= MAX_CAMERAS:
        raise InputError(f"--cameras {args.cameras} is outside 1..{MAX_CAMERAS}: the paper uses 5000")
    if not 2 <= args.trials <= MAX_TRIALS:
        raise InputError(f"--trials {args.trials} is outside 2..{MAX_TRIALS}: the paper uses 500")
    check_number("--sigma-px", args.sigma_2d, 0, 1000, hint="give a pixel standard deviation, e.g. 2")
    parse_sigma_3d(args.sigma_3d)
    check_number("--pixel-pitch-um", args.pixel_pitch_um, 0, 100, low_open=True, hint="give the sensor's pixel size in micrometres, e.g. 7.5")
    if args.batch_size < 1:
        raise InputError(f"--batch-size {args.batch_size} must be at least 1, e.g. 10")
    if args.workers is not None and args.workers < 0:
        raise InputError(f"--workers {args.workers} is negative: give a number of worker processes (0 runs in this process)")
    check_seed("--seed", args.seed)
    resolve_model(args.model, 1000)
    catalogue(args.strategies)
    if args.scheduler is not None:
        check_address("--scheduler", args.scheduler, ("tcp", "tls", "inproc", "ucx"))
    check_out_dir("--out", args.out)
    config = SurveyConfig(
        n_cameras=args.cameras,
        design_seed=args.seed,
        space=DesignSpace(pixel_pitch_um=args.pixel_pitch_um),
        sampler=sampler_from_name(args.heights),
        settings=MonteCarloSettings(trials=args.trials, sigma_3d=parse_sigma_3d(args.sigma_3d), sigma_2d=args.sigma_2d, model=args.model, seed=args.seed),
    )
    strategies = catalogue(args.strategies)
    from dronecal_field.cli import announce_first_compile

    announce_first_compile()  # the workers share the cache folder: one compile, said once
    with dask_client(args.scheduler, args.workers) as client:
        report = run_survey(config, strategies, args.out, client, batch_size=args.batch_size, progress=not args.no_progress)
    if args.json:
        json.dump(report.to_dict(), sys.stdout)
        print()
        return 0
    print(
        f"survey {report.out}: {report.total_rows} rows ({report.already_done} already stored, {report.computed} computed: "
        f"{report.degenerate} degenerate, {report.failed} failed) in {report.wall_s:.1f} s on {report.workers} worker(s), "
        f"{report.rows_per_s:.1f} rows/s"
    )
    return 0


def _results_arg(args: argparse.Namespace) -> str:
    from dronecal_field.errors import InputError

    if not args.results:
        raise InputError(f"survey {args.action} needs the results: dronecal-field survey {args.action} results.parquet")
    return args.results


def _report(args: argparse.Namespace) -> int:
    from pathlib import Path

    from dronecal_field.survey.report import write_report

    from dronecal_field.cli import check_out_dir
    from dronecal_field.errors import InputError

    results = _results_arg(args)
    if args.fig10_trials is not None and args.fig10_trials < 2:
        raise InputError(f"--fig10-trials {args.fig10_trials} is too few: give at least 2, or leave it out for the survey's trials")
    out_dir = args.report_dir or str(Path(results).with_suffix("")) + "-report"
    check_out_dir("--report-dir", out_dir)
    files = write_report(results, out_dir, fig10_trials=args.fig10_trials)
    if args.json:
        print(files.json.read_text())
        return 0
    print(files.text)
    print(f"report: {files.html} ({', '.join(p.name for p in files.figures.values())})")
    return 0


def _export(args: argparse.Namespace) -> int:
    from dronecal_field.errors import InputError
    from dronecal_field.survey.store import export_results

    results = _results_arg(args)
    if not args.to:
        raise InputError("survey export needs --to FILE.parquet")
    from dronecal_field.cli import check_out_file

    check_out_file("--to", args.to, keep_existing=True)
    dest = export_results(results, args.to)
    print(f"exported {results} -> {dest}")
    return 0
