"""Issue 23: scout -> estimate -> main plan, on the simulators (the chain of dronecal_field/demo.py).

    .venv/bin/python benchmarks/bench_scout.py --camera wide [--main] [--az-error 15] [--height-error 0.2]

``plan --scout`` gets only the pole position, its height (off by --height-error m) and the azimuth (off by --az-error
deg); the sim vehicle flies the scout, the sim camera renders through the truth (benchmarks/bench_wholeview.CAMERAS),
``fly --start`` records scout.mcap; ``plan --from-run scout.mcap`` estimates the camera (calibrate's pipeline) and
plans the main flight. With --main the main plan is flown too (main.mcap) and ``calibrate scout.mcap main.mcap --joint``
pools both; the ground 3-30 m error of each calibration against the truth is printed (sim.compare).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_wholeview import CAMERAS, DEFAULT_SPEEDUP, MARKER, fly_facts, truth_camera  # noqa: E402
from dronecal_field.demo import SITE, cli_argv, run_step, start_simulators  # noqa: E402


def fly(plan_dir: Path, truth_path: Path, run_path: Path, logs: Path, speedup: float, fps: float, tag: str) -> None:
    """Fly one plan on fresh simulators; ``fps`` is frames per VEHICLE second (what plan was told).

    The sim camera runs on the host clock (frames on a grid of wall time, stamped with it), not the vehicle's: it
    serves ``fps x speedup`` frames per wall second so that a slowed vehicle (speedup < 1, for the 4K camera's render
    time) still gets ``fps`` frames per vehicle second, and the camera ``1 / (fps x speedup)`` wall seconds per frame.
    """
    plan = json.loads((plan_dir / "mission.plan").read_text())
    home = plan["mission"]["plannedHomePosition"]
    (logs / tag).mkdir(parents=True, exist_ok=True)
    flight_wall_s = json.loads((plan_dir / "plan.json").read_text())["flight"]["flight_time_s"] / speedup
    sims = start_simulators(truth_path, tuple(home), logs / tag, speedup, fps * speedup,
                            dict(MARKER, size_m=json.loads((plan_dir / "plan.json").read_text())["marker"]["size_m"]))
    try:
        sims.wait_ready(timeout_s=300.0)  # a 4K ray map on a loaded machine
        timeout_s = int(600 + 2 * flight_wall_s)  # boot, take-off and landing at the slowed clock, with room for a loaded machine
        run_step("fly", cli_argv("fly", "--connect", sims.vehicle_url, "--mission", plan_dir / "mission.plan", "--video", sims.video_url,
                                 "--out", run_path, "--start", "--timeout-s", timeout_s), logs / f"fly-{tag}.log", timeout_s=timeout_s + 300)
    finally:
        sims.stop()
    print(f"{tag}: recorded {recorded(logs / f'fly-{tag}.log', speedup, fps)}", flush=True)


def recorded(fly_log: Path, speedup: float, fps: float) -> str:
    """The recording's frames and frame rate (wall and vehicle clock) from fly's log, against what was asked."""
    f = fly_facts(fly_log, speedup)
    if f.get("flight_vehicle_s") is None:
        return f"(no summary line in {fly_log})"
    return (f"{f['frames']} frames ({f['dropped']} dropped), {f['gnss_fixes']} GNSS fixes in {f['record_wall_s']:.0f} s wall = "
            f"{f['flight_vehicle_s']:.0f} vehicle s; {f['camera_fps_wall_measured']:.2f} fps wall = {f['camera_fps_vehicle_measured']:.2f} "
            f"per vehicle s (asked {fps * speedup:g} / {fps:g}) at speed-up {speedup:g}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--camera", default="wide", choices=sorted(CAMERAS))
    ap.add_argument("--out", type=Path, default=Path("bench-out/scout"))
    ap.add_argument("--az-error", type=float, default=15.0)
    ap.add_argument("--height-error", type=float, default=0.2)
    ap.add_argument("--fps", type=float, default=10.0, help="camera frames per vehicle second (plan's --fps; the sim camera serves fps x speedup per wall s)")
    ap.add_argument("--main", action="store_true")
    ap.add_argument("--speedup", type=float, default=None, help="sim vehicle speed-up (default bench_wholeview's: 4K 1x)")
    ap.add_argument("--min-agl", type=float, default=None, help="--min-agl for both plans (the Table 1 camera's 2 m pole: 0.5)")
    args = ap.parse_args()
    from dronecal_field.camerafile import read_camera, write_camera
    from dronecal_field.demo import in_enu_frame_of
    from dronecal_field.plan.fromrun import axis_angles_deg
    from dronecal_field.sim.compare import compare_cameras

    c = CAMERAS[args.camera]
    out = args.out / args.camera
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    truth = truth_camera(args.camera)
    truth_path = out / "truth.yaml"
    write_camera(truth_path, truth, comment="bench_scout truth")
    speedup = args.speedup or DEFAULT_SPEEDUP[args.camera]
    print(f"{args.camera}: speed-up {speedup:g}, camera {args.fps * speedup:g} fps wall = {args.fps:g} per vehicle second", flush=True)
    t0 = time.monotonic()
    scout_dir = out / "scout-plan"
    agl = [] if args.min_agl is None else ["--min-agl", args.min_agl]
    if not (out / "scout.mcap").exists():  # never re-plan what was flown
        run_step("plan", cli_argv("plan", "--scout", "--out", scout_dir, f"--lat={SITE['lat']}", f"--lon={SITE['lon']}", "--ground-alt", SITE["ground_h"],
                                  "--mount-height", c["mount_height"] + args.height_error, "--azimuth", SITE["azimuth"] + args.az_error,
                                  "--marker-offset", ",".join(str(v) for v in MARKER["offset_frd_m"]), *agl), logs / "plan-scout.log", timeout_s=120)
    sp = json.loads((scout_dir / "plan.json").read_text())
    print(f"{args.camera}: scout planned {sp['flight']['flight_time_s'] / 60:.2f} min, {sp['points']} waypoints", flush=True)
    scout_run = out / "scout.mcap"
    if not scout_run.exists():
        fly(scout_dir, truth_path, scout_run, logs, speedup, args.fps, "scout")
    print(f"scout done at {time.monotonic() - t0:.0f} s wall", flush=True)
    main_dir = out / "main-plan"
    if not ((main_dir / "plan.json").exists() and (out / "main.mcap").exists()):  # never re-plan what was flown
        run_step("plan", cli_argv("plan", "--from-run", scout_run, "--out", main_dir, "--marker-offset", ",".join(str(v) for v in MARKER["offset_frd_m"]),
                                  "--fps", args.fps, "--hover", "3", "--trials", "50", "--max-flight-time", "12", *agl), logs / "plan-main.log", timeout_s=900)
    mp = json.loads((main_dir / "plan.json").read_text())
    e = mp["from_run"]["estimate"]
    az_t, tilt_t = axis_angles_deg(truth.pose.R_cam_from_world)
    print(f"estimate: f {e['focal_px']:.1f} (truth {c['focal_px']:g}), pp ({e['cx_px']:.1f}, {e['cy_px']:.1f}) (truth {truth.intrinsics.cx:g}, "
          f"{truth.intrinsics.cy:g}), azimuth {e['azimuth_deg']:.2f} (truth {az_t:.2f}), tilt {e['tilt_deg']:.2f} (truth {tilt_t:.2f}), "
          f"k1 {e['distortion_k1_k2_p1_p2_k3'][0]:.3f} (truth {c.get('k1', 0):g}); sigma {e['sigma']}; band {e['tolerances']}", flush=True)
    print(f"main plan: {mp['strategy']['name']}, {mp['flight']['flight_time_s'] / 60:.1f} min, coverage {mp['coverage']['pct']} %, "
          f"band {mp['guess_band']['holds_in_view_of_all']}/{mp['guess_band']['holds']} in view of all corners", flush=True)
    from dronecal_field.core.camera import Camera  # noqa: F401
    from dronecal_field.plan.site import resolve_options  # noqa: F401
    if args.main:
        main_run = out / "main.mcap"
        if not main_run.exists():
            fly(main_dir, truth_path, main_run, logs, speedup, args.fps, "main")
        print(f"main done at {time.monotonic() - t0:.0f} s wall", flush=True)
        for tag, runs in (("main", [main_run]), ("pooled", [scout_run, main_run])):
            cal = out / f"calibration-{tag}"
            extra = ["--joint"] if len(runs) > 1 else []
            # settle is counted on the run's (wall) clock: 1 vehicle second
            run_step("calibrate", cli_argv("calibrate", *runs, *extra, "--out", cal, "--trials", "0", "--settle-s", 1.0 / speedup),
                     logs / f"calibrate-{tag}.log", timeout_s=1800)
            est = in_enu_frame_of(read_camera(cal / "camera.yaml"), truth.enu_origin)
            g = compare_cameras(truth, est, ground_step_m=0.5).ground
            print(f"{tag}: ground 3-30 m {g}", flush=True)
    print(f"wall {time.monotonic() - t0:.0f} s")


if __name__ == "__main__":
    main()
