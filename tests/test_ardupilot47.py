"""ArduPilot 4.7 on every link: the simulated vehicle against the figures recorded from ArduCopter
V4.7.0-dev SITL (shared/replays/arducopter-sitl README, "A second link, and `fly` itself against
this firmware", and fly-calib-t1.tlog), and the clients that must now ask for their telemetry.

Real sockets: the simulated vehicle on UDP, clients on their own links. Rates are counted per
vehicle second (the simulator runs 20x), never against the wall clock.
"""

from __future__ import annotations

import collections
import socket
import threading
import time

import numpy as np
import pytest

from dronecal_field.errors import InputError
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink.link import mavutil_module, open_link
from dronecal_field.sim.vehicle import SimVehicle, VehicleConfig
from test_mavlink_support import FAST_PARAMS, HOME, REPLAYS, ask_telemetry, wait_until

FLY_TLOG = REPLAYS / "fly-calib-t1.tlog"
UNASKED = {"HEARTBEAT", "TIMESYNC", "GPS_GLOBAL_ORIGIN", "HOME_POSITION"}  # what a silent link still gets (recorded)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _vehicle(out=(), listen=("udp:127.0.0.1:0",), speedup=20.0, boot_s=1.0, **kw) -> SimVehicle:
    """ArduPilot's defaults: GPS_RATE_MS 200, no stream-rate parameters set (unless ``kw`` says)."""
    config = VehicleConfig(home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2], speedup=speedup, boot_s=boot_s, params=FAST_PARAMS, **kw)
    return SimVehicle(config, listen=list(listen), out=list(out)).start()


class Counts:
    """Messages a link received, by type, with the vehicle time (s) each arrived at."""

    def __init__(self, link, sim: SimVehicle) -> None:
        self.sim = sim
        self.items: list[tuple[float, object]] = []
        self._lock = threading.Lock()
        link.add_listener(self._on)

    def _on(self, direction, _ns, msg) -> None:
        if direction == "in":
            with self._lock:
                self.items.append((self.sim.time_s, msg))

    def between(self, t0: float, t1: float) -> collections.Counter:
        with self._lock:
            return collections.Counter(m.get_type() for t, m in self.items if t0 <= t < t1)

    def of(self, mtype: str) -> list:
        with self._lock:
            return [m for _t, m in self.items if m.get_type() == mtype]


def _run_vehicle_seconds(sim: SimVehicle, seconds: float) -> tuple[float, float]:
    t0 = sim.time_s
    assert wait_until(lambda: sim.time_s >= t0 + seconds, seconds / sim.config.speedup * 4 + 10)
    return t0, sim.time_s


def test_a_listen_only_client_on_a_second_link_gets_only_heartbeat_and_co_until_it_asks():
    # Recorded on SERIAL1 (udpclient), 25 s after boot: HEARTBEAT 26, TIMESYNC 2, GPS_GLOBAL_ORIGIN 1,
    # HOME_POSITION 1, nothing else. Here the listener is the vehicle's second link (--out, like udpclient).
    port = _free_udp_port()
    listener = open_link(f"udpin:127.0.0.1:{port}", heartbeat_period_s=0)  # listen only: never speaks
    sim = _vehicle(out=[f"udp:127.0.0.1:{port}"])
    gcs = open_link(sim.addresses()[0])  # link 1: a GCS that asks for its telemetry
    try:
        seen = Counts(listener, sim)
        ask_telemetry(gcs)
        t0, t1 = _run_vehicle_seconds(sim, 25.0)
        counts = seen.between(0.0, t1)
        gcs_gpi = len([m for m in [gcs.latest("GLOBAL_POSITION_INT")] if m is not None])
    finally:
        gcs.close()
        listener.close()
        sim.stop()
    print(f"listen-only second link, {t1:.1f} vehicle s from boot: {dict(counts)}")
    assert set(counts) == UNASKED, counts  # no GLOBAL_POSITION_INT, ATTITUDE, GPS_RAW_INT, STATUSTEXT
    assert 0.9 * t1 <= counts["HEARTBEAT"] <= 1.1 * t1 + 1  # 1 Hz
    assert counts["GPS_GLOBAL_ORIGIN"] == 1 and counts["HOME_POSITION"] == 1
    assert 2 <= counts["TIMESYNC"] <= 4  # recorded: 2 in 25 s
    assert gcs_gpi == 1  # the GCS on link 1 got what it asked for: asking on one link opens no other


