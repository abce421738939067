"""The health of a packet stream, pure arithmetic on (arrival, presentation time) pairs. No I/O.

The lag behind the stream's own clock, pts gaps (lost frames) and corrupt
packets, as :class:`StreamIncident` records.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass


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
