"""``plan --from-run SCOUT.mcap``: the camera estimated from a recorded scout, and the main plan made from it.

The scout run is calibrated by ``calibrate``'s own pipeline (``pipeline.run.calibrate_run``: track, legs,
detections, time alignment, solve, covariance). Its camera is the main plan's guess, and its uncertainty sets
the guess band (``sampling.band``): 3 sigma of the focal length, of the tilt and azimuth (with the principal
point's sigma added as the angle it turns the view), and of the distortion at the image corner, each with a
floor (3 %, 1 deg, 1 deg, 20 %): a scout's sigmas came out optimistic (its few rows say little about the outer band).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dronecal_field.core.camera import Camera, CameraPose, PARAM_NAMES, rotation_from_vector, vector_from_rotation
from dronecal_field.errors import InputError

# a scout's sigmas are optimistic: on the simulated wide camera its focal length came out 2.9 % off at a 0.5 % sigma and its
# tilt 1.3 deg off at 0.4 deg (legs at 3.3 px RMS; benchmarks/bench_scout.py): the band never goes below these
FLOORS = dict(focal_pct=3.0, tilt_deg=1.0, azimuth_deg=1.0, distortion_share=0.20)
K_SIGMA = 3.0
# a principal point the scout cannot place is taken at the image centre; pole cameras keep it within this share of the
# image size of the centre (the band takes it as 3 sigma)
PP_CENTRE_SHARE = 0.05


def _principal_point_known(camera: Camera) -> bool:
    """The principal point inside the middle half of the image and known to PP_CENTRE_SHARE of its size (3 sigma)."""
    i, C = camera.intrinsics, camera.covariance
    if C is None:
        return False
    s_cx = math.sqrt(max(float(C[PARAM_NAMES.index("cx"), PARAM_NAMES.index("cx")]), 0.0))
    s_cy = math.sqrt(max(float(C[PARAM_NAMES.index("cy"), PARAM_NAMES.index("cy")]), 0.0))
    inside = abs(i.cx - i.width / 2.0) < i.width / 4.0 and abs(i.cy - i.height / 2.0) < i.height / 4.0
    return inside and K_SIGMA * s_cx < PP_CENTRE_SHARE * i.width and K_SIGMA * s_cy < PP_CENTRE_SHARE * i.height


def axis_angles_deg(R_cam_from_enu: np.ndarray) -> tuple[float, float]:
    """(azimuth clockwise from north, tilt below the horizon) of the optical axis, deg."""
    f = np.asarray(R_cam_from_enu, float)[2]
    return float(math.degrees(math.atan2(f[0], f[1])) % 360.0), float(math.degrees(math.asin(max(-1.0, min(1.0, -f[2])))))


@dataclass(frozen=True, eq=False)
class CameraEstimate:
    """The scout's camera (ENU at ``origin`` = the report's frame) and its 1-sigma values."""

    camera: Camera
    origin: tuple[float, float, float]  # lat, lon, h of the ENU origin
    azimuth_deg: float
    tilt_deg: float
    sigma: dict  # focal_px, cx_px, cy_px, azimuth_deg, tilt_deg, k1 (1 sigma)
    points: int
    rms_px: float
    model: str

    def tolerances(self) -> dict:
        """The guess band the estimate supports (3 sigma, floors)."""
        f = self.camera.intrinsics.fx
        s = self.sigma
        focal = max(FLOORS["focal_pct"], 100.0 * K_SIGMA * s["focal_px"] / f)
        az = max(FLOORS["azimuth_deg"], K_SIGMA * math.hypot(s["azimuth_deg"], math.degrees(s["cx_px"] / f)))
        tilt = max(FLOORS["tilt_deg"], K_SIGMA * math.hypot(s["tilt_deg"], math.degrees(s["cy_px"] / f)))
        k1 = self.camera.distortion.k1
        share = FLOORS["distortion_share"] if abs(k1) < 1e-6 else max(FLOORS["distortion_share"], K_SIGMA * s["k1"] / abs(k1))
        return {"focal_pct": round(focal, 2), "tilt_deg": round(tilt, 2), "azimuth_deg": round(az, 2), "distortion_share": round(min(share, 1.0), 3)}

    def to_dict(self) -> dict:
        i, d = self.camera.intrinsics, self.camera.distortion
        return {"focal_px": round(i.fx, 2), "cx_px": round(i.cx, 2), "cy_px": round(i.cy, 2), "width": i.width, "height": i.height,
                "distortion_k1_k2_p1_p2_k3": [round(float(v), 6) for v in d.as_array()], "azimuth_deg": round(self.azimuth_deg, 3),
                "tilt_deg": round(self.tilt_deg, 3), "position_enu_m": [round(float(v), 3) for v in self.camera.pose.position_world],
                "sigma": {k: round(float(v), 4) for k, v in self.sigma.items()}, "points": self.points, "rms_px": round(self.rms_px, 3),
                "model": self.model, "tolerances": self.tolerances()}


def _angle_sigmas(camera: Camera) -> tuple[float, float]:
    """1-sigma of azimuth and tilt (deg) from the pose block of the camera's covariance (first order, numeric)."""
    C = camera.covariance
    if C is None:
        return math.nan, math.nan
    idx = [PARAM_NAMES.index(n) for n in ("wx", "wy", "wz")]
    Cw = np.asarray(C, float)[np.ix_(idx, idx)]
    w0 = vector_from_rotation(camera.pose.R_cam_from_world)
    a0 = np.array(axis_angles_deg(camera.pose.R_cam_from_world))
    J = np.zeros((2, 3))
    for k in range(3):
        dw = np.zeros(3)
        dw[k] = 1e-6
        a = np.array(axis_angles_deg(rotation_from_vector(w0 + dw)))
        diff = a - a0
        diff[0] = (diff[0] + 180.0) % 360.0 - 180.0
        J[:, k] = diff / 1e-6
    cov = J @ np.nan_to_num(Cw) @ J.T
    return float(math.sqrt(max(cov[0, 0], 0.0))), float(math.sqrt(max(cov[1, 1], 0.0)))


