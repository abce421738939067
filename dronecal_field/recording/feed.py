"""One camera's stream into a recording: its video thread, its gaps and incidents, its counters.

The recorder runs one :class:`CameraFeed` per camera (one for a single-camera
run, whose frames go to ``/camera/...``; one per ``--video NAME=URL`` for a
several-camera run, whose frames go to ``/cameras/<name>/...``). Each feed is
on its own clock exactly as the single stream always was: its frames keep the
stamps its source gives them, its silences are its own ``video_gap`` events,
its stream's lag, losses and corrupt packets its own events, and every event
of a named camera says which (metadata ``camera``).

A feed never touches the file: it offers ``(feed, frame)`` to the recorder's
bounded frame queue and hands its events to the recorder's event sink, both
O(1) and non-blocking, so one stalled camera never holds another back.
"""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass
from typing import Any, Callable

from dronecal_field.errors import VideoError
from dronecal_field.runfile.records import Frame, RunEvent


@dataclass(frozen=True)
class CameraStatus:
    """One camera's part of the status line.

    Attributes
    ----------
    name : camera name, or None for the single camera of a ``/camera/...`` run.
    fps : frames in the last second.
    frames : frames written.
    dropped : frames dropped (slow disk + slow reader).
    gaps : video gaps so far (the open one included).
    video_ok : frames arriving.
    marker_seen : the marker in its last probed frame (None: not probed yet).
    video_lag_s : how far the recorder lags the stream's own clock (H.264/H.265), seconds.
    video_lagging : the lag is more than a frame, sustained.
    video_lost : frames lost in the stream plus corrupt packets.
    """

    name: str | None
    fps: float
    frames: int
    dropped: int
    gaps: int
    video_ok: bool
    marker_seen: bool | None
    video_lag_s: float | None = None
    video_lagging: bool = False
    video_lost: int = 0


@dataclass(frozen=True)
class CameraReport:
    """What was recorded of one camera (see recorder.RecordingReport for the meaning of each count)."""

    name: str | None
    frames_written: int
    frames_dropped: int
    frames_dropped_source: int
    frames_discarded_at_start: int
    video_gaps: int
    video_lag_events: int
    video_max_lag_s: float
    frames_lost_stream: int
    packets_corrupt: int

    def summary(self) -> str:
        """``north 1234 frames (0 dropped, 0 gaps)`` and the stream's incidents when it had any."""
        text = f"{self.name} {self.frames_written} frames ({self.frames_dropped + self.frames_dropped_source} dropped, {self.video_gaps} gaps"
        if self.video_lag_events or self.frames_lost_stream or self.packets_corrupt:
            text += (f", VIDEO FELL BEHIND {self.video_lag_events} times (up to {self.video_max_lag_s:.2f} s), "
                     f"{self.frames_lost_stream} frames lost in the stream, {self.packets_corrupt} corrupt packets")
        return text + ")"


