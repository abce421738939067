"""The live state on a Foxglove WebSocket (foxglove-sdk), loopback by default.

Topics (every one a Foxglove schema, protobuf, except the JSON status):

=============================  ==========================  ==============================================
topic                          schema                      what
=============================  ==========================  ==============================================
/live/camera/image             foxglove.CompressedImage    the camera, ~2 frames a second (JPEG as recorded)
/live/camera/annotations       foxglove.ImageAnnotations   the detection (green quad) and where the running
                                                           calibration puts the marker from GNSS (red circle)
/live/coverage                 foxglove.ImageAnnotations   every marker centre seen so far (blue dots), the
                                                           plan's ROI cells (grey outlines)
/live/camera/calibration       foxglove.CameraCalibration  the running calibration (plumb_bob)
/live/gnss                     foxglove.LocationFix        the drone's fixes
/live/waypoints                foxglove.GeoJSON            the planned waypoints, coloured by outcome
/live/status                   JSON                        status line, last summary, final verdict
=============================  ==========================  ==============================================

Foxglove keeps no message for a late client, so the worker publishes the
whole state again twice a second. docs/foxglove-layout.json opens it all.
"""

from __future__ import annotations

import json
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
        self.status = foxglove.Channel("/live/status", schema={"type": "object"}, context=ctx)
        self.server = foxglove.start_server(name="dronecal-field fly", host=host, port=port, context=ctx)
        self._mission: Any = None
        self._roi_outlines: list[np.ndarray] = []
        self._last_fix_ns = 0

    @property
    def port(self) -> int:
        return int(self.server.port)

    def close(self) -> None:
        self.server.stop()

    # ----- the plan (once) -----
    def set_plan(self, mission: Any, roi: Any) -> None:
        """The mission flown (waypoints on the map) and the plan's image ROI (coverage outlines), or None."""
        self._mission = mission
        self._roi_outlines = list(roi.outline_uv()) if roi is not None else []
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

    def publish_fixes(self, fixes: list[Any]) -> None:
        """The fixes not sent before (GnssFix records), as LocationFix."""
        m = self._fg.messages
        for fix in fixes:
            if fix.timestamp_ns <= self._last_fix_ns:
                continue
            self._last_fix_ns = fix.timestamp_ns
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
    map_panel = fl.MapPanel(title="drone and waypoints", config=fl.MapConfig(
        follow_topic="/live/gnss", zoom_level=21,
        topic_config={"/live/gnss": fl.MapTopicSettings(history_mode="all", point_size=3)},
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
