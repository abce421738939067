"""Issue 10: the whole-view check. plan -> sim vehicle + sim camera -> fly --start -> calibrate, against the truth.

    .venv/bin/python benchmarks/bench_wholeview.py --camera wide
    .venv/bin/python benchmarks/bench_wholeview.py --camera wide 4k table1 --strategy image --sampling mixed
    .venv/bin/python benchmarks/bench_wholeview.py --camera 4k --strategy paper-far -- --max-agl 3
    .venv/bin/python benchmarks/bench_wholeview.py --camera wide --label image --reuse    # re-measure, no flight
    .venv/bin/python benchmarks/bench_wholeview.py --camera wide --sampling hover --label split -- --endurance 8

The last line is the split check: an 8-minute battery cannot hold the wide
camera's hold plan, so ``plan`` writes mission-1.plan and mission-2.plan (5.8
and 3.7 min). ``plan`` splits only when no layout that covers the ROI fits
75 % of ``--endurance``: with the default sampling an 8-minute battery fits a
one-flight plan; ``-- --endurance 5`` splits that one (3.7 + 2.2 min).

Every command runs in its own process over real sockets, as ``make demo``
does (dronecal_field/demo.py): the truth camera is written to truth.yaml,
``plan`` gets only the nominal values (the truth's focal length and pose, the
distortion LEVEL guessed, not its coefficients), the simulated vehicle flies
the plan at ``--speedup`` with the simulated camera rendering through the
truth, ``fly --start`` records, ``calibrate`` calibrates. The calibrated camera
is then compared with the truth (dronecal_field/sim/compare.py) over the
visible ground 3-30 m from the pole, over the sampled volume (the convex hull
of the marker positions calibrate used) and over the whole image at 4-12 m.

Cameras (all at ArduPilot SITL's CMAC site, looking 30 deg east of north):

* ``wide``: 1920x1080, f 900 px, k1 -0.28, k2 0.07, 3.5 m pole, tilt 25; planned ``--distortion strong``;
* ``4k``: 3840x2160, f 2600 px, k1 -0.32, k2 0.12, k3 -0.02, p1 4e-4, p2 -3e-4, 4.5 m pole, tilt 35; ``--distortion medium``;
* ``table1``: the paper's distorted Table 1 camera (core/synthetic.paper_camera):
  1280x960, f 1110 px, principal point (640, 480), k1 -0.25, p1 -28e-5, p2 -5e-5, 2 m pole, tilt 30;
  ``--distortion medium``.

The frame rate is kept honest: the simulated camera serves ``--camera-fps x
--speedup`` frames per wall second, so it makes ``--camera-fps`` frames per
VEHICLE second, and ``plan`` is told that rate (``--fps``). The table shows
the frames per hold that calibrate found, and the rate the recording really
got (frames / vehicle seconds): if the renderer cannot keep up, lower
``--speedup`` (default 2, and 1 for 4K: a 4K frame takes 30+ ms to render and
encode). Settle time in calibrate is 1 vehicle second (``--settle-s`` counts
on the run's wall clock).

A plan split into flights is flown flight after flight, each a fresh ``fly
--start`` recording its own run-K.mcap (a one-flight plan records run.mcap, so
older folders still work with ``--reuse``), on ONE pair of simulators at the
plan's take-off point: between flights the vehicle lands there and disarms,
and the next ``fly --start`` uploads the next mission and re-arms it, as an
operator swaps the battery and takes off from the same spot while the pole
camera keeps running. (Fresh simulators per flight would draw the same noise
seed, i.e. the same GNSS noise, in every flight.) ``calibrate run-1.mcap
run-2.mcap ...`` then pools the runs into one camera by itself (they carry one
plan.json), and each run is also calibrated alone (OUT/CAMERA-LABEL/
calibration-flight-K/): the table's last two columns give each flight's
planned (flown) minutes and points in the joint calibration, and each flight
alone's ground 3-30 m RMS / max px against the truth, so the pooling's gain is
measured here; the JSON has them under ``run.flights`` and ``flights_alone``.

``--strategy`` and ``--sampling`` go to ``plan`` only when given; anything
after ``--`` goes to ``plan`` verbatim (options of plans to come). One table
row per camera is printed, and everything is written to
OUT/wholeview-LABEL.json; each camera's files are in OUT/CAMERA-LABEL/.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dronecal_field.demo import SITE, cli_argv, in_enu_frame_of, run_step, start_simulators, used_marker_points  # noqa: E402
from dronecal_field.errors import DronecalError  # noqa: E402

MARKER = dict(dictionary="DICT_4X4_50", marker_id=0, offset_frd_m=(0.10, 0.0, 0.05))
CAMERAS = {
    "wide": dict(width=1920, height=1080, focal_px=900.0, k1=-0.28, k2=0.07, mount_height=3.5, tilt=25.0, level="strong"),
    "4k": dict(width=3840, height=2160, focal_px=2600.0, k1=-0.32, k2=0.12, k3=-0.02, p1=4e-4, p2=-3e-4,
               mount_height=4.5, tilt=35.0, level="medium"),
    "table1": dict(width=1280, height=960, focal_px=1110.0, k1=-0.25, p1=-28e-5, p2=-5e-5, cx=640.0, cy=480.0,
                   mount_height=2.0, tilt=30.0, level="medium"),
}


# The 4K camera renders and encodes a frame in 30+ ms on one core (more while other jobs run): at 1x the
# sim camera keeps 10 frames per vehicle second; 1080p keeps 20 fps wall, i.e. 10 per vehicle second at 2x.
DEFAULT_SPEEDUP = {"wide": 2.0, "4k": 1.0, "table1": 2.0}


def truth_camera(name: str):
    """The truth Camera of one of CAMERAS, ENU at the demo site's pole foot."""
    from dronecal_field.core.camera import Distortion
    from dronecal_field.geodesy import EnuOrigin
    from dronecal_field.sim.scene import make_truth_camera

    c = CAMERAS[name]
    dist = Distortion(**{k: c.get(k, 0.0) for k in ("k1", "k2", "p1", "p2", "k3")})
    return make_truth_camera(EnuOrigin(SITE["lat"], SITE["lon"], SITE["ground_h"]), c["mount_height"], SITE["azimuth"],
                             c["tilt"], c["focal_px"], c["width"], c["height"], distortion=dist, cx=c.get("cx"), cy=c.get("cy"))