def _scout_options(trials: int):
    """calibrate's options for a scout: every frame along its legs (calibrate keeps one per 0.25 s; the scout's fast rows
    cross the view in 2-3 s, so that left 27 points of a 2 m pole's scout)."""
    from dronecal_field.pipeline.results import CalibrateOptions
    from dronecal_field.pipeline.sampling import SamplingOptions

    return CalibrateOptions(trials=trials, sampling=SamplingOptions(leg_period_s=0.0))


def estimate_from_run(path: str | Path, trials: int = 0) -> CameraEstimate:
    """Calibrate the scout run with calibrate's pipeline and read the camera and its sigmas."""
    from dronecal_field.pipeline.run import calibrate_run

    path = Path(path)
    if not path.is_file():
        raise InputError(f"--from-run {path} does not exist: give the scout's run file (fly wrote RUN.mcap)")
    report = calibrate_run(path, _scout_options(trials))
    centred = not _principal_point_known(report.camera)
    if centred:
        # the scout's rows left the principal point and the view's direction trading off (a 2 m pole's scout: (-157, -147)
        # px +- 70 for a 1280x960 camera centred at (640, 480)): solve again with it at the image centre, where pole cameras
        # put it within a few % of the image, and let the band carry that (PP_CENTRE_SHARE)
        from dronecal_field.core.calibrate import CalibrationModel

        n = len(report.used_points)
        model = CalibrationModel(distortion="k1" if n >= 30 else "none", fix_principal_point=True)
        report = calibrate_run(path, replace(_scout_options(trials), model=model))
    cam = report.camera
    C = cam.covariance
    sd = {n: (math.sqrt(max(float(C[i, i]), 0.0)) if C is not None else math.nan) for i, n in enumerate(PARAM_NAMES)}
    if centred:  # the centre's own uncertainty, as a sigma
        sd["cx"] = max(sd["cx"], PP_CENTRE_SHARE * cam.width / K_SIGMA)
        sd["cy"] = max(sd["cy"], PP_CENTRE_SHARE * cam.height / K_SIGMA)
    s_az, s_tilt = _angle_sigmas(cam)
    az, tilt = axis_angles_deg(cam.pose.R_cam_from_world)
    o = report.origin
    return CameraEstimate(
        camera=cam, origin=(o.lat_deg, o.lon_deg, o.h_m), azimuth_deg=az, tilt_deg=tilt,
        sigma={"focal_px": sd["fx"], "cx_px": sd["cx"], "cy_px": sd["cy"], "azimuth_deg": s_az, "tilt_deg": s_tilt, "k1": sd["k1"]},
        points=len(report.used_points), rms_px=float(report.result.rms_px), model=str(getattr(report.result.model, "distortion", report.result.model)) + (", principal point at the image centre" if centred else ""))


