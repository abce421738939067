"""Where a calibration can be trusted: the region of validity, its predicted error, degenerate geometry.

A camera fitted to points that fill a third of the image is exact there and
can be tens of pixels wrong at the edges, while its linearised uncertainty
stays tight: a lean model's covariance only describes the directions that
model can move in (mrcal's lesson). So the predicted error at a pixel is two
terms, root-sum-square:

- the linearised projection std of the chosen model under the measured
  per-point sigmas (``core.uncertainty.parameter_covariance``), times
  1.645 so the prediction bounds 90 % of the errors;
- the *model-extrapolation term*: how far the next richer model, fitted to
  the same points, projects the same ground point. Inside the data both
  models agree to the noise; where the data stop the richer model is free
  to bend and the two part ways.

The region of validity is the convex hull of the used points' pixels grown,
direction by direction, for as long as that predicted error stays under a
threshold (1 px, or twice its RMS inside the hull when the data are noisier);
its ground footprint is where that region meets the plane z = 0.

Pure numerical core on ``core.camera``: no I/O, no printing. Frames and
pixel conventions: docs/conventions.md (world = ENU at the pole's foot).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dronecal_field.core.calibrate import BatchState, CalibrationResult, richer_model  # noqa: F401 - richer_model is part of this module's API
from dronecal_field.core.camera import Camera, intersect_plane_z, pixel_rays_batch, project_batch
from dronecal_field.errors import DronecalError
from dronecal_field.sampling.lattice import fold_radius

THRESHOLD_PX = 1.0
HULL_FACTOR = 2.0  # the linearised std may reach twice its RMS inside the hull
# The richer model is fitted to the same limited points, so beyond them it
# is itself about as far from the truth as from the chosen model: the term
# counts twice. Measured on the wide 1080p camera (k1 chosen, k1k2 richer,
# 8 seeds, tests/test_validity.py): with the term once, the predicted error
# outside the region covered the true error at 74-100 % of the ground
# pixels 3-30 m (one seed's k2 was 1.2 std off); twice, at 98-100 %.
EXTRAPOLATION_FACTOR = 2.0
# The predicted error is a bound, not a 1-sigma figure: 1.645 times the RMS
# (over both axes) std holds at least 90 % of a Gaussian error in 2D (90 %
# when all the variance is along one axis, 93 % when it is even). Measured
# on a Table 1 flight through sim vehicle + sim camera: just outside the
# region, where the std dominates, 1 std covered the true error at 73 % of
# the ground pixels, 1.645 std at 92 %.
BOUND_FACTOR = 1.645
PROBE_DISTANCE_M = 15.0  # where a ray misses the ground, its point this far out stands in
MAX_GROUND_RANGE_M = 200.0
VISIBLE_GROUND_M = (3.0, 30.0)  # the ground a pole camera is used on
GROUND_STEP_M = 0.25
MIN_GROUND_FRACTION = 0.95  # below this share of the visible ground (or ROI) inside the region: a warning
DIRECTIONS = 96
RADIAL_STEPS = 48

# --------------------------------------------------------------------------
# The predicted error at pixels


@dataclass(frozen=True, eq=False)
class PixelErrors:
    """Predicted errors at M pixels of the calibrated camera.

    ``ground_enu_m`` (M, 3): the ground point (z = ``ground_z``) each pixel
    sees, NaN where the ray misses the ground ahead or lands beyond 200 m
    (the sky). ``std_px`` (M,): linearised RMS (sqrt of the trace) of where
    the pixel's probe point (the ground point, else 15 m along the ray)
    projects; ``extrapolation_px`` (M,): the distance between its projections
    by the chosen and the richer model (0 without a richer model).
    ``std_cm``, ``extrapolation_cm`` (M,): the same on the ground,
    horizontal, cm (NaN in the sky). ``has_ray`` (M,): False where the
    distortion model folds and the pixel is no direction's image; the pixel
    errors are infinite there.
    """

    uv_px: np.ndarray
    ground_enu_m: np.ndarray
    std_px: np.ndarray
    extrapolation_px: np.ndarray
    std_cm: np.ndarray
    extrapolation_cm: np.ndarray
    has_ray: np.ndarray

    @property
    def total_px(self) -> np.ndarray:
        """(M,) predicted projection error, px: a 90 % bound (see BOUND_FACTOR) root-sum-square with the extrapolation term."""
        return np.hypot(BOUND_FACTOR * self.std_px, self.extrapolation_px)

    @property
    def total_cm(self) -> np.ndarray:
        """(M,) predicted ground position error, cm, likewise (NaN in the sky)."""
        return np.hypot(BOUND_FACTOR * self.std_cm, self.extrapolation_cm)

    @property
    def on_ground(self) -> np.ndarray:
        return np.all(np.isfinite(self.ground_enu_m), axis=1)


def fit_richer(result: CalibrationResult, loss_scale_px: float = 2.0) -> CalibrationResult | None:
    """The next richer model fitted to ``result``'s own points, from its camera; None when it cannot be fitted.

    Too few points for the richer model, or a solve that fails, leave the
    extrapolation term at 0: the region is then the hull alone (see
    :func:`assess_validity`).
    """
    from dronecal_field.core.calibrate import calibrate

    richer = richer_model(result.model)
    if richer is None:
        return None
    try:
        return calibrate(
            result.points_world, result.pixels, result.camera.width, result.camera.height,
            model=richer, loss=result.loss, loss_scale_px=loss_scale_px, initial=result.camera,
        )
    except DronecalError:
        return None


def _probe_points(camera: Camera, uv: np.ndarray, ground_z: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground points (M, 3) (NaN in the sky), probe points (M, 3) and the has-a-ray mask (M,) of pixels uv (M, 2).

    A pixel has no ray when the distortion model cannot be inverted there:
    a radial model with k1 < 0 folds back at r^2 = -1/(3 k1), and pixels
    beyond that radius are not the image of any direction under it.
    """
    arrays = camera.batch_arrays()
    centre = camera.pose.position_world
    rays = pixel_rays_batch(arrays[0], arrays[1], arrays[2], uv[None])[0]
    probe = centre + PROBE_DISTANCE_M * rays
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        back = project_batch(*arrays, probe[None])[0]
        d_cam = rays @ camera.pose.R_cam_from_world.T
        r_undistorted = np.hypot(d_cam[:, 0], d_cam[:, 1]) / d_cam[:, 2]
        # Newton can also land on the far side of the fold, where the model
        # maps back into the image: that is no ray either (one fold for plan,
        # the survey and here: sampling.lattice.fold_radius).
        has_ray = (
            (np.linalg.norm(back - uv, axis=1) < 0.05)
            & (d_cam[:, 2] > 0)
            & (r_undistorted < fold_radius(camera.distortion.as_array()))
        )
    ground = intersect_plane_z(*arrays, uv[None], ground_z)[0]
    reach = np.linalg.norm(ground[:, :2] - centre[:2], axis=1)
    on_ground = has_ray & np.all(np.isfinite(ground), axis=1) & (reach < MAX_GROUND_RANGE_M)
    ground[~on_ground] = np.nan
    probe = np.where(on_ground[:, None], ground, probe)
    return ground, probe, has_ray


