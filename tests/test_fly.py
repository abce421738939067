"""``dronecal-field fly`` end to end: the simulated vehicle on UDP, MJPEG over HTTP, real files."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dronecal_field.cli import main
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink.link import mavutil_module, open_link
from dronecal_field.runfile.reader import open_run
from test_mavlink_support import MjpegServer, MessageLog, UdpRelay, start_sim, wait_until, write_plan

REPO = Path(__file__).resolve().parents[1]
SMALL = [(-1.0, 4.0, 1.5), (0.0, 4.0, 1.5), (1.0, 4.0, 2.0), (0.0, 5.0, 2.0)]  # ENU metres from home


@pytest.fixture()
def camera():
    server = MjpegServer(fps=15)
    yield server
    server.close()


def _tlog(path: Path) -> list:
    log = mavutil_module().mavlink_connection(str(path))
    out = []
    while (msg := log.recv_match()) is not None:
        out.append(msg)
    return out


def _fly_args(sim_url, plan, camera, out, *extra) -> list[str]:
    return ["fly", "--connect", sim_url, "--mission", str(plan), "--video", camera.url, "--out", str(out), "--marker-size", "0.3", *extra]


def test_fly_start_flies_and_records_a_whole_mission(tmp_path, camera, capsys):
    sim = start_sim(speedup=20.0, boot_s=2.0)
    plan = write_plan(tmp_path / "mission.plan", SMALL, hold_s=1.0)
    _write_marker(tmp_path)  # the flags below win over its marker; the file itself travels with the run
    out = tmp_path / "run.mcap"
    try:
        rc = main(_fly_args(sim.addresses()[0], plan, camera, out, "--start"))
    finally:
        sim.stop()
    printed = capsys.readouterr().out
    assert rc == 0
    assert "[ OK ] gnss" in printed and "started: GUIDED, armed, MISSION_START sent" in printed
    assert "wp 4/4" in printed

    with open_run(out) as run:
        meta = run.metadata_record("dronecal.run")
        assert (meta["camera.width"], meta["camera.height"], meta["marker.size_m"], meta["gnss.altitude_datum"]) == ("640", "480", "0.3", "ellipsoid")
        assert meta["camera.latency_s"] == "unknown"
        events = list(run.iter_events())
        hovers = [e for e in events if e.type == "hover"]
        gps = [f for _n, _t, f in run.iter_mavlink({"GPS_RAW_INT"})]
        attitude = [(t, f) for _n, t, f in run.iter_mavlink({"ATTITUDE"})]
        fixes = list(run.iter_fixes())
        frames = list(run.iter_frames())
        assert run.attachment("mission.plan") == plan.read_bytes()
        assert run.attachment("plan.json") == (tmp_path / "plan.json").read_bytes()
    assert [int(e.metadata["seq"]) for e in hovers] == [4, 5, 6, 7]
    # the hover windows are on the host clock: hold_s of vehicle time / the vehicle's speed-up
    (t0, a0), (t1, a1) = attitude[0], attitude[-1]
    rate = (a1["time_boot_ms"] - a0["time_boot_ms"]) / 1000.0 / ((t1 - t0) / 1e9)
    for e in hovers:
        assert e.duration_ns / 1e9 == pytest.approx(1.0 / rate, rel=0.25)
    assert len(fixes) == sum(1 for f in gps if f["fix_type"] >= 2) > 50  # every GNSS message became a fix
    assert all(f.fix_type == "rtk_fixed" and f.covariance_enu is not None for f in fixes)
    assert len(frames) > 10 and all(f.format == "jpeg" for f in frames)

    sent = [m for m in _tlog(out.with_suffix(".tlog")) if m.get_srcSystem() == 255]
    commands = [m.command for m in sent if m.get_type() == "COMMAND_LONG" and m.command != ap.CMD_SET_MESSAGE_INTERVAL]
    assert commands == [ap.CMD_DO_SET_MODE, ap.CMD_COMPONENT_ARM_DISARM, ap.CMD_MISSION_START]
    assert sum(m.get_type() == "MISSION_ITEM_INT" for m in sent) == 9 and sum(m.get_type() == "HEARTBEAT" for m in sent) >= 2


def _write_marker(folder: Path) -> None:
    """The plan.json beside the mission that fly reads the marker from."""
    (folder / "plan.json").write_text(json.dumps({"marker": {"size_m": 0.25, "dictionary": "DICT_4X4_50", "id": 0, "offset_frd_m": [0.1, 0, 0]}}))


def test_dry_run_prints_the_checklist_and_touches_nothing(tmp_path, camera, capsys):
    sim = start_sim(speedup=20.0, boot_s=1.0)
    plan = write_plan(tmp_path / "mission.plan", SMALL)
    _write_marker(tmp_path)
    out = tmp_path / "run.mcap"
    try:
        rc = main(["fly", "--connect", sim.addresses()[0], "--mission", str(plan), "--video", camera.url, "--out", str(out), "--dry-run"])
        link = open_link(sim.addresses()[0])
        link.wait_heartbeat(5)
        count = None
        for _attempt in range(3):  # a loaded machine may lose or delay the answer: ask again, as a GCS does
            link.send(link.dialect.MAVLink_mission_request_list_message(1, 1, 0))
            count = link.wait_message({"MISSION_COUNT"}, timeout_s=5.0)
            if count is not None:
                break
        link.close()
    finally:
        sim.stop()
    printed = capsys.readouterr().out
    assert rc == 0
    assert printed.count("[ OK ]") == 10 and "[ OK ] mission" in printed and "dry run: nothing uploaded" in printed
    rate = float(printed.split("gnss_rate")[1].split("new fixes/s")[0])
    assert 9.0 <= rate <= 10.5  # fly asked for 10 Hz; the simulated receiver follows
    assert not out.exists() and not out.with_suffix(".tlog").exists()
    assert count.count == 1  # only the vehicle's home: nothing was uploaded


def test_dry_run_warns_about_a_5_hz_receiver(tmp_path, camera, capsys):
    # ArduPilot's default GPS_RATE_MS = 200: asked for 10 Hz, the stream still carries 5 new fixes/s.
    sim = start_sim(speedup=20.0, boot_s=1.0, gps_rate_ms=200.0)
    plan = write_plan(tmp_path / "mission.plan", SMALL)
    _write_marker(tmp_path)
    try:
        rc = main(["fly", "--connect", sim.addresses()[0], "--mission", str(plan), "--video", camera.url, "--out", str(tmp_path / "run.mcap"), "--dry-run"])
    finally:
        sim.stop()
    captured = capsys.readouterr()
    printed = captured.out
    assert rc == 0, captured.err  # a warning, not a failure
    line = [ln for ln in printed.splitlines() if "gnss_rate" in ln][0]
    assert line.startswith("[WARN]") and "GPS_RATE_MS" in line
    assert 4.5 <= float(line.split("WARNING:")[1].split("new fixes/s")[0]) <= 5.5


def test_a_mission_the_vehicle_rejects_exits_2_with_one_line(tmp_path, camera):
    sim = start_sim(speedup=20.0, boot_s=1.0)
    # a speed change without its speed type (param 1 null): pre-flight passes it (NaN is QGC's "unset"), ArduCopter refuses it
    extra = [{"type": "SimpleItem", "command": 178, "frame": 2, "params": [None, 2, -1, 0, 0, 0, 0], "autoContinue": True, "doJumpId": 0}]
    plan = write_plan(tmp_path / "mission.plan", SMALL[:1], extra_items=extra)
    out = tmp_path / "run.mcap"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    try:
        proc = subprocess.run(
            [sys.executable, "-m", "dronecal_field", *_fly_args(sim.addresses()[0], plan, camera, out, "--start")],
            capture_output=True, text=True, timeout=60, env=env, cwd=tmp_path,
        )
    finally:
        sim.stop()
    assert proc.returncode == 2
    errors = proc.stderr.strip().splitlines()
    assert errors == ["dronecal-field fly: error: vehicle refused the mission: MAV_MISSION_INVALID_PARAM1 at item 5 (command 178, frame 2); fix that item in the plan"]
    assert not out.exists()


def test_a_command_the_autopilot_does_not_know_fails_preflight_before_any_upload(tmp_path, camera, capsys):
    sim = start_sim(speedup=20.0, boot_s=1.0)
    extra = [{"type": "SimpleItem", "command": 31999, "frame": 2, "params": [0, 0, 0, 0, 0, 0, 0], "autoContinue": True, "doJumpId": 0}]
    plan = write_plan(tmp_path / "mission.plan", SMALL[:1], extra_items=extra)
    try:
        rc = main(_fly_args(sim.addresses()[0], plan, camera, tmp_path / "run.mcap", "--start"))
    finally:
        sim.stop()
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1
    assert "pre-flight failed: mission: item 5: command 31999 is not one ArduCopter runs in a mission" in err
    assert not (tmp_path / "run.mcap").exists()


def test_unreachable_video_fails_preflight(tmp_path, capsys):
    sim = start_sim(speedup=20.0, boot_s=1.0)
    plan = write_plan(tmp_path / "mission.plan", SMALL)
    try:
        rc = main(["fly", "--connect", sim.addresses()[0], "--mission", str(plan), "--video", "http://127.0.0.1:9/none.mjpg", "--out", str(tmp_path / "r.mcap"), "--marker-size", "0.3"])
    finally:
        sim.stop()
    captured = capsys.readouterr()
    assert rc == 2
    assert "[FAIL] video" in captured.out
    assert captured.err.startswith("dronecal-field fly: error: pre-flight failed:")
    assert "video: MJPEG source http://127.0.0.1:9/none.mjpg: cannot connect" in captured.err and captured.err.count("\n") == 1


@pytest.mark.slow
def test_ctrl_c_finalises_the_file_and_commands_nothing(tmp_path, camera):
    sim = start_sim(speedup=8.0, boot_s=2.0)
    plan = write_plan(tmp_path / "mission.plan", SMALL, hold_s=3.0)
    out = tmp_path / "run.mcap"
    watcher = open_link(sim.addresses()[0])
    rec = MessageLog(watcher)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "dronecal_field", *_fly_args(sim.addresses()[0], plan, camera, out, "--start")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=tmp_path,
        # Ctrl-C as at a terminal: a test run started in the background (nohup, &) inherits SIGINT ignored
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    try:
        assert wait_until(lambda: any(m.seq == 4 for _, m in rec.of("MISSION_ITEM_REACHED")), 40)
        interrupted_ns = time.time_ns()
        proc.send_signal(signal.SIGINT)
        _stdout, stderr = proc.communicate(timeout=30)
        time.sleep(0.5)
        state = watcher.vehicle_heartbeat
    finally:
        if proc.poll() is None:
            proc.kill()
        watcher.close()
        sim.stop()
    assert proc.returncode == 130
    assert "interrupted:" in stderr and "the vehicle was not commanded" in stderr
    assert out.read_bytes().endswith(b"\x89MCAP0\r\n")  # footer written: a finalised file
    with open_run(out) as run:
        assert sum(1 for _ in run.iter_fixes()) > 20
        assert [int(e.metadata["seq"]) for e in run.iter_events() if e.type == "hover"] == [4]
    # still in its mission: AUTO (armed, or landed by the mission's own NAV_LAND: at load 15 fly took long enough to
    # finalise that the 8x mission had ended); that fly commanded nothing is the tlog's check below
    assert state.custom_mode == ap.MODE_AUTO
    log = _tlog(out.with_suffix(".tlog"))
    sent_commands = [m for m in log if m.get_srcSystem() == 255 and m.get_type() in ("COMMAND_LONG", "SET_MODE")]
    assert all(m._timestamp * 1e9 < interrupted_ns for m in sent_commands)
    assert [m.command for m in sent_commands if m.command != ap.CMD_SET_MESSAGE_INTERVAL] == [176, 400, 300]


@pytest.mark.slow
def test_link_dropped_and_video_paused_mid_mission_are_recorded_and_survived(tmp_path, camera):
    sim = start_sim(speedup=6.0, boot_s=2.0)
    relay = UdpRelay(sim.addresses()[0])
    plan = write_plan(tmp_path / "mission.plan", SMALL, hold_s=2.0)
    out = tmp_path / "run.mcap"
    watcher = open_link(sim.addresses()[0])
    rec = MessageLog(watcher)
    result = {}

    def fly():
        result["rc"] = main(_fly_args(relay.url, plan, camera, out, "--start", "--link-timeout", "1"))

    import threading

    thread = threading.Thread(target=fly)
    thread.start()
    try:
        assert wait_until(lambda: any(m.seq == 4 for _, m in rec.of("MISSION_ITEM_REACHED")), 40)
        lost_ns = time.time_ns()
        relay.blackout(2.5)
        time.sleep(3.0)
        paused_ns = time.time_ns()
        camera.pause()
        time.sleep(3.0)
        camera.resume()
        thread.join(timeout=60)
    finally:
        camera.resume()
        watcher.close()
        relay.close()
        sim.stop()
    assert result.get("rc") == 0
    with open_run(out) as run:
        events = list(run.iter_events())
        frames = [f.timestamp_ns for f in run.iter_frames()]
        fixes = [f.timestamp_ns for f in run.iter_fixes()]
        reached = [f["seq"] for _n, _t, f in run.iter_mavlink({"MISSION_ITEM_REACHED"})]
    lost = [e for e in events if e.type == "link_lost"]
    gaps = [e for e in events if e.type == "video_gap"]
    assert len(lost) == 1 and 2.0 < lost[0].duration_ns / 1e9 < 4.0
    assert abs(lost[0].timestamp_ns - lost_ns) < 0.5e9
    assert [e.type for e in events].count("link_restored") == 1
    # video kept recording while the link was down, and GNSS came back after it
    assert sum(lost[0].timestamp_ns < t < lost[0].end_ns for t in frames) > 10
    assert any(t > lost[0].end_ns for t in fixes)
    assert len(gaps) == 1 and 2.5 < gaps[0].duration_ns / 1e9 < 4.5
    assert abs(gaps[0].timestamp_ns - paused_ns) < 0.5e9
    assert reached[-1] == 8  # the RTL: the end of the mission was seen


def test_without_start_it_waits_for_the_pilot_and_commands_nothing(tmp_path, camera, capsys):
    sim = start_sim(speedup=20.0, boot_s=1.0)
    plan = write_plan(tmp_path / "mission.plan", SMALL)
    out = tmp_path / "run.mcap"
    try:
        rc = main(_fly_args(sim.addresses()[0], plan, camera, out, "--timeout-s", "1.5"))
        watcher = open_link(sim.addresses()[0])
        state = watcher.wait_heartbeat(5)
        watcher.close()
    finally:
        sim.stop()
    captured = capsys.readouterr()
    assert rc == 2
    assert "waiting for the pilot to arm and switch to AUTO" in captured.out
    assert "did not end within --timeout-s 1.5" in captured.err and "the vehicle was not commanded" in captured.err
    assert not state.base_mode & ap.MAV_MODE_FLAG_SAFETY_ARMED and state.custom_mode == ap.MODE_STABILIZE
    sent = [m for m in _tlog(out.with_suffix(".tlog")) if m.get_srcSystem() == 255 and m.get_type() in ("COMMAND_LONG", "SET_MODE")]
    assert {m.command for m in sent} == {ap.CMD_SET_MESSAGE_INTERVAL}  # telemetry requests only
    with open_run(out) as run:
        assert sum(1 for _ in run.iter_frames()) > 5
