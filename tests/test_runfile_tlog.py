"""TlogWriter: the standard .tlog, read back by pymavlink and byte-identical to a real one."""

from __future__ import annotations

import hashlib
import struct
from pathlib import Path

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav2

from conftest import REPLAYS, needs_replays
from dronecal_field.runfile.tlog import TlogWriter


def test_written_tlog_reads_back_with_pymavlink(tmp_path):
    path = tmp_path / "flight.tlog"
    vehicle = mav2.MAVLink(None, srcSystem=1, srcComponent=1)
    gcs = mav2.MAVLink(None, srcSystem=255, srcComponent=190)
    t0_us = 1_795_315_761_000_000
    sent = []
    with TlogWriter(path) as tlog:
        for i in range(50):
            msg = mav2.MAVLink_gps_raw_int_message(
                time_usec=i * 200_000, fix_type=6, lat=-353632610 + i, lon=1491652300, alt=584090,
                eph=121, epv=200, vel=0, cog=0, satellites_visible=10, alt_ellipsoid=584100, h_acc=300, v_acc=400,
            )
            tlog.write(msg.pack(vehicle), t0_us + i * 200_000)
            sent.append(("GPS_RAW_INT", t0_us + i * 200_000, 1))
            if i % 10 == 0:
                hb = mav2.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3)
                tlog.write(hb.pack(gcs), t0_us + i * 200_000 + 1)
                sent.append(("HEARTBEAT", t0_us + i * 200_000 + 1, 255))
        assert tlog.records_written == 55
    conn = mavutil.mavlink_connection(str(path))
    got = []
    lats = []
    while (m := conn.recv_msg()) is not None:
        got.append((m.get_type(), round(m._timestamp * 1e6), m.get_srcSystem()))
        if m.get_type() == "GPS_RAW_INT":
            lats.append(m.lat)
            assert (m.alt_ellipsoid, m.h_acc, m.v_acc) == (584100, 300, 400)
    assert got == sent
    assert lats == [-353632610 + i for i in range(50)]


def _records(data: bytes):
    """(timestamp_us, frame bytes) of a tlog: MAVLink 1 (0xFE) and 2 (0xFD, signed or not) frames."""
    pos = 0
    while pos + 8 < len(data):
        (t_us,) = struct.unpack(">Q", data[pos : pos + 8])
        start = pos + 8
        magic, length = data[start], data[start + 1]
        if magic == 0xFD:
            size = 10 + length + 2 + (13 if data[start + 2] & 0x01 else 0)
        elif magic == 0xFE:
            size = 6 + length + 2
        else:
            raise AssertionError(f"no MAVLink frame at byte {start}")
        yield t_us, data[start : start + size]
        pos = start + size


@needs_replays
@pytest.mark.parametrize("name", ["calib-grid-gpsloss.tlog"])
def test_rewriting_a_real_tlog_is_byte_identical(tmp_path, name):
    src = (REPLAYS / name).read_bytes()
    out = tmp_path / name
    with TlogWriter(out) as tlog:
        for t_us, frame in _records(src):
            tlog.write(frame, t_us)
    assert tlog.records_written == 19795  # README: all messages of the gpsloss log
    assert hashlib.sha256(out.read_bytes()).hexdigest() == hashlib.sha256(src).hexdigest()
    assert hashlib.sha256(src).hexdigest() == "7d024f0f92bdc8ac3ef2dc7fe2de5df538f1ce512deda32bf53a66ed337ec1e3"


def test_flushed_without_close(tmp_path):
    """The background flusher puts records on disk within about a second, with no further write."""
    import time

    path = tmp_path / "open.tlog"
    tlog = TlogWriter(path, flush_interval_s=0.2)
    msg = mav2.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3).pack(mav2.MAVLink(None, srcSystem=1, srcComponent=1))
    tlog.write(msg, 1_000)
    deadline = time.monotonic() + 10.0
    while path.stat().st_size < 8 + len(msg) and time.monotonic() < deadline:
        time.sleep(0.05)
    size_open = path.stat().st_size
    tlog.close()
    assert size_open == 8 + len(msg) == path.stat().st_size
