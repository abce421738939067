"""PX4's dialect of MAVLink: custom modes, its mission (no home item), its read-back rules.

Measured on PX4 v1.16.0 SITL with SIH (``../shared/sitl/px4-1.16``, README there):

* HEARTBEAT.autopilot is ``MAV_AUTOPILOT_PX4`` (12). ``custom_mode`` packs
  the main mode in bits 16-23 and the sub mode in bits 24-31: boot is
  AUTO.LOITER (``0x03040000``), a running mission AUTO.MISSION
  (``0x04040000``). Modes are asked for with MAV_CMD_DO_SET_MODE(1, main, sub).
* The mission starts at seq 0: there is no home item (ArduPilot's seq 0).
  ``fly`` keeps the file's numbering (seq 0 = home) everywhere and shifts by
  :data:`SEQ_OFFSET` on the wire: upload, read-back, MISSION_CURRENT and
  MISSION_ITEM_REACHED.
* After MISSION_COUNT it asks for item 0 with the old MISSION_REQUEST, then
  with MISSION_REQUEST_INT; both are answered with MISSION_ITEM_INT.
* Read-back: frame 3 (relative altitude) comes back as 6, its ``_INT``
  twin; altitude and params are float32 (3.147 m reads back as
  3.1470000743865967), positions 1e-7 degree integers, DO items keep frame 2;
  a NAV item's yaw (param 4) is kept in float32 radians (236.57 deg reads back
  as 236.56997680664062).
  DO_SET_ROI (201) with ROI mode 3 is stored with param 1 = 0 (ROI none:
  MISSION_START is DENIED right after the upload, as for any mission not yet
  checked, and ACCEPTED 1.5 s later; flown, it turns nothing): the PX4 mission uses
  DO_SET_ROI_LOCATION (195), which it stores and flies (yaw towards the
  point, within 2-3 degrees once turned).
* MISSION_ITEM_REACHED repeats the last reached item about once a second
  for ~10 s, and an item reached just before another (a hold waypoint
  followed by a DO_CHANGE_SPEED) is never reported: only the later seq
  comes. The recorder de-duplicates and counts a skipped item as reached
  with the later one (:class:`ReachedFilter`).
* MAV_CMD_MISSION_START arms and starts in one command.
* No EKF_STATUS_REPORT: ESTIMATOR_STATUS carries the same flag bits (1023 =
  healthy) and test ratios (below 1 is healthy).
* GPS_RAW_INT: fix type 3 (no RTK simulated), h_acc 900 mm, ``time_usec``
  since boot, 5 Hz.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace

from dronecal_field.mavlink import missionfile as mf
from dronecal_field.mavlink.missionfile import MissionItem

MAV_AUTOPILOT_PX4 = 12
HOLD_ACCEPTANCE_M = 0.3  # param 2 of a hold waypoint: the hold starts within 0.3 m of the point
SEQ_OFFSET = 1  # file seq = PX4 seq + SEQ_OFFSET (the file's seq 0 is the planned home)

# PX4 main modes (px4_custom_mode.h)
MAIN_MANUAL = 1
MAIN_ALTCTL = 2
MAIN_POSCTL = 3
MAIN_AUTO = 4
MAIN_ACRO = 5
MAIN_OFFBOARD = 6
MAIN_STABILIZED = 7
# AUTO sub modes
SUB_AUTO_READY = 1
SUB_AUTO_TAKEOFF = 2
SUB_AUTO_LOITER = 3
SUB_AUTO_MISSION = 4
SUB_AUTO_RTL = 5
SUB_AUTO_LAND = 6
SUB_AUTO_PRECLAND = 9

MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (MAIN_MANUAL, 0),
    "ALTCTL": (MAIN_ALTCTL, 0),
    "POSCTL": (MAIN_POSCTL, 0),
    "ACRO": (MAIN_ACRO, 0),
    "OFFBOARD": (MAIN_OFFBOARD, 0),
    "STABILIZED": (MAIN_STABILIZED, 0),
    "AUTO.READY": (MAIN_AUTO, SUB_AUTO_READY),
    "AUTO.TAKEOFF": (MAIN_AUTO, SUB_AUTO_TAKEOFF),
    "AUTO.LOITER": (MAIN_AUTO, SUB_AUTO_LOITER),
    "AUTO.MISSION": (MAIN_AUTO, SUB_AUTO_MISSION),
    "AUTO.RTL": (MAIN_AUTO, SUB_AUTO_RTL),
    "AUTO.LAND": (MAIN_AUTO, SUB_AUTO_LAND),
    "AUTO.PRECLAND": (MAIN_AUTO, SUB_AUTO_PRECLAND),
}
# ArduPilot's names for the same behaviour, so callers can say what they mean once
ALIASES = {"AUTO": "AUTO.MISSION", "MISSION": "AUTO.MISSION", "LOITER": "AUTO.LOITER", "HOLD": "AUTO.LOITER",
           "RTL": "AUTO.RTL", "LAND": "AUTO.LAND", "GUIDED": "AUTO.LOITER"}

# ESTIMATOR_STATUS.flags of a healthy EKF2 with GPS (measured: 1023); the same bits as EKF_STATUS_REPORT
ESTIMATOR_HEALTHY_FLAGS = 0x033F
H_ACC_SITL_M = 0.9  # what PX4 SITL's GPS claims, fix type 3


def custom_mode(main: int, sub: int = 0) -> int:
    """HEARTBEAT.custom_mode of PX4 ``main``.``sub``."""
    return (int(sub) << 24) | (int(main) << 16)


def split_mode(custom: int) -> tuple[int, int]:
    """(main, sub) of a PX4 HEARTBEAT.custom_mode."""
    return (int(custom) >> 16) & 0xFF, (int(custom) >> 24) & 0xFF


def mode_name(custom: int) -> str:
    """``AUTO.MISSION``, ``POSCTL``... for a PX4 custom_mode (``MODE<main>.<sub>`` when unknown)."""
    main, sub = split_mode(custom)
    for name, (m, s) in MODES.items():
        if m == main and (s == sub or (s == 0 and main != MAIN_AUTO)):
            return name
    return f"MODE{main}.{sub}"


def mode_numbers(name: str) -> tuple[int, int]:
    """(main, sub) for a mode name, PX4's (``AUTO.MISSION``) or ArduPilot's meaning (``AUTO``, ``RTL``, ``LAND``).

    Raises
    ------
    KeyError
        An unknown name.
    """
    key = name.upper()
    return MODES[ALIASES.get(key, key)]


def is_px4(autopilot: int | None) -> bool:
    """HEARTBEAT.autopilot is PX4's."""
    return autopilot == MAV_AUTOPILOT_PX4


