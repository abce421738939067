"""The end-to-end demo: plan -> fly -> calibrate on the built-in simulators, no hardware.

Each step runs the real command in its own process over real sockets (UDP
MAVLink, HTTP MJPEG), exactly as a user would on a laptop in the field: the
SITL-style vehicle, the simulated camera watching it, ``plan`` for that
camera, ``fly --start``, ``calibrate``. The result is compared with the
simulator's truth.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dronecal_field.errors import DronecalError

# The demo camera: a traffic camera on a 4 m pole at ArduPilot SITL's CMAC site
# (SITL reports AMSL = ellipsoidal height; geoid separation 0).
SITE = dict(lat=-35.363261, lon=149.165230, ground_h=584.0, mount_height=4.0, azimuth=30.0, tilt=25.0)
TRUTH = dict(focal_px=1000.0, width=1280, height=720, k1=-0.22, k2=0.05, p1=-3e-4, p2=-1e-4)
MARKER = dict(dictionary="DICT_4X4_50", marker_id=0, size_m=0.40, offset_frd_m=(0.10, 0.0, 0.05))


@dataclass(frozen=True)
class DemoResult:
    """What the demo measured: calibrated camera against truth."""

    out_dir: Path
    report_path: Path
    focal_error_pct: float
    principal_point_error_px: float
    position_error_cm: float
    principal_point_sigma_px: float
    rms_px: float
    projection_error_px: float
    sampled_projection_error_px: float
    elapsed_s: float
    ground_error_px: float = float("nan")  # RMS over the visible ground 3-30 m (sim.compare)
    ground_error_max_px: float = float("nan")
    log_problems: tuple[str, ...] = ()  # what the steps' own logs ask for (fly's "verdict: re-fly ...", calibrate's warnings)

    @property
    def camera_path(self) -> Path:
        return self.report_path.parent / "camera.yaml"

    @property
    def met_targets(self) -> bool:
        """The demo's targets: focal within 1 %, camera within 5 cm, ground 3-30 m under 1 px RMS."""
        return self.focal_error_pct < 1.0 and self.position_error_cm < 5.0 and self.ground_error_px < 1.0


def log_problems(fly_log: Path, calibrate_log: Path) -> tuple[str, ...]:
    """What the steps' own logs say is wrong, so the demo's last line never contradicts them.

    ``fly``'s live verdict (``verdict: ...``) unless it is ``good``, and ``calibrate``'s
    ``warning:`` lines and a calibration from none of the waypoints.
    """
    import re

    problems: list[str] = []
    fly = fly_log.read_text(errors="replace").splitlines() if fly_log.is_file() else []
    verdicts = [line.split("verdict:", 1)[1].strip() for line in fly if line.startswith("verdict:")]
    if verdicts and not verdicts[-1].startswith("good"):
        problems.append(f"fly: {verdicts[-1]}")
    cal = calibrate_log.read_text(errors="replace").splitlines() if calibrate_log.is_file() else []
    for line in cal:
        m = re.match(r"calibrated .*?: (\d+) of (\d+) waypoints", line)
        if m and int(m.group(1)) == 0 and int(m.group(2)) > 0 and "pairs on" not in line:
            problems.append(f"calibrate: {line.strip()}")
        if line.strip().startswith("warning:"):
            problems.append(f"calibrate: {line.strip()}")
    return tuple(problems)


