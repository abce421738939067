"""The simulated camera end to end: real MAVLink over UDP in, real MJPEG over HTTP out.

A pymavlink MAVLink 2 encoder writes GLOBAL_POSITION_INT, ATTITUDE and
GPS_RAW_INT to the camera's UDP socket; HTTP clients read the multipart
stream, decode the JPEGs and find the marker with OpenCV's ArUco detector,
where the truth camera projects it.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecal_field.camerafile import read_camera
from dronecal_field.core.camera import Camera, Distortion
from dronecal_field.errors import InputError
from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic, geodetic_to_enu
from dronecal_field.sim.camera import BOUNDARY, SimCamera, open_mavlink_listener, parse_serve_url
from dronecal_field.sim.camera_track import PoseTrack
from dronecal_field.sim.scene import MarkerSpec, make_truth_camera, marker_corners_world, yaw_towards

GEOID_SEP_M = 25.0  # ellipsoidal minus MSL height the sender reports in GPS_RAW_INT
ORIGIN = (-35.363261, 149.165230, 584.0 + GEOID_SEP_M)  # pole foot, ellipsoidal height
OFFSET = (0.1, 0.0, 0.1)
REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------- pose track (pure)


def test_track_interpolates_position_and_wraps_yaw() -> None:
    track = PoseTrack()
    assert track.pose_at(0) is None
    track.add_position(1_000_000_000, -35.0, 149.0, 600.0)
    track.add_position(2_000_000_000, -35.0 + 1e-5, 149.0, 610.0)
    track.add_attitude(1_000_000_000, 0.0, 0.0, np.radians(170.0))
    track.add_attitude(2_000_000_000, 0.1, 0.0, np.radians(-170.0))
    p = track.pose_at(1_250_000_000)
    assert p.lat_deg == pytest.approx(-35.0 + 0.25e-5, abs=1e-12)
    assert p.h_m == pytest.approx(602.5)
    assert p.roll_rad == pytest.approx(0.025)
    # 170 -> -170 deg goes the short way through 180.
    assert np.degrees(p.yaw_rad) == pytest.approx(175.0)
    assert track.pose_at(0).h_m == 600.0  # before the first sample: the first sample
    assert track.pose_at(5_000_000_000).h_m == 610.0  # after the last: hold it
    assert p.altitude_datum == "msl"


def test_track_applies_geoid_separation_and_forgets_old_samples() -> None:
    track = PoseTrack(horizon_s=2.0)
    for k in range(50):
        track.add_position(k * 100_000_000, -35.0, 149.0, 584.0)
    assert track.n_positions == 21  # the last 2 s
    track.add_gps_raw(alt_msl_m=584.2, alt_ellipsoid_m=None)  # no ellipsoid height: nothing learned
    assert track.geoid_separation_m is None
    track.add_gps_raw(alt_msl_m=584.2, alt_ellipsoid_m=604.2)
    p = track.pose_at(4_900_000_000)
    assert p.h_m == pytest.approx(604.0)
    assert p.altitude_datum == "ellipsoid"
    as_reported = PoseTrack(use_ellipsoid=False)
    as_reported.add_position(0, -35.0, 149.0, 584.0)
    as_reported.add_gps_raw(alt_msl_m=584.0, alt_ellipsoid_m=604.0)
    assert as_reported.pose_at(0).h_m == 584.0


def test_addresses_need_explicit_schemes() -> None:
    assert parse_serve_url("http://127.0.0.1:0/stream.mjpg").port == 0
    assert parse_serve_url("http://localhost:8554").path == "/stream.mjpg"
    rtsp = parse_serve_url("rtsp://127.0.0.1:8554/x")
    assert (rtsp.scheme, rtsp.port, rtsp.path) == ("rtsp", 8554, "/x") and parse_serve_url("rtsp://127.0.0.1").path == "/cam"
    with pytest.raises(InputError, match="http:// or rtsp://"):
        parse_serve_url("rtsps://127.0.0.1:8554/x")
    with pytest.raises(InputError, match="explicit scheme"):
        open_mavlink_listener("127.0.0.1:14551")
    with pytest.raises(InputError, match="explicit scheme"):
        open_mavlink_listener("/tmp/some.tlog")


# ---------------------------------------------------------------- live: MAVLink in, MJPEG out


class MavlinkSender:
    """A vehicle stand-in: MAVLink 2 over a real UDP socket to the camera."""

    def __init__(self, address: tuple[str, int], origin: EnuOrigin) -> None:
        from pymavlink.dialects.v20 import ardupilotmega as mav2

        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.address = address
        self.origin = origin
        self.mav = mav2.MAVLink(self, srcSystem=1, srcComponent=1)
        self.sent = 0

    def write(self, data: bytes) -> None:  # the file-like the encoder writes to
        self.sock.sendto(data, self.address)

    def send_pose(self, antenna_enu: np.ndarray, yaw_rad: float) -> tuple[float, float, float]:
        """Send one position/attitude/fix; returns the (lat, lon, h_ellipsoid) the wire carries."""
        lat, lon, h = enu_to_geodetic(antenna_enu, self.origin)[0]
        lat_i, lon_i = int(round(lat * 1e7)), int(round(lon * 1e7))
        h_i = int(round(h * 1000))
        msl_i = h_i - int(GEOID_SEP_M * 1000)
        self.mav.global_position_int_send(0, lat_i, lon_i, msl_i, 2000, 0, 0, 0, int(np.degrees(yaw_rad) % 360 * 100))
        self.mav.attitude_send(0, 0.0, 0.0, yaw_rad, 0.0, 0.0, 0.0)
        self.mav.gps_raw_int_send(0, 6, lat_i, lon_i, msl_i, 70, 120, 0, 0, 18, alt_ellipsoid=h_i)
        self.sent += 1
        return lat_i * 1e-7, lon_i * 1e-7, h_i * 1e-3

    def close(self) -> None:
        self.sock.close()


def read_parts(url: str, n_parts: int | None = None, duration_s: float | None = None, out: list | None = None) -> list[tuple[dict[str, str], bytes]]:
    """Read MJPEG parts (headers, JPEG bytes) from ``url`` by Content-Length."""
    parts = out if out is not None else []
    deadline = None if duration_s is None else time.monotonic() + duration_s
    with urllib.request.urlopen(url, timeout=10) as resp:
        ctype = resp.headers["Content-Type"]
        assert ctype == f"multipart/x-mixed-replace; boundary={BOUNDARY}"
        while (n_parts is None or len(parts) < n_parts) and (deadline is None or time.monotonic() < deadline):
            line = resp.readline()
            if not line.strip():
                continue
            assert line.strip() == f"--{BOUNDARY}".encode()
            headers = {}
            while True:
                line = resp.readline().strip()
                if not line:
                    break
                key, value = line.decode("ascii").split(":", 1)
                headers[key.strip()] = value.strip()
            data = resp.read(int(headers["Content-Length"]))
            assert len(data) == int(headers["Content-Length"])
            parts.append((headers, data))
    return parts


def detect(jpeg: bytes) -> tuple[np.ndarray | None, tuple[int, int]]:
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.relativeCornerRefinmentWinSize = 0.5
    det = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)
    corners, ids, _ = det.detectMarkers(img)
    if ids is None or 0 not in ids.ravel():
        return None, img.shape
    return corners[list(ids.ravel()).index(0)][0].astype(float), img.shape


def truth_corners(camera: Camera, wire: tuple[float, float, float], yaw_rad: float) -> np.ndarray:
    """Where the marker of a vehicle at the wire's (lat, lon, h) must appear."""
    ant = geodetic_to_enu(*wire, EnuOrigin(*camera.enu_origin))[0]
    return camera.project(marker_corners_world(ant, 0.0, 0.0, yaw_rad, OFFSET, 0.4))


