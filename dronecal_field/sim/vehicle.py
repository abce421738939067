"""A SITL-style simulated ArduCopter: MAVLink 2 server over UDP/TCP, several links at once.

The flight logic is :mod:`dronecal_field.sim.vehicle_flight` and the mission
protocol :mod:`dronecal_field.sim.vehicle_mission`; this module is the shell:
sockets, the vehicle clock (``speedup`` x wall time), the boot sequence and the
telemetry streams.

Streams behave per link as ArduPilot 4.7 does (shared/replays/arducopter-sitl
README, "A second link"): every link, the first included, gets only
HEARTBEAT (1 Hz), TIMESYNC (every 10 s), GPS_GLOBAL_ORIGIN and HOME_POSITION
(once, when the origin is set) until a client asks on that link (STATUSTEXT
and MISSION_ITEM_REACHED go to links a client has spoken on): SET_MESSAGE_INTERVAL for one message,
REQUEST_DATA_STREAM for a stream group, or the link's stream-rate parameters
``MAVn_*`` (n = link number + 1: ``MAV1_*`` for the first ``--listen``,
``MAV2_*`` for the second...; the older ``SRn_*`` names do nothing in 4.7).
What one client asks changes its own link only. A client's untargeted
messages (its HEARTBEAT) are routed to the other active links, as
ArduPilot's MAVLink routing does. GPS fixes come every
``gps_rate_ms`` (GPS_RATE_MS, ArduPilot's default 200), each about 104 ms old
when it goes out, with h_acc = v_acc = 300 mm whatever the scatter; a faster
GPS_RAW_INT stream repeats the last fix (same ``time_usec``). SIMSTATE (in
the EXTRA1 group, as SITL) carries the true position.

Links (explicit schemes, like SITL's ``--out``):

* listen: ``udp:HOST:PORT`` (or ``udpin:``) binds and answers whoever writes;
  ``tcp:HOST:PORT`` accepts one client at a time (like SITL's port 5760).
  Port 0 picks a free port; :meth:`SimVehicle.addresses` tells which.
* out: ``udp:HOST:PORT`` sends everything there (a simulated camera, a GCS).

Heights: ``home_alt_m`` is above mean sea level, as SITL's ``--home``;
ellipsoidal height = AMSL + ``geoid_sep_m`` (default 0, so they agree).

Example
-------
>>> sim = SimVehicle(VehicleConfig(home_lat_deg=-35.363261, home_lon_deg=149.165230, home_alt_m=584.0, speedup=10),
...                  listen=["udp:127.0.0.1:0"])             # doctest: +SKIP
>>> sim.start(); print(sim.addresses()); sim.stop()          # doctest: +SKIP
"""

from __future__ import annotations

import math
import select
import socket
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dronecal_field.errors import InputError
from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic, geodetic_to_enu
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import missionfile as mf
from dronecal_field.mavlink.link import mavutil_module
from dronecal_field.mavlink.missionfile import MissionItem
from dronecal_field.sim.vehicle_flight import CopterModel, CopterParams
from dronecal_field.sim.vehicle_mission import MissionServer

