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
import queue
import threading
import time
from dataclasses import dataclass
from typing import Iterator

from dronecal_field.errors import VideoError
from dronecal_field.video.decode import check_keyframe
from dronecal_field.video.monitor import StreamIncident, StreamMonitor
from dronecal_field.video.nal import VideoFrame, access_unit, is_keyframe, join_annexb, merge_parts, parameter_sets, starts_picture, video_format
from dronecal_field.video.source import VideoSource


RTSP_TRANSPORTS = ("tcp", "udp")


@dataclass
class _Unit:
    """One access unit on its way out of the capture thread (internal)."""

    arrival_ns: int
    pts: int | None  # in the stream's time base, as demuxed
    data: bytes
    key: bool
    corrupt: bool


class PacketSource(VideoSource):
    """An RTSP stream or a video file read as packets (PyAV, no decoding), one capture thread.

    A :class:`dronecal_field.video.source.VideoSource` (its capture thread,
    queue, ``read``, ``reopen``, ``close``, ``frames_dropped``, ``ended``), plus:

    Attributes
    ----------
    format : ``h264`` / ``h265``.
    width, height : image size from the stream parameters, pixels.
    fps : the stream's nominal frame rate (its parameters), or None.
    clock : ``rtcp`` (stamps from the camera's sender reports), ``arrival``
        (host clock through the stream's pacing) or ``file`` (start + pts).
    monitor : the :class:`StreamMonitor` of the stream (lag, lost, corrupt).
    b_frames : the stream reorders frames (B-frames); refused by ``fly``.
    sessions : connections made (1, plus one per ``reopen``).
    burst_frames : access units that arrived in an opening burst (FFmpeg
        reads the first second or so while opening and hands it over at
        once); held until the stream's pacing is known, then stamped by it.
    frames_bridged : frames of a later session stamped, before its first
        RTCP sender report, on the ``rtcp`` clock by estimate: the session's
        median ``arrival - pts`` (paced frames) + pts - the median RTCP delay
        (arrival - capture) of the frames before.
    bridge_errors_ns : per later session, the bridged stamp minus the
        capture time its first sender report gave for the same frame (the
        estimate's error; the step at the hand-over is short by as much).
    stamps_raised : stamps raised by 1 ns over the previous frame's so time
        never runs backwards (a bridged estimate meeting the next report).
    frames_before_keyframe : access units dropped because no keyframe came
        before them: at the start of a session, and from the start of the
        recording (:meth:`lock_clock`) to its first keyframe.
    keyframes_checked, keyframes_unchecked, units_undecodable : keyframes
        decoded on their own by the checker thread (live streams; at most one
        every ``check_every_s`` of stream time: a 4K H.265 keyframe costs
        ~0.1 s of CPU, 5 % of a core at one every 2 s), those it skipped, and
        those that did not decode cleanly (truncated, corrupt: also
        ``video_corrupt`` incidents). A server that cuts keyframes cuts them
        all, so a sample finds it.
    last_decode_error : the decoder's word on the last undecodable keyframe.
    """

    def __init__(
        self,
        url: str,
        live: bool,
        timeout_s: float = 5.0,
        queue_size: int = 64,
        rtsp_transport: str = "tcp",
        start_ns: int | None = None,
        check_keyframes: bool | None = None,
        check_every_s: float = 5.0,
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
        self.sessions = 0
        self.burst_frames = 0
        self.frames_bridged = 0
        self.stamps_raised = 0
        self.frames_before_keyframe = 0
        self.keyframes_checked = 0
        self.keyframes_unchecked = 0
        self.units_undecodable = 0
        self.last_decode_error: str | None = None
        self.last_checked: tuple[VideoFrame, object] | None = None  # (keyframe, its luma) the checker decoded last
        self._start_ns = time.time_ns() if start_ns is None else int(start_ns)
        self._clock_locked = False
        self._await_keyframe = False
        self._record_from_ns = 0
        self._last_stamp_ns: int | None = None
        self._bridging = False
        self.bridge_errors_ns: list[int] = []
        self._rtcp_delays: collections.deque[int] = collections.deque(maxlen=101)  # arrival - capture, paced frames
        self._session_offsets: collections.deque[int] = collections.deque(maxlen=101)  # arrival - pts, this session
        self._incidents: collections.deque[StreamIncident] = collections.deque()
        self._container = None
        self._params: list[bytes] = []
        self._length_size: int | None = None
        self._check = bool(live) if check_keyframes is None else bool(check_keyframes)
        self._check_every_ns = int(max(0.0, check_every_s) * 1e9)
        self._checked_at_ns: int | None = None
        self._check_queue: queue.Queue[VideoFrame | None] = queue.Queue(maxsize=1)
        self._checker: threading.Thread | None = None

    # -- public ------------------------------------------------------------

    def incidents(self) -> list[StreamIncident]:
        """Incidents since the last call (lag spans, lost frames, corrupt packets, undecodable keyframes)."""
        out = []
        while self._incidents:
            out.append(self._incidents.popleft())
        return out

    def lock_clock(self, start_ns: int | None = None) -> str:
        """The recording starts: fix the stamping clock for the rest of it (one clock per run) and return it.

        From then on :meth:`read` drops the access units stamped before
        ``start_ns`` (UTC ns, default now: they are not recorded anyway) and
        those after it up to the first keyframe (counted in
        ``frames_before_keyframe``): the recording starts with a decodable
        access unit.
        """
        self._clock_locked = True
        self._await_keyframe = True
        self._record_from_ns = time.time_ns() if start_ns is None else int(start_ns)
        return self.clock

    def read(self, timeout_s: float = 1.0) -> VideoFrame | None:
        """The next access unit (see :meth:`VideoSource.read`); from the recording's start on, starting at a keyframe."""
        deadline = time.monotonic() + max(0.0, timeout_s)
        while True:
            frame = super().read(timeout_s=max(0.0, deadline - time.monotonic()))
            if frame is None or not self._await_keyframe:
                return frame
            if frame.timestamp_ns < self._record_from_ns:
                continue  # from before the recording: not recorded in any case
            if frame.keyframe:
                self._await_keyframe = False
                return frame
            self.frames_before_keyframe += 1

    def reopen(self) -> None:
        """Close and connect again (a dropped stream); the pts clock starts again, the stamps stay on the run's clock."""
        self._halt()
        self.monitor.reset()
        self.open()
        self.reconnects += 1

    def close(self) -> None:
        """Stop the capture thread and the checker and release the stream (idempotent)."""
        super().close()
        checker, self._checker = self._checker, None
        if checker is not None:
            try:
                self._check_queue.put(None, timeout=1.0)
            except queue.Full:
                pass
            checker.join(timeout=5.0)
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
        self.sessions += 1

    def _disconnect(self) -> None:
        if self._thread is None or not self._thread.is_alive():
            container, self._container = self._container, None
            if container is not None:
                container.close()

    def _stamp(self, arrival_ns: int, pts_ns: int, demux_pts_ns: int, realtime_us: int | None, paced: bool = True) -> int:
        """The frame's stamp on the run's one clock, never before the previous frame's.

        ``paced``: the frame arrived at the stream's pace (not in an opening
        burst), so its arrival says something about the network's delay.
        """
        t_ns = None
        if paced:
            self._session_offsets.append(arrival_ns - pts_ns)
        if not self.live:
            t_ns = self._start_ns + pts_ns
        elif realtime_us:
            capture = int(realtime_us) * 1000 + demux_pts_ns
            if self._bridging:  # this session's first report: how far the bridged stamps were from it
                self._bridging = False
                estimate = self._bridged(arrival_ns, pts_ns)
                if estimate is not None:
                    self.bridge_errors_ns.append(estimate - capture)
            delay = arrival_ns - capture
            if self.rtcp_delay_ns is None or delay < self.rtcp_delay_ns:
                self.rtcp_delay_ns = delay
            if paced:
                self._rtcp_delays.append(delay)
            if not self._clock_locked:
                self.clock = "rtcp"
            if self.clock == "rtcp":
                t_ns = capture
        if t_ns is None and self.clock == "rtcp":
            t_ns = self._bridged(arrival_ns, pts_ns)
            if t_ns is not None:
                self.frames_bridged += 1
                self._bridging = True
        if t_ns is None:
            floor = self.monitor.floor_ns()
            t_ns = arrival_ns if floor is None else floor + pts_ns
        if self._last_stamp_ns is not None and t_ns <= self._last_stamp_ns:
            t_ns = self._last_stamp_ns + 1
            self.stamps_raised += 1
        self._last_stamp_ns = t_ns
        return t_ns

    def _bridged(self, arrival_ns: int, pts_ns: int) -> int | None:
        """Capture time of a frame of a session without its RTCP report yet: the session's typical
        ``arrival - pts`` (median over its paced frames) + pts - the typical RTCP delay seen before
        (median over the last 101 paced frames); None before any report."""
        if not self._rtcp_delays:
            return None
        offsets = sorted(self._session_offsets) if self._session_offsets else [arrival_ns - pts_ns]
        delays = sorted(self._rtcp_delays)
        return offsets[len(offsets) // 2] + pts_ns - delays[len(delays) // 2]

    def _frames(self) -> Iterator[VideoFrame]:
        """Access units of this connection: packets joined into pictures, the opening burst held, stamped."""
        container = self._container
        if container is None:
            return
        stream = container.streams.video[0]
        tb = stream.time_base
        fmt = self.format
        period_ns = self.monitor.period_ns
        first_pts: int | None = None
        last_pts: int | None = None
        seen_key = False
        settling = self.live  # the opening burst: held until a frame arrives at the stream's pace
        held: list[_Unit] = []
        self._session_offsets.clear()
        self._bridging = False

        def to_ns(pts: int) -> int:
            return int(pts * tb * 1_000_000_000)

        def emit(unit: _Unit, observe: bool = True, paced: bool = True) -> VideoFrame:
            pts_ns = to_ns(unit.pts - first_pts)
            if observe:
                self._incidents.extend(self.monitor.observe(unit.arrival_ns, pts_ns, corrupt=unit.corrupt))
            realtime = container.start_time_realtime if self.live else None
            # RTCP's start_time_realtime is the wall time of the demuxer's pts 0, not of our first frame.
            t_ns = self._stamp(unit.arrival_ns, pts_ns, to_ns(unit.pts), realtime, paced)
            frame = VideoFrame(timestamp_ns=t_ns, format=fmt, data=unit.data, keyframe=unit.key, pts_ns=pts_ns)
            if unit.key and self._check:
                self._offer_check(frame)
            return frame

        def release() -> list[VideoFrame]:
            nonlocal first_pts
            step = to_ns(1) or 1
            per = period_ns or self.monitor.period_ns or 40_000_000
            for i in range(len(held) - 2, -1, -1):  # an access unit without pts: one frame before the next
                if held[i].pts is None and held[i + 1].pts is not None:
                    held[i].pts = held[i + 1].pts - max(1, per // step)
            units = [u for u in held if u.pts is not None]
            held.clear()
            if not units:
                return []
            first_pts = units[0].pts if first_pts is None else first_pts
            self.burst_frames += max(0, len(units) - 1)
            for u in units:  # the pacing (the floor of arrival - pts) from every one of them, then the stamps
                self._incidents.extend(self.monitor.observe(u.arrival_ns, to_ns(u.pts - first_pts), corrupt=u.corrupt))
            last = units[-1]  # the one that came at the stream's pace: the session's first say on its delay
            self._session_offsets.append(last.arrival_ns - to_ns(last.pts - first_pts))
            return [emit(u, observe=False, paced=False) for u in units]

        def accept(unit: _Unit) -> list[VideoFrame]:
            nonlocal seen_key, settling, first_pts, last_pts
            if not seen_key:
                if not unit.key:
                    self.frames_before_keyframe += 1  # no reference picture before it: undecodable
                    return []
                seen_key = True
            if unit.pts is None and last_pts is not None:
                unit.pts = last_pts + max(1, (period_ns or self.monitor.period_ns or 40_000_000) // (to_ns(1) or 1))
            if unit.pts is not None:
                last_pts = unit.pts
            if not settling:
                if unit.pts is None:
                    return []
                first_pts = unit.pts if first_pts is None else first_pts
                return [emit(unit)]
            held.append(unit)
            paced = len(held) >= 2 and _arrived_at_pace(held[-2], held[-1], to_ns)
            if paced or len(held) >= 250:
                settling = False
                return release()
            return []

        yield from self._demux_units(container, stream, fmt, accept)
        if held:
            yield from release()

    def _demux_units(self, container, stream, fmt: str, accept) -> Iterator[VideoFrame]:
        """Packets -> access units (a picture may come in several packets) -> ``accept`` -> frames."""
        import av

        # Parts of one access unit: a demuxer may cut a frame in two (GStreamer's payloader repeats
        # SPS/PPS before each IDR slice, and FFmpeg's parser starts a new packet there); a packet
        # whose first slice starts a picture starts a new one even when it carries no pts.
        parts: list[bytes] = []
        part_pts: int | None = None
        part_arrival = 0
        part_key = part_corrupt = part_vcl = False

        def finish() -> _Unit | None:
            if not parts:
                return None
            nals = merge_parts(parts, fmt, self._length_size)
            key = part_key or is_keyframe(join_annexb(nals[:8]), fmt)
            au = access_unit(join_annexb(nals), fmt, key, self._params, None)
            return _Unit(part_arrival, part_pts, au, key, part_corrupt)

        try:
            for packet in container.demux(stream):
                if self._stop.is_set():
                    return
                arrival_ns = time.time_ns()
                if packet.size == 0:
                    continue  # the demuxer's end-of-stream flush packet
                data = bytes(packet)
                pts = packet.pts if packet.pts is not None else packet.dts
                if packet.pts is not None and packet.dts is not None and packet.pts != packet.dts:
                    self.b_frames = True
                new_picture = self._length_size is None and part_vcl and starts_picture(data, fmt)
                if parts and ((pts is not None and part_pts is not None and pts != part_pts) or new_picture):
                    unit = finish()
                    parts = []
                    if unit is not None:
                        yield from accept(unit)
                if not parts:
                    part_arrival, part_pts, part_key, part_corrupt, part_vcl = arrival_ns, None, False, False, False
                parts.append(data)
                part_key = part_key or bool(packet.is_keyframe)
                part_corrupt = part_corrupt or bool(packet.is_corrupt)
                part_vcl = part_vcl or (self._length_size is None and starts_picture(data, fmt) is not None)
                if pts is not None:
                    part_pts = pts
            unit = finish()
            if unit is not None:
                yield from accept(unit)
        except av.FFmpegError as exc:
            if not self._stop.is_set():
                raise VideoError(f"video source {self.url}: {exc}") from exc
        finally:
            if self._container is container:
                self._container = None
            container.close()

    def _offer_check(self, frame: VideoFrame) -> None:
        """Hand a keyframe to the checker thread; skipped (counted) within ``check_every_s`` of the last one
        handed over, or while the checker is busy with it."""
        if self._checked_at_ns is not None and frame.timestamp_ns - self._checked_at_ns < self._check_every_ns:
            self.keyframes_unchecked += 1
            return
        if self._checker is None:
            self._checker = threading.Thread(target=self._check_loop, name=f"video-check:{self.url}", daemon=True)
            self._checker.start()
        try:
            self._check_queue.put_nowait(frame)
            self._checked_at_ns = frame.timestamp_ns
        except queue.Full:
            self.keyframes_unchecked += 1

    def _check_loop(self) -> None:
        while True:
            frame = self._check_queue.get()
            if frame is None:
                return
            error, gray = check_keyframe(frame.data, frame.format)
            if gray is not None:
                self.last_checked = (frame, gray)  # one assignment: the recorder's marker probe reads it from another thread
            self.keyframes_checked += 1
            if error is not None:
                self.units_undecodable += 1
                self.last_decode_error = error
                self._incidents.append(StreamIncident("video_corrupt", frame.timestamp_ns, frame.timestamp_ns, 1.0))


def _arrived_at_pace(a: _Unit, b: _Unit, to_ns) -> bool:
    """``b`` came at least half its presentation step after ``a``: no longer the opening burst."""
    if a.pts is None or b.pts is None or b.pts <= a.pts:
        return False
    return b.arrival_ns - a.arrival_ns >= to_ns(b.pts - a.pts) // 2


def open_packet_source(url: str, timeout_s: float = 5.0, rtsp_transport: str = "tcp", queue_size: int = 64,
                       check_every_s: float = 5.0) -> PacketSource:
    """Open an ``rtsp://`` URL or a video file as an H.264/H.265 packet source (started).

    Raises
    ------
    VideoError
        when it cannot be opened or is not H.264 / H.265.
    """
    live = url.lower().startswith(("rtsp://", "rtsps://"))
    path = url[len("file://"):] if url.lower().startswith("file://") else url
    source = PacketSource(path, live=live, timeout_s=timeout_s, queue_size=queue_size, rtsp_transport=rtsp_transport,
                          check_every_s=check_every_s)
    source.open()
    return source