def plan_argv(name: str, plan_dir: Path, camera_fps: float, strategy: str | None, sampling: str | None, extra: list[str]) -> list[str]:
    """The ``plan`` command for camera ``name`` from its nominal values only."""
    c = CAMERAS[name]
    argv = [
        "plan", "--out", plan_dir, f"--lat={SITE['lat']}", f"--lon={SITE['lon']}", "--ground-alt", SITE["ground_h"],
        "--mount-height", c["mount_height"], "--azimuth", SITE["azimuth"], "--tilt", c["tilt"],
        "--image-size", f"{c['width']}x{c['height']}", "--focal-px", c["focal_px"], "--distortion", c["level"],
        "--marker-dictionary", MARKER["dictionary"], "--marker-id", MARKER["marker_id"],
        "--marker-offset", ",".join(str(v) for v in MARKER["offset_frd_m"]), "--fps", camera_fps, "--hover", "3",
    ]
    if strategy:
        argv += ["--strategy", strategy]
    if sampling:
        argv += ["--sampling", sampling]
    return cli_argv(*argv, *extra)


def find_keys(tree: object, words: tuple[str, ...], prefix: str = "") -> dict[str, float]:
    """Numeric leaves of a JSON tree whose dotted path contains one of ``words`` (case-insensitive)."""
    out: dict[str, float] = {}
    if isinstance(tree, dict):
        for k, v in tree.items():
            out.update(find_keys(v, words, f"{prefix}.{k}" if prefix else str(k)))
    elif isinstance(tree, (int, float)) and not isinstance(tree, bool):
        if any(w in prefix.lower() for w in words):
            out[prefix] = float(tree)
    return out


