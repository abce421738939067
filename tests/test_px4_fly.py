"""PX4's dialect in fly's MAVLink layer: modes, the mission without home, read-back rules, reached messages, pre-flight.

The numbers are those measured on PX4 1.16 SITL (shared/sitl/README.md, and
dronecal_field/mavlink/px4.py's docstring); tests/test_px4_sitl.py flies them.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from dronecal_field.mavlink import missionfile as mf
from dronecal_field.mavlink import px4
from dronecal_field.mavlink.preflight import VehicleSnapshot, VideoStatus, evaluate_preflight, gnss_accuracy_meaning

HOME = (-35.363261, 149.165230, 584.0)
ITEMS = (
    mf.MissionItem(seq=0, frame=0, command=16, x=-353632610, y=1491652300, z=584.0),
    mf.MissionItem(seq=1, frame=3, command=22, p4=math.nan, x=-353632610, y=1491652300, z=2.0),
    mf.MissionItem(seq=2, frame=2, command=178, p1=1.0, p2=1.5, p3=-1.0),
    mf.MissionItem(seq=3, frame=3, command=201, p1=3.0, x=-353633328, y=1491652300, z=2.0),
    mf.MissionItem(seq=4, frame=3, command=16, p1=3.0, p4=161.49, x=-353632610, y=1491652740, z=3.147),
    mf.MissionItem(seq=5, frame=3, command=21, p4=math.nan, x=-353632610, y=1491652300, z=0.0),
)
MISSION = mf.Mission(items=ITEMS, home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2])


@pytest.mark.parametrize("name, custom", [("AUTO.LOITER", 0x03040000), ("AUTO.MISSION", 0x04040000), ("AUTO.RTL", 0x05040000),
                                          ("AUTO.LAND", 0x06040000), ("POSCTL", 0x00030000)])
def test_custom_modes_round_trip(name, custom):
    """The boot mode measured on the SITL is 50593792 = 0x03040000, AUTO.LOITER."""
    assert px4.custom_mode(*px4.mode_numbers(name)) == custom
    assert px4.mode_name(custom) == name


def test_arducopter_names_mean_px4_modes():
    assert px4.mode_numbers("AUTO") == (4, 4) and px4.mode_numbers("RTL") == (4, 5) and px4.mode_numbers("land") == (4, 6)
    assert px4.mode_numbers("GUIDED") == (4, 3)  # hold where you are: AUTO.LOITER


def test_the_px4_mission_has_no_home_item_and_flies_roi_location():
    wire = px4.to_wire(ITEMS)
    assert [it.seq for it in wire] == [0, 1, 2, 3, 4]
    assert [it.command for it in wire] == [22, 178, 195, 16, 21]  # DO_SET_ROI(201) would be stored with mode 0 and refused
    assert (wire[2].x, wire[2].y, wire[2].z, wire[2].p1) == (ITEMS[3].x, ITEMS[3].y, 2.0, 0.0)
    assert wire[3].p2 == px4.HOLD_ACCEPTANCE_M == 0.3  # the hold starts at the point, not 2 m before (NAV_ACC_RAD)
    assert (wire[3].p1, wire[3].p4) == (3.0, 161.49) and wire[0].p2 == 0.0
    back = px4.from_wire(wire, ITEMS[0])
    assert [it.seq for it in back] == [0, 1, 2, 3, 4, 5]


def test_px4_read_back_rules():
    """What the SITL returned: frame 3 as 6, float32 altitude and params (3.147 -> 3.1470000743865967), NaN kept."""
    wire = px4.to_wire(ITEMS)
    back = [replace(it, frame=mf.wire_frame(it), z=float(np.float32(it.z)), p4=float(np.float32(it.p4))) for it in wire]
    assert back[3].z == 3.1470000743865967
    assert px4.compare_readback(wire, back) == []
    assert px4.compare_readback(wire, back[:-1]) == ["vehicle holds 4 items, 5 were uploaded"]
    moved = [*back[:3], replace(back[3], z=3.2), back[4]]
    assert px4.compare_readback(wire, moved) == ["PX4 seq 3 (file seq 4): z 3.147 read back as 3.2"]
    yaw = [*back[:3], replace(back[3], p4=236.56997680664062), back[4]]  # yaw through float32 radians, as the SITL
    assert px4.compare_readback([*wire[:3], replace(wire[3], p4=236.57), wire[4]], yaw) == []
    assert px4.compare_readback(wire, yaw) != []


def test_reached_is_reported_once_per_item_in_file_numbering():
    """PX4 1.16 SITL sent 2,2,2...,3,3,4,4,4,5,...,5,7,7,... (6, a hold before a DO item, was overwritten by 7)."""
    f = px4.ReachedFilter()
    seen = [f.feed(s) for s in (0, 2, 2, 2, 3, 3, 4, 5, 5, 7, 7, 8, 9, 9)]
    flat = [s for part in seen for s in part]
    assert flat == list(range(1, 11))  # file seqs 1..10, once each
    assert f.repeats == 6 and f.filled == 2


GOOD_PX4 = VehicleSnapshot(autopilot=12, vehicle_type=2, armed=False, mode_name="AUTO.LOITER", fix_type=3, satellites=10, h_acc_m=0.9,
                           ekf_flags=1023, ekf_max_variance=0.07, battery_pct=100, voltage_v=16.2, ready_to_arm=True,
                           home_lat_deg=-35.3632624, home_lon_deg=149.1652365, gnss_rate_hz=5.0)
VIDEO = VideoStatus(url="http://cam/stream.mjpg", frames=30, fps=30.0, width=1280, height=720)


def test_px4_preflight_as_measured_on_the_sitl():
    results = {r.name: r for r in evaluate_preflight(GOOD_PX4, MISSION, VIDEO, min_fix="3d")}
    assert all(r.ok for r in results.values()), [r for r in results.values() if not r.ok]
    assert results["heartbeat"].detail == "PX4 quadrotor, mode AUTO.LOITER"
    assert results["gnss"].warning and "0.9 m" in results["gnss"].detail and "~90 px" in results["gnss"].detail
    assert results["gnss_rate"].warning and "GPS_RATE_MS" in results["gnss_rate"].detail and "PX4 has no" in results["gnss_rate"].detail
    assert "ESTIMATOR_STATUS flags 0x03ff" in results["ekf"].detail
    assert "PX4 flies" in results["mission"].detail
    # without --min-fix 3d the 3D fix stops fly before anything is uploaded
    strict = {r.name: r for r in evaluate_preflight(GOOD_PX4, MISSION, VIDEO)}
    assert not strict["gnss"].ok and "need rtk_fixed" in strict["gnss"].detail
    glitch = {r.name: r for r in evaluate_preflight(replace(GOOD_PX4, ekf_flags=1023 | 32768), MISSION, VIDEO, min_fix="3d")}
    assert not glitch["ekf"].ok


def test_what_0_9_m_means():
    text = gnss_accuracy_meaning(0.9)
    assert "5.1 deg" in text and "~90 px" in text and "10 m" in text


def test_plan_writes_a_px4_variant_qgc_opens_and_fly_reads(tmp_path):
    """mission-px4.plan: firmwareType 12, the ROI as DO_SET_ROI_LOCATION, everything else as planned."""
    import json

    from dronecal_field.plan.px4 import px4_plan

    plan = json.loads(mf.to_qgc_plan(MISSION))
    out = px4_plan(plan)
    assert plan["mission"]["firmwareType"] == 3 and out["mission"]["firmwareType"] == 12
    cmds = [it["command"] for it in out["mission"]["items"]]
    assert cmds == [22, 178, 195, 16, 21]
    roi = out["mission"]["items"][2]
    assert roi["params"][:4] == [0.0, 0.0, 0.0, 0.0] and roi["params"][4:6] == pytest.approx([-35.3633328, 149.16523], abs=1e-9)
    (tmp_path / "mission-px4.plan").write_text(json.dumps(out))
    back = mf.read_mission(tmp_path / "mission-px4.plan")
    assert [it.command for it in back.items[1:]] == [22, 178, 195, 16, 21]
    assert px4.to_wire(back.items) == px4.to_wire(ITEMS)  # either file goes to PX4 as the same mission