# ArduPilot's stream groups: MAVn_* parameter suffix -> (MAV_DATA_STREAM id, the messages of the
# group this simulator builds), as in ArduCopter's GCS_Mavlink.cpp.
STREAM_GROUPS: dict[str, tuple[int, tuple[str, ...]]] = {
    "RAW_SENS": (1, ()),
    "EXT_STAT": (2, ("SYS_STATUS", "MISSION_CURRENT", "GPS_RAW_INT")),
    "RC_CHAN": (3, ()),
    "RAW_CTRL": (4, ()),
    "POSITION": (6, ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED")),
    "EXTRA1": (10, ("ATTITUDE", "SIMSTATE")),
    "EXTRA2": (11, ()),
    "EXTRA3": (12, ("SYSTEM_TIME", "EKF_STATUS_REPORT", "BATTERY_STATUS")),
    "PARAMS": (7, ()),
    "ADSB": (13, ()),
}
_GROUP_OF = {name: group for group, (_sid, names) in STREAM_GROUPS.items() for name in names}
_GROUP_BY_ID = {sid: group for group, (sid, _names) in STREAM_GROUPS.items()}
MAV_DATA_STREAM_ALL = 0

# The rates the recorded GCS asked for (calib-grid-rtk.tlog: REQUEST_DATA_STREAM ALL 2 Hz, then
# SET_MESSAGE_INTERVAL): what a GCS-like client of the simulator typically asks.
RECORDED_GCS_RATES_HZ: tuple[tuple[str, float], ...] = (
    ("GPS_RAW_INT", 5.0),
    ("GLOBAL_POSITION_INT", 10.0),
    ("ATTITUDE", 10.0),
    ("SIMSTATE", 10.0),
    ("LOCAL_POSITION_NED", 5.0),
    ("MISSION_CURRENT", 2.0),
    ("EKF_STATUS_REPORT", 2.0),
    ("SYS_STATUS", 2.0),
    ("SYSTEM_TIME", 1.0),
    ("HOME_POSITION", 0.5),
)

# Modes whose HEARTBEAT.base_mode carries MAV_MODE_FLAG_GUIDED_ENABLED (GCS_MAVLINK_Copter::base_mode:
# AUTO, RTL, LOITER, GUIDED, CIRCLE, POSHOLD, BRAKE, SMART_RTL ...), whether armed or not.
_GUIDED_FLAG_MODES = frozenset({3, 4, 5, 6, 7, 16, 17, 21})

TIMESYNC_PERIOD_S = 10.0  # ArduPilot asks every link for a TIMESYNC about every 10 s (2 in 25 s recorded)
GPS_LAG_S = 0.104  # a fix's time_usec is this much older than the tick that first carries it (recorded)
GPS_REPORTED_ACC_MM = 300  # h_acc = v_acc on every RTK-fixed fix, whatever the scatter (recorded)

# SYS_STATUS sensor words seen in the recording (before and after the pre-arm checks pass).
_SENSORS_PRESENT = 1399979023 | ap.MAV_SYS_STATUS_PREARM_CHECK
_SENSORS_ENABLED = 1380031503 | ap.MAV_SYS_STATUS_PREARM_CHECK
_SENSORS_HEALTH_BOOT = 1196530703 & ~ap.MAV_SYS_STATUS_PREARM_CHECK
_SENSORS_HEALTH_OK = 1467063343 & ~ap.MAV_SYS_STATUS_PREARM_CHECK


@dataclass(frozen=True)
class VehicleConfig:
    """Simulator settings.

    Attributes
    ----------
    home_lat_deg, home_lon_deg : float
        Home (WGS84 degrees).
    home_alt_m : float
        Home ground height above mean sea level, metres.
    geoid_sep_m : float
        Ellipsoidal minus AMSL height, metres (reported in GPS_RAW_INT.alt_ellipsoid).
    speedup : float
        Vehicle seconds per wall second.
    boot_s : float
        Vehicle seconds from start to "ready to arm"; uploads before that get NO_SPACE.
    tick_s : float
        Physics step, vehicle seconds.
    seed : int
        Noise seed.
    sysid, compid : int
        Vehicle MAVLink identity.
    max_items : int
        Mission capacity including home.
    gnss_sigma_h_m, gnss_sigma_v_m : float
        GPS_RAW_INT noise per horizontal axis / vertical, metres (RTK fixed).
    heading_deg : float
        Initial heading on the ground.
    signing_key : bytes or None
        32-byte MAVLink 2 signing key; unsigned messages are then rejected.
    params : CopterParams
        Flight parameters.
    stream_params : tuple of (str, float)
        Stream-rate parameters set at boot, as a defaults file would:
        ``(("MAV2_POSITION", 10.0), ...)`` in Hz (ArduPilot 4.7 names,
        ``MAVn_<group>``, n = link number + 1; groups in :data:`STREAM_GROUPS`).
        Empty (the default): every link silent until asked, as recorded.
    gps_rate_ms : float
        The receiver's fix interval (ArduPilot's GPS_RATE_MS, default 200 =
        5 Hz): a GPS_RAW_INT stream asked for faster repeats the last fix.
        docs/fly.md asks for 100 on a 10 Hz RTK receiver.
    gps_reported_acc_mm : int
        GPS_RAW_INT.h_acc and v_acc on an RTK-fixed fix (ArduPilot's u-blox
        driver reported 300 whatever the scatter).
    ekf_sigma_m, ekf_tau_s : float
        The EKF's horizontal error in the air, per axis (m) and its
        correlation time (s): GLOBAL_POSITION_INT and LOCAL_POSITION_NED carry
        it, SIMSTATE and the GPS do not. Recorded: EKF vs SIMSTATE 2.1 cm on
        average, 7.0 cm at most (0.017 m per axis gives that mean). 0 by
        default: the project's tests compare reported positions with their
        targets to the millimetre.
    """

    home_lat_deg: float
    home_lon_deg: float
    home_alt_m: float
    geoid_sep_m: float = 0.0
    speedup: float = 1.0
    boot_s: float = 41.8
    tick_s: float = 0.05
    seed: int = 0
    sysid: int = 1
    compid: int = 1
    max_items: int = 700
    gnss_sigma_h_m: float = 0.007
    gnss_sigma_v_m: float = 0.015
    heading_deg: float = 353.0
    signing_key: bytes | None = field(default=None, repr=False)
    params: CopterParams = CopterParams()
    stream_params: tuple[tuple[str, float], ...] = ()
    gps_rate_ms: float = 200.0
    gps_reported_acc_mm: int = GPS_REPORTED_ACC_MM
    ekf_sigma_m: float = 0.0
    ekf_tau_s: float = 10.0
    autopilot: str = "ardupilot"  # "px4": PX4 1.16's personality (sim/vehicle_px4.py)
    gnss: str = "auto"  # PX4 only: "auto" = the SITL's 3D fix (0.2 m / 0.5 m, h_acc 900 mm), "rtk" = RTK fixed (gnss_sigma_*)


def parse_home(text: str) -> tuple[float, float, float]:
    """``LAT,LON,H`` (degrees, degrees, metres AMSL) from ``--home``; a 4th value (heading) is ignored."""
    parts = [p.strip() for p in text.split(",")]
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise InputError(f"--home {text!r} is not LAT,LON,H; e.g. --home -35.363261,149.165230,584") from None
    if len(values) < 3 or not -90 <= values[0] <= 90 or not -180 <= values[1] <= 180:
        raise InputError(f"--home {text!r} is not LAT,LON,H in degrees and metres; e.g. --home -35.363261,149.165230,584")
    return values[0], values[1], values[2]


def _tcp_server_class() -> type:
    mavutil = mavutil_module()

    class TcpServerLink(mavutil.mavtcpin):  # type: ignore[name-defined,misc]
        """pymavlink's TCP listener, plus: a closed client frees the port for the next one."""

        def recv(self, n: int | None = None) -> bytes:
            if not self.port:
                try:
                    self.port, _addr = self.listen.accept()
                except OSError:
                    return b""
                self.port.setsockopt(socket.SOL_TCP, socket.TCP_NODELAY, 1)
                self.port.setblocking(False)
                self.fd = self.port.fileno()
                self.mav.buf = bytearray()  # a new client starts a new byte stream
                self.mav.buf_index = 0
            try:
                data = self.port.recv(n or self.mav.bytes_needed())
            except BlockingIOError:
                return b""
            except OSError:
                data = b""
            if not data:
                self.port.close()
                self.port = None
                self.fd = self.listen.fileno()
            return data

    return TcpServerLink


def _open_links(listen: list[str], out: list[str], config: VehicleConfig) -> list[Any]:
    mavutil = mavutil_module()
    links = []
    specs = [("listen", u) for u in listen] + [("out", u) for u in out]
    for role, url in specs:
        scheme, sep, address = url.partition(":")
        scheme = scheme.lower()
        if not sep or address.count(":") != 1:
            raise InputError(f"--{role} {url!r} is not SCHEME:HOST:PORT; e.g. udp:127.0.0.1:14550")
        try:
            if role == "listen" and scheme in ("udp", "udpin"):
                conn = mavutil.mavlink_connection(f"udpin:{address}", source_system=config.sysid, source_component=config.compid)
            elif role == "listen" and scheme in ("tcp", "tcpin"):
                conn = _tcp_server_class()(address, source_system=config.sysid, source_component=config.compid)
            elif role == "out" and scheme in ("udp", "udpout"):
                conn = mavutil.mavlink_connection(f"udpout:{address}", source_system=config.sysid, source_component=config.compid)
            else:
                raise InputError(f"--{role} scheme {scheme!r} not supported; listen on udp:/tcp:, send with udp:")
        except OSError as exc:
            for c in links:
                c.close()
            raise InputError(f"cannot open --{role} {url}: {exc.strerror}; pick a free port") from None
        if config.signing_key is not None:
            conn.setup_signing(config.signing_key, sign_outgoing=True, allow_unsigned_callback=None)
        conn._dronecal_role = role  # noqa: SLF001 (remembered for addresses())
        links.append(conn)
    return links


def parse_stream_param(name: str) -> tuple[int, str] | None:
    """``MAV2_POSITION`` -> (link index 1, group ``POSITION``); None for any other name (``SR1_*`` included)."""
    head, sep, group = name.upper().partition("_")
    if not sep or not head.startswith("MAV") or not head[3:].isdigit() or group not in STREAM_GROUPS:
        return None
    n = int(head[3:])
    return (n - 1, group) if n >= 1 else None


class LinkStreams:
    """What one link streams, as ArduPilot keeps it per MAVLink channel.

    A message's period is its SET_MESSAGE_INTERVAL if one was asked on this
    link, else its group's rate (``MAVn_<group>``, or REQUEST_DATA_STREAM on
    this link); 0 Hz = not sent.

    Attributes
    ----------
    group_hz : dict
        Stream group -> rate, Hz of vehicle time.
    interval_s : dict
        Message name -> period asked with SET_MESSAGE_INTERVAL, seconds
        (``None`` = asked off with -1).
    next_due_s : dict
        Message name -> vehicle time it is next due.
    """

    def __init__(self) -> None:
        self.group_hz: dict[str, float] = {group: 0.0 for group in STREAM_GROUPS}
        self.interval_s: dict[str, float | None] = {}
        self.next_due_s: dict[str, float] = {}

    def period_s(self, name: str) -> float | None:
        """Period of ``name`` on this link, seconds, or None when it is not streamed."""
        if name in self.interval_s:
            return self.interval_s[name]
        group = _GROUP_OF.get(name)
        hz = self.group_hz.get(group, 0.0) if group else 0.0
        return 1.0 / hz if hz > 0 else None

    def streamed(self) -> list[tuple[str, float]]:
        """(name, period s) of every message this link streams."""
        names = set(_GROUP_OF) | set(self.interval_s)
        out = []
        for name in sorted(names):
            period = self.period_s(name)
            if period is not None:
                out.append((name, period))
        return out


class SimVehicle:
    """The simulated vehicle: links, clock and telemetry around a :class:`CopterModel`.

    Parameters
    ----------
    config : VehicleConfig
        Settings.
    listen : list of str
        Listening endpoints (``udp:HOST:PORT``, ``tcp:HOST:PORT``).
    out : list of str
        Endpoints to send to (``udp:HOST:PORT``).
    """

    def __new__(cls, config: VehicleConfig, *args: Any, **kwargs: Any) -> SimVehicle:
        if cls is SimVehicle and config.autopilot == "px4":  # PX4's personality (lazy: vehicle_px4 imports this module)
            from dronecal_field.sim.vehicle_px4 import Px4Vehicle

            return super().__new__(Px4Vehicle)
        return super().__new__(cls)

    def __init__(self, config: VehicleConfig, listen: list[str], out: list[str] | None = None) -> None:
        if config.speedup <= 0:
            raise InputError(f"--speedup {config.speedup} must be positive; e.g. --speedup 10")
        self.config = config
        mavutil = mavutil_module()
        self.dialect = mavutil.mavlink
        self.enc = self.dialect.MAVLink(None, srcSystem=config.sysid, srcComponent=config.compid)
        self.links = _open_links(list(listen), list(out or []), config)
        self.rng = np.random.default_rng(config.seed)
        self.origin = EnuOrigin(config.home_lat_deg, config.home_lon_deg, config.home_alt_m + config.geoid_sep_m)
        self.model = CopterModel(self._item_enu, config.params, self.rng)
        self.model.heading_deg = config.heading_deg
        self.mission = MissionServer(
            self.enc,
            self._send_to,
            self._home_item,
            lambda: self.prearm_bit,  # uploads are taken once the pre-arm checks report (arming waits for the EKF)
            self.model.set_mission,
            self.model.say,
            config.max_items,
        )
        self.streams: dict[int, LinkStreams] = {id(conn): LinkStreams() for conn in self.links}
        self.params: dict[str, float] = {"GPS_RATE_MS": float(config.gps_rate_ms)}
        for index in range(len(self.links)):
            for group in STREAM_GROUPS:
                self.params[f"MAV{index + 1}_{group}"] = 0.0
        for name, value in config.stream_params:
            if self._set_param(name, float(value)) is None:
                for conn in self.links:
                    conn.close()
                raise InputError(
                    f"stream parameter {name!r} unknown: ArduPilot 4.7 names them MAVn_<group> (n = link number + 1, here MAV1..MAV{len(self.links)}; "
                    f"groups {', '.join(STREAM_GROUPS)}), e.g. MAV2_POSITION; the older SRn_* names do nothing"
                )
        self._last_fix: tuple[float, np.ndarray] | None = None  # the fix GPS_RAW_INT carries now
        self._next_fix_s = 0.0
        self._history: list[tuple[float, np.ndarray]] = []  # (time s, true ENU) of the last ticks
        self._next_timesync_s = 0.0
        self._next_heartbeat_s = 0.0
        self._announced_origin = False
        self._active: set[int] = set()  # links that have received a message (ArduPilot: "active" channels)
        self._ekf_error = np.zeros(3)  # EKF minus true position, ENU m
        self._ekf_rng = np.random.default_rng(config.seed + 1)  # its own stream: the GPS and flight noise stay as they were
        self.home_set = False
        self.fix_type = 0
        self.ekf_flags = ap.EKF_UNINITIALIZED
        self.prearm_bit = False  # SYS_STATUS's MAV_SYS_STATUS_PREARM_CHECK
        self._boot_steps = self._boot_sequence()
        self._heartbeat_mode = self.model.mode  # the mode the last HEARTBEAT announced
        self.start_unix_us = time.time_ns() // 1000
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self.battery_pct = 100.0
        self.sent_counts: dict[str, int] = {}

    # ----- addresses / lifecycle -----
    def addresses(self) -> list[str]:
        """The endpoints as bound (port 0 resolved), e.g. ``["udp:127.0.0.1:40123"]``."""
        out = []
        for conn in self.links:
            role = getattr(conn, "_dronecal_role", "out")
            if role == "listen" and hasattr(conn, "listen"):
                host, port = conn.listen.getsockname()[:2]
                out.append(f"tcp:{host}:{port}")
            elif role == "listen":
                host, port = conn.port.getsockname()[:2]
                out.append(f"udp:{host}:{port}")
            else:
                host, port = conn.destination_addr
                out.append(f"out udp:{host}:{port}")
        return out

    @property
    def time_s(self) -> float:
        """Vehicle time since boot, seconds."""
        return self.model.time_s

    def start(self) -> SimVehicle:
        """Run in a background thread (tests); :meth:`stop` ends it."""
        self._thread = threading.Thread(target=self.run, name="sim-vehicle", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop the loop and close every link."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        for conn in self.links:
            try:
                conn.close()
            except OSError:
                pass

    def __enter__(self) -> SimVehicle:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def run(self, stop: threading.Event | None = None) -> None:
        """The main loop: receive until the next tick is due (wall clock), step, send telemetry."""
        stop_event = stop or self._stop
        dt = self.config.tick_s
        wall_per_tick = dt / self.config.speedup
        t0 = time.monotonic()
        tick = 0
        while not stop_event.is_set() and not self._stop.is_set():
            due = t0 + (tick + 1) * wall_per_tick
            while True:
                remaining = due - time.monotonic()
                if remaining <= 0:
                    break
                self._receive(remaining)
            if time.monotonic() - due > 0.5:
                # far behind (a loaded machine): slow vehicle time down instead of bursting
                t0 = time.monotonic() - (tick + 1) * wall_per_tick
            with self._lock:
                self._tick(dt)
            tick += 1

    # ----- receiving -----
    def _receive(self, timeout_s: float) -> None:
        fds = {}
        for conn in self.links:
            if conn.fd is not None:
                fds[conn.fd] = conn
        try:
            ready, _, _ = select.select(list(fds), [], [], timeout_s)
        except (OSError, ValueError):
            time.sleep(min(timeout_s, 0.01))
            return
        for fd in ready:
            conn = fds[fd]
            for _ in range(200):
                try:
                    msg = conn.recv_msg()
                except (OSError, ValueError):
                    break
                if msg is None:
                    break
                if msg.get_type() == "BAD_DATA":
                    continue
                with self._lock:
                    self._handle(conn, msg)
                    self._heartbeat_on_mode_change()

    def _heartbeat_on_mode_change(self) -> None:
        """ArduCopter sends a HEARTBEAT on every link at once when the mode changes (after the
        command's ACK): fly-calib-t1.tlog has GUIDED's and AUTO's 0-2 ms after their COMMAND_ACKs,
        none after arming. So a ground station sees every mode, however quickly the next follows."""
        mode = self.model.mode
        if mode != self._heartbeat_mode:
            self._heartbeat_mode = mode
            self._broadcast(self._build("HEARTBEAT"))

    def _handle(self, link: Any, msg: Any) -> None:
        self._active.add(id(link))
        target = getattr(msg, "target_system", 0)
        if target == 0 and msg.get_srcSystem() != self.config.sysid:
            self._route(link, msg)
        if target not in (0, self.config.sysid):
            return
        now = self.model.time_s
        if self.mission.handle(link, msg, now):
            return
        mtype = msg.get_type()
        if mtype == "COMMAND_LONG":
            result = self._command(link, msg)
            self._send_to(link, self.enc.command_ack_encode(msg.command, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        elif mtype == "SET_MODE":
            result = self.model.set_mode(int(msg.custom_mode))
            self._send_to(link, self.enc.command_ack_encode(11, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent()))
        elif mtype == "SET_POSITION_TARGET_GLOBAL_INT":
            if msg.lat_int == 0 and msg.lon_int == 0:
                return
            e, n, _u = geodetic_to_enu(msg.lat_int * 1e-7, msg.lon_int * 1e-7, self.origin.h_m, self.origin)[0]
            up = float(msg.alt) if msg.coordinate_frame in (3, 6, 10, 11) else float(msg.alt) - self.config.home_alt_m
            self.model.guided_goto(np.array([e, n, up]))
        elif mtype == "REQUEST_DATA_STREAM":
            self._request_data_stream(link, int(msg.req_stream_id), int(msg.req_message_rate) if msg.start_stop else 0)
        elif mtype == "PARAM_SET":
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id.decode().rstrip("\x00")
            if self._set_param(name, float(msg.param_value)) is not None:
                self._broadcast_active(self._param_value(name))  # ArduPilot announces a change on every active link
        elif mtype == "PARAM_REQUEST_READ":
            name = msg.param_id.rstrip("\x00") if isinstance(msg.param_id, str) else msg.param_id.decode().rstrip("\x00")
            if name in self.params:
                self._send_to(link, self._param_value(name))
        elif mtype == "PARAM_REQUEST_LIST":
            for name in self.params:
                self._send_to(link, self._param_value(name))

    def _command(self, link: Any, msg: Any) -> int:
        cmd = int(msg.command)
        m = self.model
        if cmd == ap.CMD_COMPONENT_ARM_DISARM:
            if msg.param1 >= 0.5:
                return m.arm()
            return m.disarm(force=int(msg.param2) == ap.ARM_FORCE_MAGIC)
        if cmd == ap.CMD_DO_SET_MODE:
            return m.set_mode(int(msg.param2))
        if cmd == ap.CMD_MISSION_START:
            return m.mission_start()
        if cmd == ap.CMD_NAV_TAKEOFF:
            return m.guided_takeoff(float(msg.param7))
        if cmd == ap.CMD_NAV_RETURN_TO_LAUNCH:
            return m.set_mode(ap.MODE_RTL)
        if cmd == ap.CMD_NAV_LAND:
            return m.set_mode(ap.MODE_LAND)
        if cmd == ap.CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(link, int(msg.param1), float(msg.param2))
        if cmd == ap.CMD_REQUEST_MESSAGE:
            name = self._message_name(int(msg.param1))
            if name is None:
                return ap.MAV_RESULT_UNSUPPORTED
            out = self._build(name)
            if out is None:
                return ap.MAV_RESULT_FAILED
            self._send_to(link, out)
            return ap.MAV_RESULT_ACCEPTED
        return ap.MAV_RESULT_UNSUPPORTED

    def _message_name(self, msgid: int) -> str | None:
        cls = self.dialect.mavlink_map.get(msgid)
        return None if cls is None else cls.msgname

    def _set_interval(self, link: Any, msgid: int, interval_us: float) -> int:
        """SET_MESSAGE_INTERVAL: for the link it came on only (ArduPilot keeps intervals per channel)."""
        name = self._message_name(msgid)
        if name is None:
            return ap.MAV_RESULT_UNSUPPORTED
        streams = self.streams[id(link)]
        if interval_us < 0:
            streams.interval_s[name] = None
        elif interval_us == 0:
            streams.interval_s.pop(name, None)  # back to the group's rate
        else:
            streams.interval_s[name] = interval_us * 1e-6
        streams.next_due_s[name] = self._on_grid(streams.period_s(name))
        return ap.MAV_RESULT_ACCEPTED

    def _request_data_stream(self, link: Any, stream_id: int, rate_hz: int) -> None:
        """REQUEST_DATA_STREAM: a group's (or with id 0 every group's) rate on this link, as its MAVn_* parameter."""
        index = self.links.index(link)
        groups = list(STREAM_GROUPS) if stream_id == MAV_DATA_STREAM_ALL else [_GROUP_BY_ID.get(stream_id)]
        for group in groups:
            if group is not None:
                self._set_param(f"MAV{index + 1}_{group}", float(rate_hz))

    def _set_param(self, name: str, value: float) -> float | None:
        """Set a parameter this simulator knows (MAVn_*, GPS_RATE_MS); None for any other name (ignored, as ArduPilot)."""
        name = name.upper()
        if name == "GPS_RATE_MS":
            self.params[name] = max(50.0, value)
            return self.params[name]
        parsed = parse_stream_param(name)
        if parsed is None or name not in self.params:
            return None
        index, group = parsed
        self.params[name] = max(0.0, value)
        streams = self.streams[id(self.links[index])]
        streams.group_hz[group] = self.params[name]
        for message in STREAM_GROUPS[group][1]:
            streams.next_due_s.setdefault(message, self._on_grid(streams.period_s(message)))
        return self.params[name]

    def _on_grid(self, period_s: float | None) -> float:
        """The next multiple of ``period_s`` of vehicle time: streams and GPS fixes share one grid, as on
        SITL, so a fix goes out GPS_LAG_S after its time (not a tick later)."""
        now = self.model.time_s
        if not period_s:
            return now
        return math.ceil(now / period_s - 1e-6) * period_s

    def _param_value(self, name: str) -> Any:
        names = list(self.params)
        return self.enc.param_value_encode(name.encode("ascii"), float(self.params[name]), 9, len(names), names.index(name))

    # ----- sending -----
    def _send_to(self, link: Any, msg: Any) -> None:
        try:
            link.mav.send(msg)
        except (OSError, ValueError):
            return
        name = msg.get_type()
        self.sent_counts[name] = self.sent_counts.get(name, 0) + 1

    def _broadcast(self, msg: Any) -> None:
        for conn in self.links:
            self._send_to(conn, msg)

    def _route(self, source: Any, msg: Any) -> None:
        """ArduPilot's MAVLink routing of a client's broadcast (a HEARTBEAT, untargeted): to every other
        active link, byte for byte, so a ground station and fly hear of each other."""
        buf = msg.get_msgbuf()
        for conn in self.links:
            if conn is not source and id(conn) in self._active:
                try:
                    conn.write(buf)
                except (OSError, ValueError):
                    pass

    def _broadcast_active(self, msg: Any) -> None:
        """To the links a client has spoken on: ArduPilot sends STATUSTEXT and MISSION_ITEM_REACHED to
        active channels only, so a listen-only client hears none (recorded on SERIAL1)."""
        for conn in self.links:
            if id(conn) in self._active:
                self._send_to(conn, msg)

    # ----- boot -----
    def _boot_sequence(self) -> list[tuple[float, str]]:
        # ArduCopter 4.7 SITL (copter.parm, -w; tests/test_sitl_conformance.py): u-blox detected
        # (fix 1) at 9.76 s, RTK fixed at 10.06 s, origin set at ~12 s, SYS_STATUS's pre-arm bit at
        # ~23.7 s while arming is still refused ("PreArm: Need Position Estimate"), EKF healthy and
        # armable at ~41.8 s: the steps keep those fractions of boot_s (default 41.8 s, the firmware's).
        b = self.config.boot_s
        return [
            (0.0, "banner"),
            (0.1 * b, "ekf_init"),
            (0.2335 * b, "gps_detected"),
            (0.2407 * b, "gps_rtk"),
            (0.29 * b, "origin"),
            (0.567 * b, "prearm_bit"),  # 23.7 s: SYS_STATUS says pre-arm checks pass, yet arming is refused
            (1.0 * b, "ekf_gps"),
            (1.0 * b, "ready"),  # 41.8 s, the same tick: the EKF has a position, arming is accepted
        ]

    def _boot(self, now_s: float) -> None:
        while self._boot_steps and self._boot_steps[0][0] <= now_s:
            _, step = self._boot_steps.pop(0)
            say = self.model.say
            if step == "banner":
                say("ArduCopter V4.7.0-dev (dronecal-field sim)")
                say("Frame: QUAD/PLUS")
                say("ArduPilot Ready")
            elif step == "ekf_init":
                self.ekf_flags = ap.EKF_ATTITUDE | ap.EKF_VELOCITY_VERT | ap.EKF_POS_VERT_ABS | ap.EKF_CONST_POS_MODE
                say("EKF3 IMU0 initialised")
                say("AHRS: EKF3 active")
            elif step == "gps_detected":
                self.fix_type = 1
                say("GPS 1: detected u-blox")
            elif step == "gps_rtk":
                self.fix_type = ap.GPS_FIX_TYPE_RTK_FIXED
            elif step == "origin":
                self.home_set = True
                say("EKF3 IMU0 origin set")
                say(f"Field Elevation Set: {self.config.home_alt_m:.0f}m")
            elif step == "ekf_gps":
                self.ekf_flags = ap.EKF_HEALTHY_FLAGS
                say("EKF3 IMU0 is using GPS")
            elif step == "prearm_bit":
                self.prearm_bit = True
            elif step == "ready":
                self.prearm_bit = True
                self.model.ready = True

    # ----- one tick -----
    def _tick(self, dt: float) -> None:
        m = self.model
        m.step(dt)
        self._heartbeat_on_mode_change()  # a mode the mission or a failsafe chose
        self._ekf_step(dt)
        now = m.time_s
        self._boot(now)
        self.mission.update(now)
        if m.armed and not m.landed:
            self.battery_pct = max(0.0, self.battery_pct - dt / 30.0)  # about 1 % per 30 s of flight
        # event messages first, so a REACHED precedes the position that follows it
        for seq in m.reached:
            self._broadcast_active(self.enc.mission_item_reached_encode(seq))
        m.reached.clear()
        for severity, text in m.texts:
            self._broadcast_active(self.enc.statustext_encode(severity, text.encode("utf-8")[:50], 0, 0))
        m.texts.clear()
        self._gps_step(now)
        # every link: HEARTBEAT at 1 Hz, a TIMESYNC now and then, origin and home once
        built: dict[str, Any] = {}
        if now + 1e-9 >= self._next_heartbeat_s:
            self._next_heartbeat_s = max(self._next_heartbeat_s + 1.0, now + 0.5)
            self._broadcast(self._build_once("HEARTBEAT", built))
        if now + 1e-9 >= self._next_timesync_s:
            self._next_timesync_s = now + TIMESYNC_PERIOD_S
            self._broadcast(self.enc.timesync_encode(0, int(now * 1e9)))
        if self.home_set and not self._announced_origin:
            self._announced_origin = True
            self._broadcast(self._build_once("GPS_GLOBAL_ORIGIN", built))
            self._broadcast(self._build_once("HOME_POSITION", built))
        # then what each link asked for, built once per tick so every link carries the same values
        for conn in self.links:
            streams = self.streams[id(conn)]
            for name, period in streams.streamed():
                if name == "HEARTBEAT":
                    continue
                due = streams.next_due_s.get(name, now)
                if now + 1e-9 >= due:
                    msg = self._build_once(name, built)
                    if msg is not None:
                        self._send_to(conn, msg)
                    # keep the schedule on the grid, but never fire a backlog
                    streams.next_due_s[name] = max(due + period, now + period * 0.5)

    def _ekf_step(self, dt: float) -> None:
        """The EKF's horizontal error: a slow random walk around the truth in the air, none on the ground."""
        c = self.config
        if self.model.landed or c.ekf_sigma_m <= 0:
            self._ekf_error[:] = 0.0
            return
        k = dt / c.ekf_tau_s
        self._ekf_error[:2] += -self._ekf_error[:2] * k + c.ekf_sigma_m * math.sqrt(2.0 * k) * self._ekf_rng.standard_normal(2)

    def _build_once(self, name: str, built: dict[str, Any]) -> Any | None:
        if name not in built:
            built[name] = self._build(name)
        return built[name]

    def _gps_step(self, now: float) -> None:
        """The receiver: every GPS_RATE_MS a new fix, measured GPS_LAG_S before the tick that publishes it."""
        self._history.append((now, self.model.position.copy()))
        del self._history[:-20]
        if now + 1e-9 < self._next_fix_s:
            return
        period = self.params["GPS_RATE_MS"] * 1e-3
        self._next_fix_s = math.ceil(now / period + 0.5) * period
        if now < GPS_LAG_S:
            return  # no fix measured before boot (a negative time_usec would not even pack)
        t_fix = now - GPS_LAG_S
        c = self.config
        noise = self.rng.standard_normal(3) * np.array([c.gnss_sigma_h_m, c.gnss_sigma_h_m, c.gnss_sigma_v_m])
        self._last_fix = (t_fix, self._position_at(t_fix) + noise)

    def _position_at(self, t_s: float) -> np.ndarray:
        """True ENU position at vehicle time ``t_s`` (linear between the remembered ticks)."""
        times = np.array([t for t, _p in self._history])
        if len(times) == 0:
            return self.model.position.copy()
        positions = np.array([p for _t, p in self._history])
        return np.array([np.interp(t_s, times, positions[:, k]) for k in range(3)])

    # ----- message builders -----
    def _ekf_position(self) -> np.ndarray:
        """ENU metres the EKF reports (GLOBAL_POSITION_INT, LOCAL_POSITION_NED): the truth plus its error."""
        return self.model.position + self._ekf_error

    def _geodetic(self, truth: bool = False) -> tuple[float, float, float, float]:
        """(lat_deg, lon_deg, h_ellipsoid_m, up_m) of the EKF's position, or of the true one (SIMSTATE)."""
        pos = self.model.position if truth else self._ekf_position()
        lat, lon, h = enu_to_geodetic(pos, self.origin)[0]
        return float(lat), float(lon), float(h), float(pos[2])

    def _home_item(self) -> MissionItem:
        c = self.config
        return MissionItem(
            seq=0, frame=mf.FRAME_GLOBAL, command=mf.CMD_NAV_WAYPOINT, x=int(round(c.home_lat_deg * 1e7)), y=int(round(c.home_lon_deg * 1e7)), z=float(c.home_alt_m)
        )

    def _item_enu(self, item: MissionItem) -> np.ndarray | None:
        """ENU metres of a mission item's position; ``None`` if lat/lon are 0 ("here")."""
        if item.frame not in mf.GLOBAL_FRAMES or (item.x == 0 and item.y == 0):
            return None
        e, n, _u = geodetic_to_enu(item.x * 1e-7, item.y * 1e-7, self.origin.h_m, self.origin)[0]
        if item.frame in (mf.FRAME_GLOBAL, mf.FRAME_GLOBAL_INT):
            up = float(item.z) - self.config.home_alt_m
        else:
            up = float(item.z)
        return np.array([e, n, up])

    def _heartbeat_base_mode(self) -> int:
        m = self.model
        base = ap.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | ap.MAV_MODE_FLAG_STABILIZE_ENABLED | ap.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        if m.mode in _GUIDED_FLAG_MODES:  # armed or not: AUTO after the landing is 89 on 4.7 SITL
            base |= ap.MAV_MODE_FLAG_GUIDED_ENABLED
        if m.armed:
            base |= ap.MAV_MODE_FLAG_SAFETY_ARMED
        return base

    def _roll_pitch_rad(self) -> tuple[float, float]:
        """Roll and pitch of a copter accelerating as the model does (level on the ground), radians."""
        m = self.model
        if m.landed:
            return 0.0, 0.0
        a = m.accel
        h = math.radians(m.heading_deg)
        fwd = a[0] * math.sin(h) + a[1] * math.cos(h)
        right = a[0] * math.cos(h) - a[1] * math.sin(h)
        return math.atan2(right, 9.80665), -math.atan2(fwd, 9.80665)

    def _build(self, name: str) -> Any | None:
        m = self.model
        c = self.config
        enc = self.enc
        boot_ms = int(round(m.time_s * 1000.0))
        if name == "HEARTBEAT":
            state = ap.MAV_STATE_ACTIVE if m.armed else ap.MAV_STATE_STANDBY
            return enc.heartbeat_encode(ap.MAV_TYPE_QUADROTOR, ap.MAV_AUTOPILOT_ARDUPILOTMEGA, self._heartbeat_base_mode(), m.mode, state, 3)
        if name == "SYS_STATUS":
            health = (_SENSORS_HEALTH_OK if self.ekf_flags == ap.EKF_HEALTHY_FLAGS else _SENSORS_HEALTH_BOOT) | (ap.MAV_SYS_STATUS_PREARM_CHECK if self.prearm_bit else 0)
            current_ca = 1500 if (m.armed and not m.landed) else 0
            return enc.sys_status_encode(
                _SENSORS_PRESENT, _SENSORS_ENABLED, health, 0, 12600, current_ca, int(self.battery_pct), 0, 0, 0, 0, 0, 0, 0, 0, 0
            )
        if name == "GPS_RAW_INT":
            fix = self._last_fix
            if self.fix_type < 2 or fix is None:
                return enc.gps_raw_int_encode(int(m.time_s * 1e6), self.fix_type, 0, 0, 0, 65535, 65535, 0, 0, 0, 0, 0, 0, 0, 0, 0)
            t_fix, pos = fix
            lat, lon, h = enu_to_geodetic(pos, self.origin)[0]
            speed = float(np.hypot(m.vel[0], m.vel[1]))
            cog = int(round(math.degrees(math.atan2(m.vel[0], m.vel[1])) % 360.0 * 100)) if speed > 0.05 else 0
            acc = int(c.gps_reported_acc_mm)
            # ArduCopter 4.7 SITL (u-blox, RTK fixed): eph 121, epv 200, 10 satellites, h_acc = v_acc = 300 mm
            return enc.gps_raw_int_encode(
                int(round(t_fix * 1e6)),
                self.fix_type,
                int(round(lat * 1e7)),
                int(round(lon * 1e7)),
                int(round((h - c.geoid_sep_m) * 1000)),
                121,
                200,
                int(round(speed * 100)),
                cog,
                10,
                int(round(h * 1000)),
                acc,
                acc,
                0,
                0,
                0,
            )
        if name == "SIMSTATE":
            # SITL's truth: the simulated body's own position and attitude (here the reported
            # position is the truth too; a client that renders the vehicle should prefer this)
            if not self.home_set:
                return None
            lat, lon, _h, _up = self._geodetic(truth=True)
            roll, pitch = self._roll_pitch_rad()
            yaw = math.remainder(math.radians(m.heading_deg), 2.0 * math.pi)
            return enc.simstate_encode(roll, pitch, yaw, 0.0, 0.0, -9.80665, 0.0, 0.0, 0.0, int(round(lat * 1e7)), int(round(lon * 1e7)))
        if name == "GPS_GLOBAL_ORIGIN":
            return enc.gps_global_origin_encode(
                int(round(c.home_lat_deg * 1e7)), int(round(c.home_lon_deg * 1e7)), int(round(c.home_alt_m * 1000)), int(m.time_s * 1e6)
            )
        if name == "GLOBAL_POSITION_INT":
            hdg = int(round(m.heading_deg * 100)) % 36000
            if not self.home_set:
                return enc.global_position_int_encode(boot_ms, 0, 0, 0, 0, 0, 0, 0, hdg)
            lat, lon, h, up = self._geodetic()
            v = m.vel
            return enc.global_position_int_encode(
                boot_ms,
                int(round(lat * 1e7)),
                int(round(lon * 1e7)),
                int(round((h - c.geoid_sep_m) * 1000)),
                int(round(up * 1000)),
                int(round(v[1] * 100)),
                int(round(v[0] * 100)),
                int(round(-v[2] * 100)),
                hdg,
            )
        if name == "ATTITUDE":
            h = math.radians(m.heading_deg)
            roll, pitch = self._roll_pitch_rad()
            yaw_noise = math.radians(0.05) * float(self.rng.standard_normal()) if not m.landed else 0.0
            yaw = math.remainder(h + yaw_noise, 2.0 * math.pi)
            return enc.attitude_encode(boot_ms, roll, pitch, yaw, 0.0, 0.0, 0.0)
        if name == "SYSTEM_TIME":
            # SITL: unix time starts at the host clock and advances at vehicle rate
            return enc.system_time_encode(self.start_unix_us + int(m.time_s * 1e6), boot_ms)
        if name == "EKF_STATUS_REPORT":
            good = self.ekf_flags == ap.EKF_HEALTHY_FLAGS
            var = 0.01 if good else 0.0
            return enc.ekf_status_report_encode(self.ekf_flags, var, var * 0.6, var * 0.05, var * 0.8, 0.0, 0.0)
        if name == "BATTERY_STATUS":
            current_ca = 1500 if (m.armed and not m.landed) else 0
            return enc.battery_status_encode(
                0, 0, 0, 32767, [12600] + [65535] * 9, current_ca, -1, -1, int(self.battery_pct), 0, 1, [0, 0, 0, 0], 0, 0
            )
        if name == "HOME_POSITION":
            if not self.home_set:
                return None
            return enc.home_position_encode(
                int(round(c.home_lat_deg * 1e7)),
                int(round(c.home_lon_deg * 1e7)),
                int(round(c.home_alt_m * 1000)),
                0.0,
                0.0,
                0.0,
                [1.0, 0.0, 0.0, 0.0],
                0.0,
                0.0,
                0.0,
                int(m.time_s * 1e6),
            )
        if name == "MISSION_CURRENT":
            total = max(0, len(self.mission.items) - 1)
            return enc.mission_current_encode(m.current_seq, total, m.mission_state, 1 if m.mode == ap.MODE_AUTO else 0)
        if name == "LOCAL_POSITION_NED":
            # not in the default streams; ArduPilot sends it on request (the recorded SITL had it at 5 Hz):
            # float metres and m/s, north-east-down from the EKF origin (home here)
            if not self.home_set:
                return None
            pos, v = self._ekf_position(), m.vel
            return enc.local_position_ned_encode(boot_ms, float(pos[1]), float(pos[0]), float(-pos[2]), float(v[1]), float(v[0]), float(-v[2]))
        if name == "AUTOPILOT_VERSION":
            return enc.autopilot_version_encode(
                0xFFFF, (4 << 24) | (7 << 16) | (0 << 8), 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, c.sysid, [0] * 18
            )
        return None
