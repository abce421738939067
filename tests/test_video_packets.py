"""H.264 / H.265 pass-through: Annex B access units, /camera/video runs, lazy decoding, the stream monitor.

Real parts: clips encoded here by PyAV's libx264 / libx265 into real MP4 and
MKV files, read back as packets by PacketSource, written to and read from
real MCAP files, decoded by FFmpeg.
"""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import pytest

from dronecal_field.errors import ContractError, InputError
from dronecal_field.pipeline.detect import FrameDecoder
from dronecal_field.runfile.reader import open_run
from dronecal_field.runfile.records import FORMAT_VERSION, Frame, GnssFix, MarkerSpec, RunMetadata
from dronecal_field.runfile.writer import RunWriter
from dronecal_field.video.monitor import StreamMonitor
from dronecal_field.video.nal import VideoFrame, access_unit, is_keyframe, nal_type, parameter_sets, split_annexb
from dronecal_field.video.packets import open_packet_source

PARAMS = {"h264": {7, 8}, "h265": {32, 33, 34}}


def encode_clip(path, fmt="h264", n=30, size=(160, 128), gop=10, fps=25):
    """A real clip (MP4 / MKV, no B-frames): a bright square moving one pixel per frame on grey noise."""
    import av

    rng = np.random.default_rng(3)
    background = rng.integers(60, 120, (size[1], size[0], 3), dtype=np.uint8)
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264" if fmt == "h264" else "libx265", rate=fps)
        stream.width, stream.height, stream.pix_fmt = size[0], size[1], "yuv420p"
        if fmt == "h264":
            stream.options = {"bf": "0", "g": str(gop), "crf": "18"}
        else:
            stream.options = {"x265-params": f"bframes=0:keyint={gop}:min-keyint={gop}:log-level=error", "crf": "18"}
        for i in range(n):
            img = background.copy()
            img[20:60, 10 + i : 50 + i] = 240
            frame = av.VideoFrame.from_ndarray(img, format="rgb24")
            frame.pts, frame.time_base = i, Fraction(1, fps)
            for packet in stream.encode(frame):
                out.mux(packet)
        for packet in stream.encode(None):
            out.mux(packet)


def read_all(url):
    source = open_packet_source(url)
    frames = []
    while True:
        f = source.read(timeout_s=5.0)
        if f is None:
            break
        frames.append(f)
    source.close()
    return source, frames


def decode_all(frames, fmt):
    import av

    ctx = av.CodecContext.create("h264" if fmt == "h264" else "hevc", "r")
    out = []
    for f in frames:
        out.extend(ctx.decode(av.Packet(f.data)))
    out.extend(ctx.decode(None))
    return [np.ascontiguousarray(np.frombuffer(p.planes[0], np.uint8).reshape(p.height, p.planes[0].line_size)[:, : p.width]) for p in out]


@pytest.mark.parametrize("fmt,ext", [("h264", "mp4"), ("h265", "mkv"), ("h264", "mkv")])
def test_file_packets_become_annexb_access_units_with_parameter_sets(tmp_path, fmt, ext):
    clip = tmp_path / f"clip.{ext}"
    encode_clip(clip, fmt, n=30, gop=10)
    source, frames = read_all(str(clip))
    assert source.format == fmt and (source.width, source.height) == (160, 128)
    assert len(frames) == 30 and source.clock == "file"
    assert [f.keyframe for f in frames].count(True) == 3
    for f in frames:
        assert f.data.startswith(b"\x00\x00\x00\x01")  # avcC/hvcC samples came length-prefixed
        types = {nal_type(n, fmt) for n in split_annexb(f.data)}
        if f.keyframe:
            assert PARAMS[fmt] <= types  # SPS/PPS (+VPS) in front of every keyframe, from the extradata
        assert is_keyframe(f.data, fmt) == f.keyframe
    assert [f.pts_ns for f in frames] == [i * 40_000_000 for i in range(30)]
    # Each keyframe access unit decodes on its own, from its own bytes.
    for k in (10, 20):
        assert decode_all(frames[k:k + 5], fmt)[0].shape == (128, 160)
    assert len(decode_all(frames, fmt)) == 30
    assert source.monitor.frames_lost == 0 and not source.b_frames


