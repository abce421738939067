"""Each camera before recording: opened, probed (rate, size, keyframes, the RTCP clock), judged, described.

``fly`` probes every ``--video`` here before the pre-flight checklist, and
asks here how each camera's frames are stamped for the run's metadata
(``camera.clock`` of a single camera, ``camera.<name>.clock`` of several).
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, replace
from typing import Any


def probe_video(url: str, first_timeout_s: float = 5.0, probe_s: float = 1.0, rtsp_transport: str = "tcp", rtcp_wait_s: float = 6.0,
                queue_size: int = 16):
    """Open the stream, read the first frame and count frames for ``probe_s``: (source, first, VideoStatus).

    An H.264/H.265 stream (RTSP, files) is probed without decoding; over RTSP
    the probe waits up to ``rtcp_wait_s`` for the camera's first RTCP sender
    report, so that the recording is stamped at capture from its first frame.
    """
    from dronecal_field.errors import VideoError
    from dronecal_field.mavlink.preflight import VideoStatus
    from dronecal_field.video import open_video

    try:
        source = open_video(url, rtsp_transport=rtsp_transport, queue_size=queue_size)
    except VideoError as exc:
        return None, None, VideoStatus(url=url, error=str(exc))
    first = source.read(timeout_s=first_timeout_s)
    if first is None:
        return source, None, VideoStatus(url=url, frames=0)
    if first.format in ("h264", "h265"):
        from dronecal_field.video.probe import probe_packet_stream

        probe = probe_packet_stream(source, first, probe_s=probe_s, rtcp_wait_s=rtcp_wait_s)  # the stream's rate, a keyframe decoded
        if source.b_frames or source.monitor.reordered:
            return source, None, VideoStatus(
                url=url, frames=probe.frames, error="the camera sends B-frames (frames out of order); set its encoder to no B-frames (IP frames only, e.g. H.264 baseline)"
            )
        return source, first, VideoStatus(url=url, frames=probe.frames, fps=probe.fps or 0.0, width=source.width, height=source.height,
                                          warning=probe.warning)
    import cv2
    import numpy as np

    image = cv2.imdecode(np.frombuffer(first.data, np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        return source, None, VideoStatus(url=url, frames=1, error="the first frame is not a decodable image")
    height, width = image.shape[:2]
    frames, t0 = 1, time.monotonic()
    while time.monotonic() - t0 < probe_s:
        if source.read(timeout_s=probe_s) is not None:
            frames += 1
    fps = (frames - 1) / max(time.monotonic() - t0, 1e-6)
    return source, first, VideoStatus(url=url, frames=frames, fps=fps, width=width, height=height)


def judge_video(status, plan_json: dict | None, args: argparse.Namespace):
    """Fail the video check for a still image or a stalled stream, or a size other than the plan's camera."""
    from dataclasses import replace

    if status.error or not status.frames:
        return status
    if status.frames < 2 or status.fps < 1.0:
        return replace(status, error=f"{status.url} sent {status.frames} frame(s) in the probe ({status.fps:.1f} fps): "
                                     "a still image or a stalled stream; give the camera's live stream")
    guess = (plan_json or {}).get("camera_guess") or {}
    w, h = guess.get("width"), guess.get("height")
    if args.camera_width is None and args.camera_height is None and w and h and (w, h) != (status.width, status.height):
        return replace(status, error=f"{status.url} sends {status.width}x{status.height} but the plan's camera is {w}x{h} (plan.json): "
                                     f"re-plan with --image-size {status.width}x{status.height} or set the camera's resolution")
    return status


@dataclass
class ProbedCamera:
    """One --video as probed: its spec (name, url), open source, first frame and pre-flight status."""

    spec: Any
    source: Any
    first: Any
    status: Any


