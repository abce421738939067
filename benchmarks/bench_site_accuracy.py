"""Issue 24, the site's accuracy: calibrate a several-camera run and score every camera and pair against the simulators' truth.

Run by hand on a work folder of ``bench_site_fly.py`` (its ``site.mcap`` and ``truth-<name>.yaml``)::

    .venv/bin/python benchmarks/bench_site_fly.py --no-baseline --out /tmp/site-fly
    .venv/bin/python benchmarks/bench_site_accuracy.py /tmp/site-fly

It runs ``dronecal-field calibrate site.mcap`` (one process, as a user would; its wall and CPU time
against the flight's), then per camera: focal, principal point and position against the truth and
the ground 3-30 m reprojection error (the region users measure in, sim.compare); per pair of
cameras: the relative pose error (mm, degrees) against the 1-sigma site.json reports.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path


def calibrate(run: Path, out: Path, trials: int) -> tuple[int, float, float]:
    """Run calibrate in its own process; (exit code, wall s, CPU s)."""
    from dronecal_field.demo import cli_argv

    t0 = time.monotonic()
    argv = cli_argv("calibrate", run, "--out", out, "--trials", trials)
    pid = os.spawnv(os.P_NOWAIT, argv[0], argv)
    _pid, status, usage = os.wait4(pid, 0)
    return os.waitstatus_to_exitcode(status), time.monotonic() - t0, usage.ru_utime + usage.ru_stime


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("work", type=Path, help="bench_site_fly.py's work folder")
    p.add_argument("--run", default="site.mcap", help="the run file in it (default %(default)s)")
    p.add_argument("--trials", type=int, default=500)
    p.add_argument("--reuse", action="store_true", help="score the calibration folder already there instead of calibrating")
    p.add_argument("--flight-s", type=float, default=None, help="the flight's vehicle time, for the speed ratio (default: from the run)")
    args = p.parse_args()

    from dronecal_field.camerafile import read_camera
    from dronecal_field.demo import in_enu_frame_of
    from dronecal_field.pipeline.site import relative_pose_error, relative_pose
    from dronecal_field.runfile.reader import open_run
    from dronecal_field.sim.compare import compare_cameras

    run = args.work / args.run
    out = args.work / "calibration"
    if args.reuse and out.exists():
        rc, wall, cpu = 0, float("nan"), float("nan")  # scored again, not timed
    else:
        rc, wall, cpu = calibrate(run, out, args.trials)
    with open_run(run) as r:
        names = list(r.cameras)
        span = r.time_range_ns
    flight_s = args.flight_s if args.flight_s is not None else (span[1] - span[0]) / 1e9 if span else None
    print(f"calibrate exit {rc}: {wall:.0f} s wall, {cpu:.0f} s CPU for {len(names)} cameras"
          + (f"; run {flight_s:.0f} s (calibrate wall / recording {wall / flight_s:.2f}, CPU / recording {cpu / flight_s:.2f})" if flight_s else ""))
    truths, ests = {}, {}
    print(f"{'camera':10s} {'focal %':>8s} {'pp px':>6s} {'pos cm':>7s} {'rot deg':>7s} {'ground 3-30 m RMS / max px':>27s}  "
          "points, model, fit RMS px, time offset s, holds used/windows")
    for name in names:
        truth = read_camera(args.work / f"truth-{name}.yaml")
        path = out / name / "camera.yaml"
        if not path.exists():
            refused = {c.get("name"): c.get("error") for c in json.loads((out / "site.json").read_text()).get("cameras", [])} \
                if (out / "site.json").exists() else {}
            print(f"{name:10s} no camera written: {refused.get(name) or 'see calibrate on stderr'}")
            continue
        est = in_enu_frame_of(read_camera(path), truth.enu_origin)
        c = compare_cameras(truth, est, ground_step_m=0.5)
        truths[name], ests[name] = truth, est
        rep = json.loads((out / name / "report.json").read_text()) if (out / name / "report.json").exists() else {}
        cal, off, hw = rep.get("calibration", {}), rep.get("time_offset", {}), rep.get("hover_windows", {})
        print(f"{name:10s} {c.focal_error_pct:8.2f} {c.principal_point_error_px:6.1f} {c.position_error_cm:7.1f} {c.rotation_error_deg:7.3f} "
              f"{c.ground.rms_px:13.2f} / {c.ground.max_px:.1f}  {cal.get('n_points')}, {cal.get('model')}, "
              f"{cal.get('rms_px', float('nan')):.2f}, {off.get('offset_s', float('nan')):+.3f}, {hw.get('used')}/{hw.get('count')}")
    site = out / "site.json"
    if site.exists():
        pairs = json.loads(site.read_text()).get("pairs", [])
        print(f"\n{'pair':22s} {'shares ground':>13s} {'error mm (1 sigma)':>19s} {'error deg (1 sigma)':>20s}")
        for pair in pairs:
            a, b = pair["a"], pair["b"]
            if a not in ests or b not in ests:
                continue
            est = relative_pose(a, ests[a], None, b, ests[b], None, n=2)
            dt, dr = relative_pose_error(est, truths[a], truths[b])
            print(f"{a + ' / ' + b:22s} {str(pair['shares_ground']):>13s} {1000 * dt:9.1f} ({1000 * pair['translation_std_m']:.1f}) "
                  f"{dr:11.3f} ({pair['rotation_std_deg']:.3f})")
    else:
        print("no site.json written")
    return 0 if rc == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
