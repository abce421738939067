"""RTSP pass-through against a real RTSP server on loopback (GStreamer's, tests/rtsp_server.py).

The server runs under Debian's Python (``make rtsp-deps`` installs it; CI's
``make test`` does). Streams are small (320x240, 25 fps, a few seconds), so
each test costs seconds. Nothing here asserts a rate or a wall-clock span:
counts are of frames the server itself logged, with wide margins.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from dronecal_field.video.nal import nal_type, split_annexb
from dronecal_field.video.packets import open_packet_source
from rtsp_server import stamp_errors_ns

SERVER = Path(__file__).with_name("rtsp_server.py")
SYSTEM_PYTHON = "/usr/bin/python3"


class RtspServer:
    def __init__(self, tmp_path, *args: str) -> None:
        self.log = tmp_path / "server.log"
        self.proc = subprocess.Popen(
            [SYSTEM_PYTHON, str(SERVER), "--log", str(self.log), *args],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        line = self.proc.stdout.readline()
        if not line.startswith("READY"):
            err = self.proc.stderr.read() if self.proc.poll() is not None else ""
            self.close()
            pytest.fail(f"the RTSP server did not start ({line!r} {err[-500:]}); run `make rtsp-deps` (GStreamer RTSP server, Debian packages)")
        self.url = line.split()[1]

    def sent(self) -> list[tuple[int, int, int, int, int]]:
        """(index, pts_ns, wall_ns, payload_bytes, keyframe) of every frame the server paid out."""
        return [tuple(int(v) for v in line.split()) for line in self.log.read_text().splitlines() if line.strip()]

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


@pytest.fixture
def server(tmp_path):
    servers = []

    def start(*args: str) -> RtspServer:
        s = RtspServer(tmp_path, *args)
        servers.append(s)
        return s

    yield start
    for s in servers:
        s.close()


def _read(source, n: int, timeout_s: float = 20.0) -> list:
    frames = []
    deadline = time.monotonic() + timeout_s
    while len(frames) < n and time.monotonic() < deadline:
        f = source.read(timeout_s=1.0)
        if f is not None:
            frames.append(f)
    return frames


@pytest.mark.parametrize("codec", ["h265"])  # H.264 through RTCP: test_fly_records_an_rtsp_camera_...
def test_rtsp_stream_is_recorded_as_access_units_stamped_through_rtcp(server, codec):
    srv = server("--codec", codec, "--gop", "25")
    source = open_packet_source(srv.url)
    try:
        frames = _read(source, 175)  # 7 s: the first RTCP sender report comes within ~5 s
    finally:
        source.close()
    assert source.format == codec and (source.width, source.height) == (320, 240)
    assert len(frames) == 175
    params = {"h264": {7, 8}, "h265": {32, 33, 34}}[codec]
    keyframes = [f for f in frames if f.keyframe]
    assert 6 <= len(keyframes) <= 8
    for f in keyframes:
        assert params <= {nal_type(n, codec) for n in split_annexb(f.data)}
    # One access unit per frame, in order, 40 ms apart in the stream's clock, none lost.
    steps = {b.pts_ns - a.pts_ns for a, b in zip(frames, frames[1:])}
    assert steps == {40_000_000}
    assert source.monitor.frames_lost == 0 and source.monitor.corrupt == 0 and not source.b_frames
    # The keyframe check hands its picture on (the recorder's marker probe takes it instead of decoding again):
    # the same luma as that keyframe decoded on its own.
    import numpy as np

    from dronecal_field.video.decode import decode_keyframe_gray

    checked, gray = source.last_checked
    assert source.keyframes_checked >= 1 and checked.keyframe and gray.shape == (240, 320)
    assert np.array_equal(gray, decode_keyframe_gray(checked.data, codec))
    # The camera's (here the server's) clock through RTCP: frames are stamped when the server
    # captured them, which its log says; loopback delivery adds well under a frame.
    assert source.clock == "rtcp"
    recorded = [(f.pts_ns, f.timestamp_ns, f.data) for f in frames[-75:]]
    capture_ms = sorted(e / 1e6 for e in stamp_errors_ns(srv.sent(), recorded, codec == "h265", at="capture"))
    send_ms = sorted(e / 1e6 for e in stamp_errors_ns(srv.sent(), recorded, codec == "h265", at="send"))
    assert len(capture_ms) >= 70 and len(send_ms) >= 70
    # Stamped at capture: within a millisecond of the server's capture instant, the same for every frame ...
    assert abs(capture_ms[len(capture_ms) // 2]) < 1.0 and capture_ms[-1] - capture_ms[0] < 1.0, capture_ms
    # ... and so before the server sent it (its overlay and encoder take a few ms to tens of ms).
    assert -80.0 < send_ms[len(send_ms) // 2] < 0.0, send_ms


def test_parameter_sets_only_in_the_sdp_are_put_in_front_of_every_keyframe(server):
    srv = server("--params-out-of-band", "--gop", "10")
    source = open_packet_source(srv.url)
    try:
        frames = _read(source, 40)
    finally:
        source.close()
    keyframes = [f for f in frames if f.keyframe]
    assert len(keyframes) >= 3
    for f in keyframes:
        assert [nal_type(n, "h264") for n in split_annexb(f.data)][:3] in ([9, 7, 8], [7, 8, 5], [7, 8, 6])


def test_a_server_that_stalls_is_reported_as_lag_not_hidden(server):
    srv = server("--pause-at", "1.5", "--pause-for", "1.5")
    source = open_packet_source(srv.url)
    source.lock_clock()  # one clock throughout: arrival through the stream's pacing, or RTCP if a report came first
    frames, arrivals = [], []
    try:
        while len(frames) < 125:
            f = source.read(timeout_s=5.0)
            assert f is not None
            frames.append(f)
            arrivals.append(time.time_ns())
    finally:
        source.close()
    incidents = source.incidents()
    lags = [i for i in incidents if i.kind == "video_lag"]
    assert source.monitor.lag_events >= 1 and lags, incidents
    assert 1.0 < max(i.value for i in lags) < 2.5  # the 1.5 s stall, as the lag behind the stream's clock
    # The backlog sent in a burst keeps the frames' own times (either clock), not their late arrival.
    # (The opening burst, FFmpeg's first second read while opening, is stamped by the pacing too, before the
    # lock: read() leaves it out, the recording starts at the first keyframe after.)
    assert source.burst_frames >= 10 and frames[0].keyframe
    late = [f for f, t in zip(frames, arrivals) if t - f.timestamp_ns > 500_000_000]
    assert len(late) >= 10
    steps = {b.timestamp_ns - a.timestamp_ns for a, b in zip(late, late[1:])}
    assert steps == {40_000_000}


@pytest.mark.parametrize("transport", ["tcp", "udp"])
def test_frames_the_camera_loses_are_counted(server, transport):
    srv = server("--drop-every", "10", "--gop", "50")
    source = open_packet_source(srv.url, rtsp_transport=transport)
    try:
        frames = _read(source, 60)
    finally:
        source.close()
    span = (frames[-1].pts_ns - frames[0].pts_ns) // 40_000_000 + 1
    assert span - len(frames) == source.monitor.frames_lost
    assert 4 <= source.monitor.frames_lost <= 8  # every 10th frame of ~65
    assert source.monitor.loss_events == source.monitor.frames_lost


def test_a_consumer_slower_than_the_stream_drops_frames_counted(server):
    srv = server()
    source = open_packet_source(srv.url, queue_size=4)
    try:
        assert source.read(timeout_s=10.0) is not None
        time.sleep(2.0)  # the consumer stalls; the stream goes on
        frames = _read(source, 10)
    finally:
        source.close()
    assert len(frames) == 10
    assert source.frames_dropped >= 10  # ~50 frames arrived for a queue of 4


def test_fly_records_an_rtsp_camera_as_camera_video_stamped_through_rtcp(server, tmp_path, capsys):
    """The unmodified ``fly --start`` against the simulated vehicle and an RTSP camera."""
    import re

    from dronecal_field.cli import main
    from dronecal_field.runfile.reader import open_run
    from test_mavlink_support import start_sim, write_plan

    srv = server("--gop", "25")
    sim = start_sim(speedup=10.0, boot_s=1.0)
    plan = write_plan(tmp_path / "mission.plan", [(-1.0, 4.0, 1.5), (0.0, 4.0, 1.5)], hold_s=1.0)
    out = tmp_path / "run.mcap"
    try:
        rc = main(["fly", "--connect", sim.addresses()[0], "--mission", str(plan), "--video", srv.url, "--out", str(out),
                   "--marker-size", "0.3", "--start", "--no-live"])
    finally:
        sim.stop()
    printed = capsys.readouterr().out
    assert rc == 0, printed[-2000:]
    written = int(re.search(r"(\d+) frames \((\d+) dropped\)", printed).group(1))
    assert "VIDEO FELL BEHIND" not in printed and "VIDEO LOST" not in printed
    with open_run(out) as run:
        md = run.metadata
        frames = list(run.iter_frames())
        events = [e.type for e in run.iter_events()]
    assert run.video and (md.width, md.height) == (320, 240)
    assert md.extra["camera.clock"] == "rtcp" and md.camera_latency_s == 0.0
    assert len(frames) == written > 25 and {f.format for f in frames} == {"h264"}
    steps = {b.timestamp_ns - a.timestamp_ns for a, b in zip(frames, frames[1:])}
    assert steps == {40_000_000}  # the camera's own 25 fps clock: no arrival jitter in the stamps
    assert not {"video_lag", "video_lost", "video_corrupt"} & set(events)


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for(predicate, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def test_a_server_restart_mid_stream_is_one_gap_event_and_the_stamps_stay_on_one_rising_clock(server, tmp_path):
    """The camera's encoder restarts (its RTSP server goes away and comes back on the same port) while the recorder runs."""
    import json

    from dronecal_field.mavlink.link import open_link
    from dronecal_field.mavlink.missionfile import parse_qgc_plan
    from dronecal_field.recording.recorder import Recorder
    from dronecal_field.runfile.reader import open_run
    from dronecal_field.runfile.records import FORMAT_VERSION, MarkerSpec, RunMetadata
    from dronecal_field.runfile.writer import RunWriter
    from test_mavlink_support import plan_document, start_sim, wait_ready

    port = _free_port()
    # RTCP timing decides what is tested. A session's first sender report comes a random 0.25-0.75 of the RTCP interval
    # after PLAY (GStreamer's default interval 5 s: 1.25-3.75 s), and opening a stream took 1.3-1.6 s at load 15: on a
    # loaded machine the new session's first report could come before its first frame was stamped, so nothing was
    # bridged and no bridge error ever came (the 12 s, then 40 s, wait ran out). The first server reports every
    # second (the recorder locks the RTCP clock at once); the restarted one every 24 s, its first report 6-18 s in
    # (measured 9-15 s after open at load 15 with 30 s): its first frames are always stamped by the bridge first.
    srv = server("--port", str(port), "--gop", "25", "--rtcp-interval", "1")
    mission = parse_qgc_plan(json.dumps(plan_document([(0.0, 4.0, 1.5)], hold_s=3.0)))
    meta = RunMetadata(format_version=FORMAT_VERSION, width=320, height=240,
                       marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3))
    out = tmp_path / "restart.mcap"
    sim = start_sim(speedup=5.0, boot_s=0.5)
    link = open_link(sim.addresses()[0])
    source = open_packet_source(srv.url)
    try:
        link.wait_heartbeat(5)
        wait_ready(link)
        assert _wait_for(lambda: source.clock == "rtcp", 10.0), "no RTCP sender report from the server"
        start_ns = time.time_ns()
        assert source.lock_clock(start_ns) == "rtcp"
        recorder = Recorder(link, source, RunWriter(out, meta, camera="video"), None, mission, start_ns=start_ns).start()
        assert _wait_for(lambda: recorder.frames_written >= 40, 20.0)
        srv.close()  # the encoder goes away ...
        server("--port", str(port), "--gop", "25", "--rtcp-interval", "24")  # ... and comes back: a new RTSP session, its pts and RTCP start again
        before = recorder.frames_written
        assert _wait_for(lambda: recorder.frames_written >= before + 60, 30.0), "the recorder did not reconnect"
        assert source.frames_bridged > 0  # the premise: the new session's frames came before its first report
        assert _wait_for(lambda: source.bridge_errors_ns, 90.0), "no RTCP sender report in the new session"
        time.sleep(0.5)
        report = recorder.stop()
    finally:
        source.close()
        link.close()
        sim.stop()
    with open_run(out) as run:
        frames = list(run.iter_frames())
        gaps = [e for e in run.iter_events() if e.type == "video_gap"]
    stamps = [f.timestamp_ns for f in frames]
    steps = [b - a for a, b in zip(stamps, stamps[1:])]
    assert report.video_gaps == len(gaps) == 1, gaps
    assert source.sessions == 2 and source.reconnects == 1
    assert min(steps) > 0  # never backwards, never equal
    # The gap event spans the one long step, the restart; every other step is the stream's 40 ms.
    jump = max(range(len(steps)), key=steps.__getitem__)
    gap = gaps[0]
    assert stamps[jump] < gap.timestamp_ns < stamps[jump + 1] <= gap.timestamp_ns + gap.duration_ns
    others = sorted(steps[:jump] + steps[jump + 1:])
    assert 80_000_000 < steps[jump] < 15_000_000_000  # the restart: more than two frames (a quick server was back in 0.17 s)
    # The new session's first frames are stamped on the RTCP clock by the delay measured before its first report
    # (bridged), then by its own reports: the hand-over moves a stamp by a few ms at most.
    assert source.frames_bridged > 0 and len(source.bridge_errors_ns) == 1
    error_ns = source.bridge_errors_ns[0]
    # The session's median arrival - pts against the median RTCP delay before it: 0.08-0.14 ms from the capture time
    # its first report gave, measured here (the minimum of each, used at first, was 38-40 ms late: few frames of a
    # new session do not show its smallest delay). 10 ms leaves room for a loaded machine's arrival jitter.
    assert abs(error_ns) < 10_000_000
    # While bridged, the session's median moves a little with each frame (steps within a few ms of 40, measured
    # within 0.17 ms); the hand-over step is short by the error. Everywhere else: the camera's own 40 ms.
    off = [s for s in others if s != 40_000_000]
    assert len(off) <= source.frames_bridged + 1, off
    assert all(abs(s - 40_000_000) <= abs(error_ns) + 5_000_000 for s in off), (off, error_ns)
    # Each session's recording starts at a keyframe: the first frame, and the first after the gap.
    from dronecal_field.video.nal import is_keyframe

    assert is_keyframe(frames[0].data, "h264") and is_keyframe(frames[jump + 1].data, "h264")


