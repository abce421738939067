"""The MAVLink link: explicit schemes, MAVLink 2, optional signing, one reader thread.

Schemes (never guessed from the string's shape):

=====================  ==============================================
``udp:HOST:PORT``      we send to HOST:PORT (a vehicle or SITL listening there)
``udpout:HOST:PORT``   same as ``udp:``
``udpin:HOST:PORT``    we listen on HOST:PORT (SITL/MAVProxy ``--out`` sends to us)
``tcp:HOST:PORT``      we connect (SITL's 5760); reconnects after a drop
``serial:DEVICE``      a telemetry radio or USB, at ``baud``
=====================  ==============================================

One reader thread receives everything and fans it out to subscriptions
(queues) and listeners (callbacks, e.g. the recorder); sends are serialised
by a lock so any thread may send. A GCS heartbeat goes out once a second as
sysid 255 / compid 190, like the recording GCS.

Example
-------
>>> with open_link("udp:127.0.0.1:14550") as link:         # doctest: +SKIP
...     hb = link.wait_heartbeat(timeout_s=5)
...     result = link.command_long(400, (1, 0, 0, 0, 0, 0, 0))
"""

from __future__ import annotations

import hashlib
import os
import queue
import re
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

from dronecal_field.errors import InputError, LinkError
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import px4

GCS_SYSTEM_ID = 255
GCS_COMPONENT_ID = 190


def mavutil_module() -> Any:
    """pymavlink's ``mavutil`` with the ardupilotmega dialect on MAVLink 2.

    pymavlink picks the wire version from the ``MAVLINK20`` environment
    variable when the dialect is loaded; set it and reload the dialect if an
    earlier import chose MAVLink 1.
    """
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    if mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        mavutil.set_dialect("ardupilotmega")
    return mavutil


def mavlink_dialect() -> Any:
    """The MAVLink 2 ardupilotmega dialect module (message classes, enums)."""
    return mavutil_module().mavlink


@dataclass(frozen=True)
class Endpoint:
    """Where the link goes.

    Attributes
    ----------
    scheme : str
        ``udpout``, ``udpin``, ``tcp`` or ``serial``.
    address : str
        ``HOST:PORT`` or the serial device path.
    baud : int
        Serial baud rate (bit/s); ignored for sockets.
    """

    scheme: str
    address: str
    baud: int = 115200

    def pymavlink_device(self) -> str:
        """The device string pymavlink's ``mavlink_connection`` understands."""
        if self.scheme == "serial":
            return self.address
        return f"{self.scheme}:{self.address}"

    def __str__(self) -> str:
        return f"{self.scheme}:{self.address}"


_HOST_PORT = re.compile(r"^(?P<host>[^:]+):(?P<port>\d{1,5})$")


def parse_endpoint(url: str, baud: int = 115200) -> Endpoint:
    """Parse a connection URL with an explicit scheme.

    Parameters
    ----------
    url : str
        ``udp:HOST:PORT`` (send to), ``udpout:``, ``udpin:HOST:PORT`` (listen),
        ``tcp:HOST:PORT`` or ``serial:/dev/ttyUSB0``.
    baud : int
        Serial baud rate, bit/s.

    Raises
    ------
    InputError
        No scheme, an unknown scheme or a malformed HOST:PORT.
    """
    if url.startswith("/dev/"):
        return Endpoint(scheme="serial", address=url, baud=int(baud))  # a device path is explicit enough
    scheme, sep, rest = url.partition(":")
    if not sep:
        raise InputError(f"connection {url!r} has no scheme; write udp:HOST:PORT, udpin:HOST:PORT, tcp:HOST:PORT or serial:DEVICE")
    scheme = scheme.lower()
    if scheme == "serial":
        if not rest:
            raise InputError(f"connection {url!r} names no device; write serial:/dev/ttyUSB0")
        return Endpoint(scheme="serial", address=rest, baud=int(baud))
    if scheme in ("udp", "udpout"):
        scheme = "udpout"
    elif scheme not in ("udpin", "tcp"):
        raise InputError(f"connection scheme {scheme!r} unknown; use udp:, udpin:, tcp: or serial:")
    match = _HOST_PORT.match(rest)
    if not match or not 0 <= int(match["port"]) <= 65535:
        raise InputError(f"connection {url!r} is not {scheme}:HOST:PORT; e.g. udp:127.0.0.1:14550")
    return Endpoint(scheme=scheme, address=rest, baud=int(baud))


