"""The mission protocol client against the simulated vehicle, over real (and lossy) UDP."""

from __future__ import annotations

import json
import math

import pytest

from dronecal_field.errors import LinkError, MissionRejectedError
from dronecal_field.mavlink.link import open_link
from dronecal_field.mavlink.mission import upload_and_verify
from dronecal_field.mavlink.missionfile import MissionItem, parse_qgc_plan, read_mission
from test_mavlink_support import REPLAYS, UdpRelay, plan_document, start_sim, wait_ready

WAYPOINTS_FILE = REPLAYS / "calib-grid.waypoints"


def _grid_mission():
    if WAYPOINTS_FILE.is_file():
        return read_mission(WAYPOINTS_FILE)
    return parse_qgc_plan(json.dumps(plan_document([(x, 4.0 + y, 1.5) for x in range(-3, 4) for y in range(5)])))


@pytest.mark.parametrize("seed", [7])
def test_upload_survives_5_percent_loss_of_mission_messages_both_ways(seed):
    sim = start_sim(speedup=20.0, boot_s=0.5)
    relay = UdpRelay(sim.addresses()[0], drop_fraction=0.05, seed=seed)
    link = open_link(relay.url)
    items = _grid_mission().items
    try:
        link.wait_heartbeat(5)
        wait_ready(link)
        report = upload_and_verify(link, items, timeout_s=0.3, retries=8)
    finally:
        link.close()
        relay.close()
        sim.stop()
    assert len(report.readback) == len(items) == (75 if WAYPOINTS_FILE.is_file() else 40)
    assert relay.dropped["up"] >= 2 and relay.dropped["down"] >= 2
    total = relay.candidates["up"] + relay.candidates["down"]
    assert 0.02 < (relay.dropped["up"] + relay.dropped["down"]) / total < 0.09
    # losses were recovered by re-sending, not by luck
    assert report.item_sends > len(items) or report.count_sends > 1


def test_unsupported_command_is_rejected_naming_the_item():
    sim = start_sim(boot_s=0.5)
    link = open_link(sim.addresses()[0])
    items = list(parse_qgc_plan(json.dumps(plan_document([(0.0, 4.0, 1.5), (1.0, 4.0, 1.5)]))).items)
    items[5] = MissionItem(seq=5, frame=2, command=31999)
    try:
        link.wait_heartbeat(5)
        wait_ready(link)
        with pytest.raises(MissionRejectedError) as info:
            upload_and_verify(link, items, timeout_s=0.5)
    finally:
        link.close()
        sim.stop()
    message = str(info.value)
    assert "MAV_MISSION_UNSUPPORTED at item 5 (command 31999" in message
    assert "\n" not in message


def test_nan_param_where_arducopter_refuses_it_is_rejected():
    sim = start_sim(boot_s=0.5)
    link = open_link(sim.addresses()[0])
    items = list(parse_qgc_plan(json.dumps(plan_document([(0.0, 4.0, 1.5)]))).items)
    items[4] = MissionItem(**{**items[4].__dict__, "p1": math.nan})
    try:
        link.wait_heartbeat(5)
        wait_ready(link)
        with pytest.raises(MissionRejectedError, match="MAV_MISSION_INVALID_PARAM1 at item 4"):
            upload_and_verify(link, items, timeout_s=0.5)
    finally:
        link.close()
        sim.stop()


def test_too_many_items_for_a_ready_vehicle_is_no_space_not_a_retry_loop():
    sim = start_sim(boot_s=0.5, max_items=10)
    link = open_link(sim.addresses()[0])
    try:
        link.wait_heartbeat(5)
        wait_ready(link)
        items = _grid_mission().items
        with pytest.raises(MissionRejectedError, match=f"NO_SPACE for {len(items)} items"):
            upload_and_verify(link, items, timeout_s=0.5, ready_timeout_s=30)
    finally:
        link.close()
        sim.stop()


def test_silent_vehicle_is_a_link_error():
    sim = start_sim(boot_s=0.5)
    relay = UdpRelay(sim.addresses()[0])
    link = open_link(relay.url)
    try:
        link.wait_heartbeat(5)
        wait_ready(link)
        relay.blackout(30)
        with pytest.raises(LinkError, match="no MISSION_REQUEST"):
            upload_and_verify(link, _grid_mission().items, timeout_s=0.1, retries=2)
    finally:
        link.close()
        relay.close()
        sim.stop()


def test_upload_answers_mission_request_int_and_duplicates():
    """A raw-socket vehicle that asks with MISSION_REQUEST_INT (as PX4 does) and repeats a request."""
    import socket
    import threading

    from dronecal_field.mavlink.link import mavlink_dialect
    from dronecal_field.mavlink.mission import send_mission

    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    peer.settimeout(2.0)
    d = mavlink_dialect()
    mav = d.MAVLink(None, srcSystem=1, srcComponent=1)
    got = []

    def vehicle():
        gcs = None
        hb = d.MAVLink_heartbeat_message(2, 12, 0, 0, 3, 3)
        # announce ourselves until the GCS writes to us
        while gcs is None:
            try:
                data, gcs = peer.recvfrom(65535)
            except TimeoutError:
                continue
        peer.sendto(hb.pack(mav), gcs)
        count = None
        while count is None:
            for msg in mav.parse_buffer(peer.recvfrom(65535)[0]) or []:
                if msg.get_type() == "MISSION_COUNT":
                    count = msg.count
        for seq in list(range(count)) + [count - 1]:
            for _ in range(2 if seq == 1 else 1):  # seq 1 requested twice
                peer.sendto(d.MAVLink_mission_request_int_message(255, 190, seq, 0).pack(mav), gcs)
            while True:
                msgs = [m for m in mav.parse_buffer(peer.recvfrom(65535)[0]) or [] if m.get_type() == "MISSION_ITEM_INT"]
                if msgs and msgs[-1].seq == seq:
                    got.append(seq)
                    break
        peer.sendto(d.MAVLink_mission_ack_message(255, 190, 0, 0).pack(mav), gcs)

    thread = threading.Thread(target=vehicle, daemon=True)
    thread.start()
    link = open_link(f"udp:127.0.0.1:{peer.getsockname()[1]}")
    try:
        link.wait_heartbeat(5)
        items = parse_qgc_plan(json.dumps(plan_document([(0.0, 4.0, 1.5)]))).items
        count_sends, item_sends, _ = send_mission(link, items, timeout_s=0.5)
        thread.join(timeout=5)
    finally:
        link.close()
        peer.close()
    assert got[: len(items)] == list(range(len(items)))
    assert count_sends == 1 and item_sends >= len(items) + 1  # the duplicate request was answered again