def test_parameter_sets_from_avcc_and_annexb():
    sps, pps = bytes([0x67, 0x42, 0xC0, 0x0D, 0xDA]), bytes([0x68, 0xCE, 0x3C, 0x80])
    avcc = bytes([1, 0x42, 0xC0, 0x0D, 0xFF, 0xE1]) + len(sps).to_bytes(2, "big") + sps + b"\x01" + len(pps).to_bytes(2, "big") + pps
    assert parameter_sets(avcc, "h264") == ([sps, pps], 4)
    annexb = b"\x00\x00\x00\x01" + sps + b"\x00\x00\x01" + pps
    assert parameter_sets(annexb, "h264") == ([sps, pps], None)
    idr = bytes([0x65, 0x88, 0x84, 0x00, 0x33])
    # An Annex B keyframe without in-band parameter sets gets them (after its delimiter); a P-frame is untouched.
    au = access_unit(b"\x00\x00\x00\x01\x09\xf0" + b"\x00\x00\x01" + idr, "h264", True, [sps, pps])
    assert [nal_type(n, "h264") for n in split_annexb(au)] == [9, 7, 8, 5]
    p_frame = b"\x00\x00\x00\x01" + bytes([0x41, 0x9A, 0x00])
    assert access_unit(p_frame, "h264", False, [sps, pps]) == p_frame
    length_prefixed = len(idr).to_bytes(4, "big") + idr
    assert split_annexb(access_unit(length_prefixed, "h264", True, [sps, pps], 4)) == [sps, pps, idr]


def test_stream_monitor_reports_a_stall_a_gap_and_corruption():
    m = StreamMonitor(frame_period_s=0.04)
    t0 = 1_700_000_000_000_000_000
    incidents = []
    period = 40_000_000
    for i in range(50):  # 2 s steady, 2 ms network delay
        incidents += m.observe(t0 + i * period + 2_000_000, i * period)
    assert not m.lagging and m.lag_ns == 0
    # The server stalls for 1 s, then sends 25 backlogged frames in a burst, then runs on.
    stall_end = t0 + 50 * period + 1_000_000_000
    for k in range(25):
        incidents += m.observe(stall_end + k * 1_000_000, (50 + k) * period)
    assert m.lagging and 0.9e9 < m.max_lag_ns < 1.1e9
    for i in range(75, 200):  # caught up: pacing as before
        incidents += m.observe(t0 + i * period + 2_000_000, i * period)
    lag = [x for x in incidents if x.kind == "video_lag"]
    assert len(lag) == 1 and 0.9 < lag[0].value < 1.1 and m.lag_events == 1
    # Three frames (200-202) never arrive; the next arrives flagged corrupt.
    incidents = m.observe(t0 + 203 * period + 2_000_000, 203 * period, corrupt=True)
    assert [x.kind for x in incidents] == ["video_corrupt", "video_lost"]
    assert incidents[1].value == 3.0 and m.frames_lost == 3 and m.corrupt == 1


def _meta(width=160, height=128):
    return RunMetadata(format_version=FORMAT_VERSION, width=width, height=height, marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.5))


