"""Issue 13: the live view over a real Foxglove WebSocket, read by a client written here (RFC 6455 over a socket).

The live pipeline is fed as the recorder feeds it (``on_frame``, ``on_record``)
with frames rendered by the simulator's renderer (real JPEG) and fixes where
the drone is; the client connects to the server on loopback, checks the
advertised channels and decodes one message of each with the schema the
server advertised.
"""

from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic
from dronecal_field.live.progress import LiveOptions
from dronecal_field.live.view import LiveView
from dronecal_field.live.worker import LiveCalibration
from dronecal_field.mavlink.missionfile import parse_qgc_plan
from dronecal_field.runfile.records import Attitude, Frame, GnssFix, MarkerSpec, RunEvent
from dronecal_field.sim.render import FrameRenderer
from dronecal_field.sim.scene import MarkerSpec as SimMarker
from dronecal_field.sim.scene import VehiclePose, make_truth_camera
from test_mavlink_support import HOME, plan_document

OFFSET = (0.10, 0.0, 0.05)
WAYPOINTS = [(x, y, z) for y in (5.0, 8.0) for z in (1.5, 3.0) for x in (-1.5, 1.5)]
EXPECTED = {
    "/live/camera/image": "foxglove.CompressedImage",
    "/live/camera/annotations": "foxglove.ImageAnnotations",
    "/live/coverage": "foxglove.ImageAnnotations",
    "/live/camera/calibration": "foxglove.CameraCalibration",
    "/live/gnss": "foxglove.LocationFix",
    "/live/waypoints": "foxglove.GeoJSON",
    "/live/site": "foxglove.GeoJSON",
    "/live/status": "",
}


# ----- a minimal WebSocket client (RFC 6455): handshake, masked text frames out, frames in -----
def ws_connect(port: int, subprotocol: str = "foxglove.sdk.v1") -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                  f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: {subprotocol}\r\n\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:
        head += sock.recv(1)
    assert head.startswith(b"HTTP/1.1 101"), head
    assert subprotocol.encode() in head
    return sock


def _exact(sock: socket.socket, n: int) -> bytes:
    buf = b""
    while len(buf) < n:
        chunk = sock.recv(n - len(buf))
        assert chunk, "server closed the connection"
        buf += chunk
    return buf


def ws_recv(sock: socket.socket) -> tuple[int, bytes]:
    """(opcode, payload) of the next message, fragments joined."""
    opcode, payload = None, b""
    while True:
        b0, b1 = _exact(sock, 2)
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", _exact(sock, 2))[0]
        elif n == 127:
            n = struct.unpack(">Q", _exact(sock, 8))[0]
        data = _exact(sock, n)
        if b0 & 0x0F in (0x9, 0xA):  # ping/pong: ignore
            continue
        opcode = opcode if (b0 & 0x0F) == 0 else b0 & 0x0F
        payload += data
        if b0 & 0x80:
            return opcode, payload


def ws_send_text(sock: socket.socket, text: str) -> None:
    data = text.encode()
    mask = os.urandom(4)
    n = len(data)
    head = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n))
    sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))


