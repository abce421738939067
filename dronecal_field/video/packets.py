"""RTSP cameras and H.264/H.265 files as packets: access units, never decoded on the way to disk.

A camera's own stream is recorded as it arrived (``/camera/video``,
shared/contracts/run-format.md): one Annex B access unit per frame, the
parameter sets (SPS/PPS, and VPS for H.265) in front of every keyframe, no
B-frames. The pure parts live in :mod:`dronecal_field.video.nal` (NAL units) and
:mod:`dronecal_field.video.monitor` (lag, lost, corrupt); decoding in
:mod:`dronecal_field.video.decode`. This module is the capture shell.

Stamping (:class:`PacketSource`): RTSP cameras send RTCP sender reports that
tie the RTP clock to their wall clock (NTP); FFmpeg exposes the result as
``start_time_realtime`` (the wall time of pts 0, available after the first
report, ~2-5 s). A frame's capture time is then ``start_time_realtime + pts``
(clock ``rtcp``). Before a report, or from a camera that sends none, a frame is
stamped on the host clock through the floor of ``arrival - pts`` (clock
``arrival``): the stream's own pacing with the network's smallest delay, so a
backlog shows as lag instead of turning into stale timestamps.
"""

from __future__ import annotations

import collections
import time
from typing import Iterator

from dronecal_field.errors import VideoError
from dronecal_field.video.monitor import StreamIncident, StreamMonitor
from dronecal_field.video.nal import VideoFrame, access_unit, is_keyframe, join_annexb, merge_parts, parameter_sets, video_format
from dronecal_field.video.source import VideoSource


RTSP_TRANSPORTS = ("tcp", "udp")


