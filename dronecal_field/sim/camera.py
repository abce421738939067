"""The simulated pole camera: follows a MAVLink vehicle and serves what it sees as MJPEG over HTTP, or over RTSP.

Three threads around the pure parts (render.py, camera_track.py):

* a MAVLink client (pymavlink, the scheme given explicitly) that asks the
  vehicle on its own link for what it needs, as a GCS does (ArduPilot 4.7
  streams nothing on a link until asked): SET_MESSAGE_INTERVAL for SIMSTATE,
  GLOBAL_POSITION_INT and ATTITUDE at 10 Hz, GPS_RAW_INT and MISSION_CURRENT
  at 2 Hz, asked again whenever the position goes quiet; it never commands
  anything else. Each sample is stamped with its host arrival time; the
  vehicle is drawn at its true position and attitude (SIMSTATE, as SITL
  sends, with GLOBAL_POSITION_INT's height) when the vehicle sends SIMSTATE,
  else at the EKF's (GLOBAL_POSITION_INT, ATTITUDE);
* a frame loop that, while anyone watches, renders the vehicle as it was at
  ``frame time - latency`` through the true camera and JPEG-encodes it;
* a sender that puts each frame out ``delivery_s`` after its frame time, as a
  real camera's pipeline does at a constant delay: a recorder that stamps
  arrival then sees one constant latency, not the render time's 30-100 ms
  jitter (which, on a leg flown at 0.4 m/s, is centimetres of fake track
  error); a frame that is ready later goes out at once and is counted
  (``frames_late``);
* an HTTP server (ThreadingHTTPServer) that streams the frames as
  ``multipart/x-mixed-replace`` to any number of clients, and serves single
  frames at ``/snapshot.jpg``.

With ``rtsp://HOST:PORT/PATH`` the frames are H.264 or H.265 from
GStreamer's RTSP server instead (:mod:`dronecal_field.sim.camera_rtsp`, a
child process of Debian's Python): a real IP camera's stream, with RTCP
sender reports that put each frame at its frame time; the HTTP server and
the sender are then not started, and frames are rendered whether or not
anyone watches.

Each MJPEG part carries ``X-Dronecal-Frame-Time-Ns`` (when the frame was
made, host UTC ns) and ``X-Dronecal-Pose-Time-Ns`` (the instant whose pose it
shows, frame time minus latency). They are simulator ground truth for tests;
a recorder must not use them, as no real camera sends them.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from urllib.parse import urlsplit

from dronecal_field.core.camera import Camera
from dronecal_field.errors import InputError, LinkError
from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu
from dronecal_field.sim.camera_track import GeodeticPose, PoseTrack
from dronecal_field.sim.render import FrameRenderer
from dronecal_field.sim.scene import MarkerSpec, VehiclePose

BOUNDARY = "dronecalframe"
MAVLINK_SCHEMES = ("udpin", "udpout", "udp", "tcp", "tcpin", "udpbcast", "serial")


# What the camera asks for on its link (Hz): the truth, the EKF's position and attitude as a
# fallback, the ellipsoid height and the mission seq (for --hide-marker-at).
STREAM_REQUESTS_HZ: tuple[tuple[str, float], ...] = (
    ("SIMSTATE", 10.0),
    ("GLOBAL_POSITION_INT", 10.0),
    ("ATTITUDE", 10.0),
    ("GPS_RAW_INT", 2.0),
    ("MISSION_CURRENT", 2.0),
)
# PX4 SITL has no SIMSTATE: its truth is HIL_STATE_QUATERNION (SIH's ground truth; 10 Hz when asked, PX4 1.16)
PX4_STREAM_REQUESTS_HZ: tuple[tuple[str, float], ...] = (("HIL_STATE_QUATERNION", 10.0), *STREAM_REQUESTS_HZ[1:])
MAV_AUTOPILOT_PX4 = 12
REQUEST_AGAIN_NS = 2_000_000_000  # no position for this long: ask again


def _euler_from_quaternion(q: Any) -> tuple[float, float, float]:
    """(roll, pitch, yaw) radians of a MAVLink (w, x, y, z) quaternion, body FRD from NED."""
    w, x, y, z = (float(v) for v in q)
    roll = math.atan2(2.0 * (w * x + y * z), 1.0 - 2.0 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2.0 * (w * y - z * x))))
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return roll, pitch, yaw


@dataclass(frozen=True)
class ServeAddress:
    """Where the stream is served: ``http://host:port/path`` (MJPEG) or ``rtsp://host:port/path`` (H.264/H.265)."""

    host: str
    port: int
    path: str
    scheme: str = "http"


