"""The simulated vehicle's side of the MAVLink mission protocol, ArduPilot style.

Upload: MISSION_COUNT -> MISSION_REQUEST (id 40, never _INT: ArduCopter 4.7
does this) for each item, re-requested every second of vehicle time without
an answer, cancelled after 8 s of silence, closed by MISSION_ACK. Refused with
MISSION_ACK NO_SPACE before the vehicle is ready (just after boot) and for more
items than it can hold. Items are stored as ArduPilot stores them: ``_INT``
frames as their float twins (6 -> 3), location-less commands in frame 0, and
seq 0 is always the vehicle's own home. Storage follows
:func:`dronecal_field.mavlink.missionfile.ardupilot_readback` (what ArduCopter
keeps of each command, checked against the recorded read-back).

Download: MISSION_REQUEST_LIST -> MISSION_COUNT; MISSION_REQUEST_INT ->
MISSION_ITEM_INT; MISSION_REQUEST -> MISSION_ITEM.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import missionfile as mf
from dronecal_field.mavlink.missionfile import MissionItem, ardupilot_check, ardupilot_readback, item_from_message

REQUEST_RESEND_S = 1.0  # ArduPilot: wp_recv_timeout_ms 1000
UPLOAD_TIMEOUT_S = 8.0  # ArduPilot: upload_timeout_ms 8000


@dataclass
class _Upload:
    link: Any
    sysid: int
    compid: int
    count: int
    next_seq: int
    items: list[MissionItem]
    last_request_s: float
    last_receive_s: float


class MissionServer:
    """Mission store and protocol for the simulated vehicle.

    Parameters
    ----------
    encoder : pymavlink MAVLink
        Builds messages (``*_encode``); the shell packs them per link.
    send : callable
        ``send(link, msg)``: send to one link.
    home_item : callable
        ``home_item() -> MissionItem`` for seq 0 (the vehicle's current home).
    is_ready : callable
        ``is_ready() -> bool``: False right after boot, when uploads get NO_SPACE.
    on_mission : callable
        ``on_mission(items)`` after a successful upload (items include home).
    say : callable
        ``say(text)`` for STATUSTEXT ("Flight plan received").
    max_items : int
        Capacity, home included.
    """

    def __init__(
        self,
        encoder: Any,
        send: Callable[[Any, Any], None],
        home_item: Callable[[], MissionItem],
        is_ready: Callable[[], bool],
        on_mission: Callable[[list[MissionItem]], None],
        say: Callable[[str], None],
        max_items: int = 700,
    ) -> None:
        self.enc = encoder
        self.send = send
        self.home_item = home_item
        self.is_ready = is_ready
        self.on_mission = on_mission
        self.say = say
        self.max_items = max_items
        self.items: list[MissionItem] = []
        self.upload: _Upload | None = None
        self._last_upload: tuple[Any, int] | None = None  # (link, count) of the last completed upload

    def stored_items(self) -> list[MissionItem]:
        """The mission as it reads back: home then the stored items."""
        return [self.home_item()] + self.items[1:]

    @property
    def count(self) -> int:
        return max(1, len(self.items))

    def _ack(self, link: Any, sysid: int, compid: int, result: int) -> None:
        self.send(link, self.enc.mission_ack_encode(sysid, compid, result, 0))

    def _request(self, up: _Upload, now_s: float) -> None:
        # ArduCopter: asks with MISSION_REQUEST (id 40) even when the GCS answers with MISSION_ITEM_INT
        self.send(up.link, self.enc.mission_request_encode(up.sysid, up.compid, up.next_seq, 0))
        up.last_request_s = now_s

    def handle(self, link: Any, msg: Any, now_s: float) -> bool:
        """Handle a mission-protocol message; False if ``msg`` is not one."""
        mtype = msg.get_type()
        sysid, compid = msg.get_srcSystem(), msg.get_srcComponent()
        mission_type = getattr(msg, "mission_type", 0)
        if mtype == "MISSION_COUNT":
            if mission_type != 0:
                self._ack(link, sysid, compid, ap.MAV_MISSION_UNSUPPORTED)
            elif self.upload is not None and self.upload.link is not link:
                self._ack(link, sysid, compid, ap.MAV_MISSION_DENIED)  # another GCS is uploading
            elif not self.is_ready():
                # ArduCopter: the mission store is not ready right after boot
                self._ack(link, sysid, compid, ap.MAV_MISSION_NO_SPACE)
            elif msg.count > self.max_items:
                self._ack(link, sysid, compid, ap.MAV_MISSION_NO_SPACE)
            elif msg.count == 0:
                self.items = []
                self.on_mission(self.stored_items())
                self._ack(link, sysid, compid, ap.MAV_MISSION_ACCEPTED)
            else:
                self.upload = _Upload(link, sysid, compid, msg.count, 0, [], now_s, now_s)
                self._request(self.upload, now_s)
            return True
        if mtype in ("MISSION_ITEM_INT", "MISSION_ITEM"):
            if mission_type != 0:
                return True
            up = self.upload
            if up is None or up.link is not link:
                # a repeat of the final item means our MISSION_ACK was lost: say it again
                if self._last_upload is not None and self._last_upload[0] is link and msg.seq == self._last_upload[1] - 1:
                    self._ack(link, sysid, compid, ap.MAV_MISSION_ACCEPTED)
                return True
            up.last_receive_s = now_s
            if msg.seq != up.next_seq:
                return True  # ArduPilot ignores it; the re-request asks again
            item = item_from_message(msg)
            # seq 0 is home: ArduPilot keeps its own, whatever was sent
            result = ardupilot_check(item) if item.seq > 0 else ap.MAV_MISSION_ACCEPTED
            if result != ap.MAV_MISSION_ACCEPTED:
                self.upload = None
                self._ack(link, sysid, compid, result)
                return True
            stored = ardupilot_readback(item) if item.seq > 0 else item
            assert stored is not None  # ardupilot_check accepted it, so it is modelled
            up.items.append(stored)
            up.next_seq += 1
            if up.next_seq < up.count:
                self._request(up, now_s)
                return True
            self.items = up.items
            self.upload = None
            self._last_upload = (link, up.count)
            self.on_mission(self.stored_items())
            self._ack(link, sysid, compid, ap.MAV_MISSION_ACCEPTED)
            self.say("Flight plan received")
            return True
        if mtype == "MISSION_REQUEST_LIST":
            self.send(link, self.enc.mission_count_encode(sysid, compid, self.count if mission_type == 0 else 0, mission_type))
            return True
        if mtype in ("MISSION_REQUEST_INT", "MISSION_REQUEST"):
            items = self.stored_items()
            if mission_type != 0 or not 0 <= msg.seq < len(items):
                self._ack(link, sysid, compid, ap.MAV_MISSION_INVALID_SEQUENCE)
                return True
            item = items[msg.seq]
            if mtype == "MISSION_REQUEST_INT":
                out = self.enc.mission_item_int_encode(
                    sysid, compid, item.seq, item.frame, item.command, 0, int(item.autocontinue), item.p1, item.p2, item.p3, item.p4, item.x, item.y, item.z, 0
                )
            else:
                x = item.x * 1e-7 if item.frame in mf.GLOBAL_FRAMES else float(item.x)
                y = item.y * 1e-7 if item.frame in mf.GLOBAL_FRAMES else float(item.y)
                out = self.enc.mission_item_encode(
                    sysid, compid, item.seq, item.frame, item.command, 0, int(item.autocontinue), item.p1, item.p2, item.p3, item.p4, x, y, item.z, 0
                )
            self.send(link, out)
            return True
        if mtype == "MISSION_CLEAR_ALL":
            if mission_type == 0:
                self.items = []
                self.on_mission(self.stored_items())
            self._ack(link, sysid, compid, ap.MAV_MISSION_ACCEPTED)
            return True
        if mtype == "MISSION_ACK":
            return True  # the GCS closing a download
        return False

    def update(self, now_s: float) -> None:
        """Re-request a missing item, or give up on a silent upload (vehicle time ``now_s``)."""
        up = self.upload
        if up is None:
            return
        if now_s - up.last_receive_s > UPLOAD_TIMEOUT_S:
            self.upload = None
            self._ack(up.link, up.sysid, up.compid, ap.MAV_MISSION_OPERATION_CANCELLED)
        elif now_s - up.last_request_s > REQUEST_RESEND_S:
            self._request(up, now_s)