def _free_port(kind: int = socket.SOCK_DGRAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def cli_argv(*args: object) -> list[str]:
    """argv running ``dronecal-field ARGS`` in a fresh process of this interpreter."""
    return [sys.executable, "-m", "dronecal_field", *[str(a) for a in args]]


def _die_with_parent() -> None:
    """In the child, before exec: Linux sends it SIGTERM if the demo dies (even by SIGKILL), so no simulator runs on."""
    try:
        import ctypes

        ctypes.CDLL(None).prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    except Exception:  # noqa: BLE001 - not Linux: the demo's own clean-up still stops the group
        pass


def _start(argv: list[str], log_file) -> subprocess.Popen:
    """A child in a process group of its own, so that stopping it stops everything it started."""
    return subprocess.Popen(argv, stdout=log_file, stderr=subprocess.STDOUT, start_new_session=True,
                            preexec_fn=_die_with_parent if sys.platform.startswith("linux") else None)


def run_step(step: str, argv: list[str], log: Path, timeout_s: float) -> None:
    """Run one command to completion, its output into ``log``; DronecalError naming the step if it fails.

    The demo stopped meanwhile (Ctrl-C, SIGTERM, SIGHUP) stops the step as Ctrl-C would (``fly``
    finalises its run), then its whole process group.
    """
    with log.open("w") as f:
        proc = _start(argv, f)
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            _stop(proc, grace_s=30.0)
            raise DronecalError(f"demo step '{step}' did not finish within {timeout_s:.0f} s (stopped): see {log}") from None
        except BaseException:
            _stop(proc, grace_s=30.0)
            raise
    if proc.returncode != 0:
        tail = log.read_text().strip().splitlines()[-1:] or ["(no output)"]
        raise DronecalError(f"demo step '{step}' failed ({tail[0]}): see {log}")


def _wait_for_tcp(port: int, proc: subprocess.Popen, log: Path, timeout_s: float = 60.0) -> None:
    """Wait until a simulator accepts connections on ``port`` (it builds its ray map first)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise DronecalError(f"the simulated camera exited early (code {proc.returncode}): see {log}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.2)
    raise DronecalError(f"the simulated camera did not open port {port} within {timeout_s:.0f} s: see {log}")


def _stop(proc: subprocess.Popen, grace_s: float = 10.0) -> None:
    """SIGINT the child's process group (as Ctrl-C); SIGKILL the group after ``grace_s``; never leaves one behind."""

    def signal_group(sig: int) -> None:
        try:
            os.killpg(proc.pid, sig)
        except (ProcessLookupError, PermissionError):
            pass

    if proc.poll() is None:
        signal_group(signal.SIGINT)
        try:
            proc.wait(timeout=grace_s)
        except subprocess.TimeoutExpired:
            pass
    signal_group(signal.SIGKILL)  # whatever the child started and left running
    if proc.poll() is None:
        proc.wait()


@dataclass(frozen=True, eq=False)
class Simulators:
    """The running simulated vehicle and camera (each its own process) and where to reach them."""

    vehicle_url: str  # udp:127.0.0.1:PORT, what `fly --connect` takes
    video_url: str  # http://127.0.0.1:PORT/stream.mjpg, what `fly --video` takes
    vehicle: subprocess.Popen
    camera: subprocess.Popen
    camera_log: Path

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        """Block until the camera serves (it builds its ray map first: seconds at 4K)."""
        _wait_for_tcp(int(self.video_url.rsplit(":", 1)[1].split("/")[0]), self.camera, self.camera_log, timeout_s)

    def stop(self) -> None:
        """SIGINT both (as Ctrl-C), camera first; kill what does not stop within 10 s."""
        _stop(self.camera)
        _stop(self.vehicle)


def start_simulators(
    truth_path: Path,
    home: tuple[float, float, float],
    logs: Path,
    speedup: float,
    fps: float,
    marker: dict,
    latency_s: float = 0.0,
    noise_px: float = 2.0,
) -> Simulators:
    """Start ``sim vehicle`` (home LAT,LON,H, vehicle clock ``speedup`` x wall) and ``sim camera`` on free loopback ports.

    Parameters
    ----------
    truth_path : the truth camera.yaml the simulated camera renders through.
    home : take-off point, degrees, degrees, metres (the plan's plannedHomePosition).
    logs : folder for sim-vehicle.log and sim-camera.log.
    speedup : vehicle seconds per wall second.
    fps : camera frames per wall second.
    marker : dictionary, marker_id, size_m, offset_frd_m (as ``MARKER``).
    latency_s : the camera's frames show the vehicle this late, seconds (host clock).
    noise_px : the camera's pixel noise, standard deviation in grey levels.
    """
    vehicle_port, camera_link_port, http_port = _free_port(), _free_port(), _free_port(socket.SOCK_STREAM)
    video_url = f"http://127.0.0.1:{http_port}/stream.mjpg"
    home_lat, home_lon, home_alt = home
    vehicle = _start(cli_argv(
        "sim", "vehicle", "--listen", f"udp:127.0.0.1:{vehicle_port}", "--out", f"udp:127.0.0.1:{camera_link_port}",
        "--home", f"{home_lat},{home_lon},{home_alt}", "--speedup", speedup,
        "--gps-rate-ms", 100,  # GPS_RATE_MS 100: the 10 Hz RTK setting docs/fly.md asks for (ArduPilot's default is 200)
    ), (logs / "sim-vehicle.log").open("w"))
    camera = _start(cli_argv(
        "sim", "camera", "--connect", f"udpin:127.0.0.1:{camera_link_port}", "--camera", truth_path, "--serve", video_url,
        "--fps", fps, "--latency-s", latency_s, "--noise-dn", noise_px, "--marker-dictionary", marker["dictionary"],
        "--marker-id", marker["marker_id"], "--marker-size", marker["size_m"],
        "--marker-offset", ",".join(str(v) for v in marker["offset_frd_m"]),
    ), (logs / "sim-camera.log").open("w"))
    return Simulators(vehicle_url=f"udp:127.0.0.1:{vehicle_port}", video_url=video_url, vehicle=vehicle, camera=camera,
                      camera_log=logs / "sim-camera.log")


def used_marker_points(
    report: dict, report_origin: tuple[float, float, float] | None, origin: tuple[float, float, float] | None
) -> np.ndarray:
    """(N, 3) ENU metres at ``origin``: the marker positions calibrate used (report.json's hover windows, and the
    ends of each fly-through leg's used pairs).

    report.json gives them in the calibration's ENU frame (``report_origin``,
    the calibrated camera's ``enu_origin``); they are moved to ``origin`` (the
    truth's) when the two differ.
    """
    from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic, geodetic_to_enu

    held = [w["marker_enu_m"] for w in report["hover_windows"]["windows"] if w.get("used")]
    on_legs = [x for leg in (report.get("legs") or {}).get("legs", []) for x in leg.get("used_marker_enu_m", [])]
    sampled = np.array(held + on_legs, float).reshape(-1, 3)
    if report_origin is not None and origin is not None and not np.allclose(report_origin, origin, atol=1e-10):
        llh = enu_to_geodetic(sampled, EnuOrigin(*report_origin))
        sampled = geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2], EnuOrigin(*origin))
    return sampled


