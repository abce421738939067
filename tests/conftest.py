import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
# The recorded ArduCopter SITL session the simulator copies and the tests read.
REPLAYS = SHARED / "replays" / "arducopter-sitl"
needs_replays = pytest.mark.skipif(not REPLAYS.is_dir(), reason="../shared/replays/arducopter-sitl is not beside the repository")


def run_cli(*args: str, timeout: float = 120, **kw):
    """Run the real console entry point in a subprocess; returns CompletedProcess."""
    import subprocess

    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    return subprocess.run(
        [sys.executable, "-m", "dronecal_field", *args],
        capture_output=True, text=True, timeout=timeout, env=env, **kw,
    )
