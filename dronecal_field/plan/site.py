"""What the surveyor knows: the site file / flags, and the camera guess built from them.

A site file is TOML with the same keys as the ``plan`` flags (dashes become
underscores), e.g. ``mount_height = 4.0``. Flags override the file.
:data:`OPTIONS` is the single table of those keys: the command builds its
argparse flags from it and :func:`load_site_file` checks a file against it.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

from dronecal_field.core.camera import Camera, CameraPose, Distortion, Intrinsics, look_rotation
from dronecal_field.errors import InputError, PlanError
from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu, site_to_enu_rotation

# Brown-Conrady guesses for ``--distortion`` (OpenCV order on normalised coordinates).
# 'medium' is the paper's Table 1 distorted camera.
DISTORTION_LEVELS: dict[str, Distortion] = {
    "none": Distortion(),
    "medium": Distortion(k1=-0.25, p1=-28e-5, p2=-5e-5),
    "strong": Distortion(k1=-0.4, k2=0.15),
}

# Diagonals (mm) of the usual "1/x inch" optical formats: the name is a
# vidicon-era convention, so a lookup table, not arithmetic.
SENSOR_FORMAT_DIAGONAL_MM: dict[str, float] = {
    "1/4": 4.5, "1/3.6": 5.0, "1/3.4": 5.29, "1/3.2": 5.68, "1/3": 6.0, "1/2.9": 6.23,
    "1/2.8": 6.46, "1/2.7": 6.72, "1/2.5": 7.18, "1/2.3": 7.66, "1/2": 8.0, "1/1.9": 8.5,
    "1/1.8": 8.93, "1/1.7": 9.5, "2/3": 11.0, "1/1.2": 13.33, "1": 16.0, "4/3": 21.6,
}

ARUCO_DICTIONARIES: tuple[str, ...] = (
    "DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_4X4_1000",
    "DICT_5X5_50", "DICT_5X5_100", "DICT_5X5_250", "DICT_5X5_1000",
    "DICT_6X6_50", "DICT_6X6_100", "DICT_6X6_250", "DICT_6X6_1000",
    "DICT_7X7_50", "DICT_7X7_100", "DICT_7X7_250", "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL",
)


# --------------------------------------------------------------------------
# Value parsers shared by flags and site files


def parse_image_size(value: Any) -> tuple[int, int]:
    """(width, height) pixels from ``"3840x2160"`` or ``[3840, 2160]``."""
    try:
        if isinstance(value, str):
            w, h = value.lower().replace("×", "x").split("x")
        else:
            w, h = value
        w, h = int(w), int(h)
    except (TypeError, ValueError):
        raise InputError(f"image size {value!r} is not WIDTHxHEIGHT: give e.g. --image-size 1920x1080") from None
    if w < 16 or h < 16:
        raise InputError(f"image size {w}x{h} is too small: give the camera's full resolution, e.g. 1920x1080")
    return w, h


def parse_floats(value: Any, n: int | tuple[int, ...], what: str) -> tuple[float, ...]:
    """A tuple of floats from ``"a,b,c"`` or a list; ``n`` is the allowed count(s)."""
    counts = (n,) if isinstance(n, int) else n
    try:
        items = value.split(",") if isinstance(value, str) else list(value)
        out = tuple(float(v) for v in items)
    except (TypeError, ValueError):
        out = ()
    if len(out) not in counts or not all(math.isfinite(v) for v in out):
        raise InputError(f"{what} {value!r} needs {' or '.join(map(str, counts))} comma-separated numbers")
    return out


def parse_polygon(value: Any) -> tuple[tuple[float, float], ...]:
    """Geofence vertices ((lat, lon), ...) from ``"lat,lon;lat,lon;..."`` or [[lat, lon], ...]."""
    items = value.split(";") if isinstance(value, str) else list(value)
    verts = tuple(parse_floats(v, 2, "geofence vertex") for v in items if (not isinstance(v, str)) or v.strip())
    if len(verts) < 3:
        raise InputError(f"geofence has {len(verts)} vertices: give at least 3 as 'lat,lon;lat,lon;lat,lon'")
    return tuple((float(a), float(b)) for a, b in verts)


def _choice(options: tuple[str, ...]) -> Callable[[Any], str]:
    def parse(value: Any) -> str:
        v = str(value).strip()
        if v not in options:
            raise InputError(f"{value!r} is not one of {', '.join(options)}")
        return v

    return parse


def _bool(value: Any) -> bool:
    if isinstance(value, bool):
        return value
    if str(value).lower() in ("1", "true", "yes", "on"):
        return True
    if str(value).lower() in ("0", "false", "no", "off"):
        return False
    raise InputError(f"{value!r} is not true/false")


@dataclass(frozen=True)
class OptionSpec:
    """One site-file key / ``plan`` flag: ``--key-with-dashes`` on the command line."""

    key: str
    parse: Callable[[Any], Any]
    default: Any
    help: str
    metavar: str | None = None
    group: str = "site"
    flag_only: bool = False  # True: a boolean switch (store_true) on the command line

    @property
    def flag(self) -> str:
        return "--" + self.key.replace("_", "-")


def _pos_float(name: str) -> Callable[[Any], float]:
    def parse(value: Any) -> float:
        if isinstance(value, bool):  # TOML true is not 1 m
            raise InputError(f"{name} {str(value).lower()} is a true/false, not a number; write the number")
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise InputError(f"{name} {value!r} is not a number") from None
        if not math.isfinite(v):
            raise InputError(f"{name} {value!r} is not finite")
        return v

    return parse


def _int(name: str) -> Callable[[Any], int]:
    def parse(value: Any) -> int:
        if isinstance(value, bool) or (isinstance(value, float) and not (math.isfinite(value) and value.is_integer())):
            raise InputError(f"{name} {value!r} is not an integer; write a whole number")  # 1.9 is not read as 1
        try:
            return int(value)
        except (TypeError, ValueError):
            raise InputError(f"{name} {value!r} is not an integer") from None

    return parse


_F = _pos_float


def _pct(name: str) -> Callable[[Any], float]:
    """A percentage from ``10``, ``"10"`` or ``"10%"``."""
    def parse(value: Any) -> float:
        return _pos_float(name)(value.strip().rstrip("%") if isinstance(value, str) else value)

    return parse

OPTIONS: tuple[OptionSpec, ...] = (
    # camera position and pose
    OptionSpec("lat", _F("lat"), None, "camera pole latitude, deg WGS84", "DEG", "camera"),
    OptionSpec("lon", _F("lon"), None, "camera pole longitude, deg WGS84", "DEG", "camera"),
    OptionSpec("ground_alt", _F("ground_alt"), None, "ground height at the pole's foot, m above the WGS84 ellipsoid (what RTK receivers show as 'ellipsoidal height')", "M", "camera"),
    OptionSpec("ground_amsl", _F("ground_amsl"), None, "ground height at the pole's foot, m above mean sea level; needs --geoid-separation", "M", "camera"),
    OptionSpec("geoid_separation", _F("geoid_separation"), None, "geoid undulation N at the site, m (ellipsoidal h = AMSL + N); needed with --ground-amsl or --alt-frame amsl", "M", "camera"),
    OptionSpec("mount_height", _F("mount_height"), None, "camera height above the ground, m", "M", "camera"),
    OptionSpec("azimuth", _F("azimuth"), None, "optical axis azimuth, deg clockwise from true north", "DEG", "camera"),
    OptionSpec("tilt", _F("tilt"), None, "optical axis angle below horizontal, deg (negative: looking up)", "DEG", "camera"),
    OptionSpec("roll", _F("roll"), 0.0, "image roll, deg (positive turns the image clockwise)", "DEG", "camera"),
    # intrinsics guess
    OptionSpec("image_size", parse_image_size, None, "image size in pixels", "WxH", "intrinsics"),
    OptionSpec("focal_px", _F("focal_px"), None, "focal length in pixels", "PX", "intrinsics"),
    OptionSpec("focal_mm", _F("focal_mm"), None, "lens focal length, mm (with --sensor-width, --sensor-format or --pixel-pitch)", "MM", "intrinsics"),
    OptionSpec("sensor_width", _F("sensor_width"), None, "sensor active width, mm", "MM", "intrinsics"),
    OptionSpec("sensor_format", str, None, "optical format such as 1/2.8 (inch type; the diagonal comes from a table)", "TYPE", "intrinsics"),
    OptionSpec("pixel_pitch", _F("pixel_pitch"), None, "pixel pitch, micrometres", "UM", "intrinsics"),
    OptionSpec("hfov", _F("hfov"), None, "horizontal field of view, deg (pinhole equivalent)", "DEG", "intrinsics"),
    OptionSpec("distortion", _choice(tuple(DISTORTION_LEVELS)), "medium", "lens distortion guess: none | medium (paper Table 1) | strong", "LEVEL", "intrinsics"),
    # how far the guess may be from the camera: every planned marker stays in the image of the band's corner cameras
    OptionSpec("focal_tolerance", _pct("focal_tolerance"), 10.0, "how far the real focal length may be from the guess, % (10 or 10%): targets stay in view for focal x (1 +- this)", "PCT", "intrinsics"),
    OptionSpec("tilt_tolerance", _F("tilt_tolerance"), 1.0, "how far the real tilt may be from --tilt, deg either way", "DEG", "camera"),
    OptionSpec("azimuth_tolerance", _F("azimuth_tolerance"), 2.0, "how far the real azimuth may be from --azimuth, deg either way", "DEG", "camera"),
    OptionSpec("distortion_range", lambda v: tuple(str(x).strip() for x in (v.split(",") if isinstance(v, str) else v)), None,
               "the weakest and strongest distortion the lens may have, LOW,HIGH: levels (none,medium) or shares of the --distortion level (default 0.5,1)", "LOW,HIGH", "intrinsics"),
    OptionSpec("fps", _F("fps"), 25.0, "camera frame rate, frames/s (sets the default hover)", "HZ", "intrinsics"),
    OptionSpec("exposure_s", _F("exposure_s"), 0.004, "exposure (shutter) time, s; with the focal length it caps the leg speed (motion blur under 1 px)", "S", "intrinsics"),
    # marker
    OptionSpec("marker_size", _F("marker_size"), None, "printed ArUco marker side (black border to black border), m: plan with this marker only (default: the smallest of --marker-sizes that covers the ROI)", "M", "marker"),
    OptionSpec("marker_sizes", lambda v: parse_floats(v, tuple(range(1, 9)), "marker sizes"), (0.3, 0.6), "marker sides you can print and carry, m; the plan picks the smallest that covers the ROI", "M,M", "marker"),
    OptionSpec("aruco_dict", _choice(ARUCO_DICTIONARIES), "DICT_4X4_50", "ArUco dictionary", "NAME", "marker"),
    OptionSpec("marker_id", _int("marker_id"), 0, "ArUco marker id", "ID", "marker"),
    OptionSpec("marker_offset", lambda v: parse_floats(v, 3, "marker offset"), (0.0, 0.0, 0.0), "marker centre from the GNSS antenna in the body frame: forward, right, down, m", "F,R,D", "marker"),
    OptionSpec("min_marker_px", _F("min_marker_px"), 20.0, "smallest marker side in the image that the detector reads, px", "PX", "marker"),
    # limits and flight
    OptionSpec("min_agl", _F("min_agl"), 1.0, "lowest drone height above ground, m", "M", "limits"),
    OptionSpec("max_agl", _F("max_agl"), None, "highest drone height above ground, m (default: 3 m above the camera)", "M", "limits"),
    OptionSpec("max_range", _F("max_range"), None, "largest horizontal distance of the drone from the pole, m (a wall, a road)", "M", "limits"),
    OptionSpec("keep_out", _F("keep_out"), 2.0, "no-fly radius around the pole, m", "M", "limits"),
    OptionSpec("geofence", parse_polygon, None, "area the drone must stay in: 'lat,lon;lat,lon;...' (site file: [[lat, lon], ...])", "POLY", "limits"),
    OptionSpec("takeoff", lambda v: parse_floats(v, (2, 3), "takeoff point"), None, "take-off and landing point LAT,LON[,H] (H ellipsoidal, default the pole's ground height); default beside the grid", "LAT,LON[,H]", "limits"),
    OptionSpec("speed", _F("speed"), 1.5, "horizontal speed between points (DO_CHANGE_SPEED), m/s", "M_S", "limits"),
    OptionSpec("hover", _F("hover"), None, "hold at each point, whole s (default from --fps: 1 s to settle + 40 frames)", "S", "limits"),
    OptionSpec("alt_frame", _choice(("relative", "amsl")), "relative", "mission altitudes: relative to home (the take-off point's ground) or amsl", "FRAME", "limits"),
    OptionSpec("end", _choice(("land", "rtl")), "land", "mission end: land (NAV_LAND at the take-off point) or rtl (climbs to RTL_ALT first)", "HOW", "limits"),
    OptionSpec("yaw_mode", _choice(("roi", "condition-yaw")), "roi", "how the nose (and marker) faces the camera: one DO_SET_ROI, or a CONDITION_YAW per point", "MODE", "limits"),
    OptionSpec("endurance", _F("endurance"), 20.0, "usable battery endurance in hover, min; a flight uses at most 75 % of it, longer plans are split into flights", "MIN", "limits"),
    OptionSpec("gnss_hz", _F("gnss_hz"), 10.0, "GNSS fix rate of the drone's receiver, Hz (fixes along the fly-through legs)", "HZ", "limits"),
    # sampling design
    OptionSpec("strategy", _choice(("image", "paper-far", "paper-near", "paper-full")), "image", "image: targets spread over the ROI in the image, two depths per ray; paper-far/near/full: the paper's metric grid (X 4-8 / 0-4 / 0-8 m)", "NAME", "sampling"),
    OptionSpec("sampling", _choice(("auto", "hover", "through", "mixed")), "auto", "hover at every point, fly through legs (holds at leg ends), or mixed (holds plus the fixes between them); auto: the lower predicted ROI error within the battery", "HOW", "sampling"),
    OptionSpec("roi", str, None, "region of interest: a GeoJSON polygon file (WGS84: a road, a car park) or 'image' (the whole image); default the ground in --roi-range", "FILE|image", "sampling"),
    OptionSpec("roi_range", lambda v: parse_floats(v, 2, "ROI range"), (3.0, 40.0), "ground distances from the pole the ROI covers, m (with a layer up to 2 m above the ground)", "MIN,MAX", "sampling"),
    # evaluation
    OptionSpec("trials", _int("trials"), 200, "Monte-Carlo trials per candidate", "N", "evaluation"),
    OptionSpec("seed", _int("seed"), 0, "Monte-Carlo seed", "N", "evaluation"),
    OptionSpec("sigma_px", _F("sigma_px"), 2.0, "marker detection noise, px (paper: 2)", "PX", "evaluation"),
    OptionSpec("sigma_h", _F("sigma_h"), 0.01, "horizontal position noise, m (paper RTK: 0.01)", "M", "evaluation"),
    OptionSpec("sigma_v", _F("sigma_v"), 0.015, "vertical position noise, m (paper RTK: 0.015)", "M", "evaluation"),
    OptionSpec("model", str, "default", "calibration model used in the prediction (see calibrate --help)", "MODEL", "evaluation"),
    OptionSpec("optimize", _bool, False, "pick the candidate with the best predicted error within --max-flight-time", None, "evaluation", flag_only=True),
    OptionSpec("max_flight_time", _F("max_flight_time"), None, "flight-time budget, min: --strategy image chooses within it (default 75 % of --endurance), --optimize too (default --endurance x 0.8)", "MIN", "evaluation"),
)
OPTION_BY_KEY: dict[str, OptionSpec] = {o.key: o for o in OPTIONS}

# Site-file keys that are other names of an option (the flag's own name).
KEY_ALIASES = {"marker_dictionary": "aruco_dict"}

# Sane ranges (low, high, low_open) of the numeric options: a value outside is a typo or a unit
# error, refused in one line before any work (1e308 min of endurance, 10^8 trials).
RANGES: dict[str, tuple[float, float, bool]] = {
    "mount_height": (0.0, 1000.0, True), "roll": (-180.0, 180.0, False), "azimuth": (-360.0, 360.0, False), "tilt": (-90.0, 90.0, False),
    "ground_alt": (-1000.0, 10000.0, False), "ground_amsl": (-1000.0, 10000.0, False), "geoid_separation": (-150.0, 150.0, False),
    "focal_mm": (0.0, 10000.0, True), "sensor_width": (0.0, 1000.0, True), "pixel_pitch": (0.0, 1000.0, True), "fps": (0.0, 1000.0, True),
    "exposure_s": (0.0, 1.0, True), "marker_size": (0.0, 10.0, True), "min_marker_px": (1.0, 10000.0, False),
    "min_agl": (0.0, 1000.0, False), "max_agl": (0.0, 1000.0, True), "max_range": (0.0, 100000.0, True), "keep_out": (0.0, 1000.0, False),
    "speed": (0.0, 50.0, True), "hover": (0.0, 3600.0, False), "endurance": (0.0, 600.0, True), "gnss_hz": (0.0, 100.0, True),
    "trials": (2, 100_000, False), "seed": (0, 2**32 - 1, False), "sigma_px": (0.0, 1000.0, False), "sigma_h": (0.0, 100.0, False),
    "sigma_v": (0.0, 100.0, False), "max_flight_time": (0.0, 600.0, True),
    "focal_tolerance": (0.0, 60.0, False), "tilt_tolerance": (0.0, 30.0, False), "azimuth_tolerance": (0.0, 60.0, False),
}


def load_site_file(path: str | os.PathLike) -> dict[str, Any]:
    """Raw values of a TOML site file; unknown keys are an InputError naming the valid ones.

    Tables are flattened (``[camera] tilt = 30`` is ``tilt``) so files can be grouped
    for reading; the keys themselves are those of :data:`OPTIONS`.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"site file {path} does not exist: give a TOML file like missions/security-4k.toml")
    if not path.stat().st_size <= 1_000_000:
        raise InputError(f"site file {path} is larger than 1 MB: give the site's TOML file")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8-sig"))  # a BOM (Windows editors) is fine
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"site file {path} is not valid TOML ({exc}): fix the line it names") from None
    flat: dict[str, Any] = {}
    where: dict[str, str] = {}

    def walk(d: dict[str, Any], table: str) -> None:
        for k, v in d.items():
            if isinstance(v, dict):
                walk(v, f"{table}.{k}" if table else k)
                continue
            key = k.replace("-", "_")
            key = KEY_ALIASES.get(key, key)
            here = f"[{table}]" if table else "the top level"
            if key in flat:
                raise InputError(f"site file {path}: key {key} is given twice (in {where[key]} and in {here}): keep one")
            flat[key] = v
            where[key] = here

    walk(data, "")
    unknown = sorted(k for k in flat if k not in OPTION_BY_KEY and k not in ("name", "description"))
    if unknown:
        raise InputError(f"site file {path}: unknown key(s) {', '.join(unknown)}: valid keys are the plan flags, e.g. {', '.join(o.key for o in OPTIONS[:6])}")
    return flat


