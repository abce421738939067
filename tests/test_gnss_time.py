"""GNSS fixes are told apart by their own time, not their position (issue 14).

Real ArduCopter 4.7 (shared/replays/arducopter-sitl, ``fly-calib-t1.tlog``):
GPS at 5 Hz under a 10 Hz stream, each fix about 104 ms older than its
message, and hundreds of genuinely new fixes at exactly the position before
them during holds. ``calibrate`` must keep those; ``fly`` must stamp each fix at
its own time and write it once.
"""

from __future__ import annotations

import json
import socket
import threading
import time

import numpy as np
import pytest

from conftest import REPLAYS, needs_replays
from contract_writer import ORIGIN, MarkerLook, RunSpec, grid_waypoints, make_flight, pole_camera, write_run
from dronecal_field.pipeline.fixes import distinct_fixes
from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run
from dronecal_field.recording.recorder import FixClock

WIDE_GRID = dict(east_m=(-3.0, 0.0, 3.0), north_m=(5.0, 8.0, 11.0), up_m=(1.0, 3.0, 5.0))


@pytest.mark.parametrize(
    "t, pos, raw, arrival, rule, keep",
    [
        # the contract: one message per fix, equal positions are still fixes
        ([0, 200, 400, 400], [1, 1, 1, 1], None, False, "fix time", [1, 1, 1, 0]),
        # arrival stamps and the raw time_usec: a repeat has the same position AND time_usec
        ([0, 100, 200, 300], [1, 1, 1, 1], [5, 5, 6, 6], False, "position and GPS_RAW_INT.time_usec", [1, 0, 1, 0]),
        # arrival stamps declared, nothing else: position alone (a still hover's fixes are lost)
        ([0, 100, 200, 300], [1, 1, 1, 2], None, True, "position", [1, 0, 0, 1]),
    ],
)
def test_fix_identity_rules(t, pos, raw, arrival, rule, keep):
    lla = np.c_[np.array(pos, float) * 1e-7 - 35.0, np.full(len(pos), 149.0), np.full(len(pos), 600.0)]
    out = distinct_fixes(np.array(t, np.int64) * 1_000_000, lla, None if raw is None else np.array(raw), arrival_stamped=arrival)
    assert out.rule == rule
    assert out.keep.astype(int).tolist() == keep
    assert out.n_repeats == keep.count(0)


