"""Crash safety: run files cut at any byte, and a recorder killed with SIGKILL, still read."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecal_field.errors import ContractError
from dronecal_field.runfile.reader import open_run
from dronecal_field.runfile.records import Frame, GnssFix, MarkerSpec, RunEvent, RunMetadata
from dronecal_field.runfile.writer import RunWriter

T0 = 1_795_315_761_000_000_000
REPO = Path(__file__).resolve().parents[1]


def _meta() -> RunMetadata:
    return RunMetadata(
        format_version=1,
        width=64,
        height=48,
        marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3, offset_frd_m=(0.0, 0.0, 0.1)),
    )


def _jpegs(n: int) -> list[bytes]:
    out = []
    for i in range(n):
        img = np.zeros((48, 64, 3), np.uint8)
        cv2.circle(img, (8 + 5 * i, 24), 6, (255, 255, 255), -1)
        out.append(cv2.imencode(".jpg", img)[1].tobytes())
    return out


def test_cut_at_200_offsets_reads_a_prefix(tmp_path):
    full = tmp_path / "full.mcap"
    jpegs = _jpegs(10)
    frames = [Frame(timestamp_ns=T0 + i * 33_000_000, format="jpeg", data=jpegs[i % 10]) for i in range(300)]
    fixes = [GnssFix(timestamp_ns=T0 + i * 200_000_000, lat_deg=-35.0 + i * 1e-7, lon_deg=149.0, alt_m=600.0, covariance_enu=np.eye(3) * 1e-4, fix_type="rtk_fixed") for i in range(50)]
    with RunWriter(full, _meta(), chunk_size=8 * len(jpegs[0]), background_flush=False) as w:
        w.attach("mission.plan", b"{}", "application/json")
        for i, f in enumerate(frames):
            w.write_frame(f)
            if i % 6 == 0:
                w.write_fix(fixes[i // 6])
            if i == 150:
                w.write_event(RunEvent(timestamp_ns=f.timestamp_ns, duration_ns=10, type="hover"))
    data = full.read_bytes()
    from mcap.reader import make_reader

    with open(full, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert len(chunks) >= 20
    first_chunk_end = chunks[0].chunk_start_offset + chunks[0].chunk_length

    offsets = sorted(set(np.linspace(0, len(data), 200).astype(int).tolist()) | {first_chunk_end, len(data) - 1})
    previous = -1
    refused = 0
    for cut in offsets:
        path = tmp_path / "cut.mcap"
        path.write_bytes(data[:cut])
        try:
            run = open_run(path)
        except ContractError as exc:
            # Only a file cut before its first complete chunk lacks the required channels.
            assert cut < first_chunk_end, (cut, str(exc))
            refused += 1
            continue
        with run:
            got_frames = list(run.iter_frames())
            got_fixes = list(run.iter_fixes())
            assert run.attachment("mission.plan") == b"{}"
            if cut < len(data):
                assert run.truncated or cut >= chunks[-1].chunk_start_offset + chunks[-1].chunk_length
        n = len(got_frames)
        assert [(f.timestamp_ns, f.data) for f in got_frames] == [(f.timestamp_ns, f.data) for f in frames[:n]]
        assert [f.lat_deg for f in got_fixes] == [f.lat_deg for f in fixes[: len(got_fixes)]]
        assert n >= previous  # a longer prefix never reads less
        previous = n
    assert 0 < refused < len(offsets) // 4
    assert previous == len(frames)


CHILD = textwrap.dedent(
    """
    import sys, time
    import cv2, numpy as np
    from dronecal_field.runfile.records import Frame, GnssFix, MarkerSpec, RunMetadata
    from dronecal_field.runfile.writer import RunWriter
    meta = RunMetadata(format_version=1, width=64, height=48,
                       marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3))
    jpeg = cv2.imencode(".jpg", np.full((48, 64, 3), 128, np.uint8))[1].tobytes()
    t0 = time.time_ns()
    w = RunWriter(sys.argv[1], meta)   # default chunking: 1 MiB or 1 s
    i = 0
    while True:
        t = t0 + i * 10_000_000
        while time.time_ns() < t:
            time.sleep(0.002)
        w.write_frame(Frame(timestamp_ns=t, format="jpeg", data=jpeg))
        if i % 20 == 0:
            w.write_fix(GnssFix(timestamp_ns=t, lat_deg=-35.0, lon_deg=149.0 + i * 1e-7, alt_m=600.0))
        print(i, t, flush=True)
        i += 1
    """
)


def test_sigkill_mid_recording_keeps_all_but_the_last_second(tmp_path):
    path = tmp_path / "killed.mcap"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], stdout=subprocess.PIPE, text=True, env=env)
    try:
        last_i, t0 = -1, None
        for line in proc.stdout:
            i, t = (int(v) for v in line.split())
            if t0 is None:
                t0 = t - i * 10_000_000
            last_i = i
            if i >= 300:  # 3 s of recording at 100 frames/s
                break
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    with open_run(path) as run:
        assert run.truncated
        frames = [f.timestamp_ns for f in run.iter_frames()]
        fixes = [f.timestamp_ns for f in run.iter_fixes()]
    n = len(frames)
    assert frames == [t0 + i * 10_000_000 for i in range(n)]  # an unbroken prefix
    assert fixes == [t0 + i * 10_000_000 for i in range(0, n, 20)][: len(fixes)]
    # Chunks close at 1 s of age (+ the flusher's 0.25 s period): at most ~1.25 s lost; 2 s allows for load.
    lost_s = (last_i + 1 - n) * 0.01
    print(f"SIGKILL after {last_i + 1} frames: {n} recovered, {lost_s:.2f} s lost")
    assert lost_s <= 2.0, lost_s
    assert n >= 100


def test_background_flush_without_further_writes(tmp_path):
    """An open recording whose writes pause still has its last chunk on disk, readable while open."""
    import time

    path = tmp_path / "paused.mcap"
    jpeg = _jpegs(1)[0]
    w = RunWriter(path, _meta(), max_chunk_age_s=0.2)
    try:
        w.write_frame(Frame(timestamp_ns=T0, format="jpeg", data=jpeg))
        w.write_fix(GnssFix(timestamp_ns=T0, lat_deg=-35.0, lon_deg=149.0, alt_m=600.0))
        frames: list[Frame] = []
        deadline = time.monotonic() + 10.0
        while not frames and time.monotonic() < deadline:
            time.sleep(0.05)
            try:
                with open_run(path) as run:  # the live file: no summary yet
                    assert run.truncated
                    frames = list(run.iter_frames())
            except ContractError:
                continue  # the first chunk is not closed yet
        assert [(f.timestamp_ns, f.data) for f in frames] == [(T0, jpeg)]
    finally:
        w.close()
    with open_run(path) as run:
        assert not run.truncated and run.units_total == 1
