"""Issue 13: the live core's pure parts (verdict, refly mission, frame picking) and the observer's bounds."""

from __future__ import annotations

import json
from fractions import Fraction

import numpy as np
import pytest

from dronecal_field.live.progress import WaypointOutcome, expected_seqs, pick_frames, verdict
from dronecal_field.live.refly import refly_mission, write_refly_plan
from dronecal_field.live.worker import RING_BYTES, LiveCalibration
from dronecal_field.mavlink.missionfile import CMD_NAV_WAYPOINT, parse_qgc_plan, read_mission
from dronecal_field.runfile.records import Frame, MarkerSpec, RunEvent
from test_mavlink_support import plan_document

WAYPOINTS = [(float(x), 6.0, 2.0) for x in range(-3, 4)]  # seqs 4..10, RTL 11


def _mission(extra_items=()):
    return parse_qgc_plan(json.dumps(plan_document(WAYPOINTS, hold_s=3.0, extra_items=extra_items)))


def _outcome(seq, problem=None, kind="hold"):
    return WaypointOutcome(seq=seq, kind=kind, end_ns=0, frames=10, detections=[], point=None, problem=problem)


def test_verdict_names_missed_and_unflown_waypoints_by_reason():
    expected = [4, 5, 6, 7, 8, 9, 10]
    outcomes = [_outcome(4), _outcome(5, "marker not detected"), _outcome(6), _outcome(7, "only 1 GNSS fixes in the settled part (dropout); need 3"),
                _outcome(8, "marker not detected")]
    v = verdict(outcomes, expected, None, 0.42)
    assert not v.good and v.refly_seqs == (5, 7, 8, 9, 10)
    assert v.text.startswith("re-fly waypoints 5, 8 (marker not detected); 7 (only 1 GNSS fixes")
    assert "9, 10 (not flown)" in v.text and "2/7 detected of 5 flown" in v.text and "coverage 42 %" in v.text
    # a waypoint re-tried and then seen counts as good
    v2 = verdict([*_outcome_list(expected), _outcome(5, "marker not detected"), _outcome(5)], expected, None, None)
    assert v2.good and v2.text.startswith("good: 7/7 waypoints detected")


def _outcome_list(seqs):
    return [_outcome(s) for s in seqs]


def test_refly_mission_keeps_opening_closing_and_only_the_chosen_points(tmp_path):
    mission = _mission()
    cut, mapping = refly_mission(mission, [5, 9], expected_seqs(mission, None))
    assert [it.command for it in cut.items[1:]] == [22, 178, 201, 16, 16, 20]
    assert [it.seq for it in cut.items] == list(range(len(cut.items)))
    assert mapping == {4: 5, 5: 9}
    assert [(it.x, it.y, it.z, it.hold_s) for it in cut.items[4:6]] == [(mission.items[s].x, mission.items[s].y, mission.items[s].z, 3.0) for s in (5, 9)]
    # written and read back as a QGroundControl plan: the same items
    write_refly_plan(tmp_path / "refly.plan", mission, [5, 9], expected_seqs(mission, None))
    back = read_mission(tmp_path / "refly.plan")
    assert [(it.command, it.x, it.y, it.z) for it in back.items[1:]] == [(it.command, it.x, it.y, it.z) for it in cut.items[1:]]
    with pytest.raises(ValueError, match="not NAV_WAYPOINTs"):
        refly_mission(mission, [2], [4, 5])


def test_expected_seqs_follow_plan_grid_when_it_names_mission_waypoints():
    mission = _mission()
    assert expected_seqs(mission, None) == [4, 5, 6, 7, 8, 9, 10]
    assert expected_seqs(mission, {"grid": [{"mission_seq": 6}, {"mission_seq": 4}]}) == [4, 6]
    assert expected_seqs(mission, {"grid": [{"mission_seq": 3}]}) == [4, 5, 6, 7, 8, 9, 10]  # 3 is the ROI: not this plan's grid
    assert all(mission.items[s].command == CMD_NAV_WAYPOINT for s in expected_seqs(mission, None))


def test_pick_frames_spreads_over_the_span():
    frames = [Frame(timestamp_ns=t, format="jpeg", data=b"") for t in range(0, 100)]
    picked = pick_frames(frames, 10, 69, 4)
    assert [f.timestamp_ns for f in picked] == [10, 30, 49, 69]
    assert len(pick_frames(frames, 10, 12, 10)) == 3


