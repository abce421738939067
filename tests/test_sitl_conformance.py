"""`sim vehicle` conforms to ArduPilot's own firmware (ArduCopter 4.7 SITL), as a ground station sees it.

The same short mission flown on both by the same client code
(benchmarks/sitl_conformance.py, which prints the table): the mission read
back item by item, leg and hold timing within 5 %, message rates per link
(the second link unasked, then after asking), the GPS fix's timing and
accuracy fields, the mode and arming sequence. Times are the vehicles' own
clocks, never the wall clock. Where they differ the firmware is right: the
simulator is fixed, never the other way round (docs/simulators.md).
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from sitl import needs_sitl

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import sitl_conformance as conf  # noqa: E402

pytestmark = [needs_sitl, pytest.mark.slow, pytest.mark.timeout(300)]

SPEEDUP = 5.0  # the firmware's scheduler keeps its clock at 5x on a loaded 2-core machine


@pytest.fixture(scope="module")
def rows():
    fw = conf.observe_firmware(SPEEDUP)
    if (reason := conf.starved(fw)) is not None:
        pytest.skip(reason)  # not a conformance result: the reference itself is not running as the firmware does
    sim = conf.observe_sim(SPEEDUP)
    table = conf.conformance_rows(sim, fw)
    print("\n" + conf.format_table(table))
    return table


def _rows(table, prefix: str):
    found = [r for r in table if r.what.startswith(prefix)]
    assert found, prefix
    return found


@pytest.mark.parametrize(
    "prefix",
    [
        "read-back items",
        "read-back home",
        "MISSION_ITEM_REACHED seqs",
        "mode/armed sequence",
        "HEARTBEAT base_mode",
        "COMMAND_ACKs of the start",
    ],
)
def test_mission_modes_and_arming_conform(rows, prefix):
    for row in _rows(rows, prefix):
        assert row.ok, row


@pytest.mark.parametrize(
    "prefix",
    [
        "last wp reached -> disarmed",
        "wp seq 4 still", "wp seq 5 still", "wp seq 7 still", "wp seq 8 still",
        # legs on ArduCopter's own S-curve (dronecal_field.motion: WPNAV_JERK 1 m/s^3, the S-curve clock slowed
        # while the vehicle lags), the fly-through turn as SCurve starts it, the take-off's shaped climb
        "wp seq 5 reached after previous", "wp seq 6 reached after previous", "wp seq 7 reached after previous",
        "wp seq 8 reached after previous", "start -> wp",
    ],
)  # fmt: skip
def test_leg_and_hold_timing_conform(rows, prefix):
    bad = [r for r in _rows(rows, prefix) if not r.ok]
    assert not bad, bad


@pytest.mark.parametrize("prefix", ["GPS_RAW_INT", "GPS new-fix", "GPS fix_type", "first 3D fix", "SYS_STATUS pre-arm", "EKF healthy"])
def test_gps_fix_timing_and_accuracy_fields_conform(rows, prefix):
    bad = [r for r in _rows(rows, prefix) if not r.ok]
    assert not bad, bad


RECORDED_GPS_LAG_MS = 104.0  # ArduCopter 4.7 SITL on a quiet machine (shared/replays/arducopter-sitl README)


def test_gps_lag_conforms(rows):
    (row,) = _rows(rows, "GPS lag")
    if abs(float(row.firmware) - RECORDED_GPS_LAG_MS) > 20.0:
        # the firmware's stream order under heavy load (a loop running late at 5x) blurs this measurement itself
        pytest.skip(f"the firmware's own GPS lag measured {row.firmware} ms here, not the {RECORDED_GPS_LAG_MS:g} ms it shows on a quiet machine")
    assert row.ok, row


@pytest.mark.parametrize("prefix", ["link 1", "link 2"])
def test_message_rates_per_link_conform(rows, prefix):
    bad = [r for r in _rows(rows, prefix) if not r.ok]
    assert not bad, bad
