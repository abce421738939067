"""Client side of the MAVLink mission protocol: upload, read back, verify.

Upload: MISSION_COUNT; answer every MISSION_REQUEST_INT *and* MISSION_REQUEST
(id 40, what ArduCopter 4.7 sends) with MISSION_ITEM_INT; finished by the
vehicle's MISSION_ACK. Built for lossy radios: a MISSION_COUNT nobody answers
is sent again, duplicate requests are answered again, a lost final ACK is
recovered by repeating the last item (the vehicle acknowledges again), and the
read-back is the final word. MISSION_ACK NO_SPACE while the vehicle is still
booting (not yet ready to arm) means "try again later", so we wait and retry.

Read back: MISSION_REQUEST_LIST -> MISSION_COUNT, MISSION_REQUEST_INT per seq ->
MISSION_ITEM_INT, then MISSION_ACK; each step re-sent on timeout.
Verification follows :func:`dronecal_field.mavlink.missionfile.compare_readback`.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from dronecal_field.errors import LinkError, MissionRejectedError
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import px4
from dronecal_field.mavlink.link import MavLink
from dronecal_field.mavlink.missionfile import MissionItem, compare_readback, item_from_message, storage_changes, wire_frame

_UPLOAD_TYPES = frozenset({"MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_ACK"})
_DOWNLOAD_TYPES = frozenset({"MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_ITEM", "MISSION_ACK"})


@dataclass(frozen=True)
class UploadReport:
    """What an upload took.

    Attributes
    ----------
    items : int
        Items uploaded (home included).
    count_sends : int
        MISSION_COUNT messages sent (1 on a clean link).
    item_sends : int
        MISSION_ITEM_INT messages sent (``items`` on a clean link).
    no_space_retries : int
        Uploads refused with NO_SPACE while the vehicle booted.
    duration_s : float
        Wall seconds from the first MISSION_COUNT to the verified read-back.
    readback : tuple of MissionItem
        The mission as the vehicle holds it.
    storage_changes : tuple of str
        Where the vehicle stores an item differently from the file, as
        ArduCopter is known to (e.g. NAV_WAYPOINT yaw dropped); verified, not errors.
    """

    items: int
    count_sends: int
    item_sends: int
    no_space_retries: int
    duration_s: float
    readback: tuple[MissionItem, ...]
    storage_changes: tuple[str, ...] = ()


def _from_us(link: MavLink, msg: Any) -> bool:
    """A mission message from the vehicle addressed to us (or to everyone), for the plain mission."""
    if link.target_system and msg.get_srcSystem() != link.target_system:
        return False
    if getattr(msg, "target_system", 0) not in (0, link.source_system):
        return False
    return getattr(msg, "mission_type", 0) == 0


def _vehicle_ready(link: MavLink) -> bool:
    status = link.latest("SYS_STATUS")
    return status is not None and bool(status.onboard_control_sensors_health & ap.MAV_SYS_STATUS_PREARM_CHECK)


def _item_message(link: MavLink, item: MissionItem) -> Any:
    return link.dialect.MAVLink_mission_item_int_message(
        link.target_system,
        link.target_component,
        item.seq,
        wire_frame(item),
        item.command,
        0,
        int(item.autocontinue),
        item.p1,
        item.p2,
        item.p3,
        item.p4,
        item.x,
        item.y,
        item.z,
        0,
    )


def _mission_result_name(code: int) -> str:
    return f"MAV_MISSION_{ap.MAV_MISSION_RESULT_NAMES.get(code, str(code))}"


def send_mission(
    link: MavLink,
    items: Sequence[MissionItem],
    *,
    timeout_s: float = 1.5,
    retries: int = 5,
    ready_timeout_s: float = 120.0,
    no_space_wait_s: float = 1.0,
) -> tuple[int, int, int]:
    """Upload ``items`` (seq 0 = home) without reading back.

    Parameters
    ----------
    link : MavLink
        Open link that has seen the vehicle's heartbeat.
    items : sequence of MissionItem
        Seqs 0..n-1 in order.
    timeout_s : float
        Wall seconds of silence before re-sending.
    retries : int
        Re-sends allowed per step before giving up.
    ready_timeout_s : float
        How long NO_SPACE is retried while the vehicle is not ready to arm.
    no_space_wait_s : float
        Pause before retrying after NO_SPACE.

    Returns
    -------
    (count_sends, item_sends, no_space_retries)

    Raises
    ------
    MissionRejectedError
        The vehicle refused the mission (an ACK other than ACCEPTED).
    LinkError
        The vehicle stopped answering.
    """
    if not items or any(item.seq != i for i, item in enumerate(items)):
        raise MissionRejectedError("mission items must be numbered 0..n-1 (home at 0 on ArduPilot); re-read the mission file")
    n = len(items)
    count_sends = item_sends = no_space = 0
    ready_deadline = time.monotonic() + ready_timeout_s
    retries_after_ready = 0
    with link.subscribe(_UPLOAD_TYPES) as sub:
        while True:  # one pass per MISSION_COUNT round (NO_SPACE starts a new one)
            link.send(link.dialect.MAVLink_mission_count_message(link.target_system, link.target_component, n, 0))
            count_sends += 1
            requested: set[int] = set()
            last_sent = -1
            silent = 0
            restart = False
            while True:
                msg = sub.get(timeout_s)
                if msg is None:
                    silent += 1
                    if silent > retries:
                        what = "MISSION_REQUEST" if not requested else ("MISSION_ACK" if last_sent == n - 1 else f"a request after item {last_sent}")
                        raise LinkError(f"mission upload stalled: no {what} from the vehicle after {retries + 1} tries; check the link and retry")
                    if not requested:
                        link.send(link.dialect.MAVLink_mission_count_message(link.target_system, link.target_component, n, 0))
                        count_sends += 1
                    elif last_sent == n - 1:
                        # our last item or its ACK was lost: the vehicle acknowledges a repeat
                        link.send(_item_message(link, items[n - 1]))
                        item_sends += 1
                    # otherwise the vehicle re-requests the missing item by itself (every second)
                    continue
                if not _from_us(link, msg):
                    continue
                mtype = msg.get_type()
                if mtype in ("MISSION_REQUEST", "MISSION_REQUEST_INT"):
                    silent = 0
                    if 0 <= msg.seq < n:
                        requested.add(msg.seq)
                        link.send(_item_message(link, items[msg.seq]))  # duplicates are answered again
                        item_sends += 1
                        last_sent = msg.seq
                    continue
                # MISSION_ACK
                if msg.type == ap.MAV_MISSION_ACCEPTED:
                    if last_sent == n - 1 or len(requested) == n:
                        return count_sends, item_sends, no_space
                    continue  # a stale ACK from an earlier round
                if msg.type == ap.MAV_MISSION_NO_SPACE:
                    ready = _vehicle_ready(link)
                    if ready:
                        retries_after_ready += 1
                    if (not ready or retries_after_ready <= 1) and time.monotonic() < ready_deadline:
                        # right after boot the mission store is not ready yet (ArduCopter): wait, retry
                        no_space += 1
                        time.sleep(no_space_wait_s)
                        while sub.get(0.0) is not None:
                            pass  # drop what the refused round left behind
                        restart = True
                        break
                    raise MissionRejectedError(
                        f"vehicle refused the mission: {_mission_result_name(msg.type)} for {n} items"
                        + ("" if ready else f" (still not ready to arm after {ready_timeout_s:g} s)")
                        + "; shorten the mission or wait until the vehicle is ready"
                    )
                if msg.type == ap.MAV_MISSION_OPERATION_CANCELLED and not requested:
                    continue
                if msg.type == ap.MAV_MISSION_DENIED and not requested:
                    # ArduPilot: another link's upload is under way (one transfer at a time)
                    raise MissionRejectedError(
                        "vehicle refused the mission: DENIED before any item (another ground station is uploading a mission); "
                        "let it finish, then run fly again (its mission will be replaced by ours)"
                    )
                # the vehicle answers the item it could not take, so the culprit is the last one sent
                bad = items[max(last_sent, 0)]
                where = f" at item {bad.seq}"
                raise MissionRejectedError(
                    f"vehicle refused the mission: {_mission_result_name(msg.type)}{where} (command {bad.command}, frame {bad.frame}); fix that item in the plan"
                )
            if not restart:
                break
    raise LinkError("mission upload ended without an ACK; retry")  # pragma: no cover (loop exits by return/raise)


def download_mission(link: MavLink, *, timeout_s: float = 1.5, retries: int = 5) -> list[MissionItem]:
    """Read the vehicle's mission back (MISSION_REQUEST_LIST, MISSION_REQUEST_INT per item).

    Raises
    ------
    LinkError
        The vehicle stopped answering.
    """
    d = link.dialect
    with link.subscribe(_DOWNLOAD_TYPES) as sub:

        def ask(request: Any, accept: Any, what: str) -> Any:
            for _attempt in range(retries + 1):
                link.send(request)
                deadline = time.monotonic() + timeout_s
                while (left := deadline - time.monotonic()) > 0:
                    msg = sub.get(left)
                    if msg is not None and _from_us(link, msg) and accept(msg):
                        return msg
            raise LinkError(f"mission read-back stalled: no {what} after {retries + 1} tries; check the link and retry")

        count_msg = ask(
            d.MAVLink_mission_request_list_message(link.target_system, link.target_component, 0),
            lambda m: m.get_type() == "MISSION_COUNT",
            "MISSION_COUNT",
        )
        items = []
        for seq in range(count_msg.count):
            msg = ask(
                d.MAVLink_mission_request_int_message(link.target_system, link.target_component, seq, 0),
                lambda m, s=seq: m.get_type() in ("MISSION_ITEM_INT", "MISSION_ITEM") and m.seq == s,
                f"MISSION_ITEM_INT {seq}",
            )
            items.append(item_from_message(msg))
        link.send(d.MAVLink_mission_ack_message(link.target_system, link.target_component, ap.MAV_MISSION_ACCEPTED, 0))
    return items


def upload_and_verify(
    link: MavLink,
    items: Sequence[MissionItem],
    *,
    timeout_s: float = 1.5,
    retries: int = 5,
    ready_timeout_s: float = 120.0,
) -> UploadReport:
    """Upload ``items``, read them back and check they match (the vehicle's read-back rules).

    ``items`` are the file's (seq 0 = home). To PX4 (HEARTBEAT autopilot 12)
    the mission goes without its home item, numbered from 0, with PX4's
    commands (:func:`px4.to_wire`), and is compared with PX4's storage
    (:func:`px4.compare_readback`); the report's ``readback`` is in the
    file's numbering again.

    Raises
    ------
    MissionRejectedError
        Refused, or read back differently.
    LinkError
        The vehicle stopped answering.
    """
    t0 = time.monotonic()
    if link.is_px4:
        wire = px4.to_wire(items)
        count_sends, item_sends, no_space = send_mission(link, wire, timeout_s=timeout_s, retries=retries, ready_timeout_s=ready_timeout_s)
        back_wire = download_mission(link, timeout_s=timeout_s, retries=retries)
        problems = px4.compare_readback(wire, back_wire)
        back = px4.from_wire(back_wire, items[0])
        changes = px4.storage_changes(list(items))
    else:
        count_sends, item_sends, no_space = send_mission(link, items, timeout_s=timeout_s, retries=retries, ready_timeout_s=ready_timeout_s)
        back = download_mission(link, timeout_s=timeout_s, retries=retries)
        problems = compare_readback(list(items), back)
        changes = storage_changes(list(items))
    if problems:
        more = f" (+{len(problems) - 1} more)" if len(problems) > 1 else ""
        raise MissionRejectedError(f"vehicle read the mission back differently: {problems[0]}{more}; re-upload, or check the planner's params")
    return UploadReport(
        items=len(items),
        count_sends=count_sends,
        item_sends=item_sends,
        no_space_retries=no_space,
        duration_s=time.monotonic() - t0,
        readback=tuple(back),
        storage_changes=tuple(changes),
    )


class MissionWatch:
    """Notices the vehicle's mission being changed by another client after ours was uploaded.

    A ground station on another link (QGroundControl, MAVProxy) can upload
    while ``fly`` records; ArduPilot then announces "Flight plan received"
    on every active link and MISSION_CURRENT.total follows the new mission.
    ``fly`` never answers by uploading again (that would fight the pilot's
    ground station); it says so and records on.

    Start feeding it (``link.add_listener(watch.feed)``) before our own
    upload and call :meth:`uploaded` when that upload is verified: our own
    "Flight plan received" is expected once, whenever it arrives (a
    simulator or a busy link may deliver it after the read-back), and
    MISSION_CURRENT.total is compared from then on.

    Parameters
    ----------
    items : int
        Items of our mission, home included.
    vehicle_system : int
        The vehicle's system id (messages from others are ignored).
    """

    def __init__(self, items: int, vehicle_system: int) -> None:
        self.expected_total = int(items) - 1  # MISSION_CURRENT.total counts the items after home
        self.vehicle_system = int(vehicle_system)
        self.changes: list[str] = []
        self._own_texts_left = 1  # our upload's own "Flight plan received"
        self._uploaded = False

    def uploaded(self) -> None:
        """Our upload is done and verified: from now on the vehicle's mission must stay ours."""
        self._uploaded = True

    @property
    def changed(self) -> bool:
        """Someone else changed the mission since ours was uploaded."""
        return bool(self.changes)

    def feed(self, direction: str, _stamp_ns: int, msg: Any) -> None:
        """A message in or out (a :class:`MavLink` listener)."""
        if direction != "in" or msg.get_srcSystem() != self.vehicle_system:
            return
        mtype = msg.get_type()
        if mtype == "STATUSTEXT" and str(msg.text).startswith("Flight plan received"):
            if self._own_texts_left > 0:
                self._own_texts_left -= 1
            else:
                self.changes.append("the vehicle received another flight plan")
        elif self._uploaded and mtype == "MISSION_CURRENT" and int(getattr(msg, "total", 0) or 0) not in (0, self.expected_total):
            # total 0 = not reported (MAVLink 1 or an old firmware); it never goes back to 0 with a mission
            self.changes.append(f"the vehicle's mission now has {int(msg.total) + 1} items, ours {self.expected_total + 1}")
            self.expected_total = int(msg.total)  # said once per change

    def describe(self) -> str:
        """One line for the operator, or "" when nothing changed."""
        if not self.changes:
            return ""
        return f"MISSION CHANGED BY ANOTHER CLIENT ({'; '.join(dict.fromkeys(self.changes))}): the flight no longer follows the plan fly uploaded; fly did not re-upload"