def run_demo(
    out_dir: Path, speedup: float = 3.0, trials: int = 500, fps: float = 15.0, echo=print, latency_s: float = 0.0,
    plan_args: tuple[str, ...] = (),
) -> DemoResult:
    """Run the whole chain into ``out_dir``; ``echo`` receives progress lines.

    ``latency_s`` (seconds, host clock) makes the simulated camera's frames show
    the vehicle that long late (``sim camera --latency-s``), as a real IP camera's do.
    ``plan_args`` go to ``plan`` as given (e.g. ``("--max-flight-time", "7")``).
    """
    from dronecal_field.camerafile import read_camera, write_camera
    from dronecal_field.core.camera import Distortion
    from dronecal_field.geodesy import EnuOrigin
    from dronecal_field.sim.scene import make_truth_camera

    t0 = time.monotonic()
    out_dir.mkdir(parents=True, exist_ok=True)
    logs = out_dir / "logs"
    logs.mkdir(exist_ok=True)

    origin = EnuOrigin(SITE["lat"], SITE["lon"], SITE["ground_h"])
    truth = make_truth_camera(
        origin, SITE["mount_height"], SITE["azimuth"], SITE["tilt"], TRUTH["focal_px"], TRUTH["width"], TRUTH["height"],
        distortion=Distortion(k1=TRUTH["k1"], k2=TRUTH["k2"], p1=TRUTH["p1"], p2=TRUTH["p2"]),
    )
    truth_path = out_dir / "truth.yaml"
    write_camera(truth_path, truth, comment="simulator ground truth (dronecal-field demo)")

    echo("1/4 plan: mission for the simulated camera (rough guess: focal -5%, medium distortion)")
    plan_dir = out_dir / "plan"
    run_step("plan", cli_argv(
        "plan", "--out", plan_dir, f"--lat={SITE['lat']}", f"--lon={SITE['lon']}", "--ground-alt", SITE["ground_h"],
        "--mount-height", SITE["mount_height"], "--azimuth", SITE["azimuth"], "--tilt", SITE["tilt"],
        "--image-size", f"{TRUTH['width']}x{TRUTH['height']}", "--focal-px", TRUTH["focal_px"] * 0.95,
        "--distortion", "medium", "--marker-size", MARKER["size_m"], "--marker-dictionary", MARKER["dictionary"],
        "--marker-id", MARKER["marker_id"], "--marker-offset", ",".join(str(v) for v in MARKER["offset_frd_m"]),
        "--hover", "3", "--trials", "200",
        # the default guess band: it covers the demo's 5 % focal guess error, and since its points are screened by each
        # factor alone (not its extreme corners) it keeps the image covered (99 % of the ROI against 100 % without a band;
        # the old all-corner screen left one plan 44 % of the image and 5.2 px on the ground)
        *plan_args,
    ), logs / "plan.log", timeout_s=300)
    plan = json.loads((plan_dir / "mission.plan").read_text())
    home_lat, home_lon, home_alt = plan["mission"]["plannedHomePosition"]
    echo(f"    {len(plan['mission']['items'])} mission items; take-off point {home_lat:.7f}, {home_lon:.7f}")

    from dronecal_field.commands.fly import free_run_path

    # fly never writes over a recorded flight: a second demo into the same folder records run-2.mcap
    run_path = out_dir / "run.mcap"
    if run_path.exists() or run_path.with_suffix(".tlog").exists():
        run_path = free_run_path(run_path)
    sims = start_simulators(truth_path, (home_lat, home_lon, home_alt), logs, speedup, fps, MARKER, latency_s=latency_s)
    try:
        echo(f"2/4 simulators: vehicle on {sims.vehicle_url} (speed-up {speedup:g}x), camera at {sims.video_url}")
        sims.wait_ready()
        echo("3/4 fly --start: upload, verify, arm in GUIDED, MISSION_START, record (Ctrl-C stops cleanly)")
        run_step("fly", cli_argv(
            "fly", "--connect", sims.vehicle_url, "--mission", plan_dir / "mission.plan",
            "--video", sims.video_url, "--out", run_path, "--start", "--timeout-s", "900",
        ), logs / "fly.log", timeout_s=1200)
    finally:
        sims.stop()

    echo("4/4 calibrate: hover windows, ArUco, ENU, calibration, Monte-Carlo confidence")
    calib_dir = out_dir / ("calibration" + run_path.stem[len("run"):])
    # calibrate's defaults as a user runs them (a sped-up simulator's short holds decode every frame)
    run_step("calibrate", cli_argv("calibrate", run_path, "--out", calib_dir, "--trials", trials, "--min-fix", "rtk_fixed"),
             logs / "calibrate.log", timeout_s=600)

    est = in_enu_frame_of(read_camera(calib_dir / "camera.yaml"), truth.enu_origin)
    report = json.loads((calib_dir / "report.json").read_text())
    ti, ei = truth.intrinsics, est.intrinsics
    # Compare in the truth's ENU frame (both files use ENU at the pole's foot).
    proj = _projection_error_px(truth, est)
    sampled = used_marker_points(report, est.enu_origin, truth.enu_origin)
    sampled_proj = float(np.sqrt(np.mean(np.sum((truth.project(sampled) - est.project(sampled)) ** 2, axis=1))))
    std = report.get("calibration", {}).get("parameter_std_from_residuals", {})
    from dronecal_field.sim.compare import compare_cameras

    ground = compare_cameras(truth, est, ground_step_m=0.5).ground
    return DemoResult(
        ground_error_px=ground.rms_px,
        ground_error_max_px=ground.max_px,
        out_dir=out_dir,
        report_path=calib_dir / "report.html",
        focal_error_pct=100.0 * abs(0.5 * (ei.fx + ei.fy) - 0.5 * (ti.fx + ti.fy)) / (0.5 * (ti.fx + ti.fy)),
        principal_point_error_px=float(np.hypot(ei.cx - ti.cx, ei.cy - ti.cy)),
        principal_point_sigma_px=float(np.hypot(std.get("cx", np.nan), std.get("cy", np.nan))),
        position_error_cm=100.0 * float(np.linalg.norm(est.pose.position_world - truth.pose.position_world)),
        rms_px=float(report.get("calibration", {}).get("rms_px", float("nan"))),
        projection_error_px=proj,
        sampled_projection_error_px=sampled_proj,
        elapsed_s=time.monotonic() - t0,
        log_problems=log_problems(logs / "fly.log", logs / "calibrate.log"),
    )


