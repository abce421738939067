"""A short plan flown end to end on ArduPilot's own firmware (ArduCopter 4.7 SITL), recorded and calibrated.

`dronecal-field plan` for the demo's camera, ArduCopter SITL at the plan's
take-off point, `dronecal-field sim camera` on the SITL's second link
(SERIAL1: it asks for its own telemetry, as 4.7 streams nothing unasked),
`dronecal-field fly --start` on the first (pre-flight, upload + read-back at
the firmware's storage resolution, arm in GUIDED, MISSION_START, record to
MCAP until the firmware lands and disarms), then `dronecal-field calibrate`
on the recording, scored against the simulator's truth camera
(`sim.compare`). Every command runs in its own process, inside the SITL's
private network namespace (tests/sitl.py).

The plan is the paper's metric grid cut to 3 minutes (`--strategy paper-far
--optimize --max-flight-time 3`: 17 holds of 3 s at two heights, 2.5 min of
vehicle time, about 40 s at 4x), made with the true focal length; it covers
part of the image, so the bands are those of a short flight, not the demo's.
"""

from __future__ import annotations

import json
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from dronecal_field.camerafile import read_camera, write_camera
from dronecal_field.cli import main
from dronecal_field.core.camera import Distortion
from dronecal_field.demo import MARKER, TRUTH, cli_argv, in_enu_frame_of, used_marker_points
from dronecal_field.geodesy import EnuOrigin
from dronecal_field.mavlink import missionfile as mf
from dronecal_field.runfile.reader import open_run
from dronecal_field.sim.compare import compare_cameras
from dronecal_field.sim.scene import make_truth_camera
from sitl import ArduCopterSitl, needs_sitl, wait_for_http
from test_mavlink_support import HOME

pytestmark = [needs_sitl, pytest.mark.slow, pytest.mark.timeout(720)]

SPEEDUP = 2.0  # vehicle seconds per wall second: a 3 s hold is 1.5 s of video at 15 fps (at 4x, 0.75 s, two CI workers left 12 of 17 holds and focal 2.95 % off)
CAMERA = dict(mount_height=4.0, azimuth=30.0, tilt=25.0)
# the 10 Hz receiver docs/fly.md asks for: GPS1_RATE_MS 100 (4.7's default is 200) and SITL's simulated u-blox at 10 Hz
SITL_PARAMS = {"GPS1_RATE_MS": 100, "SIM_GPS1_HZ": 10}


def _run(sitl: ArduCopterSitl, argv: list[str], log: Path, timeout_s: float) -> int:
    with log.open("w") as f:
        return subprocess.run(sitl.argv(argv), stdout=f, stderr=subprocess.STDOUT, timeout=timeout_s).returncode


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """Plan, fly on SITL with the sim camera, calibrate: the folder with every output and the logs."""
    out = tmp_path_factory.mktemp("sitl-flight")
    origin = EnuOrigin(*HOME)  # the pole's foot; SITL reports alt_ellipsoid = alt, so AMSL = ellipsoidal here
    truth = make_truth_camera(
        origin, CAMERA["mount_height"], CAMERA["azimuth"], CAMERA["tilt"], TRUTH["focal_px"], TRUTH["width"], TRUTH["height"],
        distortion=Distortion(k1=TRUTH["k1"], k2=TRUTH["k2"], p1=TRUTH["p1"], p2=TRUTH["p2"]),
    )
    write_camera(out / "truth.yaml", truth, comment="simulator ground truth (tests/test_sitl_flight.py)")
    plan_dir = out / "plan"
    assert main([
        "plan", "--out", str(plan_dir), f"--lat={HOME[0]}", f"--lon={HOME[1]}", "--ground-alt", str(HOME[2]),
        "--mount-height", str(CAMERA["mount_height"]), "--azimuth", str(CAMERA["azimuth"]), "--tilt", str(CAMERA["tilt"]),
        "--image-size", f"{TRUTH['width']}x{TRUTH['height']}", "--focal-px", str(TRUTH["focal_px"]), "--distortion", "medium",
        "--marker-size", str(MARKER["size_m"]), "--marker-dictionary", MARKER["dictionary"], "--marker-id", str(MARKER["marker_id"]),
        "--marker-offset", ",".join(str(v) for v in MARKER["offset_frd_m"]), "--hover", "3", "--strategy", "paper-far",
        "--optimize", "--roi-range", "3,15", "--max-flight-time", "3", "--trials", "20",
    ]) == 0  # fmt: skip
    mission_path = plan_dir / "mission.plan"  # one flight
    home = json.loads(mission_path.read_text())["mission"]["plannedHomePosition"]
    logs = out / "logs"
    logs.mkdir()
    with ArduCopterSitl.start(tuple(home), speedup=SPEEDUP, params=SITL_PARAMS) as sitl:
        http_port = 8554 if sitl.private_net else _free_tcp_port()
        video_url = f"http://127.0.0.1:{http_port}/stream.mjpg"
        camera = subprocess.Popen(sitl.argv(cli_argv(
            "sim", "camera", "--connect", sitl.second_url, "--camera", out / "truth.yaml", "--serve", video_url, "--fps", 15,
            "--noise-dn", 2, "--marker-dictionary", MARKER["dictionary"], "--marker-id", MARKER["marker_id"],
            "--marker-size", MARKER["size_m"], "--marker-offset", ",".join(str(v) for v in MARKER["offset_frd_m"]),
        )), stdout=(logs / "sim-camera.log").open("w"), stderr=subprocess.STDOUT)  # fmt: skip
        try:
            wait_for_http(sitl, http_port, camera)
            t0 = time.monotonic()
            fly_rc = _run(sitl, cli_argv(
                "fly", "--connect", sitl.gcs_url, "--mission", mission_path, "--video", video_url, "--out", out / "run.mcap",
                "--start", "--no-live", "--timeout-s", 300, "--ready-timeout", 120,
            ), logs / "fly.log", timeout_s=360)  # fmt: skip
            fly_s = time.monotonic() - t0
        finally:
            camera.terminate()
            camera.wait(timeout=10)
        sitl_log = sitl.log_tail(20)
    assert fly_rc == 0, (logs / "fly.log").read_text()[-3000:] + "\nSITL: " + sitl_log
    with (logs / "calibrate.log").open("w") as f:  # offline: no network needed
        calib_rc = subprocess.run(cli_argv("calibrate", out / "run.mcap", "--out", out / "calibration", "--trials", 50, "--min-fix", "rtk_fixed"),
                                  stdout=f, stderr=subprocess.STDOUT, timeout=300).returncode  # fmt: skip
    assert calib_rc == 0, (logs / "calibrate.log").read_text()[-3000:]
    return dict(out=out, mission=mf.read_mission(mission_path), truth=truth, fly_s=fly_s)