def test_a_stream_repeating_fixes_while_moving_is_recognised():
    # 5 Hz fixes sent twice under later stamps while the drone moves at 2 m/s: no real
    # new fix keeps its position while the track moves 40 cm, so the stream repeats.
    t = np.arange(40, dtype=np.int64) * 100_000_000
    north = 2.0 * (t // 200_000_000) * 0.2  # metres: a new position every 200 ms
    lla = np.c_[-35.0 + north / 111_320.0, np.full(40, 149.0), np.full(40, 600.0)]
    out = distinct_fixes(t, lla)
    assert out.rule == "position" and out.n_repeats == 20 and out.keep.sum() == 20


@needs_replays
def test_ardupilot_tlog_fixes_are_told_apart_by_time():
    from dronecal_field.runfile.importer import read_tlog

    log = read_tlog(REPLAYS / "fly-calib-t1.tlog")
    raw = [m for m in log.messages if m.name == "GPS_RAW_INT" and m.src_system == log.vehicle_system and m.fields["fix_type"] >= 2]
    usec = np.array([m.fields["time_usec"] for m in raw])
    pos = np.array([[m.fields["lat"], m.fields["lon"], m.fields["alt_ellipsoid"]] for m in raw])
    new = np.r_[True, np.diff(usec) != 0]
    n_new = int(new.sum())
    equal_new = int(np.sum(np.all(np.diff(pos[new], axis=0) == 0, axis=1)))
    # What the README reports of this flight: a 10 Hz stream of 5 Hz fixes, many new fixes at the old position.
    assert len(raw) == 3398 and n_new == 1700 and equal_new == 751
    assert np.median(np.diff(usec[new])) == 200_000  # 5 Hz

    # The importer stamps each fix at its own time: time alone tells them apart, and none is lost.
    t = np.array([f.timestamp_ns for f in log.fixes], np.int64)
    lla = np.array([[f.lat_deg, f.lon_deg, f.alt_m] for f in log.fixes])
    by_time = distinct_fixes(t, lla)
    assert (by_time.rule, int(by_time.keep.sum()), by_time.n_equal_position_kept) == ("fix time", n_new, equal_new)
    arrival = np.array([m.time_ns for m in raw], np.int64)
    assert np.median(arrival - t) == pytest.approx(104e6, abs=2e6)  # the fix is 104 ms older than its message

    # Arrival stamps with the raw time_usec: the same count.
    with_raw = distinct_fixes(arrival, pos * np.array([1e-7, 1e-7, 1e-3]), usec)
    assert int(with_raw.keep.sum()) == n_new and with_raw.n_equal_position_kept == equal_new
    # The old rule (position alone) loses every equal-position fix.
    by_position = distinct_fixes(arrival, pos * np.array([1e-7, 1e-7, 1e-3]), arrival_stamped=True)
    assert int(by_position.keep.sum()) == n_new - equal_new


def test_calibrate_keeps_equal_position_fixes_of_a_still_hover(tmp_path):
    # MAVLink-quantised fixes of a calm hover without receiver noise: many new fixes repeat the
    # position before them; each is a fix at its own time and every one is used.
    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints(**WIDE_GRID), drift_m=0.003, seed=5)
    spec = RunSpec(site_origin=ORIGIN, gnss_sigma_m=(0.0, 0.0, 0.0), quantise_fixes=True, gnss_hz=10.0)
    path = tmp_path / "still.mcap"
    write_run(path, camera, flight, MarkerLook(), spec)
    report = calibrate_run(path, CalibrateOptions(trials=0))
    written = report.track
    from dronecal_field.runfile.reader import open_run

    with open_run(path) as run:
        fixes = list(run.iter_fixes())
    lla = np.array([[f.lat_deg, f.lon_deg, f.alt_m] for f in fixes])
    equal = int(np.sum(np.all(np.diff(lla, axis=0) == 0, axis=1)))
    assert equal > 0.2 * len(fixes)  # the situation of the tlog
    assert report.fix_identity.rule == "fix time" and report.fix_identity.n_repeats == 0
    assert report.fix_identity.n_equal_position_kept == equal
    assert len(written.t_ns) == len(fixes)
    # Every hover point averages every fix of its settled part (10 Hz).
    t_fix = np.array([f.timestamp_ns for f in fixes], np.int64)
    for p in report.hover_points:
        a, b = p.stable_ns
        assert p.n_fixes == int(np.sum((t_fix >= a) & (t_fix <= b)))
    assert np.median([p.n_fixes for p in report.used_points]) >= 17  # 1.8 s at 10 Hz
    data = report.offset.to_dict()["gnss_fix_times"]
    assert data["rule"] == "fix time" and data["equal_position_fixes_kept"] == equal

    # The same run from a writer that declares arrival stamps (gnss.latency_s): fixes are
    # shifted back by the latency, and position alone tells them apart (fewer fixes).
    late = tmp_path / "late.mcap"
    write_run(late, camera, flight, MarkerLook(), RunSpec(**{**spec.__dict__, "gnss_latency_s": 0.1}))
    report_late = calibrate_run(late, CalibrateOptions(trials=0))
    assert report_late.fix_identity.rule == "position" and report_late.gnss_latency_s == pytest.approx(0.1)
    assert len(report_late.track.t_ns) == len(fixes) - equal
    np.testing.assert_array_equal(np.isin(report_late.track.t_ns, written.t_ns), True)


def test_fix_clock_maps_boot_and_unix_fix_times():
    clock = FixClock()
    # Vehicle messages arrive 5-25 ms after their boot time; the host clock starts at 1e18.
    rng = np.random.default_rng(0)
    for k in range(50):
        boot_ms = 10_000 + 100 * k
        clock.observe(10**18 + boot_ms * 1_000_000 + int(rng.uniform(5e6, 25e6)), boot_ms)
    arrival = 10**18 + 15_000 * 1_000_000 + 12_000_000
    t = clock.to_run_ns(15_000_000 - 104_000, arrival)  # boot-time fix 104 ms before the last message
    assert abs(t - (10**18 + (15_000 - 104) * 1_000_000)) < 6_000_000  # within the smallest link delay
    clock.observe_system_time(1_700_000_000_000_000 + 15_000_000, 15_000)  # unix = boot + 1.7e15 us
    t_unix = clock.to_run_ns(1_700_000_000_000_000 + 15_000_000 - 104_000, arrival)
    assert t_unix == t
    assert clock.to_run_ns(0, arrival) == arrival and clock.fallbacks == 1  # no fix time: arrival
    assert clock.to_run_ns(5_000_000, arrival) == arrival  # ten seconds old: not this message's fix


