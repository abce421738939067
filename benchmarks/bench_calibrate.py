"""Calibration (issue 5): accuracy against the simulator's truth, and speed on a 10-minute 1080p run.

    .venv/bin/python benchmarks/bench_calibrate.py                         # both parts
    .venv/bin/python benchmarks/bench_calibrate.py --only accuracy         # ~5 min
    .venv/bin/python benchmarks/bench_calibrate.py --only speed            # ~3 min build + the timed run
    .venv/bin/python benchmarks/bench_calibrate.py --only speed --minutes 3

(a) Accuracy. For a pinhole and a distorted 1920x1080 camera on a 4 m pole,
and 3 seeds each: a 24-waypoint flight (4 x 3 x 2 lattice 6-12 m out, holds
as long as ``plan`` makes them by default: 1 s to settle + 40 frames, so 5 s at
10 fps) with 2 cm hover drift (std per horizontal axis), RTK noise (8 mm
horizontal, 12 mm vertical, white, at 10 Hz as ``fly`` asks for; ``--gnss-hz
5`` for ArduPilot's default GPS_RATE_MS), a 0.25 s camera latency the file calls
``unknown``, and a 0.4 m ArUco marker 0.27 m from the antenna. The run is
written by the tests' INDEPENDENT contract writer (tests/contract_writer.py:
raw mcap + Foxglove protobuf classes) with the simulator's renderer (sensor
noise, exact geometry) for every frame, then calibrated with
``pipeline.run.calibrate_run``. Printed against the truth: focal error (worst
of fx, fy), principal point, camera position, and the projection error
against the true camera, RMS over the flown waypoints and over the sampled
volume (uniform random points in the box the waypoints span, inside the
image). Targets: < 1 %, < 5 px, < 5 cm, < 1 px.

(b) Speed. A 10-minute 1920x1080 30 fps run (18,270 frames, 60 waypoints,
6 s holds, 4 s moves, 10 Hz GNSS and attitude, hover events, zstd chunks like
``fly`` writes, on /tmp) is written with the recorder's RunWriter. To keep the
build to a few minutes, frames are rendered (simulator renderer) at 10 Hz
while the drone moves and 2 Hz while it holds, and each rendering's JPEG bytes
are reused by the 30 fps frames nearest it. Then the real ``dronecal-field
calibrate`` (default options: 500 Monte-Carlo trials) runs on it in a fresh
process: wall time, CPU (rusage), flight duration / processing time, frames
decoded against frames in the file. Target: >= 5x (10 minutes in < 2 min).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))  # the independent contract writer and its truth-known scenes

from contract_writer import ORIGIN, MarkerLook, RunSpec, _sim_render, grid_waypoints, make_flight, pole_camera, write_run  # noqa: E402
from dronecal_field.core.synthetic import visible  # noqa: E402
from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic, geodetic_to_enu  # noqa: E402

WIDTH, HEIGHT, FOCAL_PX = 1920, 1080, 1400.0
CAMERAS = {
    "pinhole": (0.0, 0.0, 0.0, 0.0, 0.0),
    "distorted": (-0.20, 0.05, -3e-4, -1e-4, 0.0),  # k1, k2, p1, p2, k3: a wide security camera
}
LOOK = MarkerLook(marker_id=7, size_m=0.4)
OFFSET_FRD_M = (0.25, 0.0, 0.10)
LATENCY_S = 0.25


def truth_camera(kind: str):
    return pole_camera(width=WIDTH, height=HEIGHT, f_px=FOCAL_PX, position_enu=(0.0, 0.0, 4.0), tilt_deg=15.0, distortion=CAMERAS[kind])


def to_truth_frame(points_enu: np.ndarray, origin: EnuOrigin) -> np.ndarray:
    """(N, 3) points from the report's ENU frame at ``origin`` into the truth's (ORIGIN)."""
    points_enu = np.atleast_2d(points_enu)
    if np.allclose(origin.as_list(), ORIGIN.as_list(), atol=1e-10):
        return points_enu
    llh = enu_to_geodetic(points_enu, origin)
    return geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2], ORIGIN)


def rms_between(truth, est, points: np.ndarray) -> float:
    """RMS pixel distance between the truth's and the estimate's projections of ``points`` (N, 3)."""
    return float(np.sqrt(np.mean(np.sum((truth.project(points) - est.project(points)) ** 2, axis=1))))


def errors_against_truth(report, truth, seed: int = 0) -> dict:
    """Focal %, principal point px, position cm, projection px (waypoints, sampled volume), from a CalibrationReport."""
    from dronecal_field.core.camera import CameraPose

    cam = report.camera
    centre = to_truth_frame(cam.pose.position_world, report.origin)[0]
    # The frames differ at most by the tilt between two ENU frames a few metres apart (< 1e-6 rad).
    est = cam.with_(pose=CameraPose.from_position(cam.pose.R_cam_from_world, centre))
    flown = to_truth_frame(np.array([p.marker_enu_m for p in report.used_points]), report.origin)
    lo, hi = flown.min(0), flown.max(0)
    rng = np.random.default_rng(seed)
    volume = lo + rng.uniform(size=(20000, 3)) * (hi - lo)
    volume = volume[visible(truth, volume, 10.0)]
    ti, ei = truth.intrinsics, est.intrinsics
    cov = report.result.camera.covariance  # the calibration's own (residual-scaled) covariance, fx fy cx cy ... first
    return {
        "focal_pct": 100.0 * max(abs(ei.fx / ti.fx - 1.0), abs(ei.fy / ti.fy - 1.0)),
        "pp_px": float(np.hypot(ei.cx - ti.cx, ei.cy - ti.cy)),
        "pp_sigma_px": float(np.hypot(np.sqrt(max(cov[2, 2], 0.0)), np.sqrt(max(cov[3, 3], 0.0)))),
        "position_cm": 100.0 * float(np.linalg.norm(centre - truth.pose.position_world)),
        "proj_waypoints_px": rms_between(truth, est, flown),
        "proj_volume_px": rms_between(truth, est, volume),
        "volume_points": len(volume),
        "rms_px": float(report.result.rms_px),
        "model": report.result.model.name,
        "used": len(report.used_points),
        "windows": len(report.windows),
        "offset_s": float(report.offset.offset_s),
    }


# --------------------------------------------------------------------------
# (a) accuracy


def accuracy(seeds: int, fps: float, gnss_hz: float, workdir: Path, rtk_tau_s: float = 0.0) -> list[dict]:
    from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run

    waypoints = grid_waypoints(east_m=(-3.5, -1.2, 1.2, 3.5), north_m=(6.0, 9.0, 12.0), up_m=(1.0, 4.0))
    hold_s = float(math.ceil(1.0 + 40.0 / fps))  # plan's default hover for this frame rate
    rows = []
    for kind in CAMERAS:
        truth = truth_camera(kind)
        for seed in range(seeds):
            flight = make_flight(truth, waypoints, hold_s=hold_s, move_s=2.0, drift_m=0.02, offset_frd_m=OFFSET_FRD_M, seed=seed)
            spec = RunSpec(fps=fps, gnss_hz=gnss_hz, latency_s=LATENCY_S, declared_latency="unknown",
                           gnss_sigma_m=(0.008, 0.008, 0.012), renderer="sim", site_origin=ORIGIN, seed=100 + seed,
                           gnss_noise_tau_s=rtk_tau_s)
            path = workdir / f"{kind}-{seed}.mcap"
            t = time.perf_counter()
            written = write_run(path, truth, flight, LOOK, spec)
            t_write = time.perf_counter() - t
            t = time.perf_counter()
            report = calibrate_run(path, CalibrateOptions(trials=0))
            t_cal = time.perf_counter() - t
            row = {"camera": kind, "seed": seed, "frames": written["n_frames"], "write_s": t_write, "calibrate_s": t_cal,
                   **errors_against_truth(report, truth, seed)}
            rows.append(row)
            print(f"  {kind:9s} seed {seed}: focal {row['focal_pct']:.3f} %  pp {row['pp_px']:.2f} px (sigma {row['pp_sigma_px']:.2f})  position {row['position_cm']:.2f} cm  "
                  f"proj {row['proj_waypoints_px']:.3f} px (waypoints) {row['proj_volume_px']:.3f} px (volume)  "
                  f"rms {row['rms_px']:.2f} px  model {row['model']}  {row['used']}/{row['windows']} windows  "
                  f"offset {row['offset_s']:.3f} s  [{row['frames']} frames: write {t_write:.0f} s, calibrate {t_cal:.1f} s]", flush=True)
            path.unlink()
    return rows


def print_accuracy(rows: list[dict]) -> None:
    targets = {"focal_pct": 1.0, "pp_px": 5.0, "position_cm": 5.0, "proj_waypoints_px": 1.0, "proj_volume_px": 1.0}
    names = {"focal_pct": "focal error (%)", "pp_px": "principal point (px)", "position_cm": "position (cm)",
             "proj_waypoints_px": "projection, waypoints (px RMS)", "proj_volume_px": "projection, volume (px RMS)"}
    print(f"\n{'':32s}" + "".join(f"{kind + ' mean':>16s}{kind + ' max':>15s}" for kind in CAMERAS) + f"{'target':>9s}")
    verdict = True
    for key, target in targets.items():
        line = f"{names[key]:32s}"
        for kind in CAMERAS:
            values = np.array([r[key] for r in rows if r["camera"] == kind])
            line += f"{values.mean():16.3f}{values.max():15.3f}"
            verdict &= bool(values.max() < target)
        print(line + f"{'< ' + format(target, 'g'):>9s}")
    pp_ok = all(r["pp_px"] < max(5.0, 3.0 * r["pp_sigma_px"]) for r in rows)
    print(f"issue 5 accuracy targets on every seed: {'PASS' if verdict else 'FAIL'} "
          f"(principal point within max(5 px, 3 reported sigma) on every seed: {'yes' if pp_ok else 'no'})")


# --------------------------------------------------------------------------
# (c) legs (issue 14): fly-through legs against holds at the same points


LEG_CAMERAS = {
    # name: (width, height, f_px, (k1, k2, p1, p2, k3), pole height m, tilt deg, leg depths m, leg heights m)
    "wide1080": (1920, 1080, 900.0, (-0.28, 0.07, 0.0, 0.0, 0.0), 3.5, 25.0, (3.0, 5.0, 8.0, 12.0), (0.8, 2.0, 3.5, 5.0)),
    "distorted4k": (3840, 2160, 2600.0, (-0.32, 0.12, 4e-4, -3e-4, -0.02), 4.5, 35.0, (3.0, 4.5, 6.0, 8.0, 10.0), (1.0, 2.5, 4.0)),
}
LEG_MODES = ("legs", "holds", "both")


def leg_truth(name: str, scale: float = 1.0):
    """The truth camera of a leg benchmark (``scale`` < 1 renders a smaller image with the same field of view)."""
    w, h, f, dist, pole, tilt, _d, _h = LEG_CAMERAS[name]
    return pole_camera(width=int(round(w * scale)), height=int(round(h * scale)), f_px=f * scale, position_enu=(0.0, 0.0, pole),
                       tilt_deg=tilt, distortion=dist, principal_offset_px=(12.0 * scale, -8.0 * scale))


def leg_errors(report, truth) -> dict:
    """Errors against the truth (sim.compare) and the report's own 1-sigma (linearised) for the same figures."""
    from dronecal_field.sim.compare import compare_cameras

    cam = report.camera
    X = np.array([p.marker_enu_m for p in report.used_points])
    cmp = compare_cameras(truth, cam, sampled_enu_m=X)
    lin = report.linearised
    ps = lin.param_std
    ti, ei = truth.intrinsics, cam.intrinsics
    return {
        "focal_px": float(0.5 * (ei.fx + ei.fy) - 0.5 * (ti.fx + ti.fy)),
        "focal_pct": cmp.focal_error_pct,
        "pp_px": cmp.principal_point_error_px,
        "position_cm": cmp.position_error_cm,
        "volume_px": cmp.sampled.rms_px if cmp.sampled is not None else float("nan"),
        "ground_px": cmp.ground.rms_px,
        "ground15_cm": cmp.ground_error_cm_at.get(15.0) or float("nan"),
        "sigma_focal_px": float(0.5 * (ps.get("fx", 0.0) + ps.get("fy", 0.0))),
        "sigma_pp_px": float(np.hypot(ps.get("cx", 0.0), ps.get("cy", 0.0))),
        "sigma_position_cm": 100.0 * float(np.sqrt(ps.get("pos_x", 0.0) ** 2 + ps.get("pos_y", 0.0) ** 2 + ps.get("pos_z", 0.0) ** 2)),
        "sigma_ground15_cm": float(lin.ground_error_15m_cm),
        "rms_px": float(report.result.rms_px),
        "model": report.result.model.name,
        "points": len(report.used_points),
        "leg_points": len([p for p in report.used_points if p.window.source == "leg"]),
        "offset_s": float(report.offset.offset_s),
        "readout_ms": 1000.0 * report.timing.readout_s if report.timing is not None else float("nan"),
        "shutter": report.timing.rolling_shutter if report.timing is not None else "",
    }