# ----- the mission PX4 flies -----


def px4_item(item: MissionItem) -> MissionItem:
    """One file item as PX4 takes it (file numbering kept).

    DO_SET_ROI (201) in ROI-location mode becomes DO_SET_ROI_LOCATION (195):
    PX4 stores 201's mode as 0 (ROI none), so the camera-facing yaw is lost. A hold
    waypoint gets an acceptance radius (param 2) of :data:`HOLD_ACCEPTANCE_M`:
    with PX4's default (NAV_ACC_RAD, 2 m) its hold timer starts 2 m before
    the point, so holds 0.5 m apart were "reached" every 3.1 s while the
    vehicle still moved, and its heading (towards the ROI only while not yet
    reached) stayed at the take-off heading (SITL run, holds at 1 m).
    """
    if item.command == mf.CMD_DO_SET_ROI:
        return replace(item, command=mf.CMD_DO_SET_ROI_LOCATION, p1=0.0, p2=0.0, p3=0.0, p4=0.0)
    if item.command == mf.CMD_NAV_WAYPOINT and item.hold_s > 0 and not item.p2 > 0:
        return replace(item, p2=HOLD_ACCEPTANCE_M)
    return item


def to_wire(items: Sequence[MissionItem]) -> list[MissionItem]:
    """The file's items (seq 0 = home) as PX4's mission: home dropped, renumbered from 0, PX4's commands."""
    return [replace(px4_item(item), seq=item.seq - SEQ_OFFSET) for item in items[SEQ_OFFSET:]]


def from_wire(items: Sequence[MissionItem], home: MissionItem) -> list[MissionItem]:
    """PX4's read-back in the file's numbering (``home`` put back at seq 0)."""
    return [home, *(replace(item, seq=item.seq + SEQ_OFFSET) for item in items)]


def _f32(v: float) -> float:
    import numpy as np

    return float(np.float32(v))


def _same(expected: float, back: float) -> bool:
    if math.isnan(expected):
        return True  # "unset": PX4 keeps NaN, but any value means the same
    return _f32(expected) == _f32(back)


# NAV commands whose param 4 (yaw, degrees) PX4 keeps as float32 radians (mission_item.yaw)
YAW_IN_RADIANS = frozenset({16, 17, 18, 19, 21, 22, 82})


