"""The live state on a Foxglove WebSocket (foxglove-sdk), loopback by default.

Topics (every one a Foxglove schema, protobuf, except the JSON status):

=============================  ==========================  ==============================================
topic                          schema                      what
=============================  ==========================  ==============================================
/live/camera/image             foxglove.CompressedImage    the camera, ~2 frames a second (JPEG as recorded;
                                                           H.264/H.265: a keyframe decoded every 2 s)
/live/camera/annotations       foxglove.ImageAnnotations   the detection (green quad) and where the running
                                                           calibration puts the marker from GNSS (red circle)
/live/coverage                 foxglove.ImageAnnotations   every marker centre seen so far (blue dots), the
                                                           plan's ROI cells (grey outlines)
/live/camera/calibration       foxglove.CameraCalibration  the running calibration (plumb_bob)
/live/gnss                     foxglove.LocationFix        the drone's fixes
/live/waypoints                foxglove.GeoJSON            the planned waypoints, coloured by outcome
/live/site                     foxglove.GeoJSON            the flight path flown, the ROI's ground, the camera pole
/live/status                   JSON                        status line, last summary, final verdict
=============================  ==========================  ==============================================

Foxglove keeps no message for a late client, so the worker publishes the
whole state again twice a second. docs/foxglove-layout.json opens it all.

Subprotocols: the SDK's server speaks ``foxglove.sdk.v1`` only (every
foxglove-sdk release so far answers anything else with HTTP 400), while the
published protocol, what ``@foxglove/ws-protocol``, Lichtblick and older
Foxglove apps offer, is ``foxglove.websocket.v1``; Foxglove states the two
are the same protocol under two names. So the SDK listens on a loopback port
of its own and :class:`SubprotocolFront` takes the public port: it accepts
either name in the handshake, hands the SDK the name it knows, answers the
client with the name it asked for, then copies bytes both ways untouched.
"""

from __future__ import annotations

import json
import socket
import threading
from typing import Any

import numpy as np

FRAME_ID = "camera"
STATUS_COLOURS = {"good": "#2ca02c", "pending": "#7f7f7f"}