def test_after_asking_a_link_gets_the_asked_rates_and_the_other_link_keeps_its_own():
    sim = _vehicle(listen=("udp:127.0.0.1:0", "udp:127.0.0.1:0"))
    first, second = (open_link(url) for url in sim.addresses())
    try:
        c1, c2 = Counts(first, sim), Counts(second, sim)
        ask_telemetry(first)  # fly's set: GLOBAL_POSITION_INT and ATTITUDE at 10 Hz...
        second.wait_heartbeat(5)
        d = second.dialect
        assert second.command_long(ap.CMD_SET_MESSAGE_INTERVAL, (d.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 250_000)) == ap.MAV_RESULT_ACCEPTED
        second.send(d.MAVLink_request_data_stream_message(1, 1, d.MAV_DATA_STREAM_EXTRA1, 5, 1))  # ATTITUDE, SIMSTATE
        time.sleep(0.3)
        t0, t1 = _run_vehicle_seconds(sim, 20.0)
        n1, n2 = c1.between(t0, t1), c2.between(t0, t1)
        # the second link stops one message with -1; the first keeps it
        assert second.command_long(ap.CMD_SET_MESSAGE_INTERVAL, (d.MAVLINK_MSG_ID_ATTITUDE, -1)) == ap.MAV_RESULT_ACCEPTED
        time.sleep(0.2)
        t2, t3 = _run_vehicle_seconds(sim, 10.0)
        m1, m2 = c1.between(t2, t3), c2.between(t2, t3)
    finally:
        first.close()
        second.close()
        sim.stop()
    span = t1 - t0
    print(f"asked on link 2 (GPI 4 Hz, EXTRA1 5 Hz): {', '.join(f'{k} {n2[k] / span:.2f} Hz' for k in ('GLOBAL_POSITION_INT', 'ATTITUDE', 'SIMSTATE'))}; "
          f"link 1 (fly's set): {', '.join(f'{k} {n1[k] / span:.2f} Hz' for k in ('GLOBAL_POSITION_INT', 'ATTITUDE', 'GPS_RAW_INT', 'SIMSTATE'))}")
    assert n2["GLOBAL_POSITION_INT"] / span == pytest.approx(4.0, rel=0.1)
    assert n2["ATTITUDE"] / span == pytest.approx(5.0, rel=0.1) and n2["SIMSTATE"] / span == pytest.approx(5.0, rel=0.1)
    assert n2["GPS_RAW_INT"] == 0 and n2["SYS_STATUS"] == 0  # not asked on this link
    assert n1["GLOBAL_POSITION_INT"] / span == pytest.approx(10.0, rel=0.1) and n1["ATTITUDE"] / span == pytest.approx(10.0, rel=0.1)
    assert n1["SIMSTATE"] == 0  # the second link's REQUEST_DATA_STREAM changed nothing on the first
    assert m2["ATTITUDE"] == 0 and m2["SIMSTATE"] / (t3 - t2) == pytest.approx(5.0, rel=0.15)
    assert m1["ATTITUDE"] / (t3 - t2) == pytest.approx(10.0, rel=0.1)