def legs_benchmark(cameras: list[str], modes: list[str], seeds: int, gnss_hz: float, rtk_tau_s: float, readout_s: float,
                   speed_mps: float, hold_s: float, fps: float, scale4k: float, workdir: Path) -> list[dict]:
    from contract_writer import leg_waypoints, make_leg_flight
    from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run

    rows = []
    for name in cameras:
        scale = scale4k if name == "distorted4k" else 1.0
        truth = leg_truth(name, scale)
        waypoints = leg_waypoints(truth, LEG_CAMERAS[name][6], LEG_CAMERAS[name][7])
        look = MarkerLook(marker_id=7, size_m=0.3)
        for seed in range(seeds):
            flights = {}
            if "legs" in modes:
                flights["legs"] = make_leg_flight(truth, waypoints, hold_s=0.0, speed_mps=speed_mps, offset_frd_m=OFFSET_FRD_M, seed=seed)
            if "holds" in modes or "both" in modes:
                flights["holds"] = make_leg_flight(truth, waypoints, hold_s=hold_s, speed_mps=speed_mps, offset_frd_m=OFFSET_FRD_M, seed=seed)
            paths: dict[str, tuple[Path, dict, float]] = {}
            for mode in modes:
                kind = "legs" if mode == "legs" else "holds"
                flight = flights[kind]
                spec = RunSpec(fps=fps, gnss_hz=gnss_hz, latency_s=LATENCY_S, declared_latency="unknown", gnss_sigma_m=(0.008, 0.008, 0.012),
                               site_origin=ORIGIN, seed=100 + seed, gnss_noise_tau_s=rtk_tau_s, readout_s=readout_s, exposure_s=0.004,
                               with_leg_events=True)
                if kind not in paths:  # "holds" and "both" calibrate the same run
                    path = workdir / f"{name}-{kind}-{seed}.mcap"
                    t = time.perf_counter()
                    paths[kind] = (path, write_run(path, truth, flight, look, spec), time.perf_counter() - t)
                path, written, t_write = paths[kind]
                t = time.perf_counter()
                report = calibrate_run(path, CalibrateOptions(trials=0, leg_source="none" if mode == "holds" else "auto"))
                t_cal = time.perf_counter() - t
                flight_s = (flight.t_ns[-1] - flight.t_ns[0]) / 1e9
                row = {"camera": name, "mode": mode, "seed": seed, "flight_s": flight_s, "frames": written["n_frames"],
                       "write_s": t_write, "calibrate_s": t_cal, **leg_errors(report, truth)}
                rows.append(row)
                print(f"  {name:11s} {mode:5s} seed {seed}: focal {row['focal_px']:+.2f} px (1-sigma {row['sigma_focal_px']:.2f})  "
                      f"pp {row['pp_px']:.2f} px ({row['sigma_pp_px']:.2f})  position {row['position_cm']:.2f} cm ({row['sigma_position_cm']:.2f})  "
                      f"volume {row['volume_px']:.3f} px  ground 3-30 m {row['ground_px']:.2f} px  at 15 m {row['ground15_cm']:.1f} cm ({row['sigma_ground15_cm']:.1f})  "
                      f"rms {row['rms_px']:.2f}  {row['model']}  {row['points']} points ({row['leg_points']} on legs)  offset {row['offset_s']:.3f} s  "
                      f"readout {row['readout_ms']:.1f} ms ({row['shutter']})  [flight {flight_s:.0f} s, {row['frames']} frames: write {t_write:.0f} s, "
                      f"calibrate {t_cal:.1f} s]", flush=True)
            for path, _w, _t in paths.values():
                path.unlink()
    return rows


