"""Mission files: QGroundControl ``.plan`` JSON and QGC WPL 110 ``.waypoints``.

Both become one list of :class:`MissionItem` in the wire form of
MISSION_ITEM_INT (positions as integer 1e-7 degrees), with the home position as
item 0, which is what ArduPilot expects on upload. Pure parsing and formatting:
no sockets, no printing.

Example
-------
>>> mission = read_mission("site/mission.plan")          # doctest: +SKIP
>>> [item.command for item in mission.items][:3]          # doctest: +SKIP
[16, 22, 178]
"""

from __future__ import annotations

import json
import math
import os
import stat
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from dronecal_field.errors import InputError

# MAV_FRAME values: which frames carry WGS84 positions in x/y (1e-7 deg on the wire).
FRAME_GLOBAL = 0
FRAME_LOCAL_NED = 1
FRAME_MISSION = 2
FRAME_GLOBAL_RELATIVE_ALT = 3
FRAME_GLOBAL_INT = 5
FRAME_GLOBAL_RELATIVE_ALT_INT = 6
FRAME_GLOBAL_TERRAIN_ALT = 10
FRAME_GLOBAL_TERRAIN_ALT_INT = 11
GLOBAL_FRAMES = frozenset({0, 3, 5, 6, 10, 11})
LOCAL_FRAMES = frozenset({1, 4, 7, 8, 9, 20, 21})

# The float frames and their MISSION_ITEM_INT twins. ArduPilot stores one of each
# pair and reads back the float one (README "Read-back frames and home").
INT_FRAME_OF = {FRAME_GLOBAL_RELATIVE_ALT: FRAME_GLOBAL_RELATIVE_ALT_INT, FRAME_GLOBAL_TERRAIN_ALT: FRAME_GLOBAL_TERRAIN_ALT_INT}
FLOAT_FRAME_OF = {FRAME_GLOBAL_INT: FRAME_GLOBAL, FRAME_GLOBAL_RELATIVE_ALT_INT: FRAME_GLOBAL_RELATIVE_ALT, FRAME_GLOBAL_TERRAIN_ALT_INT: FRAME_GLOBAL_TERRAIN_ALT}

# MAV_CMD values used by the tool and the simulator.
CMD_NAV_WAYPOINT = 16
CMD_NAV_LOITER_TIME = 19
CMD_NAV_RETURN_TO_LAUNCH = 20
CMD_NAV_LAND = 21
CMD_NAV_TAKEOFF = 22
CMD_NAV_DELAY = 93
CMD_CONDITION_DELAY = 112
CMD_CONDITION_YAW = 115
CMD_DO_JUMP = 177
CMD_DO_CHANGE_SPEED = 178
CMD_DO_SET_HOME = 179
CMD_DO_SET_SERVO = 183
CMD_DO_SET_ROI_LOCATION = 195
CMD_DO_SET_ROI_NONE = 197
CMD_DO_SET_ROI = 201
CMD_DO_DIGICAM_CONTROL = 203
CMD_DO_SET_CAM_TRIGG_DIST = 206

# Commands ArduPilot stores without a location: they read back with frame 0
# whatever frame they were sent with (DO_CHANGE_SPEED, RTL in the recording).
NON_LOCATION_COMMANDS = frozenset(
    {
        CMD_NAV_RETURN_TO_LAUNCH,
        CMD_NAV_DELAY,
        CMD_CONDITION_DELAY,
        CMD_CONDITION_YAW,
        CMD_DO_JUMP,
        CMD_DO_CHANGE_SPEED,
        CMD_DO_SET_SERVO,
        CMD_DO_SET_ROI_NONE,
        CMD_DO_DIGICAM_CONTROL,
        CMD_DO_SET_CAM_TRIGG_DIST,
    }
)
# NAV commands: the vehicle flies them one at a time; everything else is a DO/CONDITION item.
NAV_COMMANDS = frozenset({CMD_NAV_WAYPOINT, CMD_NAV_LOITER_TIME, CMD_NAV_RETURN_TO_LAUNCH, CMD_NAV_LAND, CMD_NAV_TAKEOFF, CMD_NAV_DELAY})

