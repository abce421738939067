"""A 5 fps stream's legs keep every frame: skipping one would leave 0.4 s between detections, past the legs' cubic span.

A 4K main run recorded at 5 frames per wall second (the simulators at half speed, bench_scout --speedup 0.5) took
every other frame along its legs ('at least 0.25 s' after the last), 0.4 s apart, and pipeline.legs paired 27 fixes
on 31 legs: a ground error of 42 px RMS against the truth.
"""

from __future__ import annotations

import numpy as np

from dronecal_field.pipeline.legs import LegOptions
from dronecal_field.pipeline.sampling import FrameSelector, SamplingOptions

S = 1_000_000_000


def _leg_gaps(fps: float, jitter_s: float = 0.0, seed: int = 0) -> np.ndarray:
    """Gaps (s) between the frames decoded along a 30 s leg of a stream at ``fps`` whose stamps jitter by +-jitter_s."""
    rng = np.random.default_rng(seed)
    n = int(40 * fps)
    stamps = np.sort((np.arange(n) / fps + rng.uniform(-jitter_s, jitter_s, n)) * S).astype(np.int64)
    sel = FrameSelector([], legs=[(5 * S, 35 * S)])
    taken = np.array([t for t in stamps if sel.wants(int(t))[0] and 5 * S <= t <= 35 * S], np.int64)
    return np.diff(taken) / S


def test_the_selector_span_is_the_legs_span():
    assert SamplingOptions().leg_max_gap_s == LegOptions().max_frame_gap_s


def test_a_5_fps_leg_keeps_every_frame():
    gaps = _leg_gaps(5.0)
    assert gaps.max() <= LegOptions().max_frame_gap_s, gaps.max()
    assert abs(float(np.median(gaps)) - 0.2) < 1e-3 and len(gaps) >= 149  # 30 s at 0.2 s
    jittered = _leg_gaps(5.0, 0.01, seed=2)
    assert jittered.max() <= LegOptions().max_frame_gap_s, jittered.max()


def test_a_4_fps_leg_keeps_every_frame_though_it_cannot_meet_the_span():
    gaps = _leg_gaps(4.0)
    assert abs(float(np.median(gaps)) - 0.25) < 1e-3 and len(gaps) >= 119


def test_10_and_25_fps_keep_their_period():
    """The rule only adds frames where a skip would break the span: 10 fps still every 3rd (0.3 s), 25 fps every 7th."""
    assert abs(float(np.median(_leg_gaps(10.0))) - 0.3) < 1e-3 and abs(float(np.median(_leg_gaps(25.0))) - 0.28) < 1e-3
    assert _leg_gaps(10.0).max() <= 0.3 + 1e-6
