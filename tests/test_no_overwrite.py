"""A recorded flight is never overwritten: ``fly --out`` refuses an existing run or .tlog (exit 2, one line)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from dronecal_field.commands.fly import free_run_path

ROOT = Path(__file__).resolve().parents[1]
MISSION = ROOT / "missions" / "paper-pinhole" / "mission.plan"


def _fly(out: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "dronecal_field", "fly", "--connect", "udp:127.0.0.1:9", "--mission", str(MISSION),
         "--video", "http://127.0.0.1:9/none.mjpg", "--out", str(out), "--marker-size", "0.3", "--heartbeat-timeout", "0.5", *extra],
        capture_output=True, text=True, timeout=60,
    )


@pytest.mark.parametrize("existing", ["run.mcap", "run.tlog"])
def test_fly_refuses_an_existing_run_or_tlog(tmp_path: Path, existing: str) -> None:
    kept = tmp_path / existing
    kept.write_bytes(b"an earlier flight" * 100)
    proc = _fly(tmp_path / "run.mcap")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr
    assert "nothing was overwritten" in lines[0] and "run-2.mcap" in lines[0]
    assert kept.read_bytes() == b"an earlier flight" * 100
    assert sorted(p.name for p in tmp_path.iterdir()) == [existing]


def test_free_run_path_skips_taken_names(tmp_path: Path) -> None:
    (tmp_path / "run.mcap").write_bytes(b"x")
    (tmp_path / "run-2.mcap").write_bytes(b"x")
    (tmp_path / "run-3.tlog").write_bytes(b"x")
    assert free_run_path(tmp_path / "run.mcap") == tmp_path / "run-4.mcap"


def test_fly_video_check_fails_a_still_image_and_a_size_other_than_the_plans(tmp_path: Path) -> None:
    """Pre-flight: a still JPEG is not a video (1 frame, 0 fps), and a stream must match the plan's camera."""
    import argparse
    from dataclasses import replace

    import cv2
    import numpy as np

    from dronecal_field.commands.fly import _judge_video, _probe_video

    still = tmp_path / "still.jpg"
    cv2.imwrite(str(still), np.full((48, 64, 3), 128, np.uint8))
    source, _first, status = _probe_video(str(still))
    if source is not None:
        source.close()
    assert (status.frames, status.fps, status.width, status.height) == (1, 0.0, 64, 48)
    flags = argparse.Namespace(camera_width=None, camera_height=None)
    judged = _judge_video(status, None, flags)
    assert judged.error is not None and "still image" in judged.error and "0.0 fps" in judged.error
    live = replace(status, frames=11, fps=10.0)
    assert _judge_video(live, None, flags).error is None
    plan = {"camera_guess": {"width": 1280, "height": 960}}
    judged = _judge_video(live, plan, flags)
    assert "sends 64x48 but the plan's camera is 1280x960" in judged.error and "--image-size 64x48" in judged.error
    assert _judge_video(live, {"camera_guess": {"width": 64, "height": 48}}, flags).error is None