def test_stream_rate_parameters_are_mavn_and_srn_does_nothing():
    # Recorded: with MAV2_POSITION 10, MAV2_EXTRA1 10, MAV2_EXT_STAT 2 the SERIAL1 listener got
    # GLOBAL_POSITION_INT, ATTITUDE and SIMSTATE at ~10 Hz (218 in 25 s), GPS_RAW_INT and SYS_STATUS at 2 Hz.
    port = _free_udp_port()
    listener = open_link(f"udpin:127.0.0.1:{port}", heartbeat_period_s=0)
    sim = _vehicle(out=[f"udp:127.0.0.1:{port}"], stream_params=(("MAV2_POSITION", 10), ("MAV2_EXTRA1", 10), ("MAV2_EXT_STAT", 2)))
    gcs = open_link(sim.addresses()[0])
    try:
        seen = Counts(listener, sim)
        gcs.wait_heartbeat(5)
        t0, t1 = _run_vehicle_seconds(sim, 20.0)
        t0 = max(t0, sim.config.boot_s)  # positions start when the origin is set
        counts = seen.between(t0 + 1.0, t1)
        gcs_saw = collections.Counter(m.get_type() for m in [gcs.latest(n) for n in ("GLOBAL_POSITION_INT", "ATTITUDE")] if m is not None)
        # SR1_* over MAVLink: unknown to 4.7, no PARAM_VALUE answer, no stream
        d = gcs.dialect
        with gcs.subscribe({"PARAM_VALUE"}) as sub:
            gcs.send(d.MAVLink_param_set_message(1, 1, b"SR0_POSITION", 10.0, 9))
            no_answer = sub.get(0.5)
            gcs.send(d.MAVLink_param_set_message(1, 1, b"MAV1_POSITION", 10.0, 9))
            answer = sub.get(1.0)
        time.sleep(0.3)
        gpi_after = gcs.wait_message({"GLOBAL_POSITION_INT"}, timeout_s=2.0)
    finally:
        gcs.close()
        listener.close()
        sim.stop()
    span = t1 - t0 - 1.0
    print(f"MAV2_POSITION 10, MAV2_EXTRA1 10, MAV2_EXT_STAT 2: {', '.join(f'{k} {counts[k] / span:.2f} Hz' for k in ('GLOBAL_POSITION_INT', 'ATTITUDE', 'SIMSTATE', 'GPS_RAW_INT', 'SYS_STATUS'))}")
    for name, hz in (("GLOBAL_POSITION_INT", 10), ("ATTITUDE", 10), ("SIMSTATE", 10), ("GPS_RAW_INT", 2), ("SYS_STATUS", 2)):
        assert counts[name] / span == pytest.approx(hz, rel=0.12), name
    assert not gcs_saw  # MAV2_* is the second link's: the first still streams nothing
    assert no_answer is None
    assert answer is not None and answer.param_id == "MAV1_POSITION" and answer.param_value == 10.0
    assert gpi_after is not None
    with pytest.raises(InputError, match="MAVn_"):
        SimVehicle(VehicleConfig(home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2], stream_params=(("SR1_POSITION", 10),)), listen=["udp:127.0.0.1:0"])


def _gps_figures(gps: list, gpi_before: list) -> dict:
    """Fix interval, lag of each new fix behind the GLOBAL_POSITION_INT of its tick, repeats, accuracy."""
    usec = np.array([m.time_usec for m in gps], np.int64)
    new = np.concatenate([[True], np.diff(usec) != 0])
    lag_ms = np.array([(g.time_boot_ms * 1000 - m.time_usec) / 1000.0 for m, g in zip(gps, gpi_before)])
    return {
        "interval_ms": float(np.median(np.diff(np.unique(usec)))) / 1000.0,
        "new_fraction": float(new.mean()),
        "lag_new_ms": float(np.median(lag_ms[new])),
        "lag_repeat_ms": float(np.median(lag_ms[~new])),
        "h_acc": sorted({m.h_acc for m in gps}),
        "v_acc": sorted({m.v_acc for m in gps}),
        "eph_epv": sorted({(m.eph, m.epv) for m in gps}),
    }