def test_video_run_round_trip_and_window_decoding_from_the_keyframe(tmp_path):
    clip = tmp_path / "clip.mp4"
    encode_clip(clip, "h264", n=40, gop=10)
    _, frames = read_all(str(clip))
    t0 = 1_700_000_000_000_000_000
    path = tmp_path / "run.mcap"
    with RunWriter(path, _meta(), camera="video", chunk_size=4000) as w:
        for f in frames:
            w.write_frame(Frame(timestamp_ns=t0 + f.pts_ns, format="h264", data=f.data))
        w.write_fix(GnssFix(timestamp_ns=t0, lat_deg=1.0, lon_deg=2.0, alt_m=3.0))
        with pytest.raises(InputError, match="camera='image'"):
            w.write_frame(Frame(timestamp_ns=t0, format="jpeg", data=b"\xff\xd8"))
    reference = decode_all(frames, "h264")
    with open_run(path) as run:
        assert run.video and run.topics["/camera/video"] == "foxglove.CompressedVideo"
        assert [f.data for f in run.iter_frames()] == [f.data for f in frames]
        # Frames 23-26: the reader starts at keyframe 20, the decoder decodes 20-26 and nothing else.
        window = (t0 + 23 * 40_000_000, t0 + 26 * 40_000_000)
        got = list(run.iter_frames([window]))
    assert [g.timestamp_ns for g in got] == [t0 + k * 40_000_000 for k in range(20, 27)]
    assert isinstance(got[0], VideoFrame) and got[0].keyframe and not got[1].keyframe
    decoder = FrameDecoder()
    images = {}
    for k, g in zip(range(20, 27), got):
        decoder.push(g)
        if k in (23, 26):
            images[k] = decoder.gray()
    assert np.array_equal(images[23], reference[23]) and np.array_equal(images[26], reference[26])
    assert decoder.video_stats == (7, 0)
    # A frame asked for before any keyframe is None (counted corrupt by calibrate), never a wrong picture.
    late = FrameDecoder()
    late.push(got[1])
    assert late.gray() is None


def test_a_run_with_both_camera_topics_is_refused(tmp_path):
    path = tmp_path / "both.mcap"
    with RunWriter(path, _meta(), camera="video") as w:
        w.write_fix(GnssFix(timestamp_ns=1, lat_deg=1.0, lon_deg=2.0, alt_m=3.0))
        from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage

        w._write_proto("/camera/image", CompressedImage(data=b"x", format="jpeg"), 2)
    with pytest.raises(ContractError, match="one camera topic"):
        open_run(path)


def video_twin(src, dst, fmt="h264", gop=10, crf=16):
    """A /camera/video copy of a JPEG run: every frame encoded by PyAV's libx264/libx265 (no B-frames),
    everything else (metadata, fixes, attitude, events, MAVLink, attachments) copied as it is."""
    import av
    import cv2
    from dataclasses import replace

    from dronecal_field.video.nal import access_unit as to_annexb
    from dronecal_field.video.nal import parameter_sets as params_of

    with open_run(src) as run:
        md = replace(run.metadata, extra={**run.metadata.extra, "camera.clock": "file"})
        frames = list(run.iter_frames())
        ctx = av.CodecContext.create("libx264" if fmt == "h264" else "libx265", "w")
        ctx.width, ctx.height, ctx.pix_fmt = run.metadata.width, run.metadata.height, "yuv420p"
        ctx.time_base = Fraction(1, 1000)
        ctx.gop_size = gop
        ctx.max_b_frames = 0
        ctx.options = {"crf": str(crf)} if fmt == "h264" else {"crf": str(crf), "x265-params": f"bframes=0:keyint={gop}:log-level=error"}
        ctx.open()
        t0 = frames[0].timestamp_ns
        stamp_of = {}
        with RunWriter(dst, md, camera="video", background_flush=False) as w:
            def write(packets):
                for p in packets:
                    data = to_annexb(bytes(p), fmt, p.is_keyframe, params_of(ctx.extradata, fmt)[0])
                    w.write_frame(Frame(timestamp_ns=stamp_of[p.pts], format=fmt, data=data))

            for f in frames:
                img = cv2.imdecode(np.frombuffer(f.data, np.uint8), cv2.IMREAD_COLOR)
                vf = av.VideoFrame.from_ndarray(img, format="bgr24")
                vf.pts = (f.timestamp_ns - t0) // 1_000_000
                stamp_of[vf.pts] = f.timestamp_ns
                write(ctx.encode(vf))
            write(ctx.encode(None))
            for fix in run.iter_fixes():
                w.write_fix(fix)
            for att in run.iter_attitude():
                w.write_attitude(att)
            for ev in run.iter_events():
                w.write_event(ev)
            for name, t, fields in run.iter_mavlink():
                w.write_mavlink(name, t, fields)
            for name, _ in run._attachments:
                w.attach(name, run.attachment(name), "application/json")
    return len(frames)