def resolve_options(values: dict[str, Any]) -> dict[str, Any]:
    """Parse and default every option; ``values`` maps keys to raw values (None = unset)."""
    out: dict[str, Any] = {}
    for spec in OPTIONS:
        raw = values.get(spec.key)
        if raw is None:
            out[spec.key] = spec.default
            continue
        try:
            out[spec.key] = spec.parse(raw)
        except InputError as exc:
            raise InputError(f"{spec.flag}: {exc}") from None
        bounds = RANGES.get(spec.key)
        value = out[spec.key]
        if bounds is not None and isinstance(value, (int, float)) and not isinstance(value, bool):
            low, high, low_open = bounds
            if not (math.isfinite(value) and (value > low if low_open else value >= low) and value <= high):
                shown = f"{value}" if isinstance(value, int) else f"{value:g}"
                raise InputError(f"{spec.flag} {shown} is outside {'(' if low_open else '['}{low:g}, {high:g}]: "
                                 f"check the unit ({spec.help.split(';')[0]})")
    out["name"] = values.get("name")
    return out


# --------------------------------------------------------------------------
# Domain values


@dataclass(frozen=True)
class CameraSite:
    """Where the camera is and where it looks."""

    lat_deg: float
    lon_deg: float
    ground_h_m: float  # WGS84 ellipsoidal height of the pole's foot
    mount_height_m: float  # camera centre above the ground
    azimuth_deg: float  # optical axis, clockwise from true north
    tilt_deg: float  # below horizontal
    roll_deg: float = 0.0
    geoid_separation_m: float | None = None  # N: h = AMSL + N, when known

    @property
    def origin(self) -> EnuOrigin:
        """ENU origin: the pole's foot."""
        return EnuOrigin(lat_deg=self.lat_deg, lon_deg=self.lon_deg, h_m=self.ground_h_m)

    @property
    def R_enu_from_site(self) -> np.ndarray:
        """(3, 3) rotation from the site frame to ENU."""
        return site_to_enu_rotation(self.azimuth_deg)


