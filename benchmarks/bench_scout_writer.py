"""Issue 23 on runs from the independent writer (tests/contract_writer.py): scout -> estimate -> main plan -> calibrate.

    .venv/bin/python benchmarks/bench_scout_writer.py --camera table1 [--camera 4k ...] [--out DIR]

The chain of bench_scout.py without the simulators: ``plan --scout``'s library call gets only the pole (height
--height-error m off, azimuth --az-error deg off); the writer flies the scout through the truth camera (legs at the
scout's speed, holds where it holds) and writes a contract run; ``plan --from-run``'s library calls estimate the camera
and plan the main flight; the writer flies its waypoints (legs at the plan's leg speed); ``calibrate`` (the CLI)
calibrates the main run alone and the scout pooled with it (``--joint``). Printed: the scout's flight time, the
estimate against the truth, the main plan (time, ROI coverage), and the ground 3-30 m error of each calibration.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_wholeview import CAMERAS  # noqa: E402

OFFSET = (0.10, 0.0, 0.05)
AZIMUTH = 30.0


def _truth(name: str):
    from contract_writer import pole_camera

    c = CAMERAS[name]
    return pole_camera(width=c["width"], height=c["height"], f_px=c["focal_px"], position_enu=(0.0, 0.0, c["mount_height"]),
                       azimuth_deg=AZIMUTH, tilt_deg=c["tilt"], principal_offset_px=(0.0, 0.0),
                       distortion=tuple(c.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")))


def _site_to_origin_enu(site, pts_site: np.ndarray, origin) -> np.ndarray:
    from dronecal_field.geodesy import enu_to_geodetic, geodetic_to_enu

    llh = enu_to_geodetic(np.asarray(pts_site) @ site.R_enu_from_site.T, site.origin)
    return geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2], origin)


def _fly(truth, site, route, speed: float, path: Path, seed: int, latency_s: float = 0.0) -> None:
    from contract_writer import ORIGIN, MarkerLook, RunSpec, make_leg_flight, write_run

    grid = np.array([k == "grid" for k in route.kind])
    wps = _site_to_origin_enu(site, route.points[grid], ORIGIN)
    flight = make_leg_flight(truth, wps, hold_s=route.hold_s[grid], speed_mps=speed, offset_frd_m=OFFSET, seed=seed)
    spec = RunSpec(site_origin=ORIGIN, fps=10.0, gnss_hz=10.0, seed=seed + 2)
    if latency_s:
        spec = replace(spec, latency_s=latency_s, declared_latency="unknown")
    write_run(path, truth, flight, MarkerLook(size_m=0.4), spec)


def _ground(truth, cal_dir: Path):
    from dronecal_field.camerafile import read_camera
    from dronecal_field.demo import in_enu_frame_of
    from dronecal_field.sim.compare import compare_cameras

    est = in_enu_frame_of(read_camera(cal_dir / "camera.yaml"), truth.enu_origin)
    cmp = compare_cameras(truth, est, ground_step_m=0.5)
    i, t = est.intrinsics, truth.intrinsics
    return (f"{cmp.ground}; principal point {cmp.principal_point_error_px:.1f} px off, fx {100 * (i.fx / t.fx - 1):+.3f} %, "
            f"fy {100 * (i.fy / t.fy - 1):+.3f} %, position {100 * np.linalg.norm(est.pose.position_world - truth.pose.position_world):.2f} cm")


def run_one(name: str, out: Path, az_error: float, height_error: float, latency_s: float = 0.0) -> None:
    from contract_writer import ORIGIN

    from dronecal_field.plan.fromrun import axis_angles_deg, estimate_from_run, format_estimate, request_from_estimate
    from dronecal_field.plan.route import FlightModel
    from dronecal_field.plan.scout import ScoutSpec, make_scout
    from dronecal_field.plan.site import CameraSite, resolve_options
    from dronecal_field.plan.stage import make_plan
    from dronecal_field.sampling.lattice import Limits

    c = CAMERAS[name]
    out.mkdir(parents=True, exist_ok=True)
    truth = _truth(name)
    min_agl = 0.5 if c["mount_height"] < 3.0 else 1.0
    site = CameraSite(lat_deg=ORIGIN.lat_deg, lon_deg=ORIGIN.lon_deg, ground_h_m=ORIGIN.h_m, mount_height_m=c["mount_height"] + height_error,
                      azimuth_deg=AZIMUTH + az_error, tilt_deg=0.0, geoid_separation_m=0.0)
    limits = Limits(min_agl_m=min_agl, keep_out_m=2.0, marker_offset_frd_m=OFFSET, quiet_zone_frac=1 / 6, max_search_height_m=site.mount_height_m + 3.0)
    t0 = time.monotonic()
    scout = make_scout(site, ScoutSpec(), limits, FlightModel())
    scout_run = out / "scout.mcap"
    if not scout_run.exists():
        _fly(truth, site, scout.route, ScoutSpec().speed_m_s, scout_run, seed=11, latency_s=latency_s)
    print(f"{name}: scout {scout.route.flight_time_s / 60:.2f} min, {len(scout.rows)} rows", flush=True)
    est = estimate_from_run(scout_run)
    az_t, tilt_t = axis_angles_deg(truth.pose.R_cam_from_world)
    print(format_estimate(est), flush=True)
    print(f"  truth: f {c['focal_px']:g}, principal point ({truth.intrinsics.cx:g}, {truth.intrinsics.cy:g}), azimuth {az_t:.2f}, "
          f"tilt {tilt_t:.2f}, k1 {c.get('k1', 0.0):g}", flush=True)
    opts = resolve_options(dict(marker_size=0.4, marker_offset=",".join(map(str, OFFSET)), min_agl=min_agl, hover=3, trials=20,
                                fps=10, max_flight_time=12, lat=ORIGIN.lat_deg, lon=ORIGIN.lon_deg, ground_alt=ORIGIN.h_m,
                                mount_height=2.0, azimuth=0.0, tilt=20.0, image_size=f"{c['width']}x{c['height']}", focal_px=1000.0))
    req = request_from_estimate(est, opts)
    result = make_plan(req)
    s = result.summary
    main_s = s["flight"]["flight_time_s"]
    print(f"  main plan: {s['strategy'].get('name')}, {main_s / 60:.1f} min, ROI coverage {s['coverage']['pct']} %, "
          f"{s['guess_band']['holds_in_view_of_all']}/{s['guess_band']['holds']} in view of all corners; scout + main "
          f"{(scout.route.flight_time_s + main_s) / 60:.1f} min", flush=True)
    main_run = out / "main.mcap"
    if not main_run.exists():
        if len(result.routes) > 1:
            print(f"  main plan has {len(result.routes)} flights: only the first is written", flush=True)
        speed = result.chosen.leg_speed_m_s or 1.0
        _fly(truth, result.request.site, result.routes[0], speed, main_run, seed=21, latency_s=latency_s)
    for tag, runs in (("main", [main_run]), ("pooled", [scout_run, main_run])):
        cal = out / f"calibration-{tag}"
        argv = [sys.executable, "-m", "dronecal_field", "calibrate", *map(str, runs), "--out", str(cal), "--trials", "0"]
        if len(runs) > 1:
            argv.append("--joint")
        if not (cal / "camera.yaml").exists():
            p = subprocess.run(argv, capture_output=True, text=True, timeout=3600)
            (out / f"calibrate-{tag}.log").write_text(p.stdout + p.stderr)
            if p.returncode != 0:
                print(f"  {tag}: calibrate failed: {(p.stdout + p.stderr).strip().splitlines()[-1]}", flush=True)
                continue
        print(f"  {tag}: ground 3-30 m {_ground(truth, cal)}", flush=True)
    print(f"  wall {time.monotonic() - t0:.0f} s", flush=True)


def run_datasheet(name: str, out: Path, distortion: str, latency_s: float) -> None:
    """No scout: ``plan`` from what a datasheet and the installer say (the truth's focal, tilt, azimuth and pole, the
    --distortion level, the default guess band), flown by the writer and calibrated alone."""
    from contract_writer import ORIGIN

    from dronecal_field.plan.site import resolve_options
    from dronecal_field.plan.stage import make_plan, request_from_options

    c = CAMERAS[name]
    out.mkdir(parents=True, exist_ok=True)
    truth = _truth(name)
    t0 = time.monotonic()
    min_agl = 0.5 if c["mount_height"] < 3.0 else 1.0
    opts = resolve_options(dict(marker_size=0.4, marker_offset=",".join(map(str, OFFSET)), min_agl=min_agl, hover=3, trials=20,
                                fps=10, max_flight_time=12, lat=ORIGIN.lat_deg, lon=ORIGIN.lon_deg, ground_alt=ORIGIN.h_m,
                                mount_height=c["mount_height"], azimuth=AZIMUTH, tilt=c["tilt"], image_size=f"{c['width']}x{c['height']}",
                                focal_px=c["focal_px"], distortion=distortion))
    result = make_plan(request_from_options(opts))
    s = result.summary
    print(f"{name} from the datasheet (--distortion {distortion}, default band): {s['strategy'].get('name')}, "
          f"{s['flight']['flight_time_s'] / 60:.1f} min, ROI coverage {s['coverage']['pct']} %", flush=True)
    run = out / "main.mcap"
    if not run.exists():
        _fly(truth, result.request.site, result.routes[0], result.chosen.leg_speed_m_s or 1.0, run, seed=31, latency_s=latency_s)
    cal = out / "calibration"
    if not (cal / "camera.yaml").exists():
        p = subprocess.run([sys.executable, "-m", "dronecal_field", "calibrate", str(run), "--out", str(cal), "--trials", "0"],
                           capture_output=True, text=True, timeout=3600)
        (out / "calibrate.log").write_text(p.stdout + p.stderr)
        if p.returncode != 0:
            print(f"  calibrate failed: {(p.stdout + p.stderr).strip().splitlines()[-1]}", flush=True)
            return
    print(f"  ground 3-30 m {_ground(truth, cal)}; wall {time.monotonic() - t0:.0f} s", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--camera", action="append", choices=sorted(CAMERAS))
    ap.add_argument("--out", type=Path, default=Path("bench-out/scout-writer"))
    ap.add_argument("--az-error", type=float, default=20.0)
    ap.add_argument("--height-error", type=float, default=0.3)
    ap.add_argument("--latency", type=float, default=0.0, help="frames stamped this late, declared unknown (issue 20's 4K run: 0.35)")
    ap.add_argument("--datasheet", metavar="LEVEL", help="no scout: plan from the datasheet values with --distortion LEVEL")
    args = ap.parse_args()
    for name in args.camera or ["wide"]:
        if args.datasheet:
            run_datasheet(name, args.out / f"{name}-datasheet-{args.datasheet}", args.datasheet, args.latency)
        else:
            run_one(name, args.out / name, args.az_error, args.height_error, args.latency)


if __name__ == "__main__":
    main()