COMMAND_NAMES = {
    CMD_NAV_WAYPOINT: "WP",
    CMD_NAV_LOITER_TIME: "LoiterTime",
    CMD_NAV_RETURN_TO_LAUNCH: "RTL",
    CMD_NAV_LAND: "Land",
    CMD_NAV_TAKEOFF: "Takeoff",
    CMD_NAV_DELAY: "NavDelay",
    CMD_CONDITION_DELAY: "CondDelay",
    CMD_CONDITION_YAW: "CondYaw",
    CMD_DO_JUMP: "Jump",
    CMD_DO_CHANGE_SPEED: "ChangeSpeed",
    CMD_DO_SET_ROI_LOCATION: "SetROI",
    CMD_DO_SET_ROI_NONE: "SetROI",
    CMD_DO_SET_ROI: "SetROI",
}


@dataclass(frozen=True)
class MissionItem:
    """One mission item as MISSION_ITEM_INT carries it.

    Attributes
    ----------
    seq : int
        Position in the mission; 0 is home on ArduPilot.
    frame : int
        MAV_FRAME as written in the file (``3`` = relative altitude).
    command : int
        MAV_CMD.
    p1, p2, p3, p4 : float
        Params 1-4 (``nan`` = "unset", as QGC writes ``null``).
    x, y : int
        Latitude, longitude in 1e-7 degrees for global frames; metres x 1e4 for
        local frames; the raw param 5/6 rounded to an integer otherwise.
    z : float
        Param 7: altitude in metres (datum from ``frame``) or the raw param.
    autocontinue : bool
        Go on to the next item when this one completes.
    """

    seq: int
    frame: int
    command: int
    p1: float = 0.0
    p2: float = 0.0
    p3: float = 0.0
    p4: float = 0.0
    x: int = 0
    y: int = 0
    z: float = 0.0
    autocontinue: bool = True

    @property
    def lat_deg(self) -> float | None:
        """Latitude in degrees, or ``None`` if the frame carries no position."""
        return self.x * 1e-7 if self.frame in GLOBAL_FRAMES else None

    @property
    def lon_deg(self) -> float | None:
        """Longitude in degrees, or ``None`` if the frame carries no position."""
        return self.y * 1e-7 if self.frame in GLOBAL_FRAMES else None

    @property
    def is_nav(self) -> bool:
        """True for NAV commands (the vehicle flies them), False for DO/CONDITION items."""
        return self.command in NAV_COMMANDS

    @property
    def hold_s(self) -> float:
        """Hold time at a NAV_WAYPOINT (param 1, seconds); 0 for other commands."""
        if self.command == CMD_NAV_WAYPOINT and not math.isnan(self.p1):
            return max(0.0, float(self.p1))
        return 0.0


@dataclass(frozen=True)
class Mission:
    """A mission with its home position.

    Attributes
    ----------
    items : tuple of MissionItem
        Item 0 is home (NAV_WAYPOINT, frame GLOBAL, altitude AMSL), as ArduPilot wants it.
    home_lat_deg, home_lon_deg, home_alt_m : float
        The planned home; ``home_alt_m`` is metres above mean sea level (QGC's convention).
    source_format : str
        ``"plan"`` or ``"waypoints"``.
    """

    items: tuple[MissionItem, ...]
    home_lat_deg: float
    home_lon_deg: float
    home_alt_m: float
    source_format: str = "plan"

    @property
    def nav_items(self) -> tuple[MissionItem, ...]:
        """The NAV items after home, in order."""
        return tuple(item for item in self.items[1:] if item.is_nav)

    @property
    def last_seq(self) -> int:
        """Seq of the last item."""
        return self.items[-1].seq