class PacketSource(VideoSource):
    """An RTSP stream or a video file read as packets (PyAV, no decoding), one capture thread.

    A :class:`dronecal_field.video.VideoSource` (its capture thread, queue,
    ``read``, ``reopen``, ``close``, ``frames_dropped``, ``ended``), plus:

    Attributes
    ----------
    format : ``h264`` / ``h265``.
    width, height : image size from the stream parameters, pixels.
    clock : ``rtcp`` (stamps from the camera's sender reports), ``arrival``
        (host clock through the stream's pacing) or ``file`` (start + pts).
    monitor : the :class:`StreamMonitor` of the stream (lag, lost, corrupt).
    b_frames : the stream reorders frames (B-frames); refused by ``fly``.
    """

    def __init__(
        self,
        url: str,
        live: bool,
        timeout_s: float = 5.0,
        queue_size: int = 64,
        rtsp_transport: str = "tcp",
        start_ns: int | None = None,
    ) -> None:
        if rtsp_transport not in RTSP_TRANSPORTS:
            raise VideoError(f"--rtsp-transport {rtsp_transport!r}: use tcp or udp")
        super().__init__(url, live, timeout_s, queue_size)
        self.rtsp_transport = rtsp_transport
        self.format = ""
        self.width = 0
        self.height = 0
        self.fps: float | None = None
        self.clock = "file" if not live else "arrival"
        self.b_frames = False
        self.monitor = StreamMonitor()
        self.rtcp_delay_ns: int | None = None  # arrival - RTCP capture time, the smallest seen
        self._start_ns = time.time_ns() if start_ns is None else int(start_ns)
        self._clock_locked = False
        self._incidents: collections.deque[StreamIncident] = collections.deque()
        self._container = None
        self._params: list[bytes] = []
        self._length_size: int | None = None

    # -- public ------------------------------------------------------------

    def incidents(self) -> list[StreamIncident]:
        """Incidents since the last call (lag spans, lost frames, corrupt packets)."""
        out = []
        while self._incidents:
            out.append(self._incidents.popleft())
        return out

    def lock_clock(self) -> str:
        """Fix the stamping clock for the rest of the recording (one clock per run); returns it."""
        self._clock_locked = True
        return self.clock

    def reopen(self) -> None:
        """Close and connect again (a dropped stream); the pts clock starts again."""
        self._halt()
        self.monitor.reset()
        self.open()
        self.reconnects += 1

    def close(self) -> None:
        """Stop the capture thread and release the stream (idempotent)."""
        super().close()
        self._incidents.extend(self.monitor.close(time.time_ns()))

    # -- internals -----------------------------------------------------------

    def _connect(self) -> None:
        import av

        options = {}
        if self.url.lower().startswith(("rtsp://", "rtsps://")):
            options = {"rtsp_transport": self.rtsp_transport, "timeout": str(int(self.timeout_s * 1e6))}
        try:
            container = av.open(self.url, options=options, timeout=(self.timeout_s, self.timeout_s))
        except (av.FFmpegError, OSError) as exc:
            raise VideoError(f"video source {self.url}: cannot open it ({exc}); check the URL/path, the camera and --rtsp-transport") from exc
        streams = container.streams.video
        if not streams:
            container.close()
            raise VideoError(f"video source {self.url}: no video stream in it; give the camera's video URL")
        stream = streams[0]
        try:
            fmt = video_format(stream.codec_context.name)
        except VideoError:
            container.close()
            raise
        self.format = fmt
        self.width, self.height = int(stream.codec_context.width or 0), int(stream.codec_context.height or 0)
        rate = stream.average_rate or stream.guessed_rate
        self.fps = float(rate) if rate else None
        if self.fps and 1.0 <= self.fps <= 240.0 and self.monitor.frame_period_ns is None:
            self.monitor.frame_period_ns = int(1e9 / self.fps)
        self._params, self._length_size = parameter_sets(stream.codec_context.extradata, fmt)
        self._container = container

    def _disconnect(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            container, self._container = self._container, None
            if container is not None:
                container.close()

    def _stamp(self, arrival_ns: int, pts_ns: int, demux_pts_ns: int, realtime_us: int | None) -> int:
        if not self.live:
            return self._start_ns + pts_ns
        if realtime_us:
            capture = int(realtime_us) * 1000 + demux_pts_ns
            delay = arrival_ns - capture
            if self.rtcp_delay_ns is None or delay < self.rtcp_delay_ns:
                self.rtcp_delay_ns = delay
            if not self._clock_locked:
                self.clock = "rtcp"
            if self.clock == "rtcp":
                return capture
        floor = self.monitor.floor_ns()
        return arrival_ns if floor is None else floor + pts_ns

    def _frames(self) -> Iterator[VideoFrame]:
        import av

        container = self._container
        if container is None:
            return
        stream = container.streams.video[0]
        tb = stream.time_base
        first_pts: int | None = None
        fmt = self.format
        # Parts of one access unit: a demuxer may cut a frame in two (GStreamer's payloader repeats
        # SPS/PPS before each IDR slice, and FFmpeg's parser starts a new packet there).
        parts: list[bytes] = []
        part_pts: int | None = None
        part_arrival = 0
        part_key = part_corrupt = False

        def finish() -> VideoFrame | None:
            if not parts or part_pts is None:
                return None
            pts_ns = int((part_pts - first_pts) * tb * 1_000_000_000)
            # RTCP's start_time_realtime is the wall time of the demuxer's pts 0, not of our first frame.
            demux_pts_ns = int(part_pts * tb * 1_000_000_000)
            nals = merge_parts(parts, fmt, self._length_size)
            key = part_key or is_keyframe(join_annexb(nals[:8]), fmt)
            au = access_unit(join_annexb(nals), fmt, key, self._params, None)
            for incident in self.monitor.observe(part_arrival, pts_ns, corrupt=part_corrupt):
                self._incidents.append(incident)
            t_ns = self._stamp(part_arrival, pts_ns, demux_pts_ns, container.start_time_realtime if self.live else None)
            return VideoFrame(timestamp_ns=t_ns, format=fmt, data=au, keyframe=key, pts_ns=pts_ns)

        try:
            for packet in container.demux(stream):
                if self._stop.is_set():
                    return
                arrival_ns = time.time_ns()
                if packet.size == 0:
                    continue  # the demuxer's end-of-stream flush packet
                pts = packet.pts
                if pts is not None and packet.dts is not None and pts != packet.dts:
                    self.b_frames = True
                if pts is not None and part_pts is not None and pts != part_pts:
                    frame = finish()
                    parts = []
                    if frame is not None:
                        yield frame
                if not parts:
                    part_arrival, part_key, part_corrupt = arrival_ns, False, False
                parts.append(bytes(packet))
                part_key = part_key or bool(packet.is_keyframe)
                part_corrupt = part_corrupt or bool(packet.is_corrupt)
                if pts is not None:
                    part_pts = pts
                    if first_pts is None:
                        first_pts = pts
            frame = finish()
            if frame is not None:
                yield frame
        except av.FFmpegError as exc:
            if not self._stop.is_set():
                raise VideoError(f"video source {self.url}: {exc}") from exc
        finally:
            if self._container is container:
                self._container = None
            container.close()


def open_packet_source(url: str, timeout_s: float = 5.0, rtsp_transport: str = "tcp", queue_size: int = 64) -> PacketSource:
    """Open an ``rtsp://`` URL or a video file as an H.264/H.265 packet source (started).

    Raises
    ------
    VideoError
        when it cannot be opened or is not H.264 / H.265.
    """
    live = url.lower().startswith(("rtsp://", "rtsps://"))
    path = url[len("file://"):] if url.lower().startswith("file://") else url
    source = PacketSource(path, live=live, timeout_s=timeout_s, queue_size=queue_size, rtsp_transport=rtsp_transport)
    source.open()
    return source
