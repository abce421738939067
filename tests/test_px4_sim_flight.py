"""`fly --start` on `sim vehicle --autopilot px4` with `sim camera`, then `calibrate`: PX4's chain without the SITL.

The same plan as tests/test_px4_sitl.py (the demo's camera; saved in
tests/data/px4_sim_mission.plan), cut to 10 of its 17 holds held 6 s, flown
at 3x on the simulated PX4 (its modes, mission from seq 0, MISSION_START,
repeated reached messages, GPS time since boot).
The CI flight uses the `--gnss rtk` receiver, so the calibration is held to
RTK bands; :func:`fly_px4_sim` also flies with the SITL's 3D fix (0.2 m /
0.5 m noise, h_acc 0.9 m) for benchmarks/px4_gnss_calibration.py.
"""

from __future__ import annotations

import json
import socket
import subprocess
import time
from pathlib import Path

import pytest

from dronecal_field.camerafile import read_camera, write_camera
from dronecal_field.cli import main
from dronecal_field.core.camera import Distortion
from dronecal_field.demo import MARKER, TRUTH, cli_argv, in_enu_frame_of, used_marker_points
from dronecal_field.geodesy import EnuOrigin
from dronecal_field.sim.compare import compare_cameras
from dronecal_field.sim.scene import make_truth_camera

HOME = (-35.363261, 149.165230, 584.0)
CAMERA = dict(mount_height=4.0, azimuth=30.0, tilt=25.0)


def _free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


SAVED_MISSION = Path(__file__).parent / "data" / "px4_sim_mission.plan"  # plan_for_px4(out, saved=False)'s mission.plan, kept: planning costs minutes on a busy machine


def plan_for_px4(out: Path, max_flight_min: float = 3.0, *, saved: bool = True) -> Path:
    """The demo camera's truth (out/truth.yaml) and a short plan for it: the mission.plan path (:data:`SAVED_MISSION` unless ``saved`` is False)."""
    truth = make_truth_camera(
        EnuOrigin(*HOME), CAMERA["mount_height"], CAMERA["azimuth"], CAMERA["tilt"], TRUTH["focal_px"], TRUTH["width"], TRUTH["height"],
        distortion=Distortion(k1=TRUTH["k1"], k2=TRUTH["k2"], p1=TRUTH["p1"], p2=TRUTH["p2"]),
    )  # fmt: skip
    write_camera(out / "truth.yaml", truth, comment="simulator ground truth (tests/test_px4_sim_flight.py)")
    if saved and SAVED_MISSION.is_file():
        return SAVED_MISSION
    plan_dir = out / "plan"
    assert main([
        "plan", "--out", str(plan_dir), f"--lat={HOME[0]}", f"--lon={HOME[1]}", "--ground-alt", str(HOME[2]),
        "--mount-height", str(CAMERA["mount_height"]), "--azimuth", str(CAMERA["azimuth"]), "--tilt", str(CAMERA["tilt"]),
        "--image-size", f"{TRUTH['width']}x{TRUTH['height']}", "--focal-px", str(TRUTH["focal_px"]), "--distortion", "medium",
        "--marker-size", str(MARKER["size_m"]), "--marker-dictionary", MARKER["dictionary"], "--marker-id", str(MARKER["marker_id"]),
        "--marker-offset", ",".join(str(v) for v in MARKER["offset_frd_m"]), "--hover", "3", "--strategy", "paper-far",
        "--optimize", "--roi-range", "3,15", "--max-flight-time", str(max_flight_min), "--trials", "20",
    ]) == 0  # fmt: skip
    path = plan_dir / "mission.plan"
    return path if path.is_file() else plan_dir / "mission-1.plan"


