"""A fly-through leg's frames bracket every fix whatever the camera's rate: the selector's period against real stamps.

The four-camera site flight's MJPEG cameras ran at 8 fps with stamps ~0.1249 s apart: 'a frame at least 0.25 s after
the last' then took every third frame half of the time, 0.375 s gaps past the 0.35 s the legs' cubic may span
(pipeline.legs.LegOptions.max_frame_gap_s), and b-wide's legs gave 77 pairs of ~900 detections.
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


def test_an_8_fps_leg_slightly_fast_keeps_every_other_frame():
    max_gap = LegOptions().max_frame_gap_s
    gaps = _leg_gaps(8.0 * 1.0008, 0.0)  # 0.1249 s apart: the simulator's MJPEG stream on the site flight
    assert gaps.max() <= max_gap and abs(float(np.median(gaps)) - 0.2498) < 0.002
    jittered = _leg_gaps(8.0, 0.01, seed=1)  # +-10 ms of arrival jitter
    assert jittered.max() <= max_gap, jittered.max()
    assert len(jittered) >= 110  # 30 s at ~0.25 s


def test_faster_streams_keep_their_period():
    """25 fps keeps every 7th frame (0.28 s), 10 fps every 3rd (0.3 s): the slack is a fifth of a frame, not a frame."""
    g25 = _leg_gaps(25.0, 0.0)
    g10 = _leg_gaps(10.0, 0.0)
    assert abs(float(np.median(g25)) - 0.28) < 1e-3 and abs(float(np.median(g10)) - 0.3) < 1e-3
    assert g25.max() <= LegOptions().max_frame_gap_s and g10.max() <= LegOptions().max_frame_gap_s


# A 5 fps stream's legs keep every frame: skipping one would leave 0.4 s between detections, past the legs' cubic span.
#
# A 4K main run recorded at 5 frames per wall second (the simulators at half speed, bench_scout --speedup 0.5) took
# every other frame along its legs ('at least 0.25 s' after the last), 0.4 s apart, and pipeline.legs paired 27 fixes
# on 31 legs: a ground error of 42 px RMS against the truth.


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