def signing_key_bytes(key: str) -> bytes:
    """The 32-byte MAVLink 2 signing key from ``key``.

    64 hexadecimal characters are the key itself; anything else is a passphrase
    hashed with SHA-256 (as MAVProxy's ``signing setup`` does).
    """
    text = key.strip()
    if re.fullmatch(r"[0-9a-fA-F]{64}", text):
        return bytes.fromhex(text)
    if not text:
        raise InputError("empty --signing-key; give 64 hex characters or a passphrase")
    return hashlib.sha256(text.encode("utf-8")).digest()


class Subscription:
    """A queue of received messages of some types; close it (or use ``with``) when done."""

    def __init__(self, link: MavLink, types: frozenset[str] | None, maxsize: int) -> None:
        self._link = link
        self.types = types
        self._queue: queue.Queue[Any] = queue.Queue(maxsize=maxsize)
        self.overflowed = 0

    def _offer(self, msg: Any) -> None:
        if self.types is not None and msg.get_type() not in self.types:
            return
        try:
            self._queue.put_nowait(msg)
        except queue.Full:
            self.overflowed += 1  # a subscriber that stopped reading must not stall the reader thread

    def get(self, timeout_s: float) -> Any | None:
        """Next message, or ``None`` after ``timeout_s`` seconds."""
        try:
            return self._queue.get(timeout=max(0.0, timeout_s))
        except queue.Empty:
            return None

    def close(self) -> None:
        self._link._unsubscribe(self)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# listener(direction "in"/"out", host UTC ns, message); called on the reader (or sending) thread.
Listener = Callable[[str, int, Any], None]