@dataclass(frozen=True)
class LensGuess:
    """The rough intrinsics, and how the focal length was obtained."""

    width: int
    height: int
    focal_px: float
    distortion_level: str
    focal_source: str  # e.g. "4 mm lens on 1/2.8\" (5.63 mm wide)"
    fps: float = 25.0

    @property
    def hfov_deg(self) -> float:
        return 2.0 * math.degrees(math.atan(self.width / 2.0 / self.focal_px))

    @property
    def vfov_deg(self) -> float:
        return 2.0 * math.degrees(math.atan(self.height / 2.0 / self.focal_px))


@dataclass(frozen=True)
class Marker:
    """The ArUco marker carried by the drone."""

    size_m: float
    dictionary: str = "DICT_4X4_50"
    marker_id: int = 0
    offset_frd_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # from the GNSS antenna, body forward/right/down
    min_px: float = 20.0


def resolve_focal_px(
    width: int,
    height: int,
    focal_px: float | None = None,
    focal_mm: float | None = None,
    sensor_width_mm: float | None = None,
    sensor_format: str | None = None,
    pixel_pitch_um: float | None = None,
    hfov_deg: float | None = None,
) -> tuple[float, str]:
    """Focal length in pixels from whichever datasheet values the user has.

    Parameters
    ----------
    width, height : image size, px
    focal_px : focal length, px
    focal_mm : lens focal length, mm; needs one of sensor_width_mm, sensor_format, pixel_pitch_um
    sensor_width_mm : active sensor width, mm
    sensor_format : optical format, e.g. ``"1/2.8"``; width = diagonal x W / hypot(W, H)
    pixel_pitch_um : pixel pitch, micrometres
    hfov_deg : horizontal field of view, deg (pinhole)

    Returns
    -------
    (focal_px, description). When several forms are given they must agree to 10 %.
    """
    candidates: list[tuple[float, str]] = []
    if focal_px is not None:
        candidates.append((focal_px, f"{focal_px:g} px given"))
    if focal_mm is not None:
        if sensor_width_mm is not None:
            candidates.append((focal_mm / sensor_width_mm * width, f"{focal_mm:g} mm lens, {sensor_width_mm:g} mm wide sensor"))
        if sensor_format is not None:
            key = sensor_format.strip().rstrip('"').rstrip("in").strip()
            if key not in SENSOR_FORMAT_DIAGONAL_MM:
                raise InputError(f"sensor format {sensor_format!r} is not in the table ({', '.join(SENSOR_FORMAT_DIAGONAL_MM)}): give --sensor-width in mm instead")
            sw = SENSOR_FORMAT_DIAGONAL_MM[key] * width / math.hypot(width, height)
            candidates.append((focal_mm / sw * width, f"{focal_mm:g} mm lens on {key}\" ({sw:.2f} mm wide)"))
        if pixel_pitch_um is not None:
            candidates.append((focal_mm * 1000.0 / pixel_pitch_um, f"{focal_mm:g} mm lens, {pixel_pitch_um:g} um pixels"))
        if sensor_width_mm is None and sensor_format is None and pixel_pitch_um is None:
            raise InputError("--focal-mm needs the sensor: add --sensor-width MM, --sensor-format 1/2.8 or --pixel-pitch UM")
    if hfov_deg is not None:
        if not 1.0 < hfov_deg < 179.0:
            raise InputError(f"--hfov {hfov_deg:g} deg is outside (1, 179): give the horizontal field of view in degrees")
        candidates.append((width / 2.0 / math.tan(math.radians(hfov_deg) / 2.0), f"{hfov_deg:g} deg horizontal field of view"))
    if not candidates:
        raise InputError("no focal length: give --focal-px, or --focal-mm with --sensor-width/--sensor-format/--pixel-pitch, or --hfov")
    f0, what0 = candidates[0]
    for f, what in candidates[1:]:
        if abs(f - f0) > 0.1 * f0:
            raise InputError(f"focal length disagrees: {what0} gives {f0:.0f} px but {what} gives {f:.0f} px: drop the wrong value")
    if not f0 > 0:
        raise InputError(f"focal length {f0:g} px is not positive: check the lens values")
    return float(f0), what0