def probe_cameras(args: argparse.Namespace, plan_json: dict | None) -> list[ProbedCamera]:
    """Every --video probed at once (one thread each: four RTSP cameras wait for their RTCP reports together), judged."""
    from concurrent.futures import ThreadPoolExecutor

    from dronecal_field.recording.cameras import camera_plan

    specs = args.videos
    with ThreadPoolExecutor(max_workers=len(specs)) as pool:
        # Several cameras: each source holds more frames (64) for its reader thread, which shares the interpreter with
        # the others: at 10 fps a 1.6 s stall of it overflowed the default 16 (bench_site_fly: 29 dropped per MJPEG camera).
        queue = 16 if len(specs) == 1 else 64
        probed = list(pool.map(lambda spec: probe_video(spec.url, rtsp_transport=args.rtsp_transport, queue_size=queue), specs))
    cams = []
    for spec, (source, first, status) in zip(specs, probed):
        plan = plan_json if spec.name is None else camera_plan(plan_json, spec.name)
        cams.append(ProbedCamera(spec, source, first, judge_video(status, plan, args)))
    return cams


def camera_checks(results: list, cams: list[ProbedCamera]) -> list:
    """The checklist with one ``video NAME`` line per camera in place of the single ``video`` line."""
    from dronecal_field.mavlink.preflight import CheckResult

    out = [r for r in results if r.name != "video"]
    for cam in cams:
        v, name = cam.status, f"video {cam.spec.name}"
        if v.error:
            out.append(CheckResult(name, False, v.error if v.url in v.error else f"{v.url}: {v.error}"))
        elif v.frames == 0:
            out.append(CheckResult(name, False, f"{v.url} opened but sent no frame; check the camera stream"))
        elif v.warning:
            out.append(CheckResult(name, True, f"WARNING: {v.width}x{v.height}, {v.fps:.1f} fps, but {v.warning}", warning=True))
        else:
            out.append(CheckResult(name, True, f"{v.width}x{v.height}, {v.fps:.1f} fps"))
    return out


def run_camera(cam, args):
    """The RunCamera of one named camera: its topic, size, and how its frames are stamped (``camera.<name>.clock``)."""
    from dronecal_field.runfile.writer import RunCamera

    extra = {"url": cam.spec.url}
    if cam.first is not None and cam.first.format in ("h264", "h265"):
        clock = cam.source.lock_clock()  # one clock for the whole run, per camera
        extra["timestamps"] = CLOCK_TIMESTAMPS[clock]
        extra["rtsp_transport"] = args.rtsp_transport
        if cam.source.rtcp_delay_ns is not None:
            extra["rtcp_to_arrival_s"] = repr(cam.source.rtcp_delay_ns / 1e9)
        latency = 0.0 if clock == "rtcp" else args.camera_latency
        return RunCamera(name=cam.spec.name, topic="video", width=int(cam.status.width), height=int(cam.status.height),
                         latency_s=latency, clock=clock, extra=extra)
    extra["timestamps"] = "host UTC at frame arrival"
    return RunCamera(name=cam.spec.name, topic="image", width=int(cam.status.width), height=int(cam.status.height),
                     latency_s=args.camera_latency, clock="arrival", extra=extra)


CLOCK_TIMESTAMPS = {
    "rtcp": "capture time: RTP presentation time through the camera's RTCP sender reports (its wall clock)",
    "arrival": "host UTC at arrival through the stream's own pacing (smallest network delay); no RTCP sender report",
    "file": "recording start + presentation time in the file",
}


def video_metadata(metadata, source, args):
    """The run metadata of a /camera/video recording: how its frames are stamped (``camera.clock``)."""
    clock = source.lock_clock()  # one clock for the whole run
    extra = dict(metadata.extra)
    extra["camera.clock"] = clock
    extra["camera.timestamps"] = CLOCK_TIMESTAMPS[clock]
    extra["video.rtsp_transport"] = args.rtsp_transport
    if source.rtcp_delay_ns is not None:
        extra["camera.rtcp_to_arrival_s"] = repr(source.rtcp_delay_ns / 1e9)  # network + camera clock offset, measured
    latency = 0.0 if clock == "rtcp" else args.camera_latency
    return replace(metadata, camera_latency_s=latency, extra=extra)
