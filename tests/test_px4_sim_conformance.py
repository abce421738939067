"""`sim vehicle --autopilot px4` against PX4 1.16 SITL: the key rows of benchmarks/sim_px4_conformance.py in CI.

The same probe (tests/px4_probe.py, `fly`'s own client code) runs the short
flight (take-off 2.5 m, 2 m/s, ROI at the pole, a 3 s hold 4 m east, LAND)
on the SITL (real time, about 35 s with its boot) and on the simulator at 4x
at the same time, and every row of the table must agree: identity and modes,
GPS (fix 3, h_acc 900 mm, time since boot), the upload's request types,
PX4's read-back, MISSION_START arming, the hold's still time and yaw, the
reached messages and their repeats, the landing and the disarm. Skips with
the reason when the SITL binary or private namespaces are absent.
"""

from __future__ import annotations

import threading

import pytest

from px4_probe import SHORT, probe_sim, probe_sitl, rows
from px4_sitl import needs_px4

pytestmark = [needs_px4, pytest.mark.timeout(240)]


def test_the_simulated_px4_agrees_with_the_sitl_row_by_row():
    sim: dict = {}
    worker = threading.Thread(target=lambda: sim.update(probe_sim(4.0, scenario=SHORT, log=lambda *_a: None)), daemon=True)
    worker.start()  # the simulator's probe runs while the SITL boots and flies (real time)
    sitl = probe_sitl(SHORT, log=lambda *_a: None)
    worker.join(timeout=180)
    assert sim, "the simulator's probe did not finish"
    table = rows([sitl], sim)
    print("\n".join(f"{'ok ' if ok else 'DIFF'} {what}: SITL {a}; sim {b}" for what, a, b, ok in table))
    differ = [f"{what}: SITL {a}, sim {b}" for what, a, b, ok in table if not ok]
    # the firmware's facts, exactly
    assert sitl["boot_mode"] == sim["boot_mode"] == "AUTO.LOITER"
    assert (sitl["gps_fix_type"], sitl["gps_h_acc_mm"]) == (sim["gps_fix_type"], sim["gps_h_acc_mm"]) == (3, 900)
    assert sitl["requests_first_upload"] == sim["requests_first_upload"] == ["MISSION_REQUEST", "MISSION_REQUEST_INT"]
    assert sitl["frame3_back"] == sim["frame3_back"] == 6 and sitl["yaw_back"] == sim["yaw_back"] == 236.56997680664062
    # The simulator sends one reached message per tick (PX4: one mission_result per cycle); a tick stretched by a loaded
    # machine can fold the take-off's reached into the next item's (seen once in CI: [0, 2, 3, 4] vs [2, 3, 4])
    missing = set(sitl["reached_seqs"]) - set(sim["reached_seqs"])
    assert set(sim["reached_seqs"]) <= set(sitl["reached_seqs"]), (sitl["reached_seqs"], sim["reached_seqs"])
    assert missing <= {min(sitl["reached_seqs"])}, (sitl["reached_seqs"], sim["reached_seqs"])  # the seqs row: checked here
    assert sitl["modes"][-2:] == sim["modes"][-2:] == ["AUTO.MISSION*", "AUTO.MISSION"]
    # the key rows within their tolerance (the reached seqs above); the landing's timings vary more from one SITL run to the next than the
    # tolerances (descent 0.41-0.83 m/s, touchdown-to-disarm 2.5-4.4 s) and are printed, not asserted
    key = ("HEARTBEAT", "boot mode", "MISSION_CURRENT", "GPS fix", "GPS time", "requests", "read back", "seq 0", "frame 3", "z 2.5",
           "yaw 236", "ROI command", "modes from", "reached repeats", "hold A (", "hold A: yaw", "airborne")
    assert not [d for d in differ if d.startswith(key)], differ
