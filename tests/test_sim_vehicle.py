"""The simulated ArduCopter copies the ArduCopter 4.7 behaviours recorded in
shared/replays/arducopter-sitl (README "Quirks seen"): one test per point.

Every test talks to the simulator over real UDP sockets with the project's own
MAVLink link; times are vehicle seconds (time_boot_ms), the simulator runs 20x.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink.link import open_link
from dronecal_field.mavlink.mission import download_mission, send_mission, upload_and_verify
from dronecal_field.mavlink.missionfile import MissionItem, parse_qgc_plan
from test_mavlink_support import FAST_PARAMS, HOME, MessageLog, ask_telemetry, plan_document, start_sim, wait_until, wait_ready

ORIGIN = EnuOrigin(*HOME)
WAYPOINTS = [(-2.0, 4.0, 1.5), (0.0, 4.0, 1.5), (2.0, 4.0, 2.5)]
HOLD_S = 2.0
ROI = (0.0, 0.0, 3.0)


def _mission(**kw):
    return parse_qgc_plan(__import__("json").dumps(plan_document(WAYPOINTS, hold_s=HOLD_S, roi_enu=ROI, **kw)))


def _armed(link) -> bool:
    hb = link.vehicle_heartbeat
    return hb is not None and bool(hb.base_mode & ap.MAV_MODE_FLAG_SAFETY_ARMED)


def _statustexts(rec) -> list[tuple[float, str]]:
    return [(t, m.text) for t, m in rec.of("STATUSTEXT")]


@pytest.fixture(scope="module")
def flight():
    """One whole mission flown by the simulator: takeoff, speed, ROI, 3 holds, RTL, auto-disarm."""
    sim = start_sim(speedup=20.0, boot_s=2.0)
    link = open_link(sim.addresses()[0])
    rec = MessageLog(link)
    try:
        ask_telemetry(link)
        wait_ready(link)
        mission = _mission()
        upload_and_verify(link, mission.items, timeout_s=0.5)
        assert link.set_mode("GUIDED") == ap.MAV_RESULT_ACCEPTED
        assert link.command_long(ap.CMD_COMPONENT_ARM_DISARM, (1,)) == ap.MAV_RESULT_ACCEPTED
        start_s = rec.vehicle_s
        assert link.command_long(ap.CMD_MISSION_START) == ap.MAV_RESULT_ACCEPTED
        # flown when the vehicle has disarmed again after the RTL
        assert wait_until(lambda: rec.of("MISSION_ITEM_REACHED") and rec.of("MISSION_ITEM_REACHED")[-1][1].seq == mission.last_seq and not _armed(link), 30)
        assert wait_until(lambda: rec.vehicle_s > rec.of("MISSION_ITEM_REACHED")[-1][0] + 2.0, 5)
        yield {"rec": rec, "mission": mission, "start_s": start_s, "sim": sim}
    finally:
        link.close()
        sim.stop()


def _positions_enu(rec):
    """(t, (N,3) ENU) of GLOBAL_POSITION_INT."""
    gpi = [(t, m) for t, m in rec.of("GLOBAL_POSITION_INT") if m.lat != 0]
    t = np.array([x[0] for x in gpi])
    lat = np.array([m.lat for _, m in gpi]) * 1e-7
    lon = np.array([m.lon for _, m in gpi]) * 1e-7
    up = np.array([m.relative_alt for _, m in gpi]) * 1e-3
    enu = geodetic_to_enu(lat, lon, ORIGIN.h_m, ORIGIN)
    enu[:, 2] = up
    return t, enu


# ----- the mission protocol -----


def test_upload_requests_are_mission_request_never_int():
    sim = start_sim(boot_s=0.5)
    link = open_link(sim.addresses()[0])
    try:
        ask_telemetry(link)
        wait_ready(link)
        items = _mission().items
        with link.subscribe({"MISSION_REQUEST", "MISSION_REQUEST_INT"}) as sub:
            send_mission(link, items, timeout_s=0.5)
            requests = []
            while (msg := sub.get(0.1)) is not None:
                requests.append((msg.get_type(), msg.seq))
    finally:
        link.close()
        sim.stop()
    assert requests == [("MISSION_REQUEST", seq) for seq in range(len(items))]


def test_upload_right_after_boot_is_refused_with_no_space_then_accepted_when_ready():
    sim = start_sim(speedup=20.0, boot_s=30.0)  # about 1 s of wall time before it takes uploads
    link = open_link(sim.addresses()[0])
    try:
        ask_telemetry(link)
        d = link.dialect
        with link.subscribe({"MISSION_ACK"}) as sub:
            link.send(d.MAVLink_mission_count_message(link.target_system, link.target_component, 5, 0))
            ack = sub.get(2.0)
        items = _mission().items
        report = upload_and_verify(link, items, timeout_s=0.5, ready_timeout_s=20)
        ready_at_s = link.latest("GLOBAL_POSITION_INT").time_boot_ms / 1000.0
    finally:
        link.close()
        sim.stop()
    assert ack is not None and ack.type == ap.MAV_MISSION_NO_SPACE
    assert report.no_space_retries >= 1
    assert ready_at_s >= 0.567 * 30.0  # uploads are taken from the pre-arm bit on (ArduCopter 4.7: 23.7 of its 41.8 s)
    assert len(report.readback) == len(items)


def test_readback_frames_and_home_follow_arducopter():
    sim = start_sim(boot_s=0.5)
    link = open_link(sim.addresses()[0])
    try:
        ask_telemetry(link)
        wait_ready(link)
        items = list(_mission().items)
        # a home 1 km away: the vehicle must answer seq 0 with its own home
        items[0] = MissionItem(seq=0, frame=0, command=16, x=items[0].x + 90000, y=items[0].y + 90000, z=700.0)
        send_mission(link, items, timeout_s=0.5)
        back = download_mission(link, timeout_s=0.5)
    finally:
        link.close()
        sim.stop()
    by_command = {item.command: item for item in back[1:]}
    assert (back[0].x, back[0].y, back[0].z) == (round(HOME[0] * 1e7), round(HOME[1] * 1e7), pytest.approx(HOME[2]))
    assert by_command[16].frame == 3  # sent as 6 (GLOBAL_RELATIVE_ALT_INT)
    assert by_command[22].frame == 3
    assert by_command[201].frame == 3
    assert by_command[178].frame == 0  # DO_CHANGE_SPEED sent in frame 2
    assert by_command[20].frame == 0  # RTL sent in frame 6
    assert all(b.x == a.x and b.y == a.y for a, b in zip(items[1:], back[1:]) if b.command in (16, 201))


def test_altitudes_read_back_as_the_firmware_stores_them():
    # ArduCopter 4.7: alt_cm = (int32)(z * 100.0f), read back alt_cm * 0.01f (issue 19; tests/test_sitl_arducopter.py)
    sim = start_sim(boot_s=0.5)
    link = open_link(sim.addresses()[0])
    try:
        ask_telemetry(link)
        wait_ready(link)
        items = list(_mission().items)
        wp = next(i for i, item in enumerate(items) if item.command == 16 and item.seq > 0)
        items[wp] = MissionItem(**{**items[wp].__dict__, "z": 1.47})
        items[wp + 1] = MissionItem(**{**items[wp + 1].__dict__, "z": 3.633})
        report = upload_and_verify(link, items, timeout_s=0.5)
    finally:
        link.close()
        sim.stop()
    assert report.readback[wp].z == 1.46999990940094  # not float32(1.47) = 1.4700000286102295
    assert report.readback[wp + 1].z == pytest.approx(3.63, abs=1e-6)
    assert "seq %d: z 3.633 -> 3.63" % (wp + 1) in report.storage_changes


def test_a_mode_change_is_announced_by_a_heartbeat_at_once():
    # ArduCopter 4.7 SITL (fly-calib-t1.tlog): GUIDED's and AUTO's HEARTBEATs follow their COMMAND_ACKs within 2 ms,
    # so a ground station sees STABILIZE > GUIDED > AUTO even when arming and MISSION_START follow at once
    sim = start_sim(speedup=1.0, boot_s=0.5)
    link = open_link(sim.addresses()[0])
    rec = MessageLog(link)
    try:
        ask_telemetry(link)
        wait_ready(link)
        assert link.set_mode("GUIDED") == ap.MAV_RESULT_ACCEPTED
        acked = rec.vehicle_s
        assert wait_until(lambda: any(m.custom_mode == ap.MODE_GUIDED for _t, m in rec.of("HEARTBEAT")), 5.0)
        first = next(t for t, m in rec.of("HEARTBEAT") if m.custom_mode == ap.MODE_GUIDED)
    finally:
        link.close()
        sim.stop()
    assert first - acked < 0.2  # vehicle seconds, not the next 1 Hz beat


# ----- arming and starting on the ground -----


def test_arming_in_auto_is_refused_with_a_statustext():
    sim = start_sim(boot_s=0.5)
    link = open_link(sim.addresses()[0])
    rec = MessageLog(link)
    try:
        ask_telemetry(link)
        wait_ready(link)
        upload_and_verify(link, _mission().items, timeout_s=0.5)
        assert link.set_mode("AUTO") == ap.MAV_RESULT_ACCEPTED
        result = link.command_long(ap.CMD_COMPONENT_ARM_DISARM, (1,))
        assert wait_until(lambda: any("not armable" in text for _, text in _statustexts(rec)), 2)
    finally:
        link.close()
        sim.stop()
    assert result == ap.MAV_RESULT_FAILED == 4
    assert "Arm: AUTO mode not armable" in [text for _, text in _statustexts(rec)]
    assert not _armed(link)


def test_guided_arm_then_auto_stays_on_the_ground_and_disarms_after_10_s():
    sim = start_sim(speedup=20.0, boot_s=0.5)
    link = open_link(sim.addresses()[0])
    rec = MessageLog(link)
    try:
        ask_telemetry(link)
        wait_ready(link)
        upload_and_verify(link, _mission().items, timeout_s=0.5)
        assert link.set_mode("GUIDED") == ap.MAV_RESULT_ACCEPTED
        assert link.command_long(ap.CMD_COMPONENT_ARM_DISARM, (1,)) == ap.MAV_RESULT_ACCEPTED
        armed_s = rec.vehicle_s
        assert link.set_mode("AUTO") == ap.MAV_RESULT_ACCEPTED
        assert wait_until(lambda: any(text == "Disarming motors" for _, text in _statustexts(rec)), 5)
    finally:
        link.close()
        sim.stop()
    disarm_s = [t for t, text in _statustexts(rec) if text == "Disarming motors"][0]
    assert disarm_s - armed_s == pytest.approx(10.0, abs=0.4)
    highest_mm = max(m.relative_alt for _, m in rec.of("GLOBAL_POSITION_INT"))
    assert highest_mm < 20  # never left the ground
    assert link.vehicle_heartbeat.custom_mode == ap.MODE_AUTO


def test_guided_arm_then_mission_start_takes_off_after_spool_up(flight):
    rec, start_s = flight["rec"], flight["start_s"]
    # the vehicle announces the takeoff item in the tick that handled MISSION_START
    started_s = next(t for t, text in _statustexts(rec) if t >= start_s and text == "Mission: 1 Takeoff")
    liftoff_s = next(t for t, m in rec.of("GLOBAL_POSITION_INT") if t > started_s and m.relative_alt > 100)
    # README: above 0.1 m 3.4 s after arming + MISSION_START; +-0.25 s for the 10 Hz telemetry
    assert liftoff_s - started_s == pytest.approx(3.45, abs=0.25)
    modes = [m.custom_mode for t, m in rec.of("HEARTBEAT") if t > started_s]
    assert modes[0] == ap.MODE_AUTO


# ----- mission execution -----


def test_no_reached_for_the_takeoff_but_for_the_do_items(flight):
    reached = [m.seq for _, m in flight["rec"].of("MISSION_ITEM_REACHED")]
    assert reached == [2, 3, 4, 5, 6, 7]


def test_do_items_after_takeoff_run_when_the_takeoff_completes(flight):
    rec = flight["rec"]
    t_speed = next(t for t, text in _statustexts(rec) if text == "Mission: 2 ChangeSpeed")
    t_top = next(t for t, m in rec.of("GLOBAL_POSITION_INT") if m.relative_alt >= 1990)
    assert t_speed == pytest.approx(t_top, abs=0.15)
    reached_2 = next(t for t, m in rec.of("MISSION_ITEM_REACHED") if m.seq == 2)
    reached_3 = next(t for t, m in rec.of("MISSION_ITEM_REACHED") if m.seq == 3)
    assert reached_2 == reached_3 == pytest.approx(t_top, abs=0.15)
    # during the climb the nose keeps its initial heading (no ROI yet)
    climb = [m.yaw for t, m in rec.of("ATTITUDE") if flight["start_s"] < t < t_top - 0.2]
    assert np.degrees(np.ptp(np.unwrap(climb))) < 1.0


def test_reached_for_a_waypoint_with_a_hold_comes_when_the_hold_ends(flight):
    rec = flight["rec"]
    gpi = [(t, m) for t, m in rec.of("GLOBAL_POSITION_INT") if m.lat != 0]
    t, enu = _positions_enu(rec)
    still = np.array([m.vx == 0 and m.vy == 0 and m.vz == 0 for _, m in gpi])
    for seq, target in zip((4, 5, 6), WAYPOINTS):
        reached_s = next(tt for tt, m in rec.of("MISSION_ITEM_REACHED") if m.seq == seq)
        at_point = (np.linalg.norm(enu - np.array(target), axis=1) < 0.1) & still & (t > reached_s - 10)
        arrived_s = t[np.argmax(at_point)]
        # the hold timer starts as the S-curve target reaches the point; the vehicle comes to rest on it up to a
        # second before that (ArduCopter 4.7 SITL: 0.5-0.8 s before, its S-curve's tail is that slow) or, lagging,
        # up to half a second after: the hold ends HOLD_S -0.5..+1 s after it stands still
        assert -0.5 <= reached_s - arrived_s - (HOLD_S + FAST_PARAMS.wp_settle_s) <= 1.0


def test_do_set_roi_points_the_nose_within_1_degree_during_holds(flight):
    rec = flight["rec"]
    t, enu = _positions_enu(rec)
    att = {tt: m.yaw for tt, m in rec.of("ATTITUDE")}
    errors = []
    for seq in (4, 5, 6):
        reached_s = next(tt for tt, m in rec.of("MISSION_ITEM_REACHED") if m.seq == seq)
        for ti, p in zip(t, enu):
            if reached_s - HOLD_S <= ti <= reached_s and ti in att:
                bearing = math.degrees(math.atan2(ROI[0] - p[0], ROI[1] - p[1]))
                errors.append((math.degrees(att[ti]) - bearing + 180.0) % 360.0 - 180.0)
    assert len(errors) >= 3 * 15
    assert max(abs(e) for e in errors) < 1.0


def test_hover_wander_and_gnss_noise_are_centimetre_level(flight):
    rec = flight["rec"]
    t, enu = _positions_enu(rec)
    spreads = []
    for seq, target in zip((4, 5, 6), WAYPOINTS):
        reached_s = next(tt for tt, m in rec.of("MISSION_ITEM_REACHED") if m.seq == seq)
        inside = (t >= reached_s - HOLD_S) & (t <= reached_s)
        spreads.append(float(np.hypot(*enu[inside, :2].std(axis=0))))
    assert 0.002 < np.mean(spreads) < 0.02  # README: real RTK copters wander ~1 cm; SITL 0.96 cm
    fixes = [m for _, m in rec.of("GPS_RAW_INT") if m.fix_type == 6]
    assert len(fixes) > 50
    assert all(m.alt_ellipsoid != 0 and m.h_acc > 0 and m.v_acc > 0 for m in fixes)


def test_after_rtl_landing_it_disarms_but_stays_in_auto(flight):
    rec, mission = flight["rec"], flight["mission"]
    texts = [text for _, text in _statustexts(rec)]
    assert texts[-1] == "Disarming motors"
    last_hb = rec.of("HEARTBEAT")[-1][1]
    assert not last_hb.base_mode & ap.MAV_MODE_FLAG_SAFETY_ARMED
    assert last_hb.custom_mode == ap.MODE_AUTO
    assert rec.of("MISSION_ITEM_REACHED")[-1][1].seq == mission.last_seq
    assert rec.of("GLOBAL_POSITION_INT")[-1][1].relative_alt < 20
    assert rec.of("MISSION_CURRENT")[-1][1].seq == 0


def test_after_the_last_item_it_hovers_in_auto_until_the_mode_changes():
    sim = start_sim(speedup=20.0, boot_s=0.5)
    link = open_link(sim.addresses()[0])
    rec = MessageLog(link)
    try:
        ask_telemetry(link)
        wait_ready(link)
        mission = parse_qgc_plan(__import__("json").dumps(plan_document([(0.0, 3.0, 2.0)], hold_s=1.0, end="none")))
        upload_and_verify(link, mission.items, timeout_s=0.5)
        link.set_mode("GUIDED")
        link.command_long(ap.CMD_COMPONENT_ARM_DISARM, (1,))
        link.command_long(ap.CMD_MISSION_START)
        assert wait_until(lambda: any(m.seq == mission.last_seq for _, m in rec.of("MISSION_ITEM_REACHED")), 20)
        end_s = rec.vehicle_s
        assert wait_until(lambda: rec.vehicle_s > end_s + 5.0, 5)
        hb_after = [m for t, m in rec.of("HEARTBEAT") if t > end_s + 1.0]
        alt_after = [m.relative_alt for t, m in rec.of("GLOBAL_POSITION_INT") if t > end_s + 1.0]
        assert link.set_mode("LOITER") == ap.MAV_RESULT_ACCEPTED
        assert wait_until(lambda: link.vehicle_heartbeat.custom_mode == ap.MODE_LOITER, 2)
    finally:
        link.close()
        sim.stop()
    assert hb_after and all(m.custom_mode == ap.MODE_AUTO and m.base_mode & ap.MAV_MODE_FLAG_SAFETY_ARMED for m in hb_after)
    assert min(alt_after) > 1900 and max(alt_after) < 2100


def test_system_time_advances_at_vehicle_rate(flight):
    times = [m for _, m in flight["rec"].of("SYSTEM_TIME")]
    assert len(times) > 10
    unix_span_ms = (times[-1].time_unix_usec - times[0].time_unix_usec) / 1000.0
    boot_span_ms = times[-1].time_boot_ms - times[0].time_boot_ms
    assert unix_span_ms == pytest.approx(boot_span_ms, abs=1.0)


def test_guided_takeoff_then_land_mode_lands_and_disarms_in_land():
    sim = start_sim(speedup=20.0, boot_s=0.5)
    link = open_link(sim.addresses()[0])
    rec = MessageLog(link)
    try:
        ask_telemetry(link)
        wait_ready(link)
        assert link.set_mode("GUIDED") == ap.MAV_RESULT_ACCEPTED
        assert link.command_long(ap.CMD_COMPONENT_ARM_DISARM, (1,)) == ap.MAV_RESULT_ACCEPTED
        assert link.command_long(ap.CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, 3.0)) == ap.MAV_RESULT_ACCEPTED
        assert wait_until(lambda: (m := link.latest("GLOBAL_POSITION_INT")) is not None and m.relative_alt > 2990, 10)
        assert link.set_mode("LAND") == ap.MAV_RESULT_ACCEPTED
        assert wait_until(lambda: not _armed(link), 10)
    finally:
        link.close()
        sim.stop()
    highest = max(m.relative_alt for _, m in rec.of("GLOBAL_POSITION_INT"))
    assert 2990 <= highest <= 3010
    assert link.vehicle_heartbeat.custom_mode == ap.MODE_LAND
    assert rec.of("GLOBAL_POSITION_INT")[-1][1].relative_alt < 20
