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