def _encode_xy(value: float, frame: int) -> int:
    """Param 5/6 to MISSION_ITEM_INT's integer x/y for ``frame``."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return 0
    if frame in GLOBAL_FRAMES:
        return int(round(float(value) * 1e7))
    if frame in LOCAL_FRAMES:
        return int(round(float(value) * 1e4))
    return int(round(float(value)))


def _param(value: object, where: str) -> float:
    if value is None:
        return math.nan  # QGC writes NaN ("leave unchanged") as JSON null
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(f"{where}: param {value!r} is not a number; fix the mission file")
    value = float(value)
    if math.isinf(value):
        raise InputError(f"{where}: param {value!r} is infinite; give a finite number (or null for 'unset')")
    return value


# Commands that fly to a position: a NaN/null latitude or longitude would be sent as 0 (the Gulf of Guinea).
_NEEDS_POSITION = frozenset({16, 17, 18, 19, 82})


def _integer(value: object, where: str, key: str) -> int:
    """A JSON integer (``16``, or ``16.0``), never a truncated ``16.9``, a string or a bool."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value != int(value):
        raise InputError(f"{where}: '{key}' is {value!r}, not an integer; fix the mission file")
    return int(value)


def _home(home: object, source: str) -> tuple[float, float, float]:
    """``mission.plannedHomePosition`` as finite (lat, lon, alt) in range."""
    fix = "set the home position in the planner"
    if not isinstance(home, list) or len(home) < 3:
        raise InputError(f"{source}: mission.plannedHomePosition must be [lat, lon, alt]; {fix}")
    values = []
    for name, v in zip(("lat", "lon", "alt"), home[:3]):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise InputError(f"{source}: mission.plannedHomePosition {name} is {v!r}, not a finite number; {fix}")
        values.append(float(v))
    lat, lon, alt = values
    if not (-90 <= lat <= 90 and -180 <= lon <= 180 and -1000 <= alt <= 10000):
        raise InputError(f"{source}: mission.plannedHomePosition {home[:3]} is outside lat -90..90, lon -180..180, alt -1000..10000 m; {fix}")
    return lat, lon, alt


def parse_qgc_plan(text: str, source: str = "mission.plan") -> Mission:
    """Parse QGroundControl plan JSON (fileType "Plan", mission.items of SimpleItem).

    Parameters
    ----------
    text : str
        The file's content.
    source : str
        Name used in error messages.

    Returns
    -------
    Mission
        Home from ``mission.plannedHomePosition`` as item 0, then the items in order.
        DO_JUMP targets given as QGC ``doJumpId`` become seq numbers.

    Raises
    ------
    InputError
        Not a plan file, a ComplexItem (survey, corridor) or a malformed item.
    """
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(f"{source}: not valid JSON ({exc.msg} at line {exc.lineno}); give a QGroundControl .plan file") from None
    if not isinstance(doc, dict) or doc.get("fileType") != "Plan" or not isinstance(doc.get("mission"), dict):
        raise InputError(f"{source}: not a QGroundControl plan (fileType 'Plan' with a 'mission' object); give a .plan or .waypoints file")
    mission = doc["mission"]
    home_lat, home_lon, home_alt = _home(mission.get("plannedHomePosition"), source)
    raw_items = mission.get("items")
    if not isinstance(raw_items, list) or not raw_items:
        raise InputError(f"{source}: mission.items is empty; plan at least one waypoint")

    items: list[MissionItem] = [
        MissionItem(seq=0, frame=FRAME_GLOBAL, command=CMD_NAV_WAYPOINT, x=_encode_xy(home_lat, 0), y=_encode_xy(home_lon, 0), z=home_alt)
    ]
    jump_ids: dict[int, int] = {}
    for index, raw in enumerate(raw_items):
        where = f"{source}: mission.items[{index}]"
        if not isinstance(raw, dict):
            raise InputError(f"{where} is not an object; fix the mission file")
        if raw.get("type", "SimpleItem") != "SimpleItem":
            raise InputError(f"{where} is a {raw.get('type')} ({raw.get('complexItemType', '?')}); convert it to simple waypoints in the planner first")
        params = raw.get("params")
        if not isinstance(params, list) or len(params) != 7:
            raise InputError(f"{where}: 'params' must be a list of 7 numbers; fix the mission file")
        if "command" not in raw or "frame" not in raw:
            raise InputError(f"{where}: 'command' and 'frame' must be integers; fix the mission file")
        command = _integer(raw["command"], where, "command")
        frame = _integer(raw["frame"], where, "frame")
        p = [_param(v, where) for v in params]
        if command in _NEEDS_POSITION and frame in GLOBAL_FRAMES and (math.isnan(p[4]) or math.isnan(p[5])):
            raise InputError(f"{where}: command {command} needs a latitude and longitude (params 5, 6), not null/NaN; fix the mission file")
        seq = len(items)
        if "doJumpId" in raw and raw["doJumpId"] is not None:
            jump_ids[_integer(raw["doJumpId"], where, "doJumpId")] = seq
        p[6] = 0.0 if math.isnan(p[6]) else p[6]
        items.append(_item_from_params(seq, frame, command, p, bool(raw.get("autoContinue", True))))
    # QGC stores DO_JUMP's target as a doJumpId; on the wire it is the target's seq.
    for i, item in enumerate(items):
        if item.command == CMD_DO_JUMP and not math.isnan(item.p1):
            target = jump_ids.get(int(item.p1))
            if target is None:
                raise InputError(f"{source}: DO_JUMP at seq {item.seq} targets doJumpId {int(item.p1)}, which no item has; fix the jump")
            items[i] = replace(item, p1=float(target))
    return Mission(items=tuple(items), home_lat_deg=home_lat, home_lon_deg=home_lon, home_alt_m=home_alt, source_format="plan")


