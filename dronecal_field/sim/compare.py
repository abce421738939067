"""How far an estimated camera is from the simulator's truth, where users measure.

Pure numerics, no I/O. Both cameras must be in the same world frame (ENU at
the pole's foot: put the estimate there with ``demo.in_enu_frame_of``), the
ground being the plane z = 0. Three regions are compared:

* **ground**: a dense regular grid of ground points (z = 0) 3-30 m from the
  pole that the truth camera sees (in front, inside the image, and before its
  distortion model folds: beyond the fold the polynomial sends far rays back
  into the image, which no real lens does);
* **sampled**: points inside the convex hull of the flown marker positions,
  the only region a calibration is measured on;
* **image**: rays through the whole image at 4-12 m (the demo's figure).

Besides pixels, the ground error in centimetres: the truth pixel of each
ground point back-projected through the estimate onto z = 0, its distance to
the point, which is what a speed or position measurement would be off by.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecal_field.core.camera import Camera, intersect_plane_z, pixel_rays_batch
from dronecal_field.errors import InputError
from dronecal_field.pipeline.validity import ground_ring
from dronecal_field.sampling.lattice import fold_radius as lattice_fold_radius

GROUND_RANGES_M: tuple[float, ...] = (5.0, 15.0, 30.0)


@dataclass(frozen=True)
class ErrorStats:
    """Pixel distances between the truth's and the estimate's projections of one set of points."""

    rms_px: float
    p95_px: float
    max_px: float
    n_points: int


@dataclass(frozen=True)
class CameraComparison:
    """An estimated camera against the truth (see the module docstring for the regions).

    ``ground_error_cm_at`` maps a range from the pole (m) to the RMS ground
    error (cm) of the grid points within ``ring_half_width_m`` of it (None when
    the truth sees none there). ``ground_misses`` counts ground points whose
    truth pixel the estimate's ray does not bring down to the ground (above its
    horizon, or its distortion not invertible there); they are left out of the
    centimetre figures and counted here instead.
    """

    focal_error_pct: float
    focal_error_px: float
    principal_point_error_px: float
    position_error_cm: float
    rotation_error_deg: float
    ground: ErrorStats
    sampled: ErrorStats | None
    image: ErrorStats
    ground_error_cm_rms: float
    ground_error_cm_max: float
    ground_error_cm_at: dict[float, float | None]
    ground_misses: int
    ground_step_m: float
    ground_range_m: tuple[float, float]


def error_stats(truth: Camera, est: Camera, points: np.ndarray) -> ErrorStats:
    """RMS, 95th percentile and maximum of |truth(X) - est(X)| in pixels over ``points`` (N, 3), world metres."""
    points = np.asarray(points, float).reshape(-1, 3)
    if len(points) == 0:
        raise InputError("no points to compare the cameras on: widen the region or check that the truth camera sees it")
    d = np.linalg.norm(truth.project(points) - est.project(points), axis=1)
    return ErrorStats(rms_px=float(np.sqrt(np.mean(d**2))), p95_px=float(np.percentile(d, 95)), max_px=float(d.max()), n_points=int(len(d)))


def fold_radius(camera: Camera) -> float:
    """Undistorted normalised radius where the radial distortion stops growing (inf if it never does).

    Beyond it r_d = r (1 + k1 r^2 + k2 r^4 + k3 r^6) decreases again, so two
    rays share one pixel and the model is meaningless there
    (``sampling.lattice.fold_radius``, the one definition).
    """
    return lattice_fold_radius(camera.distortion.as_array())


def _in_view(camera: Camera, points: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
    """(N,) mask: in front, undistorted radius inside the fold, and projected inside the image."""
    R, t = camera.pose.R_cam_from_world, camera.pose.t_cam_from_world
    Xc = points @ R.T + t
    front = Xc[:, 2] > 0.1
    z = np.where(front, Xc[:, 2], 1.0)
    r = np.hypot(Xc[:, 0] / z, Xc[:, 1] / z)
    uv = camera.project(points)
    w, h = camera.width, camera.height
    inside = (uv[:, 0] >= margin_px) & (uv[:, 0] <= w - 1 - margin_px) & (uv[:, 1] >= margin_px) & (uv[:, 1] <= h - 1 - margin_px)
    return front & (r < fold_radius(camera)) & inside


def visible_ground_grid(
    truth: Camera, range_m: tuple[float, float] = (3.0, 30.0), step_m: float = 0.25
) -> tuple[np.ndarray, np.ndarray]:
    """Ground points (z = 0) on a regular ``step_m`` grid that the truth camera sees, ``range_m`` from the pole.

    The pole stands under the camera centre; range is the horizontal distance
    from it.

    Returns
    -------
    points : (N, 3) world metres, z = 0
    ranges : (N,) horizontal distance from the pole, metres
    """
    lo, hi = range_m
    if not 0.0 <= lo < hi or not step_m > 0:
        raise InputError(f"ground range {range_m} m / step {step_m} m: give 0 <= MIN < MAX and a positive step")
    pts, ranges = ground_ring(truth.pose.position_world[:2], (lo, hi), step_m)
    seen = _in_view(truth, pts)
    return pts[seen], ranges[seen]


def points_in_hull(hull_points: np.ndarray, n: int = 4000, seed: int = 0) -> np.ndarray:
    """Uniform random points (M, 3) inside the convex hull of ``hull_points`` (N, 3), metres; M <= n.

    A flat or too small set (no volume) returns the points themselves.
    """
    from scipy.spatial import Delaunay
    from scipy.spatial import QhullError

    hull_points = np.asarray(hull_points, float).reshape(-1, 3)
    if len(hull_points) < 4:
        return hull_points
    try:
        tri = Delaunay(hull_points)
    except QhullError:
        return hull_points
    rng = np.random.default_rng(seed)
    lo, hi = hull_points.min(axis=0), hull_points.max(axis=0)
    cand = rng.uniform(lo, hi, (n, 3))
    return cand[tri.find_simplex(cand) >= 0]


def image_volume_points(truth: Camera, depth_m: tuple[float, float] = (4.0, 12.0), n: int = 4000, seed: int = 0) -> np.ndarray:
    """(M, 3) points along rays through uniform random pixels of the whole image, depth (camera z) in ``depth_m``.

    Rays come from the truth's own distortion (undistorted by Newton's method);
    pixels whose undistortion does not come back to them (beyond the fold) and
    points under the ground are dropped.
    """
    rng = np.random.default_rng(seed)
    uv = rng.uniform([0.0, 0.0], [truth.width - 1.0, truth.height - 1.0], (n, 2))
    K, D, R, _ = truth.batch_arrays()
    rays = pixel_rays_batch(K, D, R, uv[None])[0]  # (n, 3) unit, world
    cam_z = rays @ R[0][2]
    depth = rng.uniform(depth_m[0], depth_m[1], n)
    pts = truth.pose.position_world + rays * (depth / cam_z)[:, None]
    ok = (cam_z > 0) & (pts[:, 2] > 0.0) & _in_view(truth, pts)
    ok &= np.linalg.norm(truth.project(pts) - uv, axis=1) < 0.01
    return pts[ok]


def ground_error_m(truth: Camera, est: Camera, ground_points: np.ndarray) -> np.ndarray:
    """(N,) metres between each ground point and where the estimate puts its truth pixel on z = 0 (NaN: a miss).

    A miss is a pixel whose estimated ray does not go down to the ground, or
    whose undistortion through the estimate does not return to the pixel.
    """
    uv = truth.project(ground_points)
    K, D, R, t = est.batch_arrays()
    hit = intersect_plane_z(K, D, R, t, uv[None], 0.0)[0]
    err = np.linalg.norm(hit[:, :2] - ground_points[:, :2], axis=1)
    ok = np.isfinite(err)
    back = np.full_like(uv, np.nan)
    back[ok] = est.project(hit[ok])
    ok &= np.linalg.norm(back - uv, axis=1) < 0.01
    return np.where(ok, err, np.nan)


def rotation_error_deg(truth: Camera, est: Camera) -> float:
    """Angle of the rotation between the two cameras' orientations, degrees."""
    from dronecal_field.core.camera import vector_from_rotation

    # Not arccos of the trace: it loses half the digits near zero.
    dR = est.pose.R_cam_from_world @ truth.pose.R_cam_from_world.T
    return float(np.degrees(np.linalg.norm(vector_from_rotation(dR))))