def _paired(messages) -> tuple[list, list]:
    """RTK-fixed GPS_RAW_INT messages and the GLOBAL_POSITION_INT received just before each (same tick)."""
    gps, gpi, last = [], [], None
    for m in messages:
        if m.get_type() == "GLOBAL_POSITION_INT":
            last = m
        elif m.get_type() == "GPS_RAW_INT" and m.fix_type == 6 and last is not None:
            gps.append(m)
            gpi.append(last)
    return gps, gpi


@pytest.mark.skipif(not FLY_TLOG.is_file(), reason="shared replays not mounted")
def test_gps_fixes_at_5_hz_104_ms_old_with_300_mm_as_recorded():
    log = mavutil_module().mavlink_connection(str(FLY_TLOG))
    recorded = []
    while (msg := log.recv_match()) is not None:
        if msg.get_srcSystem() == 1:
            recorded.append(msg)
    want = _gps_figures(*_paired(recorded))

    sim = _vehicle()  # ArduPilot's default GPS_RATE_MS 200
    link = open_link(sim.addresses()[0])
    try:
        seen = Counts(link, sim)
        ask_telemetry(link)  # fly's set: GPS_RAW_INT and GLOBAL_POSITION_INT at 10 Hz, as in the recording
        _run_vehicle_seconds(sim, 20.0)
        got = _gps_figures(*_paired([m for t, m in seen.items if t > sim.config.boot_s + 1.0]))
    finally:
        link.close()
        sim.stop()
    print(f"GPS recorded {want}\nGPS simulated {got}")
    assert want["interval_ms"] == 200.0 and got["interval_ms"] == pytest.approx(200.0, abs=1.0)
    assert want["new_fraction"] == pytest.approx(0.5, abs=0.03) and got["new_fraction"] == pytest.approx(0.5, abs=0.03)  # 10 Hz stream, 5 Hz fixes
    assert want["lag_new_ms"] == pytest.approx(104.0, abs=1.0) and got["lag_new_ms"] == pytest.approx(want["lag_new_ms"], abs=2.0)
    assert got["lag_repeat_ms"] == pytest.approx(want["lag_repeat_ms"], abs=2.0)  # 204 ms: the same fix a tick later
    assert want["h_acc"] == got["h_acc"] == [300] and want["v_acc"] == got["v_acc"] == [300]
    assert want["eph_epv"] == got["eph_epv"] == [(121, 200)]


def test_sim_camera_asks_for_its_telemetry_and_draws_the_true_position():
    """The camera listens on the vehicle's second link, which streams nothing unasked: it must ask, and
    it draws the vehicle where SIMSTATE says it is, not where the EKF (GLOBAL_POSITION_INT) thinks.
    The EKF error is made large here (0.5 m per axis) so the two cannot be confused."""
    from dronecal_field.sim.camera import SimCamera
    from dronecal_field.sim.scene import MarkerSpec, make_truth_camera

    truth = make_truth_camera(HOME, mount_height_m=3.0, azimuth_deg=0.0, tilt_deg=20.0, focal_px=500.0, width=320, height=240)
    camera = SimCamera(truth, MarkerSpec(), "udpin:127.0.0.1:0", serve_url="http://127.0.0.1:0/stream.mjpg", fps=2.0).start()
    _host, port = camera.mavlink_address
    sim = _vehicle(out=[f"udp:127.0.0.1:{port}"], ekf_sigma_m=0.5, ekf_tau_s=5.0)  # link 2 streams nothing unasked
    gcs = open_link(sim.addresses()[0])
    errors_camera, errors_ekf = [], []
    try:
        ask_telemetry(gcs)
        assert wait_until(lambda: sim.model.ready, 10)
        assert gcs.set_mode("GUIDED") == ap.MAV_RESULT_ACCEPTED
        assert gcs.command_long(ap.CMD_COMPONENT_ARM_DISARM, (1,)) == ap.MAV_RESULT_ACCEPTED
        assert gcs.command_long(ap.CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, 3.0)) == ap.MAV_RESULT_ACCEPTED
        assert wait_until(lambda: sim.model.position[2] > 2.9 and camera.position_source == "SIMSTATE", 20)
        for _ in range(10):  # hovering: sample the camera's pose against the truth and the EKF
            time.sleep(0.15)
            with sim._lock:
                true_enu = sim.model.position.copy()
                ekf_enu = true_enu + sim._ekf_error
            pose = camera.vehicle_pose(time.time_ns())
            errors_camera.append(float(np.linalg.norm(pose[0].antenna_enu_m[:2] - true_enu[:2])))
            errors_ekf.append(float(np.linalg.norm(ekf_enu[:2] - true_enu[:2])))
        camera_link = dict(sim.streams[id(sim.links[1])].streamed())
        first_link = dict(sim.streams[id(sim.links[0])].streamed())
    finally:
        gcs.close()
        sim.stop()
        camera.stop()
    print(f"sim camera: {camera.stream_requests} request rounds, drawn {np.median(errors_camera) * 100:.1f} cm from the truth (median), EKF {np.median(errors_ekf) * 100:.1f} cm off")
    assert camera.stream_requests >= 1 and camera.error is None
    assert camera_link["SIMSTATE"] == pytest.approx(0.1) and camera_link["GLOBAL_POSITION_INT"] == pytest.approx(0.1)
    assert camera_link["ATTITUDE"] == pytest.approx(0.1)
    assert "SIMSTATE" not in first_link  # the camera's requests stayed on its link
    assert np.median(errors_camera) < 0.03  # SIMSTATE: 1e-7 deg (1 cm) quantisation and hover wander
    assert np.median(errors_ekf) > 0.1  # what drawing GLOBAL_POSITION_INT would have been off by


