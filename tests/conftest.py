import os
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip("../shared is not beside the repository")
    return SHARED


def run_cli(*args: str, timeout: float = 120, **kw):
    """Run the real console entry point in a subprocess; returns CompletedProcess."""
    import subprocess

    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    return subprocess.run(
        [sys.executable, "-m", "dronecal_field", *args],
        capture_output=True, text=True, timeout=timeout, env=env, **kw,
    )