def _covariance_steps(covariance: np.ndarray) -> np.ndarray:
    """(r, 15) one-sigma steps along the covariance's principal axes (rank r)."""
    cov = 0.5 * (np.asarray(covariance, float) + np.asarray(covariance, float).T)
    w, V = np.linalg.eigh(cov)
    keep = w > max(float(w.max(initial=0.0)), 0.0) * 1e-14
    return (V[:, keep] * np.sqrt(w[keep])).T


def _linear_std(camera: Camera, covariance: np.ndarray, uv: np.ndarray, probe: np.ndarray, on_ground: np.ndarray, ground_z: float, step: float) -> tuple[np.ndarray, np.ndarray]:
    """(M,) linearised projection std of the probes, px, and ground std of the pixels' rays, m (NaN off the ground)."""
    S = _covariance_steps(covariance)
    std_px = np.zeros(len(uv))
    std_m = np.where(on_ground, 0.0, np.nan)
    if not len(S):
        return std_px, std_m
    r = len(S)
    state = BatchState.from_camera(camera, 2 * r).stepped(np.concatenate([step * S, -step * S]))
    args = (state.intrinsics, state.distortion, state.R, state.t)
    q = project_batch(*args, probe[None])  # (2r, M, 2)
    d = (q[:r] - q[r:]) / (2.0 * step)
    std_px = np.sqrt(np.sum(d**2, axis=(0, 2)))
    hits = intersect_plane_z(*args, uv[None], ground_z)[..., :2]  # (2r, M, 2)
    dg = (hits[:r] - hits[r:]) / (2.0 * step)
    # A stepped ray that misses the ground (near the horizon) leaves the std unbounded, not small.
    std_m = np.sqrt(np.sum(np.where(np.isfinite(dg), dg**2, np.inf), axis=(0, 2)))
    std_m[~on_ground] = np.nan
    return std_px, std_m


def pixel_errors(
    camera: Camera,
    covariance: np.ndarray,
    uv_px: np.ndarray,
    richer: Camera | None = None,
    richer_covariance: np.ndarray | None = None,
    ground_z: float = 0.0,
    step: float = 1e-2,
) -> PixelErrors:
    """Linearised std and model-extrapolation term at pixels; see PixelErrors.

    Parameters
    ----------
    camera : the calibrated camera (world = ENU)
    covariance : (15, 15) parameter covariance over core.camera.PARAM_NAMES (measured sigmas)
    uv_px : (M, 2) pixels
    richer : the next richer model fitted to the same points (``fit_richer``), or None
    richer_covariance : (15, 15) its covariance under the same sigmas, or None
    step : central-difference step along each principal axis, in standard deviations

    The std is propagated to first order along the covariance's principal
    axes (central differences; the rotation is a left perturbation, as in
    the covariance), so it is smooth over the image, unlike a sampled map.
    The extrapolation term is the distance between the two models'
    projections, root-sum-square with the std the richer model has beyond
    the chosen one's: its extra terms are poorly pinned exactly where the
    data stop, and the chosen model's covariance cannot say so.
    """
    uv = np.asarray(uv_px, float).reshape(-1, 2)
    ground, probe, has_ray = _probe_points(camera, uv, ground_z)
    on_ground = np.all(np.isfinite(ground), axis=1)
    std_px, std_m = _linear_std(camera, covariance, uv, probe, on_ground, ground_z, step)
    std_px[~has_ray] = np.inf  # the model does not say where this pixel looks: no bound at all
    extra_px = np.zeros(len(uv))
    extra_m = np.where(on_ground, 0.0, np.nan)
    if richer is not None:
        extra_px = np.linalg.norm(richer.project(probe) - uv, axis=1)
        g_r = intersect_plane_z(*richer.batch_arrays(), uv[None], ground_z)[0]
        extra_m = np.linalg.norm(g_r[:, :2] - ground[:, :2], axis=1)
        # The richer ray missing the ground where the chosen one hits is the
        # most the two can disagree: unbounded, not small.
        extra_m = np.where(on_ground & ~np.isfinite(extra_m), np.inf, extra_m)
        if richer_covariance is not None:
            r_px, r_m = _linear_std(richer, richer_covariance, uv, probe, on_ground, ground_z, step)
            extra_px = np.sqrt(extra_px**2 + np.maximum(r_px**2 - std_px**2, 0.0))
            with np.errstate(invalid="ignore"):
                more = np.where(np.isinf(r_m), np.inf, np.maximum(r_m**2 - std_m**2, 0.0))
                extra_m = np.sqrt(extra_m**2 + more)
        extra_px = EXTRAPOLATION_FACTOR * extra_px
        extra_m = EXTRAPOLATION_FACTOR * extra_m
    extra_px[~has_ray] = np.inf
    return PixelErrors(
        uv_px=uv, ground_enu_m=ground, std_px=std_px, extrapolation_px=extra_px,
        std_cm=100.0 * std_m, extrapolation_cm=100.0 * extra_m, has_ray=has_ray,
    )


