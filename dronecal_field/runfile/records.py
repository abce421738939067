"""Domain values of a run file: what one MCAP run holds, independent of MCAP.

Every timestamp is integer nanoseconds UTC on the run clock
(shared/contracts/run-format.md, "The run clock").
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace
from typing import Any, Mapping

import numpy as np

from dronecal_field.errors import ContractError, InputError
from dronecal_field.geodesy import EnuOrigin

FORMAT_VERSION = 1
RUN_METADATA_NAME = "dronecal.run"
SITE_METADATA_NAME = "dronecal.site"
MAX_IMAGE_SIDE_PX = 65536
CUT_METADATA_NAME = "dronecal.cut"  # written when recording stopped early (a full disk): reason, cut_at_byte, last_message_ns

MARKER_KINDS = ("aruco", "led")
ALTITUDE_DATUMS = ("ellipsoid", "msl")
FIX_TYPES = ("no_fix", "2d", "3d", "dgps", "rtk_float", "rtk_fixed")

# Keys of 'dronecal.run' that RunMetadata understands; every other key goes to `extra`.
_KNOWN_KEYS = (
    "format_version",
    "camera.width",
    "camera.height",
    "camera.latency_s",
    "marker.kind",
    "marker.dictionary",
    "marker.id",
    "marker.size_m",
    "marker.offset_frd_m",
    "gnss.altitude_datum",
    "cameras",
)

# A camera of a several-camera run (its topics /cameras/<name>/image|video), as the contract spells it.
CAMERA_NAME_PATTERN = r"[a-z0-9][a-z0-9_-]{0,31}"
_CAMERA_NAME = re.compile(CAMERA_NAME_PATTERN + r"\Z")
_CAMERA_KEY = re.compile(r"camera\.(?P<name>[^.]+)\.(?P<key>width|height|latency_s|clock)\Z")


def check_camera_name(name: str, where: str = "run.mcap") -> str:
    """``name`` when it is a contract camera name (``[a-z0-9][a-z0-9_-]{0,31}``); ContractError naming it otherwise."""
    if not _CAMERA_NAME.match(name):
        raise ContractError(
            f"{where}: camera name {name!r} is not a contract name: use 1-32 of a-z, 0-9, '_', '-', starting with a letter or digit"
        )
    return name


@dataclass(frozen=True)
class MarkerSpec:
    """The marker the drone carries.

    Attributes
    ----------
    kind : ``"aruco"`` or ``"led"``.
    dictionary : OpenCV ArUco dictionary name, e.g. ``"DICT_4X4_50"`` (aruco only).
    marker_id : marker id in that dictionary (aruco only).
    size_m : side of the black square, metres (aruco only).
    offset_frd_m : marker centre relative to the GNSS antenna phase centre,
        vehicle body frame (forward, right, down), metres.
    """

    kind: str
    dictionary: str | None = None
    marker_id: int | None = None
    size_m: float | None = None
    offset_frd_m: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class CameraMeta:
    """One camera of a several-camera run (metadata ``camera.<name>.*``).

    Attributes
    ----------
    name : the camera's name, its topic ``/cameras/<name>/image`` or ``/cameras/<name>/video``.
    width, height : image size, pixels.
    latency_s : capture-to-stamp latency of its frames, seconds; None when unknown.
    clock : how its frames were stamped (``camera.<name>.clock``, e.g. ``rtcp`` or ``arrival``), None when not said.
    """

    name: str
    width: int
    height: int
    latency_s: float | None = None
    clock: str | None = None


@dataclass(frozen=True)
class RunMetadata:
    """The ``dronecal.run`` metadata record (plus ``dronecal.site`` when known).

    Attributes
    ----------
    format_version : contract version, 1.
    width, height : image size, pixels.
    marker : the marker flown.
    altitude_datum : ``"ellipsoid"`` (WGS84 h, the default) or ``"msl"``:
        the datum of every ``GnssFix.alt_m`` in the run.
    camera_latency_s : best estimate of capture-to-stamp latency of frames
        stamped at the host on arrival, seconds; None when unknown.
    site_origin : ENU origin for reports (metadata ``dronecal.site``), or None.
    extra : further string keys of ``dronecal.run``, kept verbatim.
    cameras : the cameras of a several-camera run, in the order of metadata ``cameras``; () for a
        one-camera run (``/camera/...``). ``width``, ``height`` and ``camera_latency_s`` are then
        those of ``camera_name`` (the first camera unless :meth:`for_camera` chose another).
    camera_name : the camera this metadata describes in a several-camera run, else None.
    """

    format_version: int
    width: int
    height: int
    marker: MarkerSpec
    altitude_datum: str = "ellipsoid"
    camera_latency_s: float | None = None
    site_origin: EnuOrigin | None = None
    extra: dict[str, str] = field(default_factory=dict)
    cameras: tuple[CameraMeta, ...] = ()
    camera_name: str | None = None

    def camera_names(self) -> tuple[str, ...]:
        """Names of the cameras of a several-camera run, in order; () for a one-camera run."""
        return tuple(c.name for c in self.cameras)

    def for_camera(self, name: str) -> "RunMetadata":
        """This metadata as one camera of a several-camera run sees it (its size and latency).

        Raises
        ------
        InputError : ``name`` is not a camera of the run (names the ones it has)
        """
        for c in self.cameras:
            if c.name == name:
                return replace(self, width=c.width, height=c.height, camera_latency_s=c.latency_s, camera_name=name)
        have = ", ".join(self.camera_names()) or "none (a one-camera run)"
        raise InputError(f"the run has no camera {name!r}: its cameras are {have}")

    def to_mcap_metadata(self) -> dict[str, str]:
        """The ``dronecal.run`` metadata record, string to string.

        ``site_origin`` is not part of it: it goes to ``dronecal.site``
        (see :meth:`site_metadata`).
        """
        m = self.marker
        out = dict(self.extra)
        out.update(
            {
                "format_version": str(int(self.format_version)),
                "camera.width": str(int(self.width)),
                "camera.height": str(int(self.height)),
                "marker.kind": m.kind,
                "marker.offset_frd_m": ",".join(repr(float(v)) for v in m.offset_frd_m),
                "gnss.altitude_datum": self.altitude_datum,
                "camera.latency_s": (
                    "unknown" if self.camera_latency_s is None else repr(float(self.camera_latency_s))
                ),
            }
        )
        if m.dictionary is not None:
            out["marker.dictionary"] = m.dictionary
        if m.marker_id is not None:
            out["marker.id"] = str(int(m.marker_id))
        if m.size_m is not None:
            out["marker.size_m"] = repr(float(m.size_m))
        if self.cameras:
            # several cameras: each has its own size and latency; camera.width/height are absent (the contract)
            for key in ("camera.width", "camera.height", "camera.latency_s"):
                out.pop(key, None)
            out["cameras"] = ",".join(c.name for c in self.cameras)
            for c in self.cameras:
                out[f"camera.{c.name}.width"] = str(int(c.width))
                out[f"camera.{c.name}.height"] = str(int(c.height))
                out[f"camera.{c.name}.latency_s"] = "unknown" if c.latency_s is None else repr(float(c.latency_s))
                if c.clock is not None:
                    out[f"camera.{c.name}.clock"] = c.clock
        return out

    def site_metadata(self) -> dict[str, str] | None:
        """The ``dronecal.site`` metadata record, or None without a site origin."""
        if self.site_origin is None:
            return None
        return site_to_metadata(self.site_origin)

    @classmethod
    def from_mcap_metadata(
        cls,
        run: Mapping[str, str],
        site: Mapping[str, str] | None = None,
        source: str = "run.mcap",
    ) -> "RunMetadata":
        """Parse and check the ``dronecal.run`` (and optional ``dronecal.site``) records.

        Parameters
        ----------
        run : the ``dronecal.run`` metadata, string to string.
        site : the ``dronecal.site`` metadata, or None.
        source : file name used in error messages.

        Raises
        ------
        ContractError
            naming the missing or malformed key and what the contract expects.
        """
        where = f"{source}: metadata '{RUN_METADATA_NAME}'"

        def need(key: str, what: str) -> str:
            value = run.get(key)
            if value is None or str(value).strip() == "":
                raise ContractError(
                    f"{where} has no '{key}': write {what} (docs/runfile.md)"
                )
            return str(value).strip()

        def as_int(key: str, text: str, minimum: int | None = None) -> int:
            try:
                value = int(text)
            except ValueError:
                raise ContractError(f"{where}: '{key}' = {text!r} is not a decimal integer") from None
            if minimum is not None and value < minimum:
                raise ContractError(f"{where}: '{key}' = {value} must be >= {minimum}")
            return value

        def as_float(key: str, text: str) -> float:
            try:
                value = float(text)
            except ValueError:
                raise ContractError(f"{where}: '{key}' = {text!r} is not a number") from None
            if not np.isfinite(value):
                raise ContractError(f"{where}: '{key}' = {text!r} is not finite")
            return value

        version = as_int("format_version", need("format_version", "'1'"), minimum=1)
        if version > FORMAT_VERSION:
            raise ContractError(
                f"{where}: format_version {version} is newer than this tool reads "
                f"({FORMAT_VERSION}); upgrade dronecal-field"
            )
        def size(key: str, what: str) -> int:
            value = as_int(key, need(key, what), minimum=1)
            if value > MAX_IMAGE_SIDE_PX:
                raise ContractError(f"{where}: '{key}' = {value} px is beyond any camera (at most {MAX_IMAGE_SIDE_PX}); write the frames' size")
            return value

        def latency_of(key: str) -> float | None:
            text = str(run.get(key) or "unknown").strip()
            return None if text == "unknown" else as_float(key, text)

        cameras: list[CameraMeta] = []
        if run.get("cameras") is not None:
            names = [n.strip() for n in str(run["cameras"]).split(",")]
            if not any(names):
                raise ContractError(f"{where}: 'cameras' is empty: list the camera names, comma separated, or leave the key out for one camera")
            for name in names:
                check_camera_name(name, f"{where}: 'cameras'")
                if name in (c.name for c in cameras):
                    raise ContractError(f"{where}: 'cameras' lists {name!r} twice: give each camera once")
                clock = run.get(f"camera.{name}.clock")
                cameras.append(CameraMeta(
                    name=name, width=size(f"camera.{name}.width", f"camera {name}'s image width in pixels"),
                    height=size(f"camera.{name}.height", f"camera {name}'s image height in pixels"),
                    latency_s=latency_of(f"camera.{name}.latency_s"), clock=str(clock).strip() if clock else None,
                ))
            listed = {c.name for c in cameras}
            for key in run:
                m = _CAMERA_KEY.match(key)
                if m and m["name"] not in listed:
                    raise ContractError(f"{where}: '{key}' is for camera {m['name']!r}, which 'cameras' does not list: add it to 'cameras'")
            width, height = cameras[0].width, cameras[0].height
        else:
            width = size("camera.width", "the image width in pixels")
            height = size("camera.height", "the image height in pixels")
        kind = need("marker.kind", "'aruco' or 'led'")
        if kind not in MARKER_KINDS:
            raise ContractError(f"{where}: 'marker.kind' = {kind!r}; use one of {', '.join(MARKER_KINDS)}")
        offset_text = need("marker.offset_frd_m", "'x,y,z', the marker centre from the GNSS antenna in metres (FRD)")
        parts = [p.strip() for p in offset_text.split(",")]
        if len(parts) != 3:
            raise ContractError(f"{where}: 'marker.offset_frd_m' = {offset_text!r}; write three numbers 'x,y,z' in metres")
        offset = tuple(as_float("marker.offset_frd_m", p) for p in parts)
        dictionary = marker_id = size_m = None
        if kind == "aruco":
            dictionary = need("marker.dictionary", "the OpenCV ArUco dictionary name, e.g. DICT_4X4_50")
            marker_id = as_int("marker.id", need("marker.id", "the marker id (decimal)"), minimum=0)
            size_m = as_float("marker.size_m", need("marker.size_m", "the marker's side in metres"))
            if size_m <= 0:
                raise ContractError(f"{where}: 'marker.size_m' = {size_m} must be positive")
        else:
            dictionary = run.get("marker.dictionary") or None
            if run.get("marker.id"):
                marker_id = as_int("marker.id", run["marker.id"], minimum=0)
            if run.get("marker.size_m"):
                size_m = as_float("marker.size_m", run["marker.size_m"])
        datum = str(run.get("gnss.altitude_datum") or "ellipsoid").strip()
        if datum not in ALTITUDE_DATUMS:
            raise ContractError(f"{where}: 'gnss.altitude_datum' = {datum!r}; use 'ellipsoid' or 'msl'")
        latency = cameras[0].latency_s if cameras else latency_of("camera.latency_s")
        extra = {k: str(v) for k, v in run.items() if k not in _KNOWN_KEYS and not (cameras and _CAMERA_KEY.match(k))}
        origin = site_from_metadata(site, source) if site else None
        return cls(
            format_version=version,
            width=width,
            height=height,
            marker=MarkerSpec(
                kind=kind,
                dictionary=dictionary,
                marker_id=marker_id,
                size_m=size_m,
                offset_frd_m=offset,  # type: ignore[arg-type]
            ),
            altitude_datum=datum,
            camera_latency_s=latency,
            site_origin=origin,
            extra=extra,
            cameras=tuple(cameras),
            camera_name=cameras[0].name if cameras else None,
        )


def site_to_metadata(origin: EnuOrigin) -> dict[str, str]:
    """``dronecal.site`` record of an ENU origin (degrees, metres)."""
    return {
        "origin_lat": repr(float(origin.lat_deg)),
        "origin_lon": repr(float(origin.lon_deg)),
        "origin_h": repr(float(origin.h_m)),
    }


def site_from_metadata(site: Mapping[str, str], source: str = "run.mcap") -> EnuOrigin:
    """Parse a ``dronecal.site`` record; raise ContractError naming a missing key."""
    values = []
    for key in ("origin_lat", "origin_lon", "origin_h"):
        text = site.get(key)
        if text is None:
            raise ContractError(
                f"{source}: metadata '{SITE_METADATA_NAME}' has no '{key}': write origin_lat, "
                "origin_lon (degrees) and origin_h (metres) or leave the record out"
            )
        try:
            values.append(float(text))
        except ValueError:
            raise ContractError(f"{source}: metadata '{SITE_METADATA_NAME}': '{key}' = {text!r} is not a number") from None
    return EnuOrigin(lat_deg=values[0], lon_deg=values[1], h_m=values[2])


@dataclass(frozen=True, eq=False)
class GnssFix:
    """One GNSS position.

    Attributes
    ----------
    timestamp_ns : time of the fix, UTC ns on the run clock.
    lat_deg, lon_deg : WGS84 degrees.
    alt_m : metres above the run's altitude datum (ellipsoid unless the run says msl).
    covariance_enu : (3, 3) position covariance, m^2, ENU; None when unknown.
    fix_type : one of FIX_TYPES, or None when unknown.
    """

    timestamp_ns: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    covariance_enu: np.ndarray | None = None
    fix_type: str | None = None


@dataclass(frozen=True, eq=False)
class Frame:
    """One compressed video frame.

    Attributes
    ----------
    timestamp_ns : capture time (or host arrival time, see camera.latency_s), UTC ns.
    format : ``"jpeg"`` or ``"png"``.
    data : the compressed image bytes.
    """

    timestamp_ns: int
    format: str
    data: bytes


@dataclass(frozen=True)
class RunEvent:
    """A mark over a time range on ``/events``.

    ``type`` is ``"hover"`` for a hold at a mission waypoint (metadata
    ``seq``, ``hold_s`` and, when known, ``lat``, ``lon``, ``alt`` of the
    commanded point), or ``"video_gap"``, ``"link_lost"``, ``"link_restored"``.

    Attributes
    ----------
    timestamp_ns : start, UTC ns.
    duration_ns : length, ns (0 for an instant).
    type : event type.
    metadata : further string key/values.
    """

    timestamp_ns: int
    duration_ns: int
    type: str
    metadata: dict[str, str] = field(default_factory=dict)

    @property
    def end_ns(self) -> int:
        """End of the event, UTC ns (inclusive)."""
        return self.timestamp_ns + self.duration_ns


@dataclass(frozen=True)
class Attitude:
    """Vehicle attitude as MAVLink ATTITUDE gives it: body FRD relative to NED.

    Attributes
    ----------
    timestamp_ns : UTC ns.
    roll_rad, pitch_rad, yaw_rad : Z-Y-X Euler angles, radians; yaw clockwise from north.
    """

    timestamp_ns: int
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


def fix_type_from_mavlink(gps_fix_type: int) -> str | None:
    """Contract fix_type of a MAVLink GPS_FIX_TYPE (0..8); None for unknown values."""
    return {
        0: "no_fix",
        1: "no_fix",
        2: "2d",
        3: "3d",
        4: "dgps",
        5: "rtk_float",
        6: "rtk_fixed",
        7: "3d",  # static fixed position
        8: "3d",  # PPP
    }.get(int(gps_fix_type))


# --------------------------------------------------------------------------
# plan.json (written by ``plan`` beside the mission): the parts ``fly`` records into the run


def _plan_number(value: Any, where: str, low: float, high: float, *, integer: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or not low <= value <= high \
            or (integer and value != int(value)):
        kind = "an integer" if integer else "a number"
        raise InputError(f"{where} is {value!r}: give {kind} in {low:g}..{high:g}, or re-run plan (or pass the --marker-* flags)")
    return float(value)


def marker_from_plan_json(plan_json: Mapping[str, Any], source: str = "plan.json") -> MarkerSpec | None:
    """The ``marker`` object of plan.json as a MarkerSpec, checked key by key; None when there is none.

    Raises
    ------
    InputError
        naming the key (``marker.size_m``...) that is not of its type or range.
    """
    marker = plan_json.get("marker")
    if marker is None:
        return None
    if not isinstance(marker, Mapping):
        raise InputError(f"{source}: 'marker' is {type(marker).__name__}, not an object: re-run plan or pass the --marker-* flags")
    if marker.get("size_m") is None:
        return None
    kind = marker.get("kind", "aruco")
    if kind not in MARKER_KINDS:
        raise InputError(f"{source}: marker.kind is {kind!r}: use one of {', '.join(MARKER_KINDS)}")
    dictionary = marker.get("dictionary", "DICT_4X4_50")
    if not isinstance(dictionary, str) or not dictionary.startswith("DICT_"):
        raise InputError(f"{source}: marker.dictionary is {dictionary!r}: give an OpenCV ArUco dictionary name, e.g. DICT_4X4_50")
    marker_id = int(_plan_number(marker.get("id", 0), f"{source}: marker.id", 0, 100_000, integer=True))
    size_m = _plan_number(marker["size_m"], f"{source}: marker.size_m", 1e-3, 10.0)
    offset = marker.get("offset_frd_m", (0.0, 0.0, 0.0))
    if not isinstance(offset, (list, tuple)) or len(offset) != 3:
        raise InputError(f"{source}: marker.offset_frd_m is {offset!r}: give [forward, right, down] in metres")
    offset_m = tuple(_plan_number(v, f"{source}: marker.offset_frd_m", -5.0, 5.0) for v in offset)
    return MarkerSpec(kind=kind, dictionary=dictionary, marker_id=marker_id, size_m=size_m, offset_frd_m=offset_m)  # type: ignore[arg-type]


def site_origin_from_plan_json(plan_json: Mapping[str, Any], source: str = "plan.json") -> EnuOrigin | None:
    """plan.json's ``enu_origin`` {lat_deg, lon_deg, h_m}, checked; None when absent."""
    origin = plan_json.get("enu_origin")
    if not isinstance(origin, Mapping) or not all(k in origin for k in ("lat_deg", "lon_deg", "h_m")):
        return None
    return EnuOrigin(_plan_number(origin["lat_deg"], f"{source}: enu_origin.lat_deg", -90, 90),
                     _plan_number(origin["lon_deg"], f"{source}: enu_origin.lon_deg", -180, 180),
                     _plan_number(origin["h_m"], f"{source}: enu_origin.h_m", -1000, 10000))
