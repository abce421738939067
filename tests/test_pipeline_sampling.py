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


def _video_cost(options: SamplingOptions, gop: int, fps: float = 25.0, hold_s: float = 6.0, legs=None, start_s: float = 10.0) -> tuple[int, int, np.ndarray]:
    """(frames wanted, access units decoded, wanted stamps) of a /camera/video stream with a keyframe every ``gop`` frames.

    A wanted frame costs the access units since the last one decoded in its GOP
    (the decoder runs on from there) or since its keyframe (VideoFrameDecoder).
    """
    window = HoverWindow(index=0, start_ns=int(start_s * S), end_ns=int((start_s + hold_s) * S), source="event", seq=1)
    selector = FrameSelector([window], options, legs=legs, video=True)
    stamps = (np.arange(int(40 * fps)) * S / fps).astype(np.int64)
    wanted, units, pending = [], 0, 0
    for i, t in enumerate(stamps):
        key = i % gop == 0
        pending = 1 if key else pending + 1
        if selector.wants(int(t), keyframe=key)[0]:
            wanted.append(int(t))
            units, pending = units + pending, 0
    return len(wanted), units, np.array(wanted, np.int64)


def test_video_windows_take_keyframes_and_a_burst_not_frames_spread_over_each_gop():
    """A 6 s hold at 25 fps, 2 s GOP: the old choice (a frame every 0.4 s) decodes nearly every access unit of
    the widened window (8.4 s, 210 frames); keyframes + 2 frames after each decode 12, 17x fewer."""
    old_wanted, old_units, _ = _video_cost(SamplingOptions(video_bursts=False), gop=50)
    new_wanted, new_units, stamps = _video_cost(SamplingOptions(), gop=50)
    assert old_wanted == 24 and old_units >= 200
    assert new_units == new_wanted == 12  # 4 keyframes in [8.8 s, 17.2 s], each with the 2 frames after it
    assert np.count_nonzero(stamps % (2 * S) == 0) == 4 and np.diff(stamps).max() <= 2 * S
    # A 4 s GOP: its keyframes alone (no frame is worth decoding half a GOP for); a 10 s GOP still gets a
    # burst in the hold's middle, decoded from its keyframe (the cost such a camera imposes, counted).
    assert _video_cost(SamplingOptions(), gop=100)[1] == 6
    wanted, units, stamps = _video_cost(SamplingOptions(), gop=250)
    assert np.count_nonzero((stamps >= 13 * S) & (stamps <= 13 * S + 3 * S // 25)) == 3 and 60 < units < 100
    # An image run (video=False) keeps the clock-spaced choice whatever keyframe says.
    plain = FrameSelector([HoverWindow(index=0, start_ns=10 * S, end_ns=16 * S, source="event", seq=1)])
    assert sum(plain.wants(int(t), keyframe=True)[0] for t in np.arange(8 * S, 18 * S, S // 25)) == 24


def test_a_video_hold_shorter_than_its_gop_still_gets_a_burst_in_its_settled_part():
    """plan's default hold at 25 fps is 2.6 s (1 s to settle + 40 frames): with a 2 s GOP its settled part
    (1.4 s) may hold no keyframe. Whatever the phase, it gets 3 frames there, at most one GOP decoded for them."""
    for phase in np.arange(0.0, 2.0, 0.1):
        wanted, units, stamps = _video_cost(SamplingOptions(), gop=50, hold_s=2.6, start_s=10.0 + phase)
        settled = stamps[(stamps >= (11.0 + phase) * S) & (stamps <= (12.4 + phase) * S)]
        assert len(settled) >= 3, phase
        assert units <= 2 * 3 + 50 + 3, phase  # keyframe bursts in the margins, plus at most one GOP's run-up


def test_video_legs_keep_their_period_and_decode_every_access_unit():
    """A 6 s leg (8.4 s with its margins) at 25 fps, 2 s GOP: frames every 0.25 s as for images, so the decoder runs
    through nearly every access unit of the leg; each leg fix needs two detections on each side, which a burst
    gives one or two fixes of a GOP for a third of it. The hold before it still costs its 12 units only."""
    legs = [(20 * S, 26 * S)]
    wanted, units, stamps = _video_cost(SamplingOptions(), gop=50, legs=legs)
    on_leg = stamps[(stamps >= 18 * S) & (stamps <= 28 * S)]
    assert len(on_leg) == 31 and np.diff(on_leg).max() <= 0.28 * S  # 18.8 s to 27.2 s, every 7th frame
    # The hold's 12, then every unit from the keyframe at 18 s to 27.2 s (231) but the 1-2 of each GOP's tail after
    # its last wanted frame.
    assert units == 12 + 221