def parse_serve_url(url: str) -> ServeAddress:
    """Split ``http://HOST:PORT/PATH`` or ``rtsp://HOST:PORT/PATH`` (port 0 = any free port)."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "rtsp") or not parts.hostname:
        raise InputError(f"--serve {url!r} is not an http:// or rtsp:// URL: use e.g. http://127.0.0.1:8554/stream.mjpg or rtsp://127.0.0.1:8554/cam")
    try:
        port = parts.port if parts.port is not None else (80 if parts.scheme == "http" else 554)
    except ValueError:
        raise InputError(f"--serve {url!r} has a bad port: use 0..65535") from None
    default = "/stream.mjpg" if parts.scheme == "http" else "/cam"
    return ServeAddress(host=parts.hostname, port=port, path=parts.path or default, scheme=parts.scheme)


def open_mavlink_listener(connect: str) -> "mavutil.mavfile":  # noqa: F821 (pymavlink, imported lazily)
    """A pymavlink connection for ``connect``, whose scheme must be explicit.

    ``udpin:HOST:PORT`` (or ``udp:``) listens for a vehicle sending to us,
    ``tcp:HOST:PORT`` connects to a vehicle's TCP port (e.g. SITL 5760),
    ``udpout:HOST:PORT`` / ``tcpin:`` / ``udpbcast:`` as pymavlink,
    ``serial:DEVICE[:BAUD]`` a telemetry radio. Nothing is ever sent.
    """
    from pymavlink import mavutil

    scheme, sep, rest = connect.partition(":")
    if not sep or scheme not in MAVLINK_SCHEMES or not rest:
        raise InputError(f"--connect {connect!r} needs an explicit scheme: one of {', '.join(s + ':' for s in MAVLINK_SCHEMES)} (e.g. udpin:127.0.0.1:14551)")
    try:
        if scheme == "serial":
            device, _, baud = rest.rpartition(":") if rest.rsplit(":", 1)[-1].isdigit() else (rest, "", "57600")
            return mavutil.mavlink_connection(device, baud=int(baud))
        return mavutil.mavlink_connection(connect)
    except (OSError, ValueError) as exc:
        raise LinkError(f"cannot open MAVLink {connect!r}: {exc}; check the address and that the port is free") from None


class FrameHub:
    """The latest encoded frame and the clients waiting for the next one."""

    def __init__(self) -> None:
        self._cond = threading.Condition()
        self._seq = 0
        self._jpeg = b""
        self._headers: dict[str, str] = {}
        self._watchers = 0
        self._closed = False

    def publish(self, jpeg: bytes, headers: dict[str, str]) -> None:
        """Make ``jpeg`` (with its part headers) the latest frame and wake the clients."""
        with self._cond:
            self._seq += 1
            self._jpeg, self._headers = jpeg, headers
            self._cond.notify_all()

    def next_frame(self, after_seq: int, timeout_s: float) -> tuple[int, bytes, dict[str, str]] | None:
        """The first frame newer than ``after_seq``, or None on timeout or close."""
        with self._cond:
            self._cond.wait_for(lambda: self._closed or self._seq > after_seq, timeout=timeout_s)
            if self._closed or self._seq <= after_seq:
                return None
            return self._seq, self._jpeg, self._headers

    def watch(self, delta: int) -> None:
        """A client starts (+1) or stops (-1) watching; frames are made only while someone watches."""
        with self._cond:
            self._watchers += delta
            self._cond.notify_all()

    def wait_for_watchers(self, timeout_s: float) -> bool:
        """True once someone watches; False on timeout or close."""
        with self._cond:
            return self._cond.wait_for(lambda: self._closed or self._watchers > 0, timeout=timeout_s) and not self._closed

    @property
    def seq(self) -> int:
        """Number of the latest frame (0 before the first)."""
        with self._cond:
            return self._seq

    @property
    def closed(self) -> bool:
        """True after ``close``."""
        return self._closed

    def close(self) -> None:
        """Release every waiting client and stop the stream."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()