def test_fly_beside_a_ground_station_on_another_link(tmp_path, capsys):
    """fly on link 1 while a GCS on link 2 watches at its own rates and, mid-flight, uploads its own
    mission: fly's requests stay on fly's link, the GCS's rates are untouched, fly never re-uploads
    and says the mission was changed."""
    import json

    from dronecal_field.cli import main
    from dronecal_field.mavlink.mission import send_mission
    from dronecal_field.mavlink.missionfile import parse_qgc_plan
    from dronecal_field.runfile.reader import open_run
    from test_mavlink_support import MjpegServer, plan_document, write_plan

    waypoints = [(-1.0, 4.0, 1.5), (0.0, 4.0, 1.5), (1.0, 4.0, 2.0)]
    plan = write_plan(tmp_path / "mission.plan", waypoints, hold_s=1.0)
    theirs = parse_qgc_plan(json.dumps(plan_document(waypoints + [(0.0, 3.0, 2.0)], hold_s=1.0)))  # one more point
    sim = _vehicle(listen=("udp:127.0.0.1:0", "udp:127.0.0.1:0"), gps_rate_ms=100.0)
    fly_url, gcs_url = sim.addresses()
    camera = MjpegServer(fps=10)
    gcs = open_link(gcs_url, source_component=230)  # another ground station (MAVProxy's component id)
    out = tmp_path / "run.mcap"
    result: dict = {}
    try:
        seen = Counts(gcs, sim)
        d = gcs.dialect
        ask_telemetry(gcs, (("GLOBAL_POSITION_INT", 4.0), ("ATTITUDE", 4.0), ("MISSION_CURRENT", 1.0)))  # the GCS's own choice
        flying = threading.Thread(
            target=lambda: result.update(rc=main(["fly", "--connect", fly_url, "--mission", str(plan), "--video", camera.url, "--out", str(out),
                                                  "--marker-size", "0.3", "--start", "--no-live", "--timeout-s", "120"])),
            daemon=True,
        )
        flying.start()
        assert wait_until(lambda: any(m.seq >= 5 for m in seen.of("MISSION_ITEM_REACHED")), 60)
        t_upload = sim.time_s
        send_mission(gcs, theirs.items, timeout_s=0.5)  # the pilot's ground station changes the mission
        flying.join(timeout=120)
        t_end = sim.time_s
        gcs_streams = dict(sim.streams[id(sim.links[1])].streamed())
        fly_streams = dict(sim.streams[id(sim.links[0])].streamed())
    finally:
        gcs.close()
        sim.stop()
        camera.close()
    captured = capsys.readouterr()
    assert result.get("rc") == 0, captured.err[-2000:]
    t_start = min(t for t, m in seen.items if m.get_type() == "MISSION_ITEM_REACHED")
    during = seen.between(t_start, t_end)
    span = t_end - t_start
    # the GCS's link kept the GCS's rates all flight; fly's asks (GPS 10 Hz, GPI 10 Hz) went to fly's link only
    assert during["GLOBAL_POSITION_INT"] / span == pytest.approx(4.0, rel=0.12)
    assert during["ATTITUDE"] / span == pytest.approx(4.0, rel=0.12)
    assert during["GPS_RAW_INT"] == 0 and during["SYS_STATUS"] == 0
    assert gcs_streams["GLOBAL_POSITION_INT"] == pytest.approx(0.25) and fly_streams["GLOBAL_POSITION_INT"] == pytest.approx(0.1)
    assert fly_streams["GPS_RAW_INT"] == pytest.approx(0.1)
    # both see the mission progress; fly noticed the other upload, said so, and did not upload again
    assert "MISSION CHANGED BY ANOTHER CLIENT" in captured.err and "fly did not re-upload" in captured.err
    reached_gcs = sorted({m.seq for m in seen.of("MISSION_ITEM_REACHED")})
    with open_run(out) as run:
        reached_fly = sorted({int(e.metadata["seq"]) for e in run.iter_events() if e.type == "hover"})
        fixes = list(run.iter_fixes())
        vehicle_sysid = run.metadata_record("dronecal.run")["vehicle.sysid"]
    tlog = mavutil_tlog(out.with_suffix(".tlog"))
    sent = [m for m in tlog if m.get_srcSystem() == 255 and m.get_srcComponent() == 190]
    # ArduPilot routes the GCS's HEARTBEAT to fly's link: fly hears it and still follows the vehicle
    assert any(m.get_type() == "HEARTBEAT" and (m.get_srcSystem(), m.get_srcComponent()) == (255, 230) for m in tlog)
    assert vehicle_sysid == "1"
    assert sum(m.get_type() == "MISSION_COUNT" for m in sent) == 1  # fly's one upload, before the flight
    assert {4, 5, 6} <= set(reached_fly) and {4, 5, 6, 7} <= set(reached_gcs)  # seq 7: the GCS's extra point, flown
    assert len(fixes) > 0.8 * 10 * (t_end - t_start)  # 10 Hz GNSS on fly's link
    print(f"fly beside a GCS: flight {t_end - t_start:.1f} vehicle s, GCS upload at {t_upload - t_start:.1f} s, "
          f"GCS GLOBAL_POSITION_INT {during['GLOBAL_POSITION_INT'] / span:.2f} Hz, fly fixes {len(fixes)} ({len(fixes) / span:.1f}/s), "
          f"reached fly {reached_fly} GCS {reached_gcs}")