def _item_from_params(seq: int, frame: int, command: int, p: list[float], autocontinue: bool) -> MissionItem:
    """A MissionItem from a file's seven params (lat/lon as degrees in global frames)."""
    return MissionItem(
        seq=seq, frame=frame, command=command, p1=p[0], p2=p[1], p3=p[2], p4=p[3],
        x=_encode_xy(p[4], frame), y=_encode_xy(p[5], frame), z=p[6], autocontinue=autocontinue,
    )


def parse_waypoints(text: str, source: str = "mission.waypoints") -> Mission:
    """Parse a QGC WPL 110 file (tab-separated; item 0 is home).

    Columns: seq, current, frame, command, p1, p2, p3, p4, x (lat deg), y (lon deg),
    z (m), autocontinue.

    Raises
    ------
    InputError
        Wrong header, a malformed line or seq numbers out of order.
    """
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if not lines or not lines[0].startswith("QGC WPL 110"):
        raise InputError(f"{source}: first line must be 'QGC WPL 110'; give a QGC .waypoints or .plan file")
    items: list[MissionItem] = []
    for lineno, line in enumerate(lines[1:], start=2):
        cols = line.split()
        if len(cols) != 12:
            raise InputError(f"{source}:{lineno}: expected 12 columns, found {len(cols)}; fix the line")
        try:
            seq, _current, frame, command = (int(c) for c in cols[:4])
            p = [float(c) for c in cols[4:11]]
            autocontinue = bool(int(cols[11]))
        except ValueError:
            raise InputError(f"{source}:{lineno}: non-numeric column; fix the line") from None
        if any(math.isinf(v) for v in p) or (command in STORED_IN_LOCATION and any(math.isnan(v) for v in p[4:])):
            raise InputError(f"{source}:{lineno}: a parameter is infinite or the position is NaN; give finite numbers")
        if seq != len(items):
            raise InputError(f"{source}:{lineno}: seq {seq} out of order (expected {len(items)}); renumber the items")
        items.append(_item_from_params(seq, frame, command, p, autocontinue))
    if len(items) < 2:
        raise InputError(f"{source}: needs home (item 0) and at least one more item; plan a waypoint")
    home = items[0]
    return Mission(items=tuple(items), home_lat_deg=home.x * 1e-7, home_lon_deg=home.y * 1e-7, home_alt_m=home.z, source_format="waypoints")


MAX_MISSION_FILE_BYTES = 16_000_000  # a 10 000-item .plan is about 3 MB