def test_calibrate_reads_a_camera_video_twin_of_the_nominal_replay(tmp_path):
    """The nominal replay's frames as an H.264 stream (/camera/video) calibrate as its JPEGs do.

    Measured against the JPEG run (same bands as tests/test_replays.py): focal
    0.35 % (JPEG) vs 0.02 % (H.264), principal point 4.3 vs 4.8 px, position
    0.8 vs 1.1 cm, 150 vs 149 frames with the marker of 171. Before the fixes
    paired across the image track's gaps (the replay keeps 3-4 frames a hold):
    0.33 %, 4.4 px, 0.8 cm. Its 1 s holds (speed-up 3) decode every frame either way.
    """
    import json

    from conftest import ROOT, run_cli
    from test_replays import MANIFEST, _errors

    twin = tmp_path / "nominal-h264.mcap"
    assert video_twin(ROOT / "replays" / "nominal.mcap", twin) == 171
    out = tmp_path / "cal"
    proc = run_cli("calibrate", str(twin), "--out", str(out), "--trials", "50", timeout=180)
    assert proc.returncode == 0, proc.stderr
    focal_pct, pp_px, pos_m = _errors(out, ROOT / "replays" / MANIFEST["nominal"]["truth"])
    assert focal_pct < 1.5 and pp_px < 6.0 and pos_m < 0.05
    frames = json.loads((out / "report.json").read_text())["frames"]
    assert frames["formats"] == ["h264"] and frames["frames_corrupt_skipped"] == 0
    assert frames["frames_with_marker"] >= 140


def test_held_video_run_decodes_keyframe_bursts_and_stays_within_the_truth_bands(tmp_path):
    """Real 4.5 s holds at 10 fps as an H.264 stream with a 2 s GOP (a camera's usual): calibrate decodes the
    keyframes and short bursts, far fewer access units than the old choice (a frame every 0.4 s, each from
    its keyframe), and the camera stays within the bands of the JPEG run.

    Measured (this scene, seed 21; 12 windows): JPEG focal 0.25 %, principal point 1.1 px, position 1.4 cm
    (439 frames decoded); H.264 keyframe bursts 0.18 %, 2.3 px, 1.0 cm with 177 access units decoded (14.8
    per window); the old choice on the same stream 0.25 %, 1.1 px, 1.3 cm with 762 (63.5 per window).
    """
    from contract_writer import ORIGIN, MarkerLook, RunSpec, grid_waypoints, make_flight, pole_camera, write_run

    from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run
    from dronecal_field.pipeline.sampling import FrameSelector, SamplingOptions

    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints(east_m=(-3.0, 0.0, 3.0), north_m=(6.0, 9.0), up_m=(1.0, 4.0)), hold_s=4.5, move_s=2.0, seed=21)
    jpeg, video = tmp_path / "held.mcap", tmp_path / "held-h264.mcap"
    write_run(jpeg, camera, flight, MarkerLook(), RunSpec(fps=10.0, latency_s=0.25, site_origin=ORIGIN))
    video_twin(jpeg, video, gop=20)
    report = calibrate_run(video, CalibrateOptions(trials=0))
    est, truth = report.camera.intrinsics, camera.intrinsics
    assert abs(est.fx / truth.fx - 1) < 0.01 and np.hypot(est.cx - truth.cx, est.cy - truth.cy) < 5.0
    assert np.linalg.norm(report.camera.pose.position_world - camera.pose.position_world) < 0.04
    assert len(report.used_points) == len(flight.holds) == 12 and abs(report.offset.offset_s - 0.25) < 0.01
    units = report.frames.video_units_decoded
    assert units == report.frames.frames_decoded  # bursts decode in sequence: every access unit decoded is a frame used
    # The old choice on the same frames, counted without decoding: a wanted frame costs the units since the
    # last one decoded in its GOP. (Transitions are taken only after a hold showed the marker: all did.)
    with open_run(video) as run:
        old = FrameSelector(report.windows, SamplingOptions(video_bursts=False), video=True)
        for k in range(len(report.windows)):
            old.record(k, True)
        old_units, pending = 0, 0
        for frame in run.iter_frames(old.read_windows()):
            pending = 1 if frame.keyframe else pending + 1
            if old.wants(frame.timestamp_ns, keyframe=frame.keyframe)[0]:
                old_units, pending = old_units + pending, 0
    assert units * 3 < old_units, (units, old_units)