@pytest.fixture(scope="module")
def truth() -> Camera:
    return make_truth_camera(ORIGIN, 3.0, 0.0, 30.0, 500.0, 640, 480, Distortion(k1=-0.2, k2=0.05, p1=0.0005, p2=-0.0003))


def start_sender(sender: MavlinkSender, schedule, stop: threading.Event, log: list) -> threading.Thread:
    """Send ``schedule(elapsed_s) -> (antenna_enu, yaw)`` at 50 Hz until ``stop``; log (t_ns, wire, yaw)."""

    def loop() -> None:
        t0 = time.monotonic()
        while not stop.is_set():
            ant, yaw = schedule(time.monotonic() - t0)
            t_ns = time.time_ns()
            log.append((t_ns, sender.send_pose(ant, yaw), yaw))
            stop.wait(0.02)

    th = threading.Thread(target=loop, daemon=True)
    th.start()
    return th


def test_hovering_drone_is_streamed_where_the_truth_camera_sees_it(truth: Camera) -> None:
    ant = np.array([0.6, 5.0, 2.0])
    yaw = yaw_towards(ant, truth.pose.position_world)
    sim = SimCamera(truth, MarkerSpec(offset_frd_m=OFFSET), connect="udpin:127.0.0.1:0", serve_url="http://127.0.0.1:0/stream.mjpg", fps=20, noise_sigma_dn=2.0, seed=1)
    stop, log = threading.Event(), []
    with sim:
        sender = MavlinkSender(sim.mavlink_address, EnuOrigin(*truth.enu_origin))
        th = start_sender(sender, lambda _t: (ant, yaw), stop, log)
        try:
            deadline = time.monotonic() + 10
            while sim.track.geoid_separation_m is None and time.monotonic() < deadline:
                time.sleep(0.02)
            # Two clients at once, each reading its own stream.
            results: list[list] = [[], []]
            clients = [threading.Thread(target=read_parts, args=(sim.url, 4), kwargs={"out": r}) for r in results]
            for c in clients:
                c.start()
            for c in clients:
                c.join(timeout=20)
            snapshot = urllib.request.urlopen(sim.url.replace("/stream.mjpg", "/snapshot.jpg"), timeout=10).read()
        finally:
            stop.set()
            th.join()
            sender.close()
    assert sim.error is None
    assert sim.track.geoid_separation_m == pytest.approx(GEOID_SEP_M, abs=1e-3)
    expected = truth_corners(truth, log[-1][1], yaw)
    for parts in results:
        assert len(parts) == 4
        frame_times = [int(h["X-Dronecal-Frame-Time-Ns"]) for h, _ in parts]
        # Distinct frames on the 20 fps grid (a slow client may skip some, never repeats one).
        assert all(b > a for a, b in zip(frame_times, frame_times[1:]))
        assert all(t % 50_000_000 == 0 for t in frame_times)
        for headers, jpeg in parts:
            assert headers["Content-Type"] == "image/jpeg"
            assert headers["X-Dronecal-Altitude-Datum"] == "ellipsoid"
            corners, shape = detect(jpeg)
            assert shape == (480, 640)
            assert corners is not None
            assert np.abs(corners - expected).max() < 1.0
    corners, _ = detect(snapshot)
    assert np.abs(corners - expected).max() < 1.0


