"""The MAVLink link: explicit schemes, GCS heartbeat, thread-safe sends, signing, TCP reconnect."""

from __future__ import annotations

import socket
import threading
import time

import pytest

from dronecal_field.errors import InputError, LinkError
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink.link import Endpoint, mavutil_module, open_link, parse_endpoint, signing_key_bytes
from test_mavlink_support import start_sim, wait_until


@pytest.mark.parametrize(
    "url, scheme, address",
    [
        ("udp:127.0.0.1:14550", "udpout", "127.0.0.1:14550"),
        ("udpout:10.0.0.2:14550", "udpout", "10.0.0.2:14550"),
        ("udpin:0.0.0.0:14550", "udpin", "0.0.0.0:14550"),
        ("tcp:127.0.0.1:5760", "tcp", "127.0.0.1:5760"),
        ("serial:/dev/ttyUSB0", "serial", "/dev/ttyUSB0"),
        ("/dev/ttyACM0", "serial", "/dev/ttyACM0"),
    ],
)
def test_parse_endpoint_schemes(url, scheme, address):
    assert parse_endpoint(url, baud=57600) == Endpoint(scheme=scheme, address=address, baud=57600)


@pytest.mark.parametrize("url, fragment", [("127.0.0.1:14550", "unknown"), ("ttyUSB0", "no scheme"), ("udp:localhost", "HOST:PORT"), ("ws:1.2.3.4:5", "unknown")])
def test_parse_endpoint_refuses_guessing(url, fragment):
    with pytest.raises(InputError, match=fragment):
        parse_endpoint(url)


def test_signing_key_from_hex_or_passphrase_and_never_shown():
    raw = bytes(range(32))
    assert signing_key_bytes(raw.hex()) == raw
    key = signing_key_bytes("correct horse battery staple")
    assert len(key) == 32 and key == __import__("hashlib").sha256(b"correct horse battery staple").digest()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    link = open_link(f"udp:127.0.0.1:{sock.getsockname()[1]}", signing_key="correct horse battery staple", heartbeat_period_s=0)
    try:
        assert "horse" not in repr(link) and key.hex() not in repr(link)
    finally:
        link.close()
        sock.close()


def _parse_all(datagrams: list[bytes]) -> list:
    mav = mavutil_module().mavlink.MAVLink(None)
    mav.robust_parsing = True
    out = []
    for data in datagrams:
        out.extend(m for m in mav.parse_buffer(data) or [] if m.get_type() != "BAD_DATA")
    return out


def test_gcs_heartbeat_and_thread_safe_sends_on_the_wire():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    # a loaded machine can starve the receiver for a while: a 4 MB buffer holds all 800 datagrams
    # (the default ~200 kB dropped 26 of them in CI), so a loss here is the link's, not the kernel's
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4 << 20)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.2)
    datagrams: list[bytes] = []
    stop = threading.Event()

    def receive() -> None:  # drain the socket while the senders run, so the kernel drops nothing
        while not stop.is_set():
            try:
                datagrams.append(sock.recvfrom(65535)[0])
            except TimeoutError:
                continue

    receiver = threading.Thread(target=receive)
    receiver.start()
    link = open_link(f"udp:127.0.0.1:{sock.getsockname()[1]}")
    d = link.dialect

    def burst(k: int) -> None:
        for i in range(200):
            link.send(d.MAVLink_named_value_int_message(i, f"t{k}".encode(), i))
            if i % 20 == 0:
                time.sleep(0.001)

    threads = [threading.Thread(target=burst, args=(k,)) for k in range(4)]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert wait_until(lambda: sum(dg[0] == 0xFD and dg[7] == 0 for dg in list(datagrams)) >= 2, 5)  # two heartbeats
    finally:
        link.close()
        stop.set()
        receiver.join()
        sock.close()
    msgs = _parse_all(datagrams)
    values = [m for m in msgs if m.get_type() == "NAMED_VALUE_INT"]
    assert len(values) == 800
    heartbeats = [m for m in msgs if m.get_type() == "HEARTBEAT"]
    assert len(heartbeats) >= 2
    assert {(m.get_srcSystem(), m.get_srcComponent(), m.type) for m in heartbeats} == {(255, 190, ap.MAV_TYPE_GCS)}
    assert all(datagram[0] == 0xFD for datagram in datagrams)  # MAVLink 2 on the wire
    # one sequence counter shared by every thread: consecutive numbers, no duplicates
    seqs = [m.get_seq() for m in msgs]
    assert all((b - a) % 256 == 1 for a, b in zip(seqs, seqs[1:]))


def test_signed_link_talks_to_a_signed_vehicle_and_a_wrong_key_hears_nothing():
    key = signing_key_bytes("field key")
    sim = start_sim(boot_s=0.5, signing_key=key)
    good = open_link(sim.addresses()[0], signing_key="field key")
    try:
        hb = good.wait_heartbeat(5)
        assert hb.get_signed()
        assert good.set_mode("GUIDED") == ap.MAV_RESULT_ACCEPTED  # the vehicle took our signed command
    finally:
        good.close()
    wrong = open_link(sim.addresses()[0], signing_key="other key")
    try:
        with pytest.raises(LinkError, match="no HEARTBEAT"):
            wrong.wait_heartbeat(1.0)
    finally:
        wrong.close()
        sim.stop()


def test_tcp_link_reconnects_after_the_vehicle_restarts():
    probe = socket.socket()
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    sim = start_sim(boot_s=0.5, listen=[f"tcp:127.0.0.1:{port}"])
    link = open_link(f"tcp:127.0.0.1:{port}")
    link.reconnect_interval_s = 0.1
    try:
        link.wait_heartbeat(5)
        sim.stop()
        assert wait_until(lambda: link.seconds_since_receive() > 0.3, 3)
        sim = start_sim(boot_s=0.5, listen=[f"tcp:127.0.0.1:{port}"])
        before = link.received
        assert wait_until(lambda: link.received > before + 5, 10)
        assert link.reconnects >= 1
        assert link.set_mode("GUIDED") == ap.MAV_RESULT_ACCEPTED
    finally:
        link.close()
        sim.stop()


def test_udpin_link_hears_a_vehicle_sending_to_it():
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    link = open_link(f"udpin:127.0.0.1:{port}")
    from dronecal_field.sim.vehicle import SimVehicle, VehicleConfig
    from test_mavlink_support import HOME

    sim = SimVehicle(VehicleConfig(home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2], speedup=20, boot_s=0.5), listen=[], out=[f"udp:127.0.0.1:{port}"]).start()
    try:
        hb = link.wait_heartbeat(5)
        assert hb.autopilot == ap.MAV_AUTOPILOT_ARDUPILOTMEGA
        assert link.set_mode("LOITER") == ap.MAV_RESULT_ACCEPTED  # answers go back the same way
    finally:
        link.close()
        sim.stop()


def test_serial_link_names_what_is_missing():
    with pytest.raises(LinkError, match="pyserial|cannot open serial:/dev/ttyDRONECAL0"):
        open_link("serial:/dev/ttyDRONECAL0", baud=57600)