def predicted_roi_px(plan: dict) -> tuple[str | None, float | None]:
    """The plan's predicted projection error over its region of interest / the ground, px, and the key it came from.

    Looks for the figures plans of issue 10 will carry (a key with 'roi' and
    'px'), then today's Monte-Carlo ground figure.
    """
    combined = plan.get("prediction", {}).get("combined_px", {}).get("rms")
    if combined is not None:  # issue 10's plan: linearised and extrapolation terms combined, over its ROI
        return "prediction.combined_px.rms", float(combined)
    found = find_keys(plan, ("roi",))
    for key, value in sorted(found.items()):
        if "px" in key.lower() and "rms" in key.lower() and "p95" not in key.lower() and not key.startswith("candidates"):
            return key, value
    for key, value in sorted(found.items()):
        if "px" in key.lower() and not key.startswith("candidates"):
            return key, value
    key = "uncertainty.monte_carlo.ground_projection_error_px"
    value = plan.get("uncertainty", {}).get("monte_carlo", {}).get("ground_projection_error_px")
    return (key, float(value)) if value is not None else (None, None)


def run_one(name: str, out: Path, args: argparse.Namespace, extra: list[str], echo=print) -> dict:
    """plan -> simulators -> fly --start (every flight of the plan) -> calibrate -> compare, for one camera; returns the numbers.

    A plan split into flights is flown flight after flight (run-1.mcap,
    run-2.mcap, ...; a one-flight plan records run.mcap), calibrated jointly
    (``calibrate run-1.mcap run-2.mcap`` pools the flights of one plan), and
    each flight is also calibrated alone, so the table shows what pooling
    gains. With ``args.reuse`` a step whose output is already in ``out``
    (plan.json, a finished run file, report.json) is not run again: the
    comparison can be re-measured without flying.
    """
    from dronecal_field.camerafile import read_camera, write_camera
    from dronecal_field.sim.compare import compare_cameras

    t0 = time.monotonic()
    out.mkdir(parents=True, exist_ok=True)
    logs = out / "logs"
    logs.mkdir(exist_ok=True)
    truth = truth_camera(name)
    truth_path = out / "truth.yaml"
    write_camera(truth_path, truth, comment=f"simulator ground truth (bench_wholeview {name})")
    times: dict[str, float] = {}

    plan_dir = out / "plan"
    if not (args.reuse and (plan_dir / "plan.json").is_file()):
        echo(f"[{name}] plan")
        t = time.monotonic()
        run_step("plan", plan_argv(name, plan_dir, args.camera_fps, args.strategy, args.sampling, extra), logs / "plan.log", timeout_s=600)
        times["plan"] = time.monotonic() - t
    plan = json.loads((plan_dir / "plan.json").read_text())
    missions = mission_files(plan, plan_dir)
    home = takeoff_point(missions)
    marker = dict(MARKER, size_m=plan["marker"]["size_m"], offset_frd_m=tuple(plan["marker"]["offset_frd_m"]))
    flights = [Flight(k + 1, m, *flight_paths(out, k + 1, len(missions))) for k, m in enumerate(missions)]

    todo = [f for f in flights if not (args.reuse and f.recorded)]
    if todo:
        fly_flights(name, todo, plan, truth_path, home, marker, logs, args, times, echo)
        (out / "flight.json").write_text(json.dumps(dict(speedup=args.speedup, camera_fps=args.camera_fps, n_flights=len(flights))))
    else:  # the flights' own clock rates, not this invocation's
        flown = json.loads((out / "flight.json").read_text())
        args = argparse.Namespace(**dict(vars(args), speedup=flown["speedup"], camera_fps=flown["camera_fps"]))
    wall_fps = args.camera_fps * args.speedup
    per_flight = [dict(fly_facts(f.log, args.speedup), file=f.mission.name, run=f.run.name) for f in flights]
    fly = flights_total(per_flight)

    calib_dir = out / "calibration"
    row = dict(
        camera=name,
        strategy=args.strategy or plan.get("strategy", {}).get("candidate"),
        sampling=args.sampling,
        plan_extra=extra,
        speedup=args.speedup,
        camera_fps_vehicle=args.camera_fps,
        camera_fps_wall=wall_fps,
        marker_size_m=marker["size_m"],
        plan=plan_facts(plan),
        run=fly,
        calibration=None,
        comparison=None,
        measured_over_predicted=None,
        flights_alone=None,
        error=None,
        times_s=times,
        out_dir=str(out),
    )
    if not (args.reuse and (calib_dir / "report.json").is_file()):
        echo(f"[{name}] calibrate " + (" + ".join(f.run.name for f in flights) + " jointly" if len(flights) > 1 else flights[0].run.name))
        t = time.monotonic()
        try:
            run_step("calibrate", calibrate_argv([f.run for f in flights], calib_dir, args), logs / "calibrate.log", timeout_s=1800)
        except DronecalError:
            # A refusal is a result (e.g. the points are coplanar): keep it in the table.
            row["error"] = (logs / "calibrate.log").read_text().strip().splitlines()[-1]
            times["calibrate"] = time.monotonic() - t
            return row
        times["calibrate"] = time.monotonic() - t
    report = json.loads((calib_dir / "report.json").read_text())
    if len(flights) > 1 and report.get("joint", {}).get("n_runs") != len(flights):
        # calibrate pools the flights of one plan by itself: a batch here means it did not see one plan
        row["error"] = f"calibrate did not pool the {len(flights)} runs into one camera (report.json has no joint section of {len(flights)} runs)"
        return row
    est_file = read_camera(calib_dir / "camera.yaml")
    est = in_enu_frame_of(est_file, truth.enu_origin)
    sampled = used_marker_points(report, est_file.enu_origin, truth.enu_origin)
    cmp = compare_cameras(truth, est, sampled)
    # The plan predicts over its own ROI (default the ground 3-40 m and 2 m above it): the ground out to 40 m too.
    roi_range = tuple(row["plan"]["roi_range_m"] or (3.0, 40.0))
    cmp_roi = compare_cameras(truth, est, None, ground_range_m=roi_range)
    roi_px = row["plan"]["predicted_roi_px"]
    if len(flights) > 1:
        for f, facts, joint_run in zip(flights, per_flight, report["joint"]["runs"]):
            facts.update(points_in_joint=joint_run.get("points_used"), hover_points_in_joint=joint_run.get("hover_points_used"),
                         leg_pairs_in_joint=joint_run.get("leg_pairs_used"), calibrated_alone_first=joint_run.get("calibrated_alone_first"))
        t = time.monotonic()
        row["flights_alone"] = [flight_alone(name, f, truth, out / f"calibration-flight-{f.k}", logs, args, echo) for f in flights]
        times["calibrate_alone"] = time.monotonic() - t
    times["total"] = time.monotonic() - t0
    row.update(
        run=dict(fly, **run_facts(report, calib_dir / "detections.csv")),
        calibration=calibration_facts(report),
        comparison=asdict(cmp),
        comparison_roi_ground=dict(range_m=roi_range, px=asdict(cmp_roi.ground), cm_rms=cmp_roi.ground_error_cm_rms),
        measured_over_predicted=(cmp_roi.ground.rms_px / roi_px) if roi_px else None,
    )
    return row


