"""Mission files (.plan, .waypoints) and ArduCopter's mission storage rules."""

from __future__ import annotations

import json
import math

import pytest

from dronecal_field.errors import InputError
from dronecal_field.mavlink.missionfile import (
    MissionItem,
    ardupilot_check,
    ardupilot_readback,
    compare_readback,
    parse_qgc_plan,
    parse_waypoints,
    readback_alt_m,
    read_mission,
    storage_changes,
    stored_alt_cm,
    to_qgc_plan,
    wire_frame,
)
from test_mavlink_support import REPLAYS, plan_document

WAYPOINTS_FILE = REPLAYS / "calib-grid.waypoints"


@pytest.mark.skipif(not WAYPOINTS_FILE.is_file(), reason="shared replays not mounted")
def test_reads_the_recorded_waypoints_file():
    mission = read_mission(WAYPOINTS_FILE)
    assert len(mission.items) == 75
    assert mission.source_format == "waypoints"
    home, takeoff, speed, roi, first = mission.items[:5]
    assert (home.x, home.y, home.z) == (-353632610, 1491652300, 584.0)
    assert (takeoff.command, takeoff.frame, takeoff.z) == (22, 3, 2.0)
    assert (speed.command, speed.frame, speed.p2, speed.p3) == (178, 2, 1.5, -1.0)
    assert (roi.command, roi.p1, roi.x, roi.y, roi.z) == (201, 3.0, -353632610, 1491652300, 3.0)
    assert (first.command, first.p1, first.hold_s) == (16, 3.0, 3.0)
    assert mission.items[-1].command == 20
    assert [wire_frame(item) for item in mission.items[:4]] == [0, 6, 2, 6]


def test_plan_parsing_keeps_positions_to_1e7_and_nulls_as_nan(tmp_path):
    doc = plan_document([(1.0, 5.0, 1.5)], hold_s=3.0)
    path = tmp_path / "mission.plan"
    path.write_text(json.dumps(doc))
    mission = read_mission(path)
    wp = mission.items[4]
    lat, lon = doc["mission"]["items"][3]["params"][4:6]
    assert (wp.x, wp.y) == (round(lat * 1e7), round(lon * 1e7))
    assert math.isnan(wp.p4) and math.isnan(mission.items[1].p4)
    assert mission.items[0].seq == 0 and mission.items[0].z == 584.0
    assert [item.seq for item in mission.items] == list(range(len(mission.items)))


def test_plan_round_trip_through_to_qgc_plan():
    mission = parse_qgc_plan(json.dumps(plan_document([(0.0, 4.0, 1.5), (1.0, 4.0, 2.5)])))
    again = parse_qgc_plan(to_qgc_plan(mission))
    for a, b in zip(mission.items, again.items):
        assert (a.command, a.frame, a.x, a.y, a.z) == (b.command, b.frame, b.x, b.y, b.z)
        assert all((math.isnan(u) and math.isnan(v)) or u == v for u, v in zip((a.p1, a.p2, a.p3, a.p4), (b.p1, b.p2, b.p3, b.p4)))


def test_do_jump_target_becomes_a_seq():
    doc = plan_document([(0.0, 4.0, 1.5)], end="none")
    doc["mission"]["items"].append({"type": "SimpleItem", "command": 177, "frame": 2, "params": [4, 2, 0, 0, 0, 0, 0], "autoContinue": True, "doJumpId": 99})
    mission = parse_qgc_plan(json.dumps(doc))
    jump = mission.items[-1]
    target = doc["mission"]["items"][3]  # doJumpId 4 is the waypoint
    assert target["doJumpId"] == 4 and jump.p1 == 4.0 == float(mission.items[4].seq)


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("{}", "fileType"),
        ("not json", "not valid JSON"),
        (json.dumps({"fileType": "Plan", "mission": {"items": [], "plannedHomePosition": [1, 2, 3]}}), "empty"),
        (json.dumps({"fileType": "Plan", "mission": {"items": [{"type": "ComplexItem", "complexItemType": "survey"}], "plannedHomePosition": [1, 2, 3]}}), "survey"),
        (json.dumps({"fileType": "Plan", "mission": {"items": [{"type": "SimpleItem", "command": 16, "frame": 3, "params": [0]}], "plannedHomePosition": [1, 2, 3]}}), "7 numbers"),
    ],
)
def test_bad_plans_are_input_errors(text, fragment):
    with pytest.raises(InputError, match=fragment):
        parse_qgc_plan(text)


