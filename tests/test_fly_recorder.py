"""The recorder's parts: a slow disk costs frames, never GNSS; pure conversions; the pre-flight table."""

from __future__ import annotations

import dataclasses

import json
import time

import numpy as np
import pytest

from dronecal_field.mavlink.link import mavlink_dialect, open_link
from dronecal_field.mavlink.missionfile import parse_qgc_plan
from dronecal_field.mavlink.preflight import GnssRateMeter, VehicleSnapshot, VideoStatus, evaluate_preflight, format_checklist
from dronecal_field.recording.recorder import Recorder
from dronecal_field.recording.status import RecorderStatus, VehicleClock, fix_from_gps_raw, format_status, hover_event, remaining_s
from dronecal_field.runfile.reader import open_run
from dronecal_field.runfile.records import FORMAT_VERSION, MarkerSpec, RunMetadata
from dronecal_field.runfile.writer import RunWriter
from dronecal_field.video import open_video
from test_mavlink_support import FAST_PARAMS, MjpegServer, plan_document, start_sim, wait_ready

MISSION = parse_qgc_plan(json.dumps(plan_document([(0.0, 4.0, 1.5), (1.0, 4.0, 1.5)], hold_s=3.0)))


class SlowDiskRunWriter(RunWriter):
    """The real RunWriter on a disk that needs 40 ms per frame."""

    def write_frame(self, frame):
        time.sleep(0.04)
        super().write_frame(frame)


def test_a_slow_disk_drops_frames_but_never_a_gnss_fix(tmp_path):
    sim = start_sim(speedup=5.0, boot_s=0.5)
    camera = MjpegServer(fps=60)
    link = open_link(sim.addresses()[0])
    video = open_video(camera.url)
    meta = RunMetadata(format_version=FORMAT_VERSION, width=640, height=480, marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3))
    out = tmp_path / "slow.mcap"
    try:
        link.wait_heartbeat(5)
        wait_ready(link)
        recorder = Recorder(link, video, SlowDiskRunWriter(out, meta), None, MISSION, frame_queue_size=4).start()
        time.sleep(2.5)
        report = recorder.stop()
    finally:
        video.close()
        link.close()
        camera.close()
        sim.stop()
    assert report.frames_dropped > 10  # 60 fps offered, about 25 fps written
    assert report.frames_written + report.frames_dropped + report.frames_dropped_source >= 100
    with open_run(out) as run:
        gps = [f for _n, _t, f in run.iter_mavlink({"GPS_RAW_INT"})]
        fixes = list(run.iter_fixes())
        frames = sum(1 for _ in run.iter_frames())
    assert len(gps) > 40 and len(fixes) == len(gps) == report.fixes_written
    assert frames == report.frames_written


def _gps(**kw):
    fields = dict(time_usec=0, fix_type=6, lat=-353632610, lon=1491652300, alt=584000, eph=70, epv=120, vel=0, cog=0, satellites_visible=18, alt_ellipsoid=604500, h_acc=10, v_acc=15, vel_acc=0, hdg_acc=0, yaw=0)
    fields.update(kw)
    return mavlink_dialect().MAVLink_gps_raw_int_message(**fields)


def test_fix_from_gps_raw_int_datums_and_covariance():
    fix = fix_from_gps_raw(_gps(), 123, "ellipsoid")
    assert (fix.timestamp_ns, fix.lat_deg, fix.lon_deg, fix.alt_m, fix.fix_type) == (123, pytest.approx(-35.363261), pytest.approx(149.16523), 604.5, "rtk_fixed")
    np.testing.assert_allclose(np.diag(fix.covariance_enu), [1e-4, 1e-4, 2.25e-4])
    assert fix_from_gps_raw(_gps(alt_ellipsoid=0), 1, "ellipsoid") is None  # no ellipsoidal height: not in this run's datum
    assert fix_from_gps_raw(_gps(alt_ellipsoid=0), 1, "msl").alt_m == 584.0
    assert fix_from_gps_raw(_gps(fix_type=1), 1) is None
    assert fix_from_gps_raw(_gps(h_acc=0, v_acc=0), 1).covariance_enu is None
    assert fix_from_gps_raw(_gps(fix_type=5), 1).fix_type == "rtk_float"