@dataclass(frozen=True)
class Flight:
    """One flight of the plan: its number, its mission file, the run file it records and fly's log."""

    k: int
    mission: Path
    run: Path
    log: Path

    @property
    def recorded(self) -> bool:
        """The run file is there and fly said it recorded it (a flight cut short leaves no 'recorded' line)."""
        return self.run.is_file() and self.log.is_file() and "recorded" in self.log.read_text()


def mission_files(plan: dict, plan_dir: Path) -> list[Path]:
    """The plan's mission files in flight order: mission.plan, or mission-1.plan, mission-2.plan, ... when split."""
    files = [f["file"] for f in plan["flight"].get("flights") or [] if f.get("file")]
    if not files:  # plan.json of plans before the flights list: whatever mission files are in the folder
        files = ["mission.plan"] if (plan_dir / "mission.plan").is_file() else sorted(
            (p.name for p in plan_dir.glob("mission-*.plan")), key=lambda n: int(n[len("mission-"):-len(".plan")]))
    missing = [f for f in files if not (plan_dir / f).is_file()]
    if not files or missing:
        raise DronecalError(f"{plan_dir}: no mission file {', '.join(missing or ['mission.plan'])}: plan again (drop --reuse)")
    return [plan_dir / f for f in files]


def takeoff_point(missions: list[Path]) -> tuple[float, float, float]:
    """The take-off point (lat, lon deg, h m) every flight of the plan starts from and lands at.

    The flights are flown one after the other by one simulated vehicle that
    lands, disarms and is re-armed where it stands, as an operator swaps the
    battery and takes off again from the same spot; a plan whose flights start
    at different points cannot be flown so.
    """
    from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu

    homes = [tuple(json.loads(m.read_text())["mission"]["plannedHomePosition"]) for m in missions]
    first = EnuOrigin(*homes[0])
    for m, h in zip(missions[1:], homes[1:]):
        apart = float(np.linalg.norm(geodetic_to_enu(h[0], h[1], h[2], first)[0]))
        if apart > 0.5:
            raise DronecalError(f"{m.name} takes off {apart:.1f} m from {missions[0].name}'s take-off point: "
                                "this bench flies every flight of a plan from one take-off point")
    return homes[0]