def test_a_4k_frame_is_searched_at_half_size_then_in_a_box_at_full_size():
    """A new window's first 4K frame: the half-size search boxes the marker; the full-size box finds the same
    corners as a whole-frame search (to 1e-3 px) for about a quarter of its cost (0.11 + 0.04 s vs 0.69 s CPU here)."""
    import cv2

    from dronecal_field.pipeline.detect import COARSE_SEARCH_PX, detect_aruco, make_aruco_detector
    from dronecal_field.pipeline.detect import coarse_roi as _coarse_roi

    image = np.random.default_rng(0).integers(60, 120, (2160, 3840), dtype=np.uint8)
    image[900:1220, 1900:2220] = 255
    image[1000:1120, 2000:2120] = cv2.aruco.generateImageMarker(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), 7, 120)
    assert image.size >= COARSE_SEARCH_PX
    detector = make_aruco_detector("DICT_4X4_50")
    roi = _coarse_roi(image, detector, 7)
    x0, y0, x1, y1 = roi
    assert x0 < 2000 and x1 > 2120 and y0 < 1000 and y1 > 1120 and (x1 - x0) * (y1 - y0) < image.size / 20
    boxed, whole = detect_aruco(image, detector, 7, 0, roi).detection, detect_aruco(image, detector, 7, 0).detection
    assert abs(boxed.u_px - whole.u_px) < 1e-3 and abs(boxed.v_px - whole.v_px) < 1e-3 and abs(whole.u_px - 2059.5) < 1.0
    # No marker at half size: None, and calibrate searches the whole frame.
    assert _coarse_roi(np.full((2160, 3840), 90, np.uint8), detector, 7) is None


def test_a_legs_only_video_run_pairs_its_leg_fixes_and_decodes_the_legs_whole(tmp_path):
    """Fly-through legs as an H.264 stream (15 fps, 2 s GOP): legs keep a frame every 0.25 s, so each leg fix has
    its four detections around it and the decoder runs through the legs' access units (counted). With 8-frame
    bursts on legs this run had no point at all.

    Measured (seed 4/8): 112 leg points, focal 0.09 %, principal point 7.2 px, position 4.1 cm, 502 of 573
    access units read decoded; its JPEG run: 112 points, 0.07 %, 5.8 px, 3.6 cm.
    """
    from contract_writer import ORIGIN, MarkerLook, RunSpec, leg_waypoints, make_leg_flight, pole_camera, write_run

    from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run
    from dronecal_field.sim.compare import compare_cameras

    camera = pole_camera(width=640, height=360, f_px=300, position_enu=(0, 0, 3.5), tilt_deg=25, distortion=(-0.28, 0.07, 0, 0, 0))
    flight = make_leg_flight(camera, leg_waypoints(camera, depths_m=(3.0, 5.0), heights_m=(0.8, 2.0, 3.5)), hold_s=0.0, speed_mps=2.0, seed=4)
    jpeg, video = tmp_path / "legs.mcap", tmp_path / "legs-h264.mcap"
    write_run(jpeg, camera, flight, MarkerLook(size_m=0.3), RunSpec(site_origin=ORIGIN, latency_s=0.25, declared_latency="unknown", gnss_hz=5.0, seed=8, fps=15.0))
    video_twin(jpeg, video, gop=30)
    report = calibrate_run(video, CalibrateOptions(trials=0))
    assert len(report.leg_points) >= 100 and len(report.used_points) == len(report.leg_points)
    cmp = compare_cameras(camera, report.camera, sampled_enu_m=np.array([p.marker_enu_m for p in report.used_points]))
    assert cmp.focal_error_pct < 0.5 and cmp.principal_point_error_px < 12.0 and cmp.position_error_cm < 8.0
    assert report.frames.video_units_decoded >= 0.8 * report.frames.frames_read