def test_bad_waypoints_are_input_errors():
    with pytest.raises(InputError, match="QGC WPL 110"):
        parse_waypoints("hello")
    with pytest.raises(InputError, match="out of order"):
        parse_waypoints("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t1\t2\t3\t1\n2\t0\t3\t16\t0\t0\t0\t0\t1\t2\t3\t1\n")


@pytest.mark.parametrize(
    "item, expected",
    [
        # hold stored as uint16 seconds; yaw (p4) dropped; relative frame reads back as 3
        (MissionItem(seq=1, frame=6, command=16, p1=1.5, p4=144.37, x=1, y=2, z=1.5), dict(p1=1.0, p4=0.0, frame=3, z=1.5)),
        # z truncated to whole centimetres in float32
        (MissionItem(seq=1, frame=3, command=16, p1=3.0, x=1, y=2, z=1.537), dict(p1=3.0, z=float(__import__("numpy").float32(1.53)), frame=3)),
        # NAV_LAND's p4 is a direction flag: 0 reads back as 1
        (MissionItem(seq=1, frame=3, command=21, x=1, y=2, z=0.0), dict(p4=1.0, frame=3)),
        # CONDITION_YAW keeps float angles; no location: frame 0, x/y/z 0
        (MissionItem(seq=1, frame=2, command=115, p1=144.37, p2=0, p3=0, p4=0, x=5, y=6, z=7.0), dict(p1=float(__import__("numpy").float32(144.37)), frame=0, x=0, z=0.0)),
        # RTL in frame 6 reads back in frame 0
        (MissionItem(seq=1, frame=6, command=20), dict(frame=0)),
        # absolute altitude frame
        (MissionItem(seq=1, frame=5, command=16, x=1, y=2, z=600.25), dict(frame=0, z=600.25)),
        # a fly-through waypoint: hold 0 stays 0; Copter drops the acceptance radius (p2), WPNAV_RADIUS applies
        (MissionItem(seq=1, frame=3, command=16, p1=0.0, p2=0.5, x=1, y=2, z=2.0), dict(p1=0.0, p2=0.0, frame=3, z=2.0)),
        # a hold under half a second is stored as 0: flown through as well
        (MissionItem(seq=1, frame=3, command=16, p1=0.4, x=1, y=2, z=2.0), dict(p1=0.0)),
    ],
)
def test_ardupilot_readback_table(item, expected):
    stored = ardupilot_readback(item)
    for name, value in expected.items():
        assert getattr(stored, name) == value, name
    assert compare_readback([item, item], [item, stored]) == []


def test_compare_readback_reports_real_differences():
    sent = [MissionItem(seq=0, frame=0, command=16), MissionItem(seq=1, frame=6, command=16, p1=2.0, x=100, y=200, z=2.0)]
    moved = [sent[0], MissionItem(seq=1, frame=3, command=16, p1=2.0, x=101, y=200, z=2.0)]
    shorter_hold = [sent[0], MissionItem(seq=1, frame=3, command=16, p1=1.0, x=100, y=200, z=2.0)]
    assert compare_readback(sent, moved) == ["seq 1: position (100, 200) read back as (101, 200) [1e-7 deg]"]
    assert compare_readback(sent, shorter_hold) == ["seq 1: p1 2.0 read back as 1.0"]
    assert compare_readback(sent, sent[:1]) == ["vehicle holds 1 items, 2 were uploaded"]