def mavutil_tlog(path) -> list:
    log = mavutil_module().mavlink_connection(str(path))
    out = []
    while (msg := log.recv_match()) is not None:
        out.append(msg)
    return out


def test_an_upload_while_another_ground_station_uploads_is_refused_in_one_line():
    from dronecal_field.errors import MissionRejectedError
    from dronecal_field.mavlink.mission import upload_and_verify
    from test_mavlink_support import plan_document

    sim = _vehicle(listen=("udp:127.0.0.1:0", "udp:127.0.0.1:0"))
    fly_link, gcs = (open_link(url) for url in sim.addresses())
    try:
        ask_telemetry(gcs)
        ask_telemetry(fly_link)
        assert wait_until(lambda: sim.model.ready, 10)
        gcs.send(gcs.dialect.MAVLink_mission_count_message(1, 1, 10, 0))  # the GCS's upload starts (and stalls)
        assert gcs.wait_message({"MISSION_REQUEST"}, timeout_s=2.0) is not None
        import json

        from dronecal_field.mavlink.missionfile import parse_qgc_plan

        items = parse_qgc_plan(json.dumps(plan_document([(0.0, 4.0, 1.5)]))).items
        with pytest.raises(MissionRejectedError, match="another ground station is uploading") as err:
            upload_and_verify(fly_link, items, timeout_s=0.5)
    finally:
        fly_link.close()
        gcs.close()
        sim.stop()
    assert "\n" not in str(err.value)