def _clip_with_cut_keyframes(path, n: int = 150, gop: int = 25, keep: float = 0.5, size=(320, 240), fps: int = 25) -> None:
    """A real H.264 Matroska clip whose keyframe slices are cut to ``keep`` of their bytes (their NAL lengths fixed),
    as a server with a send buffer smaller than a keyframe delivers them."""
    from fractions import Fraction

    import av
    import numpy as np

    from dronecal_field.video.nal import nal_type as type_of
    from dronecal_field.video.nal import split_length_prefixed

    rng = np.random.default_rng(5)
    background = rng.integers(40, 200, (size[1], size[0], 3), dtype=np.uint8)  # noise: keyframes of real size
    with av.open(str(path), "w") as out:
        stream = out.add_stream("libx264", rate=fps)
        stream.width, stream.height, stream.pix_fmt = size[0], size[1], "yuv420p"
        stream.options = {"bf": "0", "g": str(gop), "keyint_min": str(gop), "crf": "20"}

        def mux(packets):
            for p in packets:
                if p.is_keyframe and p.size:
                    data = bytes(p)
                    annexb = data.startswith((b"\x00\x00\x01", b"\x00\x00\x00\x01"))
                    units = split_annexb(data) if annexb else split_length_prefixed(data, 4)
                    nals = [n[: max(8, int(len(n) * keep))] if type_of(n, "h264") == 5 else n for n in units]
                    cut = av.Packet(b"".join((b"\x00\x00\x00\x01" if annexb else len(x).to_bytes(4, "big")) + x for x in nals))
                    cut.pts, cut.dts, cut.time_base, cut.is_keyframe = p.pts, p.dts, p.time_base, True
                    cut.stream = stream
                    p = cut
                out.mux(p)

        for i in range(n):
            img = background.copy()
            img[40:120, 10 + i % 200 : 90 + i % 200] = 250
            frame = av.VideoFrame.from_ndarray(img, format="rgb24")
            frame.pts, frame.time_base = i, Fraction(1, fps)
            mux(stream.encode(frame))
        mux(stream.encode(None))


