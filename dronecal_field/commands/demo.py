"""``dronecal-field demo``: the whole chain on the built-in simulators (plan -> fly -> calibrate).

Starts the SITL-style vehicle and the simulated camera on loopback sockets,
plans a mission for the simulated camera, flies it with ``fly --start``,
calibrates the recorded run, and prints the calibrated camera next to the
truth, then one line saying whether the demo met its targets (agreeing with
the steps' own logs, whose complaints it prints) and where camera.yaml is.
A few minutes (measured in the README). A second demo into the same folder
records run-2.mcap: a flight is never overwritten. Ctrl-C, SIGTERM or SIGHUP
stop every step it started (fly finalises its run).
"""

from __future__ import annotations

import argparse
from pathlib import Path


# Faster than this the simulators fall behind the wall clock on 2 cores and the holds are too short to see.
MAX_SPEEDUP = 10.0


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser("demo", help="plan -> fly -> calibrate on the built-in simulators", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=Path("demo-output"), help="output folder (default demo-output)")
    p.add_argument("--speedup", type=float, default=3.0, help=f"simulated vehicle speed-up, above 0 and at most {MAX_SPEEDUP:g} (default 3)")
    p.add_argument("--trials", type=int, default=500, help="Monte-Carlo trials in calibrate (default 500; 0 skips)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dronecal_field.cli import check_number, check_out_dir
    from dronecal_field.demo import SITE, TRUTH, run_demo
    from dronecal_field.errors import InputError

    # Checked before the simulators start: a typo costs seconds, not minutes.
    check_number("--speedup", args.speedup, 0, MAX_SPEEDUP, low_open=True, hint="give a vehicle speed-up such as 3")
    if args.trials == 1 or not 0 <= args.trials <= 100_000:
        raise InputError(f"--trials {args.trials}: give 0 to skip the Monte-Carlo, or 2..100000 (500 is the default)")
    check_out_dir("--out", args.out)
    from dronecal_field.cli import announce_first_compile

    announce_first_compile(now=True)  # plan and calibrate compile in their own processes, into the shared cache

    print(f"dronecal-field demo: a {TRUTH['width']}x{TRUTH['height']} camera on a {SITE['mount_height']:g} m pole "
          f"at {SITE['lat']}, {SITE['lon']} looking {SITE['azimuth']:g} deg, tilted {SITE['tilt']:g} deg down")
    result = run_demo(args.out, speedup=args.speedup, trials=args.trials, echo=lambda s: print(s, flush=True))
    print()
    print(f"{'':28}{'calibrated':>14}{'truth':>14}")
    from dronecal_field.camerafile import read_camera
    from dronecal_field.demo import in_enu_frame_of

    truth = read_camera(result.out_dir / "truth.yaml")
    est = in_enu_frame_of(read_camera(result.camera_path), truth.enu_origin)
    rows = [
        ("fx (px)", est.intrinsics.fx, truth.intrinsics.fx),
        ("fy (px)", est.intrinsics.fy, truth.intrinsics.fy),
        ("cx (px)", est.intrinsics.cx, truth.intrinsics.cx),
        ("cy (px)", est.intrinsics.cy, truth.intrinsics.cy),
        ("k1", est.distortion.k1, truth.distortion.k1),
        ("k2", est.distortion.k2, truth.distortion.k2),
        ("p1", est.distortion.p1, truth.distortion.p1),
        ("p2", est.distortion.p2, truth.distortion.p2),
    ]
    for i, axis in enumerate("ENU"):
        rows.append((f"camera {axis} (m)", est.pose.position_world[i], truth.pose.position_world[i]))
    for name, a, b in rows:
        print(f"{name:28}{a:14.5g}{b:14.5g}")
    print()
    print(f"focal error {result.focal_error_pct:.2f} %, principal point error {result.principal_point_error_px:.1f} px "
          f"(1-sigma from the residuals {result.principal_point_sigma_px:.1f} px), camera position error {result.position_error_cm:.1f} cm")
    print(f"projection error against the truth: {result.sampled_projection_error_px:.2f} px RMS over the sampled volume, "
          f"{result.projection_error_px:.2f} px over the whole image at 4-12 m; reprojection RMS {result.rms_px:.2f} px")
    print(f"ground 3-30 m from the pole (where users measure): {result.ground_error_px:.2f} px RMS, max {result.ground_error_max_px:.1f} px against the truth")
    print(f"report: {result.report_path}   ({result.elapsed_s:.0f} s)")
    targets = "(focal < 1 %, camera < 5 cm, ground 3-30 m < 1 px RMS)"
    if result.log_problems:
        for problem in result.log_problems:
            print(f"  {problem}")
    if not result.met_targets:
        print(f"demo MISSED its targets {targets}; camera: {result.camera_path}")
    elif result.log_problems:
        print(f"demo met its accuracy targets {targets}, but its logs ask for more ({len(result.log_problems)} above, "
              f"{result.out_dir / 'logs'}); camera: {result.camera_path}")
    else:
        print(f"demo met its targets {targets}; its flight and calibration logs agree; camera: {result.camera_path}")
    return 0
