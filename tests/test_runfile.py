"""Run file: write -> read round trips, contract checks, files from other writers."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from dronecal_field.errors import ContractError, InputError
from dronecal_field.geodesy import EnuOrigin
from dronecal_field.runfile.reader import open_run
from dronecal_field.runfile.records import (
    Attitude,
    Frame,
    GnssFix,
    MarkerSpec,
    RunEvent,
    RunMetadata,
)
from dronecal_field.runfile.writer import RunWriter

T0 = 1_795_315_761_000_000_000  # a UTC time in ns


def _meta(**kw) -> RunMetadata:
    base = dict(
        format_version=1,
        width=64,
        height=48,
        marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=7, size_m=0.3, offset_frd_m=(0.05, -0.02, 0.12)),
        altitude_datum="ellipsoid",
        camera_latency_s=0.085,
        site_origin=EnuOrigin(lat_deg=-35.363261, lon_deg=149.16523, h_m=584.0),
        extra={"recorder.version": "test"},
    )
    base.update(kw)
    return RunMetadata(**base)


def _jpeg(i: int) -> bytes:
    img = np.zeros((480, 640, 3), np.uint8)  # the size the metadata states
    cv2.putText(img, str(i), (5, 35), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (255, 255, 255), 2)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def _png(i: int) -> bytes:
    ok, buf = cv2.imencode(".png", np.full((48, 64), i, np.uint8))
    assert ok
    return buf.tobytes()


def _fix(i: int) -> GnssFix:
    cov = np.array([[4e-4, 1e-5, 0.0], [1e-5, 5e-4, 0.0], [0.0, 0.0, 9e-4]]) if i % 2 else np.diag([1e-4, 1e-4, 4e-4])
    return GnssFix(
        timestamp_ns=T0 + i * 200_000_000,
        lat_deg=-35.363261 + i * 1e-7,
        lon_deg=149.16523 - i * 2e-7,
        alt_m=585.5 + 0.01 * i,
        covariance_enu=cov if i % 3 else None,
        fix_type=("rtk_fixed", "rtk_float", None)[i % 3],
    )


def test_round_trip_every_record_type(tmp_path):
    path = tmp_path / "run.mcap"
    frames = [Frame(timestamp_ns=T0 + i * 33_333_333, format="png" if i % 5 == 0 else "jpeg", data=_png(i) if i % 5 == 0 else _jpeg(i)) for i in range(30)]
    fixes = [_fix(i) for i in range(5)]
    atts = [Attitude(timestamp_ns=T0 + i * 100_000_000, roll_rad=0.05 * i, pitch_rad=-0.03 * i, yaw_rad=-3.0 + 0.6 * i) for i in range(10)]
    events = [
        RunEvent(timestamp_ns=T0 + 100, duration_ns=3_000_000_000, type="hover", metadata={"seq": "4", "hold_s": "3.0", "lat": "-35.3", "lon": "149.1", "alt": "1.5"}),
        RunEvent(timestamp_ns=T0 + 200, duration_ns=0, type="link_lost"),
    ]
    with RunWriter(path, _meta()) as w:
        for i, f in enumerate(frames):
            w.write_frame(f)
            if i % 6 == 0:
                w.write_fix(fixes[i // 6])
        for a in atts:
            w.write_attitude(a)
        for e in events:
            w.write_event(e)
        w.write_mavlink("GPS_RAW_INT", T0 + 5, {"mavpackettype": "GPS_RAW_INT", "lat": -353632610, "eph": float("nan"), "raw": b"\x01\x02"})
        w.write_mavlink("HEARTBEAT", T0 + 6, {"type": 2})
        w.attach("mission.plan", b'{"fileType": "Plan"}', "application/json")
        w.write_site(EnuOrigin(lat_deg=1.0, lon_deg=2.0, h_m=3.0))

    with open_run(path) as run:
        assert not run.truncated
        md = run.metadata
        assert md == _meta(site_origin=EnuOrigin(lat_deg=1.0, lon_deg=2.0, h_m=3.0))  # the later site record wins
        assert md.marker.offset_frd_m == (0.05, -0.02, 0.12)
        assert md.camera_latency_s == 0.085
        got_frames = list(run.iter_frames())
        assert [f.timestamp_ns for f in got_frames] == [f.timestamp_ns for f in frames]
        assert all(g.data == f.data and g.format == f.format for g, f in zip(got_frames, frames))
        got_fixes = list(run.iter_fixes())
        assert len(got_fixes) == 5
        for g, f in zip(got_fixes, fixes):
            assert (g.timestamp_ns, g.lat_deg, g.lon_deg, g.alt_m, g.fix_type) == (f.timestamp_ns, f.lat_deg, f.lon_deg, f.alt_m, f.fix_type)
            if f.covariance_enu is None:
                assert g.covariance_enu is None
            else:
                np.testing.assert_array_equal(g.covariance_enu, f.covariance_enu)
        got_atts = list(run.iter_attitude())
        assert len(got_atts) == 10
        for g, a in zip(got_atts, atts):
            assert g.timestamp_ns == a.timestamp_ns
            assert g.roll_rad == pytest.approx(a.roll_rad, abs=1e-9)
            assert g.pitch_rad == pytest.approx(a.pitch_rad, abs=1e-9)
            assert np.angle(np.exp(1j * (g.yaw_rad - a.yaw_rad))) == pytest.approx(0.0, abs=1e-9)
        assert list(run.iter_events()) == events
        mav = list(run.iter_mavlink())
        assert mav[0] == ("GPS_RAW_INT", T0 + 5, {"lat": -353632610, "eph": None, "raw": [1, 2], "_time_unix_ns": T0 + 5})
        assert [m[0] for m in run.iter_mavlink({"HEARTBEAT"})] == ["HEARTBEAT"]
        assert run.attachment("mission.plan") == b'{"fileType": "Plan"}'
        assert run.attachment("nope") is None
        assert run.time_range_ns == (T0, T0 + 29 * 33_333_333)
        assert run.topics["/mavlink/GPS_RAW_INT"] == "mavlink.GPS_RAW_INT"


def test_attitude_from_mavlink_when_no_pose_topic(tmp_path):
    path = tmp_path / "run.mcap"
    with RunWriter(path, _meta()) as w:
        w.write_frame(Frame(timestamp_ns=T0, format="jpeg", data=_jpeg(0)))
        w.write_fix(_fix(0))
        for i in range(3):
            w.write_mavlink("ATTITUDE", T0 + i, {"time_boot_ms": i, "roll": 0.1 * i, "pitch": 0.2, "yaw": -1.0})
    with open_run(path) as run:
        atts = list(run.iter_attitude())
    assert [(a.timestamp_ns, a.roll_rad, a.pitch_rad, a.yaw_rad) for a in atts] == [
        (T0 + i, 0.1 * i, 0.2, -1.0) for i in range(3)
    ]


def test_windows_read_only_overlapping_chunks(tmp_path):
    """A 60 s run at 10 fps with 1 s chunks: two 1 s windows touch a handful of chunks, not all 60."""
    path = tmp_path / "run.mcap"
    jpg = _jpeg(1)
    # A tiny chunk size stands in for the writer's one-second chunks without a minute of wall time.
    with RunWriter(path, _meta(), chunk_size=10 * len(jpg), background_flush=False) as w:
        for i in range(600):
            w.write_frame(Frame(timestamp_ns=T0 + i * 100_000_000, format="jpeg", data=jpg))
            if i % 2 == 0:
                w.write_fix(_fix(i // 2))
    windows = [(T0 + 10_000_000_000, T0 + 11_000_000_000), (T0 + 40_000_000_000, T0 + 41_000_000_000)]
    with open_run(path) as run:
        assert run.units_total >= 55
        got = [f.timestamp_ns for f in run.iter_frames(windows)]
        assert got == [T0 + i * 100_000_000 for i in list(range(100, 111)) + list(range(400, 411))]
        # each window widened by LOG_TIME_SLACK_NS (1 s) on both sides: ~3 chunks + edges per window
        assert run.units_read <= 12 < run.units_total // 4


def test_metadata_missing_key_names_it(tmp_path):
    path = tmp_path / "run.mcap"
    meta = _meta(marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=3, size_m=None))
    with RunWriter(path, meta) as w:
        w.write_frame(Frame(timestamp_ns=T0, format="jpeg", data=_jpeg(0)))
        w.write_fix(_fix(0))
    with pytest.raises(ContractError, match=r"run.mcap: metadata 'dronecal.run' has no 'marker.size_m'"):
        open_run(path)


@pytest.mark.parametrize(
    "key, value, pattern",
    [
        ("format_version", None, "has no 'format_version'"),
        ("camera.width", "wide", "'camera.width' = 'wide' is not a decimal integer"),
        ("format_version", "2", "format_version 2 is newer"),
        ("marker.kind", "qr", "'marker.kind' = 'qr'"),
        ("marker.offset_frd_m", "1,2", "write three numbers"),
        ("gnss.altitude_datum", "geoid", "use 'ellipsoid' or 'msl'"),
    ],
)
def test_metadata_table_of_errors(key, value, pattern):
    run = _meta().to_mcap_metadata()
    if value is None:
        del run[key]
    else:
        run[key] = value
    with pytest.raises(ContractError, match=pattern):
        RunMetadata.from_mcap_metadata(run)


def test_led_marker_needs_no_dictionary():
    meta = RunMetadata(format_version=1, width=10, height=20, marker=MarkerSpec(kind="led"), altitude_datum="msl")
    back = RunMetadata.from_mcap_metadata(meta.to_mcap_metadata())
    assert back == meta
    assert back.altitude_datum == "msl" and back.camera_latency_s is None


def _raw_writer_file(path, topics, metadata=True, compression="lz4", fix_schema=None, summary_channels=False):
    """A run written with mcap's Writer and the foxglove protobuf classes directly, not RunWriter."""
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
    from google.protobuf.timestamp_pb2 import Timestamp
    from mcap.writer import CompressionType, IndexType, Writer
    from mcap_protobuf.schema import build_file_descriptor_set

    with open(path, "wb") as f:
        w = Writer(
            f,
            compression={"lz4": CompressionType.LZ4, "none": CompressionType.NONE}[compression],
            index_types=IndexType.CHUNK,  # no message/metadata/attachment indexes
            repeat_channels=summary_channels,  # with channels but no schemas in the summary, or neither
            repeat_schemas=False,
            use_statistics=False,
        )
        w.start()
        ids = {}
        # Fixes registered before images, unlike RunWriter.
        for topic, cls in (("/gnss/fix", LocationFix), ("/camera/image", CompressedImage)):
            if topic not in topics:
                continue
            name = fix_schema if (topic == "/gnss/fix" and fix_schema) else cls.DESCRIPTOR.full_name
            sid = w.register_schema(name=name, encoding="protobuf", data=build_file_descriptor_set(cls).SerializeToString())
            ids[topic] = w.register_channel(topic=topic, message_encoding="protobuf", schema_id=sid)
        for i in range(20):
            t = T0 + i * 50_000_000
            if "/gnss/fix" in ids and i % 4 == 0:
                msg = LocationFix(timestamp=Timestamp(seconds=t // 10**9, nanos=t % 10**9), latitude=-35.0 - i * 1e-6, longitude=149.0, altitude=600.0)
                w.add_message(ids["/gnss/fix"], log_time=t, data=msg.SerializeToString(), publish_time=t)
            if "/camera/image" in ids:
                # log time 30 ms after capture, as a recorder stamping on write would
                msg = CompressedImage(timestamp=Timestamp(seconds=t // 10**9, nanos=t % 10**9), format="jpeg", data=_jpeg(i))
                w.add_message(ids["/camera/image"], log_time=t + 30_000_000, data=msg.SerializeToString(), publish_time=t)
        if metadata:
            # Metadata at the end, as some writers do.
            w.add_metadata(
                "dronecal.run",
                {
                    "marker.size_m": "0.25",
                    "marker.offset_frd_m": "0,0,0.1",
                    "marker.id": "0",
                    "marker.dictionary": "DICT_5X5_100",
                    "marker.kind": "aruco",
                    "camera.height": "480",
                    "camera.width": "640",
                    "format_version": "1",
                },
            )
        w.finish()


@pytest.mark.parametrize("compression, summary_channels", [("lz4", False), ("none", False), ("lz4", True)])
def test_reads_a_minimal_independent_writer(tmp_path, compression, summary_channels):
    path = tmp_path / "other.mcap"
    _raw_writer_file(path, {"/gnss/fix", "/camera/image"}, compression=compression, summary_channels=summary_channels)
    with open_run(path) as run:
        assert not run.truncated
        assert (run.metadata.width, run.metadata.height, run.metadata.marker.size_m) == (640, 480, 0.25)
        assert run.metadata.altitude_datum == "ellipsoid" and run.metadata.camera_latency_s is None
        frames = list(run.iter_frames())
        assert [f.timestamp_ns for f in frames] == [T0 + i * 50_000_000 for i in range(20)]
        assert frames[3].data == _jpeg(3)
        fixes = list(run.iter_fixes())
        assert [round(f.lat_deg, 7) for f in fixes] == [round(-35.0 - i * 1e-6, 7) for i in range(0, 20, 4)]
        assert all(f.covariance_enu is None and f.fix_type is None for f in fixes)
        assert list(run.iter_events()) == [] and list(run.iter_attitude()) == []
        # the capture-time window applies to the message timestamp, not the 30 ms later log time
        got = [f.timestamp_ns for f in run.iter_frames([(T0 + 100_000_000, T0 + 200_000_000)])]
        assert got == [T0 + 100_000_000, T0 + 150_000_000, T0 + 200_000_000]


def test_unchunked_file_reads(tmp_path):
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
    from mcap.writer import Writer
    from mcap_protobuf.schema import register_schema

    path = tmp_path / "flat.mcap"
    with open(path, "wb") as f:
        w = Writer(f, use_chunking=False)
        w.start()
        w.add_metadata("dronecal.run", _meta().to_mcap_metadata())
        img = w.register_channel("/camera/image", "protobuf", register_schema(w, CompressedImage))
        fix = w.register_channel("/gnss/fix", "protobuf", register_schema(w, LocationFix))
        for i in range(4):
            w.add_message(img, T0 + i, CompressedImage(format="jpeg", data=b"x" * i).SerializeToString(), T0 + i)
        w.add_message(fix, T0, LocationFix(latitude=1.5).SerializeToString(), T0)
        w.finish()
    with open_run(path) as run:
        assert [(f.timestamp_ns, f.data) for f in run.iter_frames()] == [(T0 + i, b"x" * i) for i in range(4)]
        assert [f.lat_deg for f in run.iter_fixes()] == [1.5]


def test_missing_metadata_record(tmp_path):
    path = tmp_path / "nometa.mcap"
    _raw_writer_file(path, {"/gnss/fix", "/camera/image"}, metadata=False)
    with pytest.raises(ContractError, match="no metadata record 'dronecal.run'"):
        open_run(path)


@pytest.mark.parametrize("present, missing", [({"/camera/image"}, "/gnss/fix"), ({"/gnss/fix"}, "/camera/image")])
def test_missing_topic_names_it(tmp_path, present, missing):
    path = tmp_path / "partial.mcap"
    _raw_writer_file(path, present)
    with pytest.raises(ContractError, match=f"no topic '{missing}'"):
        open_run(path)


def test_wrong_schema_names_it(tmp_path):
    path = tmp_path / "wrong.mcap"
    _raw_writer_file(path, {"/gnss/fix", "/camera/image"}, fix_schema="sensor_msgs.NavSatFix")
    with pytest.raises(ContractError, match="topic '/gnss/fix' has schema 'sensor_msgs.NavSatFix'"):
        open_run(path)


def test_not_an_mcap_file(tmp_path):
    path = tmp_path / "x.mcap"
    path.write_bytes(b"hello world, not mcap at all")
    with pytest.raises(ContractError, match="not an MCAP file"):
        open_run(path)


def test_writer_refuses_unknown_frame_format_and_writes_after_close(tmp_path):
    w = RunWriter(tmp_path / "r.mcap", _meta())
    with pytest.raises(InputError, match="encode as jpeg or png"):
        w.write_frame(Frame(timestamp_ns=T0, format="bmp", data=b"BM"))
    w.close()
    with pytest.raises(InputError, match="is closed"):
        w.write_fix(_fix(0))


def test_json_schema_of_mavlink_channel(tmp_path):
    from mcap.reader import make_reader

    path = tmp_path / "r.mcap"
    with RunWriter(path, _meta()) as w:
        w.write_frame(Frame(timestamp_ns=T0, format="jpeg", data=_jpeg(0)))
        w.write_fix(_fix(0))
        w.write_mavlink("SYS_STATUS", T0, {"voltage_battery": 12000, "load": 1.5, "name": "x"})
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    sch = {s.name: s for s in summary.schemas.values()}["mavlink.SYS_STATUS"]
    assert sch.encoding == "jsonschema"
    props = json.loads(sch.data)["properties"]
    assert props["voltage_battery"] == {"type": "number"} and props["name"] == {"type": "string"}
    chan = [c for c in summary.channels.values() if c.topic == "/mavlink/SYS_STATUS"][0]
    assert chan.message_encoding == "json"


def test_events_are_also_written_as_log_lines_the_foxglove_app_shows(tmp_path):
    """foxglove.Event is not among the schemas the Foxglove app renders; /events/log (foxglove.Log) carries the same events."""
    from foxglove_schemas_protobuf.Log_pb2 import Log
    from mcap.reader import make_reader

    path = tmp_path / "run.mcap"
    events = [
        RunEvent(timestamp_ns=T0 + 100, duration_ns=3_000_000_000, type="hover", metadata={"seq": "4", "hold_s": "3.0"}),
        RunEvent(timestamp_ns=T0 + 5_000_000_000, duration_ns=1_500_000_000, type="link_lost"),
    ]
    with RunWriter(path, _meta()) as w:
        for e in events:
            w.write_event(e)
    with open(path, "rb") as f:
        logs = [(s.name, m.log_time, Log.FromString(m.data)) for s, _, m in make_reader(f).iter_messages(topics=["/events/log"])]
    assert [name for name, _, _ in logs] == ["foxglove.Log", "foxglove.Log"]
    assert [t for _, t, _ in logs] == [e.timestamp_ns for e in events]
    assert logs[0][2].message == "hover 3.00 s: seq=4 hold_s=3.0" and logs[0][2].level == Log.INFO
    assert logs[1][2].message == "link_lost 1.50 s" and logs[1][2].level == Log.WARNING
    with open_run(path) as run:
        assert [e.type for e in run.iter_events()] == ["hover", "link_lost"]  # the reader's events are unchanged