def read_mission(path: str | os.PathLike) -> Mission:
    """Read a ``.plan`` (JSON) or ``.waypoints`` (QGC WPL 110) file, told apart by content.

    Raises
    ------
    InputError
        The file is missing or neither format.
    """
    p = Path(path)
    try:
        st = p.stat()
        if not stat.S_ISREG(st.st_mode):  # a FIFO would block for ever, /dev/zero never end
            raise InputError(f"mission {p} is not a regular file (a pipe, device or folder); give the .plan or .waypoints file")
        if st.st_size > MAX_MISSION_FILE_BYTES:
            raise InputError(f"mission {p} is {st.st_size / 1e6:.0f} MB, more than any mission ({MAX_MISSION_FILE_BYTES / 1e6:.0f} MB); give the .plan or .waypoints file")
        with p.open("rb") as f:
            text = f.read(MAX_MISSION_FILE_BYTES + 1).decode("utf-8")
    except OSError as exc:
        raise InputError(f"cannot read mission {p}: {exc.strerror}; check --mission") from None
    if text.lstrip().startswith("QGC WPL"):
        return parse_waypoints(text, source=str(p))
    return parse_qgc_plan(text, source=str(p))


def _decode_xy(value: int, frame: int) -> float:
    if frame in GLOBAL_FRAMES:
        return value * 1e-7
    if frame in LOCAL_FRAMES:
        return value * 1e-4
    return float(value)


def to_qgc_plan(mission: Mission) -> str:
    """QGroundControl plan JSON for ``mission`` (home from item 0, the rest as SimpleItems).

    Used to attach the flown mission to a run when it came from a ``.waypoints`` file.
    """

    def num(v: float) -> float | None:
        return None if math.isnan(v) else v

    items = []
    for item in mission.items[1:]:
        params = [item.p1, item.p2, item.p3, item.p4, _decode_xy(item.x, item.frame), _decode_xy(item.y, item.frame), item.z]
        items.append(
            {
                "type": "SimpleItem",
                "command": item.command,
                "frame": item.frame,
                "params": [num(float(v)) for v in params],
                "autoContinue": item.autocontinue,
                "doJumpId": item.seq,
            }
        )
    doc = {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "dronecal-field",
        "geoFence": {"circles": [], "polygons": [], "version": 2},
        "rallyPoints": {"points": [], "version": 2},
        "mission": {
            "version": 2,
            "firmwareType": 3,
            "vehicleType": 2,
            "cruiseSpeed": 5,
            "hoverSpeed": 5,
            "plannedHomePosition": [mission.home_lat_deg, mission.home_lon_deg, mission.home_alt_m],
            "items": items,
        },
    }
    return json.dumps(doc, indent=2)


def wire_frame(item: MissionItem) -> int:
    """The frame to send in MISSION_ITEM_INT: relative/terrain frames become their ``_INT`` twins.

    Matches the recording (home in frame 0, waypoints in frame 6).
    """
    return INT_FRAME_OF.get(item.frame, item.frame)


# Commands ArduPilot stores with a location (AP_Mission::stored_in_location); all others read
# back with frame 0 and x = y = z = 0.
STORED_IN_LOCATION = frozenset({16, 17, 18, 19, 21, 22, 30, 31, 82, 92, 179, 189, 191, 201, 84, 85, 94})


def _f32(v: float) -> float:
    """``v`` rounded to a C float (float32), as a Python float."""
    import numpy as np

    return float(np.float32(v))


def _int_c(v: float, lo: int, hi: int) -> int:
    """C float-to-integer conversion (truncation toward zero), clamped to the type's range."""
    if math.isnan(v):
        return 0
    return int(max(lo, min(hi, math.trunc(_f32(v)))))


def _u8(v: float) -> int:
    return int(_int_c(v, 0, 255))


def _i8(v: float) -> int:
    return int(_int_c(v, -128, 127))


def _u16(v: float) -> int:
    return int(_int_c(v, 0, 65535))


def _i16(v: float) -> int:
    return int(_int_c(v, -32768, 32767))


