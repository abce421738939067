"""The simulator's message flow resembles the recorded ArduCopter SITL tlog
(shared/replays/arducopter-sitl/calib-grid-rtk.tlog): telemetry rates per vehicle
second, and the exact mission-protocol exchange for the same 75-item mission."""

from __future__ import annotations

import collections

import pytest

from dronecal_field.mavlink.link import mavutil_module, open_link
from dronecal_field.mavlink.mission import upload_and_verify
from dronecal_field.mavlink.missionfile import MissionItem, read_mission
from test_mavlink_support import REPLAYS, ask_like_recorded_gcs, start_sim, wait_until, wait_ready

TLOG = REPLAYS / "calib-grid-rtk.tlog"
PROTOCOL = {"MISSION_COUNT", "MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_ACK", "MISSION_REQUEST_LIST"}
STREAMS = ("ATTITUDE", "GLOBAL_POSITION_INT", "GPS_RAW_INT", "SYS_STATUS", "EKF_STATUS_REPORT", "BATTERY_STATUS", "MISSION_CURRENT", "HEARTBEAT", "SYSTEM_TIME", "HOME_POSITION")

pytestmark = pytest.mark.skipif(not TLOG.is_file(), reason="shared replays not mounted")


def _item(msg) -> MissionItem:
    return MissionItem(seq=msg.seq, frame=msg.frame, command=msg.command, p1=msg.param1, p2=msg.param2, p3=msg.param3, p4=msg.param4, x=msg.x, y=msg.y, z=msg.z, autocontinue=bool(msg.autocontinue))


@pytest.fixture(scope="module")
def recorded():
    """Rates per SITL second, the mission-protocol exchange and the read-back, from the tlog."""
    log = mavutil_module().mavlink_connection(str(TLOG))
    counts: collections.Counter[str] = collections.Counter()
    first_ms = last_ms = None
    exchange, readback = [], {}
    while (msg := log.recv_match()) is not None:
        mtype = msg.get_type()
        vehicle = msg.get_srcSystem() == 1
        if vehicle:
            counts[mtype] += 1
            if mtype == "ATTITUDE":
                first_ms = msg.time_boot_ms if first_ms is None else first_ms
                last_ms = msg.time_boot_ms
        if mtype in PROTOCOL:
            exchange.append(("vehicle" if vehicle else "gcs", mtype, getattr(msg, "seq", None)))
            if vehicle and mtype == "MISSION_ITEM_INT":
                readback[msg.seq] = _item(msg)
    span_s = (last_ms - first_ms) / 1000.0
    return {"rates": {k: counts[k] / span_s for k in STREAMS}, "exchange": exchange, "readback": [readback[i] for i in range(len(readback))]}


@pytest.fixture(scope="module")
def simulated():
    """The same mission uploaded to the simulator by our client, every message logged both ways,
    after asking for the streams the recording GCS asked for (the vehicle sends none unasked)."""
    sim = start_sim(speedup=20.0, boot_s=1.0)
    link = open_link(sim.addresses()[0])
    log: list[tuple[str, float, object]] = []
    vehicle_ms = [0]

    def listen(direction, _ns, msg):
        if hasattr(msg, "time_boot_ms"):
            vehicle_ms[0] = msg.time_boot_ms
        log.append((direction, vehicle_ms[0] / 1000.0, msg))

    link.add_listener(listen)
    try:
        ask_like_recorded_gcs(link)
        wait_ready(link)
        start = len(log)
        report = upload_and_verify(link, read_mission(REPLAYS / "calib-grid.waypoints").items, timeout_s=1.0)
        protocol = [("gcs" if d == "out" else "vehicle", m.get_type(), getattr(m, "seq", None)) for d, _t, m in log[start:] if m.get_type() in PROTOCOL]
        t0 = vehicle_ms[0] / 1000.0
        assert wait_until(lambda: vehicle_ms[0] / 1000.0 > t0 + 46.0, 15)
        window = [(t, m) for d, t, m in log if d == "in" and t0 + 5 <= t < t0 + 45]
    finally:
        link.close()
        sim.stop()
    counts = collections.Counter(m.get_type() for _t, m in window)
    return {"rates": {k: counts[k] / 40.0 for k in STREAMS}, "exchange": protocol, "readback": list(report.readback)}


def test_telemetry_rates_match_the_recording(recorded, simulated):
    for name in STREAMS:
        assert simulated["rates"][name] == pytest.approx(recorded["rates"][name], rel=0.08), name
    assert recorded["rates"]["ATTITUDE"] == pytest.approx(10.0, rel=0.01)


def test_mission_protocol_exchange_matches_the_recording(recorded, simulated):
    assert len(recorded["exchange"]) == 1 + 75 * 2 + 1 + 1 + 1 + 75 * 2 + 1
    assert simulated["exchange"] == recorded["exchange"]


def test_readback_matches_the_recorded_vehicle_except_its_home(recorded, simulated):
    assert simulated["readback"][1:] == recorded["readback"][1:]
    # the recorded vehicle put its own home (584.09 m) in slot 0; ours is its configured home
    assert recorded["readback"][0].z == pytest.approx(584.09, abs=0.01)
    assert simulated["readback"][0].z == pytest.approx(584.0)