def test_observer_memory_is_bounded_and_a_full_queue_skips_waypoints_without_waiting():
    marker = MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.4)
    live = LiveCalibration(_mission(), marker, 1920, 1080, job_queue=2)  # not started: nothing drains the queue
    blob = bytes(1 << 20)  # 1 MB frames at 30 fps for 200 s
    for k in range(6000):
        live.on_frame(Frame(timestamp_ns=k * 33_333_333, format="jpeg", data=blob))
    assert live._ring_bytes <= RING_BYTES and len(live._frames) == RING_BYTES // len(blob)
    kept = np.diff([f.timestamp_ns for f in live._frames])
    assert kept.min() >= 62_500_000  # ring keeps at most 16 frames a second
    for seq in (4, 5, 6, 7):
        live.on_record(RunEvent(timestamp_ns=0, duration_ns=1, type="hover", metadata={"seq": str(seq)}))
    assert live.jobs_dropped == 2 and live.unchecked == [6, 7]
    # Nothing looked at their frames (no worker ran; the ring let them go; no run file): "not checked", never "missed".
    result = live.finish(timeout_s=1.0)
    assert result.unchecked == [4, 5, 6, 7] and result.verdict.refly_seqs == (8, 9, 10) and result.checked_after_landing == []


def test_docs_layout_is_the_generated_one_and_names_only_live_topics():
    from pathlib import Path

    from dronecal_field.live.view import layout_json

    text = (Path(__file__).resolve().parents[1] / "docs" / "foxglove-layout.json").read_text()
    assert text == layout_json()  # regenerate: python -c "from dronecal_field.live.view import layout_json; print(layout_json(), end='')"
    import re

    topics = set(re.findall(r'"(/live/[a-z/]+)"', text))
    assert topics == {"/live/camera/image", "/live/camera/calibration", "/live/camera/annotations", "/live/coverage", "/live/gnss", "/live/status",
                      "/live/waypoints", "/live/site"}


def test_an_estimate_is_shown_only_when_tight_and_where_the_plan_put_the_camera():
    from dronecal_field.core.camera import CameraPose
    from dronecal_field.live.progress import LiveEstimate, constrained
    from dronecal_field.sim.scene import make_truth_camera

    cam = make_truth_camera((-35.36, 149.16, 584.0), 4.0, 0.0, 20.0, 1000.0, 1280, 720)
    est = LiveEstimate(waypoints=20, n_points=18, camera=cam, model="k1", rms_px=0.5, focal_px=1000.0, focal_std_px=20.0, ground_error_15m_cm=3.0)
    assert constrained(est) and constrained(est, cam)
    assert not constrained(LiveEstimate(**{**est.__dict__, "focal_std_px": 30.0}))  # 3 % > 2 %
    moved = cam.with_(pose=CameraPose.from_position(cam.pose.R_cam_from_world, cam.pose.position_world + [0.0, 3.0, 0.0]))
    assert constrained(LiveEstimate(**{**est.__dict__, "camera": moved})) and not constrained(LiveEstimate(**{**est.__dict__, "camera": moved}), cam)
    assert not constrained(None)


@pytest.mark.parametrize("text", ["a,b", "0", "3,-1", ","])
def test_sim_camera_refuses_bad_hide_marker_seqs_in_one_line(text, capsys):
    from dronecal_field.cli import main

    rc = main(["sim", "camera", "--connect", "udpin:127.0.0.1:0", "--hide-marker-at", text])
    err = capsys.readouterr().err
    assert rc == 2 and "--hide-marker-at" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def moving_marker_h264(n: int, t0_ns: int, dt_ns: int, gop: int = 10) -> list:
    """``n`` H.264 access units (a keyframe exactly every ``gop``, no B-frames, 640x480) of the marker moving 1 px a frame, stamped t0 + k dt."""
    import av
    import cv2

    from dronecal_field.video.nal import VideoFrame, is_keyframe
    from test_mavlink_support import marker_jpeg

    gray = cv2.imdecode(np.frombuffer(marker_jpeg(640, 480), np.uint8), cv2.IMREAD_GRAYSCALE)
    enc = av.CodecContext.create("libx264", "w")
    enc.width, enc.height, enc.pix_fmt, enc.gop_size = 640, 480, "yuv420p", gop
    enc.options = {"bframes": "0", "repeat-headers": "1", "tune": "zerolatency", "keyint_min": str(gop), "scenecut": "0"}
    enc.time_base = Fraction(dt_ns, 1_000_000_000)
    data = []
    for k in range(n):
        img = av.VideoFrame.from_ndarray(np.dstack([np.roll(gray, k, axis=1)] * 3), format="bgr24").reformat(format="yuv420p")
        img.pts = k
        data += [bytes(p) for p in enc.encode(img)]
    data += [bytes(p) for p in enc.encode(None)]
    return [VideoFrame(timestamp_ns=t0_ns + k * dt_ns, format="h264", data=d, keyframe=is_keyframe(d, "h264")) for k, d in enumerate(data)]


