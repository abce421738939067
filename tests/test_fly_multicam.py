"""Issue 24, fly's side: ``fly --video NAME=URL`` (repeated) records several cameras into one run.

One simulated vehicle, two simulated pole cameras, each ``sim camera`` its own
process (as a pole camera is its own device) on its own MAVLink link and its
own stream: ``north`` serves MJPEG over HTTP, ``south`` H.264 over RTSP
(GStreamer's server, RTCP sender reports). The run is read back with the raw
``mcap`` reader against the contract's "Several cameras in one run".
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from dronecal_field.camerafile import write_camera
from dronecal_field.cli import main
from dronecal_field.core.camera import Distortion
from dronecal_field.sim.scene import make_truth_camera
from dronecal_field.sim.vehicle import SimVehicle, VehicleConfig
from test_mavlink_support import FAST_PARAMS, HOME, write_plan

REPO = Path(__file__).resolve().parents[1]

OFFSET = (0.10, 0.0, 0.05)
WAYPOINTS = [(-1.5, 5.0, 1.5), (1.5, 8.0, 3.0), (0.0, 6.5, 2.0)]
FPS = 15


def _raw(path):
    """(dronecal.run metadata, {topic: (schema name, [(log_time, decoded message)])}) through mcap's own reader."""
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.CompressedVideo_pb2 import CompressedVideo
    from foxglove_schemas_protobuf.Event_pb2 import Event

    classes = {"foxglove.CompressedImage": CompressedImage, "foxglove.CompressedVideo": CompressedVideo, "foxglove.Event": Event}
    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = [m.metadata for m in reader.iter_metadata() if m.name == "dronecal.run"]
        topics: dict[str, tuple[str, list]] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            entry = topics.setdefault(channel.topic, (schema.name if schema else "", []))
            cls = classes.get(entry[0])
            if cls is not None:
                entry[1].append((message.log_time, cls.FromString(message.data)))
    assert len(meta) == 1
    return meta[0], topics


def _ns(ts) -> int:
    return ts.seconds * 1_000_000_000 + ts.nanos


def _stamp(msg) -> int:
    return _ns(msg.timestamp)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class CameraProcess:
    """``dronecal-field sim camera`` in a process of its own, listening for the vehicle on its own UDP port."""

    def __init__(self, tmp_path: Path, name: str, truth, serve: str, seed: int, *extra: str) -> None:
        truth_path = tmp_path / f"truth-{name}.yaml"
        write_camera(truth_path, truth, comment=f"test_fly_multicam: {name}")
        self.link_port = _free_udp_port()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "dronecal_field", "sim", "camera", "--connect", f"udpin:127.0.0.1:{self.link_port}",
             "--camera", str(truth_path), "--serve", serve, "--fps", str(FPS), "--noise-dn", "1", "--seed", str(seed),
             "--marker-size", "0.4", "--marker-offset", ",".join(map(str, OFFSET)), *extra],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, start_new_session=True,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            # a suite started in the background (CI under nohup, `make test &`) hands its children SIGINT ignored:
            # stop() is Ctrl-C, so the camera must hear it to say how many frames it made
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        self.name = name
        self.url = ""
        self.made: int | None = None

    def wait_ready(self) -> str:
        """Its URL, once it serves (after its ray map and server are up)."""
        line = self.proc.stdout.readline()  # "sim camera: serving URL (...)"
        match = re.search(r"serving (\S+)", line)
        if match is None:
            self.stop()
            pytest.fail(f"sim camera {self.name} did not start: {line!r} {self.proc.stderr.read()[-800:]}")
        self.url = match.group(1)
        return self.url

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)  # as Ctrl-C: it says how many frames it made
        try:
            _out, err = self.proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            _out, err = self.proc.communicate()
        made = re.search(r"sim camera: (\d+) frames", err or "")
        self.made = int(made.group(1)) if made else None


