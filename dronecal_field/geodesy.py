"""WGS84 <-> local ENU through pyproj's topocentric conversion.

All geodesy in the project goes through here. Heights are metres above the
WGS84 ellipsoid unless a caller says otherwise (and then uses one datum
throughout, see shared/contracts/run-format.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np


@dataclass(frozen=True)
class EnuOrigin:
    """Origin of a local ENU frame: WGS84 latitude/longitude (deg) and ellipsoidal height (m)."""

    lat_deg: float
    lon_deg: float
    h_m: float

    def __post_init__(self) -> None:
        # numpy scalars would print as "np.float64(...)" inside the PROJ pipeline string
        for name in ("lat_deg", "lon_deg", "h_m"):
            object.__setattr__(self, name, float(getattr(self, name)))

    def as_list(self) -> list[float]:
        return [self.lat_deg, self.lon_deg, self.h_m]


@lru_cache(maxsize=64)
def _transformers(lat_deg: float, lon_deg: float, h_m: float):
    from pyproj import Transformer

    pipeline = (
        "+proj=pipeline "
        "+step +proj=unitconvert +xy_in=deg +xy_out=rad "
        "+step +proj=cart +ellps=WGS84 "
        f"+step +proj=topocentric +ellps=WGS84 +lat_0={float(lat_deg)!r} +lon_0={float(lon_deg)!r} +h_0={float(h_m)!r}"
    )
    forward = Transformer.from_pipeline(pipeline)
    return forward


def geodetic_to_enu(
    lat_deg: np.ndarray | float,
    lon_deg: np.ndarray | float,
    h_m: np.ndarray | float,
    origin: EnuOrigin,
) -> np.ndarray:
    """ENU metres (N, 3) of WGS84 points (each argument scalar or (N,))."""
    fwd = _transformers(origin.lat_deg, origin.lon_deg, origin.h_m)
    lat, lon, h = np.broadcast_arrays(
        np.atleast_1d(np.asarray(lat_deg, float)),
        np.atleast_1d(np.asarray(lon_deg, float)),
        np.atleast_1d(np.asarray(h_m, float)),
    )
    e, n, u = fwd.transform(lon, lat, h)
    return np.stack([np.asarray(e), np.asarray(n), np.asarray(u)], -1)


def enu_to_geodetic(enu: np.ndarray, origin: EnuOrigin) -> np.ndarray:
    """WGS84 (N, 3) [lat_deg, lon_deg, h_m] of ENU points (N, 3) metres."""
    from pyproj.enums import TransformDirection

    fwd = _transformers(origin.lat_deg, origin.lon_deg, origin.h_m)
    enu = np.atleast_2d(np.asarray(enu, float))
    lon, lat, h = fwd.transform(enu[:, 0], enu[:, 1], enu[:, 2], direction=TransformDirection.INVERSE)
    return np.stack([np.asarray(lat), np.asarray(lon), np.asarray(h)], -1)


# PROJ's EGM96 grid (pyproj's data directory or PROJ_DATA); not shipped with pyproj's wheel.
EGM96_GRID = "us_nga_egm96_15.tif"


@lru_cache(maxsize=1)
def _egm96_transformer():
    """WGS84 ellipsoidal -> EGM96 height, or None when PROJ has no grid offline (it would then fall
    back to a "ballpark" transformation that leaves heights unchanged: a silent 0 m separation)."""
    import warnings

    from pyproj.transformer import TransformerGroup

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "best transformation is not available": answered by returning None
        group = TransformerGroup("EPSG:4979", "EPSG:4326+5773", always_xy=True)
    if not group.best_available or not group.transformers:
        return None
    return group.transformers[0]


def geoid_separation_m(lat_deg: float, lon_deg: float) -> float | None:
    """EGM96 geoid separation N (ellipsoidal minus AMSL height, m) at a point, or None.

    From PROJ's EGM96 grid when it is installed where PROJ finds it offline
    (``EGM96_GRID`` in pyproj's data directory or ``PROJ_DATA``); None when it
    is not, so a caller can say which datum it wrote instead of writing an
    ellipsoidal height where AMSL is read (about 30 m off in Atlanta).

    Parameters
    ----------
    lat_deg, lon_deg : float
        WGS84 degrees.
    """
    transformer = _egm96_transformer()
    if transformer is None:
        return None
    _lon, _lat, h_amsl = transformer.transform(float(lon_deg), float(lat_deg), 0.0)
    if not np.isfinite(h_amsl):
        return None
    return float(0.0 - h_amsl)


def site_to_enu_rotation(azimuth_deg: float) -> np.ndarray:
    """(3, 3) R_enu_from_site: site frame X along the azimuth, Y left, Z up (docs/conventions.md)."""
    a = np.radians(azimuth_deg)
    x_axis = np.array([np.sin(a), np.cos(a), 0.0])  # east, north components of the azimuth
    z_axis = np.array([0.0, 0.0, 1.0])
    y_axis = np.cross(z_axis, x_axis)  # left of X
    return np.stack([x_axis, y_axis, z_axis], axis=1)