def print_legs(rows: list[dict]) -> None:
    keys = (("focal_pct", "focal error (%)"), ("pp_px", "principal point (px)"), ("position_cm", "position (cm)"),
            ("volume_px", "projection, sampled volume (px RMS)"), ("ground_px", "projection, ground 3-30 m (px RMS)"),
            ("ground15_cm", "ground error at 15 m (cm)"), ("flight_s", "flight (s)"), ("calibrate_s", "calibrate (s)"))
    groups = sorted({(r["camera"], r["mode"]) for r in rows}, key=lambda g: (g[0], LEG_MODES.index(g[1])))
    print("\n| median over seeds | " + " | ".join(f"{c} {m}" for c, m in groups) + " |")
    print("|---|" + "---:|" * len(groups))
    for key, label in keys:
        print(f"| {label} | " + " | ".join(f"{np.median([abs(r[key]) for r in rows if (r['camera'], r['mode']) == g]):.3g}" for g in groups) + " |")
    print("\nmedian |true error| / reported 1-sigma (linearised), target 0.5-1.5:")
    for g in groups:
        sel = [r for r in rows if (r["camera"], r["mode"]) == g]
        ratios = {k: float(np.median([abs(r[t]) / max(r[s], 1e-12) for r in sel])) for k, t, s in (
            ("focal", "focal_px", "sigma_focal_px"), ("pp", "pp_px", "sigma_pp_px"), ("position", "position_cm", "sigma_position_cm"),
            ("ground15", "ground15_cm", "sigma_ground15_cm"))}
        print(f"  {g[0]} {g[1]}: " + ", ".join(f"{k} {v:.2f}" for k, v in ratios.items()))
    all_ratios = {k: float(np.median([abs(r[t]) / max(r[s], 1e-12) for r in rows])) for k, t, s in (
        ("focal", "focal_px", "sigma_focal_px"), ("pp", "pp_px", "sigma_pp_px"), ("position", "position_cm", "sigma_position_cm"),
        ("ground15", "ground15_cm", "sigma_ground15_cm"))}
    print("  all runs: " + ", ".join(f"{k} {v:.2f}" for k, v in all_ratios.items()))


