"""A site file with several cameras: ``[[pole]]`` and ``[[camera]]`` tables (``plan --site``, issue 24).

A single-camera site file (``[camera]`` as one table, keys as the ``plan``
flags) is read by ``plan.site`` exactly as before. A file whose ``camera`` is
an array of tables is a *site*: several cameras planned into one mission.

    name = "two poles over a car park"
    [marker]                       # shared: one marker on the drone, one flight
    marker_sizes = [0.3, 0.6]
    [limits]
    endurance = 20.0
    [[pole]]
    name = "a"
    lat = -35.363261
    lon = 149.165230
    ground_alt = 584.0
    [[camera]]
    name = "a-wide"                # the run's camera name: [a-z0-9][a-z0-9_-]{0,31}
    pole = "a"                     # or lat/lon/ground_alt of its own
    mount_height = 3.5
    azimuth = 80.0
    tilt = 25.0
    focal_px = 900
    image_size = "1920x1080"
    distortion = [-0.28, 0.07]     # k1, k2[, p1, p2[, k3]], or a level: none | medium | strong

Keys outside the ``[[pole]]`` / ``[[camera]]`` tables are the shared plan
options (marker, limits, flight, evaluation); a camera-level key given there
(``fps``, ``focal_tolerance``, ...) is every camera's default. A camera table
takes the camera and intrinsics keys, ``roi`` / ``roi_range``, ``pole`` and
``from_run`` (a scout run whose estimate replaces the guess, ``plan.fromrun``).
Every problem is one line naming the camera or pole and the fix.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dronecal_field.core.camera import Distortion
from dronecal_field.errors import InputError

NAME_RE = re.compile(r"^[a-z0-9][a-z0-9_-]{0,31}$")  # the run contract's camera names (/cameras/<name>/...)
POLE_KEYS = ("name", "description", "lat", "lon", "ground_alt", "ground_amsl", "geoid_separation")
POSITION_KEYS = ("lat", "lon", "ground_alt", "ground_amsl")
CAMERA_EXTRA_KEYS = ("name", "description", "pole", "from_run", "roi", "roi_range")
REQUIRED_CAMERA_KEYS = ("mount_height", "azimuth", "tilt", "image_size")
MAX_CAMERAS = 16


@dataclass(frozen=True)
class SiteCameraSpec:
    """One ``[[camera]]`` table: its name, its pole, and its raw plan options (pole position merged in)."""

    name: str
    pole: str | None  # None: the camera gives its own position
    values: dict[str, Any]  # raw option values for ``plan.site.resolve_options`` (shared defaults + pole + camera)
    distortion: Distortion | None = None  # coefficients given as a list (None: the named level)
    from_run: str | None = None


@dataclass(frozen=True)
class SiteSpec:
    """A parsed multi-camera site file."""

    path: str
    name: str | None
    shared: dict[str, Any]  # raw shared option values (outside the pole/camera tables)
    poles: tuple[str, ...]
    cameras: tuple[SiteCameraSpec, ...]


def is_multi_site(path: str | os.PathLike) -> bool:
    """True when the TOML file's ``camera`` is an array of tables (``[[camera]]``); False for a single-camera file
    or one that cannot be read (``plan.site.load_site_file`` then says why)."""
    try:
        p = Path(path)
        if not p.is_file() or p.stat().st_size > 1_000_000:
            return False
        data = tomllib.loads(p.read_text(encoding="utf-8-sig"))
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return False
    return isinstance(data.get("camera"), list)


def _flatten(d: dict[str, Any], table: str, path: str, out: dict[str, Any], where: dict[str, str]) -> None:
    from dronecal_field.plan.site import KEY_ALIASES

    for k, v in d.items():
        if isinstance(v, dict):
            _flatten(v, f"{table}.{k}" if table else k, path, out, where)
            continue
        key = KEY_ALIASES.get(k.replace("-", "_"), k.replace("-", "_"))
        here = f"[{table}]" if table else "the top level"
        if key in out:
            raise InputError(f"site file {path}: key {key} is given twice (in {where[key]} and in {here}): keep one")
        out[key] = v
        where[key] = here


def _check_name(path: str, what: str, name: Any, seen: set[str]) -> str:
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise InputError(f"site file {path}: {what} name {name!r} is not [a-z0-9][a-z0-9_-]{{0,31}} "
                         "(lower case, digits, '-' or '_', at most 32; the run's topic /cameras/<name>/ uses it): rename it")
    if name in seen:
        raise InputError(f"site file {path}: {what} name {name!r} is used twice: give every {what} its own name")
    seen.add(name)
    return name


def parse_distortion(value: Any, where: str) -> tuple[str | None, Distortion | None]:
    """``distortion`` of a camera: a level name, or [k1, k2[, p1, p2[, k3]]] coefficients (OpenCV order)."""
    if isinstance(value, (list, tuple)):
        try:
            k = [float(v) for v in value]
        except (TypeError, ValueError):
            k = []
        if len(k) not in (1, 2, 4, 5) or not all(math.isfinite(v) for v in k) or any(abs(v) > 10 for v in k):
            raise InputError(f"{where}: distortion {value!r} is not [k1, k2] / [k1, k2, p1, p2] / [k1, k2, p1, p2, k3] "
                             "(OpenCV order, |k| <= 10) or a level none | medium | strong")
        k = k + [0.0] * (5 - len(k))
        return None, Distortion(k1=k[0], k2=k[1], p1=k[2], p2=k[3], k3=k[4])
    return value, None


def nearest_level(d: Distortion) -> str:
    """The named distortion level closest to coefficients ``d`` (by k1): what the guess band scales."""
    from dronecal_field.plan.site import DISTORTION_LEVELS

    return min(DISTORTION_LEVELS, key=lambda n: abs(DISTORTION_LEVELS[n].k1 - d.k1))


def load_multi_site(path: str | os.PathLike) -> SiteSpec:
    """Read and check a multi-camera site file; every problem is an ``InputError`` of one line."""
    from dronecal_field.plan.site import OPTION_BY_KEY

    p = Path(path)
    if not p.is_file():
        raise InputError(f"site file {p} does not exist: give a TOML file like missions/site-two-poles.toml")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8-sig"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"site file {p} is not valid TOML ({exc}): fix the line it names") from None
    poles_raw, cams_raw = data.pop("pole", []), data.pop("camera", [])
    if not isinstance(poles_raw, list) or not all(isinstance(x, dict) for x in poles_raw):
        raise InputError(f"site file {p}: 'pole' must be [[pole]] tables (name, lat, lon, ground_alt)")
    if not isinstance(cams_raw, list) or not cams_raw or not all(isinstance(x, dict) for x in cams_raw):
        raise InputError(f"site file {p}: 'camera' must be [[camera]] tables, one per camera")
    if len(cams_raw) > MAX_CAMERAS:
        raise InputError(f"site file {p}: {len(cams_raw)} cameras; plan at most {MAX_CAMERAS} in one site file (split the site)")
    shared: dict[str, Any] = {}
    _flatten(data, "", str(p), shared, {})
    name = shared.pop("name", None)
    shared.pop("description", None)
    unknown = sorted(k for k in shared if k not in OPTION_BY_KEY)
    if unknown:
        raise InputError(f"site file {p}: unknown key(s) {', '.join(unknown)}: valid keys are the plan flags, e.g. marker_sizes, endurance, speed")
    placed = sorted(k for k in shared if k in POSITION_KEYS)
    if placed:
        raise InputError(f"site file {p}: {', '.join(placed)} at the top level of a site: give each position in its [[pole]] or [[camera]] table")

    poles: dict[str, dict[str, Any]] = {}
    seen: set[str] = set()
    for k, t in enumerate(poles_raw):
        pname = _check_name(str(p), "pole", t.get("name"), seen)
        bad = sorted(set(t) - set(POLE_KEYS))
        if bad:
            raise InputError(f"site file {p}: pole {pname!r}: unknown key(s) {', '.join(bad)}: a pole takes {', '.join(POLE_KEYS)}")
        for key in ("lat", "lon"):
            if key not in t:
                raise InputError(f"site file {p}: pole {pname!r} has no {key}: give the pole's WGS84 {key} in degrees")
        if "ground_alt" not in t and "ground_amsl" not in t:
            raise InputError(f"site file {p}: pole {pname!r} has no ground height: give ground_alt (ellipsoidal, m) or ground_amsl with geoid_separation")
        poles[pname] = {k2: v for k2, v in t.items() if k2 not in ("name", "description")}

    allowed = {o.key for o in OPTION_BY_KEY.values() if o.group in ("camera", "intrinsics")} | set(CAMERA_EXTRA_KEYS)
    cameras: list[SiteCameraSpec] = []
    cam_seen: set[str] = set()
    for t in cams_raw:
        t = {k.replace("-", "_"): v for k, v in t.items()}
        cname = _check_name(str(p), "camera", t.get("name"), cam_seen)
        where = f"site file {p}: camera {cname!r}"
        bad = sorted(set(t) - allowed)
        if bad:
            raise InputError(f"{where}: unknown key(s) {', '.join(bad)}: a camera takes pole, mount_height, azimuth, tilt, focal_px, image_size, "
                             "distortion, ... (shared keys such as marker_sizes go outside the [[camera]] tables)")
        pole = t.get("pole")
        values = dict(shared)
        if pole is not None:
            if pole not in poles:
                raise InputError(f"{where}: pole {pole!r} is not one of the [[pole]] tables ({', '.join(poles) or 'none given'}): fix the name")
            own = sorted(k for k in POSITION_KEYS if k in t)
            if own:
                raise InputError(f"{where}: gives pole {pole!r} and its own {', '.join(own)}: keep one")
            values.update(poles[pole])
        elif not all(k in t for k in ("lat", "lon")):
            raise InputError(f"{where}: no position: give pole = \"NAME\" (a [[pole]] table) or lat, lon and ground_alt")
        missing = [k for k in REQUIRED_CAMERA_KEYS if k not in t and k not in values]
        if missing and t.get("from_run") is None:
            raise InputError(f"{where}: missing {', '.join(missing)}: give the camera's {', '.join(missing)} in its [[camera]] table")
        dist = None
        for k, v in t.items():
            if k in ("name", "description", "pole", "from_run"):
                continue
            if k == "distortion":
                level, dist = parse_distortion(v, where)
                values[k] = level if level is not None else nearest_level(dist)
                continue
            values[k] = v
        values["name"] = cname
        from_run = t.get("from_run")
        if from_run is not None:
            fr = Path(str(from_run))
            fr = fr if fr.is_absolute() else p.parent / fr
            if not fr.is_file():
                raise InputError(f"{where}: from_run {from_run!r} does not exist (paths are relative to the site file): give the scout run")
            from_run = str(fr)
        cameras.append(SiteCameraSpec(name=cname, pole=pole, values=values, distortion=dist, from_run=from_run))
    used = {c.pole for c in cameras}
    unused = [n for n in poles if n not in used]
    if unused:
        raise InputError(f"site file {p}: pole(s) {', '.join(unused)} carry no camera: remove them or give a camera pole = \"{unused[0]}\"")
    return SiteSpec(path=str(p), name=name, shared=shared, poles=tuple(poles), cameras=tuple(cameras))