def _stored_params(item: MissionItem) -> tuple[float | int, float | int, float | int, float | int] | None:
    """Params 1-4 as ArduCopter reads them back, or ``None`` for a command not modelled here.

    Transcribes AP_Mission::mavlink_int_to_mission_cmd / mission_cmd_to_mavlink_int
    (Copter build): what is kept, in which C type, and what is dropped. A param
    kept in an integer type (or dropped, or a flag) is returned as ``int``, one
    kept as a C ``float`` as a float32-rounded ``float``: :func:`compare_readback`
    compares each in its own type.
    """
    c, p1, p2, p3, p4 = item.command, item.p1, item.p2, item.p3, item.p4
    if c in (CMD_NAV_WAYPOINT, CMD_NAV_TAKEOFF, CMD_DO_SET_HOME, CMD_DO_SET_ROI):
        return (_u16(p1), 0, 0, 0)  # hold s / min pitch / use-current / ROI mode: uint16; the rest dropped
    if c == CMD_NAV_LOITER_TIME:
        return (_u16(p1), 0, -1 if p3 < 0 else 1, 1 if p4 > 0 else 0)
    if c == CMD_NAV_RETURN_TO_LAUNCH:
        return (0, 0, 0, 0)
    if c == CMD_NAV_LAND:
        return (_u16(p1), 0, 0, -1 if p4 < 0 else 1)  # p4 = yaw direction flag: 0 reads back as 1
    if c == CMD_NAV_DELAY:
        return (_f32(p1), _i8(p2), _i8(p3), _i8(p4))
    if c == CMD_CONDITION_DELAY:
        return (_f32(p1), 0, 0, 0)
    if c == CMD_CONDITION_YAW:
        return (_f32(p1), _f32(p2), _i8(p3), _u8(p4))
    if c == CMD_DO_JUMP:
        return (_u16(p1), _i16(p2), 0, 0)
    if c == CMD_DO_CHANGE_SPEED:
        return (_u8(p1), _f32(p2), _f32(p3), 0)
    if c == CMD_DO_SET_SERVO:
        return (_u8(p1), _u16(p2), 0, 0)
    if c == CMD_DO_SET_CAM_TRIGG_DIST:
        return (_f32(p1), 0, 0, 0)
    return None


# Params that may be NaN per command (AP_Mission::sanity_check_params: param 4 of these).
_NAN_OK_P4 = frozenset({CMD_NAV_WAYPOINT, CMD_NAV_LAND, CMD_NAV_TAKEOFF})


def ardupilot_check(item: MissionItem) -> int:
    """MAV_MISSION_RESULT ArduCopter answers for this uploaded item (0 = accepted).

    Unknown commands are MAV_MISSION_UNSUPPORTED (3); NaN params where
    ArduPilot does not allow them are INVALID_PARAM1..4 (6..9); bad positions
    INVALID_PARAM5_X/6_Y/7 (10..12); frames other than global/mission
    UNSUPPORTED_FRAME (2).
    """
    if _stored_params(item) is None:
        return 3
    for index, value in enumerate((item.p1, item.p2, item.p3, item.p4)):
        if math.isnan(value) and not (index == 3 and item.command in _NAN_OK_P4):
            return 6 + index
    if item.command in STORED_IN_LOCATION:
        if item.frame not in (FRAME_MISSION, FRAME_GLOBAL, FRAME_GLOBAL_INT, FRAME_GLOBAL_RELATIVE_ALT, FRAME_GLOBAL_RELATIVE_ALT_INT, FRAME_GLOBAL_TERRAIN_ALT, FRAME_GLOBAL_TERRAIN_ALT_INT):
            return 2
        if abs(item.x) > 900000000:
            return 10
        if abs(item.y) > 1800000000:
            return 11
        if math.isnan(item.z) or abs(item.z) >= 83000.0:
            return 12
    return 0


def stored_alt_cm(z: float) -> int:
    """A location's altitude as ArduPilot stores it: whole centimetres, truncated.

    AP_Mission::mavlink_int_to_mission_cmd: ``cmd.content.location.alt =
    packet.z * 100.0f`` (float32 multiply, then C's float-to-int32 conversion,
    which truncates toward zero). So 1.537 m is kept as 153 cm; 1.47 m
    (float32 1.47000003) as 147 cm.
    """
    import numpy as np

    if math.isnan(z):
        return 0
    return int(np.trunc(np.float32(z) * np.float32(100.0)))


def readback_alt_m(alt_cm: int) -> float:
    """The z ArduPilot reads back for a stored altitude: ``alt_cm * 0.01f`` (float32 multiply).

    AP_Mission::mission_cmd_to_mavlink_int: ``packet.z = cmd.content.location.alt * 0.01f``.
    147 cm reads back as 1.46999990940094 (not float32(1.47) = 1.4700000286102295).
    """
    import numpy as np

    return float(np.float32(alt_cm) * np.float32(0.01))