def test_two_cameras_mjpeg_and_rtsp_record_into_one_run_each_on_its_own_topic_and_clock(tmp_path, capsys):
    north_truth = make_truth_camera(HOME, 4.0, 0.0, 20.0, 560.0, 640, 480, distortion=Distortion(k1=-0.1))
    south_truth = make_truth_camera(HOME, 4.0, 0.0, 20.0, 420.0, 480, 360, distortion=Distortion(k1=-0.05))
    north = CameraProcess(tmp_path, "north", north_truth, "http://127.0.0.1:0/stream.mjpg", 3)
    south = CameraProcess(tmp_path, "south", south_truth, "rtsp://127.0.0.1:0/cam", 4, "--codec", "h264")
    try:
        north.wait_ready()  # both start at once
        south.wait_ready()
    except BaseException:
        north.stop()
        south.stop()
        raise
    assert south.url.startswith("rtsp://127.0.0.1:") and north.url.startswith("http://127.0.0.1:")
    config = VehicleConfig(home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2], speedup=4.0, boot_s=1.0, params=FAST_PARAMS)
    outs = [f"udp:127.0.0.1:{c.link_port}" for c in (north, south)]  # each camera on its own link
    sim = SimVehicle(config, listen=["udp:127.0.0.1:0"], out=outs).start()
    plan = write_plan(tmp_path / "mission.plan", WAYPOINTS, hold_s=4.0, takeoff_alt_m=2.0, speed_mps=3.0)
    out = tmp_path / "run.mcap"
    try:
        rc = main(["fly", "--connect", sim.addresses()[0], "--mission", str(plan), "--video", f"north={north.url}",
                   "--video", f"south={south.url}", "--out", str(out), "--marker-size", "0.4",
                   "--marker-offset", ",".join(map(str, OFFSET)), "--start", "--timeout-s", "240"])
    finally:
        sim.stop()
        north.stop()
        south.stop()
    printed = capsys.readouterr().out
    assert rc == 0, printed[-3000:]
    # the checklist and the status: a line per camera
    assert re.search(r"\[ OK \] video north +640x480", printed) and re.search(r"\[ OK \] video south +480x360", printed), printed[:3000]
    assert re.search(r"2 cameras \d+ dropped", printed)
    assert re.search(r"  cam north: +[0-9.]+ fps \d+ frames", printed) and re.search(r"  cam south: +[0-9.]+ fps \d+ frames", printed)

    meta, topics = _raw(out)
    # metadata: the cameras in order, each one's size, latency and clock; no single-camera keys
    assert meta["cameras"] == "north,south"
    assert (meta["camera.north.width"], meta["camera.north.height"]) == ("640", "480")
    assert (meta["camera.south.width"], meta["camera.south.height"]) == ("480", "360")
    assert meta["camera.north.clock"] == "arrival" and meta["camera.north.latency_s"] == "unknown"
    assert meta["camera.south.clock"] == "rtcp" and float(meta["camera.south.latency_s"]) == 0.0
    assert "camera.width" not in meta and "camera.height" not in meta and "camera.latency_s" not in meta
    # topics: one per camera with its standard schema, no /camera/... topic
    assert not [t for t in topics if t.startswith("/camera/")]
    assert topics["/cameras/north/image"][0] == "foxglove.CompressedImage"
    assert topics["/cameras/south/video"][0] == "foxglove.CompressedVideo"
    jpegs = topics["/cameras/north/image"][1]
    units = topics["/cameras/south/video"][1]
    assert len(jpegs) > 40 and len(units) > 40, (len(jpegs), len(units))
    assert {m.format for _t, m in jpegs} == {"jpeg"} and {m.frame_id for _t, m in jpegs} == {"north"}
    assert {m.format for _t, m in units} == {"h264"} and {m.frame_id for _t, m in units} == {"south"}
    # stamps: each frame's timestamp is its log time, rising on each camera's own clock
    for frames in (jpegs, units):
        stamps = np.array([_stamp(m) for _t, m in frames], np.int64)
        assert np.array_equal(stamps, np.array([t for t, _m in frames], np.int64))
        assert np.all(np.diff(stamps) > 0)
    # events: the holds are shared; every video event names its camera
    events = topics["/events"][1]
    kinds = [dict((kv.key, kv.value) for kv in m.metadata) for _t, m in events]
    assert [int(k["seq"]) for k in kinds if k["type"] == "hover"] == [4, 5, 6]
    assert not [k for k in kinds if "camera" in k and k["type"] in ("hover", "leg")]  # shared: no camera named
    video = [(k, m) for k, (_t, m) in zip(kinds, events) if k["type"].startswith("video_")]
    assert all(k.get("camera") in ("north", "south") for k, _m in video), video  # a stream's incident always says whose
    # A camera process starved on a loaded machine goes quiet for seconds: a gap of that camera's, closed when frames return.
    gaps = {name: [(_ns(m.start_time), _ns(m.end_time)) for k, m in video if k["type"] == "video_gap" and k["camera"] == name]
            for name in ("north", "south")}
    # The RTSP camera is stamped at capture through RTCP: every step a whole number of its 1/15 s periods, up to its
    # first gap (a reconnect starts a new RTP session); a frame it did not make in time is a pts gap counted as lost.
    until = min([a for a, _b in gaps["south"]], default=None)
    south_ns = [_stamp(m) for _t, m in units if until is None or _stamp(m) < until]
    steps = np.diff(south_ns) / (1e9 / FPS)
    assert len(steps) > 20
    assert np.all(np.abs(steps - np.round(steps)) < 0.002) and np.all(np.round(steps) >= 1)
    lost = sum(int(k["frames"]) for k, m in video
               if k["type"] == "video_lost" and k["camera"] == "south" and south_ns[0] < _ns(m.start_time) < south_ns[-1])
    assert lost == int(np.sum(np.round(steps) - 1))
    assert not [k for k, _m in video if k["type"] == "video_lost" and k["camera"] == "north"]  # MJPEG has no pts to lose
    # both on the run clock: every frame after the recording's start and before its end (the last message)
    start_ns = int(meta["recording.start_ns"])
    with open(out, "rb") as f:
        end_ns = make_reader(f).get_summary().statistics.message_end_time
    for frames in (jpegs, units):
        assert start_ns <= _stamp(frames[0][1]) and _stamp(frames[-1][1]) <= end_ns
    # nothing invented: at most the frames each simulator made
    assert north.made is not None and south.made is not None
    assert len(jpegs) <= north.made and len(units) <= south.made

    # the live check ran per camera: each camera's verdict; a camera without a gap saw the marker at every hold
    live = json.loads((tmp_path / "run.live.json").read_text())
    assert sorted(live["cameras"]) == ["north", "south"]
    for name in ("north", "south"):
        checked = sorted({w["seq"] for w in live["cameras"][name]["waypoints"]})
        good = sorted({w["seq"] for w in live["cameras"][name]["waypoints"] if w["good"]})
        assert checked == [4, 5, 6], (name, live["cameras"][name]["waypoints"])
        assert re.search(rf"verdict camera {name}: marker seen at {len(good)} of 3 waypoints checked", printed)
        if not gaps[name]:
            assert good == [4, 5, 6], (name, live["cameras"][name]["waypoints"])
            assert re.search(rf"  cam {name}: .*\| marker yes", printed)  # the status line's probe, camera by camera
    assert not (tmp_path / "refly.plan").exists()