def message_class(channel: dict):
    """A protobuf class from the FileDescriptorSet the server advertised for ``channel``."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


# ----- feeding the live pipeline as the recorder does -----
def feed_flight(live: LiveCalibration, truth, t0_ns: int) -> int:
    """Eight 2 s holds: frames at 15 Hz, fixes at 10 Hz and attitude at 10 Hz, then each hold's ``hover`` event;
    returns the stamp after the last hold."""
    renderer = FrameRenderer(truth, SimMarker(size_m=0.4, offset_frd_m=OFFSET), noise_sigma_dn=1.0, seed=4)
    origin = EnuOrigin(*HOME)
    rng = np.random.default_rng(5)
    t = t0_ns
    for k, (x, y, z) in enumerate(WAYPOINTS):
        yaw = float(np.arctan2(-x, -y))  # nose (and marker) towards the camera
        start = t
        for j in range(30):  # 2 s at 15 Hz
            ts = start + j * 66_666_667
            pose = VehiclePose(antenna_enu_m=np.array([x, y, z]), yaw_rad=yaw)
            ok, jpeg = cv2.imencode(".jpg", renderer.render(pose), [cv2.IMWRITE_JPEG_QUALITY, 90])
            live.on_frame(Frame(timestamp_ns=ts, format="jpeg", data=jpeg.tobytes()))
        for j in range(21):  # 10 Hz
            ts = start + j * 100_000_000
            lat, lon, h = enu_to_geodetic(np.array([[x, y, z]]) + rng.normal(0, 0.005, 3), origin)[0]
            live.on_record(GnssFix(timestamp_ns=ts, lat_deg=lat, lon_deg=lon, alt_m=h, covariance_enu=np.diag([1e-4, 1e-4, 2e-4]), fix_type="rtk_fixed"))
            live.on_record(Attitude(timestamp_ns=ts, roll_rad=0.0, pitch_rad=0.0, yaw_rad=yaw))
        end = start + 2_000_000_000
        live.on_record(RunEvent(timestamp_ns=start, duration_ns=end - start, type="hover", metadata={"seq": str(4 + k)}))
        t = end + 500_000_000
    return t


def keep_flying(live: LiveCalibration, end_ns: int, k: int) -> None:
    """The k-th fix and attitude at the last waypoint after the flight ``feed_flight`` ended at ``end_ns``."""
    x, y, z = WAYPOINTS[-1]
    ts = end_ns + k * 100_000_000
    lat, lon, h = enu_to_geodetic(np.array([[x, y, z]]), EnuOrigin(*HOME))[0]
    live.on_record(GnssFix(timestamp_ns=ts, lat_deg=lat, lon_deg=lon, alt_m=h, covariance_enu=np.diag([1e-4, 1e-4, 2e-4]), fix_type="rtk_fixed"))
    live.on_record(Attitude(timestamp_ns=ts, roll_rad=0.0, pitch_rad=0.0, yaw_rad=float(np.arctan2(-x, -y))))



def test_foxglove_client_sees_every_channel_and_decodes_one_message_of_each():
    truth = make_truth_camera(HOME, 4.0, 0.0, 20.0, 560.0, 640, 480)
    mission = parse_qgc_plan(json.dumps(plan_document(WAYPOINTS, hold_s=3.0)))
    view = LiveView(port=0)
    marker = MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.4, offset_frd_m=OFFSET)
    live = LiveCalibration(mission, marker, 640, 480, origin=EnuOrigin(*HOME), options=LiveOptions(), view=view).start()
    sock = None
    try:
        end_ns = feed_flight(live, truth, time.time_ns())
        sock = ws_connect(view.port)
        channels: dict[str, dict] = {}
        deadline = time.monotonic() + 20
        while set(channels) != set(EXPECTED) and time.monotonic() < deadline:
            op, payload = ws_recv(sock)
            if op == 1:
                msg = json.loads(payload)
                if msg.get("op") == "advertise":
                    channels.update({c["topic"]: c for c in msg["channels"]})
        assert set(channels) == set(EXPECTED)
        for topic, schema in EXPECTED.items():
            if schema:
                assert channels[topic]["schemaName"] == schema and channels[topic]["encoding"] == "protobuf", channels[topic]
        assert channels["/live/status"]["encoding"] == "json"
        by_sub = {k: c for k, c in enumerate(channels.values(), start=1)}
        ws_send_text(sock, json.dumps({"op": "subscribe", "subscriptions": [{"id": k, "channelId": c["id"]} for k, c in by_sub.items()]}))

        decoded: dict[str, object] = {}
        deadline = time.monotonic() + 30
        fixes_after = iter(range(1_000))
        next_fix = 0.0
        while len(decoded) < len(EXPECTED) and time.monotonic() < deadline:
            if time.monotonic() > next_fix:
                # the flight goes on while the client subscribes: a fix the worker published before the subscription
                # (a busy machine's order) is not sent again, a real receiver's next one is
                keep_flying(live, end_ns, next(fixes_after))
                next_fix = time.monotonic() + 0.3
            op, payload = ws_recv(sock)
            if op != 2 or payload[0] != 0x01:
                continue
            sub, _log_time = struct.unpack_from("<IQ", payload, 1)
            c = by_sub[sub]
            body = payload[13:]
            if c["topic"] in decoded:
                continue
            if c["topic"] in ("/live/camera/calibration", "/live/camera/annotations") and live.estimate is None:
                continue  # wait for the running calibration (and its reprojection)
            message = json.loads(body) if c["encoding"] == "json" else message_class(c).FromString(body)
            if c["topic"] == "/live/coverage" and not sum(len(p.points) for p in message.points):
                continue  # the view thread publishes from the start: wait for one drawn after a detection
            decoded[c["topic"]] = message
        assert set(decoded) == set(EXPECTED), sorted(set(EXPECTED) - set(decoded))
    finally:
        if sock is not None:
            sock.close()
        result = live.finish()
        view.close()

    # every good hold was seen, and the calibration from 8 points is the truth's within 2 %
    assert result.verdict.good and len(result.outcomes) == 8
    cal = decoded["/live/camera/calibration"]
    assert (cal.width, cal.height, cal.distortion_model) == (640, 480, "plumb_bob")
    assert cal.K[0] == pytest.approx(560.0, rel=0.02) and cal.K[8] == 1.0
    assert result.estimate is not None and abs(result.estimate.focal_px - 560.0) < 5 * result.estimate.focal_std_px + 2.0
    image = decoded["/live/camera/image"]
    assert image.format == "jpeg" and cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_GRAYSCALE).shape == (480, 640)
    fix = decoded["/live/gnss"]
    assert fix.latitude == pytest.approx(HOME[0], abs=2e-4) and fix.longitude == pytest.approx(HOME[1], abs=2e-4)
    assert fix.position_covariance[0] == pytest.approx(1e-4)
    waypoints = json.loads(decoded["/live/waypoints"].geojson)
    assert len(waypoints["features"]) == 8
    coverage = decoded["/live/coverage"]
    assert sum(len(p.points) for p in coverage.points) > 0
    # the red circle: a hold's GNSS position through the live calibration, where the truth sees the marker (that hold's)
    annotations = decoded["/live/camera/annotations"]
    reprojected = [(c.position.x, c.position.y) for c in annotations.circles if c.diameter == 14.0]
    assert len(reprojected) == 1
    markers = np.array([[x, y, z] + VehiclePose(antenna_enu_m=np.zeros(3), yaw_rad=float(np.arctan2(-x, -y))).R_enu_from_frd @ np.array(OFFSET)
                        for x, y, z in WAYPOINTS])
    assert np.min(np.hypot(*(truth.project(markers) - np.array(reprojected[0])).T)) < 3.0
    assert "status" in decoded["/live/status"] or "verdict" in decoded["/live/status"]


# ----- a client we did not write: @foxglove/ws-protocol's FoxgloveClient (Node), offering foxglove.websocket.v1 only -----
CLIENT_DIR = Path(__file__).with_name("foxglove_client")


def node_client() -> Path:
    """tests/foxglove_client with its npm packages installed (package-lock.json, ``npm ci``); skips without Node/npm."""
    import shutil
    import subprocess

    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("Node.js and npm are needed for the third-party Foxglove client (apt-get install nodejs npm)")
    if not (CLIENT_DIR / "node_modules" / "@foxglove" / "ws-protocol").is_dir():
        try:
            subprocess.run(["npm", "ci", "--no-audit", "--no-fund", "--ignore-scripts"], cwd=CLIENT_DIR, check=True,
                           capture_output=True, text=True, timeout=240)
        except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as exc:
            pytest.skip(f"npm ci in {CLIENT_DIR} failed (no registry?): {getattr(exc, 'stderr', '') or exc}"[:400])
    return CLIENT_DIR


def test_a_standard_foxglove_client_offering_foxglove_websocket_v1_only_decodes_every_channel():
    """@foxglove/ws-protocol's FoxgloveClient over ws (what Lichtblick and older Foxglove apps use) against the live view."""
    import subprocess

    client_dir = node_client()
    truth = make_truth_camera(HOME, 4.0, 0.0, 20.0, 560.0, 640, 480)
    mission = parse_qgc_plan(json.dumps(plan_document(WAYPOINTS, hold_s=3.0)))
    view = LiveView(port=0)
    marker = MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.4, offset_frd_m=OFFSET)
    live = LiveCalibration(mission, marker, 640, 480, origin=EnuOrigin(*HOME), options=LiveOptions(), view=view).start()
    try:
        feed_flight(live, truth, time.time_ns())
        deadline = time.monotonic() + 60
        while live.estimate is None and time.monotonic() < deadline:
            time.sleep(0.2)  # the running calibration, so its topics carry messages
        assert live.estimate is not None
        client = subprocess.Popen(["node", "client.mjs", f"ws://127.0.0.1:{view.port}", "30", "2"], cwd=client_dir,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        origin = EnuOrigin(*HOME)
        while client.poll() is None:  # the drone, landed at the last hold, still sends its fixes (new ones go out once)
            lat, lon, h = enu_to_geodetic(np.array([list(WAYPOINTS[-1])]), origin)[0]
            live.on_record(GnssFix(timestamp_ns=time.time_ns(), lat_deg=lat, lon_deg=lon, alt_m=h,
                                   covariance_enu=np.diag([1e-4, 1e-4, 2e-4]), fix_type="rtk_fixed"))
            time.sleep(0.1)
        out, err = client.communicate(timeout=10)
        run = subprocess.CompletedProcess(client.args, client.returncode, out, err)
    finally:
        live.finish()
        view.close()
    report = json.loads(run.stdout.strip().splitlines()[-1])
    assert run.returncode == 0, ({t: (v["messages"], v["errors"]) for t, v in report["topics"].items()}, report["error"], run.stderr[-2000:])
    assert report["protocol"] == "foxglove.websocket.v1" and report["error"] is None
    assert view.front.renamed == 1
    topics = report["topics"]
    assert set(topics) == set(EXPECTED)
    for topic, schema in EXPECTED.items():
        t = topics[topic]
        assert t["messages"] >= 2 and t["errors"] == 0, (topic, t)
        assert t["encoding"] == ("protobuf" if schema else "json") and (not schema or t["schemaName"] == schema)
    image = topics["/live/camera/image"]["last"]
    assert image["format"] == "jpeg" and image["data"]["head"].startswith("ffd8") and image["data"]["length"] > 1000
    cal = topics["/live/camera/calibration"]["last"]
    assert (cal["width"], cal["height"]) == (640, 480) and cal["K"][0] == pytest.approx(560.0, rel=0.02)
    fix = topics["/live/gnss"]["last"]
    assert fix["latitude"] == pytest.approx(HOME[0], abs=2e-4) and fix["longitude"] == pytest.approx(HOME[1], abs=2e-4)
    assert len(json.loads(topics["/live/waypoints"]["last"]["geojson"])["features"]) == 8
    site = {f["properties"]["name"].split(" (")[0]: f["geometry"] for f in json.loads(topics["/live/site"]["last"]["geojson"])["features"]}
    assert site["camera pole"]["coordinates"] == pytest.approx([HOME[1], HOME[0]], abs=1e-7)  # no plan.json: the ENU origin
    path = np.array(site["flight path"]["coordinates"])  # (N, 2) lon, lat: the eight holds flown
    assert len(path) >= 8 and np.ptp(path[:, 0]) > 2.5 / 111_320.0
    assert sum(len(p["points"]) for p in topics["/live/coverage"]["last"]["points"]) > 0
    assert "status" in topics["/live/status"]["last"] or "verdict" in topics["/live/status"]["last"]


def test_the_map_shows_the_rois_ground_and_the_camera_pole_of_a_plan():
    from dronecal_field.geodesy import geodetic_to_enu
    from dronecal_field.live.progress import image_roi
    from dronecal_field.live.view import site_features

    plan = json.loads((Path(__file__).parents[1] / "missions" / "paper-pinhole" / "plan.json").read_text())
    roi = image_roi(plan)
    assert roi is not None
    origin = EnuOrigin(*HOME)
    features = {f["properties"]["name"].split(" (")[0]: f for f in site_features(plan, roi, origin)}
    assert set(features) == {"ROI", "camera pole"}
    ring = np.array(features["ROI"]["geometry"]["coordinates"][0])  # (K + 1, 2) lon, lat, closed
    assert np.allclose(ring[0], ring[-1]) and len(ring) >= 4
    enu = geodetic_to_enu(ring[:, 1], ring[:, 0], HOME[2], origin)  # (K + 1, 3)
    R = np.asarray(plan["site_frame"]["R_enu_from_site"], float)
    ground = roi.points_site[roi.on_ground] @ R.T
    # The polygon is the hull of the ROI's ground points: every one inside its bounding box, the box no larger.
    lo, hi = enu[:, :2].min(axis=0), enu[:, :2].max(axis=0)
    assert np.all(ground[:, :2] >= lo - 0.01) and np.all(ground[:, :2] <= hi + 0.01)
    assert np.allclose(lo, ground[:, :2].min(axis=0), atol=0.01) and np.allclose(hi, ground[:, :2].max(axis=0), atol=0.01)
    pole = np.asarray(plan["camera_guess"]["position_enu_m"], float)
    lon, lat = features["camera pole"]["geometry"]["coordinates"]
    assert np.allclose(geodetic_to_enu(lat, lon, HOME[2], origin)[0, :2], pole[:2], atol=0.01)


def test_an_h264_camera_is_shown_as_its_keyframes_decoded_at_a_low_rate(tmp_path):
    from test_video_packets import encode_clip

    from dronecal_field.video.files import read_video_packets

    encode_clip(tmp_path / "clip.mp4", "h264", n=30, size=(160, 128), gop=10)
    units = [f for _, f, _ in read_video_packets(str(tmp_path / "clip.mp4"), 1_000_000_000)]  # 25 fps: keyframes 0.4 s apart
    view = LiveView(port=0)
    try:
        shown = []
        for unit in units:
            view.offer_video(unit)  # the recorder's thread: a reference kept, nothing decoded
            image = view.video_image(every_s=0.5)
            if image is not None:
                shown.append(image)
    finally:
        view.close()
    assert [u.timestamp_ns for u in units if u.keyframe] == [1_000_000_000, 1_400_000_000, 1_800_000_000]
    assert [f.timestamp_ns for f in shown] == [1_000_000_000, 1_800_000_000]  # at most one every 0.5 s
    gray = cv2.imdecode(np.frombuffer(shown[0].data, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert shown[0].format == "jpeg" and gray.shape == (128, 160)
    assert gray[40, 30] > 200 and gray[100, 150] < 140  # the clip's bright square on its grey background
