"""``dronecal-field calibrate RUN.mcap``: calibrate the camera from a recorded flight.

Finds the hover windows, detects the marker in the frames around them,
aligns the camera and GNSS clocks, builds one robust 3D-2D point per
waypoint, calibrates, and estimates the confidence (Monte-Carlo with the
measured sigmas). Writes camera.yaml, camera_info.yaml, ground_homography.yaml,
detections.csv, report.json and report.html into --out.
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
    parser.add_argument("run", type=Path, help="the run file (.mcap), complete or cut off")
    parser.add_argument("--out", type=Path, default=None, help="output directory (default: <run>-calibration beside the run)")
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
    parser.add_argument("--max-frames-per-window", type=int, default=24, help="frames decoded per hover window (default 24)")
    parser.add_argument("--annotate", action="store_true", help="also write a copy of the run with the calibration and detections for Foxglove")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from dronecal_field.pipeline.points import PointOptions
    from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run
    from dronecal_field.pipeline.sampling import SamplingOptions

    out = args.out if args.out is not None else args.run.with_name(args.run.stem + "-calibration")
    options = CalibrateOptions(
        out_dir=out,
        min_fix=args.min_fix,
        model=args.model,
        loss=args.loss,
        loss_scale_px=args.loss_scale_px,
        trials=args.trials,
        seed=args.seed,
        annotate=args.annotate,
        hover_source=args.hover_source,
        points=replace(PointOptions(), settle_s=args.settle_s, min_fix=args.min_fix),
        sampling=replace(SamplingOptions(), max_frames_per_window=args.max_frames_per_window),
    )
    report = calibrate_run(args.run, options)
    cam = report.camera
    i = cam.intrinsics
    mc = report.monte_carlo or report.linearised
    off = report.offset
    dropped = [p for p in report.points if not p.used]
    lines = [
        f"calibrated {args.run.name}: {len(report.used_points)} of {len(report.windows)} waypoints "
        f"(windows from {report.window_source}), model {report.result.model.name}",
        f"  fx {i.fx:.2f}  fy {i.fy:.2f}  cx {i.cx:.2f}  cy {i.cy:.2f} px;  distortion "
        + " ".join(f"{v:.4g}" for v in cam.distortion.as_array()),
        "  camera at ENU " + " ".join(f"{v:.3f}" for v in cam.pose.position_world) + " m",
        f"  RMS reprojection {report.result.rms_px:.3f} px; {len(report.result.outliers)} outliers",
        f"  camera time offset {off.offset_s:+.3f} s"
        + (f" ± {off.std_s:.3f} s" if off.std_s is not None else "")
        + f" ({off.method})",
        f"  confidence ({mc.method}): RMS mean {mc.rms_mean:.3f} px; at 15 m: {mc.ground_error_15m_cm:.1f} cm, "
        f"{mc.speed_error_15m_kmh:.2f} km/h at 50 km/h",
    ]
    for p in dropped[:5]:
        lines.append(f"  dropped window {p.window.index}" + (f" (seq {p.window.seq})" if p.window.seq is not None else "") + f": {p.dropped}")
    if len(dropped) > 5:
        lines.append(f"  ... {len(dropped) - 5} more dropped windows in report.json")
    for w in report.warnings:
        lines.append(f"  warning: {w}")
    lines.append(f"report: {report.outputs.get('report_html', out)}")
    print("\n".join(lines))
    return 0