def request_from_estimate(est: CameraEstimate, opts: dict):
    """The main plan's request: the user's options (marker, limits, sampling...) with the pole, pose and lens of the estimate,
    the estimated camera itself as the guess, and the band its uncertainty supports."""
    from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic
    from dronecal_field.plan.stage import request_from_options
    from dronecal_field.sampling.band import GuessBand, scaled_distortion

    cam = est.camera
    p = cam.pose.position_world
    foot = enu_to_geodetic(np.array([[p[0], p[1], 0.0]]), EnuOrigin(*est.origin))[0]
    tol = est.tolerances()
    filled = dict(opts)
    filled.update(lat=float(foot[0]), lon=float(foot[1]), ground_alt=float(foot[2]), ground_amsl=None, mount_height=float(p[2]),
                  azimuth=est.azimuth_deg, tilt=est.tilt_deg, image_size=(cam.width, cam.height), focal_px=cam.intrinsics.fx,
                  focal_mm=None, hfov=None, distortion="none")
    if filled.get("geoid_separation") is None:
        filled["geoid_separation"] = None
    req = request_from_options(filled)
    # the estimated camera, moved to the new origin (the pole's foot under it; a few cm: same axes)
    cam_enu = cam.with_(pose=CameraPose.from_position(cam.pose.R_cam_from_world, np.array([0.0, 0.0, p[2]])),
                        enu_origin=(float(foot[0]), float(foot[1]), float(foot[2])), covariance=None)
    share = tol["distortion_share"]
    band = GuessBand(focal_tolerance=tol["focal_pct"] / 100.0, tilt_tolerance_deg=tol["tilt_deg"], azimuth_tolerance_deg=tol["azimuth_deg"],
                     distortions=(scaled_distortion(cam.distortion, 1.0 - share), scaled_distortion(cam.distortion, 1.0 + share)),
                     distortion_names=(f"{1 - share:.2f}x estimate", f"{1 + share:.2f}x estimate"))
    return replace(req, camera_enu=cam_enu, band=band)


def format_estimate(est: CameraEstimate, truth: Camera | None = None) -> str:
    """Two lines: the estimate with its sigmas, and the band it supports."""
    i, s, t = est.camera.intrinsics, est.sigma, est.tolerances()
    return "\n".join([
        f"scout estimate ({est.points} points, {est.rms_px:.2f} px RMS, model {est.model}): f {i.fx:.1f} +- {s['focal_px']:.1f} px, "
        f"principal point ({i.cx:.1f}, {i.cy:.1f}) +- ({s['cx_px']:.1f}, {s['cy_px']:.1f}) px, k1 {est.camera.distortion.k1:.3f} +- {s['k1']:.3f}, "
        f"azimuth {est.azimuth_deg:.2f} +- {s['azimuth_deg']:.2f} deg, tilt {est.tilt_deg:.2f} +- {s['tilt_deg']:.2f} deg",
        f"main plan's guess band from it: focal +-{t['focal_pct']:g} %, tilt +-{t['tilt_deg']:g} deg, azimuth +-{t['azimuth_deg']:g} deg, "
        f"distortion {1 - t['distortion_share']:.2f}-{1 + t['distortion_share']:.2f}x the estimate",
    ])