def test_vehicle_clock_rate():
    clock = VehicleClock()
    for i in range(30):
        clock.update(i * 100_000_000, 5000 + i * 1000)  # 1 vehicle s per 0.1 host s
    assert clock.rate == pytest.approx(10.0)
    clock.update(40 * 100_000_000, 200)  # reboot
    assert clock.rate == 1.0
    real = VehicleClock()
    for i in range(30):
        real.update(i * 100_000_000, i * 102)  # 2 % fast: a real autopilot and jitter
    assert real.rate == 1.0


def test_hover_window_ends_at_the_reached_message():
    event = hover_event(MISSION, 4, 10_000_000_000, clock_rate=2.0)
    assert (event.type, event.timestamp_ns, event.duration_ns, event.end_ns) == ("hover", 8_500_000_000, 1_500_000_000, 10_000_000_000)
    assert event.metadata["seq"] == "4" and float(event.metadata["hold_s"]) == 3.0 and float(event.metadata["vehicle_clock_rate"]) == 2.0
    assert hover_event(MISSION, 2, 1, 1.0) is None  # DO_CHANGE_SPEED has no hold
    assert remaining_s(MISSION, 4) == pytest.approx(3.0 + 1.0 / 2.0 + 3.0, rel=0.01)


def test_status_line():
    status = RecorderStatus(waypoint=3, waypoints=12, mode="AUTO", armed=True, fix="rtk_fixed", satellites=18, fps=29.8, frames=100, dropped=2, marker_seen=True, link_ok=False, video_ok=True, elapsed_s=62, remaining_s=190)
    assert format_status(status) == "wp 3/12 AUTO armed | rtk_fixed 18 sats | 29.8 fps 2 dropped | marker yes | 01:02 / ~03:10 left | LINK LOST"


GOOD = VehicleSnapshot(
    autopilot=3, vehicle_type=2, armed=False, mode_name="LOITER", fix_type=6, satellites=18, h_acc_m=0.01, ekf_flags=0x033F, ekf_max_variance=0.02,
    battery_pct=90, voltage_v=16.4, ready_to_arm=True, home_lat_deg=-35.363261, home_lon_deg=149.16523,
)
VIDEO = VideoStatus(url="http://cam/stream.mjpg", frames=30, fps=30.0, width=1920, height=1080)


@pytest.mark.parametrize(
    "change, min_fix, failing, warning",
    [
        ({}, "rtk_fixed", set(), set()),
        ({"fix_type": 5}, "rtk_fixed", {"gnss"}, set()),
        ({"fix_type": 5}, "rtk_float", set(), {"gnss"}),
        ({"fix_type": 3}, "rtk_float", {"gnss"}, set()),
        ({"autopilot": 0}, "rtk_fixed", {"heartbeat"}, set()),  # generic: neither ArduPilot nor PX4 (12 passes: tests/test_px4_fly.py)
        ({"armed": True}, "rtk_fixed", {"disarmed"}, set()),
        ({"ekf_flags": 0x0025}, "rtk_fixed", {"ekf"}, set()),
        ({"battery_pct": 12}, "rtk_fixed", {"battery"}, set()),
        ({"battery_pct": None}, "rtk_fixed", set(), {"battery"}),
        ({"ready_to_arm": False, "last_text": "PreArm: Throttle below failsafe"}, "rtk_fixed", {"ready_to_arm"}, set()),
        ({"home_lat_deg": -35.37}, "rtk_fixed", {"home"}, set()),  # 750 m south
    ],
)
def test_preflight_table(change, min_fix, failing, warning):
    snapshot = VehicleSnapshot(**{**GOOD.__dict__, **change})
    results = evaluate_preflight(snapshot, MISSION, VIDEO, min_fix=min_fix)
    assert [r.name for r in results] == ["heartbeat", "disarmed", "gnss", "ekf", "battery", "ready_to_arm", "home", "mission", "video"]
    assert {r.name for r in results if not r.ok} == failing
    assert {r.name for r in results if r.warning} == warning
    text = format_checklist(results)
    assert text.count("\n") == 8 and ("[WARN]" in text) == bool(warning)
    if "ready_to_arm" in failing:
        assert "Throttle below failsafe" in text


def _with_item(index: int, **change):
    items = list(MISSION.items)
    items[index] = dataclasses.replace(items[index], **change)
    return dataclasses.replace(MISSION, items=tuple(items))


WP = next(i for i, item in enumerate(MISSION.items) if item.command == 16 and item.seq > 0)