def test_latency_shows_the_vehicle_where_it_was(truth: Camera) -> None:
    latency_s = 0.4
    a = np.array([0.6, 5.0, 2.0])
    b = np.array([-0.6, 5.0, 2.0])  # 1.2 m to the west: about 110 px to the left
    yaw_a = yaw_towards(a, truth.pose.position_world)
    yaw_b = yaw_towards(b, truth.pose.position_world)
    sim = SimCamera(truth, MarkerSpec(offset_frd_m=OFFSET), connect="udpin:127.0.0.1:0", serve_url="http://127.0.0.1:0/stream.mjpg", fps=20, latency_s=latency_s, noise_sigma_dn=1.0, seed=2)
    stop, log = threading.Event(), []
    jump_after_s = 1.0
    with sim:
        sender = MavlinkSender(sim.mavlink_address, EnuOrigin(*truth.enu_origin))
        th = start_sender(sender, lambda t: (a, yaw_a) if t < jump_after_s else (b, yaw_b), stop, log)
        try:
            parts = read_parts(sim.url, duration_s=jump_after_s + latency_s + 0.8)
        finally:
            stop.set()
            th.join()
            sender.close()
    assert sim.error is None
    t_jump = next(t for t, _, yaw in log if yaw == yaw_b)  # first B message left the sender
    wire_a = next(w for _, w, yaw in log if yaw == yaw_a)
    wire_b = next(w for _, w, yaw in log if yaw == yaw_b)
    expect_a, expect_b = truth_corners(truth, wire_a, yaw_a), truth_corners(truth, wire_b, yaw_b)
    margin_ns = 80_000_000  # telemetry arrival and the interpolation between the last A and first B sample
    late_a = shown_b = 0
    for headers, jpeg in parts:
        frame_t = int(headers["X-Dronecal-Frame-Time-Ns"])
        pose_t = int(headers["X-Dronecal-Pose-Time-Ns"])
        assert frame_t - pose_t == 400_000_000
        corners, _ = detect(jpeg)
        if log[0][0] + margin_ns < pose_t < t_jump - margin_ns:
            assert np.abs(corners - expect_a).max() < 1.0
            if frame_t > t_jump + margin_ns:
                late_a += 1  # made after the jump, still showing the old place: the latency
        elif pose_t > t_jump + margin_ns:
            assert np.abs(corners - expect_b).max() < 1.0
            shown_b += 1
    # 0.4 s latency at 20 fps: about 5 frames made after the jump still show A.
    assert late_a >= 3
    assert shown_b >= 3