def test_h264_access_units_are_decoded_from_their_keyframe_and_the_marker_found():
    """A /camera/video stream (H.264, GOP of 10): the live detector decodes from the keyframe before the picked frames."""
    from dronecal_field.live.progress import detect_in_frames, pick_frames
    from dronecal_field.pipeline.detect import make_aruco_detector
    from test_mavlink_support import marker_jpeg

    stream = moving_marker_h264(25, 0, 33_333_333)
    assert [f.keyframe for f in stream].count(True) == 3
    picked = pick_frames(stream, 13 * 33_333_333, 18 * 33_333_333, 3)  # inside the second GOP, after its keyframe
    marker = MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3)
    dets = detect_in_frames(picked, marker, make_aruco_detector("DICT_4X4_50"), stream)
    assert len(dets) == 3
    jpeg = detect_in_frames([Frame(timestamp_ns=0, format="jpeg", data=marker_jpeg(640, 480))], marker, make_aruco_detector("DICT_4X4_50"))
    # the marker moves 1 px a frame: the H.264 detections sit where the JPEG one does, shifted by the frame index
    assert [d.u_px - jpeg[0].u_px for d in dets] == pytest.approx([13.0, 15.0, 18.0], abs=0.5)


def test_the_zone_pass_detects_every_ring_frame_around_a_hold_once_and_covers_only_what_it_saw():
    """The frame cache (live/worker.py): a hover event opens calibrate's read window around the hold; every ring
    frame in it is detected once; frames the ring evicted before the event are not covered (calibrate reads them
    from the file); on finish() a zone still open is covered up to its last detected frame."""
    import time

    from dronecal_field.pipeline.detect import decode_gray, detect_marker, make_aruco_detector
    from dronecal_field.pipeline.sampling import SamplingOptions
    from test_mavlink_support import marker_jpeg

    marker = MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.4)
    live = LiveCalibration(_mission(), marker, 640, 480, ring_frames=20).start()
    jpeg = marker_jpeg(640, 480)
    t0, dt = 1_700_000_000_000_000_000, 66_666_667  # 15 fps
    stamp = [t0 + k * dt for k in range(91)]  # 6 s of frames

    def wait_for(n):  # the worker is niced: give it time (no assertion on how long it takes)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            cache = live.frame_results()
            if cache is not None and len(cache) >= n:
                return
            time.sleep(0.02)

    for k in range(40):  # no zone yet: the 20-frame ring evicts frames 0-19 undetected
        live.on_frame(Frame(timestamp_ns=stamp[k], format="jpeg", data=jpeg))
    hold = (t0 + 1_000_000_000, t0 + 2_000_000_000)
    live.on_record(RunEvent(timestamp_ns=hold[0], duration_ns=hold[1] - hold[0], type="hover", metadata={"seq": "4"}))
    wait_for(20)
    for start in range(40, 91, 10):  # in batches the ring holds: nothing more is lost
        for k in range(start, min(start + 10, 91)):
            live.on_frame(Frame(timestamp_ns=stamp[k], format="jpeg", data=jpeg))
        wait_for(sum(1 for k in range(20, min(start + 10, 91)) if stamp[k] <= hold[1] + 3_200_000_000))  # the first zone's
    # a second hold whose zone runs past the last frame: pending when the flight ends
    live.on_record(RunEvent(timestamp_ns=t0 + 5_500_000_000, duration_ns=300_000_000, type="hover", metadata={"seq": "5"}))
    wait_for(71)
    result = live.finish(timeout_s=30.0)
    cache = result.frames
    widen = int((SamplingOptions().margin_s + SamplingOptions().dense_s) * 1e9)
    assert hold[1] + widen < stamp[90]  # the premise: the first zone closed while frames still came
    # covered: from just after frame 19 (the last evicted undetected) to frame 90 (the last detected)
    assert cache.covered == ((stamp[19] + 1, stamp[90]),)
    assert cache.t_ns.tolist() == stamp[20:91]  # each ring frame of the zones once, nothing outside them
    whole = detect_marker(decode_gray(jpeg), marker, make_aruco_detector("DICT_4X4_50"), 0).detection
    assert all(r.detection is not None and abs(r.detection.u_px - whole.u_px) < 1e-3 for r in cache.results)
    assert cache.uncovered([(t0, stamp[90])]) == [(t0, stamp[19])]
    assert result.to_dict()["frame_cache"]["frames_detected"] == 71