def _make_handler(hub: FrameHub, stream_path: str):
    class MjpegHandler(BaseHTTPRequestHandler):
        server_version = "dronecal-sim-camera/1"

        def log_message(self, format: str, *args: object) -> None:  # library code does not print
            pass

        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            path = urlsplit(self.path).path
            if path == stream_path:
                self._stream()
            elif path == "/snapshot.jpg":
                self._snapshot()
            else:
                self.send_error(404, f"try {stream_path} or /snapshot.jpg")

        def _snapshot(self) -> None:
            hub.watch(+1)
            try:
                frame = hub.next_frame(hub.seq, timeout_s=5.0)
            finally:
                hub.watch(-1)
            if frame is None:
                self.send_error(503, "no frame")
                return
            _, jpeg, headers = frame
            self.send_response(200)
            self.send_header("Content-Type", "image/jpeg")
            self.send_header("Content-Length", str(len(jpeg)))
            for k, v in headers.items():
                self.send_header(k, v)
            self.end_headers()
            self.wfile.write(jpeg)

        def _stream(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
            self.send_header("Cache-Control", "no-cache, no-store")
            self.send_header("Pragma", "no-cache")
            self.send_header("Connection", "close")
            self.end_headers()
            hub.watch(+1)
            try:
                seq = hub.seq
                while not hub.closed:
                    frame = hub.next_frame(seq, timeout_s=1.0)
                    if frame is None:
                        continue
                    seq, jpeg, headers = frame
                    head = [f"--{BOUNDARY}", "Content-Type: image/jpeg", f"Content-Length: {len(jpeg)}"]
                    head += [f"{k}: {v}" for k, v in headers.items()]
                    self.wfile.write(("\r\n".join(head) + "\r\n\r\n").encode("ascii") + jpeg + b"\r\n")
                    self.wfile.flush()
            except (BrokenPipeError, ConnectionResetError, ConnectionAbortedError):
                pass  # the client went away
            finally:
                hub.watch(-1)

    return MjpegHandler


class SimCamera:
    """A simulated fixed camera that watches a MAVLink vehicle and serves MJPEG.

    Parameters
    ----------
    camera : the true camera, world frame ENU at ``camera.enu_origin`` (required).
    marker : the marker mounted on the vehicle.
    connect : MAVLink address with an explicit scheme (``open_mavlink_listener``).
    serve_url : ``http://HOST:PORT/PATH``; port 0 picks a free port (see ``url``).
    fps : frames per second while a client watches.
    latency_s : the image shows the vehicle as it was this long before the frame time.
    delivery_s : each frame is sent this long after its frame time (the camera's constant pipeline delay).
    noise_sigma_dn : Gaussian pixel noise, grey levels.
    jpeg_quality : 0..100.
    seed : background and noise seed.
    use_ellipsoid : convert GLOBAL_POSITION_INT's MSL heights to ellipsoidal ones with
        GPS_RAW_INT.alt_ellipsoid when the vehicle reports it (else use them as they are).
    vehicle_sysid : follow this MAVLink system; None follows the first that reports a position.
    hide_marker_at : mission seqs (MISSION_CURRENT.seq) during which the marker is covered: from the moment
        the vehicle heads for that waypoint until it leaves it (the hold included), to rehearse missed waypoints.

    Use as a context manager, or ``start()`` / ``stop()``.
    """

    def __init__(
        self,
        camera: Camera,
        marker: MarkerSpec,
        connect: str,
        serve_url: str = "http://127.0.0.1:8554/stream.mjpg",
        fps: float = 10.0,
        latency_s: float = 0.0,
        noise_sigma_dn: float = 2.0,
        jpeg_quality: int = 90,
        seed: int = 0,
        use_ellipsoid: bool = True,
        vehicle_sysid: int | None = None,
        hide_marker_at: frozenset[int] | set[int] | tuple[int, ...] = frozenset(),
        delivery_s: float = 0.15,
        codec: str = "h264",
    ) -> None:
        if camera.enu_origin is None:
            raise InputError("the truth camera has no enu_origin: the simulator needs it to place the vehicle (write it with make_truth_camera)")
        if not fps > 0:
            raise InputError(f"--fps {fps} must be positive")
        if latency_s < 0:
            raise InputError(f"--latency-s {latency_s} must be zero or positive")
        if not 0 <= delivery_s <= 5:
            raise InputError(f"delivery_s {delivery_s} must be within 0-5 s")
        self.camera = camera
        self.marker = marker
        self.connect = connect
        self.fps = float(fps)
        self.latency_ns = int(round(latency_s * 1e9))
        self.delivery_ns = int(round(delivery_s * 1e9))
        self.frames_late = 0  # frames ready after their delivery time, sent at once
        self._outbox: queue.Queue = queue.Queue(maxsize=max(4, int(2 * fps * (delivery_s + 0.5))))
        self.jpeg_quality = int(jpeg_quality)
        self.vehicle_sysid = vehicle_sysid
        self.hide_marker_at = frozenset(int(s) for s in hide_marker_at)
        self.mission_seq: int | None = None  # the vehicle's MISSION_CURRENT.seq
        self.frames_hidden = 0
        self.stream_requests = 0  # times the camera asked the vehicle for its streams
        self._vehicle_autopilot: int | None = None  # HEARTBEAT.autopilot (12 = PX4: its truth is HIL_STATE_QUATERNION)
        self.position_source: str | None = None  # "SIMSTATE" (truth) or "GLOBAL_POSITION_INT" (EKF)
        self._vehicle_compid: int | None = None
        self.origin = EnuOrigin(*camera.enu_origin)
        self.track = PoseTrack(horizon_s=max(30.0, 4.0 * latency_s), use_ellipsoid=use_ellipsoid)
        self.renderer = FrameRenderer(camera, marker, noise_sigma_dn=noise_sigma_dn, seed=seed)
        self.serve = parse_serve_url(serve_url)
        self.codec = codec
        self._rtsp = None  # camera_rtsp.RtspOut when serving rtsp://
        self.hub = FrameHub()
        self.frames_rendered = 0
        self.messages_received = 0
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._mav = None
        self._server: ThreadingHTTPServer | None = None
        self._error: BaseException | None = None

    # -- lifecycle

    def start(self) -> "SimCamera":
        """Open the MAVLink link and the HTTP port (or the RTSP server), then start the threads."""
        self._mav = open_mavlink_listener(self.connect)
        if self.serve.scheme == "rtsp":
            from dronecal_field.sim.camera_rtsp import RtspAddress, RtspOut

            try:
                self._rtsp = RtspOut(RtspAddress(self.serve.host, self.serve.port, self.serve.path), self.camera.width, self.camera.height,
                                     self.fps, self.codec)
            except Exception:
                self._mav.close()
                raise
            for name, target in (("sim-camera-mavlink", self._listen), ("sim-camera-frames", self._frames)):
                th = threading.Thread(target=target, name=name, daemon=True)
                th.start()
                self._threads.append(th)
            return self
        try:
            server = ThreadingHTTPServer((self.serve.host, self.serve.port), _make_handler(self.hub, self.serve.path))
        except OSError as exc:
            self._mav.close()
            raise InputError(f"cannot serve on {self.serve.host}:{self.serve.port}: {exc.strerror}; pick a free port (0 = any)") from None
        server.daemon_threads = True
        self._server = server
        for name, target in (("sim-camera-mavlink", self._listen), ("sim-camera-frames", self._frames), ("sim-camera-sender", self._send),
                             ("sim-camera-http", server.serve_forever)):
            th = threading.Thread(target=target, name=name, daemon=True)
            th.start()
            self._threads.append(th)
        return self

    def stop(self) -> None:
        """Stop the threads and close the sockets."""
        self._stop.set()
        self.hub.close()
        if self._rtsp is not None:
            self._rtsp.close()
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
        for th in self._threads:
            th.join(timeout=5.0)
        if self._mav is not None:
            self._mav.close()

    def __enter__(self) -> "SimCamera":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def url(self) -> str:
        """The stream's URL, with the port actually bound."""
        if self._rtsp is not None:
            return self._rtsp.url
        host, port = self._server.server_address[:2] if self._server else (self.serve.host, self.serve.port)
        return f"http://{host}:{port}{self.serve.path}"

    @property
    def mavlink_address(self) -> tuple[str, int] | None:
        """(host, port) of the local MAVLink socket (the port to send to with ``udpin:HOST:0``)."""
        port = getattr(self._mav, "port", None)
        try:
            return port.getsockname()[:2] if port is not None and hasattr(port, "getsockname") else None
        except OSError:
            return None

    @property
    def error(self) -> BaseException | None:
        """The exception that stopped a thread, if any."""
        return self._error

    # -- pose

    def vehicle_pose(self, time_ns: int) -> tuple[VehiclePose, GeodeticPose] | None:
        """The vehicle at ``time_ns`` in the camera's ENU world, or None before any position."""
        g = self.track.pose_at(time_ns)
        if g is None:
            return None
        enu = geodetic_to_enu(g.lat_deg, g.lon_deg, g.h_m, self.origin)[0]
        return VehiclePose(antenna_enu_m=enu, roll_rad=g.roll_rad, pitch_rad=g.pitch_rad, yaw_rad=g.yaw_rad), g

    # -- threads

    def _request_streams(self, mav, target_system: int, target_component: int) -> None:
        """SET_MESSAGE_INTERVAL on this link for what the camera needs (no ACK awaited: asked again if quiet)."""
        from pymavlink import mavutil

        for name, hz in PX4_STREAM_REQUESTS_HZ if self._vehicle_autopilot == MAV_AUTOPILOT_PX4 else STREAM_REQUESTS_HZ:
            msgid = getattr(mavutil.mavlink, f"MAVLINK_MSG_ID_{name}")
            mav.mav.command_long_send(target_system, target_component, mavutil.mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, msgid, 1e6 / hz, 0, 0, 0, 0, 0)
        self.stream_requests += 1

    def _listen(self) -> None:
        types = ["HEARTBEAT", "SIMSTATE", "HIL_STATE_QUATERNION", "GLOBAL_POSITION_INT", "ATTITUDE", "GPS_RAW_INT", "MISSION_CURRENT"]
        mav = self._mav
        last_position_ns = 0
        last_request_ns = 0
        last_heartbeat_ns = 0
        simstate_seen = False
        alt_msl_m: float | None = None
        try:
            while not self._stop.is_set():
                msg = mav.recv_match(type=types, blocking=True, timeout=0.2)
                now_ns = time.time_ns()
                if now_ns - last_heartbeat_ns > 1_000_000_000:
                    # a camera's heartbeat (MAV_TYPE_CAMERA, no autopilot): lets a vehicle listening on
                    # udpin/tcp learn this link's address before the camera's first request
                    mav.mav.heartbeat_send(30, 8, 0, 0, 0)
                    last_heartbeat_ns = now_ns
                if (
                    self.vehicle_sysid is not None
                    # PX4 streams GLOBAL_POSITION_INT (the EKF's) unasked: without its truth yet, ask for HIL_STATE_QUATERNION anyway
                    and (now_ns - last_position_ns > REQUEST_AGAIN_NS or (self._vehicle_autopilot == MAV_AUTOPILOT_PX4 and not simstate_seen))
                    and now_ns - last_request_ns > REQUEST_AGAIN_NS
                    and self._vehicle_compid is not None
                ):
                    # nothing (or nothing lately: a restarted vehicle forgets) on this link: ask, as a GCS does
                    self._request_streams(mav, self.vehicle_sysid, self._vehicle_compid)
                    last_request_ns = now_ns
                if msg is None:
                    continue
                sysid = msg.get_srcSystem()
                kind = msg.get_type()
                if kind == "HEARTBEAT":
                    if msg.type == 6 or msg.autopilot == 8:  # a GCS (MAV_TYPE_GCS) or no autopilot: not a vehicle
                        continue
                    if self.vehicle_sysid is None:
                        self.vehicle_sysid = sysid  # follow the first vehicle that announces itself
                    if sysid == self.vehicle_sysid:
                        self._vehicle_compid = msg.get_srcComponent()
                        self._vehicle_autopilot = int(msg.autopilot)
                    continue
                if self.vehicle_sysid is None:
                    if kind != "GLOBAL_POSITION_INT":
                        continue
                    self.vehicle_sysid = sysid  # a vehicle whose heartbeat we missed but that streams to us
                if sysid != self.vehicle_sysid:
                    continue
                self.messages_received += 1
                if kind == "SIMSTATE":
                    # SITL's truth: lat/lon and attitude (no height: GLOBAL_POSITION_INT's, the EKF's, is used)
                    simstate_seen = True
                    last_position_ns = now_ns
                    self.position_source = "SIMSTATE"
                    if alt_msl_m is not None:
                        self.track.add_position(now_ns, msg.lat * 1e-7, msg.lng * 1e-7, alt_msl_m)
                    self.track.add_attitude(now_ns, msg.roll, msg.pitch, msg.yaw)
                elif kind == "HIL_STATE_QUATERNION":
                    # PX4 SIH's truth: position with its own AMSL height, attitude as a quaternion
                    simstate_seen = True
                    last_position_ns = now_ns
                    self.position_source = "HIL_STATE_QUATERNION"
                    self.track.add_position(now_ns, msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
                    self.track.add_attitude(now_ns, *_euler_from_quaternion(msg.attitude_quaternion))
                elif kind == "GLOBAL_POSITION_INT":
                    alt_msl_m = msg.alt * 1e-3
                    if not simstate_seen:
                        last_position_ns = now_ns
                        self.position_source = "GLOBAL_POSITION_INT"
                        self.track.add_position(now_ns, msg.lat * 1e-7, msg.lon * 1e-7, alt_msl_m)
                elif kind == "ATTITUDE":
                    if not simstate_seen:
                        self.track.add_attitude(now_ns, msg.roll, msg.pitch, msg.yaw)
                elif kind == "MISSION_CURRENT":
                    self.mission_seq = int(msg.seq)
                else:
                    alt_ell = getattr(msg, "alt_ellipsoid", 0)  # a MAVLink 2 extension: 0 when absent
                    if msg.fix_type >= 3:
                        self.track.add_gps_raw(msg.alt * 1e-3, alt_ell * 1e-3 if alt_ell else None)
        except Exception as exc:  # keep the reason for the caller; the thread cannot raise to it
            if not self._stop.is_set():
                self._error = exc

    def _frames(self) -> None:
        import cv2

        period_ns = int(round(1e9 / self.fps))
        params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality]
        try:
            while not self._stop.is_set():
                if self._rtsp is None and not self.hub.wait_for_watchers(timeout_s=0.5):
                    continue
                # Frames on a fixed grid of the UTC clock, like a free-running sensor.
                now = time.time_ns()
                tick = (now // period_ns + 1) * period_ns
                if self._stop.wait((tick - now) / 1e9):
                    break
                pose_time = tick - self.latency_ns
                pose = self.vehicle_pose(pose_time)
                hidden = self.mission_seq is not None and self.mission_seq in self.hide_marker_at
                img = self.renderer.render_in_place(pose[0] if pose else None, show_marker=not hidden)  # sent or encoded before the next frame
                self.frames_hidden += int(hidden)
                if self._rtsp is not None:
                    self.frames_rendered += 1
                    if not self._rtsp.send(tick, img):  # shown at its frame time: RTCP carries it to the recorder
                        raise RuntimeError("the RTSP server process ended")
                    continue
                ok, buf = cv2.imencode(".jpg", img, params)
                if not ok:
                    raise RuntimeError("JPEG encoding failed")
                headers = {"X-Dronecal-Frame-Time-Ns": str(tick), "X-Dronecal-Pose-Time-Ns": str(pose_time)}
                if pose is not None:
                    v, g = pose
                    headers["X-Dronecal-Antenna-Enu-M"] = ",".join(f"{x:.4f}" for x in v.antenna_enu_m)
                    headers["X-Dronecal-Altitude-Datum"] = g.altitude_datum
                self.frames_rendered += 1
                while not self._stop.is_set():
                    try:
                        self._outbox.put((tick, buf.tobytes(), headers), timeout=0.5)
                        break
                    except queue.Full:
                        continue
        except Exception as exc:
            if not self._stop.is_set():
                self._error = exc
                self.hub.close()

    def _send(self) -> None:
        """Publish each frame at its frame time + ``delivery_s`` (at once, counted late, when it is ready after that)."""
        try:
            while not self._stop.is_set():
                try:
                    tick, jpeg, headers = self._outbox.get(timeout=0.5)
                except queue.Empty:
                    continue
                wait_ns = tick + self.delivery_ns - time.time_ns()
                if wait_ns > 0:
                    if self._stop.wait(wait_ns / 1e9):
                        break
                elif wait_ns < -1_000_000:
                    self.frames_late += 1
                self.hub.publish(jpeg, headers)
        except Exception as exc:
            if not self._stop.is_set():
                self._error = exc
                self.hub.close()