def test_command_makes_truth_serves_snapshots_and_rejects_bad_addresses(tmp_path: Path) -> None:
    truth_path = tmp_path / "truth.yaml"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    cmd = [
        sys.executable, "-m", "dronecal_field", "sim", "camera",
        "--connect", "udpin:127.0.0.1:0",
        "--site-lat", "-35.363261", "--site-lon", "149.165230", "--site-h", "584.0",
        "--site-image-size", "320x240", "--site-focal-px", "250", "--site-azimuth", "90",
        "--write-truth", str(truth_path),
        "--serve", "http://127.0.0.1:0/stream.mjpg",
        "--duration-s", "20",
    ]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=env)
    try:
        line = proc.stdout.readline()
        assert line.startswith("sim camera: serving http://127.0.0.1:"), line + proc.stderr.read() if proc.poll() is not None else line
        url = line.split()[3]
        jpeg = urllib.request.urlopen(url.replace("/stream.mjpg", "/snapshot.jpg"), timeout=10).read()
    finally:
        proc.terminate()
        proc.wait(timeout=10)
    img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
    assert img.shape == (240, 320, 3)
    cam = read_camera(truth_path)
    assert cam.enu_origin == pytest.approx((-35.363261, 149.165230, 584.0))
    assert cam.intrinsics.fx == 250.0 and cam.distortion.k1 == pytest.approx(-0.25)
    np.testing.assert_allclose(cam.pose.R_cam_from_world[2], [np.cos(np.radians(30)), 0.0, -np.sin(np.radians(30))], atol=1e-9)

    bad = subprocess.run(
        [sys.executable, "-m", "dronecal_field", "sim", "camera", "--connect", "127.0.0.1:14551", "--camera", str(truth_path), "--duration-s", "1"],
        capture_output=True, text=True, cwd=REPO, env=env, timeout=60,
    )
    assert bad.returncode == 2
    assert "explicit scheme" in bad.stderr


# ---------------------------------------------------------------- RTSP: fly's recorder against the simulated camera's H.264