class CameraFeed:
    """One camera of the recording (its source, first frame and live observer) and everything counted about it.

    Parameters
    ----------
    name : str or None
        The camera's name in a several-camera run (``/cameras/<name>/...``), None for the single camera.
    video : VideoSource
        Open source (``read``, ``reopen``, ``frames_dropped``; optional ``incidents``, ``monitor``, ``live``).
    first_frame : Frame or None
        A frame already read (the probe's), recorded first unless it arrived before the start.
    observer : object with ``on_frame(frame)`` or None
        Told of every frame as it arrives (the live check of this camera); must return at once.
    video_timeout_s : float
        Seconds without a frame before a video gap starts and the source is reopened.
    """

    def __init__(self, name: str | None, video: Any, first_frame: Frame | None = None, observer: Any = None,
                 video_timeout_s: float = 2.0) -> None:
        self.name = name
        self.video = video
        self.first_frame = first_frame
        self.observer = observer
        self.observer_errors = 0
        self.video_timeout_s = video_timeout_s
        self.frames_written = 0  # by the writer thread
        self.frames_dropped = 0  # the frame queue was full (a slow disk)
        self.frames_discarded_at_start = 0
        self.frames_not_recorded = 0
        self.video_gaps = 0
        self.video_lag_events = 0
        self.video_max_lag_s = 0.0
        self.frames_lost_stream = 0
        self.packets_corrupt = 0
        self.marker_seen: bool | None = None
        self.latest_keyframe: Frame | None = first_frame
        self.gap_start_ns: int | None = None
        self._frame_times: collections.deque[float] = collections.deque(maxlen=256)
        self._last_frame_mono = time.monotonic()
        self._source_dropped_at_start = 0

    # ----- start -----
    def discard_stale(self, started_ns: int) -> Frame | None:
        """Empty a live source's queue of frames stamped before ``started_ns``; the first fresh frame, if any.

        A file source loses nothing by waiting, so its queued frames and the first frame are all recorded.
        The source's drop counter is taken as the zero afterwards: while its queue was full, each arrival
        pushed out an older, pre-start frame, and those are not recording losses.
        """
        fresh = self._first_fresh(started_ns)
        self._source_dropped_at_start = int(getattr(self.video, "frames_dropped", 0))
        if fresh is not None:
            self.latest_keyframe = fresh
        self._last_frame_mono = time.monotonic()
        return fresh

    def _first_fresh(self, started_ns: int) -> Frame | None:
        first = self.first_frame
        if not getattr(self.video, "live", True):
            return first
        if first is not None and first.timestamp_ns >= started_ns:
            return first
        if first is not None:
            self.frames_discarded_at_start += 1
            self.latest_keyframe = None
        # Ends at the first fresh frame or an empty queue; the cap only guards
        # against a source that stamps frames in the past faster than we read.
        for _ in range(100_000):
            frame = self.video.read(timeout_s=0.0)
            if frame is None:
                return None
            if frame.timestamp_ns >= started_ns:
                return frame
            self.frames_discarded_at_start += 1
        return None

    # ----- video thread -----
    def run(self, stop: Any, offer: Callable[["CameraFeed", Frame], None], emit: Callable[[RunEvent], None]) -> None:
        """Read frames until ``stop`` (a threading.Event) is set: offer each, mark gaps, reopen a silent source."""
        last_reopen = 0.0
        while not stop.is_set():
            frame = self.video.read(timeout_s=0.2)
            now = time.monotonic()
            if frame is None:
                silent_s = now - self._last_frame_mono
                if self.gap_start_ns is None and silent_s > self.video_timeout_s:
                    self.gap_start_ns = time.time_ns() - int(silent_s * 1e9)
                if (self.gap_start_ns is not None or getattr(self.video, "ended", False)) and now - last_reopen > 1.0:
                    if self.gap_start_ns is None:  # the stream ended: a reconnect is a gap however short
                        self.gap_start_ns = time.time_ns() - int(silent_s * 1e9)
                    last_reopen = now
                    try:
                        self.video.reopen()
                    except VideoError:
                        pass  # camera still away: try again in a second
                continue
            if self.gap_start_ns is not None:
                start = self.gap_start_ns
                self.gap_start_ns = None
                emit(RunEvent(start, max(0, frame.timestamp_ns - start), "video_gap",
                              self.event_metadata({"reopens": str(getattr(self.video, "reconnects", 0))})))
                self.video_gaps += 1
            self._last_frame_mono = now
            self._frame_times.append(now)
            if getattr(frame, "keyframe", True):
                self.latest_keyframe = frame  # the marker probe decodes keyframes only (an H.264/H.265 stream)
            offer(self, frame)
            self._stream_incidents(emit)
            observer = self.observer
            if observer is not None:
                try:
                    observer.on_frame(frame)
                except Exception:  # noqa: BLE001 - a live view must never cost the recording
                    self.observer_errors += 1
                    self.observer = None

    def _stream_incidents(self, emit: Callable[[RunEvent], None]) -> None:
        """Events and counts of the stream's own incidents (lag, frames lost, corrupt packets): loud, never hidden."""
        take = getattr(self.video, "incidents", None)
        if take is None:
            return
        for incident in take():
            span = max(0, incident.end_ns - incident.start_ns)
            if incident.kind == "video_lag":
                self.video_lag_events += 1
                self.video_max_lag_s = max(self.video_max_lag_s, incident.value)
                meta = {"lag_s": f"{incident.value:.3f}"}
            elif incident.kind == "video_lost":
                self.frames_lost_stream += int(incident.value)
                meta = {"frames": str(int(incident.value))}
            else:
                self.packets_corrupt += int(incident.value)
                meta = {"packets": str(int(incident.value))}
            emit(RunEvent(incident.start_ns, span, incident.kind, self.event_metadata(meta)))

    def event_metadata(self, meta: dict[str, str]) -> dict[str, str]:
        """An event's metadata, with ``camera`` = this camera's name when it has one."""
        return meta if self.name is None else {**meta, "camera": self.name}

    def close_gap(self, now_ns: int) -> RunEvent | None:
        """The gap still open at the end of the recording, as an event (``open`` true), or None."""
        start, self.gap_start_ns = self.gap_start_ns, None
        if start is None:
            return None
        self.video_gaps += 1
        return RunEvent(start, now_ns - start, "video_gap", self.event_metadata({"open": "true"}))

    def report(self) -> CameraReport:
        return CameraReport(
            name=self.name, frames_written=self.frames_written, frames_dropped=self.frames_dropped,
            frames_dropped_source=self.frames_dropped_source, frames_discarded_at_start=self.frames_discarded_at_start,
            video_gaps=self.video_gaps, video_lag_events=self.video_lag_events, video_max_lag_s=self.video_max_lag_s,
            frames_lost_stream=self.frames_lost_stream, packets_corrupt=self.packets_corrupt,
        )

    # ----- status -----
    @property
    def frames_dropped_source(self) -> int:
        """Frames the video source dropped since the start (it was not read fast enough)."""
        return max(0, int(getattr(self.video, "frames_dropped", 0)) - self._source_dropped_at_start)

    @property
    def video_ok(self) -> bool:
        return self.gap_start_ns is None

    @property
    def video_lag_s(self) -> float | None:
        """How far the recorder lags the stream's own clock now, seconds (H.264/H.265 sources); None otherwise."""
        monitor = getattr(self.video, "monitor", None)
        return None if monitor is None else monitor.lag_ns / 1e9

    def status(self, now: float) -> CameraStatus:
        """A snapshot at monotonic ``now``."""
        fps = float(sum(1 for t in list(self._frame_times) if now - t <= 1.0))
        return CameraStatus(
            name=self.name,
            fps=fps,
            frames=self.frames_written,
            dropped=self.frames_dropped + self.frames_dropped_source,
            gaps=self.video_gaps + (0 if self.video_ok else 1),
            video_ok=self.video_ok,
            marker_seen=self.marker_seen,
            video_lag_s=self.video_lag_s,
            video_lagging=bool(getattr(getattr(self.video, "monitor", None), "lagging", False)),
            video_lost=self.frames_lost_stream + self.packets_corrupt,
        )