class LiveView:
    """The Foxglove server and its channels (own foxglove.Context: nothing leaks into other servers).

    Parameters
    ----------
    host : address to bind (127.0.0.1: this machine only).
    port : TCP port; 0 picks a free one (see ``port``).
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8765) -> None:
        import foxglove
        from foxglove import channels

        self._fg = foxglove
        self.context = foxglove.Context()
        ctx = self.context
        self.image = channels.CompressedImageChannel("/live/camera/image", context=ctx)
        self.annotations = channels.ImageAnnotationsChannel("/live/camera/annotations", context=ctx)
        self.coverage = channels.ImageAnnotationsChannel("/live/coverage", context=ctx)
        self.calibration = channels.CameraCalibrationChannel("/live/camera/calibration", context=ctx)
        self.gnss = channels.LocationFixChannel("/live/gnss", context=ctx)
        self.waypoints = channels.GeoJsonChannel("/live/waypoints", context=ctx)
        self.site = channels.GeoJsonChannel("/live/site", context=ctx)
        self.status = foxglove.Channel("/live/status", schema={"type": "object"}, context=ctx)
        self.server = foxglove.start_server(name="dronecal-field fly", host="127.0.0.1", port=0, context=ctx)
        try:
            self.front = SubprotocolFront(host, port, ("127.0.0.1", int(self.server.port)))
        except OSError:
            self.server.stop()
            raise
        self._mission: Any = None
        self._roi_outlines: list[np.ndarray] = []
        self._site_features: list[dict] = []
        self._path: list[list[float]] = []  # [lon, lat] of the fixes flown, thinned
        self._last_fix_ns = 0
        self._video_key: Any = None  # the latest keyframe of an H.264/H.265 camera (a reference, not decoded)
        self._video_shown_ns = 0

    @property
    def port(self) -> int:
        """The public port (the front's)."""
        return self.front.port

    def close(self) -> None:
        self.front.close()
        self.server.stop()

    # ----- the plan (once) -----
    def set_plan(self, mission: Any, roi: Any, plan: dict | None = None, origin: Any = None) -> None:
        """The mission flown (waypoints on the map), the plan's image ROI (coverage outlines) and, with
        plan.json and the site origin, the ROI's ground and the camera pole on the map."""
        self._mission = mission
        self._roi_outlines = list(roi.outline_uv()) if roi is not None else []
        self._site_features = site_features(plan, roi, origin)
        self.publish_waypoints({})

    # ----- publishing -----
    def publish_waypoints(self, statuses: dict[int, str]) -> None:
        """GeoJSON points of the NAV_WAYPOINTs, each with its seq and status (good / the problem / pending)."""
        from dronecal_field.mavlink.missionfile import CMD_NAV_WAYPOINT

        if self._mission is None:
            return
        features = []
        for item in self._mission.items[1:]:
            if item.command != CMD_NAV_WAYPOINT or item.lat_deg is None:
                continue
            status = statuses.get(item.seq, "pending")
            features.append({
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": [item.lon_deg, item.lat_deg]},
                "properties": {"name": f"seq {item.seq}: {status}", "seq": item.seq, "status": status,
                               "style": {"color": STATUS_COLOURS.get(status, "#d62728")}},
            })
        self.waypoints.log(self._fg.messages.GeoJson(geojson=json.dumps({"type": "FeatureCollection", "features": features})))
        self.publish_site()

    def publish_site(self) -> None:
        """The map's other layer: the ROI's ground (polygon), the camera pole (point), the flight path (line)."""
        features = list(self._site_features)
        if len(self._path) >= 2:
            features.append({"type": "Feature", "geometry": {"type": "LineString", "coordinates": list(self._path)},
                             "properties": {"name": "flight path", "style": {"color": "#1f77b4", "weight": 2}}})
        self.site.log(self._fg.messages.GeoJson(geojson=json.dumps({"type": "FeatureCollection", "features": features})))

    def publish_fixes(self, fixes: list[Any]) -> None:
        """The fixes not sent before (GnssFix records), as LocationFix."""
        m = self._fg.messages
        for fix in fixes:
            if fix.timestamp_ns <= self._last_fix_ns:
                continue
            self._last_fix_ns = fix.timestamp_ns
            self._extend_path(fix.lon_deg, fix.lat_deg)
            cov = fix.covariance_enu
            self.gnss.log(
                m.LocationFix(
                    timestamp=_stamp(m, fix.timestamp_ns), frame_id="gnss", latitude=fix.lat_deg, longitude=fix.lon_deg, altitude=fix.alt_m,
                    position_covariance=None if cov is None else [float(v) for v in np.asarray(cov).ravel()],
                    position_covariance_type=m.LocationFixPositionCovarianceType.DiagonalKnown if cov is not None else m.LocationFixPositionCovarianceType.Unknown,
                ),
                log_time=fix.timestamp_ns,
            )

    def publish_image(self, frame: Any, detection: Any, reprojection_uv: np.ndarray | None, seen_uv: np.ndarray) -> None:
        """One frame, its detection and the running reprojection; the coverage so far on the same stamp."""
        m = self._fg.messages
        ts = _stamp(m, frame.timestamp_ns)
        self.image.log(m.CompressedImage(timestamp=ts, frame_id=FRAME_ID, data=frame.data, format=frame.format), log_time=frame.timestamp_ns)
        points, circles, texts = [], [], []
        if detection is not None and detection.corners_px is not None:
            points.append(m.PointsAnnotation(
                timestamp=ts, type=m.PointsAnnotationType.LineLoop, thickness=2.0,
                points=[m.Point2(x=float(u), y=float(v)) for u, v in np.asarray(detection.corners_px)],
                outline_color=m.Color(r=0.1, g=0.9, b=0.1, a=1.0),
            ))
        if detection is not None:
            circles.append(m.CircleAnnotation(timestamp=ts, position=m.Point2(x=detection.u_px, y=detection.v_px), diameter=6.0,
                                              thickness=2.0, outline_color=m.Color(r=0.1, g=0.9, b=0.1, a=1.0)))
        if reprojection_uv is not None and np.all(np.isfinite(reprojection_uv)):
            circles.append(m.CircleAnnotation(timestamp=ts, position=m.Point2(x=float(reprojection_uv[0]), y=float(reprojection_uv[1])),
                                              diameter=14.0, thickness=2.0, outline_color=m.Color(r=0.9, g=0.1, b=0.1, a=1.0)))
            texts.append(m.TextAnnotation(timestamp=ts, position=m.Point2(x=float(reprojection_uv[0]) + 10, y=float(reprojection_uv[1]) - 10),
                                          text="GNSS through the live calibration", font_size=14.0,
                                          text_color=m.Color(r=0.9, g=0.1, b=0.1, a=1.0)))
        self.annotations.log(m.ImageAnnotations(circles=circles, points=points, texts=texts), log_time=frame.timestamp_ns)
        cover = [m.PointsAnnotation(
            timestamp=ts, type=m.PointsAnnotationType.LineLoop, thickness=1.0, outline_color=m.Color(r=0.6, g=0.6, b=0.6, a=0.8),
            points=[m.Point2(x=float(u), y=float(v)) for u, v in outline],
        ) for outline in self._roi_outlines]
        if len(seen_uv):
            cover.append(m.PointsAnnotation(
                timestamp=ts, type=m.PointsAnnotationType.Points, thickness=6.0, outline_color=m.Color(r=0.1, g=0.4, b=1.0, a=1.0),
                points=[m.Point2(x=float(u), y=float(v)) for u, v in seen_uv],
            ))
        self.coverage.log(m.ImageAnnotations(points=cover), log_time=frame.timestamp_ns)

    def _extend_path(self, lon_deg: float, lat_deg: float, min_step_m: float = 0.25, max_points: int = 20_000) -> None:
        """The flight path: a point when the drone moved ``min_step_m`` (thinned by half when it grows past ``max_points``)."""
        if self._path:
            lon0, lat0 = self._path[-1]
            dn = (lat_deg - lat0) * 111_320.0
            de = (lon_deg - lon0) * 111_320.0 * np.cos(np.radians(lat_deg))
            if dn * dn + de * de < min_step_m * min_step_m:
                return
        self._path.append([float(lon_deg), float(lat_deg)])
        if len(self._path) > max_points:
            self._path = self._path[::2] + ([self._path[-1]] if len(self._path) % 2 == 0 else [])

    def offer_video(self, frame: Any) -> None:
        """An access unit of an H.264/H.265 camera (from the recorder's thread): a keyframe is kept, nothing decoded."""
        if getattr(frame, "keyframe", False):
            self._video_key = frame

    def video_image(self, every_s: float = 2.0, jpeg_quality: int = 80) -> Any:
        """The latest keyframe decoded and encoded as JPEG (a Frame), at most once every ``every_s``; else None.

        The camera image of an H.264/H.265 camera at a low rate: a keyframe
        decodes on its own, so nothing else of the stream is decoded here.
        """
        key = self._video_key
        if key is None or key.timestamp_ns - self._video_shown_ns < every_s * 1e9:
            return None
        import cv2

        from dronecal_field.runfile.records import Frame
        from dronecal_field.video.decode import decode_keyframe_gray

        self._video_shown_ns = key.timestamp_ns
        gray = decode_keyframe_gray(key.data, key.format)
        if gray is None:
            return None
        ok, jpeg = cv2.imencode(".jpg", gray, [int(cv2.IMWRITE_JPEG_QUALITY), int(jpeg_quality)])
        return Frame(timestamp_ns=key.timestamp_ns, format="jpeg", data=jpeg.tobytes()) if ok else None

    def publish_calibration(self, estimate: Any, t_ns: int) -> None:
        """The running calibration as CameraCalibration (plumb_bob: k1, k2, p1, p2, k3)."""
        m = self._fg.messages
        cam = estimate.camera
        i = cam.intrinsics
        K = [i.fx, 0.0, i.cx, 0.0, i.fy, i.cy, 0.0, 0.0, 1.0]
        self.calibration.log(
            m.CameraCalibration(
                timestamp=_stamp(m, t_ns), frame_id=FRAME_ID, width=cam.width, height=cam.height, distortion_model="plumb_bob",
                D=[float(v) for v in cam.distortion.as_array()], K=K, R=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                P=[i.fx, 0.0, i.cx, 0.0, 0.0, i.fy, i.cy, 0.0, 0.0, 0.0, 1.0, 0.0],
            ),
            log_time=int(t_ns),
        )

    def publish_status(self, status: dict) -> None:
        self.status.log(status)


def site_features(plan: dict | None, roi: Any, origin: Any) -> list[dict]:
    """GeoJSON features of the site: the ROI's ground (the hull of its z = 0 points) and the camera pole.

    Parameters
    ----------
    plan : plan.json (its ``site_frame.R_enu_from_site`` and ``camera_guess.position_enu_m``), or None.
    roi : the plan's ROI (``sampling.roi.Roi``: ``points_site`` (M, 3) site metres, ``on_ground`` (M,)), or None.
    origin : the ENU origin (``geodesy.EnuOrigin``, at the camera pole), or None: then nothing.
    """
    if origin is None:
        return []
    from dronecal_field.geodesy import enu_to_geodetic

    features = []
    R = np.eye(3)
    try:
        R = np.asarray((plan or {})["site_frame"]["R_enu_from_site"], float).reshape(3, 3)
    except (KeyError, TypeError, ValueError):
        pass
    if roi is not None and np.count_nonzero(roi.on_ground) >= 3:
        import cv2

        ground_enu = np.asarray(roi.points_site, float)[np.asarray(roi.on_ground, bool)] @ R.T  # (K, 3) ENU metres
        hull = cv2.convexHull(ground_enu[:, :2].astype(np.float32)).reshape(-1, 2).astype(float)
        ring = np.column_stack([hull, np.zeros(len(hull))])
        geo = enu_to_geodetic(np.vstack([ring, ring[:1]]), origin)  # (K + 1, 3) lat, lon, h
        features.append({"type": "Feature", "geometry": {"type": "Polygon", "coordinates": [[[float(lon), float(lat)] for lat, lon, _ in geo]]},
                         "properties": {"name": f"ROI ({roi.spec.describe()})", "style": {"color": "#ff7f0e", "fill": True, "fillOpacity": 0.15}}})
    pole = np.zeros(3)
    try:
        pole = np.asarray(plan["camera_guess"]["position_enu_m"], float).reshape(3)  # type: ignore[index]
    except (KeyError, TypeError, ValueError):
        pass
    lat, lon, _h = enu_to_geodetic(np.array([[pole[0], pole[1], 0.0]]), origin)[0]
    features.append({"type": "Feature", "geometry": {"type": "Point", "coordinates": [float(lon), float(lat)]},
                     "properties": {"name": f"camera pole ({pole[2]:.1f} m up)", "style": {"color": "#000000"}}})
    return features


class SubprotocolFront:
    """The public port of the live view: both names of the Foxglove WebSocket protocol, one SDK server behind.

    A client offering ``foxglove.websocket.v1`` (the published protocol) or
    ``foxglove.sdk.v1`` is connected to the SDK's server on loopback: the
    handshake request goes on with ``foxglove.sdk.v1``, the SDK's 101 answer
    comes back with the name the client asked for, and from then on bytes pass
    untouched both ways (WebSocket frames, masks and extensions are end to
    end: ``Sec-WebSocket-Key`` and ``-Extensions`` go through as sent). Any
    other offer gets the SDK's own 400. Two threads per client.

    Parameters
    ----------
    host, port : where to listen (port 0: a free one, see ``port``).
    upstream : (host, port) of the SDK's server.
    """

    NAMES = ("foxglove.websocket.v1", "foxglove.sdk.v1")
    SDK_NAME = "foxglove.sdk.v1"

    def __init__(self, host: str, port: int, upstream: tuple[str, int]) -> None:
        self.upstream = upstream
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._listener = socket.create_server((host, int(port)), family=family)
        self._listener.settimeout(0.5)
        self.port = int(self._listener.getsockname()[1])
        self._closed = threading.Event()
        self._sockets: set[socket.socket] = set()
        self._lock = threading.Lock()
        self.clients = 0  # connections handed to the SDK
        self.renamed = 0  # of them, offered foxglove.websocket.v1 only
        self._thread = threading.Thread(target=self._accept_loop, name="foxglove-front", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._closed.set()
        self._listener.close()
        with self._lock:
            socks, self._sockets = list(self._sockets), set()
        for s in socks:
            _shut(s)
        self._thread.join(timeout=2.0)

    def _accept_loop(self) -> None:
        while not self._closed.is_set():
            try:
                client, _addr = self._listener.accept()
            except (TimeoutError, socket.timeout):
                continue
            except OSError:
                return
            threading.Thread(target=self._serve, args=(client,), name="foxglove-front-client", daemon=True).start()

    def _track(self, *socks: socket.socket) -> None:
        with self._lock:
            self._sockets.update(socks)

    def _serve(self, client: socket.socket) -> None:
        upstream = None
        try:
            client.settimeout(10.0)
            request, rest = _read_head(client)
            if request is None:
                return
            request, asked = rename_offer(request, self.SDK_NAME)
            upstream = socket.create_connection(self.upstream, timeout=10.0)
            self._track(client, upstream)
            upstream.sendall(request + rest)
            response, rest = _read_head(upstream)
            if response is None:
                return
            if asked is not None and response.startswith(b"HTTP/1.1 101"):
                response = response.replace(self.SDK_NAME.encode(), asked.encode(), 1)
                self.renamed += 1
            self.clients += 1
            client.sendall(response + rest)
            client.settimeout(None)
            upstream.settimeout(None)
            pump = threading.Thread(target=_copy, args=(upstream, client), name="foxglove-front-down", daemon=True)
            pump.start()
            _copy(client, upstream)
            pump.join()
        except OSError:
            pass
        finally:
            _shut(client)
            if upstream is not None:
                _shut(upstream)
            with self._lock:
                self._sockets.discard(client)
                if upstream is not None:
                    self._sockets.discard(upstream)


def rename_offer(request: bytes, sdk_name: str) -> tuple[bytes, str | None]:
    """A handshake request offering ``foxglove.websocket.v1`` but not ``sdk_name``, offering ``sdk_name`` instead.

    Returns (request, the name to answer with) or (request unchanged, None).
    """
    lines = request.split(b"\r\n")
    offered = []
    for line in lines[1:]:
        key, _, value = line.partition(b":")
        if key.strip().lower() == b"sec-websocket-protocol":
            offered += [v.strip().decode("latin-1") for v in value.split(b",")]
    if sdk_name in offered or "foxglove.websocket.v1" not in offered:
        return request, None
    out = [line for line in lines if line.partition(b":")[0].strip().lower() != b"sec-websocket-protocol"]
    out.insert(1, b"Sec-WebSocket-Protocol: " + sdk_name.encode())
    return b"\r\n".join(out), "foxglove.websocket.v1"


def _read_head(sock: socket.socket, limit: int = 65536) -> tuple[bytes | None, bytes]:
    """(HTTP head up to and with its blank line, bytes already read after it); (None, b"") if the peer closed first."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        chunk = sock.recv(4096)
        if not chunk or len(buf) > limit:
            return None, b""
        buf += chunk
    i = buf.index(b"\r\n\r\n") + 4
    return buf[:i], buf[i:]


def _copy(src: socket.socket, dst: socket.socket) -> None:
    try:
        while True:
            data = src.recv(65536)
            if not data:
                break
            dst.sendall(data)
    except OSError:
        pass
    finally:
        _shut(dst)
        _shut(src)


def _shut(sock: socket.socket) -> None:
    try:
        sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        sock.close()
    except OSError:
        pass


def _stamp(m: Any, t_ns: int):
    """foxglove.messages.Timestamp of UTC ``t_ns``."""
    return m.Timestamp(sec=int(t_ns) // 1_000_000_000, nsec=int(t_ns) % 1_000_000_000)


def layout_json() -> str:
    """The Foxglove layout of docs/foxglove-layout.json (built with the SDK's ``foxglove.layouts``).

    Left: the camera with the detections, the running reprojection and the
    coverage drawn on it (the calibration topic lets Foxglove undistort).
    Right: the map (fixes and planned waypoints), the status and the
    calibration's numbers.
    """
    import foxglove.layouts as fl

    image = fl.ImagePanel(
        title="camera: detection (green), GNSS through the live calibration (red), coverage (blue) over the plan's ROI (grey)",
        config=fl.ImageConfig(image_mode=fl.ImageModeConfig(
            image_topic="/live/camera/image", calibration_topic="/live/camera/calibration",
            annotations={"/live/camera/annotations": fl.ImageAnnotationSettings(visible=True),
                         "/live/coverage": fl.ImageAnnotationSettings(visible=True)},
        )),
    )
    map_panel = fl.MapPanel(title="drone, flight path, waypoints, ROI and camera pole", config=fl.MapConfig(
        follow_topic="/live/gnss", zoom_level=21,
        topic_config={"/live/gnss": fl.MapTopicSettings(history_mode="all", point_size=3),
                      "/live/waypoints": fl.MapTopicSettings(), "/live/site": fl.MapTopicSettings()},
    ))
    status = fl.RawMessagesPanel(title="status, summary, verdict", config=fl.RawMessagesConfig(topic_path="/live/status", expansion="all"))
    calibration = fl.RawMessagesPanel(title="live calibration", config=fl.RawMessagesConfig(topic_path="/live/camera/calibration", expansion="all"))
    layout = fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=3, content=image),
        fl.SplitItem(proportion=2, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=3, content=map_panel),
            fl.SplitItem(proportion=1, content=status),
            fl.SplitItem(proportion=1, content=calibration),
        ])),
    ]))
    return json.dumps(json.loads(layout.to_json()), indent=2) + "\n"
