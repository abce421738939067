"""``dronecal-field import`` on the recorded ArduCopter SITL flights, and its clock logic."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from dronecal_field.cli import main
from dronecal_field.errors import InputError
from dronecal_field.runfile.importer import (
    MissionItem,
    boot_segments,
    fit_clock,
    gnss_covariance,
    hover_windows,
    import_run,
    parse_iso8601_ns,
    read_dataflash,
    read_tlog,
)
from dronecal_field.runfile.reader import open_run
from dronecal_field.runfile.records import MarkerSpec
from conftest import REPLAYS, needs_replays

MARKER = MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3, offset_frd_m=(0.0, 0.0, 0.1))


def _checks(name: str) -> dict:
    return json.loads((REPLAYS / f"{name}.checks.json").read_text())


@pytest.fixture(scope="module")
def rtk_log():
    return read_tlog(REPLAYS / "calib-grid-rtk.tlog")


def _write_video(path: Path, n: int, fps: float = 10.0) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (160, 120))
    for i in range(n):
        writer.write(np.full((120, 160, 3), 10 * i, np.uint8))
    writer.release()


# --- the SITL recordings ------------------------------------------------------------


@needs_replays
def test_rtk_tlog_hover_windows_match_the_checks(rtk_log):
    """70 grid holds of 3.0 s ending at MISSION_ITEM_REACHED, on the vehicle clock (speedup 5 undone)."""
    expected = {seq: t for seq, t, _ in _checks("calib-grid-rtk")["reached"] if 4 <= seq <= 73}
    hovers = rtk_log.hovers
    assert [int(h.metadata["seq"]) for h in hovers] == list(range(4, 74))
    clock = rtk_log.clocks[0]
    assert clock.method == "system_time" and clock.samples == 589
    for h in hovers:
        assert h.type == "hover" and h.duration_ns == 3_000_000_000
        assert float(h.metadata["hold_s"]) == 3.0
        # checks.json rounds SITL seconds to 0.01 s
        assert clock.to_boot_s(h.end_ns) == pytest.approx(expected[int(h.metadata["seq"])], abs=0.006)
    # The 8-byte record stamps ran 5.01x faster than the vehicle (README), the windows did not.
    assert rtk_log.host_seconds_per_vehicle_second == pytest.approx(1 / 5.014, rel=0.01)
    first = hovers[0]
    assert float(first.metadata["lat"]) == pytest.approx(-35.3632249) and float(first.metadata["alt"]) == 1.5
    assert first.metadata["frame"] == "6"


@needs_replays
def test_rtk_tlog_fixes_and_clock(rtk_log):
    checks = _checks("calib-grid-rtk")
    assert len(rtk_log.fixes) == checks["fix_type_counts"]["6"] == 2938
    assert rtk_log.skipped_no_fix == 38  # fix_type 0 x37 and 1 x1 during boot
    assert {f.fix_type for f in rtk_log.fixes} == {"rtk_fixed"}
    assert rtk_log.altitude_datum == "ellipsoid" and rtk_log.position_source == "GPS_RAW_INT"
    np.testing.assert_allclose(rtk_log.fixes[0].covariance_enu, np.diag([0.09, 0.09, 0.09]))  # h_acc = v_acc = 300 mm
    # SYSTEM_TIME's UTC at boot: first sample minus its boot time, within the fit residual.
    st = checks["system_time"]
    clock = rtk_log.clocks[0]
    assert clock.rate == pytest.approx(1.0, abs=1e-6) and clock.residual_ms < 1.0
    stamps = [f.timestamp_ns for f in rtk_log.fixes]
    assert stamps == sorted(stamps)
    span_s = (stamps[-1] - stamps[0]) / 1e9
    assert span_s == pytest.approx(598.0 - 10.06, abs=0.5)  # vehicle seconds, not the 119 s of record time
    first_st = next(m for m in rtk_log.messages if m.name == "SYSTEM_TIME" and m.fields["time_unix_usec"] > 0)
    assert first_st.fields["time_unix_usec"] == st["unix_first"]
    assert clock.to_utc_ns(first_st.fields["time_boot_ms"] * 1_000_000) == pytest.approx(st["unix_first"] * 1000, abs=1e6)
    assert first_st.time_ns == clock.to_utc_ns(first_st.fields["time_boot_ms"] * 1_000_000)
    names = {m.name for m in rtk_log.messages}
    assert len(rtk_log.messages) == 54106 and {"MISSION_ITEM_INT", "SIMSTATE", "STATUSTEXT"} <= names


@needs_replays
def test_gpsloss_tlog():
    log = read_tlog(REPLAYS / "calib-grid-gpsloss.tlog")
    expected = {seq: t for seq, t, _ in _checks("calib-grid-gpsloss")["reached"] if seq >= 4}
    assert [int(h.metadata["seq"]) for h in log.hovers] == list(range(4, 23))
    for h in log.hovers:
        assert log.clocks[0].to_boot_s(h.end_ns) == pytest.approx(expected[int(h.metadata["seq"])], abs=0.006)
    assert len(log.fixes) == 960 and log.skipped_no_fix == 77  # 0 x37, 1 x40 (boot + 8 s outage)
    gap = max(b.timestamp_ns - a.timestamp_ns for a, b in zip(log.fixes, log.fixes[1:])) / 1e9
    assert gap == pytest.approx(185.45 - 177.45, abs=0.25)  # the outage, in vehicle seconds


@needs_replays
@pytest.mark.parametrize("name, n_holds", [("calib-grid-rtk", 70), ("calib-grid-gpsloss", 19)])
def test_dataflash_hover_windows(name, n_holds):
    log = read_dataflash(REPLAYS / f"{name}.BIN")
    expected = {seq: t for seq, t, _ in _checks(name)["reached"] if seq >= 4}
    assert [int(h.metadata["seq"]) for h in log.hovers] == list(range(4, 4 + n_holds))
    clock = log.clocks[0]
    assert clock.method == "gps_time" and clock.residual_ms < 1.0
    # DataFlash stamps the message when it is logged; the tlog's "last time_boot_ms seen" is a 10 Hz
    # stream tick on either side of it.
    errors = [expected[int(h.metadata["seq"])] - clock.to_boot_s(h.end_ns) for h in log.hovers]
    assert max(abs(e) for e in errors) <= 0.15
    assert all(h.duration_ns == 3_000_000_000 for h in log.hovers)
    assert log.altitude_datum == "ellipsoid" and {f.fix_type for f in log.fixes} == {"rtk_fixed"}
    np.testing.assert_allclose(log.fixes[0].covariance_enu, np.diag([0.09, 0.09, 0.09]), rtol=1e-6)
    assert len(log.attitudes) > 1000


@needs_replays
def test_dataflash_and_tlog_share_one_utc(rtk_log):
    bin_log = read_dataflash(REPLAYS / "calib-grid-rtk.BIN")
    # Same flight, two clocks: SYSTEM_TIME in the tlog, GPS week/ms in the log; they agree to tens of ms.
    by_seq = {h.metadata["seq"]: h.end_ns for h in rtk_log.hovers}
    diffs = [(by_seq[h.metadata["seq"]] - h.end_ns) / 1e9 for h in bin_log.hovers]
    assert len(diffs) == 70 and abs(np.median(diffs)) <= 0.05 and max(np.abs(diffs)) <= 0.15


# --- the command, end to end -------------------------------------------------------------


@needs_replays
def test_import_command_end_to_end(tmp_path, capsys):
    video = tmp_path / "camera.mp4"
    _write_video(video, 20, fps=10.0)
    out = tmp_path / "run.mcap"
    code = main([
        "import", "--tlog", str(REPLAYS / "calib-grid-gpsloss.tlog"), "--video", str(video),
        "--video-start", "2026-11-22T03:20:00.500Z", "--marker-dictionary", "DICT_4X4_50",
        "--marker-id", "3", "--marker-size", "0.3", "--marker-offset", "0.1,0,0.2", "--out", str(out),
    ])
    assert code == 0
    printed = capsys.readouterr().out
    assert "hovers   19" in printed and "frames   20 of 160x120" in printed
    start = parse_iso8601_ns("2026-11-22T03:20:00.500Z")
    with open_run(out) as run:
        md = run.metadata
        assert (md.width, md.height, md.marker.marker_id, md.marker.offset_frd_m) == (160, 120, 3, (0.1, 0.0, 0.2))
        assert md.altitude_datum == "ellipsoid" and md.extra["import.log_kind"] == "tlog"
        assert [f.timestamp_ns - start for f in run.iter_frames()] == [i * 100_000_000 for i in range(20)]
        assert sum(1 for _ in run.iter_fixes()) == 960
        events = list(run.iter_events())
        assert [e.metadata["seq"] for e in events] == [str(s) for s in range(4, 23)]
        reached = list(run.iter_mavlink({"MISSION_ITEM_REACHED"}))
        assert len(reached) == 21 and reached[0][2]["_sysid"] == 1
        assert sum(1 for _ in run.iter_attitude()) == 2073
        report = json.loads(run.attachment("import_report.json"))
        assert report["hovers"] == 19 and report["clocks"][0]["method"] == "system_time"
        assert run.attachment("mission.waypoints").decode().splitlines()[5].split("\t")[3] == "16"


@needs_replays
def test_import_dataflash_without_video(tmp_path):
    out = tmp_path / "bin.mcap"
    log = read_dataflash(REPLAYS / "calib-grid-gpsloss.BIN")
    report = import_run(out, log, MARKER, image_size=(1920, 1080))
    assert report.frames == 0 and report.hovers == 19
    with open_run(out) as run:
        assert (run.metadata.width, run.metadata.height) == (1920, 1080)
        assert sum(1 for _ in run.iter_fixes()) == len(log.fixes) == report.fixes
        assert "/dataflash/CMD" in run.topics and run.topics["/dataflash/CMD"] == "dataflash.CMD"


@needs_replays
def test_video_start_defaults_to_first_fix_with_warning(tmp_path):
    from dronecal_field.runfile.importer import FlightLog

    video = tmp_path / "c.mp4"
    _write_video(video, 3)
    base = read_dataflash(REPLAYS / "calib-grid-gpsloss.BIN")
    report = import_run(tmp_path / "r.mcap", base, MARKER, video=video)
    assert report.video_start_source == "first GNSS fix"
    assert report.video_start_ns == base.fixes[0].timestamp_ns
    assert any("--video-start" in w for w in report.warnings)
    assert isinstance(base, FlightLog)


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--marker-id", "0", "--marker-size", "0.3"], "needs --marker-dictionary"),
        (["--marker-dictionary", "DICT_9X9_1", "--marker-id", "0", "--marker-size", "0.3"], "not an OpenCV ArUco dictionary"),
        (["--marker-dictionary", "DICT_4X4_50", "--marker-id", "0", "--marker-size", "0.3", "--video-start", "2026-01-01T00:00:00"], "has no time zone"),
    ],
)
def test_import_command_errors_exit_2(tmp_path, capsys, extra, message):
    code = main(["import", "--tlog", str(tmp_path / "missing.tlog"), "--out", str(tmp_path / "o.mcap"), *extra])
    assert code == 2
    assert message in capsys.readouterr().err


# --- a synthetic tlog: no SYSTEM_TIME, host clock at speedup 2 ---------------------------


def test_tlog_without_system_time_keeps_vehicle_durations(tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as mav2

    from dronecal_field.runfile.tlog import TlogWriter

    vehicle = mav2.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = mav2.MAVLink(None, srcSystem=255, srcComponent=190)
    host0_us = 1_700_000_000_000_000
    path = tmp_path / "fast.tlog"

    def host(boot_ms: float) -> int:  # the host clock runs at half the vehicle's time: speedup 2
        return host0_us + int(boot_ms * 1000 / 2)

    with TlogWriter(path) as t:
        t.write(mav2.MAVLink_mission_count_message(1, 1, 3, 0).pack(gcs), host(0))
        for seq, hold in ((0, 0.0), (1, 2.0), (2, 4.0)):
            item = mav2.MAVLink_mission_item_int_message(1, 1, seq, 6, 16, 0, 1, hold, 0, 0, 0, -353632249 + seq, 1491651970, 1.5, 0)
            t.write(item.pack(gcs), host(1))
        for k in range(0, 200):  # 20 s of vehicle time at 10 Hz
            boot_ms = 1000 + k * 100
            if k % 10 == 0:
                t.write(mav2.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(vehicle), host(boot_ms))
            att = mav2.MAVLink_attitude_message(boot_ms, 0.0, 0.0, 1.0, 0, 0, 0)
            t.write(att.pack(vehicle), host(boot_ms))
            if k % 2 == 0:
                gps = mav2.MAVLink_gps_raw_int_message(boot_ms * 1000 - 50_000, 3, -353632249, 1491651970, 586000, 80, 120, 0, 0, 12, 0, 0, 0, 0, 0)
                t.write(gps.pack(vehicle), host(boot_ms))
            if boot_ms == 8000:
                t.write(mav2.MAVLink_mission_item_reached_message(1).pack(vehicle), host(boot_ms) + 300)
            if boot_ms == 15000:
                t.write(mav2.MAVLink_mission_item_reached_message(2).pack(vehicle), host(boot_ms) + 300)
    log = read_tlog(path)
    clock = log.clocks[0]
    assert clock.method == "host_clock"
    assert clock.utc_at_boot_ns == host0_us * 1000 + 500_000_000 - 1_000_000_000  # anchored at the first ATTITUDE
    assert [(h.metadata["seq"], clock.to_boot_s(h.timestamp_ns), clock.to_boot_s(h.end_ns)) for h in log.hovers] == [
        ("1", pytest.approx(6.0), pytest.approx(8.0)),
        ("2", pytest.approx(11.0), pytest.approx(15.0)),
    ]
    assert log.host_seconds_per_vehicle_second == pytest.approx(0.5)
    assert log.altitude_datum == "msl" and len(log.fixes) == 100
    assert clock.to_boot_s(log.fixes[0].timestamp_ns) == pytest.approx(0.95)  # time_usec is the fix time
    # no h_acc/v_acc: HDOP 0.8 x 3 m for a 3D fix, approximated
    np.testing.assert_allclose(np.diag(log.fixes[0].covariance_enu), [2.4**2, 2.4**2, 3.6**2])
    assert any("SYSTEM_TIME" in w for w in log.warnings) and any("mean sea level" in w for w in log.warnings)


# --- pure helpers ---------------------------------------------------------------------


def test_fit_clock_recovers_drift_and_ignores_outliers():
    rng = np.random.default_rng(3)
    boot = np.arange(0, 600e9, 1e9)
    utc = 1.7e18 + boot * (1 + 20e-6) + rng.normal(0, 0.3e6, boot.size)
    utc[100] += 5e9  # one bad pair (a GPS time jump)
    clock = fit_clock(boot.astype(np.int64), utc.astype(np.int64), "system_time")
    assert clock.rate == pytest.approx(1 + 20e-6, abs=1e-7)
    assert clock.samples == 599 and clock.residual_ms < 0.5
    assert abs(clock.to_utc_ns(300e9) - (1.7e18 + 300e9 * (1 + 20e-6))) < 0.2e6
    short = fit_clock(np.array([5_000_000_000]), np.array([1_700_000_005_000_000_000]), "x")
    assert (short.rate, short.utc_at_boot_ns) == (1.0, 1_700_000_000_000_000_000)


def test_boot_segments_split_at_reboot():
    boot = np.array([1000, 2000, 1900, 3000, 50_000, 60_000, 500, 1500, 2500])
    assert boot_segments(boot).tolist() == [0, 0, 0, 0, 0, 0, 1, 1, 1]


def test_hover_windows_table():
    mission = {
        2: MissionItem(seq=2, command=178, frame=2, param1=1.0, lat_deg=0, lon_deg=0, alt_m=0),
        4: MissionItem(seq=4, command=16, frame=6, param1=3.0, lat_deg=-35.1, lon_deg=149.2, alt_m=1.5),
        5: MissionItem(seq=5, command=16, frame=6, param1=0.0, lat_deg=-35.1, lon_deg=149.2, alt_m=1.5),
        6: MissionItem(seq=6, command=19, frame=3, param1=2.5, lat_deg=-35.1, lon_deg=149.2, alt_m=2.5),
    }
    reached = [(2, 10), (4, 10_000_000_000), (4, 11_000_000_000), (5, 12_000_000_000), (6, 20_000_000_000), (9, 1)]
    ev = hover_windows(reached, mission)
    assert [(e.metadata["seq"], e.timestamp_ns, e.duration_ns) for e in ev] == [
        ("4", 7_000_000_000, 3_000_000_000),
        ("6", 17_500_000_000, 2_500_000_000),
    ]


@pytest.mark.parametrize(
    "args, diag",
    [
        ((0.3, 0.4), [0.09, 0.09, 0.16]),
        ((0.0, 0.0, 1.2, 2.0, "rtk_fixed"), [(1.2 * 0.02) ** 2, (1.2 * 0.02) ** 2, (2.0 * 0.02) ** 2]),
        ((None, None, 1.0, None, "3d"), [9.0, 9.0, 20.25]),
        ((None, None, None, None, "3d"), None),
    ],
)
def test_gnss_covariance_table(args, diag):
    cov = gnss_covariance(*args)
    if diag is None:
        assert cov is None
    else:
        np.testing.assert_allclose(np.diag(cov), diag)


def test_parse_iso8601():
    assert parse_iso8601_ns("1970-01-01T00:00:01.25Z") == 1_250_000_000
    assert parse_iso8601_ns("1970-01-01T02:00:00+02:00") == 0
    with pytest.raises(InputError, match="not ISO 8601"):
        parse_iso8601_ns("yesterday")


@needs_replays
@pytest.mark.parametrize("fmt,ext", [("h265", "mkv")])  # H.264 in MP4 (avcC): tests/test_video_packets.py
def test_import_of_an_nvr_export_writes_camera_video_without_reencoding(tmp_path, capsys, fmt, ext):
    from test_video_packets import encode_clip

    from dronecal_field.video.packets import open_packet_source

    video = tmp_path / f"nvr.{ext}"
    encode_clip(video, fmt, n=25, size=(160, 128), gop=10, fps=25)
    source = open_packet_source(str(video))
    expected = []
    while (f := source.read(timeout_s=5.0)) is not None:
        expected.append(f.data)
    source.close()
    out = tmp_path / "run.mcap"
    code = main([
        "import", "--tlog", str(REPLAYS / "calib-grid-gpsloss.tlog"), "--video", str(video), "--max-fps", "5",
        "--video-start", "2026-11-22T03:20:00.500Z", "--marker-dictionary", "DICT_4X4_50",
        "--marker-id", "3", "--marker-size", "0.3", "--out", str(out),
    ])
    assert code == 0
    assert "frames   25 of 160x128" in capsys.readouterr().out
    start = parse_iso8601_ns("2026-11-22T03:20:00.500Z")
    with open_run(out) as run:
        assert run.video and "/camera/image" not in run.topics and run.metadata.extra["camera.clock"] == "file"
        frames = list(run.iter_frames())
        report = json.loads(run.attachment("import_report.json"))
    assert [f.format for f in frames] == [fmt] * 25
    assert [f.data for f in frames] == expected  # the stream as it was, access unit by access unit
    assert [f.timestamp_ns - start for f in frames] == [i * 40_000_000 for i in range(25)]
    assert any("--max-fps 5 ignored" in w for w in report["warnings"])
    # --video-reencode stores JPEG frames instead.
    out2 = tmp_path / "jpeg.mcap"
    assert main([
        "import", "--tlog", str(REPLAYS / "calib-grid-gpsloss.tlog"), "--video", str(video), "--video-reencode",
        "--video-start", "2026-11-22T03:20:00.500Z", "--marker-dictionary", "DICT_4X4_50", "--marker-id", "3",
        "--marker-size", "0.3", "--out", str(out2),
    ]) == 0
    with open_run(out2) as run:
        assert not run.video and {f.format for f in run.iter_frames()} == {"jpeg"}