def ardupilot_readback(item: MissionItem) -> MissionItem | None:
    """The item as ArduCopter 4.7 stores it and reads it back, or ``None`` if not modelled.

    Location commands keep x/y exactly (1e-7 degree integers); z is stored in
    whole centimetres, truncated (:func:`stored_alt_cm`) and read back as
    ``alt_cm * 0.01f`` (:func:`readback_alt_m`: 1.47 m comes back as
    1.46999990940094, 3.633 m as 3.63 m). Relative frames read back as 3
    (terrain as 10) and absolute ones as 0. Location-less commands read back in
    frame 0 with x = y = z = 0. Params keep only what fits the stored C type (a
    1.5 s hold reads back as 1 s; NAV_WAYPOINT's yaw in param 4 reads back as
    0). ``autocontinue`` always reads back 1. Checked against ArduCopter 4.7
    SITL in tests/test_sitl_arducopter.py.
    """
    params = _stored_params(item)
    if params is None:
        return None
    if item.command in STORED_IN_LOCATION:
        if item.frame in (FRAME_GLOBAL_RELATIVE_ALT, FRAME_GLOBAL_RELATIVE_ALT_INT):
            frame = FRAME_GLOBAL_RELATIVE_ALT
        elif item.frame in (FRAME_GLOBAL_TERRAIN_ALT, FRAME_GLOBAL_TERRAIN_ALT_INT):
            frame = FRAME_GLOBAL_TERRAIN_ALT
        else:
            frame = FRAME_GLOBAL
        z = readback_alt_m(stored_alt_cm(item.z))
        x, y = item.x, item.y
    else:
        frame, x, y, z = FRAME_GLOBAL, 0, 0, 0.0
    p1, p2, p3, p4 = (float(v) for v in params)
    return MissionItem(seq=item.seq, frame=frame, command=item.command, p1=p1, p2=p2, p3=p3, p4=p4, x=x, y=y, z=z, autocontinue=True)


def _readback_cm(z: float) -> int | None:
    """A read-back z (metres) in the firmware's whole centimetres, or ``None`` if not finite."""
    if not math.isfinite(z):
        return None
    return int(round(z * 100.0))


def storage_changes(items: list[MissionItem] | tuple[MissionItem, ...]) -> list[str]:
    """Where ArduCopter will store an item differently from the file (expected, not errors).

    E.g. ``seq 5: p4 144.37 -> 0`` for NAV_WAYPOINT's yaw, ``seq 7: z 3.633 -> 3.63``
    for an altitude finer than a centimetre. Frame renaming, unset (NaN)
    params, seq 0 (home) and float32 representation (1.47 read back as
    1.4699999) are not listed.
    """
    notes = []
    for item in items[1:]:
        stored = _stored_params(item)
        if stored is None:
            continue
        for name, back in zip(("p1", "p2", "p3", "p4"), stored):
            sent = getattr(item, name)
            if not math.isnan(sent) and _f32(sent) != _f32(back):  # NaN means "unset" anyway
                notes.append(f"seq {item.seq}: {name} {sent:g} -> {back:g}")
        if item.command in STORED_IN_LOCATION and not math.isnan(item.z):
            alt_cm = stored_alt_cm(item.z)
            if abs(item.z - alt_cm / 100.0) > 1e-4:  # more than float32's representation of a whole centimetre
                notes.append(f"seq {item.seq}: z {item.z:g} -> {alt_cm / 100:g}")
    return notes


def _same_stored(expected: float | int, back: float) -> bool:
    """``back`` equals ``expected`` in the stored C type: integers as integers, floats as float32."""
    if isinstance(expected, int):
        return math.isfinite(back) and round(back) == expected and abs(back - expected) < 0.5
    if math.isnan(expected):
        return True  # "unset": the autopilot may store anything
    return _f32(expected) == _f32(back)