@pytest.mark.parametrize("mission, needle", [
    (_with_item(WP, x=0, y=0), "latitude 0, longitude 0"),
    (_with_item(WP, x=int(1e10 * 1e7)), "out of range"),
    (_with_item(WP, z=1e308), "outside -10..500"),
    (_with_item(WP, z=-50.0), "outside -10..500"),
    (_with_item(WP, z=float("inf")), "not a finite number"),
    (_with_item(WP, p1=float("inf")), "infinite"),
    (_with_item(WP, command=31999), "command 31999"),
    (_with_item(WP, frame=99), "frame 99"),
    (_with_item(WP, frame=1), "frame 1"),
    (dataclasses.replace(MISSION, items=MISSION.items + tuple(dataclasses.replace(MISSION.items[WP], seq=len(MISSION.items) + k) for k in range(10_003))),
     "more than the vehicle holds"),
])
def test_preflight_checks_every_item_it_will_upload(mission, needle):
    from dronecal_field.mavlink.preflight import check_mission_items

    assert check_mission_items(MISSION) == []
    problems = check_mission_items(mission)
    assert problems and needle in problems[0]
    results = evaluate_preflight(GOOD, mission, VIDEO)
    assert [r.name for r in results if not r.ok] == ["mission"]


def test_gnss_rate_counts_new_fixes_and_warns_below_8_hz():
    # A 10 Hz stream from a 5 Hz receiver repeats every fix, its time_usec included (ArduPilot 4.7);
    # a 10 Hz receiver does not. Consecutive fixes may share a position: still new fixes.
    mav = mavlink_dialect().MAVLink(None)
    rng = np.random.default_rng(0)
    rates = {}
    for receiver_hz in (5, 10):
        meter = GnssRateMeter()
        lat = lon = 0
        for k in range(40):  # 4 s of a 10 Hz stream
            if k % (10 // receiver_hz) == 0:
                lat, lon = -353632610 + int(rng.integers(-3, 4)), 1491652300 + int(rng.integers(-3, 4))
            alt = 584000 + (k // (10 // receiver_hz)) % 7
            fix_usec = 1_000_000 + (k - k % (10 // receiver_hz)) * 100_000
            meter.feed(mav.gps_raw_int_encode(fix_usec, 6, lat, lon, alt, 65535, 65535, 0, 0, 20, alt_ellipsoid=alt))
        rates[receiver_hz] = meter.rate_hz()
    assert rates[5] == pytest.approx(5.0, abs=0.6) and rates[10] == pytest.approx(10.0, abs=0.6)
    slow = evaluate_preflight(VehicleSnapshot(**{**GOOD.__dict__, "gnss_rate_hz": rates[5]}), MISSION, VIDEO)
    line = [r for r in slow if r.name == "gnss_rate"][0]
    assert line.ok and line.warning and "GPS_RATE_MS" in line.detail
    fast = evaluate_preflight(VehicleSnapshot(**{**GOOD.__dict__, "gnss_rate_hz": rates[10]}), MISSION, VIDEO)
    assert [(r.ok, r.warning) for r in fast if r.name == "gnss_rate"] == [(True, False)]
    assert GnssRateMeter().rate_hz() is None  # nothing measured: no line
    assert "gnss_rate" not in [r.name for r in evaluate_preflight(GOOD, MISSION, VIDEO)]


def test_preflight_video_without_frames_fails():
    results = evaluate_preflight(GOOD, MISSION, VideoStatus(url="rtsp://cam/1", frames=0))
    assert [r.detail for r in results if not r.ok] == ["rtsp://cam/1 opened but sent no frame; check the camera stream"]


def test_fly_records_leg_events_and_fixes_at_their_own_time(tmp_path, capsys):
    # A mission whose middle waypoints are flown through (hold 0): fly writes a "leg" event from
    # each waypoint reached to the next, and one /gnss/fix per new GPS_RAW_INT.time_usec stamped
    # at that time on the run clock.
    from dronecal_field.cli import main
    from test_mavlink_support import plan_document

    doc = plan_document([(-3.0, 5.0, 2.0), (3.0, 5.0, 2.0), (3.0, 8.0, 3.0), (-3.0, 8.0, 3.0)], hold_s=0.0, speed_mps=2.0)
    navs = [item for item in doc["mission"]["items"] if item["command"] == 16]
    navs[0]["params"][0] = 2.0  # hold at the first and the last waypoint only
    navs[-1]["params"][0] = 2.0
    plan = tmp_path / "legs.plan"
    plan.write_text(json.dumps(doc))
    # a snappy copter (1 m/s^2, WPNAV_JERK 10 m/s^3, no settle): the legs reach their 2 m/s, so their durations follow from length / speed
    sim = start_sim(speedup=5.0, boot_s=0.5, params=dataclasses.replace(FAST_PARAMS, wp_accel_mps2=1.0, wp_jerk_mps3=10.0, wp_settle_s=0.0))
    camera = MjpegServer(fps=15)
    out = tmp_path / "legs.mcap"
    try:
        rc = main(["fly", "--connect", sim.addresses()[0], "--mission", str(plan), "--video", camera.url, "--out", str(out), "--marker-size", "0.3", "--start"])
    finally:
        camera.close()
        sim.stop()
    assert rc == 0, capsys.readouterr().out[-2000:]
    with open_run(out) as run:
        events = [e for e in run.iter_events() if e.type == "leg"]
        hovers = [e for e in run.iter_events() if e.type == "hover"]
        raw = [(t, f["time_usec"]) for _n, t, f in run.iter_mavlink({"GPS_RAW_INT"}) if f["fix_type"] >= 2]
        fixes = list(run.iter_fixes())
    seqs = [(int(e.metadata["seq_from"]), int(e.metadata["seq_to"])) for e in events]
    first = int(navs[0]["doJumpId"])  # mission seq: the QGC items (numbered from 1) follow home (seq 0)
    assert seqs == [(first, first + 1), (first + 1, first + 2), (first + 2, first + 3)]
    assert len(hovers) == 2
    # Legs of 6, 3.2 and 6 m at 2 m/s (vehicle time) at a 5x speedup, end to end in time.
    rate = float(events[0].metadata["vehicle_clock_rate"])
    assert rate == pytest.approx(5.0, rel=0.1)
    durations = [e.duration_ns / 1e9 * rate for e in events]
    # (the first and last legs start or end at rest: ArduCopter's S-curve, its clock slowed while the vehicle lags, 4.4 and 6.2 s)
    assert durations[1] == pytest.approx(3.2 / 2.0, rel=0.35) and all(2.0 < d < 7.5 for d in (durations[0], durations[2]))
    assert all(b.timestamp_ns == pytest.approx(a.end_ns, abs=5e7) for a, b in zip(events, events[1:]))
    assert events[-1].end_ns <= hovers[-1].timestamp_ns + 5e7  # the leg ends where the last hold begins
    # One fix per time_usec, each stamped no later than the message that brought it.
    usec = np.array([u for _t, u in raw])
    assert len(fixes) == len(np.unique(usec))
    first_arrival = {}
    for t, u in raw:
        first_arrival.setdefault(u, t)
    lags = np.array([first_arrival[u] - f.timestamp_ns for u, f in zip(sorted(first_arrival), fixes)])
    assert np.all(lags >= 0) and np.median(lags) < 50e6


def test_a_step_of_the_recording_computers_clock_is_found_and_said_once():
    """The host clock steps +2 s (an NTP step) at message 200 of a 10 Hz stream with 0-60 ms link delays: one jump,
    of +2.0 s, where it happened; a link stall that delays one block of messages by 1.5 s is not a jump."""
    from dronecal_field.recording.status import ClockJumpMonitor

    rng = np.random.default_rng(4)
    t0 = 1_795_000_000_000_000_000
    boot_ms = np.arange(600) * 100
    host = t0 + boot_ms * 1_000_000 + rng.uniform(0, 60e6, 600).astype(np.int64)
    stalled = host.copy()
    stalled[120:160] += 1_500_000_000  # a whole block held up by the link, then back
    host[200:] += 2_000_000_000
    mon = ClockJumpMonitor()
    jumps = [j for h, b in zip(host, boot_ms) if (j := mon.observe(int(h), int(b))) is not None]
    assert len(jumps) == 1 and jumps[0][1] == pytest.approx(2.0, abs=0.07)
    assert abs(jumps[0][0] - host[200]) < 5e9  # the block where the clock stepped
    mon = ClockJumpMonitor()
    assert [j for h, b in zip(stalled, boot_ms) if (j := mon.observe(int(h), int(b))) is not None] == []
    # a sped-up simulator whose rate estimate settles from 1 to 2 (host - boot / rate moves by boot / 2): no jump
    fast = t0 + boot_ms * 500_000
    mon = ClockJumpMonitor()
    assert [j for k, (h, b) in enumerate(zip(fast, boot_ms)) if (j := mon.observe(int(h), int(b), 1.0 if k < 130 else 2.0)) is not None] == []