def _free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_recorded_flight_reached_every_waypoint_of_the_mission(flight):
    mission = flight["mission"]
    waypoints = {item.seq for item in mission.items[1:] if item.command == mf.CMD_NAV_WAYPOINT}
    with open_run(flight["out"] / "run.mcap") as run:
        reached = {int(fields["seq"]) for _name, _t, fields in run.iter_mavlink({"MISSION_ITEM_REACHED"})}
        armed = [bool(f["base_mode"] & 128) for _n, _t, f in run.iter_mavlink({"HEARTBEAT"}) if f.get("type") == 2]
        hovers = [e for e in run.iter_events() if e.type == "hover"]
        fix_types = {f.fix_type for f in run.iter_fixes()}
        frames = sum(1 for _ in run.iter_frames())
    assert waypoints <= reached, sorted(waypoints - reached)
    # the landing completed: ArduCopter 4.7 sends no MISSION_ITEM_REACHED for a NAV_LAND; it disarms on the ground
    assert mission.items[-1].command == mf.CMD_NAV_LAND and mission.items[-1].seq not in reached
    assert any(armed) and not armed[-1]
    assert len(hovers) == sum(1 for item in mission.items[1:] if item.hold_s > 0)
    assert fix_types == {"rtk_fixed"}, fix_types  # SITL's simulated GPS: RTK fixed throughout
    assert frames > 100


def test_calibration_of_the_firmware_flight_against_the_truth(flight):
    """Bands for this short flight (17 holds near the pole, 1.5 s of video each at 2x), from runs on the loaded
    CI machine: focal 0.08-0.51 %, camera 0.6-1.7 cm, ground over the plan's ROI (3-15 m) 1.7-4.0 px RMS,
    sampled volume 2.2-2.3 px RMS; the ground out to 30 m (2.1-3.5 px) lies outside what the flight sampled."""
    truth = flight["truth"]
    est = in_enu_frame_of(read_camera(flight["out"] / "calibration" / "camera.yaml"), truth.enu_origin)
    report = json.loads((flight["out"] / "calibration" / "report.json").read_text())
    sampled = used_marker_points(report, est.enu_origin, truth.enu_origin)
    roi = compare_cameras(truth, est, sampled_enu_m=sampled, ground_range_m=(3.0, 15.0), ground_step_m=0.5)
    wide = compare_cameras(truth, est, ground_range_m=(3.0, 30.0), ground_step_m=0.5)
    ti, ei = truth.intrinsics, est.intrinsics
    focal_err_pct = 100.0 * abs(0.5 * (ei.fx + ei.fy) - 0.5 * (ti.fx + ti.fy)) / (0.5 * (ti.fx + ti.fy))
    position_err_cm = 100.0 * float(np.linalg.norm(est.pose.position_world - truth.pose.position_world))
    print(f"SITL flight: fly {flight['fly_s']:.0f} s wall; focal {focal_err_pct:.2f} %, camera position {position_err_cm:.1f} cm, "
          f"ground 3-15 m {roi.ground.rms_px:.2f} px RMS, sampled volume {roi.sampled.rms_px:.2f} px ({len(sampled)} points), "
          f"ground 3-30 m {wide.ground.rms_px:.2f} px, calibration rms {report['calibration']['rms_px']:.2f} px")  # fmt: skip
    # This 3-minute, 17-hold plan checks the firmware chain, not the product's accuracy (test_end_to_end and the demo
    # do, on whole-view plans): over the CI runs seen it gave focal 0.08-2.95 %, camera 0.6-11.6 cm, ground 3-15 m 1.7-7.5 px,
    # the spread coming from how many holds a loaded machine's camera frames made usable (12-17).
    assert focal_err_pct < 5.0
    assert position_err_cm < 20.0
    # Beyond the 17 holds the error grows with the lens model's extrapolation (the plan itself predicts 74 px RMS over its
    # ROI for this point set): one CI run gave 17.9 px over 3-15 m. What must hold is honesty: either the ground is good,
    # or the report's predicted ground error covers the true one and its warnings send the user to the region of validity.
    predicted_px = report["uncertainty"]["monte_carlo"]["ground_projection_error_px"]
    print(f"SITL flight: ground predicted by the report {predicted_px:.2f} px RMS against the true {wide.ground.rms_px:.2f} px (3-30 m)")
    if roi.ground.rms_px >= 10.0:
        assert wide.ground.rms_px <= 1.5 * predicted_px
        assert any("region of validity covers" in w for w in report["warnings"]), report["warnings"]
    assert roi.sampled.rms_px < 4.0
    assert len(sampled) >= 10  # of the 17 holds
