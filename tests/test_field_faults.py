"""Field faults: a full disk, a second process, a signal, a device as input. Real files, real processes, real mounts.

Each test asserts the same things: no traceback, exit 2 (or the signal's code)
with one line, no recording lost, no half files left, no hang (every
subprocess has a timeout), no orphan processes.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MISSION = ROOT / "missions" / "paper-pinhole" / "mission.plan"
PY = [sys.executable, "-m", "dronecal_field"]


@pytest.fixture
def small_disk(tmp_path: Path):
    """A real 3 MB file system (tmpfs), mounted for the test; skipped where mounting is not permitted."""
    mnt = tmp_path / "small"
    mnt.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here ({proc.stderr.strip() or proc.returncode}): needs root")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def _fill(folder: Path) -> None:
    """Fill the file system of ``folder`` to the last byte."""
    with open(folder / "filler", "wb", buffering=0) as f:
        for size in (65536, 4096, 1):
            try:
                while True:
                    f.write(b"\xff" * size)
            except OSError:
                pass


def _thread_tracebacks():
    """Collect exceptions that escape any thread (they would print a traceback)."""
    caught: list[BaseException] = []
    old = threading.excepthook

    def hook(args):
        caught.append(args.exc_value)

    threading.excepthook = hook
    return caught, old


def test_a_run_file_that_cannot_start_on_a_full_disk_is_one_line(small_disk: Path) -> None:
    from dronecal_field.errors import InputError
    from dronecal_field.runfile.records import FORMAT_VERSION, MarkerSpec, RunMetadata
    from dronecal_field.runfile.writer import RunWriter

    _fill(small_disk)
    meta = RunMetadata(format_version=FORMAT_VERSION, width=64, height=48,
                       marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3))
    with pytest.raises(InputError, match="free some space"):
        RunWriter(small_disk / "run.mcap", meta)


# --------------------------------------------------------------------------
# signals: SIGTERM and SIGHUP are a clean stop, like Ctrl-C


def _fly_argv(out: Path, connect: str = "udp:127.0.0.1:9", mission: Path = MISSION, video: str = "http://127.0.0.1:9/x.mjpg", *extra: str) -> list[str]:
    return [*PY, "fly", "--connect", connect, "--mission", str(mission), "--video", video, "--out", str(out), "--marker-size", "0.3", *extra]


def _wait_for(predicate, timeout_s: float = 60.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.1)
    return False


def _our_processes(marker: str) -> list[str]:
    """Command lines of running processes that mention ``marker`` (a test's own folder): orphans."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (entry / "stat").read_text().split(")")[-1].split()[0]
        except OSError:
            continue
        if marker in cmd and state != "Z":
            found.append(cmd)
    return found


@pytest.mark.parametrize("sig", [signal.SIGHUP])
def test_fly_stopped_before_recording_says_so_and_gives_the_names_back(tmp_path: Path, sig: int) -> None:
    out = tmp_path / "run.mcap"
    proc = subprocess.Popen(_fly_argv(out, "udp:127.0.0.1:9", MISSION, "http://127.0.0.1:9/x.mjpg", "--heartbeat-timeout", "60"),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert _wait_for(out.exists, 30)  # claimed at start, before the link opens
    proc.send_signal(sig)
    _stdout, stderr = proc.communicate(timeout=30)
    assert proc.returncode == 128 + sig
    assert "Traceback" not in stderr and stderr.strip().splitlines() == [f"dronecal-field fly: stopped by {signal.Signals(sig).name}"]
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # the empty claims are given back


def test_two_fly_with_one_out_the_second_is_refused_in_one_line(tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    first = subprocess.Popen(_fly_argv(out, "udp:127.0.0.1:9", MISSION, "http://127.0.0.1:9/x.mjpg", "--heartbeat-timeout", "60"),
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_for(out.exists, 30)
        second = subprocess.run(_fly_argv(out), capture_output=True, text=True, timeout=60)
    finally:
        first.send_signal(signal.SIGTERM)
        first_stderr = first.communicate(timeout=30)[1]
    assert first.returncode == 128 + signal.SIGTERM and first_stderr.strip().splitlines() == ["dronecal-field fly: stopped by SIGTERM"]
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # the first gave its claims back
    lines = second.stderr.strip().splitlines()
    assert second.returncode == 2 and len(lines) == 1 and "Traceback" not in second.stderr
    assert "already exists" in lines[0] and "another fly" in lines[0] and "run-2.mcap" in lines[0]


@pytest.mark.parametrize("sig", [signal.SIGTERM])
def test_fly_stopped_while_recording_finalises_the_run(tmp_path: Path, sig: int) -> None:
    from dronecal_field.runfile.reader import open_run
    from test_mavlink_support import MjpegServer, plan_document, start_sim

    plan = tmp_path / "m.plan"
    plan.write_text(json.dumps(plan_document([(0.0, 4.0, 1.5), (1.0, 4.0, 1.5)], hold_s=30.0)))
    sim = start_sim(speedup=2.0, boot_s=0.5)
    camera = MjpegServer(fps=15)
    out = tmp_path / "run.mcap"
    lines: list[str] = []
    try:
        proc = subprocess.Popen(_fly_argv(out, sim.addresses()[0], plan, camera.url, "--start", "--no-live"),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
        reader.start()
        assert _wait_for(lambda: any(line.startswith("started:") for line in lines), 90), lines
        time.sleep(1.5)  # a few chunks recorded
        proc.send_signal(sig)
        stderr = proc.communicate(timeout=60)[1]
    finally:
        camera.close()
        sim.stop()
    assert proc.returncode == 128 + sig, stderr
    assert "Traceback" not in stderr
    assert "finalised" in stderr and f"stopped by {signal.Signals(sig).name}" in stderr
    with open_run(out) as run:
        assert not run.truncated
        assert sum(1 for _ in run.iter_fixes()) > 0 and sum(1 for _ in run.iter_frames()) > 0
    assert out.with_suffix(".tlog").stat().st_size > 0


def test_demo_stopped_stops_its_children_and_leaves_no_temporary_folder(tmp_path: Path) -> None:
    """SIGTERM to the demo while its plan step runs: the plan stops (its staged folder removed), nothing runs on."""
    out = tmp_path / "demo-signal"
    proc = subprocess.Popen([*PY, "demo", "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    try:
        assert _wait_for(lambda: (out / "logs" / "plan.log").exists(), 120)  # its plan step has started
        assert _wait_for(lambda: any(str(out) in cmd and " plan " in cmd for cmd in _our_processes(str(out))), 60)
        time.sleep(1.0)
        proc.send_signal(signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert "Traceback" not in stderr and "stopped by SIGTERM" in stderr
    assert _wait_for(lambda: not _our_processes(str(out)), 30), _our_processes(str(out))
    assert not [p.name for p in out.glob(".*tmp-*")]


# --------------------------------------------------------------------------
# runs that lie: contradicting metadata, payloads that do not decode, two runs joined


def _copy_run(src: Path, out: Path, width: int | None = None, height: int | None = None, garbage_every: int = 0) -> tuple[int, int]:
    """Rewrite ``src`` with RunWriter (optionally another stated size, and a non-protobuf payload on
    /gnss/fix, /camera/image and /events every ``garbage_every`` messages); (fixes, frames) written."""
    from dataclasses import replace

    from dronecal_field.runfile import messages as pm
    from dronecal_field.runfile.reader import open_run
    from dronecal_field.runfile.writer import RunWriter

    with open_run(src) as run:
        meta = replace(run.metadata, width=width or run.metadata.width, height=height or run.metadata.height)
        fixes, frames, events = list(run.iter_fixes())[:400], list(run.iter_frames())[:40], list(run.iter_events())
    with RunWriter(out, meta, background_flush=False) as w:
        for i, fix in enumerate(fixes):
            w.write_fix(fix)
            if garbage_every and i % garbage_every == 0:
                with w._lock:
                    w._add_locked(w._channels[pm.FIX_TOPIC], fix.timestamp_ns, b"\xff\x01 not a LocationFix")
        for i, frame in enumerate(frames):
            w.write_frame(frame)
            if garbage_every and i % garbage_every == 0:
                with w._lock:
                    w._add_locked(w._channels[pm.IMAGE_TOPIC], frame.timestamp_ns, b"\xff\x01 not an image")
        for event in events:
            w.write_event(event)
            if garbage_every:
                with w._lock:
                    w._add_locked(w._channels[pm.EVENTS_TOPIC], event.timestamp_ns, b"\xff\x02")
    return len(fixes), len(frames)


def test_runs_that_lie_are_refused_corrected_or_skipped_and_counted(tmp_path: Path) -> None:
    from dronecal_field.errors import ContractError
    from dronecal_field.runfile.reader import open_run

    nominal = ROOT / "replays" / "nominal.mcap"
    huge = tmp_path / "huge.mcap"
    _copy_run(nominal, huge, width=100_000)
    with pytest.raises(ContractError, match="camera.width' = 100000"):
        open_run(huge)
    wrong = tmp_path / "wrong-size.mcap"
    _copy_run(nominal, wrong, width=1280, height=720)  # frames are 640x360
    with open_run(wrong) as run:
        assert (run.metadata.width, run.metadata.height) == (640, 360)
        assert any("1280x720 but the frames are 640x360" in w for w in run.warnings)
    garbage = tmp_path / "garbage.mcap"
    n_fixes, n_frames = _copy_run(nominal, garbage, garbage_every=50)
    with open_run(garbage) as run:
        assert len(list(run.iter_fixes())) == n_fixes and sum(1 for _ in run.iter_frames()) == n_frames
        assert len(list(run.iter_events())) > 0
        assert run.undecodable["/gnss/fix"] == len(range(0, n_fixes, 50)) and run.undecodable["/camera/image"] > 0
        assert any("do not decode" in w for w in run.warnings)
    joined = tmp_path / "joined.mcap"
    joined.write_bytes(nominal.read_bytes() + (ROOT / "replays" / "latency.mcap").read_bytes())
    with pytest.raises(ContractError, match="second MCAP file starts at byte"):
        open_run(joined)


# --------------------------------------------------------------------------
# hand-edited files, devices and sizes: one table, each case in this process through cli.main


def _hand_edited(d: Path) -> list[tuple[str, list[str], str]]:
    """(case, argv, needle) of files a user edited by hand, devices, and numbers far out of range."""
    plan = json.loads(MISSION.read_text())
    cases: list[tuple[str, list[str], str]] = []
    fly_tail = ["--connect", "udp:127.0.0.1:9", "--video", "http://127.0.0.1:9/x.mjpg", "--heartbeat-timeout", "0.5"]

    def mission_case(name: str, edit, needle: str, with_marker: bool = True) -> None:
        doc = json.loads(json.dumps(plan))
        folder = d / name
        folder.mkdir()
        edit(doc)
        path = folder / "mission.plan"
        path.write_text(json.dumps(doc))
        cases.append((f"fly {name}", ["fly", "--mission", str(path), *fly_tail, "--out", str(folder / "run.mcap"),
                                      *(["--marker-size", "0.3"] if with_marker else [])], needle))

    def item(doc, i=3):
        return doc["mission"]["items"][i]

    mission_case("home-strings", lambda doc: doc["mission"].__setitem__("plannedHomePosition", ["a", "b", "c"]), "plannedHomePosition")
    mission_case("param-infinity", lambda doc: item(doc)["params"].__setitem__(0, float("inf")), "infinite")
    mission_case("dojumpid-x", lambda doc: item(doc).__setitem__("doJumpId", "x"), "doJumpId")
    mission_case("command-16.9", lambda doc: item(doc).__setitem__("command", 16.9), "command")
    mission_case("command-string", lambda doc: item(doc).__setitem__("command", "16"), "command")
    mission_case("lat-null", lambda doc: item(doc)["params"].__setitem__(4, None) if item(doc)["command"] == 16 else None, "latitude")
    waypoints = d / "inf.waypoints"
    waypoints.write_text("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t-35.3\t149.1\t584\t1\n1\t0\t3\t16\t0\t0\t0\t0\tInfinity\t149.1\t5\t1\n")
    cases.append(("fly .waypoints Infinity", ["fly", "--mission", str(waypoints), *fly_tail, "--out", str(d / "w.mcap"), "--marker-size", "0.3"], "infinite"))
    for name, marker, needle in (("size-abc", {"size_m": "abc"}, "marker.size_m"), ("size-list", {"size_m": [1]}, "marker.size_m"),
                                 ("id-float", {"size_m": 0.3, "id": 1.5}, "marker.id"), ("offset-short", {"size_m": 0.3, "offset_frd_m": [0, 1]}, "offset_frd_m")):
        folder = d / f"planjson-{name}"
        folder.mkdir()
        (folder / "mission.plan").write_text(MISSION.read_text())
        (folder / "plan.json").write_text(json.dumps({"marker": marker}))
        cases.append((f"fly plan.json {name}", ["fly", "--mission", str(folder / "mission.plan"), *fly_tail, "--out", str(folder / "run.mcap")], needle))
    folder = d / "planjson-list"
    folder.mkdir()
    (folder / "mission.plan").write_text(MISSION.read_text())
    (folder / "plan.json").write_text("[1, 2]")
    cases.append(("fly plan.json a list", ["fly", "--mission", str(folder / "mission.plan"), *fly_tail, "--out", str(folder / "run.mcap")], "JSON object"))
    fifo = d / "mission-fifo.plan"
    os.mkfifo(fifo)
    os.mkfifo(d / "run-fifo.mcap")
    cases.append(("fly --mission fifo", ["fly", "--mission", str(fifo), *fly_tail, "--out", str(d / "f.mcap"), "--marker-size", "0.3"], "not a regular file"))
    cases.append(("fly --mission /dev/zero", ["fly", "--mission", "/dev/zero", *fly_tail, "--out", str(d / "z.mcap"), "--marker-size", "0.3"], "not a regular file"))
    cases.append(("fly --out its tlog", ["fly", "--mission", str(MISSION), *fly_tail, "--out", str(d / "r.tlog"), "--marker-size", "0.3"], "same file"))
    cases.append(("fly --out the mission", ["fly", "--mission", str(MISSION), *fly_tail, "--out", str(MISSION), "--marker-size", "0.3"], "--mission"))
    # site TOML by hand
    site = ROOT / "missions" / "paper-pinhole.toml"
    for name, text, needle in (
        ("duplicate-key", "[a]\ntilt = 30\n[b]\ntilt = 31\n", "twice"),
        ("bool-height", "mount_height = true\n", "mount_height"),
        ("float-id", "marker_id = 1.9\n", "marker_id"),
    ):
        path = d / f"site-{name}.toml"
        path.write_text(site.read_text().replace("mount_height", "# mount_height").replace("tilt", "# tilt").replace("marker_id", "# marker_id") + text)
        cases.append((f"plan --site {name}", ["plan", "--site", str(path), "--out", str(d / f"plan-{name}")], needle))
    for flag in ("--trials", "--endurance", "--exposure-s", "--gnss-hz", "--sigma-h"):
        value = "100000000" if flag == "--trials" else "1e308"
        cases.append((f"plan {flag} {value}", ["plan", "--site", str(site), flag, value, "--out", str(d / "plan-big")], flag))
    cases.append(("plan --site fifo", ["plan", "--site", str(fifo), "--out", str(d / "plan-fifo")], str(fifo)))
    cases.append(("import --tlog /dev/zero", ["import", "--tlog", "/dev/zero", "--video", str(MISSION), "--out", str(d / "i.mcap"),
                                              "--marker-size", "0.3", "--marker-dictionary", "DICT_4X4_50", "--marker-id", "0"], "/dev/zero"))
    cases.append(("calibrate /dev/zero", ["calibrate", "/dev/zero", "--out", str(d / "cal-zero")], "/dev/zero"))
    cases.append(("calibrate fifo.mcap", ["calibrate", str(d / "run-fifo.mcap"), "--out", str(d / "cal-fifo")], "run-fifo.mcap"))
    return cases


def test_hand_edited_files_devices_and_sizes_are_one_line_exit_2(tmp_path: Path) -> None:
    """Every case: exit 2, one line naming the key or value, no traceback, nothing left behind. In-process (fast)."""
    from test_bad_input import _run

    cases = _hand_edited(tmp_path)
    before = {p for p in tmp_path.rglob("*")}
    failures = []
    for case, argv, needle in cases:
        code, _out, err = _run(argv)
        lines = err.strip().splitlines()
        if "Traceback" in err or code != 2 or len(lines) != 1 or needle.lower() not in lines[0].lower():
            failures.append(f"{case}: exit {code}: {err.strip()[-400:]}")
    assert not failures, "\n".join(failures)
    assert {p for p in tmp_path.rglob("*")} == before  # no half files, no claims left
    assert len(cases) >= 25


def test_fly_on_a_disk_that_fills_mid_flight_says_so_at_once_and_exits_2(small_disk: Path) -> None:
    """The whole command on a real 3 MB disk: the status line says RECORDING STOPPED: DISK FULL while the
    flight goes on, no thread prints a traceback, the run reads back up to its cut, exit 2 in one line."""
    from dronecal_field.runfile.reader import open_run
    from test_mavlink_support import MjpegServer, plan_document, start_sim

    plan = small_disk.parent / "m.plan"
    plan.write_text(json.dumps(plan_document([(0.0, 4.0, 1.5), (1.0, 4.0, 1.5)], hold_s=60.0)))
    (small_disk / "other-files").write_bytes(b"\xff" * 1_500_000)  # the disk is half full already
    sim = start_sim(speedup=4.0, boot_s=0.5)
    camera = MjpegServer(fps=30)
    out = small_disk / "run.mcap"
    try:
        proc = subprocess.run(_fly_argv(out, sim.addresses()[0], plan, camera.url, "--start", "--no-live", "--timeout-s", "6"),
                              capture_output=True, text=True, timeout=240)
    finally:
        camera.close()
        sim.stop()
    assert "Traceback" not in proc.stderr and "Traceback" not in proc.stdout
    assert proc.returncode == 2, proc.stderr
    assert proc.stdout.startswith("WARNING: only ")  # said before anything connected: the disk is small
    status = [line for line in proc.stdout.splitlines() if line.startswith("wp ")]
    assert any("RECORDING STOPPED: DISK FULL" in line for line in status)
    assert "RECORDING STOPPED EARLY (disk full" in proc.stderr.strip().splitlines()[-1]  # said in fly's last line
    with open_run(out) as run:
        assert not run.truncated and run.recording_stopped is not None
        assert sum(1 for _ in run.iter_fixes()) > 0 and sum(1 for _ in run.iter_frames()) > 0


def test_the_demo_verdict_reads_its_own_logs(tmp_path: Path) -> None:
    """The demo's last line never says 'met its targets' beside logs that ask to re-fly."""
    from dronecal_field.demo import log_problems

    fly, cal = tmp_path / "fly.log", tmp_path / "calibrate.log"
    fly.write_text("wp 3/4 ...\nverdict: re-fly waypoints 4, 5 (marker not detected) — 39/60 detected of 60 flown\n")
    cal.write_text("calibrated run.mcap: 0 of 24 waypoints (windows from events), model full\n  warning: the holds lasted 0.3 s\n")
    problems = log_problems(fly, cal)
    assert problems[0].startswith("fly: re-fly waypoints 4, 5") and len(problems) == 3
    fly.write_text("verdict: good: 60/60 waypoints detected\n")
    cal.write_text("calibrated run.mcap: 24 of 24 waypoints (windows from events), model full\n")
    assert log_problems(fly, cal) == ()


def test_import_onto_a_full_disk_leaves_no_half_file(small_disk: Path, tmp_path: Path) -> None:
    from conftest import REPLAYS
    from test_bad_input import _run
    from test_import import _write_video

    tlog = REPLAYS / "calib-grid-gpsloss.tlog"
    if not tlog.exists():
        pytest.skip("the SITL replays are not here")
    video = tmp_path / "camera.mp4"
    _write_video(video, 20, fps=10.0)
    (small_disk / "other-files").write_bytes(b"\xff" * 2_900_000)  # about 100 kB left
    code, _out, err = _run(["import", "--tlog", str(tlog), "--video", str(video), "--video-start", "2026-11-22T03:20:00.500Z",
                            "--marker-dictionary", "DICT_4X4_50", "--marker-id", "3", "--marker-size", "0.3",
                            "--out", str(small_disk / "run.mcap")])
    assert code == 2 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "nothing was written" in err
    assert sorted(p.name for p in small_disk.iterdir()) == ["other-files"]  # no run.mcap, no .run.mcap.tmp-*


def test_a_read_only_disk_is_refused_before_anything_starts(tmp_path: Path) -> None:
    """--out on a read-only file system: fly (also --dry-run), plan, import and calibrate say so in one line, exit 2."""
    from test_bad_input import _run

    ro = tmp_path / "ro"
    ro.mkdir()
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(ro)], capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs here ({proc.stderr.strip() or proc.returncode}): needs root")
    try:
        fly = ["fly", "--connect", "udp:127.0.0.1:9", "--mission", str(MISSION), "--video", "http://127.0.0.1:9/x.mjpg",
               "--marker-size", "0.3", "--heartbeat-timeout", "0.5", "--out", str(ro / "run.mcap")]
        cases = [
            ("fly", fly),
            ("fly --dry-run", [*fly, "--dry-run"]),
            ("plan", ["plan", "--site", str(ROOT / "missions" / "paper-pinhole.toml"), "--out", str(ro / "plan")]),
            ("calibrate", ["calibrate", str(ROOT / "replays" / "nominal.mcap"), "--out", str(ro / "cal")]),
            ("import", ["import", "--tlog", str(MISSION), "--image-size", "640x480", "--marker-dictionary", "DICT_4X4_50",
                        "--marker-id", "0", "--marker-size", "0.3", "--out", str(ro / "i.mcap")]),
        ]
        failures = []
        for name, argv in cases:
            code, _out, err = _run(argv)
            lines = err.strip().splitlines()
            if code != 2 or "Traceback" in err or len(lines) != 1 or "Read-only file system" not in lines[0]:
                failures.append(f"{name}: exit {code}: {err.strip()[-300:]}")
        assert not failures, "\n".join(failures)
        assert list(ro.iterdir()) == []
    finally:
        subprocess.run(["umount", "-l", str(ro)], capture_output=True)


def test_a_stop_swallowed_by_a_library_is_raised_again(tmp_path: Path) -> None:
    """A library that catches everything (pymavlink's and ssl's imports do) must not lose a SIGTERM."""
    script = tmp_path / "swallow.py"
    script.write_text(
        "import time, types\n"
        "from dronecal_field import cli\n"
        "cli._install_stop_signals()\n"
        "lib = types.ModuleType('somelib')\n"
        "exec('def swallow():\\n    import time\\n    t = time.monotonic()\\n    while time.monotonic() - t < 2:\\n"
        "        try:\\n            time.sleep(0.01)\\n        except:\\n            pass\\n', lib.__dict__)\n"
        "print('ready', flush=True)\n"
        "cli._run_command(types.SimpleNamespace(command='test', func=lambda args: (lib.swallow(), time.sleep(300), 0)[-1]))\n"
        "print('returned', flush=True)\n"
    )
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    assert proc.stdout.readline().strip() == "ready"
    time.sleep(0.5)  # inside the library's loop
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=120)  # not the 300 s sleep after the library (20 s was too short at load 15)
    assert "Traceback" not in stderr and stderr.strip() == "dronecal-field test: stopped by SIGTERM"
    assert stdout.strip() == "returned"


def test_import_stopped_midway_leaves_no_half_file(tmp_path: Path) -> None:
    import cv2
    import numpy as np
    from conftest import REPLAYS

    tlog = REPLAYS / "calib-grid-gpsloss.tlog"
    if not tlog.exists():
        pytest.skip("the SITL replays are not here")
    video = tmp_path / "camera.mp4"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (640, 480))
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    for i in range(600):
        writer.write(np.roll(noise, i, axis=1))
    writer.release()
    out = tmp_path / "out" / "run.mcap"
    out.parent.mkdir()
    proc = subprocess.Popen([*PY, "import", "--tlog", str(tlog), "--video", str(video), "--video-start", "2026-11-22T03:20:00.500Z",
                             "--marker-dictionary", "DICT_4X4_50", "--marker-id", "3", "--marker-size", "0.3", "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    writing = _wait_for(lambda: any(out.parent.glob(".run.mcap.tmp-*")) or proc.poll() is not None, 60)
    proc.send_signal(signal.SIGTERM)
    _stdout, stderr = proc.communicate(timeout=60)
    if not writing or proc.returncode == 0:
        pytest.skip("import finished before it could be stopped")
    assert proc.returncode == 128 + signal.SIGTERM and "Traceback" not in stderr, stderr
    assert stderr.strip().splitlines() == ["dronecal-field import: stopped by SIGTERM"]
    assert list(out.parent.iterdir()) == []  # no half run to block the retry, no temporary file