def short_mission(out: Path, source: Path = SAVED_MISSION, *, keep: tuple[int, ...] = (4, 6, 8, 9, 11, 13, 15, 17, 19, 20), hold_s: float = 6.0) -> Path:
    """``source`` cut to the holds ``keep`` (file seqs; 10 of its 17, every height), each held ``hold_s``: out/short.plan.

    The simulated camera gets 3-8 frames a second on a busy machine (load
    25-45): at 3x a 6 s hold leaves it 5-13 frames after the settle; 5 s
    holds at 4x left 1-2 at load 45 (calibrate then drops the window).
    """
    from dataclasses import replace

    from dronecal_field.mavlink import missionfile as mf

    mission = mf.read_mission(source)
    items = [it for it in mission.items if not (it.command == mf.CMD_NAV_WAYPOINT and it.hold_s > 0 and it.seq not in keep)]
    items = [replace(it, seq=i, p1=hold_s if (it.command == mf.CMD_NAV_WAYPOINT and it.hold_s > 0) else it.p1) for i, it in enumerate(items)]
    path = out / "short.plan"
    path.write_text(mf.to_qgc_plan(replace(mission, items=tuple(items))))
    return path


def fly_px4_sim(out: Path, mission_path: Path, *, gnss: str = "rtk", speedup: float = 3.0, seed: int = 0, trials: int = 30) -> dict:
    """sim vehicle --autopilot px4 (--gnss ``gnss``) + sim camera + fly --start + calibrate into ``out``; logs and outputs."""
    logs = out / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    home = json.loads(mission_path.read_text())["mission"]["plannedHomePosition"]
    vport, cport, hport = _free_port(), _free_port(), _free_port(socket.SOCK_STREAM)
    video_url = f"http://127.0.0.1:{hport}/stream.mjpg"
    vehicle = subprocess.Popen(cli_argv(
        "sim", "vehicle", "--autopilot", "px4", "--gnss", gnss, "--listen", f"udp:127.0.0.1:{vport}", "--out", f"udp:127.0.0.1:{cport}",
        "--home", ",".join(str(v) for v in home), "--speedup", speedup, "--seed", seed,
    ), stdout=(logs / "sim-vehicle.log").open("w"), stderr=subprocess.STDOUT)  # fmt: skip
    camera = subprocess.Popen(cli_argv(
        "sim", "camera", "--connect", f"udpin:127.0.0.1:{cport}", "--camera", out / "truth.yaml", "--serve", video_url, "--fps", 15,
        "--noise-dn", 2, "--marker-dictionary", MARKER["dictionary"], "--marker-id", MARKER["marker_id"],
        "--marker-size", MARKER["size_m"], "--marker-offset", ",".join(str(v) for v in MARKER["offset_frd_m"]),
    ), stdout=(logs / "sim-camera.log").open("w"), stderr=subprocess.STDOUT)  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            assert camera.poll() is None, (logs / "sim-camera.log").read_text()[-2000:]
            try:
                socket.create_connection(("127.0.0.1", hport), timeout=0.5).close()
                break
            except OSError:
                time.sleep(0.2)
        min_fix = "rtk_fixed" if gnss == "rtk" else "3d"
        with (logs / "fly.log").open("w") as f:
            fly_rc = subprocess.run(cli_argv(
                "fly", "--connect", f"udp:127.0.0.1:{vport}", "--mission", mission_path, "--video", video_url, "--out", out / "run.mcap",
                "--start", "--no-live", "--min-fix", min_fix, "--timeout-s", 300, "--ready-timeout", 120,
                "--marker-size", MARKER["size_m"], "--marker-dictionary", MARKER["dictionary"], "--marker-id", MARKER["marker_id"],
                "--marker-offset", ",".join(str(v) for v in MARKER["offset_frd_m"]),
            ), stdout=f, stderr=subprocess.STDOUT, timeout=400).returncode  # fmt: skip
    finally:
        for proc in (camera, vehicle):
            proc.terminate()
            proc.wait(timeout=10)
    assert fly_rc == 0, (logs / "fly.log").read_text()[-3000:]
    with (logs / "calibrate.log").open("w") as f:
        # --settle-s on the run clock: the 1 s a hold settles in vehicle time is 1/speedup of a wall second
        calib_rc = subprocess.run(cli_argv("calibrate", out / "run.mcap", "--out", out / "calibration", "--trials", trials, "--min-fix", min_fix,
                                           "--settle-s", f"{1.0 / speedup:.3f}"),
                                  stdout=f, stderr=subprocess.STDOUT, timeout=400).returncode  # fmt: skip
    assert calib_rc == 0, (logs / "calibrate.log").read_text()[-3000:]
    return dict(out=out, fly_log=(logs / "fly.log").read_text(), calibrate_log=(logs / "calibrate.log").read_text())


