"""Flight control from the GCS: telemetry requests and the one start sequence we ever send.

``fly`` commands the vehicle only when the pilot asked for it with ``--start``:
GUIDED, arm, then MAV_CMD_MISSION_START, the sequence that works on ArduCopter
4.7 (arming in AUTO is refused; GUIDED-arm then a bare switch to AUTO leaves it
on the ground until it disarms itself: shared/replays/arducopter-sitl README).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

from dronecal_field.errors import LinkError
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import px4
from dronecal_field.mavlink.link import MavLink

# Telemetry the recorder needs, in Hz. GNSS at 10 Hz, what an RTK receiver gives
# and what the calibration assumes (the recorded SITL session asked for 5 Hz).
TELEMETRY_RATES_HZ: tuple[tuple[str, float], ...] = (
    ("GPS_RAW_INT", 10.0),
    ("GLOBAL_POSITION_INT", 10.0),
    ("ATTITUDE", 10.0),
    ("SYS_STATUS", 2.0),
    ("EKF_STATUS_REPORT", 2.0),
    ("BATTERY_STATUS", 2.0),
    ("MISSION_CURRENT", 2.0),
    ("SYSTEM_TIME", 1.0),
    ("HOME_POSITION", 0.5),
)
# PX4 sends no EKF_STATUS_REPORT: ESTIMATOR_STATUS has the same flag bits (measured on 1.16 SITL)
PX4_TELEMETRY_RATES_HZ: tuple[tuple[str, float], ...] = tuple(
    ("ESTIMATOR_STATUS", hz) if name == "EKF_STATUS_REPORT" else (name, hz) for name, hz in TELEMETRY_RATES_HZ
)


def telemetry_rates(link: MavLink) -> tuple[tuple[str, float], ...]:
    """The rates ``fly`` asks for from this vehicle (ArduPilot's or PX4's message set)."""
    return PX4_TELEMETRY_RATES_HZ if link.is_px4 else TELEMETRY_RATES_HZ


@dataclass(frozen=True)
class VehicleState:
    """What the last HEARTBEAT says.

    Attributes
    ----------
    mode : int
        HEARTBEAT.custom_mode (ArduCopter's mode number; PX4's packed main/sub mode).
    mode_name : str
        ``AUTO``, ``GUIDED``, ... or ``MODE<n>``; PX4: ``AUTO.MISSION``, ``AUTO.LOITER``...
    armed : bool
        Motors armed.
    """

    mode: int
    mode_name: str
    armed: bool


def vehicle_state(link: MavLink) -> VehicleState | None:
    """The vehicle's mode and arming state from its last HEARTBEAT (``None`` before the first)."""
    hb = link.vehicle_heartbeat
    if hb is None:
        return None
    mode = int(hb.custom_mode)
    name = px4.mode_name(mode) if px4.is_px4(int(hb.autopilot)) else ap.MODE_NAMES.get(mode, f"MODE{mode}")
    return VehicleState(mode=mode, mode_name=name, armed=bool(hb.base_mode & ap.MAV_MODE_FLAG_SAFETY_ARMED))


def request_telemetry(link: MavLink, rates_hz: tuple[tuple[str, float], ...] | None = None) -> dict[str, int]:
    """Ask for each message at its rate with MAV_CMD_SET_MESSAGE_INTERVAL (no flight effect).

    Returns
    -------
    dict
        Message name -> MAV_RESULT (a vehicle that already streams may refuse; that is fine).
    """
    results = {}
    for name, hz in telemetry_rates(link) if rates_hz is None else rates_hz:
        msgid = getattr(link.dialect, f"MAVLINK_MSG_ID_{name}")
        try:
            results[name] = link.command_long(ap.CMD_SET_MESSAGE_INTERVAL, (msgid, 1e6 / hz), timeout_s=0.5, retries=1)
        except LinkError:
            results[name] = -1
    return results


class StreamKeeper:
    """Asks again for a requested stream that stopped while the vehicle still talks.

    ArduPilot 4.7 streams nothing on a link until asked and forgets what was
    asked when it reboots; a SET_MESSAGE_INTERVAL lost on a radio link leaves
    that stream silent for good. Feed it every message (a :class:`MavLink`
    listener) and call :meth:`check` now and then (``fly``'s status loop, once
    a second): a message of ``rates_hz`` unseen for ``max(3 periods,
    min_silence_s)`` while HEARTBEATs arrive is asked for again (without
    waiting for the ACK, at most once per ``min_silence_s``), on this link only.

    Parameters
    ----------
    link : MavLink
        The link the streams were asked on.
    rates_hz : tuple of (str, float)
        What was asked, Hz.
    min_silence_s : float
        Shortest silence (host seconds) that counts as a stopped stream.
    """

    def __init__(self, link: MavLink, rates_hz: tuple[tuple[str, float], ...] | None = None, min_silence_s: float = 3.0) -> None:
        self.link = link
        self.rates_hz = tuple(telemetry_rates(link) if rates_hz is None else rates_hz)
        self.min_silence_s = float(min_silence_s)
        now = time.monotonic()
        self._last_seen = {name: now for name, _hz in self.rates_hz}
        self._last_ask = {name: now for name, _hz in self.rates_hz}
        self.re_requests = 0  # SET_MESSAGE_INTERVAL sent again, all messages counted

    def feed(self, direction: str, _stamp_ns: int, msg: Any) -> None:
        """A message in or out (a :class:`MavLink` listener)."""
        if direction == "in" and msg.get_srcSystem() == self.link.target_system:
            name = msg.get_type()
            if name in self._last_seen:
                self._last_seen[name] = time.monotonic()

    def check(self) -> list[str]:
        """Ask again for the streams that stopped; returns their names."""
        now = time.monotonic()
        if self.link.last_heartbeat_monotonic is None or now - self.link.last_heartbeat_monotonic > self.min_silence_s:
            return []  # the vehicle itself is silent: a lost link, not a forgotten request
        asked = []
        for name, hz in self.rates_hz:
            silence = max(3.0 / hz, self.min_silence_s)
            if now - self._last_seen[name] > silence and now - self._last_ask[name] > self.min_silence_s:
                msgid = getattr(self.link.dialect, f"MAVLINK_MSG_ID_{name}")
                self.link.send(self.link.dialect.MAVLink_command_long_message(
                    self.link.target_system, self.link.target_component, ap.CMD_SET_MESSAGE_INTERVAL, 0, msgid, 1e6 / hz, 0, 0, 0, 0, 0))
                self._last_ask[name] = now
                asked.append(name)
        self.re_requests += len(asked)
        return asked