def test_holds_whose_frames_left_the_ring_are_checked_after_landing_from_the_run_file(tmp_path):
    """Issue 19: a worker too slow for the flight (here: none ran) never calls a waypoint "missed" unlooked. The ring
    keeps 10 frames, so it has let go of every hold but the last; after landing, ``finish`` reads them from the run."""
    import time

    from dronecal_field.geodesy import EnuOrigin
    from dronecal_field.runfile.records import FORMAT_VERSION, Attitude, GnssFix, RunMetadata
    from dronecal_field.runfile.writer import RunWriter
    from dronecal_field.sim.scene import make_truth_camera
    from test_live_foxglove import HOME, OFFSET, WAYPOINTS as HOLDS, feed_flight
    from test_mavlink_support import plan_document

    mission = parse_qgc_plan(json.dumps(plan_document(HOLDS, hold_s=3.0)))
    marker = MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.4, offset_frd_m=OFFSET)
    live = LiveCalibration(mission, marker, 640, 480, origin=EnuOrigin(*HOME), job_queue=len(HOLDS), ring_frames=10)
    run_path = tmp_path / "run.mcap"
    writer = RunWriter(run_path, RunMetadata(format_version=FORMAT_VERSION, width=640, height=480, marker=marker), camera="image")

    class Tee:  # the recorder's part: every record to the file and to the live observer
        def on_frame(self, frame):
            writer.write_frame(frame)
            live.on_frame(frame)

        def on_record(self, record):
            if isinstance(record, GnssFix):
                writer.write_fix(record)
            elif isinstance(record, Attitude):
                writer.write_attitude(record)
            elif isinstance(record, RunEvent):
                writer.write_event(record)
            live.on_record(record)

    feed_flight(Tee(), make_truth_camera(HOME, 4.0, 0.0, 20.0, 560.0, 640, 480), time.time_ns())
    writer.close()
    result = live.finish(timeout_s=1.0, run_path=run_path)
    seqs = list(range(4, 4 + len(HOLDS)))
    assert result.checked_after_landing == seqs and result.unchecked == []
    assert sorted(o.seq for o in result.outcomes if o.good) == seqs  # every hold's marker found, from the file
    assert result.verdict.good and not result.verdict.refly_seqs
    assert result.estimate is not None and abs(result.estimate.focal_px - 560.0) < 0.03 * 560.0


def test_a_scout_flight_never_asks_to_re_fly_the_waypoints_its_camera_does_not_see():
    from dronecal_field.live.progress import scout_verdict

    mission = _mission()
    assert expected_seqs(mission, {"kind": "scout", "grid": [{"mission_seq": 4}]}) == []
    v = scout_verdict([_outcome(4), _outcome(5, "marker not detected"), _outcome(6)])
    assert v.good and v.refly_seqs == () and "seen at 2 of 3 waypoints" in v.text and "--from-run" in v.text
    assert not scout_verdict([_outcome(4, "marker not detected")]).good


def test_the_zone_pass_decodes_h264_access_units_in_stream_order_and_caches_them_for_calibrate():
    """Issue 22: live detection on compressed video. H.264 (GOP of 10, the marker moving 1 px a frame): a hold's zone
    is decoded in flight from the keyframe before it, every access unit in it detected once and covered, so calibrate
    takes those outcomes instead of decoding the file again; units before the first keyframe are left to calibrate."""
    import time

    from dronecal_field.pipeline.sampling import SamplingOptions

    t0, dt = 1_700_000_000_000_000_000, 66_666_667
    units = moving_marker_h264(90, t0, dt)
    marker = MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.4)
    live = LiveCalibration(_mission(), marker, 640, 480).start()
    for unit in units[3:8]:  # the stream joined mid-GOP: the ring's first keyframe is unit 10
        live.on_frame(unit)
    for unit in units[10:90]:
        live.on_frame(unit)
    hold = (t0 + 2 * 1_000_000_000, t0 + 3 * 1_000_000_000)  # units 30-45, its zone widened by calibrate's margins
    live.on_record(RunEvent(timestamp_ns=hold[0], duration_ns=hold[1] - hold[0], type="hover", metadata={"seq": "4"}))
    deadline = time.monotonic() + 120
    s = SamplingOptions()
    widen = int((s.margin_s + s.dense_s) * 1e9)
    in_zone = [u.timestamp_ns for u in units[3:8] + units[10:90] if hold[0] - widen <= u.timestamp_ns <= hold[1] + widen]
    while time.monotonic() < deadline and not all(t in live._outcomes for t in in_zone if t >= units[10].timestamp_ns):
        time.sleep(0.05)
    result = live.finish(timeout_s=30.0)
    cache = result.frames
    assert cache is not None and cache.formats == ("h264",)
    in_zone = [t for t in in_zone if t >= units[10].timestamp_ns]  # before the first keyframe: left to calibrate
    assert cache.t_ns.tolist() == in_zone  # each access unit of the zone once, nothing outside it
    found = [r.detection for r in cache.results if r is not None and r.detection is not None]
    assert len(found) == len(in_zone)
    # the marker moves 1 px a frame: each detection sits at its unit's shift from the first
    k = np.round((cache.t_ns - t0) / dt).astype(int)
    u = np.array([d.u_px for d in found])
    assert np.allclose(u - u[0], k - k[0], atol=0.5)
    assert len(cache.covered) == 1 and cache.covered[0][0] <= in_zone[0] and cache.covered[0][1] >= in_zone[-1]
