"""Compressed video pass-through: H.264 / H.265 access units, never decoded on the way to disk.

A camera's own stream is recorded as it arrived (``/camera/video``,
shared/contracts/run-format.md): one Annex B access unit per frame, the
parameter sets (SPS/PPS, and VPS for H.265) in front of every keyframe, no
B-frames. Three layers, as everywhere in the project:

- pure functions on bytes: Annex B / length-prefixed (avcC, hvcC) NAL units,
  parameter sets from extradata, keyframe tests (:func:`access_unit`,
  :func:`is_keyframe`, :func:`parameter_sets`);
- :class:`StreamMonitor`, pure arithmetic on (arrival, presentation time)
  pairs: the lag behind the stream's own clock, pts gaps (lost frames) and
  corrupt packets, as :class:`StreamIncident` records;
- the PyAV shells: :class:`PacketSource` (RTSP or a file, packets only, one
  capture thread) and :class:`VideoFrameDecoder` (the offline stage's decoder,
  which decodes from the keyframe before a wanted frame and nothing after it).

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
from dataclasses import dataclass
from typing import Iterator

from dronecal_field.errors import VideoError
from dronecal_field.runfile.records import Frame
from dronecal_field.video import VideoSource

VIDEO_FORMATS = ("h264", "h265")
_CODEC_OF_FORMAT = {"h264": "h264", "h265": "hevc"}
_FORMAT_OF_CODEC = {"h264": "h264", "hevc": "h265", "h265": "h265"}
START_CODE = b"\x00\x00\x00\x01"

# NAL unit types: parameter sets, keyframe slices, access unit delimiters.
_PARAM_TYPES = {"h264": (7, 8), "h265": (32, 33, 34)}
_KEY_TYPES = {"h264": (5,), "h265": (16, 17, 18, 19, 20, 21)}  # IDR; H.265 IRAP (BLA, IDR, CRA)
_VCL_TYPES = {"h264": range(1, 6), "h265": range(0, 32)}


@dataclass(frozen=True)
class VideoFrame(Frame):
    """One access unit of an H.264 / H.265 stream (``format`` ``h264`` or ``h265``).

    Attributes
    ----------
    keyframe : the access unit starts a GOP (IDR / IRAP) and carries its parameter sets.
    pts_ns : presentation time in the stream's own clock, ns from its first
        frame; None when the source gives none (frames read back from a run).
    """

    keyframe: bool = False
    pts_ns: int | None = None


# --- pure: NAL units ---------------------------------------------------------


def video_format(codec_name: str) -> str:
    """``h264`` / ``h265`` of an FFmpeg codec name; VideoError for anything else."""
    fmt = _FORMAT_OF_CODEC.get(codec_name.lower())
    if fmt is None:
        raise VideoError(
            f"the stream is {codec_name}, not H.264 or H.265; set the camera to H.264/H.265, or use its MJPEG stream (http://)"
        )
    return fmt


def nal_type(nal: bytes, fmt: str) -> int:
    """The NAL unit type of one NAL unit (its header first, no start code)."""
    if not nal:
        return -1
    return nal[0] & 0x1F if fmt == "h264" else (nal[0] >> 1) & 0x3F


def split_annexb(data: bytes) -> list[bytes]:
    """NAL units of an Annex B byte stream, start codes (3 or 4 bytes) removed.

    Emulation prevention guarantees ``00 00 01`` never occurs inside a NAL
    unit, so finding start codes finds the units; a trailing zero of a 4-byte
    start code is trimmed from the unit before it.
    """
    out = []
    i = data.find(b"\x00\x00\x01")
    while i >= 0:
        start = i + 3
        j = data.find(b"\x00\x00\x01", start)
        end = len(data) if j < 0 else j
        nal = data[start:end]
        if j >= 0:
            nal = nal.rstrip(b"\x00")  # the leading zero of the next 4-byte start code (trailing_zero_8bits)
        if nal:
            out.append(nal)
        i = j
    return out


def split_length_prefixed(data: bytes, length_size: int) -> list[bytes]:
    """NAL units of an MP4/MKV sample (each unit prefixed by its big-endian length)."""
    out = []
    pos, n = 0, len(data)
    while pos + length_size <= n:
        size = int.from_bytes(data[pos : pos + length_size], "big")
        pos += length_size
        if size <= 0 or pos + size > n:
            break
        out.append(data[pos : pos + size])
        pos += size
    return out


def join_annexb(nals: list[bytes]) -> bytes:
    """An Annex B byte stream of NAL units (4-byte start codes)."""
    return b"".join(START_CODE + n for n in nals)


def parameter_sets(extradata: bytes | None, fmt: str) -> tuple[list[bytes], int | None]:
    """(parameter-set NAL units, NAL length size) of a stream's extradata.

    Extradata is either an ``avcC`` / ``hvcC`` record (MP4, MKV: the samples
    are then length-prefixed with the returned size) or Annex B (RTSP's SDP
    ``sprop-parameter-sets``: size None).
    """
    if not extradata:
        return [], None
    data = bytes(extradata)
    if fmt == "h264" and data[0] == 1 and len(data) >= 7:
        length_size = (data[4] & 0x03) + 1
        nals, pos = [], 5
        count = data[pos] & 0x1F
        pos += 1
        for table in range(2):
            if table == 1:
                if pos >= len(data):
                    break
                count = data[pos]
                pos += 1
            for _ in range(count):
                size = int.from_bytes(data[pos : pos + 2], "big")
                nals.append(data[pos + 2 : pos + 2 + size])
                pos += 2 + size
        return [n for n in nals if n], length_size
    if fmt == "h265" and data[0] == 1 and len(data) >= 23:
        length_size = (data[21] & 0x03) + 1
        nals, pos = [], 23
        for _ in range(data[22]):
            pos += 1  # array_completeness, reserved, NAL_unit_type
            count = int.from_bytes(data[pos : pos + 2], "big")
            pos += 2
            for _ in range(count):
                size = int.from_bytes(data[pos : pos + 2], "big")
                nals.append(data[pos + 2 : pos + 2 + size])
                pos += 2 + size
        return [n for n in nals if n], length_size
    return [n for n in split_annexb(data) if nal_type(n, fmt) in _PARAM_TYPES[fmt]], None


def access_unit(
    data: bytes,
    fmt: str,
    keyframe: bool,
    params: list[bytes],
    length_size: int | None = None,
) -> bytes:
    """One access unit in Annex B, the parameter sets in front when it is a keyframe that lacks them.

    Parameters
    ----------
    data : the packet: Annex B (RTSP, .ts, .h264) or length-prefixed (MP4/MKV, ``length_size`` given).
    fmt : ``h264`` or ``h265``.
    keyframe : the packet starts a GOP.
    params : the stream's parameter sets (:func:`parameter_sets`), for keyframes without in-band ones.
    length_size : NAL length size of a length-prefixed packet; None for Annex B.
    """
    if length_size is None:
        if not keyframe or not params:
            return bytes(data)
        nals = split_annexb(bytes(data))
    else:
        nals = split_length_prefixed(bytes(data), length_size)
        if not keyframe or not params:
            return join_annexb(nals)
    types = {nal_type(n, fmt) for n in nals}
    if keyframe and params and not all(nal_type(p, fmt) in types for p in params):
        nals = [n for n in nals if nal_type(n, fmt) not in _PARAM_TYPES[fmt]]
        # An access unit delimiter stays first (H.264 7.4.1.2.3).
        head = [n for n in nals[:1] if nal_type(n, fmt) == (9 if fmt == "h264" else 35)]
        nals = head + list(params) + nals[len(head):]
    return join_annexb(nals)


def is_keyframe(data: bytes, fmt: str) -> bool:
    """True when an Annex B access unit holds a keyframe slice (IDR; H.265 IRAP).

    Only the NAL headers up to the first slice are looked at: the start codes
    are found by ``bytes.find``, never a byte loop over a 4K frame.
    """
    key, vcl = _KEY_TYPES[fmt], _VCL_TYPES[fmt]
    i = data.find(b"\x00\x00\x01")
    while 0 <= i < len(data) - 3:
        t = nal_type(data[i + 3 : i + 4], fmt)
        if t in key:
            return True
        if t in vcl:
            return False
        i = data.find(b"\x00\x00\x01", i + 3)
    return False


def video_frame_of(frame: Frame) -> VideoFrame:
    """A Frame read back from ``/camera/video`` as a VideoFrame (keyframe found from its NAL units)."""
    if isinstance(frame, VideoFrame):
        return frame
    return VideoFrame(timestamp_ns=frame.timestamp_ns, format=frame.format, data=frame.data, keyframe=is_keyframe(frame.data, frame.format))


# --- pure: falling behind -------------------------------------------------------


@dataclass(frozen=True)
class StreamIncident:
    """Something the operator must hear about: the recorder lags the stream, or frames were lost.

    Attributes
    ----------
    kind : ``video_lag`` (frames arrive later than the stream's own pacing
        allows: a backlog), ``video_lost`` (a gap in the presentation times:
        frames the camera sent never arrived) or ``video_corrupt`` (packets
        flagged corrupt by the demuxer, e.g. UDP losses inside a frame).
    start_ns, end_ns : host UTC ns of the span.
    value : the lag in seconds (video_lag, its largest), or the frame count.
    """

    kind: str
    start_ns: int
    end_ns: int
    value: float


class StreamMonitor:
    """Lag, gaps and corruption of a packet stream from (arrival, pts) pairs. No I/O.

    The lag of a frame is ``arrival - (floor + pts)``, with ``floor`` the
    smallest ``arrival - pts`` seen in the last ``floor_window_s`` (the
    network's least delay; the window lets a camera clock drift slowly
    against the host's). Single late frames (a large keyframe, jitter) are
    not a backlog: the stream lags when the smallest lag over the last
    ``lag_span_s`` exceeds ``max_lag_frames`` frame periods.

    Parameters
    ----------
    frame_period_s : the nominal frame period, seconds (1/fps); None learns
        it from the median pts step.
    """

    def __init__(
        self,
        frame_period_s: float | None = None,
        max_lag_frames: float = 1.0,
        lag_span_s: float = 1.0,
        floor_window_s: float = 60.0,
    ) -> None:
        self.frame_period_ns = int(frame_period_s * 1e9) if frame_period_s else None
        self.max_lag_frames = float(max_lag_frames)
        self.lag_span_ns = int(lag_span_s * 1e9)
        self.floor_window_ns = int(floor_window_s * 1e9)
        self._floors: collections.deque[tuple[int, int]] = collections.deque()  # (arrival ns, arrival - pts) minima per second
        self._recent: collections.deque[tuple[int, int]] = collections.deque()  # (arrival ns, lag ns)
        self._steps: collections.deque[int] = collections.deque(maxlen=31)
        self._last_pts: int | None = None
        self._lag_start: int | None = None
        self._lag_max_ns = 0
        self.frames = 0
        self.frames_lost = 0
        self.corrupt = 0
        self.reordered = 0
        self.lag_ns = 0  # the smallest lag over the last lag_span_s
        self.max_lag_ns = 0
        self.lag_events = 0
        self.loss_events = 0

    @property
    def period_ns(self) -> int | None:
        if self.frame_period_ns:
            return self.frame_period_ns
        if len(self._steps) >= 5:
            return sorted(self._steps)[len(self._steps) // 2]
        return None

    @property
    def lagging(self) -> bool:
        return self._lag_start is not None

    def reset(self) -> None:
        """A new connection: the pts clock starts again."""
        self._floors.clear()
        self._recent.clear()
        self._last_pts = None

    def floor_ns(self) -> int | None:
        """The smallest ``arrival - pts`` in the window, ns; None before the first frame."""
        return min((f for _, f in self._floors), default=None)

    def observe(self, arrival_ns: int, pts_ns: int | None, corrupt: bool = False) -> list[StreamIncident]:
        """One frame; the incidents it completes (a lag that ended, a gap, a corrupt packet)."""
        out: list[StreamIncident] = []
        self.frames += 1
        if corrupt:
            self.corrupt += 1
            out.append(StreamIncident("video_corrupt", arrival_ns, arrival_ns, 1.0))
        if pts_ns is None:
            return out
        if self._last_pts is not None:
            step = pts_ns - self._last_pts
            if step <= 0:
                self.reordered += 1  # out of order: B-frames, or a camera clock jump
            else:
                period = self.period_ns
                if period and step > 1.5 * period:
                    lost = int(round(step / period)) - 1
                    self.frames_lost += lost
                    self.loss_events += 1
                    out.append(StreamIncident("video_lost", arrival_ns - (step - period), arrival_ns, float(lost)))
                self._steps.append(step)
        self._last_pts = pts_ns if self._last_pts is None else max(self._last_pts, pts_ns)
        offset = arrival_ns - pts_ns
        second = arrival_ns // 1_000_000_000
        if self._floors and self._floors[-1][0] // 1_000_000_000 == second:
            if offset < self._floors[-1][1]:
                self._floors[-1] = (self._floors[-1][0], offset)
        else:
            self._floors.append((arrival_ns, offset))
        while self._floors and arrival_ns - self._floors[0][0] > self.floor_window_ns:
            self._floors.popleft()
        lag = offset - (self.floor_ns() or offset)
        self._recent.append((arrival_ns, lag))
        while self._recent and arrival_ns - self._recent[0][0] > self.lag_span_ns:
            self._recent.popleft()
        self.lag_ns = min(l for _, l in self._recent)
        self.max_lag_ns = max(self.max_lag_ns, self.lag_ns)
        period = self.period_ns
        limit = self.max_lag_frames * period if period else None
        if limit is not None and self.lag_ns > limit:
            if self._lag_start is None:
                self._lag_start = arrival_ns - self.lag_ns
                self._lag_max_ns = 0
                self.lag_events += 1
            self._lag_max_ns = max(self._lag_max_ns, self.lag_ns)
        elif self._lag_start is not None:
            out.append(StreamIncident("video_lag", self._lag_start, arrival_ns, self._lag_max_ns / 1e9))
            self._lag_start = None
        return out

    def close(self, now_ns: int) -> list[StreamIncident]:
        """The incident still open at the end (a lag that never recovered)."""
        if self._lag_start is None:
            return []
        start, self._lag_start = self._lag_start, None
        return [StreamIncident("video_lag", start, now_ns, self._lag_max_ns / 1e9)]


# --- PyAV: the capture shell -------------------------------------------------------


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


def merge_parts(parts: list[bytes], fmt: str, length_size: int | None = None) -> list[bytes]:
    """NAL units of one access unit delivered in several packets.

    Parameter sets are kept once and only before the first slice (H.264
    7.4.1.2.3: they do not follow the slices of the picture); delimiters
    after the first are dropped.
    """
    nals: list[bytes] = []
    seen_vcl = False
    params_seen: set[bytes] = set()
    for part in parts:
        units = split_annexb(part) if length_size is None else split_length_prefixed(part, length_size)
        for n in units:
            t = nal_type(n, fmt)
            if t in _PARAM_TYPES[fmt]:
                if seen_vcl or n in params_seen:
                    continue
                params_seen.add(n)
            elif t == (9 if fmt == "h264" else 35) and nals:
                continue
            elif t in _VCL_TYPES[fmt]:
                seen_vcl = True
            nals.append(n)
    return nals


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


# --- PyAV: decoding for the offline stage and the live check --------------------------


class VideoFrameDecoder:
    """Decode an access-unit stream lazily: only from the keyframe before a wanted frame up to it.

    Feed every access unit in order with :meth:`push`; ask for the picture of
    the last one pushed with :meth:`gray`. Access units are kept, not decoded,
    until a picture is asked for; a keyframe drops what was kept, so a GOP
    with no wanted frame is never decoded and a GOP is decoded only up to its
    last wanted frame. Slice threads only: frame threads would hold pictures
    back, and the decoder could not hand out the one just pushed.
    """

    def __init__(self, fmt: str, threads: int = 2) -> None:
        import av

        self.format = fmt
        self._ctx = av.CodecContext.create(_CODEC_OF_FORMAT[fmt], "r")
        self._ctx.thread_type = "SLICE"
        self._ctx.thread_count = max(1, int(threads))
        self._pending: list[bytes] = []
        self._have_key = False  # the decoder holds a decodable reference chain
        self.decoded = 0  # access units decoded
        self.skipped = 0  # access units never decoded (GOP tails with no wanted frame)
        self.errors = 0

    def push(self, frame: Frame) -> None:
        """The next access unit of the stream (in decode = presentation order)."""
        key = frame.keyframe if isinstance(frame, VideoFrame) else is_keyframe(frame.data, self.format)
        if key:
            self.skipped += len(self._pending) if self._have_key else 0
            self._pending = []
            self._have_key = True
        elif not self._have_key:
            self.skipped += 1
            return  # before the first keyframe: undecodable
        self._pending.append(frame.data)

    def gray(self):
        """(H, W) uint8 luma of the access unit pushed last, or None (no keyframe before it, corrupt data)."""
        import av

        if not self._have_key or not self._pending:
            return None
        pending, self._pending = self._pending, []
        last = None
        for data in pending:
            try:
                frames = self._ctx.decode(av.Packet(data))
            except av.FFmpegError:
                self.errors += 1
                frames = []
            self.decoded += 1
            if frames:
                last = frames[-1]
        if last is None:
            return None
        import numpy as np

        plane = last.planes[0]
        h, w = last.height, last.width
        arr = np.frombuffer(plane, np.uint8).reshape(h, plane.line_size)[:, :w]
        return np.ascontiguousarray(arr)


def decode_keyframe_gray(data: bytes, fmt: str):
    """(H, W) uint8 luma of one keyframe access unit decoded on its own, or None."""
    import av

    ctx = av.CodecContext.create(_CODEC_OF_FORMAT[fmt], "r")
    try:
        frames = list(ctx.decode(av.Packet(data))) + list(ctx.decode(None))
    except av.FFmpegError:
        return None
    if not frames:
        return None
    import numpy as np

    f = frames[0]
    plane = f.planes[0]
    return np.ascontiguousarray(np.frombuffer(plane, np.uint8).reshape(f.height, plane.line_size)[:, : f.width])


def read_video_packets(path: str, start_ns: int) -> Iterator[tuple[int, VideoFrame, tuple[int, int]]]:
    """Access units of an H.264/H.265 file (MP4, MKV, TS...) as recorded, stamped by position.

    Yields
    ------
    (index, frame, (width, height)) : ``frame.timestamp_ns`` = ``start_ns`` +
        the presentation time since the first frame; Annex B with the
        parameter sets in front of every keyframe.

    Raises
    ------
    VideoError
        when the file cannot be opened, is not H.264/H.265, or has B-frames
        (frames out of presentation order cannot be a ``/camera/video`` run).
    """
    import av

    try:
        container = av.open(str(path))
    except (av.FFmpegError, OSError) as exc:
        raise VideoError(f"video file {path}: cannot open it ({exc}); check the file") from exc
    try:
        if not container.streams.video:
            raise VideoError(f"video file {path}: no video stream in it")
        stream = container.streams.video[0]
        fmt = video_format(stream.codec_context.name)
        params, length_size = parameter_sets(stream.codec_context.extradata, fmt)
        size = (int(stream.codec_context.width), int(stream.codec_context.height))
        tb = stream.time_base
        first: int | None = None
        last: int | None = None
        index = 0
        for packet in container.demux(stream):
            if packet.size == 0 or packet.pts is None:
                continue
            if (packet.dts is not None and packet.pts != packet.dts) or (last is not None and packet.pts <= last):
                raise VideoError(
                    f"video file {path}: frames out of order at frame {index} (B-frames); "
                    "/camera/video needs a stream without B-frames: import with --video-reencode (JPEG frames)"
                )
            last = packet.pts
            first = packet.pts if first is None else first
            data = bytes(packet)
            key = bool(packet.is_keyframe) or (length_size is None and is_keyframe(data, fmt))
            au = access_unit(data, fmt, key, params, length_size)
            t_ns = int(start_ns) + int((packet.pts - first) * tb * 1_000_000_000)
            yield index, VideoFrame(timestamp_ns=t_ns, format=fmt, data=au, keyframe=key, pts_ns=t_ns - int(start_ns)), size
            index += 1
    finally:
        container.close()


def probe_video_format(path: str) -> str | None:
    """``h264`` / ``h265`` when the file's first video stream is one of them, else None (or unreadable)."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                return None
            return _FORMAT_OF_CODEC.get(container.streams.video[0].codec_context.name.lower())
    except (av.FFmpegError, OSError):
        return None