def _last_statustext(link: MavLink) -> str:
    msg = link.latest("STATUSTEXT")
    return "" if msg is None else f" ({msg.text})"


def arm_and_start_mission(link: MavLink, timeout_s: float = 2.0) -> None:
    """GUIDED, arm, MAV_CMD_MISSION_START: the start the pilot asked for with ``--start``.

    On PX4 (HEARTBEAT autopilot 12): MAV_CMD_MISSION_START alone, which arms
    and switches to AUTO.MISSION (PX4 1.16 SITL); no GUIDED (PX4 has none).

    Raises
    ------
    LinkError
        A step was refused, with the vehicle's last STATUSTEXT (e.g. a PreArm reason).
    """
    if link.is_px4:
        _px4_arm_and_start(link, timeout_s)
        return
    result = link.set_mode("GUIDED", timeout_s=timeout_s)
    if result != ap.MAV_RESULT_ACCEPTED:
        raise LinkError(f"vehicle refused GUIDED mode ({ap.MAV_RESULT_NAMES.get(result, result)}){_last_statustext(link)}; check the mode switch and GPS")
    result = link.command_long(ap.CMD_COMPONENT_ARM_DISARM, (1,), timeout_s=timeout_s)
    if result != ap.MAV_RESULT_ACCEPTED:
        time.sleep(0.2)  # let the PreArm STATUSTEXT arrive
        raise LinkError(f"vehicle refused to arm ({ap.MAV_RESULT_NAMES.get(result, result)}){_last_statustext(link)}; fix the pre-arm failure and retry")
    result = link.command_long(ap.CMD_MISSION_START, timeout_s=timeout_s)
    if result != ap.MAV_RESULT_ACCEPTED:
        raise LinkError(f"vehicle refused MISSION_START ({ap.MAV_RESULT_NAMES.get(result, result)}){_last_statustext(link)}; it is armed in GUIDED: disarm or take over")


def _px4_arm_and_start(link: MavLink, timeout_s: float, valid_wait_s: float = 15.0) -> None:
    """MAV_CMD_MISSION_START alone: PX4 arms and switches to AUTO.MISSION in one command.

    PX4 answers DENIED until its navigator has checked the new mission
    (``mission_result.valid``), a moment after the upload; so DENIED is
    retried each second for ``valid_wait_s``. Nothing is armed until accepted.
    """
    deadline = time.monotonic() + valid_wait_s
    while True:
        result = link.command_long(ap.CMD_MISSION_START, (0, 0), timeout_s=timeout_s)
        if result == ap.MAV_RESULT_ACCEPTED:
            return
        if result not in (ap.MAV_RESULT_DENIED, ap.MAV_RESULT_TEMPORARILY_REJECTED) or time.monotonic() >= deadline:
            break
        time.sleep(1.0)
    raise LinkError(f"PX4 refused MISSION_START ({ap.MAV_RESULT_NAMES.get(result, result)}){_last_statustext(link)} for {valid_wait_s:g} s; "
                    "its reasons come as events (QGroundControl shows them): a mission it finds infeasible, or a failed pre-arm check")


def describe_heartbeat(msg: Any) -> str:
    """``ArduPilot quadrotor, GUIDED, disarmed`` for a HEARTBEAT."""
    autopilot = "ArduPilot" if msg.autopilot == ap.MAV_AUTOPILOT_ARDUPILOTMEGA else ("PX4" if px4.is_px4(msg.autopilot) else f"autopilot {msg.autopilot}")
    kind = "quadrotor" if msg.type == ap.MAV_TYPE_QUADROTOR else f"type {msg.type}"
    if px4.is_px4(msg.autopilot):
        mode = px4.mode_name(int(msg.custom_mode))
    else:
        mode = ap.MODE_NAMES.get(int(msg.custom_mode), f"mode {msg.custom_mode}")
    armed = "armed" if msg.base_mode & ap.MAV_MODE_FLAG_SAFETY_ARMED else "disarmed"
    return f"{autopilot} {kind}, {mode}, {armed}"