def flight_paths(out: Path, k: int, n: int) -> tuple[Path, Path]:
    """(run file, fly log) of flight ``k`` of ``n``: run.mcap and logs/fly.log for a one-flight plan (older folders
    keep working with --reuse), run-K.mcap and logs/fly-K.log otherwise."""
    if n == 1:
        return out / "run.mcap", out / "logs" / "fly.log"
    return out / f"run-{k}.mcap", out / "logs" / f"fly-{k}.log"


def fly_flights(name: str, flights: list[Flight], plan: dict, truth_path: Path, home: tuple[float, float, float], marker: dict,
                logs: Path, args: argparse.Namespace, times: dict[str, float], echo) -> None:
    """Fly ``flights`` one after the other with ``fly --start`` on ONE pair of simulators.

    The pole camera keeps running (a real one never stops) and the vehicle
    lands at the take-off point, disarms, and is re-armed by the next ``fly
    --start`` (the sim vehicle accepts a new mission and MISSION_START once
    landed: mission state reset on upload, GUIDED then arm). Fresh simulators
    per flight would replay the same noise seed, the same GNSS noise draws, in
    every flight; the sim vehicle has no battery to swap.
    """
    wall_fps = args.camera_fps * args.speedup
    planned = {f["file"]: f for f in plan["flight"].get("flights") or []}
    sims = start_simulators(truth_path, home, logs, args.speedup, wall_fps, marker)
    try:
        sims.wait_ready(timeout_s=180)
        for f in flights:
            p = planned.get(f.mission.name, dict(points=plan.get("points"), flight_time_s=plan["flight"]["flight_time_s"]))
            echo(f"[{name}] fly {f.mission.name} (flight {f.k} of {len(planned) or 1}) -> {f.run.name}: {p.get('points')} points, "
                 f"{p['flight_time_s'] / 60:.1f} min planned, speed-up {args.speedup:g}, "
                 f"camera {wall_fps:g} fps wall = {args.camera_fps:g} fps vehicle clock")
            t = time.monotonic()
            run_step("fly", cli_argv("fly", "--connect", sims.vehicle_url, "--mission", f.mission, "--video", sims.video_url,
                                     "--out", f.run, "--start", "--timeout-s", 3600), f.log, timeout_s=4000)
            times[f"fly_wall_{f.k}"] = time.monotonic() - t
    finally:
        sims.stop()
    times["fly_wall"] = sum(v for k, v in times.items() if k.startswith("fly_wall_"))


def calibrate_argv(runs: list[Path], out_dir: Path, args: argparse.Namespace) -> list[str]:
    """``calibrate RUN... --out OUT_DIR`` with this bench's options (the flights of one plan are pooled by calibrate itself)."""
    return cli_argv("calibrate", *runs, "--out", out_dir, "--trials", args.trials, "--min-fix", "rtk_fixed",
                    "--max-frames-per-window", int(24 * args.speedup),
                    # settle is counted on the run (wall) clock: 1 vehicle second
                    "--settle-s", 1.0 / args.speedup)