def legs_speed(name: str, minutes: float, fps: float, scale: float, workdir: Path) -> dict:
    """A ``minutes``-long legs-and-holds run of camera ``name`` (the leg pattern flown again and again,
    5 s holds at the ends of every other pass), then ``dronecal-field calibrate`` (default options,
    500 Monte-Carlo trials) in a fresh process: flight duration / wall time."""
    from contract_writer import leg_waypoints, make_leg_flight

    truth = leg_truth(name, scale)
    pattern = leg_waypoints(truth, LEG_CAMERAS[name][6], LEG_CAMERAS[name][7])
    waypoints, holds = [], []
    k = 0
    while True:
        waypoints.append(pattern if k % 2 == 0 else pattern[::-1])
        holds.append(np.full(len(pattern), 5.0 if k % 2 else 0.0))
        flight = make_leg_flight(truth, np.vstack(waypoints), hold_s=np.concatenate(holds), speed_mps=2.0, offset_frd_m=OFFSET_FRD_M, seed=k)
        if (flight.t_ns[-1] - flight.t_ns[0]) / 1e9 >= minutes * 60 or k > 40:
            break
        k += 1
    path = workdir / f"speed-{name}.mcap"
    t = time.perf_counter()
    written = write_run(path, truth, flight, MarkerLook(marker_id=7, size_m=0.3), RunSpec(
        fps=fps, gnss_hz=5.0, latency_s=LATENCY_S, declared_latency="unknown", site_origin=ORIGIN, seed=7, readout_s=0.03, exposure_s=0.004))
    build_s = time.perf_counter() - t
    duration = (flight.t_ns[-1] - flight.t_ns[0]) / 1e9
    res = timed_calibrate(path, workdir / f"speed-{name}-out")
    if res["rc"] != 0:
        print(res["output"][-3000:])
        raise SystemExit(f"calibrate failed with exit code {res['rc']}")
    report = json.loads((workdir / f"speed-{name}-out" / "report.json").read_text())
    out = {"camera": name, "size": f"{truth.width}x{truth.height}", "duration_s": duration, "frames": written["n_frames"], "build_s": build_s,
           "wall_s": res["wall_s"], "cpu_s": res["cpu_s"], "ratio": duration / res["wall_s"], "frames_decoded": report["frames"]["frames_decoded"],
           "timings_s": report["timings_s"], "legs": len(flight.legs), "holds": len(flight.holds)}
    path.unlink()
    print(f"  {name} {out['size']}: flight {duration / 60:.1f} min ({out['legs']} legs, {out['holds']} holds), {out['frames']} frames at {fps:g} fps "
          f"(built in {build_s:.0f} s); calibrate wall {res['wall_s']:.1f} s, CPU {res['cpu_s']:.1f} s, decoded {out['frames_decoded']} frames; "
          f"flight / calibrate = {out['ratio']:.1f}x (target >= 10x): {'PASS' if out['ratio'] >= 10 else 'FAIL'}", flush=True)
    print("    stage timings (s): " + ", ".join(f"{k} {v:.1f}" for k, v in out["timings_s"].items() if isinstance(v, (int, float))), flush=True)
    return out