def test_ardupilot_check_codes():
    assert ardupilot_check(MissionItem(seq=1, frame=3, command=16, x=1, y=2, z=2.0)) == 0
    assert ardupilot_check(MissionItem(seq=1, frame=3, command=16, p4=math.nan, x=1, y=2, z=2.0)) == 0
    assert ardupilot_check(MissionItem(seq=1, frame=3, command=16, p1=math.nan, x=1, y=2, z=2.0)) == 6
    assert ardupilot_check(MissionItem(seq=1, frame=3, command=31999)) == 3
    assert ardupilot_check(MissionItem(seq=1, frame=1, command=16)) == 2
    assert ardupilot_check(MissionItem(seq=1, frame=3, command=16, x=950000000, y=0, z=1.0)) == 10


def test_storage_changes_lists_what_arducopter_will_not_keep():
    mission = parse_qgc_plan(json.dumps(plan_document([(0.0, 4.0, 1.5)], hold_s=2.0)))
    items = list(mission.items)
    items[4] = MissionItem(**{**items[4].__dict__, "p4": 90.0})
    assert storage_changes(items) == ["seq 4: p4 90 -> 0"]


@pytest.mark.parametrize(
    "z, alt_cm, readback",
    [
        (1.47, 147, 1.46999990940094),  # issue 19: what ArduCopter 4.7 SITL read back
        (3.633, 363, 3.6299998760223389),  # truncated to the centimetre, then * 0.01f
        (2.0, 200, 2.0),
        (1.537, 153, 1.5299999713897705),
        (-0.004, 0, 0.0),  # truncation toward zero
    ],
)
def test_altitudes_are_stored_in_truncated_centimetres_and_read_back_times_0_01f(z, alt_cm, readback):
    import numpy as np

    item = MissionItem(seq=1, frame=6, command=16, p1=3.0, x=1, y=2, z=z)
    stored = ardupilot_readback(item)
    assert stored_alt_cm(z) == alt_cm
    assert stored.z == float(np.float32(readback)) == readback_alt_m(alt_cm)
    assert compare_readback([item, item], [item, stored]) == []


def test_the_comparison_is_at_storage_resolution_not_float_identity():
    home = MissionItem(seq=0, frame=0, command=16)
    sent = MissionItem(seq=1, frame=6, command=16, p1=3.0, x=100, y=200, z=1.47)
    as_firmware = MissionItem(seq=1, frame=3, command=16, p1=3.0, x=100, y=200, z=1.46999990940094)
    as_old_model = MissionItem(seq=1, frame=3, command=16, p1=3.0, x=100, y=200, z=1.4700000286102295)
    one_cm_low = MissionItem(seq=1, frame=3, command=16, p1=3.0, x=100, y=200, z=1.46)
    assert compare_readback([home, sent], [home, as_firmware]) == []  # the refusal, now accepted
    assert compare_readback([home, sent], [home, as_old_model]) == []  # the same 147 cm
    assert compare_readback([home, sent], [home, one_cm_low]) == ["seq 1: z 1.47 (147 cm stored) read back as 1.46"]
    # params in their stored C types: a uint16 hold compares as an integer, DO_CHANGE_SPEED's speed as float32
    speed = MissionItem(seq=1, frame=2, command=178, p1=1.0, p2=1.5, p3=-1.0)
    assert compare_readback([home, speed], [home, MissionItem(seq=1, frame=0, command=178, p1=1.0, p2=1.5, p3=-1.0)]) == []
    assert compare_readback([home, speed], [home, MissionItem(seq=1, frame=0, command=178, p1=1.0, p2=1.5000001, p3=-1.0)]) != []


def test_storage_changes_lists_sub_centimetre_altitudes_but_not_float32_representation():
    home = MissionItem(seq=0, frame=0, command=16)
    items = [home, MissionItem(seq=1, frame=6, command=16, p1=3.0, x=1, y=2, z=1.47), MissionItem(seq=2, frame=6, command=16, p1=3.0, x=1, y=2, z=3.633)]
    assert storage_changes(items) == ["seq 2: z 3.633 -> 3.63"]