def compare_readback(sent: Sequence[MissionItem], back: Sequence[MissionItem]) -> list[str]:
    """Differences between a PX4 upload (:func:`to_wire`'s items) and its read-back, at PX4's storage.

    PX4 stores params and the altitude as float32 and positions as 1e-7
    degree integers; frames 3 and 10 read back as their ``_INT`` twins (6, 11).
    """
    if len(sent) != len(back):
        return [f"vehicle holds {len(back)} items, {len(sent)} were uploaded"]
    problems: list[str] = []
    for a, b in zip(sent, back):
        where = f"PX4 seq {a.seq} (file seq {a.seq + SEQ_OFFSET})"
        if a.seq != b.seq:
            problems.append(f"{where}: read back as seq {b.seq}")
            continue
        if a.command != b.command:
            problems.append(f"{where}: command {a.command} read back as {b.command}")
            continue
        if mf.wire_frame(a) != mf.wire_frame(b):
            problems.append(f"{where}: frame {a.frame} read back as {b.frame}")
        for name in ("p1", "p2", "p3", "p4"):
            if name == "p4" and a.command in YAW_IN_RADIANS and not math.isnan(a.p4) and abs(a.p4 - b.p4) < 1e-3:
                continue  # yaw kept as float32 radians: 236.57 deg reads back as 236.56997680664062
            if not _same(getattr(a, name), getattr(b, name)):
                problems.append(f"{where}: {name} {getattr(a, name)!r} read back as {getattr(b, name)!r}")
        if a.frame in mf.GLOBAL_FRAMES and (a.x != b.x or a.y != b.y):
            problems.append(f"{where}: position ({a.x}, {a.y}) read back as ({b.x}, {b.y}) [1e-7 deg]")
        if not _same(a.z, b.z):
            problems.append(f"{where}: z {a.z!r} read back as {b.z!r}")
    return problems


def storage_changes(items: Sequence[MissionItem]) -> list[str]:
    """What PX4 keeps differently from the file, on purpose (file items, home at seq 0)."""
    out = ["home item (seq 0) not uploaded: PX4 numbers the mission from 0"]
    for item in items[SEQ_OFFSET:]:
        if item.command == mf.CMD_DO_SET_ROI:
            out.append(f"seq {item.seq}: DO_SET_ROI sent as DO_SET_ROI_LOCATION (195)")
        if item.z != _f32(item.z) and item.frame in mf.GLOBAL_FRAMES:
            out.append(f"seq {item.seq}: z {item.z:g} kept as float32 {_f32(item.z)!r}")
            if len(out) > 6:
                break
    return out


# ----- reached messages -----


class ReachedFilter:
    """PX4's MISSION_ITEM_REACHED turned into one report per item, in the file's numbering.

    PX4 repeats the last reached seq about once a second for ~10 s, and an
    item reached just before the next (a hold waypoint, then a
    DO_CHANGE_SPEED) is overwritten before it is sent: a jump from seq a
    to seq b > a + 1 reports a+1..b, all at this message's time.

    Parameters
    ----------
    seq_offset : int
        Added to the vehicle's seq (1 for PX4: its seq 0 is the file's 1).
    """

    def __init__(self, seq_offset: int = SEQ_OFFSET) -> None:
        self.seq_offset = int(seq_offset)
        self.last: int | None = None  # file seq of the last item reported
        self.repeats = 0
        self.filled = 0

    def feed(self, vehicle_seq: int) -> list[int]:
        """File seqs newly reached by this message (empty for a repeat)."""
        seq = int(vehicle_seq) + self.seq_offset
        if self.last is not None and seq <= self.last:
            self.repeats += 1
            return []
        first = self.seq_offset if self.last is None else self.last + 1
        self.filled += max(0, seq - first)
        self.last = seq
        return list(range(first, seq + 1))


@dataclass(frozen=True)
class Px4Advice:
    """What to set on a PX4 vehicle, said where ``fly`` says ArduPilot's parameters."""

    gps_rate: str = ("PX4 has no GPS_RATE_MS: its GPS driver configures the receiver's rate itself, so a 5 Hz stream "
                     "is the receiver's (PX4 SITL's simulated GPS makes 5 fixes/s); fit a 10 Hz RTK receiver or fly longer holds (plan --hover)")
    streams: str = ("PX4 streams on its GCS link without being asked (MAV_0_MODE Normal, MAV_0_RATE); fly still asks "
                    "for its rates with SET_MESSAGE_INTERVAL on its own link")