def _raw_vehicle(peer: socket.socket, stop: threading.Event, sent: list) -> None:
    """ArduCopter's GPS timing over a real UDP socket: 10 Hz GPS_RAW_INT carrying 5 Hz fixes 104 ms
    old, the position repeated exactly by consecutive new fixes in a still hover."""
    from dronecal_field.mavlink.link import mavlink_dialect

    d = mavlink_dialect()
    mav = d.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = None
    while gcs is None and not stop.is_set():
        try:
            _, gcs = peer.recvfrom(65535)
        except TimeoutError:
            continue
    t0 = time.monotonic()
    k = 0
    while not stop.is_set():
        boot_ms = 20_000 + int((time.monotonic() - t0) * 1000)
        fix_ms = ((boot_ms - 104) // 200) * 200
        lat = -353632610 + (fix_ms // 800)  # a new position every 4th fix: 3 of 4 equal the one before
        if k % 10 == 0:
            peer.sendto(d.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3).pack(mav), gcs)
        peer.sendto(d.MAVLink_attitude_message(boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0).pack(mav), gcs)
        gps = d.MAVLink_gps_raw_int_message(fix_ms * 1000, 6, lat, 1491652300, 584000, 70, 120, 0, 0, 18, alt_ellipsoid=604000, h_acc=10, v_acc=15)
        peer.sendto(gps.pack(mav), gcs)
        sent.append((time.time_ns(), fix_ms))
        k += 1
        time.sleep(0.1)


def test_recorder_writes_one_fix_per_fix_time_stamped_at_the_fix(tmp_path):
    from test_fly_recorder import MISSION
    from test_mavlink_support import MjpegServer

    from dronecal_field.mavlink.link import open_link
    from dronecal_field.recording.recorder import Recorder
    from dronecal_field.runfile.reader import open_run
    from dronecal_field.runfile.records import FORMAT_VERSION, MarkerSpec, RunMetadata
    from dronecal_field.runfile.writer import RunWriter
    from dronecal_field.video import open_video

    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    peer.settimeout(0.5)
    stop = threading.Event()
    sent: list = []
    vehicle = threading.Thread(target=_raw_vehicle, args=(peer, stop, sent), daemon=True)
    vehicle.start()
    camera = MjpegServer(fps=10)
    link = open_link(f"udp:127.0.0.1:{peer.getsockname()[1]}")
    video = open_video(camera.url)
    meta = RunMetadata(format_version=FORMAT_VERSION, width=640, height=480, marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3))
    out = tmp_path / "fixes.mcap"
    try:
        link.wait_heartbeat(5)
        time.sleep(0.5)  # a few ATTITUDE messages to map the boot clock
        recorder = Recorder(link, video, RunWriter(out, meta), None, MISSION).start()
        time.sleep(4.0)
        report = recorder.stop()
    finally:
        stop.set()
        video.close()
        link.close()
        camera.close()
        vehicle.join(timeout=2)
        peer.close()
    with open_run(out) as run:
        raw = [(t, f["time_usec"], f["lat"]) for _n, t, f in run.iter_mavlink({"GPS_RAW_INT"})]
        fixes = list(run.iter_fixes())
    usec = np.array([r[1] for r in raw])
    n_new = len(np.unique(usec))
    assert len(raw) >= 30 and n_new >= 15  # 10 Hz messages, 5 Hz fixes
    assert len(fixes) == report.fixes_written == n_new  # one message per fix
    assert report.fixes_repeated == len(raw) - n_new
    # Stamped at the fix's own time: about 104 ms (plus the interval since the fix) before arrival.
    first_arrival = {}
    for t, u, _ in raw:
        first_arrival.setdefault(u, t)
    lags_ms = np.array([(first_arrival[u] - f.timestamp_ns) / 1e6 for u, f in zip(sorted(first_arrival), fixes)])
    assert np.all(lags_ms > 90) and np.median(lags_ms) < 220
    assert np.allclose(np.diff([f.timestamp_ns for f in fixes]) / 1e6, 200, atol=15)  # fix times 200 ms apart
    # Equal positions, distinct fixes: calibrate's rule keeps every one.
    lla = np.array([[f.lat_deg, f.lon_deg, f.alt_m] for f in fixes])
    kept = distinct_fixes(np.array([f.timestamp_ns for f in fixes], np.int64), lla)
    assert kept.rule == "fix time" and int(kept.keep.sum()) == n_new and kept.n_equal_position_kept >= n_new // 2


def test_arrival_stamped_fixes_are_told_apart_by_the_raw_time_usec(tmp_path):
    # An older writer: each GPS_RAW_INT of a 10 Hz stream from a 5 Hz receiver becomes a /gnss/fix
    # stamped at its arrival, with the raw message beside it. Repeats (same time_usec) are left out;
    # new fixes at the position before them (a still hover, MAVLink quantisation) are kept.
    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints(**WIDE_GRID), drift_m=0.003, seed=5)
    spec = RunSpec(site_origin=ORIGIN, gnss_sigma_m=(0.0, 0.0, 0.0), quantise_fixes=True, repeat_fixes=2, with_gps_raw=True)
    path = tmp_path / "raw.mcap"
    write_run(path, camera, flight, MarkerLook(), spec)
    plain = tmp_path / "plain.mcap"
    write_run(plain, camera, flight, MarkerLook(), RunSpec(**{**spec.__dict__, "repeat_fixes": 1, "with_gps_raw": False}))
    report = calibrate_run(path, CalibrateOptions(trials=0))
    reference = calibrate_run(plain, CalibrateOptions(trials=0))
    assert report.fix_identity.rule == "position and GPS_RAW_INT.time_usec"
    assert report.fix_identity.n_repeats == len(reference.track.t_ns)  # every fix sent twice, once too many
    assert report.fix_identity.n_equal_position_kept == reference.fix_identity.n_equal_position_kept > 50
    assert len(report.track.t_ns) == len(reference.track.t_ns)
    assert [p.n_fixes for p in report.hover_points] == [p.n_fixes for p in reference.hover_points]