@pytest.mark.parametrize("videos, says", [
    (["North=http://a/s.mjpg"], "camera name 'North' is not [a-z0-9][a-z0-9_-]{0,31}"),
    (["a=http://a/s.mjpg", "a=http://b/s.mjpg"], "--video a=... is given twice"),
    (["http://a/s.mjpg", "b=http://b/s.mjpg"], "has no name but there are 2 cameras"),
    (["a=http://a/s.mjpg", "b=http://a/s.mjpg"], "is given twice: each camera needs its own stream"),
    (["x" * 33 + "=http://a/s.mjpg"], "is not [a-z0-9][a-z0-9_-]{0,31}"),
    (["a="], "gives no stream"),
])
def test_bad_camera_names_are_one_line_errors_before_anything_opens(tmp_path, capsys, videos, says):
    plan = write_plan(tmp_path / "mission.plan", WAYPOINTS, hold_s=1.0)
    args = ["fly", "--connect", "udp:127.0.0.1:9", "--mission", str(plan), "--out", str(tmp_path / "run.mcap"), "--marker-size", "0.3"]
    for v in videos:
        args += ["--video", v]
    rc = main(args)
    err = capsys.readouterr().err.strip()
    assert rc == 2 and says in err and len(err.splitlines()) == 1, err
    assert not (tmp_path / "run.mcap").exists()


def test_a_url_with_a_query_is_a_bare_single_camera():
    from dronecal_field.recording.cameras import parse_video_flags

    specs = parse_video_flags(["http://cam/stream.mjpg?res=1080&fps=25"])
    assert [(s.name, s.url) for s in specs] == [(None, "http://cam/stream.mjpg?res=1080&fps=25")]
    specs = parse_video_flags(["n-1=rtsp://cam/a?x=1", "n_2=/dev/video0"])
    assert [(s.name, s.url) for s in specs] == [("n-1", "rtsp://cam/a?x=1"), ("n_2", "/dev/video0")]