def score(out: Path) -> dict:
    """The calibration in ``out`` against out/truth.yaml: true errors and the report's own confidence."""
    truth = read_camera(out / "truth.yaml")
    est = in_enu_frame_of(read_camera(out / "calibration" / "camera.yaml"), truth.enu_origin)
    report = json.loads((out / "calibration" / "report.json").read_text())
    sampled = used_marker_points(report, est.enu_origin, truth.enu_origin)
    cmp = compare_cameras(truth, est, sampled_enu_m=sampled, ground_range_m=(3.0, 30.0), ground_step_m=0.5)
    mc = report["uncertainty"]["monte_carlo"]
    return dict(
        focal_pct=cmp.focal_error_pct, focal_px=cmp.focal_error_px, focal_std_px=mc["param_std"]["fx"],
        position_cm=cmp.position_error_cm, ground_px=cmp.ground.rms_px,
        ground_15m_cm=cmp.ground_error_cm_at.get(15.0), ground_15m_std_cm=mc["ground_error_15m_cm"], ground_15m_p95_cm=mc["ground_error_15m_cm_p95"],
        holds_used=report["hover_windows"]["used"], fix_types=report["gnss"]["fix_types"], report=report, compare=cmp,
    )  # fmt: skip


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_fly_start_on_the_simulated_px4_records_and_calibrates(tmp_path):
    plan_for_px4(tmp_path)
    mission_path = short_mission(tmp_path)
    result = fly_px4_sim(tmp_path, mission_path, gnss="rtk", speedup=3.0, trials=10)
    log = result["fly_log"]
    assert "PX4 quadrotor" in log and "uploaded and read back identical" in log, log[-2000:]
    s = score(tmp_path)
    print(f"simulated PX4 (RTK): focal {s['focal_pct']:.2f} % (std {s['focal_std_px']:.1f} px, true {s['focal_px']:.1f} px), "
          f"camera {s['position_cm']:.1f} cm, ground at 15 m {s['ground_15m_cm']} cm (report {s['ground_15m_std_cm']:.1f}), "
          f"holds used {s['holds_used']}")  # fmt: skip
    from dronecal_field.mavlink import missionfile as mf

    holds = sum(1 for it in mf.read_mission(mission_path).items[1:] if it.hold_s > 0)
    assert s["report"]["hover_windows"]["count"] == holds  # one hover per hold although PX4 repeats MISSION_ITEM_REACHED
    assert s["holds_used"] >= 6  # calibrate's minimum; a loaded machine's camera may leave a hold too few frames
    assert set(s["fix_types"]) == {"rtk_fixed"}
    assert any("RTK fixed" in q for q in s["report"]["gnss"]["quality"])  # the report says what the receiver's accuracy means
    # 10 holds at 1-3.4 m cannot separate the medium distortion (calibrate fits none): focal 4.9 % off, camera 4 cm on an idle
    # machine; under two CPU hogs the starved camera moved it to 9.3 % / 21.8 cm with a reported focal std of 192.7 px against
    # 93 px true. So: calibrated (a gross bound), and never tighter than the truth (the honesty the SITL tests check)
    assert abs(s["focal_pct"]) < 20.0 and s["position_cm"] < 60.0
    assert s["focal_std_px"] >= 0.5 * abs(s["focal_px"])
    if s["ground_15m_cm"] is not None:  # the report's confidence is not much tighter than the truth (its focal std, with no
        assert s["ground_15m_p95_cm"] >= 0.5 * s["ground_15m_cm"]  # distortion fitted, was 19 px against 61 px true: printed above)
