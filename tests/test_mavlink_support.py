"""Shared parts for the MAVLink, simulated-vehicle and fly tests (plus tests of the parts themselves).

Real wires only: the simulated vehicle on real UDP sockets, a real UDP relay that
drops datagrams, a real HTTP server streaming real JPEG frames (MJPEG).
"""

from __future__ import annotations

import json
import random
import select
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

from conftest import REPLAYS  # noqa: F401 - the recorded ArduCopter SITL session, re-exported for the sim tests
from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink.link import open_link
from dronecal_field.sim.vehicle import SimVehicle, VehicleConfig
from dronecal_field.sim.vehicle_flight import CopterParams

HOME = (-35.363261, 149.165230, 584.0)  # SITL's CMAC site, AMSL
# MAVLink ids of the mission protocol: ITEM, REQUEST, SET_CURRENT, REQUEST_LIST, COUNT, CLEAR_ALL, ACK, REQUEST_INT, ITEM_INT
MISSION_MSG_IDS = frozenset({39, 40, 41, 43, 44, 45, 47, 51, 73})

# Quick flight parameters for tests: a low RTL and a short loiter keep flights short.
FAST_PARAMS = CopterParams(rtl_alt_m=4.0, rtl_loiter_s=1.0)


def start_sim(speedup: float = 20.0, boot_s: float = 2.0, params: CopterParams = FAST_PARAMS, **kw) -> SimVehicle:
    """A simulated vehicle in a thread, listening on an ephemeral UDP port.

    Its GPS makes 10 fixes a second (GPS_RATE_MS 100, the field setting
    docs/fly.md asks for) unless ``gps_rate_ms`` says otherwise; like
    ArduPilot 4.7 it streams nothing but HEARTBEAT until a client asks
    (:func:`ask_telemetry`).
    """
    listen = kw.pop("listen", None) or ["udp:127.0.0.1:0"]
    kw.setdefault("gps_rate_ms", 100.0)
    config = VehicleConfig(home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2], speedup=speedup, boot_s=boot_s, params=params, **kw)
    return SimVehicle(config, listen=listen).start()


def wait_until(predicate, timeout_s: float, poll_s: float = 0.01) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(poll_s)
    return bool(predicate())


def ask_telemetry(link, rates_hz=None) -> None:
    """Ask for telemetry on this link as a GCS does (SET_MESSAGE_INTERVAL; fly's set by default)."""
    from dronecal_field.mavlink.control import TELEMETRY_RATES_HZ, request_telemetry

    link.wait_heartbeat(5)
    wanted = dict(rates_hz or TELEMETRY_RATES_HZ)
    results = request_telemetry(link, tuple(wanted.items()))
    for _ in range(3):  # a loaded CI machine can miss an ACK's 0.5 s: ask again for the unanswered ones, as a GCS does
        missing = tuple((name, hz) for name, hz in wanted.items() if results.get(name) != 0)
        if not missing:
            break
        results.update(request_telemetry(link, missing))
    assert all(r == 0 for r in results.values()), results
    link.asked_telemetry = True  # wait_ready must not ask again over this client's own choice


def ask_like_recorded_gcs(link) -> None:
    """Ask for the streams the recording GCS asked for (calib-grid-rtk.tlog): REQUEST_DATA_STREAM ALL
    at 2 Hz, then SET_MESSAGE_INTERVAL for each of its messages."""
    from dronecal_field.sim.vehicle import RECORDED_GCS_RATES_HZ

    link.wait_heartbeat(5)
    link.send(link.dialect.MAVLink_request_data_stream_message(link.target_system, link.target_component, 0, 2, 1))
    ask_telemetry(link, RECORDED_GCS_RATES_HZ)


def wait_ready(link, timeout_s: float = 20.0) -> None:
    """Until SYS_STATUS says the vehicle is ready to arm (asks for the telemetry first, as a GCS does)."""
    if not getattr(link, "asked_telemetry", False):
        ask_telemetry(link)

    def ready():  # the pre-arm bit, and a healthy EKF where reported: ArduCopter 4.7 sets the bit ~18 s before it can arm
        status, ekf = link.latest("SYS_STATUS"), link.latest("EKF_STATUS_REPORT")
        ekf_ok = ekf is None or (not (ap.EKF_HEALTHY_FLAGS & ~int(ekf.flags)) and not (int(ekf.flags) & ap.EKF_BAD_FLAGS))
        return status is not None and bool(status.onboard_control_sensors_health & (1 << 28)) and ekf_ok

    assert wait_until(ready, timeout_s), "vehicle never became ready to arm"