def test_keyframes_cut_short_are_counted_and_the_preflight_probe_warns(server, tmp_path):
    from dronecal_field.video.probe import probe_packet_stream

    clip = tmp_path / "cut.mkv"
    _clip_with_cut_keyframes(clip)
    srv = server("--file", str(clip), "--codec", "h264")
    source = open_packet_source(srv.url, check_every_s=0.0)  # every keyframe (fly samples one every 5 s)
    try:
        first = source.read(timeout_s=10.0)
        assert first is not None and first.keyframe
        probe = probe_packet_stream(source, first, probe_s=1.0, rtcp_wait_s=0.0)
        frames = _read(source, 60)
    finally:
        source.close()
    # The demuxer passes the cut keyframes as good packets; the decoder does not.
    assert source.monitor.corrupt == 0 and source.units_undecodable >= 3
    assert probe.keyframes_undecodable >= 1 and probe.warning is not None and "do not decode" in probe.warning, probe
    assert source.keyframes_checked >= 3
    assert source.units_undecodable == source.keyframes_checked  # every keyframe of this stream is cut, every one is found
    corrupt = [i for i in source.incidents() if i.kind == "video_corrupt"]
    assert len(corrupt) == source.units_undecodable
    assert len(frames) == 60


@pytest.mark.parametrize("codec", ["h264", "h265"])
def test_the_preflight_rate_is_the_streams_not_the_opening_burst(server, codec):
    from dronecal_field.video.probe import probe_packet_stream

    srv = server("--codec", codec, "--fps", "25")
    source = open_packet_source(srv.url)
    try:
        first = source.read(timeout_s=10.0)
        t0 = time.monotonic()
        probe = probe_packet_stream(source, first, probe_s=1.0, rtcp_wait_s=0.0)
        elapsed = time.monotonic() - t0
    finally:
        source.close()
    assert probe.burst_frames >= 10  # FFmpeg read ~1 s while opening, handed over at once
    arrival_rate = (probe.frames - 1) / elapsed  # what counting arrivals says: the burst inflates it
    assert arrival_rate > 30.0, arrival_rate
    assert abs(probe.fps - 25.0) <= 0.05 * 25.0, probe
    assert probe.keyframes_undecodable == 0 and probe.warning is None and probe.keyframes_decoded >= 1


def test_a_recording_that_starts_mid_gop_starts_at_the_next_keyframe(server):
    srv = server("--gop", "50")  # a keyframe every 2 s
    source = open_packet_source(srv.url)
    try:
        first = source.read(timeout_s=10.0)
        assert first is not None and first.keyframe  # a session starts at a keyframe
        frames = _read(source, 30)
        assert not frames[-1].keyframe  # we are inside a GOP
        start_ns = time.time_ns()
        source.lock_clock(start_ns)  # the recording starts here
        recorded = _read(source, 10)
    finally:
        source.close()
    assert recorded[0].keyframe and recorded[0].timestamp_ns >= start_ns
    # What came between the start and that keyframe was dropped and counted: up to one GOP (50 frames).
    assert 1 <= source.frames_before_keyframe <= 50
    skipped = (recorded[0].pts_ns - frames[-1].pts_ns) // 40_000_000 - 1
    assert skipped >= source.frames_before_keyframe  # (and those stamped before the start were not recorded anyway)
    assert {b.pts_ns - a.pts_ns for a, b in zip(recorded, recorded[1:])} == {40_000_000}