def test_fly_records_the_simulated_cameras_rtsp_h264_stamped_through_rtcp_with_the_marker_in_it(tmp_path: Path, capsys) -> None:
    """``sim camera --serve rtsp://...`` (GStreamer's RTSP server, RTCP sender reports) under the unmodified ``fly --start``."""
    import json
    import re

    from dronecal_field.cli import main
    from dronecal_field.core.camera import Distortion
    from dronecal_field.runfile.reader import open_run
    from dronecal_field.sim.vehicle import SimVehicle, VehicleConfig
    from dronecal_field.video.nal import is_keyframe
    from test_mavlink_support import FAST_PARAMS, HOME, write_plan

    offset = (0.10, 0.0, 0.05)
    waypoints = [(-1.5, 5.0, 1.5), (1.5, 8.0, 3.0)]
    truth = make_truth_camera(HOME, 4.0, 0.0, 20.0, 560.0, 640, 480, distortion=Distortion(k1=-0.1))
    cam = SimCamera(truth, MarkerSpec(size_m=0.4, offset_frd_m=offset), connect="udpin:127.0.0.1:0", serve_url="rtsp://127.0.0.1:0/cam",
                    codec="h264", fps=15, noise_sigma_dn=1.0, seed=3).start()
    assert cam.url.startswith("rtsp://127.0.0.1:") and cam.url.endswith("/cam")
    host, port = cam.mavlink_address
    config = VehicleConfig(home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2], speedup=4.0, boot_s=1.0, params=FAST_PARAMS)
    sim = SimVehicle(config, listen=["udp:127.0.0.1:0"], out=[f"udp:{host}:{port}"]).start()
    plan = write_plan(tmp_path / "mission.plan", waypoints, hold_s=4.0, takeoff_alt_m=2.0, speed_mps=3.0)
    out = tmp_path / "run.mcap"
    try:
        rc = main(["fly", "--connect", sim.addresses()[0], "--mission", str(plan), "--video", cam.url, "--out", str(out),
                   "--marker-size", "0.4", "--marker-offset", ",".join(map(str, offset)), "--start", "--timeout-s", "240"])
    finally:
        sim.stop()
        cam.stop()
    printed = capsys.readouterr().out
    assert rc == 0, printed[-3000:]
    # The pre-flight rate is the stream's (not inflated by the opening burst); a busy machine's simulator may make fewer.
    fps = float(re.search(r"video +640x480, ([0-9.]+) fps", printed).group(1))
    assert 10.0 <= fps <= 15.0 * 1.05, printed[:3000]
    with open_run(out) as run:
        md = run.metadata
        frames = list(run.iter_frames())
        all_events = list(run.iter_events())
    events = [e.type for e in all_events]
    assert run.video and md.extra["camera.clock"] == "rtcp" and {f.format for f in frames} == {"h264"}
    assert is_keyframe(frames[0].data, "h264")  # the recording starts at a keyframe
    faults = [(e.type, e.timestamp_ns - frames[0].timestamp_ns, dict(e.metadata)) for e in all_events if e.type in ("video_gap", "video_corrupt")]
    assert not faults, (faults, printed[-2000:])
    # Stamped at the frame's own instant (the simulator's 1/15 s grid, through RTCP): every step a whole number of periods.
    period_ns = 1e9 / 15
    steps = np.diff([f.timestamp_ns for f in frames]) / period_ns
    assert np.all(np.abs(steps - np.round(steps)) < 0.002) and np.all(np.round(steps) >= 1)
    # A frame the simulator did not make in time on a busy machine is a pts gap, counted as lost: nothing unaccounted.
    lost = sum(int(e.metadata["frames"]) for e in all_events if e.type == "video_lost" and e.timestamp_ns > frames[0].timestamp_ns)
    assert lost == int(np.sum(np.round(steps) - 1)) and np.mean(np.round(steps) == 1) > 0.8
    # The marker is in the stream: the live pass decoded the holds' H.264 frames and found it at every waypoint.
    live = json.loads((tmp_path / "run.live.json").read_text())
    assert sorted(w["seq"] for w in live["waypoints"] if w["good"]) == [4, 5], live["waypoints"]