# --------------------------------------------------------------------------
# (b) speed


def long_flight(truth, lattice: np.ndarray, minutes: float, hold_s: float, move_s: float, min_waypoints: int, drift_m: float, seed: int):
    """(waypoints, flight, render) of a ``minutes``-long flight over an even pick of ``lattice`` (at least ``min_waypoints``)."""
    n_wp = int(np.clip(round((minutes * 60.0 - 13.0) / (hold_s + move_s)), min_waypoints, len(lattice)))
    waypoints = lattice[np.unique(np.round(np.linspace(0, len(lattice) - 1, n_wp)).astype(int))]
    flight = make_flight(truth, waypoints, hold_s=hold_s, move_s=move_s, drift_m=drift_m, offset_frd_m=OFFSET_FRD_M, seed=seed)
    return waypoints, flight, _sim_render(truth, flight, LOOK, seed)


def flight_telemetry(flight, hold_s: float, rng: np.random.Generator) -> list[tuple[int, int, object]]:
    """(write time ns, order, record) of a flight, in write order: 10 Hz fixes (RTK noise) and attitude,
    hover events written when the hold ends (as fly does)."""
    from dronecal_field.runfile.records import Attitude, GnssFix, RunEvent

    t0, t1 = int(flight.t_ns[0]), int(flight.t_ns[-1])
    telemetry: list[tuple[int, int, object]] = []
    fix_t = np.arange(t0, t1, 100_000_000, dtype=np.int64)
    pos, rpy = flight.at(fix_t)
    sigma = np.array([0.008, 0.008, 0.012])
    geo = enu_to_geodetic(pos + rng.normal(size=pos.shape) * sigma, ORIGIN)
    cov = np.diag(sigma**2)
    for k, t in enumerate(fix_t):
        telemetry.append((int(t), 0, GnssFix(timestamp_ns=int(t), lat_deg=float(geo[k, 0]), lon_deg=float(geo[k, 1]), alt_m=float(geo[k, 2]),
                                             covariance_enu=cov, fix_type="rtk_fixed")))
        yaw = float((rpy[k, 2] + np.pi) % (2 * np.pi) - np.pi)
        telemetry.append((int(t), 1, Attitude(timestamp_ns=int(t), roll_rad=float(rpy[k, 0]), pitch_rad=float(rpy[k, 1]), yaw_rad=yaw)))
    for a, b, seq in flight.holds:
        telemetry.append((b, 2, RunEvent(timestamp_ns=a, duration_ns=b - a, type="hover", metadata={"seq": str(seq), "hold_s": f"{hold_s:g}"})))
    telemetry.sort(key=lambda r: (r[0], r[1]))
    return telemetry