def test_a_site_plan_gives_each_camera_the_waypoints_it_sees(tmp_path):
    """plan --site's plan.json: each camera's live plan holds its own guess and origin and the grid points it sees."""
    from dronecal_field.live.progress import expected_seqs
    from dronecal_field.live.site import camera_live_plan
    from dronecal_field.mavlink.missionfile import CMD_NAV_WAYPOINT, read_mission

    mission = read_mission(write_plan(tmp_path / "mission.plan", WAYPOINTS, hold_s=1.0))
    nav = [it for it in mission.items if it.command == CMD_NAV_WAYPOINT and it.seq >= 4]
    grid = [{"mission_seq": it.seq, "lat_deg": it.x * 1e-7, "lon_deg": it.y * 1e-7, "camera": cam, "seen_by": seen}
            for it, cam, seen in zip(nav, ("a", "b", "a"), ({"a": {}}, {"b": {}, "a": {}}, {"a": {}}))]
    plan = {"kind": "site", "grid": grid, "marker": {"size_m": 0.4},
            "cameras": [{"name": "a", "enu_origin": {"lat_deg": 1.0, "lon_deg": 2.0, "h_m": 3.0}, "camera_guess": {"width": 640}},
                        {"name": "b", "enu_origin": {"lat_deg": 1.5, "lon_deg": 2.5, "h_m": 3.0}, "camera_guess": {"width": 480}}]}
    a, b = camera_live_plan(plan, "a"), camera_live_plan(plan, "b")
    assert camera_live_plan(plan, "c") is None and camera_live_plan(None, "a") is None
    assert (a["camera_guess"]["width"], b["camera_guess"]["width"]) == (640, 480) and b["enu_origin"]["lat_deg"] == 1.5
    assert expected_seqs(mission, a) == [4, 5, 6] and expected_seqs(mission, b) == [5]
    assert a["marker"] == {"size_m": 0.4}


def test_one_camera_of_two_lost_is_named_loudly_and_its_return_said():
    """The video-loss alarm per camera (no --on-video-loss hold: nothing is commanded, so no link is needed)."""
    from dronecal_field.recording.alarm import VideoLossAlarm
    from dronecal_field.recording.feed import CameraStatus
    from dronecal_field.recording.status import RecorderStatus, format_camera_status, format_status

    def status(north_ok: bool, south_ok: bool) -> RecorderStatus:
        cams = tuple(CameraStatus(name=n, fps=15.0 if ok else 0.0, frames=300, dropped=0, gaps=0 if ok else 1, video_ok=ok, marker_seen=True)
                     for n, ok in (("north", north_ok), ("south", south_ok)))
        return RecorderStatus(waypoint=3, waypoints=8, mode="AUTO", armed=True, fix="rtk_fixed", satellites=18, fps=sum(c.fps for c in cams),
                              frames=600, dropped=0, marker_seen=True, link_ok=True, video_ok=north_ok and south_ok, elapsed_s=62,
                              remaining_s=190, cameras=cams)

    alarm = VideoLossAlarm(link=None)
    assert alarm.update(status(True, True), 100.0) == [] and alarm.lost_since is None
    [(text, loud)] = alarm.update(status(True, False), 101.0)
    assert loud and text.startswith("VIDEO LOST FROM CAMERA south at waypoint 3/8: no frame from it (1 of 2 cameras still recording)")
    assert "--on-video-loss hold would hold" in text and alarm.lost_since == 101.0
    assert alarm.update(status(True, False), 110.0) == []  # said every 15 s, not every tick
    assert alarm.update(status(True, False), 116.5) == [("VIDEO STILL LOST FROM CAMERA south (16 s)", True)]
    assert alarm.update(status(True, True), 121.0) == [("video from camera south back after 20.0 s (the gap is marked in the run)", False)]
    assert alarm.lost_since is None and alarm.losses == 1 and not alarm.held
    # the single camera's words are as they were
    single = VideoLossAlarm(link=None)
    [(text, loud)] = single.update(RecorderStatus(waypoint=5, waypoints=24, mode="AUTO", armed=True, fix="rtk_fixed", satellites=18, fps=0.0,
                                                  frames=10, dropped=0, marker_seen=None, link_ok=True, video_ok=False, elapsed_s=1,
                                                  remaining_s=None), 5.0)
    assert loud and text.startswith("VIDEO LOST at waypoint 5/24: no frame from the camera; waypoints flown now have no images")
    # the status: the main line counts the cameras and names the lost one; each camera has its own line
    line = format_status(status(True, False))
    assert line == "wp 3/8 AUTO armed | rtk_fixed 18 sats | 2 cameras 0 dropped | 01:02 / ~03:10 left | NO VIDEO from 1 of 2: south"
    assert format_camera_status(status(True, False).cameras[1], live="live 2 ok 0 missed") == \
        "  cam south:  0.0 fps 300 frames 0 dropped 1 gaps | marker yes | NO VIDEO | live 2 ok 0 missed"