def in_enu_frame_of(camera, origin: tuple[float, float, float] | None):
    """``camera`` re-expressed in the ENU frame at ``origin`` (position exact; the few-metre frame tilt is below 1e-6 rad)."""
    from dronecal_field.core.camera import CameraPose
    from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic, geodetic_to_enu

    if origin is None or camera.enu_origin is None or np.allclose(camera.enu_origin, origin, rtol=0.0, atol=1e-10):
        return camera
    llh = enu_to_geodetic(camera.pose.position_world[None], EnuOrigin(*camera.enu_origin))[0]
    pos = geodetic_to_enu(llh[0], llh[1], llh[2], EnuOrigin(*origin))[0]
    return camera.with_(pose=CameraPose.from_position(camera.pose.R_cam_from_world, pos), enu_origin=tuple(origin))


def _projection_error_px(truth, est) -> float:
    """RMS pixel distance between the two cameras' projections of a volume 4-12 m in front of the truth."""
    from dronecal_field.core.synthetic import visible

    R = truth.pose.R_cam_from_world
    c = truth.pose.position_world
    rng = np.random.default_rng(0)
    depth = rng.uniform(4.0, 12.0, 4000)
    uv = rng.uniform([0, 0], [truth.width, truth.height], (4000, 2))
    x = (uv[:, 0] - truth.intrinsics.cx) / truth.intrinsics.fx
    y = (uv[:, 1] - truth.intrinsics.cy) / truth.intrinsics.fy
    pts = c + (np.stack([x, y, np.ones_like(x)], 1) * depth[:, None]) @ R
    pts = pts[(pts[:, 2] > 0.3) & visible(truth, pts, 5.0)]
    return float(np.sqrt(np.mean(np.sum((truth.project(pts) - est.project(pts)) ** 2, axis=1))))