def write_telemetry(writer, telemetry: list[tuple[int, int, object]], j: int, until_ns: int) -> int:
    """Write ``telemetry`` from index ``j`` while its write time is at most ``until_ns``; the next index."""
    from dronecal_field.runfile.records import Attitude, GnssFix

    while j < len(telemetry) and telemetry[j][0] <= until_ns:
        record = telemetry[j][2]
        if isinstance(record, GnssFix):
            writer.write_fix(record)
        elif isinstance(record, Attitude):
            writer.write_attitude(record)
        else:
            writer.write_event(record)
        j += 1
    return j


def build_long_run(path: Path, minutes: float, fps: float, move_hz: float, hold_hz: float, seed: int = 0) -> dict:
    """Write a ``minutes``-long 1080p run with RunWriter; frames rendered at ``move_hz`` / ``hold_hz`` and reused between."""
    from dronecal_field.runfile.records import FORMAT_VERSION, Frame, MarkerSpec, RunEvent, RunMetadata
    from dronecal_field.runfile.writer import RunWriter
    from contract_writer import encode_jpeg

    truth = truth_camera("distorted")
    lattice = grid_waypoints(east_m=(-3.6, -1.8, 0.0, 1.8, 3.6), north_m=(6.0, 8.5, 11.0, 13.5), up_m=(1.0, 2.5, 4.0))
    hold_s, move_s = 6.0, 4.0
    waypoints, flight, render = long_flight(truth, lattice, minutes, hold_s, move_s, 8, 0.02, seed)
    rng = np.random.default_rng(seed)
    t0, t1 = int(flight.t_ns[0]), int(flight.t_ns[-1])

    telemetry = flight_telemetry(flight, hold_s, rng)

    # Frames: capture at 30 fps, stamped LATENCY_S later; the rendering nearest in time (10 Hz moving, 2 Hz holding).
    capture = t0 + np.round(np.arange(int((t1 - t0) * 1e-9 * fps)) / fps * 1e9).astype(np.int64)
    holds = np.array([(a, b) for a, b, _ in flight.holds], np.int64)

    def key_of(t: int) -> int:
        i = np.searchsorted(holds[:, 0], t, side="right") - 1
        if i >= 0 and t < holds[i, 1]:
            period = int(1e9 / hold_hz)
            return int(min(holds[i, 0] + ((t - holds[i, 0]) // period) * period + period // 2, holds[i, 1] - 1))
        period = int(1e9 / move_hz)
        return int(t0 + round((t - t0) / period) * period)

    metadata = RunMetadata(
        format_version=FORMAT_VERSION, width=WIDTH, height=HEIGHT,
        marker=MarkerSpec(kind="aruco", dictionary=LOOK.dictionary, marker_id=LOOK.marker_id, size_m=LOOK.size_m, offset_frd_m=OFFSET_FRD_M),
        camera_latency_s=None, site_origin=ORIGIN, extra={"recorder": "benchmarks/bench_calibrate.py"},
    )
    latency_ns = int(LATENCY_S * 1e9)
    renders, last_key, data, j = 0, None, b"", 0
    jpeg_bytes = 0
    with RunWriter(path, metadata, background_flush=False) as writer:
        for t in capture:
            stamp = int(t) + latency_ns
            j = write_telemetry(writer, telemetry, j, stamp)
            key = key_of(int(t))
            if key != last_key:
                data, last_key = encode_jpeg(render(key), 92), key
                renders += 1
            jpeg_bytes += len(data)
            writer.write_frame(Frame(timestamp_ns=stamp, format="jpeg", data=data))
        for _t, _o, record in telemetry[j:]:  # the last hold's event comes after the last frame
            if isinstance(record, RunEvent):
                writer.write_event(record)
    return {"truth": truth, "duration_s": (t1 - t0) / 1e9, "frames": len(capture), "renders": renders, "waypoints": len(waypoints),
            "fixes": sum(1 for _, order, _ in telemetry if order == 0), "mean_jpeg_kb": jpeg_bytes / len(capture) / 1e3, "size_mb": path.stat().st_size / 1e6}


def timed_calibrate(run: Path, out: Path) -> dict:
    """``dronecal-field calibrate`` in a fresh process: wall seconds and CPU seconds (rusage of the child)."""
    argv = [sys.executable, "-m", "dronecal_field", "calibrate", str(run), "--out", str(out)]
    t = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, cwd=ROOT)
    output = proc.stdout.read().decode(errors="replace")
    _pid, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t
    proc.returncode = os.waitstatus_to_exitcode(status)
    return {"rc": proc.returncode, "wall_s": wall, "cpu_s": usage.ru_utime + usage.ru_stime, "peak_rss_mb": usage.ru_maxrss / 1024, "output": output}


def speed(minutes: float, fps: float, move_hz: float, hold_hz: float, workdir: Path) -> dict:
    path = workdir / "long.mcap"
    t = time.perf_counter()
    built = build_long_run(path, minutes, fps, move_hz, hold_hz)
    build_s = time.perf_counter() - t
    print(f"  built {path}: {built['duration_s']:.0f} s flight, {built['frames']} frames {WIDTH}x{HEIGHT} at {fps:g} fps "
          f"({built['renders']} distinct renderings, mean JPEG {built['mean_jpeg_kb']:.0f} KB), {built['waypoints']} waypoints, "
          f"{built['fixes']} fixes; {built['size_mb']:.0f} MB in {build_s:.0f} s", flush=True)
    print(f"  machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f} before the timed run", flush=True)
    res = timed_calibrate(path, workdir / "long-calibration")
    if res["rc"] != 0:
        print(res["output"][-3000:])
        raise SystemExit(f"calibrate failed with exit code {res['rc']}")
    report = json.loads((workdir / "long-calibration" / "report.json").read_text())
    frames = report["frames"]
    cam = report["calibration"]["camera"]
    truth = built["truth"]
    ti = truth.intrinsics
    centre = to_truth_frame(np.array(cam["camera_position_enu_m"], float), EnuOrigin(**{
        "lat_deg": report["frame"]["enu_origin"]["lat_deg"], "lon_deg": report["frame"]["enu_origin"]["lon_deg"], "h_m": report["frame"]["enu_origin"]["h_m"]}))[0]
    out = {
        **{k: built[k] for k in ("duration_s", "frames", "renders", "waypoints", "size_mb", "mean_jpeg_kb")},
        "build_s": build_s, "wall_s": res["wall_s"], "cpu_s": res["cpu_s"], "peak_rss_mb": res["peak_rss_mb"],
        "ratio": built["duration_s"] / res["wall_s"],
        "frames_read": frames["frames_read"], "frames_decoded": frames["frames_decoded"], "frames_with_marker": frames["frames_with_marker"],
        "timings_s": report["timings_s"], "used": report["hover_windows"]["used"], "windows": report["hover_windows"]["count"],
        "focal_pct": 100.0 * max(abs(cam["fx"] / ti.fx - 1), abs(cam["fy"] / ti.fy - 1)),
        "pp_px": float(np.hypot(cam["cx"] - ti.cx, cam["cy"] - ti.cy)),
        "pp_sigma_px": float(np.hypot(report["calibration"]["parameter_std_from_residuals"]["cx"], report["calibration"]["parameter_std_from_residuals"]["cy"])),
        "model": report["calibration"]["model"],
        "position_cm": 100.0 * float(np.linalg.norm(centre - truth.pose.position_world)),
        "offset_s": report["time_offset"]["offset_s"], "trials": report["options"]["trials"],
    }
    path.unlink()
    return out


def print_speed(s: dict) -> None:
    print(f"\n  flight {s['duration_s'] / 60:.1f} min, {s['frames']} frames; calibrate (fresh process, {s['trials']} Monte-Carlo trials): "
          f"wall {s['wall_s']:.1f} s, CPU {s['cpu_s']:.1f} s ({s['cpu_s'] / s['wall_s']:.2f} cores), peak RSS {s['peak_rss_mb']:.0f} MB")
    print(f"  frames read {s['frames_read']} of {s['frames']} ({100 * s['frames_read'] / s['frames']:.0f} %), decoded {s['frames_decoded']} "
          f"({100 * s['frames_decoded'] / s['frames']:.1f} %), marker found in {s['frames_with_marker']}; {s['used']}/{s['windows']} windows used")
    steps = ", ".join(f"{k} {v:.1f}" for k, v in s["timings_s"].items() if isinstance(v, (int, float)))
    print(f"  stage timings (s, report.json): {steps}")
    print(f"  accuracy on this run: focal {s['focal_pct']:.3f} %, pp {s['pp_px']:.2f} px (sigma {s['pp_sigma_px']:.2f}), "
          f"position {s['position_cm']:.2f} cm, model {s['model']}, offset {s['offset_s']:.3f} s (true {LATENCY_S} s)")
    print(f"  flight duration / processing time = {s['ratio']:.1f}x; issue 5 target >= 5x: {'PASS' if s['ratio'] >= 5 else 'FAIL'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", choices=("accuracy", "speed", "legs", "legs-speed"))
    parser.add_argument("--leg-cameras", default="wide1080,distorted4k", help="cameras of the legs part (default both)")
    parser.add_argument("--leg-modes", default="legs,holds,both", help="legs only, holds only (same points), both")
    parser.add_argument("--readout", type=float, default=0.03, metavar="S", help="rolling-shutter readout of the legs runs (default 0.03)")
    parser.add_argument("--leg-speed", type=float, default=2.0, help="leg speed, m/s (default 2)")
    parser.add_argument("--leg-hold", type=float, default=3.0, help="hold at each leg end in the holds runs, s (default 3)")
    parser.add_argument("--scale4k", type=float, default=1.0, help="render the 4K camera at this scale (default 1: full 3840x2160)")
    parser.add_argument("--seeds", type=int, default=3, help="seeds per camera for the accuracy part (default 3)")
    parser.add_argument("--accuracy-fps", type=float, default=10.0, help="frame rate of the accuracy runs (default 10)")
    parser.add_argument("--gnss-hz", type=float, default=10.0,
                        help="GNSS rate of the accuracy runs (default 10, what fly asks for; 5 is ArduPilot's GPS_RATE_MS default)")
    parser.add_argument("--rtk-tau", type=float, default=0.0, metavar="S",
                        help="RTK noise correlation time of the accuracy runs, seconds (default 0: white noise)")
    parser.add_argument("--minutes", type=float, default=10.0, help="length of the speed run (default 10)")
    parser.add_argument("--fps", type=float, default=30.0, help="frame rate of the speed run (default 30)")
    parser.add_argument("--move-hz", type=float, default=10.0, help="distinct renderings per second while moving (default 10)")
    parser.add_argument("--hold-hz", type=float, default=2.0, help="distinct renderings per second while holding (default 2)")
    parser.add_argument("--workdir", type=Path, help="where to write the runs (default: a new folder in /tmp, removed at the end)")
    args = parser.parse_args()

    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="bench_calibrate_", dir="/tmp"))
    workdir.mkdir(parents=True, exist_ok=True)
    try:
        if args.only in (None, "accuracy"):
            print(f"(a) accuracy: {WIDTH}x{HEIGHT}, f {FOCAL_PX:g} px, 24 waypoints, {math.ceil(1 + 40 / args.accuracy_fps)} s holds, 2 cm drift, "
                  f"RTK noise ({'white' if not args.rtk_tau else f'correlated over {args.rtk_tau:g} s'}), {LATENCY_S} s unknown latency, {args.accuracy_fps:g} fps, {args.gnss_hz:g} Hz GNSS, {args.seeds} seeds per camera", flush=True)
            rows = accuracy(args.seeds, args.accuracy_fps, args.gnss_hz, workdir, args.rtk_tau)
            print_accuracy(rows)
        if args.only == "legs":
            cams = args.leg_cameras.split(",")
            modes = args.leg_modes.split(",")
            print(f"(c) legs: {', '.join(cams)}; {', '.join(modes)}; {args.leg_speed:g} m/s legs, {args.leg_hold:g} s holds, readout "
                  f"{args.readout * 1000:g} ms, {args.accuracy_fps:g} fps, {args.gnss_hz:g} Hz GNSS, RTK noise "
                  f"{'white' if not args.rtk_tau else f'correlated over {args.rtk_tau:g} s'}, {LATENCY_S} s unknown latency, {args.seeds} seeds", flush=True)
            rows = legs_benchmark(cams, modes, args.seeds, args.gnss_hz, args.rtk_tau, args.readout, args.leg_speed, args.leg_hold,
                                  args.accuracy_fps, args.scale4k, workdir)
            print_legs(rows)
        if args.only == "legs-speed":
            print(f"(d) legs speed: {args.minutes:g}-minute legs-and-holds runs at {args.accuracy_fps:g} fps through `dronecal-field calibrate`", flush=True)
            for name in args.leg_cameras.split(","):
                legs_speed(name, args.minutes if name == "wide1080" else 0.6 * args.minutes, args.accuracy_fps,
                           args.scale4k if name == "distorted4k" else 1.0, workdir)
        if args.only in (None, "speed"):
            print(f"\n(b) speed: a {args.minutes:g}-minute {WIDTH}x{HEIGHT} {args.fps:g} fps run through `dronecal-field calibrate`", flush=True)
            print_speed(speed(args.minutes, args.fps, args.move_hz, args.hold_hz, workdir))
    finally:
        if args.workdir is None:
            shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    main()
