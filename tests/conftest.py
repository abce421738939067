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


# The modules that wait longest on real-time simulators and firmware, longest first. `make test` hands modules to its
# two workers in collection order (pytest-xdist --dist loadfile --no-loadscope-reorder; xdist's default is most tests
# first), so these go first and run beside the many short ones instead of after them (the suite's wall time was set by
# a PX4 SITL flight started last).
LONGEST_FIRST = (
    "test_px4_sitl.py", "test_sitl_flight.py", "test_end_to_end.py", "test_px4_sim_flight.py", "test_live_flight.py",
    "test_plan_files.py", "test_perturbation.py", "test_px4_sim_conformance.py", "test_sitl_conformance.py",
    "test_calibrate_batch.py", "test_plan_site.py", "test_rtsp.py", "test_fly_multicam.py", "test_site_calibrate.py",
    "test_scout.py", "test_sitl_arducopter.py",
)


def pytest_collection_modifyitems(config, items) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order kept within a module