def enu_to_latlon(enu_m, origin=HOME) -> np.ndarray:
    """(N, 3) [lat, lon, h] of ENU offsets from home (h ellipsoidal = AMSL with the sim's 0 geoid)."""
    return enu_to_geodetic(np.atleast_2d(np.asarray(enu_m, float)), EnuOrigin(*origin))


def plan_document(waypoints_enu, hold_s: float = 1.0, takeoff_alt_m: float = 2.0, speed_mps: float = 2.0, roi_enu=(0.0, 0.0, 3.0), end: str = "rtl", extra_items=()) -> dict:
    """A QGroundControl plan: takeoff, speed, ROI, waypoints (relative alt), then RTL/land/none."""

    def simple(command, frame, params):
        return {"type": "SimpleItem", "command": command, "frame": frame, "params": params, "autoContinue": True, "doJumpId": 0}

    items = [simple(22, 3, [0, 0, 0, None, 0, 0, takeoff_alt_m]), simple(178, 2, [1, speed_mps, -1, 0, 0, 0, 0])]
    if roi_enu is not None:
        lat, lon, _h = enu_to_latlon(roi_enu)[0]
        items.append(simple(201, 3, [3, 0, 0, 0, lat, lon, roi_enu[2]]))
    for e, n, u in waypoints_enu:
        lat, lon, _h = enu_to_latlon([e, n, 0.0])[0]
        items.append(simple(16, 3, [hold_s, 0, 0, None, lat, lon, u]))
    items.extend(extra_items)
    if end == "rtl":
        items.append(simple(20, 3, [0, 0, 0, 0, 0, 0, 0]))
    for i, item in enumerate(items, start=1):
        item["doJumpId"] = i
    return {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "tests",
        "mission": {"version": 2, "firmwareType": 3, "vehicleType": 2, "cruiseSpeed": 5, "hoverSpeed": 5, "plannedHomePosition": list(HOME), "items": items},
        "geoFence": {"circles": [], "polygons": [], "version": 2},
        "rallyPoints": {"points": [], "version": 2},
    }


def write_plan(path: Path, *args, **kw) -> Path:
    path.write_text(json.dumps(plan_document(*args, **kw)))
    return path


class UdpRelay:
    """A real UDP relay between a GCS and a vehicle that can lose datagrams.

    The GCS sends to :attr:`url`; the relay forwards to ``target`` from its own
    socket and sends the answers back. ``drop_fraction`` of the datagrams that
    carry a message id in ``drop_ids`` are dropped, in both directions
    (seeded); :meth:`blackout` drops everything for a while (a lost link).
    """

    def __init__(self, target: str, drop_fraction: float = 0.0, drop_ids=MISSION_MSG_IDS, seed: int = 1) -> None:
        _scheme, host, port = target.split(":")
        self.target = (host, int(port))
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind(("127.0.0.1", 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.bind(("127.0.0.1", 0))
        self.drop_fraction = drop_fraction
        self.drop_ids = frozenset(drop_ids)
        self.rng = random.Random(seed)
        self.gcs_addr = None
        self.forwarded = {"up": 0, "down": 0}
        self.dropped = {"up": 0, "down": 0}
        self.candidates = {"up": 0, "down": 0}
        self._blackout_until = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"udp:127.0.0.1:{self.front.getsockname()[1]}"

    def blackout(self, seconds: float) -> None:
        self._blackout_until = time.monotonic() + seconds

    @staticmethod
    def msgid(data: bytes) -> int | None:
        if len(data) >= 10 and data[0] == 0xFD:
            return data[7] | (data[8] << 8) | (data[9] << 16)
        if len(data) >= 6 and data[0] == 0xFE:
            return data[5]
        return None

    def _drop(self, data: bytes, direction: str) -> bool:
        if time.monotonic() < self._blackout_until:
            self.dropped[direction] += 1
            return True
        if self.msgid(data) in self.drop_ids:
            self.candidates[direction] += 1
            if self.rng.random() < self.drop_fraction:
                self.dropped[direction] += 1
                return True
        return False

    def _run(self) -> None:
        while not self._stop.is_set():
            ready, _, _ = select.select([self.front, self.back], [], [], 0.05)
            for sock in ready:
                try:
                    data, addr = sock.recvfrom(65535)
                except OSError:
                    continue
                if sock is self.front:
                    self.gcs_addr = addr
                    if not self._drop(data, "up"):
                        self.back.sendto(data, self.target)
                        self.forwarded["up"] += 1
                elif self.gcs_addr is not None and not self._drop(data, "down"):
                    self.front.sendto(data, self.gcs_addr)
                    self.forwarded["down"] += 1

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.front.close()
        self.back.close()


def marker_jpeg(width: int = 640, height: int = 480, marker_id: int = 0, seed: int = 0) -> bytes:
    """A real JPEG: grey noise with an ArUco DICT_4X4_50 marker in the middle."""
    import cv2

    rng = np.random.default_rng(seed)
    image = rng.integers(90, 160, size=(height, width), dtype=np.uint8)
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)
    side = min(width, height) // 3
    marker = cv2.aruco.generateImageMarker(dictionary, marker_id, side)
    pad = side // 6
    canvas = np.full((side + 2 * pad, side + 2 * pad), 255, np.uint8)
    canvas[pad:-pad, pad:-pad] = marker
    y0, x0 = (height - canvas.shape[0]) // 2, (width - canvas.shape[1]) // 2
    image[y0 : y0 + canvas.shape[0], x0 : x0 + canvas.shape[1]] = canvas
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, 85])
    assert ok
    return buf.tobytes()


