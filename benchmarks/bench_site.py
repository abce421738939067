"""Several cameras in one run (issue 24): each camera's accuracy, the relative pose against its uncertainty, the wall time.

Runs from the independent writer (tests/contract_writer.write_site_run), two cameras each, truth known:

* ``same``: two cameras on one pole 5 m up, 44 degrees apart (a 520 px and a 600 px focal, 640x480);
* ``apart``: two poles 8 m apart (5 m and 6 m up), looking at the same ground from either side.

Each camera has its own clock offset to the GNSS stream (+0.12 s, -0.08 s). The flight holds at the
union of a 3x3x2 grid in front of each camera (2.5 s holds, 8 fps, RTK noise 8 mm / 12 mm). Printed per
run: each camera's ground 3-30 m RMS px against its truth (sim.compare, as bench_calibrate measures it),
focal %, position cm; the relative pose's error (mm, deg) against its reported 1-sigma; calibrate's wall
and CPU time against the flight time (the wall time means little on a loaded machine). By hand (several minutes):

    .venv/bin/python benchmarks/bench_site.py [--seeds 3] [--trials 0] [--kinds same,apart]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from contract_writer import (  # noqa: E402
    ORIGIN,
    MarkerLook,
    RunSpec,
    SiteCamera,
    facing_point,
    make_flight,
    pole_camera,
    site_waypoints,
    write_site_run,
)


def cameras(kind: str):
    if kind == "same":
        a = pole_camera(azimuth_deg=-22, position_enu=(0, 0, 5.0), tilt_deg=18)
        b = pole_camera(azimuth_deg=22, position_enu=(0, 0, 5.0), tilt_deg=14, f_px=600, principal_offset_px=(-5, 3))
    else:
        a = pole_camera(azimuth_deg=15, position_enu=(-4, 0, 5.0), tilt_deg=16)
        b = pole_camera(azimuth_deg=-15, position_enu=(4, 0, 6.0), tilt_deg=14, f_px=600, principal_offset_px=(-5, 3))
    return a, b


def one(kind: str, seed: int, trials: int, folder: Path) -> dict:
    from dronecal_field.pipeline.run import CalibrateOptions, calibrate_runs
    from dronecal_field.pipeline.site import relative_pose_error
    from dronecal_field.sim.compare import compare_cameras

    a, b = cameras(kind)
    wps = site_waypoints([a, b], lateral_m=(-3.0, 0.0, 3.0), ahead_m=(6.0, 9.0, 12.0), up_m=(1.5, 4.0))
    flight = make_flight(facing_point([a, b]), wps, hold_s=2.5, move_s=1.5, seed=seed)
    truth = {"a": a, "b": b}
    path = folder / f"{kind}-{seed}.mcap"
    write_site_run(path, [SiteCamera("a", a, latency_s=0.12, declared_latency="unknown"), SiteCamera("b", b, latency_s=-0.08, phase_s=0.04)],
                   flight, MarkerLook(), RunSpec(fps=8.0, seed=seed + 3, site_origin=ORIGIN))
    tick, cpu = time.perf_counter(), time.process_time()
    site = calibrate_runs([path], CalibrateOptions(trials=trials, seed=seed, out_dir=folder / f"{kind}-{seed}"))
    wall, cpu = time.perf_counter() - tick, time.process_time() - cpu
    row = {"kind": kind, "seed": seed, "wall_s": wall, "cpu_s": cpu, "flight_s": (flight.t_ns[-1] - flight.t_ns[0]) / 1e9, "holds": len(wps)}
    for name, report in site.cameras.items():
        c = compare_cameras(truth[name], report.camera)
        row[name] = (c.ground.rms_px, c.focal_error_pct, c.position_error_cm, len(report.used_points), report.offset.offset_s)
    (pair,) = site.pairs
    dt, dr = relative_pose_error(pair, a, b)
    row["pair"] = (1000 * dt, 1000 * pair.translation_std_m, dr, pair.rotation_std_deg, pair.shared_ground_m2)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--trials", type=int, default=0)
    ap.add_argument("--kinds", default="same,apart")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for kind in args.kinds.split(","):
            for seed in range(args.seeds):
                row = one(kind, seed, args.trials, Path(tmp))
                rows.append(row)
                print(f"{kind} seed {seed}: " + "; ".join(
                    f"{n}: ground 3-30 m {row[n][0]:.2f} px, focal {row[n][1]:.2f} %, position {row[n][2]:.1f} cm, "
                    f"{row[n][3]} points, offset {row[n][4]:+.3f} s" for n in ("a", "b"))
                    + f"; relative {row['pair'][0]:.1f} mm (1-sigma {row['pair'][1]:.1f}), {row['pair'][2]:.3f} deg "
                      f"(1-sigma {row['pair'][3]:.3f}), shared ground {row['pair'][4]:.0f} m2; calibrate {row['wall_s']:.0f} s wall, "
                      f"{row['cpu_s']:.0f} s CPU for a {row['flight_s']:.0f} s flight ({row['cpu_s'] / row['flight_s']:.2f}x in CPU)", flush=True)
    print("\n| run | a ground 3-30 m px | b ground 3-30 m px | relative mm (1-sigma) | relative deg (1-sigma) | calibrate wall, CPU / flight |")
    print("| --- | --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['kind']} {r['seed']} | {r['a'][0]:.2f} | {r['b'][0]:.2f} | {r['pair'][0]:.1f} ({r['pair'][1]:.1f}) | "
              f"{r['pair'][2]:.3f} ({r['pair'][3]:.3f}) | {r['wall_s']:.0f} s, {r['cpu_s']:.0f} s / {r['flight_s']:.0f} s |")
    z_t = np.array([r["pair"][0] / r["pair"][1] for r in rows])
    z_r = np.array([r["pair"][2] / r["pair"][3] for r in rows])
    print(f"error / 1-sigma: translation max {z_t.max():.2f} (mean {z_t.mean():.2f}), rotation max {z_r.max():.2f} (mean {z_r.mean():.2f})")


if __name__ == "__main__":
    main()