class MavLink:
    """A MAVLink 2 connection to one vehicle, shared by threads.

    Parameters
    ----------
    endpoint : Endpoint
        Where to connect.
    signing_key : bytes or None
        32-byte signing key; outgoing messages are signed and unsigned incoming
        ones rejected. Never logged or shown by ``repr``.
    source_system, source_component : int
        Our identity (the GCS: 255/190).
    heartbeat_period_s : float
        Seconds between our HEARTBEATs; 0 sends none.
    reconnect_interval_s : float
        Wait between reopen attempts after the transport failed (TCP drop).
    """

    def __init__(
        self,
        endpoint: Endpoint,
        *,
        signing_key: bytes | None = None,
        source_system: int = GCS_SYSTEM_ID,
        source_component: int = GCS_COMPONENT_ID,
        heartbeat_period_s: float = 1.0,
        reconnect_interval_s: float = 1.0,
    ) -> None:
        self.endpoint = endpoint
        self._signing_key = signing_key
        self.source_system = source_system
        self.source_component = source_component
        self.heartbeat_period_s = heartbeat_period_s
        self.reconnect_interval_s = reconnect_interval_s
        self._mavutil = mavutil_module()
        self.dialect = self._mavutil.mavlink
        self._conn: Any = None
        self._send_lock = threading.Lock()
        self._subs_lock = threading.Lock()
        self._subs: list[Subscription] = []
        self._listeners: list[Listener] = []
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._latest: dict[str, Any] = {}
        self.target_system = 0
        self.target_component = 0
        self.vehicle_heartbeat: Any = None
        self.last_receive_monotonic: float | None = None
        self.last_heartbeat_monotonic: float | None = None
        self.received = 0
        self.sent = 0
        self.reconnects = 0
        self.transport_errors = 0
        # an encoder that exists even while the transport is down, so messages can be built
        self.mav = self.dialect.MAVLink(None, srcSystem=source_system, srcComponent=source_component)

    def __repr__(self) -> str:
        return f"MavLink({self.endpoint}, signed={self._signing_key is not None}, target={self.target_system}/{self.target_component})"

    # ----- lifecycle -----
    def open(self) -> MavLink:
        """Open the transport and start the reader and heartbeat threads.

        Raises
        ------
        LinkError
            The port cannot be opened (busy, refused, no such device).
        """
        self._conn = self._open_transport()
        self._start_thread(self._reader, "mavlink-reader")
        if self.heartbeat_period_s > 0:
            self._start_thread(self._heartbeat_loop, "mavlink-heartbeat")
        return self

    def _start_thread(self, target: Callable[[], None], name: str) -> None:
        thread = threading.Thread(target=target, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)

    def _open_transport(self) -> Any:
        ep = self.endpoint
        if ep.scheme == "serial":
            import importlib.util

            if importlib.util.find_spec("serial") is None:  # pymavlink's serial port needs pyserial
                raise LinkError("serial links need pyserial; install it with: pip install pyserial")
        try:
            conn = self._mavutil.mavlink_connection(
                ep.pymavlink_device(),
                baud=ep.baud,
                source_system=self.source_system,
                source_component=self.source_component,
                autoreconnect=False,
                retries=0,
            )
        except (OSError, ValueError) as exc:
            raise LinkError(f"cannot open {ep}: {exc}; check the address and that the vehicle or SITL is running") from None
        if ep.scheme == "tcp":
            # pymavlink prints and carries on at EOF; make a drop an exception the reader handles
            def dropped() -> None:
                raise ConnectionResetError("TCP connection closed by the vehicle")

            conn.handle_eof = dropped
            conn.handle_disconnect = dropped
        if self._signing_key is not None:
            conn.setup_signing(self._signing_key, sign_outgoing=True, allow_unsigned_callback=None)
        # keep our sequence numbers running across reconnects
        conn.mav.seq = self.mav.seq
        return conn

    def close(self) -> None:
        """Stop the threads and close the transport (idempotent)."""
        self._stop.set()
        for thread in self._threads:
            if thread is not threading.current_thread():
                thread.join(timeout=2.0)
        self._threads.clear()
        with self._send_lock:
            if self._conn is not None:
                try:
                    self._conn.close()
                except OSError:
                    pass
                self._conn = None

    def __enter__(self) -> MavLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----- receiving -----
    def _reader(self) -> None:
        while not self._stop.is_set():
            conn = self._conn
            if conn is None:
                if self._stop.wait(self.reconnect_interval_s):
                    return
                try:
                    new = self._open_transport()
                except LinkError:
                    continue
                with self._send_lock:
                    self._conn = new
                self.reconnects += 1
                continue
            try:
                if not conn.select(0.1):
                    continue
                while not self._stop.is_set():
                    msg = conn.recv_msg()
                    if msg is None:
                        break
                    self._dispatch(msg)
            except (OSError, ConnectionError, ValueError):
                # transport failed (TCP drop, device unplugged): reopen in the loop above
                self.transport_errors += 1
                with self._send_lock:
                    try:
                        conn.close()
                    except OSError:
                        pass
                    if self._conn is conn:
                        self._conn = None

    def _dispatch(self, msg: Any) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            return
        now = time.monotonic()
        self.received += 1
        self.last_receive_monotonic = now
        self._latest[mtype] = msg
        if mtype == "HEARTBEAT" and msg.type != ap.MAV_TYPE_GCS and msg.autopilot != ap.MAV_AUTOPILOT_INVALID:
            if self.target_system == 0:
                self.target_system = msg.get_srcSystem()
                self.target_component = msg.get_srcComponent()
            if msg.get_srcSystem() == self.target_system:
                self.vehicle_heartbeat = msg
                self.last_heartbeat_monotonic = now
        stamp_ns = time.time_ns()
        for listener in list(self._listeners):
            listener("in", stamp_ns, msg)
        with self._subs_lock:
            subs = list(self._subs)
        for sub in subs:
            sub._offer(msg)

    def subscribe(self, types: Iterable[str] | None = None, maxsize: int = 10000) -> Subscription:
        """A queue of every received message whose type is in ``types`` (all if ``None``)."""
        sub = Subscription(self, frozenset(types) if types is not None else None, maxsize)
        with self._subs_lock:
            self._subs.append(sub)
        return sub

    def _unsubscribe(self, sub: Subscription) -> None:
        with self._subs_lock:
            if sub in self._subs:
                self._subs.remove(sub)

    def add_listener(self, listener: Listener) -> None:
        """Call ``listener(direction, time_ns, msg)`` for every message in and out (keep it fast)."""
        self._listeners.append(listener)

    def remove_listener(self, listener: Listener) -> None:
        if listener in self._listeners:
            self._listeners.remove(listener)

    def latest(self, mtype: str) -> Any | None:
        """The last received message of type ``mtype`` (any system), or ``None``."""
        return self._latest.get(mtype)

    def seconds_since_receive(self) -> float:
        """Seconds since any message arrived (``inf`` if none yet)."""
        last = self.last_receive_monotonic
        return float("inf") if last is None else time.monotonic() - last

    def wait_heartbeat(self, timeout_s: float = 10.0) -> Any:
        """Wait for the vehicle's HEARTBEAT.

        Raises
        ------
        LinkError
            Nothing from an autopilot within ``timeout_s`` seconds.
        """
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.vehicle_heartbeat is not None:
                return self.vehicle_heartbeat
            time.sleep(0.02)
        raise LinkError(
            f"no HEARTBEAT from a vehicle on {self.endpoint} within {timeout_s:g} s; check --connect (udp: sends, udpin: listens) and the signing key"
        )

    def wait_message(self, types: Iterable[str], predicate: Callable[[Any], bool] | None = None, timeout_s: float = 5.0) -> Any | None:
        """The next message of ``types`` that satisfies ``predicate``, or ``None`` on timeout."""
        deadline = time.monotonic() + timeout_s
        with self.subscribe(types) as sub:
            while True:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                msg = sub.get(left)
                if msg is not None and (predicate is None or predicate(msg)):
                    return msg

    # ----- sending -----
    def send(self, msg: Any) -> bool:
        """Send one message (thread-safe). Returns False if the transport is down."""
        with self._send_lock:
            conn = self._conn
            if conn is None:
                return False
            # pymavlink's MAVLink.send, split so listeners see the message before any reply can
            # arrive: a log of both directions stays in causal order
            mav = conn.mav
            buf = msg.pack(mav)
            mav.seq = (mav.seq + 1) % 256
            mav.total_packets_sent += 1
            mav.total_bytes_sent += len(buf)
            self.mav.seq = mav.seq
            stamp_ns = time.time_ns()
            for listener in list(self._listeners):
                listener("out", stamp_ns, msg)
            try:
                conn.write(buf)
            except (OSError, ConnectionError):
                self.transport_errors += 1
                return False
            self.sent += 1
        return True

    def _heartbeat_loop(self) -> None:
        while not self._stop.is_set():
            self.send(self.dialect.MAVLink_heartbeat_message(ap.MAV_TYPE_GCS, ap.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3))
            self._stop.wait(self.heartbeat_period_s)

    def command_long(
        self,
        command: int,
        params: tuple[float, ...] = (0, 0, 0, 0, 0, 0, 0),
        *,
        timeout_s: float = 1.5,
        retries: int = 2,
    ) -> int:
        """Send COMMAND_LONG and return the COMMAND_ACK result (MAV_RESULT).

        Re-sends with ``confirmation`` incremented when no ACK arrives in
        ``timeout_s`` seconds.

        Raises
        ------
        LinkError
            No ACK after ``retries + 1`` tries.
        """
        p = tuple(float(v) for v in params) + (0.0,) * (7 - len(params))
        with self.subscribe({"COMMAND_ACK"}) as sub:
            for attempt in range(retries + 1):
                self.send(self.dialect.MAVLink_command_long_message(self.target_system, self.target_component, command, attempt, *p))
                deadline = time.monotonic() + timeout_s
                while (left := deadline - time.monotonic()) > 0:
                    ack = sub.get(left)
                    if ack is not None and ack.command == command:
                        return int(ack.result)
        raise LinkError(f"vehicle did not acknowledge command {command} after {retries + 1} tries; check the link")

    @property
    def is_px4(self) -> bool:
        """The vehicle's HEARTBEAT says PX4 (MAV_AUTOPILOT_PX4); ArduPilot otherwise."""
        hb = self.vehicle_heartbeat
        return hb is not None and int(hb.autopilot) == px4.MAV_AUTOPILOT_PX4

    def set_mode(self, mode: int | str, timeout_s: float = 1.5) -> int:
        """Ask for a mode with MAV_CMD_DO_SET_MODE; returns MAV_RESULT.

        ArduCopter: a mode number or name (``GUIDED``). PX4: a name, PX4's
        (``AUTO.LOITER``) or ArduPilot's meaning (``AUTO`` -> AUTO.MISSION,
        ``GUIDED`` -> AUTO.LOITER, ``RTL``, ``LAND``), sent as main/sub mode.
        """
        if self.is_px4 and isinstance(mode, str):
            main, sub = px4.mode_numbers(mode)
            return self.command_long(ap.CMD_DO_SET_MODE, (ap.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub), timeout_s=timeout_s)
        number = ap.COPTER_MODES[mode.upper()] if isinstance(mode, str) else int(mode)
        return self.command_long(ap.CMD_DO_SET_MODE, (ap.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, number), timeout_s=timeout_s)


def open_link(
    url: str,
    *,
    baud: int = 115200,
    signing_key: str | None = None,
    source_system: int = GCS_SYSTEM_ID,
    source_component: int = GCS_COMPONENT_ID,
    heartbeat_period_s: float = 1.0,
) -> MavLink:
    """Open a MAVLink 2 link from a URL with an explicit scheme (see module docstring).

    Parameters
    ----------
    url : str
        ``udp:HOST:PORT``, ``udpin:HOST:PORT``, ``tcp:HOST:PORT`` or ``serial:DEVICE``.
    baud : int
        Serial baud rate, bit/s.
    signing_key : str or None
        64 hex characters or a passphrase (SHA-256); ``None`` = unsigned.
    heartbeat_period_s : float
        Seconds between GCS heartbeats; 0 for none.

    Returns
    -------
    MavLink
        Open, with its reader and heartbeat threads running; close it (``with``).
    """
    endpoint = parse_endpoint(url, baud)
    key = signing_key_bytes(signing_key) if signing_key else None
    return MavLink(
        endpoint,
        signing_key=key,
        source_system=source_system,
        source_component=source_component,
        heartbeat_period_s=heartbeat_period_s,
    ).open()