class MjpegServer:
    """A tiny real MJPEG-over-HTTP server (multipart/x-mixed-replace) on an ephemeral port.

    ``pause()`` stops sending frames (a video gap) until ``resume()``.
    """

    def __init__(self, fps: float = 15.0, width: int = 640, height: int = 480) -> None:
        self.frames = [marker_jpeg(width, height, seed=i) for i in range(3)]
        self.fps = fps
        self.sent = 0
        self._running = threading.Event()
        self._running.set()
        self._stop = threading.Event()
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):  # keep test output clean
                pass

            def do_GET(self):
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                i = 0
                try:
                    while not server._stop.is_set():
                        if not server._running.wait(0.05):
                            continue
                        data = server.frames[i % len(server.frames)]
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: " + str(len(data)).encode() + b"\r\n\r\n" + data + b"\r\n")
                        self.wfile.flush()
                        server.sent += 1
                        i += 1
                        time.sleep(1.0 / server.fps)
                except (BrokenPipeError, ConnectionResetError):
                    return

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.httpd.daemon_threads = True
        self._thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}/stream.mjpg"

    def pause(self) -> None:
        self._running.clear()

    def resume(self) -> None:
        self._running.set()

    def close(self) -> None:
        self._stop.set()
        self.httpd.shutdown()
        self.httpd.server_close()


class MessageLog:
    """Collects every message of a link with the vehicle time (s) it was seen at."""

    def __init__(self, link) -> None:
        self.link = link
        self.messages: list[tuple[float, object]] = []
        self.vehicle_s = 0.0
        self._lock = threading.Lock()
        link.add_listener(self._on)

    def _on(self, direction, _ns, msg) -> None:
        if direction != "in":
            return
        t = getattr(msg, "time_boot_ms", None)
        with self._lock:
            if t is not None:
                self.vehicle_s = t / 1000.0
            self.messages.append((self.vehicle_s, msg))

    def of(self, mtype: str) -> list[tuple[float, object]]:
        with self._lock:
            return [(t, m) for t, m in self.messages if m.get_type() == mtype]


# ----- tests of the test parts themselves -----


def test_relay_drops_the_requested_fraction_of_mission_messages():
    sim = start_sim(speedup=20.0, boot_s=0.5)
    relay = UdpRelay(sim.addresses()[0], drop_fraction=0.3, drop_ids={0, 30}, seed=3)  # HEARTBEAT, ATTITUDE
    link = open_link(relay.url)
    try:
        ask_telemetry(link)  # ATTITUDE is streamed only when asked for
        assert wait_until(lambda: relay.candidates["down"] >= 300, 10)
        fraction = relay.dropped["down"] / relay.candidates["down"]
        assert 0.2 < fraction < 0.4
    finally:
        link.close()
        relay.close()
        sim.stop()


def test_mjpeg_server_streams_decodable_jpegs_with_a_marker():
    import cv2

    from dronecal_field.video import open_video

    server = MjpegServer(fps=30)
    try:
        source = open_video(server.url)
        frame = source.read(timeout_s=5)
        source.close()
    finally:
        server.close()
    assert frame is not None and frame.format == "jpeg"
    image = cv2.imdecode(np.frombuffer(frame.data, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert image.shape == (480, 640)
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    _corners, ids, _rej = detector.detectMarkers(image)
    assert ids is not None and ids.ravel().tolist() == [0]