def compare_readback(sent: list[MissionItem] | tuple[MissionItem, ...], back: list[MissionItem] | tuple[MissionItem, ...]) -> list[str]:
    """Differences between an uploaded mission and the vehicle's read-back, at the firmware's storage resolution.

    Each sent item is first turned into what ArduCopter stores
    (:func:`ardupilot_readback`: ``_INT`` frames read back as their float twins,
    location-less commands such as DO_CHANGE_SPEED and RTL in frame 0, params
    in their stored C types), then compared with the read-back in those
    stored units: positions as 1e-7 degree integers, altitudes in whole
    centimetres (the read-back z rounded to the centimetre, so 1.46999990940094
    is the 147 cm that 1.47 m was stored as), params in their command's C type
    (integers as integers, floats as float32). Seq 0 is skipped: the vehicle
    replaces it with its own home. Commands not modelled are compared as sent,
    with the frame rules only (params as float32, z to the centimetre).

    Returns
    -------
    list of str
        One line per difference; empty when the missions agree.
    """
    problems: list[str] = []
    if len(sent) != len(back):
        return [f"vehicle holds {len(back)} items, {len(sent)} were uploaded"]
    for a_sent, b in zip(sent[1:], back[1:]):
        where = f"seq {a_sent.seq}"
        if b.seq != a_sent.seq:
            problems.append(f"{where}: read back as seq {b.seq}")
            continue
        if a_sent.command != b.command:
            problems.append(f"{where}: command {a_sent.command} read back as {b.command}")
            continue
        stored = _stored_params(a_sent)
        expected = ardupilot_readback(a_sent)
        if expected is not None and stored is not None:
            a = expected
            params: tuple[float | int, ...] = stored
            alt_cm = stored_alt_cm(a_sent.z) if a_sent.command in STORED_IN_LOCATION else 0
            frame_ok = a.frame == b.frame
            check_autocontinue = False
        else:
            a = a_sent
            params = (a.p1, a.p2, a.p3, a.p4)
            alt_cm = _readback_cm(a.z)
            fa = FLOAT_FRAME_OF.get(a.frame, a.frame)
            fb = FLOAT_FRAME_OF.get(b.frame, b.frame)
            frame_ok = fa == fb or (b.frame == FRAME_GLOBAL and (a.command in NON_LOCATION_COMMANDS or a.frame == FRAME_MISSION))
            check_autocontinue = True
        if not frame_ok:
            problems.append(f"{where}: frame {a_sent.frame} read back as {b.frame} (expected {a.frame})")
        for name, value in zip(("p1", "p2", "p3", "p4"), params):
            if not _same_stored(value, getattr(b, name)):
                problems.append(f"{where}: {name} {getattr(a, name)!r} read back as {getattr(b, name)!r}")
        if a.x != b.x or a.y != b.y:
            problems.append(f"{where}: position ({a.x}, {a.y}) read back as ({b.x}, {b.y}) [1e-7 deg]")
        if alt_cm is not None and _readback_cm(b.z) != alt_cm:
            problems.append(f"{where}: z {a_sent.z!r} ({alt_cm} cm stored) read back as {b.z!r}")
        if check_autocontinue and a.autocontinue != b.autocontinue:
            problems.append(f"{where}: autocontinue {a.autocontinue} read back as {b.autocontinue}")
    return problems


def item_from_message(msg: Any) -> MissionItem:
    """A MissionItem from a MISSION_ITEM_INT or MISSION_ITEM message (float lat/lon scaled to 1e-7 deg ints).

    Both sides of the mission protocol use it: the client reading a mission
    back and the simulated vehicle receiving one.
    """
    if msg.get_type() == "MISSION_ITEM":
        if msg.frame in GLOBAL_FRAMES:
            x, y = int(round(msg.x * 1e7)), int(round(msg.y * 1e7))
        else:
            x, y = int(round(msg.x)), int(round(msg.y))
    else:
        x, y = int(msg.x), int(msg.y)
    return MissionItem(
        seq=int(msg.seq),
        frame=int(msg.frame),
        command=int(msg.command),
        p1=float(msg.param1),
        p2=float(msg.param2),
        p3=float(msg.param3),
        p4=float(msg.param4),
        x=x,
        y=y,
        z=float(msg.z),
        autocontinue=bool(msg.autocontinue),
    )