def flight_alone(name: str, flight: Flight, truth, calib_dir: Path, logs: Path, args: argparse.Namespace, echo) -> dict:
    """Flight ``flight`` of a split plan calibrated alone, against the truth: what the joint calibration is measured against."""
    from dronecal_field.camerafile import read_camera
    from dronecal_field.sim.compare import compare_cameras

    log = logs / f"calibrate-flight-{flight.k}.log"
    if not (args.reuse and (calib_dir / "report.json").is_file()):
        echo(f"[{name}] calibrate {flight.run.name} alone")
        try:
            run_step("calibrate", calibrate_argv([flight.run], calib_dir, args), log, timeout_s=1200)
        except DronecalError:  # a flight too small to calibrate alone is a result too
            return dict(flight=flight.k, run=flight.run.name, error=log.read_text().strip().splitlines()[-1])
    report = json.loads((calib_dir / "report.json").read_text())
    est_file = read_camera(calib_dir / "camera.yaml")
    sampled = used_marker_points(report, est_file.enu_origin, truth.enu_origin)
    cmp = compare_cameras(truth, in_enu_frame_of(est_file, truth.enu_origin), sampled)
    cal = report.get("calibration", {})
    return dict(flight=flight.k, run=flight.run.name, error=None, points_used=cal.get("n_points"), model=cal.get("model"),
                rms_px=cal.get("rms_px"), ground=asdict(cmp.ground), sampled=asdict(cmp.sampled) if cmp.sampled else None,
                focal_error_pct=cmp.focal_error_pct, principal_point_error_px=cmp.principal_point_error_px,
                position_error_cm=cmp.position_error_cm, ground_error_cm_rms=cmp.ground_error_cm_rms)


def flights_total(per_flight: list[dict]) -> dict:
    """The recording summed over the flights (frames, fixes, flight time), with each flight's own facts under ``flights``."""
    if len(per_flight) == 1:
        return dict(per_flight[0], n_flights=1, flights=per_flight)
    if any(f.get("flight_vehicle_s") is None for f in per_flight):
        return dict(flight_vehicle_s=None, n_flights=len(per_flight), flights=per_flight)
    frames = sum(f["frames"] for f in per_flight)
    wall_s = sum(f["record_wall_s"] for f in per_flight)
    vehicle_s = sum(f["flight_vehicle_s"] for f in per_flight)
    return dict(frames=frames, dropped=sum(f["dropped"] for f in per_flight), gnss_fixes=sum(f["gnss_fixes"] for f in per_flight),
                record_wall_s=wall_s, flight_vehicle_s=vehicle_s, camera_fps_wall_measured=frames / wall_s,
                camera_fps_vehicle_measured=frames / vehicle_s, n_flights=len(per_flight), flights=per_flight)


def fly_facts(fly_log: Path, speedup: float) -> dict:
    """Frames, fixes and duration of the recording from fly's last line; the flight in vehicle seconds."""
    import re

    text = fly_log.read_text() if fly_log.is_file() else ""
    m = re.search(r"recorded .*?: (\d+) frames \((\d+) dropped\), (\d+) GNSS fixes.*? in ([0-9.]+) s", text)
    if not m:
        return dict(flight_vehicle_s=None)
    frames, dropped, fixes, wall_s = int(m[1]), int(m[2]), int(m[3]), float(m[4])
    return dict(frames=frames, dropped=dropped, gnss_fixes=fixes, record_wall_s=wall_s, flight_vehicle_s=wall_s * speedup,
                camera_fps_wall_measured=frames / wall_s, camera_fps_vehicle_measured=frames / wall_s / speedup)


def plan_facts(plan: dict) -> dict:
    """Points, flight time, marker pixels and the predicted ROI error from plan.json."""
    roi_key, roi_px = predicted_roi_px(plan)
    return dict(points=plan.get("points"), flight_time_s=plan["flight"]["flight_time_s"],
                marker_px=[plan["marker"].get("px_min"), plan["marker"].get("px_max")], strategy=plan.get("strategy"),
                predicted_roi_key=roi_key, predicted_roi_px=roi_px,
                predicted_roi_ground_cm=plan.get("prediction", {}).get("ground_combined_cm", {}).get("rms"),
                roi_range_m=plan.get("roi", {}).get("range_m"), coverage_pct=plan.get("coverage", {}).get("pct"),
                n_flights=plan["flight"].get("n_flights", 1), sampling=plan.get("samples"),
                flights=[dict(file=f.get("file"), flight_time_s=f.get("flight_time_s"), points=f.get("points"))
                         for f in plan["flight"].get("flights") or []] or None,
                paper_far_prediction=plan.get("comparison"), warnings=plan.get("warnings"))


