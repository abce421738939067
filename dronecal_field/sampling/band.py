"""The guess band: the cameras ``plan`` may really be facing, and which planned markers each one sees.

``plan`` starts from a guess (a datasheet focal length, a tilt from the
installer, a compass azimuth, a distortion level). A target planned on the
guessed image's edge is off the real image when the focal length is 5 %
longer (the demo's camera: 14 of 60 waypoints never seen). The band states
how wrong the guess may be; its *corner cameras* (focal +-, tilt +-, azimuth
+-, distortion from the low to the high level) are the extremes of what the
pole may hold, and a point is kept only if the whole marker, with its quiet
zone, is in the image of every one of them (``lattice.screen_points`` ANDs
them through ``Limits.band``).

Pure functions on cameras in one world frame (the site frame in ``plan``).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, replace

import numpy as np

from dronecal_field.core.camera import Camera, Distortion, rotation_from_vector


@dataclass(frozen=True)
class GuessBand:
    """How far the guessed camera may be from the real one.

    ``focal_tolerance`` a fraction (0.10 = +-10 %), ``tilt_tolerance_deg`` and
    ``azimuth_tolerance_deg`` degrees either way, ``distortions`` the lowest and
    highest distortion the lens may have (e.g. none and the guessed level).
    """

    focal_tolerance: float = 0.10
    tilt_tolerance_deg: float = 1.0
    azimuth_tolerance_deg: float = 2.0
    distortions: tuple[Distortion, ...] = (Distortion(),)
    distortion_names: tuple[str, ...] = ("none",)

    @property
    def is_empty(self) -> bool:
        return self.focal_tolerance == 0 and self.tilt_tolerance_deg == 0 and self.azimuth_tolerance_deg == 0 and not self.distortions

    def describe(self) -> str:
        """e.g. 'focal +-10 %, tilt +-1 deg, azimuth +-2 deg, distortion none..medium'."""
        dist = "..".join(self.distortion_names) if self.distortion_names else "as guessed"
        return (f"focal +-{100 * self.focal_tolerance:g} %, tilt +-{self.tilt_tolerance_deg:g} deg, "
                f"azimuth +-{self.azimuth_tolerance_deg:g} deg, distortion {dist}")

    def to_dict(self) -> dict:
        return {"focal_tolerance_pct": 100 * self.focal_tolerance, "tilt_tolerance_deg": self.tilt_tolerance_deg,
                "azimuth_tolerance_deg": self.azimuth_tolerance_deg, "distortion": list(self.distortion_names)}


def turned(camera: Camera, tilt_deg: float = 0.0, azimuth_deg: float = 0.0) -> Camera:
    """``camera`` tilted further down by ``tilt_deg`` (about its x axis) and turned ``azimuth_deg`` clockwise
    seen from above (about the world's vertical, Z up), about its own centre."""
    R = np.asarray(camera.pose.R_cam_from_world, float)
    c = camera.pose.position_world
    # camera x right, y down, z forward: a positive turn about x moves the axis towards +y, i.e. down
    R_tilt = rotation_from_vector(np.array([math.radians(tilt_deg), 0.0, 0.0]))
    # a clockwise (seen from above) turn of the camera is the world turned anticlockwise under it
    R_az = rotation_from_vector(np.array([0.0, 0.0, math.radians(azimuth_deg)]))
    R_new = R_tilt @ R @ R_az
    pose = type(camera.pose).from_position(R_new, c)
    return camera.with_(pose=pose)


def corner_cameras(camera: Camera, band: GuessBand, narrow_only: bool = False) -> tuple[Camera, ...]:
    """The band's corner cameras around ``camera`` (the guess): focal x (1 +- tol), tilt +- tol, azimuth +- tol,
    each distortion of ``band.distortions`` (the guess's own distortion when none is given).

    Up to 2 x 2 x 2 x len(distortions) cameras; a zero tolerance gives one value for that factor.
    ``narrow_only``: only the corners that see least (the longest focal length and the weakest
    distortion, every tilt and azimuth): a shorter focal length or a stronger barrel sees a wider
    field round the same axis, so a marker these see is seen by every corner.
    """
    fs = sorted({1.0 - band.focal_tolerance, 1.0 + band.focal_tolerance})
    ts = sorted({-band.tilt_tolerance_deg, band.tilt_tolerance_deg})
    az = sorted({-band.azimuth_tolerance_deg, band.azimuth_tolerance_deg})
    dists = band.distortions or (camera.distortion,)
    if narrow_only:
        fs = fs[-1:]
        dists = (max(dists, key=lambda d: _radial_factor(camera, d)),)
    out = []
    for f, t, a, d in itertools.product(fs, ts, az, dists):
        intr = replace(camera.intrinsics, fx=camera.intrinsics.fx * f, fy=camera.intrinsics.fy * f)
        out.append(turned(camera, t, a).with_(intrinsics=intr, distortion=d))
    return tuple(out)


def screen_cameras(camera: Camera, band: GuessBand) -> tuple[Camera, ...]:
    """The cameras every point ``plan`` keeps must see whole: each factor of the band at its full tolerance *alone*
    (focal x (1 + tol) with the guessed lens, tilt -+, azimuth -+, the weakest distortion of the band).

    A point lost only where two or more factors are at their extremes together (an *extreme corner* of the band: the
    focal length 10 % long AND the weakest lens AND the tilt and azimuth off) is kept: screening by those corners took
    the outer third of the image from a demo plan (66 % of the image left to sample, its ground error 5.0 px predicted
    against 2.2 px without a band). ``band_report`` names the kept points an extreme corner may lose and what losing
    them costs.
    """
    out = []
    if band.focal_tolerance > 0:
        intr = replace(camera.intrinsics, fx=camera.intrinsics.fx * (1.0 + band.focal_tolerance), fy=camera.intrinsics.fy * (1.0 + band.focal_tolerance))
        out.append(camera.with_(intrinsics=intr))
    for t in sorted({-band.tilt_tolerance_deg, band.tilt_tolerance_deg} - {0.0}):
        out.append(turned(camera, t, 0.0))
    for a in sorted({-band.azimuth_tolerance_deg, band.azimuth_tolerance_deg} - {0.0}):
        out.append(turned(camera, 0.0, a))
    if band.distortions:
        weakest = max(band.distortions, key=lambda d: _radial_factor(camera, d))
        if not np.allclose(weakest.as_array(), camera.distortion.as_array()):
            out.append(camera.with_(distortion=weakest))
    return tuple(out)


def _radial_factor(camera: Camera, d: Distortion) -> float:
    """r_distorted / r of the ray that the guess sees at its image corner, under distortion ``d``: the larger,
    the further out that ray lands and the less of the scene the lens shows."""
    r = math.hypot(camera.width / 2.0, camera.height / 2.0) / camera.intrinsics.fx
    x = r * r
    return 1.0 + d.k1 * x + d.k2 * x * x + d.k3 * x ** 3


def scaled_distortion(d: Distortion, scale: float) -> Distortion:
    """Every coefficient of ``d`` times ``scale`` (0: no distortion)."""
    return Distortion.from_array(np.asarray(d.as_array(), float) * float(scale))


def quiet_zone_fraction(dictionary: str) -> float:
    """The quiet zone (one white cell each side) as a fraction of the marker side, for an ArUco dictionary.

    A DICT_4X4 marker is 4 data cells plus a black border cell each side: 6 cells, so its quiet
    zone adds 1/6 of the side on each side. ARUCO_ORIGINAL markers are 5x5 (7 cells).
    """
    name = dictionary.upper()
    for n in (4, 5, 6, 7):
        if f"_{n}X{n}" in name:
            return 1.0 / (n + 2)
    return 1.0 / 7.0


def markers_in_view(camera: Camera, marker_site: np.ndarray, limits) -> np.ndarray:
    """(N,) bool: the whole marker (with ``limits``' quiet zone and margin) at each (N, 3) centre is in ``camera``'s image.

    The count a truth camera gives a plan: ``markers_in_view(truth, plan_markers, limits).sum()``.
    ``limits.band`` is ignored: this is one camera's view.
    """
    from dronecal_field.sampling.lattice import screen_points

    pts = np.atleast_2d(np.asarray(marker_site, float))
    if len(pts) == 0:
        return np.zeros(0, bool)
    return screen_points(camera, pts, replace(limits, band=()))["in_view"]


def band_report(camera: Camera, band: GuessBand, marker_site: np.ndarray, limits) -> dict:
    """What the band costs and guarantees, JSON-ready.

    ``holds_in_view_of_all``: the planned markers (N, 3) every corner camera sees whole (with the quiet zone);
    ``lost_by_corner``: per corner camera, how many it would not see (0 everywhere for a band-screened plan);
    ``image_share_pct``: the share of the guess's image (a 64 x 36 lattice of pixel rays at 10 m) that every
    corner camera still sees: the rest is the outer ring no planned marker may use, where the calibration
    extrapolates the lens unless the real camera turns out wider.
    """
    from dronecal_field.core.camera import pixel_rays_batch

    cams = corner_cameras(camera, band)
    lim = replace(limits, band=())
    seen = np.ones(len(marker_site), bool)
    lost = []
    for cam in cams:
        v = markers_in_view(cam, marker_site, lim)
        lost.append(int((~v).sum()))
        seen &= v
    u = (np.arange(64) + 0.5) / 64 * camera.width
    w = (np.arange(36) + 0.5) / 36 * camera.height
    uv = np.stack(np.meshgrid(u, w), -1).reshape(-1, 2)
    K, D, R, _ = camera.batch_arrays()
    pts = camera.pose.position_world + 10.0 * pixel_rays_batch(K, D, R, uv[None])[0]
    inside = np.ones(len(uv), bool)
    for cam in cams:
        p = cam.project(pts)
        inside &= (p[:, 0] >= 0) & (p[:, 0] <= cam.width - 1) & (p[:, 1] >= 0) & (p[:, 1] <= cam.height - 1)
    return {**band.to_dict(), "corner_cameras": len(cams), "holds": int(len(marker_site)),
            "holds_in_view_of_all": int(seen.sum()), "lost_by_corner": lost,
            "may_be_lost": [int(i) for i in np.flatnonzero(~seen)],
            "screened_by": "the guess and each factor at its full tolerance alone (sampling.band.screen_cameras); a point in "
                           "may_be_lost is out of view only where factors are at their extremes together",
            "image_share_pct": round(100.0 * float(inside.mean()), 1), "text": band.describe()}


def band_cost(camera: Camera, band: GuessBand, samples_site: np.ndarray, limits, predict) -> dict | None:
    """What the points an extreme corner of the band may lose cost: the predicted ROI error with every sample and with
    only the samples all corner cameras see whole (JSON-ready, with a one-line ``text``); None when every corner sees all.

    ``samples_site`` (S, 3): the plan's samples (holds and fixes along legs), site frame; ``predict(keep)`` the
    predicted ``combined_px`` RMS (px over the ROI) of the samples where the (S,) bool ``keep`` is True.
    """
    samples_site = np.atleast_2d(np.asarray(samples_site, float))
    lim = replace(limits, band=())
    seen = np.ones(len(samples_site), bool)
    for cam in corner_cameras(camera, band):
        seen &= markers_in_view(cam, samples_site, lim)
    if seen.all() or len(samples_site) == 0:
        return None
    with_all = float(predict(np.ones(len(samples_site), bool)))
    without = float(predict(seen)) if seen.sum() >= 12 else math.inf
    text = (f"{int((~seen).sum())} of {len(samples_site)} samples are out of view for an extreme corner of the guess band "
            f"({band.describe()}): predicted ROI error {with_all:.2f} px RMS with them, "
            + (f"{without:.2f} px if they are lost" if math.isfinite(without) else "too few left to calibrate if they are lost"))
    return {"samples": int(len(samples_site)), "may_be_lost": int((~seen).sum()), "predicted_px_with": round(with_all, 3),
            "predicted_px_without": None if not math.isfinite(without) else round(without, 3), "text": text}
