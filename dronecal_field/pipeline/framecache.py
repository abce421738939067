"""Detector outcomes made elsewhere (the live pass in ``fly``), for ``calibrate`` to reuse instead of decoding again.

``fly``'s live worker runs ``calibrate``'s detector over the frames it keeps
(its ring: frames ``live.worker.RING_HZ`` apart) around every hold and leg,
as they are recorded. Handed to ``calibrate_run(..., live=)`` in the same
process, those outcomes stand in for the file's frames wherever the live
pass saw *every* frame it kept: its covered intervals. Outside them
``calibrate`` reads and decodes the file as usual. Nothing is written to the
run file; the run-file contract is unchanged.

Pure: stamps and intervals, no I/O, no threads. Stamps are frame
``timestamp_ns`` (the camera clock as recorded), intervals ``[a, b]``
inclusive, in ns.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from dronecal_field.pipeline.detect import FrameResult

Interval = tuple[int, int]


def merge_intervals(ranges: list[Interval] | tuple[Interval, ...]) -> list[Interval]:
    """Sorted, disjoint ``[a, b]`` covering the same stamps (touching integer intervals join)."""
    out: list[list[int]] = []
    for a, b in sorted((int(a), int(b)) for a, b in ranges if b >= a):
        if out and a <= out[-1][1] + 1:
            out[-1][1] = max(out[-1][1], b)
        else:
            out.append([a, b])
    return [(a, b) for a, b in out]


def subtract_intervals(ranges: list[Interval], minus: list[Interval]) -> list[Interval]:
    """The stamps of ``ranges`` outside ``minus`` (both lists of inclusive ``[a, b]``), sorted and disjoint."""
    holes = merge_intervals(minus)
    out: list[Interval] = []
    for a, b in merge_intervals(ranges):
        start = a
        for c, d in holes:
            if d < start or c > b:
                continue
            if c > start:
                out.append((start, c - 1))
            start = max(start, d + 1)
            if start > b:
                break
        if start <= b:
            out.append((start, b))
    return out


def intersect_intervals(ranges: list[Interval], other: list[Interval]) -> list[Interval]:
    """The stamps in both lists of inclusive ``[a, b]``, sorted and disjoint."""
    x, y = merge_intervals(ranges), merge_intervals(other)
    out: list[Interval] = []
    i = j = 0
    while i < len(x) and j < len(y):
        a, b = max(x[i][0], y[j][0]), min(x[i][1], y[j][1])
        if a <= b:
            out.append((a, b))
        if x[i][1] < y[j][1]:
            i += 1
        else:
            j += 1
    return out


@dataclass(frozen=True, eq=False)
class FrameResults:
    """Per frame stamp the detector's outcome, and where every candidate frame has one.

    Attributes
    ----------
    t_ns : (N,) int64, sorted: the stamps of the frames the detector ran on.
    results : N outcomes in the same order: a ``detect.FrameResult`` (the marker or
        None, other ArUco ids), or None where the frame did not decode (corrupt).
    covered : sorted disjoint ``[a, b]``: inside these every frame the producer kept
        has an outcome; the frames it kept are the candidates there (a 30 fps
        stream kept at 16 Hz offers every other frame).
    source : who made them, for reports (``"live pass"``).
    formats : the frames' formats (``jpeg``, ``png``), for the report's list of what was decoded.
    """

    t_ns: np.ndarray
    results: tuple[FrameResult | None, ...]
    covered: tuple[Interval, ...]
    source: str = "live pass"
    formats: tuple[str, ...] = ()

    @classmethod
    def build(cls, outcomes: dict[int, FrameResult | None], covered: list[Interval], source: str = "live pass",
              formats: tuple[str, ...] = ()) -> "FrameResults":
        """From ``{stamp: outcome}`` (any order) and covered intervals (any order, may overlap)."""
        stamps = sorted(int(t) for t in outcomes)
        return cls(
            t_ns=np.asarray(stamps, np.int64), results=tuple(outcomes[t] for t in stamps),
            covered=tuple(merge_intervals(list(covered))), source=source, formats=tuple(formats),
        )

    def __len__(self) -> int:
        return len(self.t_ns)

    def covered_at(self, t_ns: int) -> bool:
        """Whether ``t_ns`` lies in a covered interval."""
        k = bisect.bisect_right(self.covered, (int(t_ns), float("inf"))) - 1
        return k >= 0 and self.covered[k][0] <= t_ns <= self.covered[k][1]

    def uncovered(self, ranges: list[Interval]) -> list[Interval]:
        """The parts of ``ranges`` the cache does not cover: what must still be read from the file."""
        return subtract_intervals(list(ranges), list(self.covered))

    def lookup(self, t_ns: int) -> tuple[bool, FrameResult | None]:
        """(has an outcome, the outcome) of the frame stamped ``t_ns``, covered or not."""
        k = int(np.searchsorted(self.t_ns, int(t_ns)))
        if k < len(self.t_ns) and int(self.t_ns[k]) == int(t_ns):
            return True, self.results[k]
        return False, None

    def items_in(self, ranges: list[Interval]) -> list[tuple[int, FrameResult | None]]:
        """(stamp, outcome) of the frames inside both ``ranges`` and the covered intervals, in time order."""
        out: list[tuple[int, FrameResult | None]] = []
        for a, b in intersect_intervals(list(ranges), list(self.covered)):
            lo, hi = int(np.searchsorted(self.t_ns, a, side="left")), int(np.searchsorted(self.t_ns, b, side="right"))
            out.extend((int(self.t_ns[k]), self.results[k]) for k in range(lo, hi))
        return out

    @property
    def covered_s(self) -> float:
        """Seconds of the run the cache covers."""
        return sum(b - a for a, b in self.covered) / 1e9
