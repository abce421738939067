"""Hover windows: when the drone held still at a waypoint.

Three sources, best first: hover ``/events`` written by the recorder;
MISSION_ITEM_REACHED telemetry (ArduCopter sends it when a hold ENDS, so the
window is the hold time before it); and the GNSS track alone (speed and
spread below thresholds for long enough), which every run has.

Pure functions on arrays and plain tuples; times are integer nanoseconds on
the run clock (the GNSS / vehicle clock; the camera's offset is found later by
``align``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

SOURCES = ("event", "mission_item_reached", "gnss_track")


@dataclass(frozen=True)
class HoverWindow:
    """One hold at one waypoint, on the GNSS clock.

    ``seq`` is the mission item when known; ``index`` numbers the windows of a
    run in time order (the report's waypoint number).
    """

    index: int
    start_ns: int
    end_ns: int
    source: str
    seq: int | None = None

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9

    def stable(self, settle_s: float, tail_s: float) -> tuple[int, int]:
        """(start_ns, end_ns) of the settled part: ``settle_s`` after arrival to ``tail_s`` before leaving.

        A short window keeps at least its middle third, so a 1 s hold still
        yields a point instead of an empty interval.
        """
        a = self.start_ns + int(settle_s * 1e9)
        b = self.end_ns - int(tail_s * 1e9)
        if b - a < (self.end_ns - self.start_ns) // 3:
            third = (self.end_ns - self.start_ns) // 3
            a, b = self.start_ns + third, self.end_ns - third
        return a, b


@dataclass(frozen=True)
class TrackThresholds:
    """When the GNSS track counts as hovering (defaults suit RTK and 1-5 s holds)."""

    max_speed_mps: float = 0.2  # over a ~1 s baseline; RTK noise alone gives ~0.02
    max_spread_m: float = 0.15  # distance from the hold's anchor position
    min_duration_s: float = 1.5
    max_gap_s: float = 1.0  # a longer GNSS gap splits a window (dropout)
    speed_baseline_s: float = 1.0


def windows_from_intervals(
    intervals: Sequence[tuple[int, int, int | None]],
    source: str,
) -> list[HoverWindow]:
    """Windows from (start_ns, end_ns, seq) intervals (e.g. hover events), sorted and numbered.

    Empty or reversed intervals are skipped; overlapping duplicates (the same
    hold announced twice) are merged into the first.
    """
    clean = sorted((int(a), int(b), s) for a, b, s in intervals if b > a)
    merged: list[tuple[int, int, int | None]] = []
    for a, b, s in clean:
        if merged and a < merged[-1][1] and (s is None or s == merged[-1][2]):
            pa, pb, ps = merged[-1]
            merged[-1] = (pa, max(pb, b), ps)
            continue
        merged.append((a, b, s))
    return [HoverWindow(index=k, start_ns=a, end_ns=b, source=source, seq=s) for k, (a, b, s) in enumerate(merged)]


def track_speed(t_ns: np.ndarray, enu_m: np.ndarray, baseline_s: float = 1.0, max_gap_s: float = 1.0) -> np.ndarray:
    """(N,) speed in m/s of a track from the displacement over ~``baseline_s`` around each sample.

    Parameters
    ----------
    t_ns : (N,) int64, increasing
    enu_m : (N, 3) metres
    baseline_s : float
        Longer than the fix interval, so RTK noise (~1 cm) gives ~0.02 m/s.
    max_gap_s : float
        A sample next to a gap longer than this uses only its own side.

    Samples with no neighbour within the baseline get speed NaN.
    """
    t = (np.asarray(t_ns, np.int64) - int(t_ns[0])).astype(float) * 1e-9 if len(t_ns) else np.zeros(0)
    p = np.asarray(enu_m, float)
    n = len(t)
    if n < 2:
        return np.full(n, np.nan)
    half = baseline_s / 2
    lo = np.searchsorted(t, t - half, side="left")
    hi = np.searchsorted(t, t + half, side="right") - 1
    idx = np.arange(n)
    # Do not look across a gap: clamp each side to the contiguous block.
    gap_after = np.r_[np.diff(t) > max_gap_s, True]
    block = np.r_[0, np.cumsum(gap_after[:-1])]
    first_in_block = np.searchsorted(block, block, side="left")
    last_in_block = np.searchsorted(block, block, side="right") - 1
    lo = np.maximum(lo, first_in_block)
    hi = np.minimum(hi, last_in_block)
    span = t[hi] - t[lo]
    speed = np.linalg.norm(p[hi] - p[lo], axis=1) / np.where(span > 0, span, np.nan)
    speed[(hi == idx) & (lo == idx)] = np.nan
    return speed


def windows_from_track(
    t_ns: np.ndarray,
    enu_m: np.ndarray,
    thresholds: TrackThresholds = TrackThresholds(),
) -> list[HoverWindow]:
    """Hover windows found in a GNSS track alone.

    A window is a run of samples whose speed is below ``max_speed_mps``, that
    stay within ``max_spread_m`` of the run's anchor (its first half-second's
    median), with no gap over ``max_gap_s``, lasting ``min_duration_s`` or more.

    Parameters
    ----------
    t_ns : (N,) int64 increasing, GNSS clock
    enu_m : (N, 3) metres (antenna or marker; the difference is constant in a hold)
    """
    t_ns = np.asarray(t_ns, np.int64)
    p = np.asarray(enu_m, float)
    if len(t_ns) < 3:
        return []
    speed = track_speed(t_ns, p, thresholds.speed_baseline_s, thresholds.max_gap_s)
    still = np.nan_to_num(speed, nan=np.inf) < thresholds.max_speed_mps
    gap = np.r_[False, np.diff(t_ns) > thresholds.max_gap_s * 1e9]
    intervals: list[tuple[int, int, int | None]] = []
    i, n = 0, len(t_ns)
    min_ns = thresholds.min_duration_s * 1e9
    while i < n:
        if not still[i]:
            i += 1
            continue
        head = i + max(1, int(np.searchsorted(t_ns[i:], t_ns[i] + 500_000_000)))
        anchor = np.median(p[i : min(head, n)], axis=0)
        j = i + 1
        while j < n and still[j] and not gap[j] and np.linalg.norm(p[j] - anchor) <= thresholds.max_spread_m:
            j += 1
        if t_ns[j - 1] - t_ns[i] >= min_ns:
            intervals.append((int(t_ns[i]), int(t_ns[j - 1]), None))
        i = j
    return windows_from_intervals(intervals, "gnss_track")


def windows_from_reached(
    reached: Sequence[tuple[int, int]],
    t_ns: np.ndarray,
    enu_m: np.ndarray,
    hold_s_by_seq: dict[int, float] | None = None,
    thresholds: TrackThresholds = TrackThresholds(),
    tolerance_s: float = 0.6,
) -> list[HoverWindow]:
    """Windows from MISSION_ITEM_REACHED (t_ns, seq) pairs, which ArduCopter sends at the END of a hold.

    With the mission's hold time for a seq (``hold_s_by_seq``, from the plan)
    the window is that long before the message; without it, it starts where
    the GNSS track became still. Either way the track must be still just
    before the message: DO items and the takeoff also get "reached" and are
    not hovers.

    Parameters
    ----------
    reached : sequence of (timestamp_ns, seq)
    t_ns : (N,) int64, enu_m : (N, 3)
        The GNSS track (same clock as ``reached``).
    """
    t_ns = np.asarray(t_ns, np.int64)
    p = np.asarray(enu_m, float)
    if len(t_ns) < 3:
        return []
    # A relaxed track segmentation: the hold's start is where stillness began.
    relaxed = replace(thresholds, min_duration_s=0.0)
    segments = windows_from_track(t_ns, p, relaxed)
    seen: set[int] = set()
    intervals: list[tuple[int, int, int | None]] = []
    tol = int(tolerance_s * 1e9)
    for t_end, seq in sorted(reached):
        if seq in seen:
            continue
        # Still just before the message (speed over the baseline rises ~0.5 s
        # before the vehicle leaves, hence the tolerance on both sides).
        probe = t_end - tol
        segment = next((w for w in segments if w.start_ns <= probe <= w.end_ns + tol), None)
        if segment is None:
            continue
        hold = None if hold_s_by_seq is None else hold_s_by_seq.get(seq)
        if hold is not None and hold <= 0:
            continue
        start = t_end - int(hold * 1e9) if hold is not None else segment.start_ns
        start = max(start, segment.start_ns - tol)
        if (t_end - start) < thresholds.min_duration_s * 1e9:
            continue
        seen.add(seq)
        intervals.append((int(start), int(t_end), int(seq)))
    return windows_from_intervals(intervals, "mission_item_reached")