def run_facts(report: dict, detections_csv: Path) -> dict:
    """Points, frames and fixes per hold, and the marker's measured size, from calibrate's report.json and detections.csv."""
    windows = report.get("hover_windows", {}).get("windows", [])
    used = [w for w in windows if w.get("used")]

    def spread(key: str) -> list[float] | None:
        v = [w[key] for w in used if isinstance(w.get(key), (int, float))]
        return [min(v), float(np.median(v)), max(v)] if v else None

    size = []
    if detections_csv.is_file():
        import csv

        with detections_csv.open() as f:
            size = [float(r["size_px"]) for r in csv.DictReader(f) if r.get("size_px")]
    return dict(
        windows=len(windows),
        points_used=report.get("calibration", {}).get("n_points", len(used)),
        detections_per_hold=spread("n_detections"),
        fixes_per_hold=spread("n_fixes"),
        marker_px_measured=[min(size), max(size)] if size else None,
        frames=report.get("frames"),
        gnss_fix_rate_hz_run_clock=report.get("gnss", {}).get("fix_rate_hz"),
        legs=report.get("legs"),
    )


def calibration_facts(report: dict) -> dict:
    """What calibrate claims about itself: model, RMS, its own ground error at 15 m, warnings."""
    cal = report.get("calibration", {})
    return dict(
        model=cal.get("model"),
        rms_px=cal.get("rms_px"),
        claims=find_keys(report, ("ground", "15m", "roi", "valid")),
        warnings=report.get("warnings"),
    )


def _fmt(v: object, spec: str = ".2f") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, spec)