def test_a_stream_the_vehicle_forgot_is_asked_for_again_on_this_link_only():
    """A rebooted ArduPilot forgets every SET_MESSAGE_INTERVAL: fly's StreamKeeper asks again while
    HEARTBEATs still come, and never while the streams flow."""
    from dronecal_field.mavlink.control import StreamKeeper
    from dronecal_field.sim.vehicle import LinkStreams

    sim = _vehicle(listen=("udp:127.0.0.1:0", "udp:127.0.0.1:0"))
    link, other = (open_link(url) for url in sim.addresses())
    try:
        ask_telemetry(link)
        ask_telemetry(other, (("ATTITUDE", 2.0),))
        keeper = StreamKeeper(link, min_silence_s=1.0)
        link.add_listener(keeper.feed)
        quiet = []
        for _ in range(8):  # streams flowing: nothing to ask
            time.sleep(0.25)
            quiet += keeper.check()
        with sim._lock:
            sim.streams[id(sim.links[0])] = LinkStreams()  # the vehicle forgot what this link asked for
        asked_again: list[str] = []
        assert wait_until(lambda: asked_again.extend(keeper.check()) or "GPS_RAW_INT" in asked_again, 5.0)
        t0 = sim.time_s
        assert wait_until(lambda: sim.time_s > t0 + 5.0, 5.0)
        restored = dict(sim.streams[id(sim.links[0])].streamed())
        other_streams = dict(sim.streams[id(sim.links[1])].streamed())
    finally:
        link.close()
        other.close()
        sim.stop()
    assert quiet == []
    assert {"GPS_RAW_INT", "GLOBAL_POSITION_INT", "ATTITUDE"} <= set(asked_again)
    assert restored["GPS_RAW_INT"] == pytest.approx(0.1) and restored["GLOBAL_POSITION_INT"] == pytest.approx(0.1)
    assert other_streams == {"ATTITUDE": pytest.approx(0.5)}  # the other link's choice untouched


def test_mission_watch_expects_our_own_flight_plan_text_once_whenever_it_comes():
    from dronecal_field.mavlink.link import mavlink_dialect
    from dronecal_field.mavlink.mission import MissionWatch

    d = mavlink_dialect()
    mav = d.MAVLink(None, srcSystem=1, srcComponent=1)

    def from_vehicle(msg):
        return d.MAVLink(None).parse_char(msg.pack(mav))

    text = from_vehicle(d.MAVLink_statustext_message(6, b"Flight plan received"))
    old_mission = from_vehicle(d.MAVLink_mission_current_message(0, 3, 2, 0))  # before our upload: 4 items
    ours = from_vehicle(d.MAVLink_mission_current_message(0, 9, 2, 0))  # ours: 10 items
    theirs = from_vehicle(d.MAVLink_mission_current_message(2, 11, 3, 1))
    watch = MissionWatch(10, vehicle_system=1)
    watch.feed("in", 0, old_mission)  # the vehicle's previous mission, seen during our upload: expected
    watch.uploaded()
    watch.feed("in", 0, text)  # our own text, arriving after the read-back (a fast simulator does that)
    watch.feed("in", 0, ours)
    assert not watch.changed and watch.describe() == ""
    watch.feed("in", 0, text)  # a second plan: someone else's
    watch.feed("in", 0, theirs)
    assert watch.changed and len(watch.changes) == 2
    assert "12 items, ours 10" in watch.describe() and "did not re-upload" in watch.describe()