def guess_camera(site: CameraSite, lens: LensGuess, frame: str = "enu") -> Camera:
    """The guessed camera: pinhole from the lens, principal point at the image centre.

    Parameters
    ----------
    site : pole position and pose
    lens : intrinsics guess
    frame : ``"enu"`` (world = ENU at the pole's foot, for camera_guess.yaml) or
        ``"site"`` (world = site frame: X along the azimuth, Y left, Z up), which
        the grid code uses.
    """
    a = math.radians(site.azimuth_deg)
    t = math.radians(site.tilt_deg)
    forward_enu = np.array([math.sin(a) * math.cos(t), math.cos(a) * math.cos(t), -math.sin(t)])
    if abs(site.tilt_deg) >= 89.5:
        raise PlanError(f"tilt {site.tilt_deg:g} deg looks straight {'down' if site.tilt_deg > 0 else 'up'}: this planner needs a camera that looks across the ground (tilt below 89 deg)")
    R_cam_from_enu = look_rotation(forward_enu, roll_deg=site.roll_deg)
    position_enu = np.array([0.0, 0.0, site.mount_height_m])
    if frame == "site":
        R = R_cam_from_enu @ site.R_enu_from_site
        position = site.R_enu_from_site.T @ position_enu
        origin = None
    elif frame == "enu":
        R, position, origin = R_cam_from_enu, position_enu, tuple(site.origin.as_list())
    else:
        raise ValueError(f"frame must be 'enu' or 'site', not {frame!r}")
    return Camera(
        intrinsics=Intrinsics(fx=lens.focal_px, fy=lens.focal_px, cx=lens.width / 2.0, cy=lens.height / 2.0, width=lens.width, height=lens.height),
        distortion=DISTORTION_LEVELS[lens.distortion_level],
        pose=CameraPose.from_position(R, position),
        enu_origin=origin,
    )


def latlon_to_site(site: CameraSite, lat_lon: np.ndarray, h_m: np.ndarray | float | None = None) -> np.ndarray:
    """Site-frame points (N, 3) of (N, 2) lat/lon deg at ellipsoidal heights ``h_m`` (default the ground)."""
    ll = np.atleast_2d(np.asarray(lat_lon, float))
    h = site.ground_h_m if h_m is None else h_m
    enu = geodetic_to_enu(ll[:, 0], ll[:, 1], h, site.origin)
    return enu @ site.R_enu_from_site