def compare_cameras(
    truth: Camera,
    est: Camera,
    sampled_enu_m: np.ndarray | None = None,
    ground_range_m: tuple[float, float] = (3.0, 30.0),
    ground_step_m: float = 0.25,
    ring_half_width_m: float = 0.5,
    seed: int = 0,
) -> CameraComparison:
    """Compare an estimated camera with the truth over the ground, the sampled volume and the image.

    Parameters
    ----------
    truth, est : cameras in one world frame (ENU at the pole's foot, ground z = 0).
    sampled_enu_m : (N, 3) metres, the marker positions used by the calibration
        (their convex hull is the sampled volume); None skips that region.
    ground_range_m : (min, max) horizontal distance from the pole of the ground grid, metres.
    ground_step_m : ground grid spacing, metres.
    ring_half_width_m : half width of the rings for ``ground_error_cm_at``, metres.
    seed : seed of the random points of the sampled volume and the image.

    Returns
    -------
    CameraComparison
    """
    ti, ei = truth.intrinsics, est.intrinsics
    f_true, f_est = 0.5 * (ti.fx + ti.fy), 0.5 * (ei.fx + ei.fy)
    ground, ranges = visible_ground_grid(truth, ground_range_m, ground_step_m)
    if len(ground) == 0:
        raise InputError(f"the truth camera sees no ground {ground_range_m[0]:g}-{ground_range_m[1]:g} m from the pole: check its tilt and height")
    err_m = ground_error_m(truth, est, ground)
    hits = np.isfinite(err_m)
    at: dict[float, float | None] = {}
    for r in GROUND_RANGES_M:
        ring = hits & (np.abs(ranges - r) <= ring_half_width_m)
        at[r] = float(100.0 * np.sqrt(np.mean(err_m[ring] ** 2))) if ring.any() else None
    sampled = None
    if sampled_enu_m is not None and len(sampled_enu_m):
        inside = points_in_hull(sampled_enu_m, seed=seed)
        inside = inside[_in_view(truth, inside)]
        sampled = error_stats(truth, est, inside) if len(inside) else None
    return CameraComparison(
        focal_error_pct=100.0 * abs(f_est - f_true) / f_true,
        focal_error_px=abs(f_est - f_true),
        principal_point_error_px=float(np.hypot(ei.cx - ti.cx, ei.cy - ti.cy)),
        position_error_cm=100.0 * float(np.linalg.norm(est.pose.position_world - truth.pose.position_world)),
        rotation_error_deg=rotation_error_deg(truth, est),
        ground=error_stats(truth, est, ground),
        sampled=sampled,
        image=error_stats(truth, est, image_volume_points(truth, seed=seed)),
        ground_error_cm_rms=float(100.0 * np.sqrt(np.mean(err_m[hits] ** 2))) if hits.any() else float("nan"),
        ground_error_cm_max=float(100.0 * err_m[hits].max()) if hits.any() else float("nan"),
        ground_error_cm_at=at,
        ground_misses=int((~hits).sum()),
        ground_step_m=float(ground_step_m),
        ground_range_m=(float(ground_range_m[0]), float(ground_range_m[1])),
    )
