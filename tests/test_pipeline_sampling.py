"""Which frames the offline stage decodes: few per window, but dense enough to bracket every fix."""

from __future__ import annotations

import numpy as np

from dronecal_field.pipeline.hover import HoverWindow
from dronecal_field.pipeline.sampling import FrameSelector, SamplingOptions

S = 1_000_000_000


def _decoded_in(window: HoverWindow, fps: float = 30.0, options: SamplingOptions = SamplingOptions()) -> np.ndarray:
    selector = FrameSelector([window], options)
    stamps = np.arange(window.start_ns - 3 * S, window.end_ns + 3 * S, int(S / fps), dtype=np.int64)
    taken = [t for t in stamps if selector.wants(int(t))[0]]
    return np.array([t for t in taken if window.start_ns <= t <= window.end_ns], np.int64)


def test_a_short_hold_gets_its_frame_budget_and_a_long_one_stays_dense():
    short = _decoded_in(HoverWindow(index=0, start_ns=10 * S, end_ns=13 * S, source="event", seq=1))
    long = _decoded_in(HoverWindow(index=0, start_ns=10 * S, end_ns=30 * S, source="event", seq=1))
    # 3 s hold: 24 frames over the window and its 1.2 s margins, about 0.23 s apart.
    assert 11 <= len(short) <= 14 and np.diff(short).max() <= 0.25 * S
    # 20 s hold: the budget alone would put frames 0.93 s apart; they stay within 0.4 s (+ one frame).
    assert np.diff(long).max() <= 0.4 * S + S // 30
    assert len(long) >= 20 / 0.44
    # The cap can be lifted for speed (frames then as the budget spreads them).
    sparse = _decoded_in(HoverWindow(index=0, start_ns=10 * S, end_ns=30 * S, source="event", seq=1),
                         options=SamplingOptions(max_period_s=10.0))
    assert np.diff(sparse).max() >= 0.9 * S


def test_a_sped_up_one_second_hold_decodes_every_frame_it_has():
    """A simulator at speed-up 3 turns a 3 s hold into 1 s of run time: its middle third holds ~5 frames at 15 fps."""
    hold = HoverWindow(index=0, start_ns=10 * S, end_ns=11 * S, source="event", seq=1)
    taken = _decoded_in(hold, fps=15.0)
    assert len(taken) == 15  # every frame of the hold, not a 24-frame budget spread over its margins
    # A real 3 s hold keeps its budget (frames about 0.23 s apart).
    assert len(_decoded_in(HoverWindow(index=0, start_ns=10 * S, end_ns=13 * S, source="event", seq=1), fps=15.0)) <= 14
