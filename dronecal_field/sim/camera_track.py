"""The vehicle track the simulated camera follows: timestamped telemetry, interpolated.

Pure bookkeeping, no I/O: the MAVLink listener (sim/camera.py) feeds it
samples stamped with their host arrival time (integer nanoseconds, UTC), and
the frame loop asks where the vehicle was at ``frame time - latency``.

Heights: MAVLink GLOBAL_POSITION_INT.alt is above mean sea level. When the
vehicle also reports ``GPS_RAW_INT.alt_ellipsoid`` (non-zero), the track
learns the geoid separation (``alt_ellipsoid - alt`` of the same fix) and
returns WGS84 ellipsoidal heights; otherwise heights are returned as reported,
and the truth camera's ``enu_origin`` height must then be in that same datum
(docs/simulators.md).
"""

from __future__ import annotations

import bisect
import threading
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class GeodeticPose:
    """Antenna position (WGS84 degrees, metres in ``altitude_datum``) and FRD attitude (radians)."""

    lat_deg: float
    lon_deg: float
    h_m: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    altitude_datum: str  # "ellipsoid" or "msl"


def _wrap_pi(a: float) -> float:
    return float((a + np.pi) % (2.0 * np.pi) - np.pi)


class PoseTrack:
    """Thread-safe buffer of the last ``horizon_s`` of positions and attitudes.

    Parameters
    ----------
    horizon_s : how much history to keep, seconds (must exceed the camera latency).
    use_ellipsoid : apply GPS_RAW_INT's geoid separation when the vehicle reports one.
    """

    def __init__(self, horizon_s: float = 30.0, use_ellipsoid: bool = True) -> None:
        self._horizon_ns = int(horizon_s * 1e9)
        self._use_ellipsoid = use_ellipsoid
        self._lock = threading.Lock()
        self._pos_t: list[int] = []
        self._pos: list[tuple[float, float, float]] = []
        self._att_t: list[int] = []
        self._att: list[tuple[float, float, float]] = []
        self._undulation_m: float | None = None

    @property
    def geoid_separation_m(self) -> float | None:
        """Ellipsoidal minus MSL height learned from GPS_RAW_INT, metres, or None."""
        return self._undulation_m

    def add_position(self, time_ns: int, lat_deg: float, lon_deg: float, alt_msl_m: float) -> None:
        """A GLOBAL_POSITION_INT sample: degrees, metres above mean sea level."""
        with self._lock:
            self._insert(self._pos_t, self._pos, int(time_ns), (float(lat_deg), float(lon_deg), float(alt_msl_m)))

    def add_attitude(self, time_ns: int, roll_rad: float, pitch_rad: float, yaw_rad: float) -> None:
        """An ATTITUDE sample, radians."""
        with self._lock:
            self._insert(self._att_t, self._att, int(time_ns), (float(roll_rad), float(pitch_rad), float(yaw_rad)))

    def add_gps_raw(self, alt_msl_m: float, alt_ellipsoid_m: float | None) -> None:
        """A GPS_RAW_INT fix: its MSL and ellipsoidal heights (None or 0 when not reported)."""
        if self._use_ellipsoid and alt_ellipsoid_m:
            self._undulation_m = float(alt_ellipsoid_m) - float(alt_msl_m)

    def _insert(self, times: list[int], values: list, t: int, value: tuple) -> None:
        if times and t < times[-1]:
            i = bisect.bisect_right(times, t)
            times.insert(i, t)
            values.insert(i, value)
        else:
            times.append(t)
            values.append(value)
        cut = bisect.bisect_left(times, times[-1] - self._horizon_ns)
        if cut > 0:
            del times[:cut]
            del values[:cut]

    @staticmethod
    def _interpolate(times: list[int], values: list, t: int, angles: bool) -> tuple[float, ...] | None:
        if not times:
            return None
        i = bisect.bisect_right(times, t)
        if i == 0:
            return values[0]
        if i == len(times):
            return values[-1]  # hold the last sample: a vehicle whose telemetry pauses stays put
        t0, t1 = times[i - 1], times[i]
        f = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
        a, b = values[i - 1], values[i]
        if angles:
            return tuple(_wrap_pi(x + f * _wrap_pi(y - x)) for x, y in zip(a, b))
        return tuple(x + f * (y - x) for x, y in zip(a, b))

    def pose_at(self, time_ns: int) -> GeodeticPose | None:
        """The vehicle at ``time_ns`` (linear in position, shortest way in angles), or None before any position.

        Before the first attitude sample the vehicle is taken as level, nose north.
        """
        with self._lock:
            pos = self._interpolate(self._pos_t, self._pos, int(time_ns), angles=False)
            att = self._interpolate(self._att_t, self._att, int(time_ns), angles=True)
            und = self._undulation_m
        if pos is None:
            return None
        roll, pitch, yaw = att if att is not None else (0.0, 0.0, 0.0)
        return GeodeticPose(
            lat_deg=pos[0],
            lon_deg=pos[1],
            h_m=pos[2] + (und or 0.0),
            roll_rad=roll,
            pitch_rad=pitch,
            yaw_rad=yaw,
            altitude_datum="ellipsoid" if und is not None else "msl",
        )

    @property
    def n_positions(self) -> int:
        """Position samples held."""
        with self._lock:
            return len(self._pos_t)