def table(rows: list[dict]) -> str:
    """The markdown table of the runs."""
    head = ("camera | plan | points used/planned | flight min plan (run) | cover % | marker px plan (seen) | model | "
            "focal % | pp px | pos cm | rot deg | ground 3-30 m RMS / p95 / max px | sampled RMS px | image RMS px | "
            "ground cm RMS / @5 / @15 / @30 | ROI px predicted / measured (ratio) | fps (vehicle) | det/hold | calibrate claims | "
            "flights: min plan (run), points used | each flight alone: ground 3-30 m RMS / max px")
    lines = ["| " + head + " |", "|" + " --- |" * (head.count("|") + 1)]
    for r in rows:
        p, run = r["plan"], r["run"]
        plan_label = str(r["strategy"]) + (f"/{r['sampling']}" if r["sampling"] else "")
        first = [r["camera"], plan_label]
        flight = f"{p['flight_time_s'] / 60:.1f} ({_fmt(run['flight_vehicle_s'] and run['flight_vehicle_s'] / 60, '.1f')})"
        marker = f"{_fmt(p['marker_px'][0], '.0f')}-{_fmt(p['marker_px'][1], '.0f')}"
        if r["comparison"] is None:
            lines.append("| " + " | ".join(first + [f"-/{p['points']}", flight, _fmt(p.get("coverage_pct"), ".0f"), marker,
                                                     f"calibrate refused: {r['error']}"]) + " |")
            continue
        each = run.get("flights") or []
        flights = f"{len(each)}: " + " + ".join(
            f"{_fmt(pf and pf['flight_time_s'] / 60, '.1f')} ({_fmt(f.get('flight_vehicle_s') and f['flight_vehicle_s'] / 60, '.1f')})"
            for f, pf in zip(each, p.get("flights") or [None] * len(each)))
        if len(each) > 1:
            flights += ", " + " + ".join(str(f.get("points_in_joint", "-")) for f in each) + " points"
        alone = "; ".join(f"{a['flight']}: {a['error']}" if a.get("error") else
                          f"{a['flight']}: {_fmt(a['ground']['rms_px'])} / {_fmt(a['ground']['max_px'], '.1f')}"
                          for a in r.get("flights_alone") or []) or "-"
        c, cal = r["comparison"], r["calibration"]
        at = {float(k): v for k, v in c["ground_error_cm_at"].items()}  # float keys, or str after a JSON round trip
        cl = cal["claims"]
        claims = ", ".join(f"{label} {cl[k]:.3g}" for k, label in (
            ("uncertainty.monte_carlo.ground_projection_error_px", "ground px"),
            ("uncertainty.at_15m.ground_position_error_cm", "15 m cm")) if k in cl) or "-"
        dph = run["detections_per_hold"]
        seen = run["marker_px_measured"]
        roi = r["comparison_roi_ground"]
        lines.append("| " + " | ".join(first + [
            f"{run['points_used']}/{p['points']}", flight, _fmt(p.get("coverage_pct"), ".0f"),
            marker + (f" ({seen[0]:.0f}-{seen[1]:.0f})" if seen else ""), str(cal["model"]),
            _fmt(c["focal_error_pct"]), _fmt(c["principal_point_error_px"], ".1f"), _fmt(c["position_error_cm"], ".1f"),
            _fmt(c["rotation_error_deg"], ".3f"),
            f"{_fmt(c['ground']['rms_px'])} / {_fmt(c['ground']['p95_px'])} / {_fmt(c['ground']['max_px'], '.1f')}",
            _fmt(c["sampled"]["rms_px"]) if c["sampled"] else "-", _fmt(c["image"]["rms_px"]),
            f"{_fmt(c['ground_error_cm_rms'], '.1f')} / {_fmt(at[5.0], '.1f')} / {_fmt(at[15.0], '.1f')} / {_fmt(at[30.0], '.1f')}",
            f"{_fmt(p['predicted_roi_px'])} / {_fmt(roi['px']['rms_px'])} ({_fmt(r['measured_over_predicted'])})",
            _fmt(run.get("camera_fps_vehicle_measured"), ".1f"),
            f"{dph[0]:.0f}-{dph[2]:.0f}" if dph else "-", f"{claims}; {len(cal['warnings'] or [])} warnings", flights, alone,
        ]) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--camera", nargs="+", choices=tuple(CAMERAS), default=["wide"], help="truth camera(s), run one after the other")
    parser.add_argument("--strategy", help="plan --strategy (only passed when given)")
    parser.add_argument("--sampling", help="plan --sampling hover|through|mixed (only passed when given)")
    parser.add_argument("--speedup", type=float,
                        help="vehicle seconds per wall second (default 2; 1 for 4k, whose frames take 30+ ms to render)")
    parser.add_argument("--camera-fps", type=float, default=10.0,
                        help="camera frames per vehicle second, told to plan as --fps (default 10; the sim camera serves this x speed-up)")
    parser.add_argument("--trials", type=int, default=200, help="calibrate's Monte-Carlo trials (default 200)")
    parser.add_argument("--out", type=Path, default=Path("/tmp/wholeview"), help="output folder (default /tmp/wholeview)")
    parser.add_argument("--reuse", action="store_true", help="skip the steps whose outputs are already in the run's folder")
    parser.add_argument("--label", help="sub-folder name of this run (default: the strategy/sampling)")
    args, extra = parser.parse_known_args()
    extra = [a for a in extra if a != "--"]
    label = args.label or "-".join(v for v in (args.strategy or "default", args.sampling) if v)
    rows = []
    speedup = args.speedup
    for name in args.camera:
        args.speedup = speedup or DEFAULT_SPEEDUP.get(name, 2.0)
        try:
            rows.append(run_one(name, args.out / f"{name}-{label}", args, extra, echo=lambda s: print(s, flush=True)))
        except DronecalError as exc:  # plan refused or the flight failed: say so, go on with the next camera
            print(f"[{name}] {exc}", flush=True)
            continue
        (args.out / f"wholeview-{label}.json").write_text(json.dumps(rows, indent=1, default=str))
        print(table(rows[-1:]), flush=True)
    print()
    print(table(rows))
    print(f"\nall numbers: {args.out / f'wholeview-{label}.json'}")


if __name__ == "__main__":
    main()
