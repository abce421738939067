"""Issue 22: the live pass's frame cache on H.264 (real libx264 access units, FFmpeg decoding, calibrate's detector).

A unit that does not decode where the live pass looked (no keyframe before it in what it held, no picture in it) is
no corrupt frame of the file: it is left out of the cache, and calibrate decodes it from the run file. A covered span
must hold a keyframe, or calibrate's read of the file after it would start without its reference chain.
"""

from __future__ import annotations

import json
import time

import pytest

from dronecal_field.live.worker import LiveCalibration
from dronecal_field.mavlink.missionfile import parse_qgc_plan
from dronecal_field.runfile.records import Frame, MarkerSpec, RunEvent
from dronecal_field.video.decode import VideoFrameDecoder
from dronecal_field.video.nal import VideoFrame
from test_live_progress import moving_marker_h264
from test_mavlink_support import marker_jpeg, plan_document

T0, DT = 1_700_000_000_000_000_000, 66_666_667  # 15 fps
MARKER = MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.4)
AUD_ONLY = b"\x00\x00\x00\x01\x09\xf0"  # an access unit delimiter and nothing else: a unit with no picture in it


def h264_units(n: int, gop: int) -> list[VideoFrame]:
    """``n`` H.264 access units (no B-frames, 640x480) of the marker moving 1 px a frame, a keyframe every ``gop``."""
    return moving_marker_h264(n, T0, DT, gop)


def jpeg_u_px() -> float:
    from dronecal_field.pipeline.detect import decode_gray, detect_marker, make_aruco_detector

    return detect_marker(decode_gray(marker_jpeg(640, 480)), MARKER, make_aruco_detector("DICT_4X4_50"), 0).detection.u_px


def _mission():
    return parse_qgc_plan(json.dumps(plan_document([(float(x), 6.0, 2.0) for x in range(-3, 4)], hold_s=3.0)))


def test_a_unit_with_no_picture_decodes_to_none_never_to_the_picture_before_it():
    units = h264_units(3, gop=10)
    dec = VideoFrameDecoder("h264", threads=1)
    dec.push(units[0])
    first = dec.gray()
    assert first is not None and first.shape == (480, 640)
    dec.push(VideoFrame(timestamp_ns=units[1].timestamp_ns, format="h264", data=AUD_ONLY, keyframe=False))
    assert dec.gray() is None  # it used to hand back unit 0's picture under unit 1's stamp
    assert dec.decoded == 2


def test_units_that_do_not_decode_in_the_live_pass_are_left_out_of_the_cache_not_counted_corrupt():
    """After landing, a hold checked from the ring: the ring joined the stream mid-GOP (units 12-19 come before its
    first keyframe, 20) and unit 21 carries no picture. The hold's picks are decoded in stream order; the
    undecodable ones get no outcome (calibrate decodes them from the file), every other one its detection."""
    units = h264_units(60, gop=10)
    units[21] = VideoFrame(timestamp_ns=units[21].timestamp_ns, format="h264", data=AUD_ONLY, keyframe=False)
    live = LiveCalibration(_mission(), MARKER, 640, 480)  # no worker: the hold is checked by finish()
    for unit in units[12:]:
        live.on_frame(unit)
    live.on_record(RunEvent(timestamp_ns=units[0].timestamp_ns, duration_ns=units[59].timestamp_ns - units[0].timestamp_ns,
                            type="hover", metadata={"seq": "4"}))
    result = live.finish(timeout_s=1.0)
    assert result.checked_after_landing == [4]
    cache = result.frames
    assert cache is not None and cache.formats == ("h264",)
    stamps = cache.t_ns.tolist()
    assert len(stamps) >= 5
    assert None not in cache.results  # nothing in the cache says "corrupt"
    dropped = [units[k].timestamp_ns for k in list(range(12, 20)) + [21]]
    assert not set(stamps) & set(dropped)
    assert all(cache.lookup(t) == (False, None) for t in dropped)
    u0 = jpeg_u_px()
    exact = 0
    for t, r in zip(stamps, cache.results):
        k = (t - T0) // DT
        assert k >= 20 and r.detection is not None
        if k == 20 or k >= 30:  # 22-29 follow the unit with no picture: FFmpeg conceals them from unit 20 (no error)
            assert r.detection.u_px - u0 == pytest.approx(k, abs=0.5)  # its own picture: the marker moved k px
            exact += 1
    assert exact >= 4


def test_a_zone_with_no_keyframe_inside_is_detected_but_not_covered():
    """A GOP longer than the zone (one keyframe, unit 0): the zone pass decodes and detects every zone unit from that
    keyframe, but covers nothing, so calibrate reads the zone from the file with its chain; its frames still serve
    by stamp (``FrameResults.lookup``)."""
    from dronecal_field.pipeline.sampling import SamplingOptions

    units = h264_units(120, gop=200)
    assert [u.keyframe for u in units].count(True) == 1
    live = LiveCalibration(_mission(), MARKER, 640, 480, options=_options(margin_s=0.5, dense_s=0.0)).start()
    for unit in units:
        live.on_frame(unit)
    hold = (units[60].timestamp_ns, units[75].timestamp_ns)
    live.on_record(RunEvent(timestamp_ns=hold[0], duration_ns=hold[1] - hold[0], type="hover", metadata={"seq": "4"}))
    s = SamplingOptions(margin_s=0.5, dense_s=0.0)
    in_zone = [u.timestamp_ns for u in units if hold[0] - s.margin_s * 1e9 <= u.timestamp_ns <= hold[1] + s.margin_s * 1e9]
    deadline = time.monotonic() + 120  # the worker is niced on a busy machine: wait for it, assert nothing on time
    while time.monotonic() < deadline and not all(t in live._outcomes for t in in_zone):
        time.sleep(0.05)
    result = live.finish(timeout_s=30.0)
    cache = result.frames
    assert set(in_zone) <= set(cache.t_ns.tolist())
    assert cache.covered == ()
    u0 = jpeg_u_px()
    for t in in_zone:
        has, r = cache.lookup(t)
        assert has and r.detection is not None and r.detection.u_px - u0 == pytest.approx((t - T0) // DT, abs=0.5)


def _options(margin_s: float, dense_s: float):
    from dataclasses import replace

    from dronecal_field.live.progress import LiveOptions
    from dronecal_field.pipeline.sampling import SamplingOptions

    return replace(LiveOptions(), sampling=SamplingOptions(margin_s=margin_s, dense_s=dense_s))


def test_a_jpeg_frame_that_does_not_decode_is_still_corrupt():
    """JPEG frames decode on their own: one that does not is corrupt in the file too, and the cache says so."""
    live = LiveCalibration(_mission(), MARKER, 640, 480)
    good = marker_jpeg(640, 480)
    frames = [Frame(timestamp_ns=T0 + k * DT, format="jpeg", data=good if not 25 <= k <= 35 else good[: len(good) // 3])
              for k in range(60)]
    for f in frames:
        live.on_frame(f)
    live.on_record(RunEvent(timestamp_ns=T0, duration_ns=59 * DT, type="hover", metadata={"seq": "4"}))
    result = live.finish(timeout_s=1.0)
    cache = result.frames
    assert cache is not None and len(cache) >= 5
    bad = {frames[k].timestamp_ns for k in range(25, 36)}
    corrupt = {t for t, r in zip(cache.t_ns.tolist(), cache.results) if r is None}  # looked at, did not decode
    assert corrupt and corrupt <= bad and all(r is not None and r.detection is not None for t, r in zip(cache.t_ns.tolist(), cache.results) if t not in bad)
