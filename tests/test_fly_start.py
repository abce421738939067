"""``fly`` starts recording clean (issue 4): frames queued during the upload are not drops, nor recorded; GNSS at 10 Hz."""

from __future__ import annotations

import re

import numpy as np
import pytest

from dronecal_field.cli import main
from dronecal_field.runfile.reader import open_run
from test_mavlink_support import MjpegServer, UdpRelay, start_sim, write_plan

SMALL = [(-1.0, 4.0, 1.5), (0.0, 4.0, 1.5), (1.0, 4.0, 2.0)]  # ENU metres from home
MISSION_COUNT_ID = 44


def test_frames_queued_during_a_slow_upload_are_neither_drops_nor_recorded_and_gnss_is_10_hz(tmp_path, capsys):
    sim = start_sim(speedup=10.0, boot_s=1.0)
    # The first MISSION_COUNT is lost (seed 1 draws 0.13, then 0.85, 0.76): the upload waits one 1.5 s
    # retry while nobody reads the 30 fps stream, so the source's 16-frame queue overflows.
    relay = UdpRelay(sim.addresses()[0], drop_fraction=0.5, drop_ids={MISSION_COUNT_ID}, seed=1)
    camera = MjpegServer(fps=30)
    plan = write_plan(tmp_path / "mission.plan", SMALL, hold_s=1.0)
    out = tmp_path / "run.mcap"
    try:
        rc = main(["fly", "--connect", relay.url, "--mission", str(plan), "--video", camera.url, "--out", str(out), "--marker-size", "0.3", "--start"])
    finally:
        camera.close()
        relay.close()
        sim.stop()
    printed = capsys.readouterr().out
    assert rc == 0

    # the premise: the upload was held up long enough to overflow the source's queue
    upload_s = float(re.search(r"read back identical in ([\d.]+) s", printed).group(1))
    assert relay.dropped["up"] == 1 and upload_s > 1.4
    summary = re.search(r"(\d+) frames \((\d+) dropped\).* in [\d.]+ s \((\d+) frames from before the start not recorded\)", printed)
    assert summary is not None, printed[-2000:]
    written, dropped, discarded = (int(g) for g in summary.groups())
    assert dropped == 0  # an unloaded machine, a fast disk: nothing is lost while recording
    # the probe's first frame, and of the 16 the queue held the ones that arrived before the start
    assert 1 <= discarded <= 17
    status_drops = [int(n) for n in re.findall(r"fps (\d+) dropped", printed)]
    assert status_drops and max(status_drops) == 0

    with open_run(out) as run:
        start_ns = int(run.metadata_record("dronecal.run")["recording.start_ns"])
        frames = [f.timestamp_ns for f in run.iter_frames()]
        fixes = list(run.iter_fixes())
        gps_usec = np.array([f["time_usec"] for _n, _t, f in run.iter_mavlink({"GPS_RAW_INT"}) if f["fix_type"] >= 2], np.int64)
    assert len(frames) == written > 30
    assert frames[0] >= start_ns and frames == sorted(frames)
    assert (frames[0] - start_ns) / 1e9 < 0.5  # and the first fresh frame is kept
    # /gnss/fix at 10 Hz of vehicle time (time_usec is the vehicle's clock; the sim runs 10x faster than the host)
    assert len(fixes) == len(gps_usec) > 100
    hz = (len(gps_usec) - 1) / ((gps_usec[-1] - gps_usec[0]) / 1e6)
    assert hz == pytest.approx(10.0, rel=0.05)
    assert np.median(np.diff(gps_usec)) == pytest.approx(100_000, rel=0.05)
