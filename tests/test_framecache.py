"""The live pass's detections reused by calibrate (pipeline/framecache.py, calibrate_run(..., live=)).

Intervals first (pure); then a real run file from the independent contract
writer, its frames detected once into a FrameResults (as fly's live worker
does), and calibrate with it: the same camera as without, the stats saying the
outcomes came from the cache, and a cache with a hole reading the hole's frames
from the file.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from contract_writer import RunSpec, MarkerLook, grid_waypoints, make_flight, pole_camera, write_run
from dronecal_field.pipeline.detect import FrameResult, decode_gray, detect_marker, make_aruco_detector
from dronecal_field.pipeline.framecache import FrameResults, intersect_intervals, merge_intervals, subtract_intervals
from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run
from dronecal_field.runfile.reader import open_run

S = 1_000_000_000


@pytest.mark.parametrize(
    "ranges, minus, expected",
    [
        ([(0, 10)], [], [(0, 10)]),
        ([(0, 10)], [(3, 5)], [(0, 2), (6, 10)]),
        ([(0, 10)], [(0, 10)], []),
        ([(0, 10)], [(-5, 2), (8, 20)], [(3, 7)]),
        ([(0, 10), (20, 30)], [(5, 25)], [(0, 4), (26, 30)]),
        ([(0, 10), (5, 15)], [(11, 11)], [(0, 10), (12, 15)]),  # overlapping input merges first
        ([(0, 10)], [(11, 20)], [(0, 10)]),
    ],
)
def test_interval_subtraction(ranges, minus, expected):
    assert subtract_intervals(ranges, minus) == expected
    # what is left and what was taken out make the whole again, and never overlap
    left = subtract_intervals(ranges, minus)
    assert merge_intervals(left + intersect_intervals(ranges, minus)) == merge_intervals(ranges)
    assert intersect_intervals(left, minus) == []


def test_frame_results_lookup_covered_and_items_in():
    det = FrameResult(detection=None, other_ids=(3,))
    cache = FrameResults.build({30: det, 10: None, 20: FrameResult(detection=None), 55: det}, [(15, 35), (5, 12), (34, 40)])
    assert cache.t_ns.tolist() == [10, 20, 30, 55]
    assert cache.covered == ((5, 12), (15, 40))
    assert [cache.covered_at(t) for t in (4, 5, 12, 13, 15, 40, 41)] == [False, True, True, False, True, True, False]
    assert cache.uncovered([(0, 100)]) == [(0, 4), (13, 14), (41, 100)]
    # items only where covered: 55 has an outcome but lies outside every covered interval
    assert [t for t, _ in cache.items_in([(0, 100)])] == [10, 20, 30]
    assert [t for t, _ in cache.items_in([(11, 25)])] == [20]
    assert cache.lookup(55) == (True, det) and cache.lookup(10) == (True, None) and cache.lookup(11) == (False, None)
    assert cache.covered_s == pytest.approx((7 + 25) / 1e9)


@pytest.fixture(scope="module")
def replay(tmp_path_factory):
    """A 12-hold run (events, 10 fps JPEG) and every one of its frames detected once, as the live pass would."""
    tmp = tmp_path_factory.mktemp("cache")
    camera = pole_camera(distortion=(-0.1, 0.0, 0.0, 0.0, 0.0))
    flight = make_flight(camera, grid_waypoints(east_m=(-2.5, 0.0, 2.5), north_m=(6.0, 9.0), up_m=(1.5, 3.5)), seed=5)
    path = tmp / "run.mcap"
    write_run(path, camera, flight, MarkerLook(marker_id=7), RunSpec(latency_s=0.2))
    detector = make_aruco_detector("DICT_4X4_50")
    with open_run(path) as run:
        marker = run.metadata.marker
        outcomes = {}
        for f in run.iter_frames():
            image = decode_gray(f.data)
            outcomes[f.timestamp_ns] = None if image is None else detect_marker(image, marker, detector, f.timestamp_ns)
    options = CalibrateOptions(trials=0)
    return path, outcomes, options, calibrate_run(path, options)


def _same_camera(a, b) -> None:
    ia, ib = a.camera.intrinsics, b.camera.intrinsics
    assert abs(ia.fx / ib.fx - 1) < 2e-3 and abs(ia.fy / ib.fy - 1) < 2e-3, (ia, ib)
    assert np.hypot(ia.cx - ib.cx, ia.cy - ib.cy) < 1.0
    assert np.linalg.norm(a.camera.pose.position_world - b.camera.pose.position_world) < 0.01
    assert abs(a.result.rms_px - b.result.rms_px) < 0.05


def test_calibrate_with_a_full_cache_decodes_nothing_and_finds_the_same_camera(replay):
    path, outcomes, options, plain = replay
    stamps = sorted(outcomes)
    cache = FrameResults.build(outcomes, [(stamps[0], stamps[-1])], formats=("jpeg",))
    cached = calibrate_run(path, replace(options, out_dir=path.parent / "cached"), live=cache)
    assert cached.frames.formats == plain.frames.formats == ("jpeg",)
    html = (path.parent / "cached" / "report.html").read_text()
    assert f"{cached.frames.frames_from_live} detected in flight by the live pass" in html
    assert plain.frames.frames_from_live == 0
    assert cached.frames.frames_from_live == cached.frames.frames_decoded > 100
    assert cached.frames.frames_decoded == plain.frames.frames_decoded  # same candidates, same choices
    assert cached.frames.frames_with_marker == pytest.approx(plain.frames.frames_with_marker, abs=3)
    assert cached.background is not None and cached.background.shape == (480, 640)  # read from the file: no frame was decoded
    _same_camera(cached, plain)


def test_a_hole_in_the_cache_is_read_from_the_file(replay):
    path, outcomes, options, plain = replay
    stamps = sorted(outcomes)
    # the live ring lost a third of the run in the middle before detecting it: no outcomes, not covered
    a, b = stamps[len(stamps) // 3], stamps[2 * len(stamps) // 3]
    kept = {t: r for t, r in outcomes.items() if not a <= t <= b}
    cache = FrameResults.build(kept, [(stamps[0], a - 1), (b + 1, stamps[-1])])
    cached = calibrate_run(path, options, live=cache)
    in_hole = sum(a <= d.timestamp_ns <= b for d in cached.detections)
    assert in_hole > 20  # the hole's frames came from the file
    assert 0.4 * cached.frames.frames_decoded < cached.frames.frames_from_live < 0.8 * cached.frames.frames_decoded
    assert cached.frames.to_dict()["frames_from_live_pass"] == cached.frames.frames_from_live
    _same_camera(cached, plain)
