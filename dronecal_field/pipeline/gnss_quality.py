"""What the run's GNSS quality means for the calibration: a pure function from the reported accuracy to sentences.

A calibration is as good as the positions of its marker points. The
receiver says how good they are (GPS_RAW_INT ``h_acc``/``v_acc``, stored as
each fix's covariance) and what kind of fix it had. Two numbers follow:

* **camera position**: a receiver without RTK errs by about its reported
  accuracy, and that error drifts over minutes (multipath, atmosphere), so it
  does not average out over the holds of one flight: the whole point cloud,
  and with it the camera, may sit ``h_acc`` away. (A simulator's white noise
  does average out, so a simulated flight may do better than this says.)
* **focal length**: the focal is fixed by the angles between points seen
  from the camera. An error ``e`` in a point ``r`` metres away turns its
  direction by ``e / r``; the points span an angle ``spread``; with ``n``
  independent holds the focal's relative error is about
  ``e / (r * spread * sqrt(n))``. ``e`` here is the part of the error that
  differs between holds: for a drifting receiver about half of ``h_acc``
  over a few minutes (the rest moves every point together and so moves the
  camera, not the focal).

Example
-------
>>> q = gnss_quality(["3d"] * 100, h_acc_m=0.9, holds_used=16, median_range_m=10.0)
>>> q.camera_position_m, round(q.focal_pct, 1)
(0.9, 2.2)
>>> print(q.headline)  # doctest: +NORMALIZE_WHITESPACE
GNSS reported 0.9 m (3D fix, no RTK): from the GNSS alone the camera position is known to ~0.9 m and focal to ~2.2 %; fly with RTK for a survey-grade calibration
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass

FIX_NAMES = {"no_fix": "no fix", "2d": "2D fix", "3d": "3D fix", "dgps": "DGPS fix", "rtk_float": "RTK float", "rtk_fixed": "RTK fixed"}
RTK_FIXES = frozenset({"rtk_fixed"})
DRIFTING_SHARE = 0.5  # the part of a non-RTK error that differs between holds a minute apart (the rest is common)
SPREAD_RAD = 0.5  # angle the marker points span from the camera (a plan fills about half of a 60-90 deg view)
SURVEY_GRADE_M = 0.05  # below this reported accuracy the GNSS is not what limits the calibration


@dataclass(frozen=True)
class GnssQuality:
    """The run's GNSS and what it allows.

    Attributes
    ----------
    fix_type : str or None
        The most common fix type of the used fixes (``3d``, ``rtk_fixed``...).
    h_acc_m, v_acc_m : float or None
        Median reported horizontal / vertical accuracy, metres (None = not reported).
    rtk : bool
        RTK fixed.
    camera_position_m : float or None
        How well the GNSS lets the camera position be known, metres.
    focal_pct : float or None
        How well it lets the focal length be known, percent.
    sentences : tuple of str
        The headline, then what to do (empty when GNSS is not the limit).
    """

    fix_type: str | None
    h_acc_m: float | None
    v_acc_m: float | None
    rtk: bool
    camera_position_m: float | None
    focal_pct: float | None
    sentences: tuple[str, ...]

    @property
    def headline(self) -> str:
        return self.sentences[0] if self.sentences else ""

    @property
    def limits_calibration(self) -> bool:
        """The reported accuracy, not the camera, limits the calibration (no RTK, or worse than 5 cm)."""
        return self.h_acc_m is not None and (not self.rtk or self.h_acc_m > SURVEY_GRADE_M)


def gnss_quality(
    fix_types: Sequence[str | None],
    h_acc_m: float | None,
    v_acc_m: float | None = None,
    *,
    holds_used: int,
    median_range_m: float,
    spread_rad: float = SPREAD_RAD,
    focal_std_pct: float | None = None,
) -> GnssQuality:
    """What a run's GNSS means for its calibration.

    Parameters
    ----------
    fix_types : sequence of str or None
        The fix type of each used fix (``report.track.fix_types``).
    h_acc_m, v_acc_m : float or None
        The receiver's reported accuracy (median over the fixes), metres; None
        when it reported none.
    holds_used : int
        Hover windows the calibration used.
    median_range_m : float
        Median distance from the camera to the marker points, metres.
    spread_rad : float
        Angle the points span from the camera, radians.
    focal_std_pct : float or None
        This calibration's own focal standard deviation (its Monte-Carlo),
        percent: said beside the GNSS floor, and the larger is ``focal_pct``
        (a flight whose geometry does not separate focal from distance does
        worse than the GNSS alone allows).

    Returns
    -------
    GnssQuality
    """
    counts = Counter(t for t in fix_types if t)
    fix = counts.most_common(1)[0][0] if counts else None
    rtk = fix in RTK_FIXES
    fix_name = FIX_NAMES.get(fix or "", fix or "unknown fix")
    if h_acc_m is None or not math.isfinite(h_acc_m) or h_acc_m <= 0:
        text = f"GNSS reported no accuracy ({fix_name}): the calibration's own residuals are the only measure of its positions"
        return GnssQuality(fix, None, v_acc_m, rtk, None, None, (text,))
    e = h_acc_m if rtk else h_acc_m * DRIFTING_SHARE  # RTK noise is white over a hold; a drifting receiver's only partly differs between holds
    focal = 100.0 * e / (max(median_range_m, 1.0) * spread_rad * math.sqrt(max(holds_used, 1)))
    position = h_acc_m if not rtk else h_acc_m / math.sqrt(max(holds_used, 1))
    vertical = "" if v_acc_m is None else f" / {_m(v_acc_m)} vertical"
    kind = fix_name if rtk else f"{fix_name}, no RTK"
    flight = ""
    if focal_std_pct is not None and math.isfinite(focal_std_pct):
        flight = f" at best (this flight's Monte-Carlo: ±{_pct(focal_std_pct)} %)"
        focal = max(focal, focal_std_pct)
        floor = 100.0 * e / (max(median_range_m, 1.0) * spread_rad * math.sqrt(max(holds_used, 1)))
    else:
        floor = focal
    head = (f"GNSS reported {_m(h_acc_m)}{vertical} ({kind}): from the GNSS alone the camera position is known to ~{_m(position)} "
            f"and focal to ~{_pct(floor)} %{flight}")  # fmt: skip
    if rtk:
        # no advice: receivers report RTK fixed conservatively (ArduPilot's u-blox driver says 0.3 m whatever the scatter)
        return GnssQuality(fix, h_acc_m, v_acc_m, rtk, position, focal, (head,))
    return GnssQuality(fix, h_acc_m, v_acc_m, rtk, position, focal, (f"{head}; fly with RTK for a survey-grade calibration",))


def _pct(v: float) -> str:
    return f"{v:.0f}" if v >= 10 else f"{v:.2g}"


def _m(v: float) -> str:
    """Centimetres below half a metre (the RTK scale), metres above: an RTK sentence reads in one unit."""
    return f"{v * 100:.2g} cm" if v < 0.5 else f"{v:.2g} m"


def gnss_quality_of_report(report: object) -> GnssQuality:
    """:func:`gnss_quality` for a :class:`~dronecal_field.pipeline.run.CalibrationReport` (its track and used holds)."""
    import numpy as np

    track = report.track  # type: ignore[attr-defined]
    sigma = np.asarray(track.sigma_enu_m, float).reshape(-1, 3)
    h = np.nanmedian(sigma[:, :2]) if np.isfinite(sigma[:, :2]).any() else None
    v = np.nanmedian(sigma[:, 2]) if np.isfinite(sigma[:, 2]).any() else None
    pts = getattr(report, "points", None) or []
    used = [p for p in pts if getattr(p, "used", False)]
    cam = getattr(getattr(report, "result", None), "camera", None)
    ranges = []
    if cam is not None:
        centre = np.asarray(cam.pose.position_world, float)
        ranges = [float(np.linalg.norm(np.asarray(p.marker_enu_m, float) - centre)) for p in used if getattr(p, "marker_enu_m", None) is not None]
    median_range = float(np.median(ranges)) if ranges else 10.0
    mc = getattr(report, "monte_carlo", None) or getattr(report, "linearised", None)
    fx_std = (getattr(mc, "param_std", None) or {}).get("fx") if mc is not None else None
    fx = cam.intrinsics.fx if cam is not None else None
    focal_std = 100.0 * fx_std / fx if fx_std is not None and fx else None
    return gnss_quality(track.fix_types, None if h is None else float(h), None if v is None else float(v),
                        holds_used=len(used), median_range_m=median_range, focal_std_pct=focal_std)  # fmt: skip