# --------------------------------------------------------------------------
# Polygons


def convex_hull(points: np.ndarray) -> np.ndarray:
    """(H, 2) counter-clockwise convex hull of points (N, 2) (monotone chain; collinear points dropped)."""
    P = np.unique(np.asarray(points, float).reshape(-1, 2), axis=0)
    if len(P) < 3:
        return P

    def half(pts):
        out: list[np.ndarray] = []
        for p in pts:
            while len(out) >= 2 and _cross(out[-1] - out[-2], p - out[-2]) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(P), half(P[::-1])
    return np.array(lower[:-1] + upper[:-1])


def _cross(a: np.ndarray, b: np.ndarray) -> float:
    return float(a[0] * b[1] - a[1] * b[0])


def polygon_area(polygon: np.ndarray) -> float:
    """Area of a simple polygon (K, 2) (shoelace), in its units squared."""
    p = np.asarray(polygon, float)
    if len(p) < 3:
        return 0.0
    x, y = p[:, 0], p[:, 1]
    return float(0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def points_in_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(N,) mask of points (N, 2) inside the simple polygon (K, 2) (even-odd rule)."""
    pts = np.asarray(points, float).reshape(-1, 2)
    poly = np.asarray(polygon, float)
    inside = np.zeros(len(pts), bool)
    if len(poly) < 3:
        return inside
    x, y = pts[:, 0:1], pts[:, 1:2]
    x0, y0 = poly[:, 0][None], poly[:, 1][None]
    x1, y1 = np.roll(poly[:, 0], -1)[None], np.roll(poly[:, 1], -1)[None]
    crosses = (y0 > y) != (y1 > y)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # horizontal edges never cross (masked)
        x_at = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
    return np.logical_xor.reduce(crosses & (x < x_at), axis=1)


def _ray_exit(centre: np.ndarray, dirs: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(D,) distance from ``centre`` (inside the convex polygon) along unit dirs (D, 2) to its boundary."""
    a = polygon
    b = np.roll(polygon, -1, axis=0)
    e = b - a  # (K, 2)
    w = a - centre  # (K, 2)
    # centre + s d = a + u e  ->  solve for s, u per (direction, edge)
    den = dirs[:, None, 0] * (-e[None, :, 1]) - dirs[:, None, 1] * (-e[None, :, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (w[None, :, 0] * (-e[None, :, 1]) - w[None, :, 1] * (-e[None, :, 0])) / den
        u = (dirs[:, None, 0] * w[None, :, 1] - dirs[:, None, 1] * w[None, :, 0]) / den
    ok = np.isfinite(s) & (s >= 0) & (u >= -1e-9) & (u <= 1 + 1e-9)
    return np.where(ok, s, np.inf).min(axis=1)


def grow_region(
    supported,
    hull_px: np.ndarray,
    width: int,
    height: int,
    directions: int = DIRECTIONS,
    steps: int = RADIAL_STEPS,
) -> np.ndarray:
    """(directions, 2) star-shaped polygon: the hull grown outward while the calibration stays supported.

    Parameters
    ----------
    supported : callable mapping pixels (M, 2) to a mask (M,): the predicted error is small enough there
    hull_px : (H, 2) convex hull of the used points' pixels

    Along each direction from the hull's centroid the boundary moves from
    the hull towards the image border and stops before the first pixel that
    is not supported. The region always contains the hull: where the data
    are, the fit is what it is.
    """
    hull = np.asarray(hull_px, float)
    centre = hull.mean(axis=0)
    theta = np.linspace(0.0, 2.0 * np.pi, directions, endpoint=False)
    dirs = np.c_[np.cos(theta), np.sin(theta)]
    frame = np.array([[-0.5, -0.5], [width - 0.5, -0.5], [width - 0.5, height - 0.5], [-0.5, height - 0.5]])
    r_hull = _ray_exit(centre, dirs, hull)
    r_edge = np.maximum(_ray_exit(centre, dirs, frame), r_hull)
    frac = np.linspace(0.0, 1.0, steps)[1:]
    radii = r_hull[:, None] + (r_edge - r_hull)[:, None] * frac[None]  # (D, S)
    pix = centre + radii[..., None] * dirs[:, None, :]
    bad = ~np.asarray(supported(pix.reshape(-1, 2)), bool).reshape(radii.shape)
    first_bad = np.where(bad.any(axis=1), bad.argmax(axis=1), len(frac))
    radius = np.where(first_bad == 0, r_hull, radii[np.arange(directions), np.maximum(first_bad - 1, 0)])
    radius = np.where(first_bad == len(frac), r_edge, radius)
    return centre + radius[:, None] * dirs


# --------------------------------------------------------------------------
# Degenerate geometry


@dataclass(frozen=True)
class GeometryDiagnosis:
    """Can the points separate focal length, principal point and pose?

    From the linearised covariance with the measured sigmas:
    ``focal_std_rel`` the focal length's std over its value; ``principal_point_std_px``
    the norm of (std cx, std cy); ``focal_distance_correlation`` the
    correlation between the focal length and the camera's distance to the
    points' centroid (near 1: a longer lens farther away explains the points
    as well); ``image_coverage`` the share of the image inside the points'
    convex hull; ``thickness_m`` the span of the points' heights (z), m
    (two heights 0.4 m apart: 0.4). ``message`` is the warning, or None when
    the geometry separates them.
    """

    focal_std_rel: float
    principal_point_std_px: float
    focal_distance_correlation: float
    image_coverage: float
    thickness_m: float
    degenerate: bool
    message: str | None

    def to_dict(self) -> dict:
        return {
            "focal_std_percent": 100.0 * self.focal_std_rel,
            "principal_point_std_px": self.principal_point_std_px,
            "focal_distance_correlation": self.focal_distance_correlation,
            "image_coverage": self.image_coverage,
            "thickness_m": self.thickness_m,
            "degenerate": self.degenerate,
            "message": self.message,
        }


def diagnose_geometry(
    camera: Camera,
    covariance: np.ndarray,
    points_world: np.ndarray,
    pixels: np.ndarray,
    max_focal_std_rel: float = 0.005,
    max_pp_std_fraction: float = 0.01,
) -> GeometryDiagnosis:
    """Whether the points pin focal length, principal point and pose, from the measured-sigma covariance.

    Parameters
    ----------
    camera : the calibrated camera
    covariance : (15, 15) linearised covariance with the measured per-point sigmas
    points_world : (N, 3) the used points, metres; pixels : (N, 2)
    max_focal_std_rel : focal std (fraction of the focal length) above which the geometry is flagged
    max_pp_std_fraction : principal point std (fraction of the image width) above which it is flagged

    A thin band of points at one distance cannot tell a longer lens farther
    away from a shorter one closer: the focal length and the camera's
    distance move together (correlation near 1) and both have large stds.
    Measured with 1 cm (1.5 cm up) / 0.3 px sigmas (tests/test_validity.py):
    the paper's Table 1 camera (2 m pole, tilt 30 deg) over its 4-8 m grid
    at heights 1.0 and 1.4 m has a focal std of 0.7-1.4 % and a principal
    point std of 16-27 px (correlation with the distance 0.7: the principal
    point and k1 share the ambiguity); the wide 1080p camera over a grid
    filling 74 % of the image at four heights: 0.08 % and 1.8 px. The
    thresholds sit between the two.
    """
    X = np.asarray(points_world, float)
    uv = np.asarray(pixels, float)
    cov = np.asarray(covariance, float)
    i = camera.intrinsics
    f = 0.5 * (i.fx + i.fy)
    centroid = X.mean(axis=0)
    S = _covariance_steps(cov)
    focal_sd = dist_sd = corr = 0.0
    if len(S):
        r = len(S)
        h = 1e-3
        state = BatchState.from_camera(camera, 2 * r).stepped(np.concatenate([h * S, -h * S]))
        focal = 0.5 * (state.intrinsics[:, 0] + state.intrinsics[:, 1])
        centres = -np.einsum("kji,kj->ki", state.R, state.t)
        dist = np.linalg.norm(centres - centroid, axis=1)
        df = (focal[:r] - focal[r:]) / (2 * h)
        dd = (dist[:r] - dist[r:]) / (2 * h)
        focal_sd = float(np.sqrt(df @ df))
        dist_sd = float(np.sqrt(dd @ dd))
        corr = float(df @ dd / (focal_sd * dist_sd)) if focal_sd > 0 and dist_sd > 0 else 0.0
    pp_sd = float(np.hypot(np.sqrt(max(cov[2, 2], 0.0)), np.sqrt(max(cov[3, 3], 0.0))))
    coverage = polygon_area(convex_hull(uv)) / float(camera.width * camera.height)
    thickness = float(np.ptp(X[:, 2]))
    focal_rel = focal_sd / f
    degenerate = focal_rel > max_focal_std_rel or pp_sd > max_pp_std_fraction * camera.width
    message = None
    if degenerate:
        if abs(corr) >= 0.9:
            what = f"focal length and camera distance are not separated (std {100 * focal_rel:.1f} %, correlation {abs(corr):.2f})"
        else:
            what = (
                f"focal length and principal point are poorly determined (focal std {100 * focal_rel:.1f} %, "
                f"principal point std {pp_sd:.0f} px, focal/distance correlation {abs(corr):.2f})"
            )
        message = (
            f"{what}: the points cover {coverage:.0%} of the image at heights spanning {thickness:.1f} m; "
            "fly more heights and lower/closer points (plan --strategy image)"
        )
    return GeometryDiagnosis(
        focal_std_rel=float(focal_rel),
        principal_point_std_px=pp_sd,
        focal_distance_correlation=corr,
        image_coverage=float(coverage),
        thickness_m=thickness,
        degenerate=bool(degenerate),
        message=message,
    )


# --------------------------------------------------------------------------
# The region of validity


@dataclass(frozen=True, eq=False)
class ValidityRegion:
    """Where the calibration is supported by its points, in the image and on the ground.

    ``polygon_px`` (K, 2): the region of validity, pixels (OpenCV: centre of
    the top-left pixel at 0, 0); ``hull_px`` (H, 2): the convex hull of the
    used points' pixels. ``ground_polygon_enu_m`` (L, 3): its footprint on
    z = 0 (None when no part of it sees the ground within 200 m);
    ``ground_polygon_wgs84`` (L, 3) [lat_deg, lon_deg, h_m] of that footprint
    when the ENU origin is known. Fractions are of the image area and of the
    visible ground 3-30 m from the pole (and of the given ROI). Errors
    ``inside_*`` / ``outside_*`` are predicted (linearised std and model
    extrapolation, root-sum-square) over the visible ground 3-30 m inside /
    outside the region. ``richer`` is the richer model's fit (None without
    one); ``geometry`` the degeneracy diagnosis.
    """

    polygon_px: np.ndarray
    hull_px: np.ndarray
    threshold_px: float
    std_limit_px: float
    image_fraction: float
    hull_fraction: float
    ground_polygon_enu_m: np.ndarray | None
    ground_polygon_wgs84: np.ndarray | None
    visible_ground_fraction: float | None
    roi_fraction: float | None
    inside_px_rms: float | None
    inside_px_max: float | None
    inside_cm_rms: float | None
    inside_cm_max: float | None
    outside_px_max: float | None
    outside_cm_max: float | None
    chosen_model: str
    richer_model: str | None
    geometry: GeometryDiagnosis
    warnings: tuple[str, ...]
    richer: CalibrationResult | None = field(default=None, repr=False)
    richer_covariance: np.ndarray | None = field(default=None, repr=False)
    # Whether the ground point 15 m out on the heading (the report's "at 15 m" figures,
    # core.uncertainty.ground_probe) lies inside the region: outside, those figures are not supported.
    probe_15m_inside: bool | None = None
    at_15m: object | None = field(default=None, repr=False)  # pipeline.ground15.AtFifteen, set by the uncertainty stage

    @property
    def richer_camera(self) -> Camera | None:
        return None if self.richer is None else self.richer.camera

    def to_dict(self) -> dict:
        """JSON-ready content of report.json's ``validity`` section."""
        return {
            "polygon_px": self.polygon_px.tolist(),
            "hull_px": self.hull_px.tolist(),
            "threshold_px": self.threshold_px,
            "std_limit_px": self.std_limit_px,
            "image_fraction": self.image_fraction,
            "hull_fraction": self.hull_fraction,
            "ground_polygon_enu_m": None if self.ground_polygon_enu_m is None else self.ground_polygon_enu_m.tolist(),
            "ground_polygon_wgs84": None if self.ground_polygon_wgs84 is None else self.ground_polygon_wgs84.tolist(),
            "visible_ground_m": list(VISIBLE_GROUND_M),
            "visible_ground_fraction": self.visible_ground_fraction,
            "roi_fraction": self.roi_fraction,
            "predicted_error": {
                "method": "90 % bound: 1.645 x the linearised std (measured sigmas), root-sum-square with the model extrapolation",
                "inside_px_rms": self.inside_px_rms, "inside_px_max": self.inside_px_max,
                "inside_cm_rms": self.inside_cm_rms, "inside_cm_max": self.inside_cm_max,
                "outside_px_max": self.outside_px_max, "outside_cm_max": self.outside_cm_max,
            },
            "chosen_model": self.chosen_model,
            "richer_model": self.richer_model,
            "at_15m_inside": self.probe_15m_inside,
            "geometry": self.geometry.to_dict(),
            "warnings": list(self.warnings),
        }

    def geojson(self) -> dict | None:
        """The ground footprint as a GeoJSON FeatureCollection (RFC 7946: [lon, lat], closed ring), None without one."""
        if self.ground_polygon_wgs84 is None or len(self.ground_polygon_wgs84) < 3:
            return None
        ring = [[float(p[1]), float(p[0])] for p in self.ground_polygon_wgs84]
        ring.append(ring[0])
        return {
            "type": "FeatureCollection",
            "features": [{
                "type": "Feature",
                "geometry": {"type": "Polygon", "coordinates": [ring]},
                "properties": {
                    "name": "region of validity (ground z = 0)",
                    "threshold_px": self.threshold_px,
                    "visible_ground_fraction": self.visible_ground_fraction,
                    "model": self.chosen_model,
                },
            }],
        }


def visible_ground(camera: Camera, ranges_m: tuple[float, float] = VISIBLE_GROUND_M, step_m: float = GROUND_STEP_M, ground_z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Ground points (N, 3) on a ``step_m`` grid between ``ranges_m`` of the pole's foot that the camera sees, and their pixels (N, 2)."""
    pts, _ = ground_ring(camera.pose.position_world[:2], ranges_m, step_m, ground_z)
    seen, uv = seen_on_ground(camera, pts, ground_z)
    return pts[seen], uv[seen]


def ground_ring(foot_xy: np.ndarray, ranges_m: tuple[float, float], step_m: float, ground_z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) of a ``step_m`` grid on z = ``ground_z`` whose horizontal distance from ``foot_xy`` lies in
    ``ranges_m``, and those distances (N,): the region users measure in, for the report and the simulator's check."""
    r0, r1 = ranges_m
    g = np.arange(-r1, r1 + 1e-9, step_m)
    X, Y = np.meshgrid(g, g, indexing="ij")
    rho = np.hypot(X, Y).ravel()
    keep = (rho >= r0) & (rho <= r1)
    pts = np.c_[X.ravel()[keep] + foot_xy[0], Y.ravel()[keep] + foot_xy[1], np.full(int(keep.sum()), ground_z)]
    return pts, rho[keep]


def seen_on_ground(camera: Camera, points: np.ndarray, ground_z: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(N,) mask of ground points (N, 3) the camera sees, and their pixels (N, 2).

    Seen: in front, inside the fold of the distortion model, inside the
    image, and the pixel's own ray comes back to the point. The fold matters
    for a radial model fitted near the centre: beyond it (k1 < 0 turns back
    at r^2 = -1/(3 k1)) the model maps points far outside the view into the
    middle of the image.
    """
    pts = np.asarray(points, float).reshape(-1, 3)
    uv = np.full((len(pts), 2), np.nan)
    Xc = pts @ camera.pose.R_cam_from_world.T + camera.pose.t_cam_from_world
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.hypot(Xc[:, 0], Xc[:, 1]) / Xc[:, 2]
    front = (Xc[:, 2] > 0.1) & (r < fold_radius(camera.distortion.as_array()))
    uv[front] = camera.project(pts[front])
    with np.errstate(invalid="ignore"):
        ok = front & (uv[:, 0] >= -0.5) & (uv[:, 0] <= camera.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] <= camera.height - 0.5)
    if ok.any():
        back = intersect_plane_z(*camera.batch_arrays(), uv[ok][None], ground_z)[0]
        reach = np.linalg.norm(pts[ok, :2] - camera.pose.position_world[:2], axis=1)
        miss = ~(np.linalg.norm(back[:, :2] - pts[ok, :2], axis=1) <= 1e-3 * np.maximum(reach, 1.0))
        ok[np.flatnonzero(ok)[miss]] = False
    return ok, uv


def ground_footprint(camera: Camera, polygon_px: np.ndarray, ground_z: float = 0.0, max_range_m: float = MAX_GROUND_RANGE_M) -> np.ndarray | None:
    """(L, 3) polygon on z = ``ground_z`` of the ground the image polygon (K, 2) sees, ENU metres; None if none.

    On each bearing from the pole's foot the ground the camera sees inside
    the polygon is one interval of range; the footprint joins the near ends
    and then the far ends, bearing by bearing.
    """
    c = camera.pose.position_world
    ranges = np.geomspace(0.3, max_range_m, 240)
    fwd = camera.pose.R_cam_from_world[2]
    heading = np.arctan2(fwd[1], fwd[0])
    bearings = heading + np.radians(np.linspace(-90.0, 90.0, 181))
    B, Rg = np.meshgrid(bearings, ranges, indexing="ij")  # (nb, nr)
    pts = np.stack([c[0] + Rg * np.cos(B), c[1] + Rg * np.sin(B), np.full(B.shape, ground_z)], -1).reshape(-1, 3)
    seen, uv = seen_on_ground(camera, pts, ground_z)
    inside = seen.copy()
    inside[seen] = points_in_polygon(uv[seen], polygon_px)
    inside = inside.reshape(B.shape)
    rows = np.flatnonzero(inside.any(axis=1))
    if len(rows) < 2:
        return None
    near = np.array([Rg[b, inside[b].argmax()] for b in rows])
    far = np.array([Rg[b, len(ranges) - 1 - inside[b][::-1].argmax()] for b in rows])
    bb = bearings[rows]
    ring_b = np.r_[bb, bb[::-1]]
    ring_r = np.r_[near, far[::-1]]
    return np.c_[c[0] + ring_r * np.cos(ring_b), c[1] + ring_r * np.sin(ring_b), np.full(len(ring_b), ground_z)]


@dataclass(frozen=True, eq=False)
class PlanRoi:
    """The ground a camera is meant to serve, from the plan: a range of distances from the pole or a polygon.

    ``range_m`` (near, far) metres from the pole's foot; ``polygon_enu_m``
    (K, 2) metres in the calibration's ENU frame, or None; ``text`` the
    plan's own description.
    """

    range_m: tuple[float, float]
    polygon_enu_m: np.ndarray | None
    text: str


def roi_from_plan(plan: dict, origin=None) -> PlanRoi | None:
    """The ROI of a plan.json (as ``plan`` writes it and ``fly`` attaches it to the run), None without one.

    Parameters
    ----------
    plan : the parsed plan.json
    origin : geodesy.EnuOrigin of the calibration's ENU frame; a polygon given
        in the plan's site frame is moved into it through WGS84 (None: the
        plan's own frame, at the pole's foot)

    A ``range`` ROI is the ground between two distances from the pole; an
    ``image`` ROI (every ray up to a range) counts as the ground up to that
    range; a ``polygon`` ROI is turned from the site frame (X along the
    camera azimuth, Y left) into ENU.
    """
    from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic, geodetic_to_enu

    roi = plan.get("roi") if isinstance(plan, dict) else None
    if not isinstance(roi, dict):
        return None
    try:
        near, far = (float(v) for v in roi.get("range_m") or VISIBLE_GROUND_M)
        text = str(roi.get("text") or roi.get("kind"))
        if roi.get("kind") == "image":
            return PlanRoi(range_m=(0.0, far), polygon_enu_m=None, text=text)
        poly = roi.get("polygon_site_m")
        if roi.get("kind") != "polygon" or not poly:
            return PlanRoi(range_m=(near, far), polygon_enu_m=None, text=text)
        R = np.asarray(plan["site_frame"]["R_enu_from_site"], float)
        xy = np.asarray(poly, float)[:, :2]
        enu = np.c_[xy, np.zeros(len(xy))] @ R.T
        o = plan.get("enu_origin") or {}
        if origin is not None and o:
            plan_origin = EnuOrigin(lat_deg=float(o["lat_deg"]), lon_deg=float(o["lon_deg"]), h_m=float(o["h_m"]))
            llh = enu_to_geodetic(enu, plan_origin)
            enu = geodetic_to_enu(llh[:, 0], llh[:, 1], llh[:, 2], origin)
        return PlanRoi(range_m=(near, far), polygon_enu_m=enu[:, :2], text=text)
    except (KeyError, TypeError, ValueError):
        return None


def assess_validity(
    result: CalibrationResult,
    covariance: np.ndarray,
    sigma_3d: np.ndarray,
    sigma_2d: np.ndarray,
    origin=None,
    roi: "PlanRoi | None" = None,
    richer: CalibrationResult | None | str = "fit",
    threshold_px: float = THRESHOLD_PX,
    loss_scale_px: float = 2.0,
    ground_z: float = 0.0,
) -> ValidityRegion:
    """The region of validity of a calibration, its ground footprint, predicted errors and warnings.

    Parameters
    ----------
    result : the calibration (its camera in ENU metres at the pole's foot; its points and pixels)
    covariance : (15, 15) linearised covariance with the measured per-point sigmas
        (``core.uncertainty.parameter_covariance``)
    sigma_3d : (N, 3) or (3,) those sigmas of the points, metres; sigma_2d : (N,) or scalar, px
        (for the richer model's covariance)
    origin : geodesy.EnuOrigin of the ENU frame, for the WGS84 footprint (None: ENU only)
    roi : the ground the camera is meant to serve (``roi_from_plan`` of the run's plan.json), or None
    richer : "fit" fits the next richer model (``fit_richer``); or a given fit, or None for no extrapolation term
    threshold_px : model-extrapolation term allowed inside the region, px; the linearised
        std may reach this or twice its RMS inside the hull, whichever is larger
    loss_scale_px : robust loss scale for the richer fit, px

    Returns
    -------
    ValidityRegion; its ``warnings`` say when the visible ground 3-30 m (or
    the ROI) reaches beyond the region, by how much, and what to fly.

    Examples
    --------
    >>> v = assess_validity(result, parameter_covariance(camera, X, s3, s2, result.model), s3, s2, origin)
    >>> v.visible_ground_fraction, v.outside_px_max, v.warnings
    """
    camera = result.camera
    w, h = camera.width, camera.height
    if isinstance(richer, str):
        richer = fit_richer(result, loss_scale_px)
    richer_cam = None if richer is None else richer.camera
    richer_cov = None
    if richer is not None:
        from dronecal_field.core.uncertainty import parameter_covariance

        richer_cov = parameter_covariance(richer_cam, result.points_world, sigma_3d, sigma_2d, richer.model)
    uv_used = np.asarray(result.pixels, float)

    hull = convex_hull(uv_used)
    if len(hull) < 3:  # points on a line in the image: nothing to grow from
        hull = np.array([uv_used.min(0), [uv_used.max(0)[0], uv_used.min(0)[1]], uv_used.max(0)])
    std_hull = pixel_errors(camera, covariance, _fill(hull, 200), None, None, ground_z).std_px
    hull_rms = float(np.sqrt(np.nanmean(std_hull**2))) if np.isfinite(std_hull).any() else 0.0
    std_limit = max(threshold_px, HULL_FACTOR * hull_rms)

    def supported(uv: np.ndarray) -> np.ndarray:
        e = pixel_errors(camera, covariance, uv, richer_cam, richer_cov, ground_z)
        return (e.extrapolation_px <= threshold_px) & (e.std_px <= std_limit)

    polygon = grow_region(supported, hull, w, h)
    footprint = ground_footprint(camera, polygon, ground_z)
    wgs84 = None
    if footprint is not None and origin is not None:
        from dronecal_field.geodesy import enu_to_geodetic

        wgs84 = enu_to_geodetic(footprint, origin)  # an EnuOrigin holds plain floats (the PROJ string needs them)

    g, g_uv = visible_ground(camera, ground_z=ground_z)
    stats: dict[str, float | None] = dict.fromkeys(
        ("frac", "in_px_rms", "in_px_max", "in_cm_rms", "in_cm_max", "out_px_max", "out_cm_max")
    )
    if len(g):
        inside = points_in_polygon(g_uv, polygon)
        e = pixel_errors(camera, covariance, g_uv, richer_cam, richer_cov, ground_z)
        px, cm = e.total_px, e.total_cm
        stats["frac"] = float(inside.mean())
        if inside.any():
            stats["in_px_rms"] = float(np.sqrt(np.mean(px[inside] ** 2)))
            stats["in_px_max"] = float(np.max(px[inside]))
            stats["in_cm_rms"] = float(np.sqrt(np.nanmean(cm[inside] ** 2)))
            stats["in_cm_max"] = float(np.nanmax(cm[inside]))
        if (~inside).any():
            stats["out_px_max"] = float(np.max(px[~inside]))
            stats["out_cm_max"] = float(np.nanmax(cm[~inside]))
    roi_fraction = None if roi is None else _roi_fraction(camera, roi, polygon, ground_z)

    geometry = diagnose_geometry(camera, covariance, result.points_world, result.pixels)
    warnings = _warnings(stats, roi_fraction, None if roi is None else roi.text, geometry, threshold_px)
    probe_inside = _probe_15m_inside(camera, polygon, ground_z)
    if probe_inside is False:
        warnings.append(
            "the ground 15 m out on the camera's heading lies outside the region of validity: the report's ground "
            "and speed errors there include the lens's extrapolation; fly points that reach that part of the image"
        )
    return ValidityRegion(
        polygon_px=polygon,
        hull_px=hull,
        threshold_px=float(threshold_px),
        std_limit_px=float(std_limit),
        image_fraction=polygon_area(polygon) / float(w * h),
        hull_fraction=polygon_area(hull) / float(w * h),
        ground_polygon_enu_m=footprint,
        ground_polygon_wgs84=wgs84,
        visible_ground_fraction=stats["frac"],
        roi_fraction=roi_fraction,
        inside_px_rms=stats["in_px_rms"],
        inside_px_max=stats["in_px_max"],
        inside_cm_rms=stats["in_cm_rms"],
        inside_cm_max=stats["in_cm_max"],
        outside_px_max=stats["out_px_max"],
        outside_cm_max=stats["out_cm_max"],
        chosen_model=result.model.name,
        richer_model=None if richer is None else richer.model.name,
        geometry=geometry,
        warnings=tuple(warnings),
        richer=richer,
        richer_covariance=richer_cov,
        probe_15m_inside=probe_inside,
    )


def _probe_15m_inside(camera: Camera, polygon_px: np.ndarray, ground_z: float) -> bool | None:
    """Whether the report's ground probe 15 m out projects inside the region (None when the camera does not see it)."""
    from dronecal_field.core.uncertainty import ground_probe

    point = ground_probe(camera, ground_z).point
    if camera.depth(point[None])[0] <= 0:
        return None
    uv = camera.project(point[None])
    if not (np.all(np.isfinite(uv)) and 0 <= uv[0, 0] <= camera.width - 1 and 0 <= uv[0, 1] <= camera.height - 1):
        return None
    return bool(points_in_polygon(uv, polygon_px)[0])


def _fill(polygon: np.ndarray, n: int) -> np.ndarray:
    """About ``n`` pixels on a regular grid inside a polygon (K, 2), plus its vertices."""
    lo, hi = polygon.min(0), polygon.max(0)
    k = max(int(np.sqrt(n)), 2)
    U, V = np.meshgrid(np.linspace(lo[0], hi[0], k), np.linspace(lo[1], hi[1], k))
    grid = np.c_[U.ravel(), V.ravel()]
    return np.r_[grid[points_in_polygon(grid, polygon)], polygon]


def _roi_fraction(camera: Camera, roi: "PlanRoi", polygon_px: np.ndarray, ground_z: float) -> float | None:
    """Share of the ROI's ground the camera sees that lies inside the region (None when it sees none of it)."""
    if roi.polygon_enu_m is None:
        _, uv = visible_ground(camera, roi.range_m, ground_z=ground_z)
        return float(points_in_polygon(uv, polygon_px).mean()) if len(uv) else None
    poly = np.asarray(roi.polygon_enu_m, float)[:, :2]
    if len(poly) < 3:
        return None
    lo, hi = poly.min(0), poly.max(0)
    step = max(float(np.max(hi - lo)) / 150.0, 0.05)
    E, N = np.meshgrid(np.arange(lo[0], hi[0] + step, step), np.arange(lo[1], hi[1] + step, step))
    pts = np.c_[E.ravel(), N.ravel()]
    pts = pts[points_in_polygon(pts, poly)]
    if not len(pts):
        return None
    P = np.c_[pts, np.full(len(pts), ground_z)]
    seen, uv = seen_on_ground(camera, P, ground_z)
    if not seen.any():
        return None
    return float(points_in_polygon(uv[seen], polygon_px).mean())


def _warnings(stats: dict, roi_fraction: float | None, roi_text: str | None, geometry: GeometryDiagnosis, threshold: float) -> list[str]:
    out: list[str] = []
    frac = stats["frac"]
    lo, hi = VISIBLE_GROUND_M
    if frac is not None and frac < MIN_GROUND_FRACTION:
        reach = stats["out_px_max"]
        cm = stats["out_cm_max"]
        how_bad = (
            f"outside it the predicted error reaches {_px(reach)}" + (f" ({_cm(cm)} on the ground)" if cm is not None and np.isfinite(cm) else "")
            if reach is not None else "outside it the error is not predicted"
        )
        out.append(
            f"the region of validity (model extrapolation under {threshold:.1f} px) covers {frac:.0%} of the visible ground "
            f"{lo:g}-{hi:g} m; {how_bad}: fly the whole view (plan --strategy image) or use the camera only inside "
            "validity_polygon_px"
        )
    if roi_fraction is not None and roi_fraction < MIN_GROUND_FRACTION:
        out.append(
            f"the region of validity covers {roi_fraction:.0%} of the plan's ROI ({roi_text}): fly points over the rest "
            "of it (plan --strategy image)"
        )
    if geometry.message is not None:
        out.append(geometry.message)
    return out


def _px(v: float) -> str:
    return "beyond 1000 px" if not np.isfinite(v) or v > 1000 else f"{v:.0f} px" if v >= 10 else f"{v:.1f} px"


def _cm(v: float) -> str:
    return "over 10 m" if not np.isfinite(v) or v > 1000 else f"{v:.0f} cm"
