"""What a calibration means over the image and on the ground.

- ``choose_model`` / ``select_model``: the camera model the points can
  support, from their number (the engine's rule), their spread over the
  image (distortion grows with the radius; points near the centre cannot pin
  k2 or p1, p2) and F-tests; square pixels unless the data demand otherwise.
- (the parameter covariance under the measured per-point sigmas comes from
  ``core.uncertainty.parameter_covariance``, the linearised twin of the Monte-Carlo.)
- ``uncertainty_maps``: that covariance propagated to every pixel of a
  regular grid (plus the model-extrapolation term of ``validity``): the
  projection error (px) of the ground point seen at each pixel and the
  ground-position error (cm) of each pixel's ray on the plane z = 0.
- ``ground_homography``: image <-> ground plane z = 0 (ENU), for speed
  measurement, on undistorted pixels.

Pure numpy on the core camera model.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecal_field.core.calibrate import BatchState, CalibrationModel, resolve_model
from dronecal_field.core.camera import (
    Camera,
    Distortion,
    intersect_plane_z,
    pixel_rays_batch,
    project_batch,
)
from dronecal_field.errors import CalibrationError, DronecalError
from dronecal_field.pipeline.validity import BOUND_FACTOR, pixel_errors

MAX_GROUND_RANGE_M = 200.0


FULL_MODEL_REACH = 0.6  # k3 (r^6) needs points well out (a 4K camera with k3 -0.02 reaching 72 %: k1k2 left 90 px RMS)


def choose_model(uv_px: np.ndarray, width: int, height: int) -> tuple[CalibrationModel, str]:
    """(model, reason) for points observed at pixels (N, 2): the richest model ``auto`` may try.

    The engine's ``auto`` rule bounds the model by the point count; the
    radius the points reach bounds the distortion further, because a
    distortion term is only determined where it is large (k3 only when the
    points reach 60 % of the half-diagonal).
    """
    from dataclasses import replace

    uv = np.asarray(uv_px, float)
    n = len(uv)
    by_count = resolve_model("auto", n)
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    half_diag = 0.5 * np.hypot(width, height)
    r = np.linalg.norm(uv - centre, axis=1) / half_diag
    r_max = float(np.percentile(r, 90)) if n else 0.0
    order = ("none", "k1", "k1k2", "k1k2p1p2", "full")
    if r_max < 0.3:
        cap, why = "none", f"points reach only {r_max:.0%} of the half-diagonal: no distortion term is observable"
    elif r_max < 0.55:
        cap, why = "k1", f"points reach {r_max:.0%} of the half-diagonal: only k1 is observable"
    elif r_max < FULL_MODEL_REACH:
        cap, why = "k1k2p1p2", f"points reach {r_max:.0%} of the half-diagonal: k3 is not observable"
    else:
        cap, why = "full", f"points reach {r_max:.0%} of the half-diagonal"
    allowed = by_count.distortion if by_count.distortion in order else "k1k2p1p2"
    if allowed == "k1k2p1p2" and n >= CalibrationModel(distortion="full").n_free:
        allowed = "full"
    name = order[min(order.index(allowed), order.index(cap))]
    model = replace(by_count, distortion=name)
    return model, f"{n} points allow {replace(by_count, distortion=allowed).name}; {why}"


K3_OUTER_REACH = 0.8  # points whose 90th-percentile radius reaches this share of the half-diagonal sample k3's ring
K3_SIGNIFICANCE = 0.05  # the F-test level for k3 then


def k3_significance(uv_px: np.ndarray, width: int, height: int, significance: float) -> float:
    """The F-test level for adding k3: ``significance``, relaxed to ``K3_SIGNIFICANCE`` when the points reach the
    image's outer ring.

    The costs are not symmetric there. k3 (r^6) acts in the outer ring, where the ground 3-30 m of a pole camera
    lies; a k3 the points sample is interpolated, so a spurious one costs little, while a missing one is an
    extrapolation error at the corners. Measured: the 4K chain on the simulators (k3 -0.02 true) rejected k3 at
    p = 0.012 and missed the ground by 1.27 px RMS (max 11.4) where k3 gave 0.30 px (its points' 90th percentile at
    0.8 or more of the half-diagonal, like the writer's corner layout, 0.82). Applied to every step of the ladder the
    level 0.05 cost Table 1 with correlated RTK noise 1.38 -> 2.85 px (k1k2), so only k3 gets it, and only there:
    the writer's 4K run without its last quarter (reach 0.74) keeps k1k2p1p2 (0.45 px; with k3 0.22).
    """
    uv = np.asarray(uv_px, float)
    if not len(uv):
        return significance
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    reach = float(np.percentile(np.linalg.norm(uv - centre, axis=1), 90)) / (0.5 * np.hypot(width, height))
    return max(significance, K3_SIGNIFICANCE) if reach >= K3_OUTER_REACH else significance


def select_model(
    points_world: np.ndarray,
    pixels: np.ndarray,
    width: int,
    height: int,
    loss: str = "huber",
    loss_scale_px: float = 2.0,
    significance: float = 0.01,
    max_pp_inflation: float = 1.5,
    max_focal_inflation: float = 1.5,
    n_effective: float | None = None,
):
    """Calibrate with the richest model the data support: (CalibrationResult, reason).

    Square pixels (fx = fy) first, as for nearly every modern sensor. Climbs
    none -> k1 -> k1k2 -> k1k2p1p2 -> full up to the cap of
    :func:`choose_model` and keeps a richer model only when it lowers the
    residual sum of squares significantly (an F-test at ``significance``).
    With few points a rich model fits the noise: it halves the RMS while
    moving the principal point by pixels, which the F-test refuses.

    Tangential terms (p1, p2) face a second test: they trade off almost
    exactly against the principal point, so a fit that takes them also
    scatters (cx, cy). They are kept only when the principal point's standard
    deviation grows by at most ``max_pp_inflation`` (measured: on a pinhole
    camera with 2 cm hover drift, p1 and p2 passed the F-test, inflated the
    principal point's std ~3x and moved it by 20 px).

    Last, the aspect ratio is freed only when the data demand it: the same
    F-test for the one extra parameter, and the focal length's std may grow
    by at most ``max_focal_inflation``, so a free fy never absorbs a thin
    band of points that cannot separate focal length from distance.

    Parameters
    ----------
    points_world : (N, 3) metres, pixels : (N, 2)
    significance : float
        F-test level for each added group of terms.
    max_pp_inflation : float
        Largest accepted ratio of the principal point's std (the norm of
        std cx, std cy) with the tangential terms to without.
    max_focal_inflation : float
        Largest accepted ratio of fx's std with a free aspect ratio to without.
    n_effective : float, optional
        How many independent points the data are worth for the aspect ratio's
        F-test (default: all). Pairs along a leg share its timing error and the
        RTK noise correlated over seconds: 1000 of them freed fy 1.1 % off the
        truth (rolling shutter 30 ms, RTK noise correlated over 10 s) where the
        holds alone kept square pixels.
    """
    from dataclasses import replace

    from dronecal_field.core.calibrate import calibrate

    cap, why = choose_model(pixels, width, height)
    ladder = ("none", "k1", "k1k2", "k1k2p1p2", "full")
    ladder = ladder[: ladder.index(cap.distortion) + 1]
    square = replace(cap, fix_aspect_ratio=True)

    def fit(model: CalibrationModel, *starts):
        """The lowest-RMS fit of ``model`` from the DLT and from each start camera (terms it does not free zeroed)."""
        fits = []
        for start in (None, *starts):
            if start is not None:
                keep = np.isin(("k1", "k2", "p1", "p2", "k3"), model.free_names())
                start = start.with_(distortion=Distortion.from_array(np.where(keep, start.distortion.as_array(), 0.0)))
            try:
                fits.append(calibrate(points_world, pixels, width, height, model=model, loss=loss, loss_scale_px=loss_scale_px, initial=start))
            except DronecalError:
                if start is None and not starts:
                    raise
        if not fits:
            raise CalibrationError(f"no {model.name} fit converged")
        return min(fits, key=lambda r: r.rms_px)

    # Strong distortion far out can trap the lean models' fits from the DLT
    # (a 4K camera with k1 -0.32 k2 0.12 k3 -0.02: k1 and k1k2 stopped at
    # 88-90 px RMS); the richest model finds the pose, and every model also
    # starts from it.
    try:
        top = fit(replace(square, distortion=ladder[-1]))
    except DronecalError:
        top = None
    tops = () if top is None else (top.camera,)
    best = fit(replace(square, distortion=ladder[0]), *tops)
    fits = {ladder[0]: best}
    rejected = []
    outer_ring = ""
    for name in ladder[1:]:
        try:
            candidate = fit(replace(square, distortion=name), best.camera, *tops)
        except DronecalError:  # a richer model that does not converge is simply not chosen
            rejected.append(f"{name} (no fit)")
            continue
        fits[name] = candidate
        p = _f_test(best, candidate, len(points_world))
        level = k3_significance(pixels, width, height, significance) if name == "full" else significance
        if p >= level:
            rejected.append(f"{name} (p={p:.2g})")
            continue
        if p >= significance:
            outer_ring = f"k3 at p={p:.2g}: the points reach the outer ring, where it acts and where a missing k3 costs the most"
        if "p1" in candidate.model.free_names() and "p1" not in best.model.free_names():
            inflation = _pp_std(candidate) / max(_pp_std(best), 1e-12)
            if inflation > max_pp_inflation:
                rejected.append(f"{name} (p={p:.2g} but the principal point's std grows {inflation:.1f}x)")
                continue
        best = candidate
    best, poor = _never_far_worse(best, fits, top)
    if poor:
        rejected = [r for r in rejected if not r.startswith(best.model.distortion + " ")]
    aspect = "square pixels"
    if not cap.fix_aspect_ratio:
        try:
            free = fit(replace(best.model, fix_aspect_ratio=False), best.camera)
        except DronecalError:
            free = None
        if free is not None:
            n_eff = _correlated_n(free.residuals_px, len(points_world) if n_effective is None else n_effective)
            p = _f_test(best, free, len(points_world), n_eff)
            inflation = _focal_std(free) / max(_focal_std(best), 1e-12)
            if p < significance and inflation <= max_focal_inflation:
                best, aspect = free, f"aspect ratio freed (p={p:.2g})"
            elif p < significance:
                aspect = f"square pixels (a free aspect ratio is significant, p={p:.2g}, but grows the focal length's std {inflation:.1f}x)"
            else:
                aspect = f"square pixels (a free aspect ratio is not significant, p={p:.2g})"
    if outer_ring and best.model.distortion != "full":
        outer_ring = ""
    reason = (why + f"; {aspect}" + (f"; {outer_ring}" if outer_ring else "")
              + (f"; not significant: {', '.join(rejected)}" if rejected else "") + poor)
    return best, reason


FAR_WORSE = 4.0  # a chosen model whose RMS is this many times a richer model's ...
FAR_WORSE_SLACK_PX = 0.5  # ... plus this, while the richer one fits, is not kept


def _never_far_worse(best, fits: dict, top) -> tuple[object, str]:
    """(model, note): never a model whose residuals are many times those of a richer model that fits.

    The F-test compares sums of squares; a few wild points (a transit leg paired
    at the wrong instant) inflate both fits' sums so that no richer model looks
    significant, and the ladder stops at ``none`` with 80 px RMS while ``k1k2``
    fits the rest to 0.4 px. Then the simplest model within 1.5x (+ 0.2 px) of
    the richest fit's RMS is taken instead, and the reason says so.
    """
    candidates = [f for f in fits.values() if f is not None] + ([top] if top is not None else [])
    if not candidates:
        return best, ""
    floor = min(c.rms_px for c in candidates)
    if best.rms_px <= FAR_WORSE * floor + FAR_WORSE_SLACK_PX:
        return best, ""
    for name, f in fits.items():  # ladder order: simplest first
        if f.rms_px <= 1.5 * floor + 0.2:
            return f, (f"; {best.model.distortion} kept by the F-test fit to {best.rms_px:.2f} px, {best.rms_px / floor:.0f}x "
                       f"the richest fit's {floor:.2f} px: {name} taken")
    return best, ""


def _correlated_n(residuals_px: np.ndarray, n_effective: float) -> float:
    """``n_effective`` shrunk by the lag-1 correlation of consecutive residuals (N, 2) (points in time order).

    RTK noise correlated over 10 s shifts consecutive holds alike (the fixes of a
    5 s hold-and-move cycle correlate at about 0.6): N such points are worth
    N (1 - rho) / (1 + rho) independent ones (an AR(1) series). Measured on the
    richer fit's residuals, so a pattern that model explains does not count as
    correlation: on the paper's grid for the wide camera with RTK noise
    correlated over 10 s the aspect ratio was freed and fy came out 1.6 % off (fx 0.4 %).
    """
    r = np.asarray(residuals_px, float)
    if len(r) < 8:
        return n_effective
    r = r - r.mean(0)
    rho = float(np.sum(r[1:] * r[:-1]) / max(float(np.sum(r * r)), 1e-12))
    if rho <= 0:
        return n_effective
    return min(n_effective, len(r) * (1.0 - rho) / (1.0 + rho))


def _f_test(simpler, richer, n_points: int, n_effective: float | None = None) -> float:
    """p-value of the F-test that ``richer`` (a CalibrationResult) fits better than ``simpler`` only by chance.

    ``n_effective`` (< ``n_points``): the points are worth fewer independent ones (correlated errors); the
    drop in the sum of squares and the residual degrees of freedom shrink by that share.
    """
    from scipy import stats

    dp = richer.model.n_free - simpler.model.n_free
    share = 1.0 if n_effective is None else float(np.clip(n_effective / max(n_points, 1), 1e-6, 1.0))
    dof = 2 * n_points * share - richer.model.n_free
    rss_b = float(np.sum(simpler.residuals_px**2))
    rss_c = float(np.sum(richer.residuals_px**2))
    if dof <= 0 or rss_c <= 0 or dp <= 0:
        return 0.0 if rss_c < rss_b else 1.0
    F = share * ((rss_b - rss_c) / dp) / (rss_c / (2 * n_points - richer.model.n_free))
    return float(stats.f.sf(F, dp, dof)) if F > 0 else 1.0


def _focal_std(result) -> float:
    """Standard deviation of fx of a CalibrationResult, px."""
    return float(np.sqrt(max(result.camera.covariance[0, 0], 0.0)))


def _pp_std(result) -> float:
    """Norm of the principal point's (cx, cy) standard deviations of a CalibrationResult, px."""
    cov = result.camera.covariance
    return float(np.hypot(np.sqrt(max(cov[2, 2], 0.0)), np.sqrt(max(cov[3, 3], 0.0))))


@dataclass(frozen=True, eq=False)
class UncertaintyMaps:
    """Predicted errors over a regular grid of the image.

    ``u_px`` (nu,), ``v_px`` (nv,) grid coordinates; ``projection_px``
    (nv, nu) predicted pixel error of the ground point each grid pixel sees
    (the ray's point 15 m out where it misses the ground): a 90 % bound,
    1.645 times the linearised std ``std_px`` (validity.BOUND_FACTOR) and,
    when a richer model was given, the model-extrapolation term
    ``extrapolation_px``, root-sum-square;
    ``ground_cm`` (nv, nu) the same for the horizontal position of that
    ground point, cm, NaN where the ray misses the ground in front of the
    camera or lands beyond 200 m (``sky``, (nv, nu) bool); both are inf
    where the distortion model folds (``no_ray``). ``samples`` is
    0 for the linearised maps, else the number of sampled cameras.
    """

    u_px: np.ndarray
    v_px: np.ndarray
    projection_px: np.ndarray
    ground_cm: np.ndarray
    samples: int
    std_px: np.ndarray | None = None
    extrapolation_px: np.ndarray | None = None
    extrapolation_cm: np.ndarray | None = None

    @property
    def no_ray(self) -> np.ndarray:
        """(nv, nu) pixels the distortion model maps no direction to (beyond its fold)."""
        return ~np.isfinite(self.projection_px)

    @property
    def sky(self) -> np.ndarray:
        """(nv, nu) pixels whose ray misses the ground within 200 m."""
        return ~np.isfinite(self.ground_cm) & ~self.no_ray

    def summary(self) -> dict:
        g = self.ground_cm[np.isfinite(self.ground_cm)]
        p = self.projection_px[np.isfinite(self.projection_px)]
        return {
            "grid": [int(len(self.u_px)), int(len(self.v_px))],
            "method": "linearised" if self.samples == 0 else f"{self.samples} sampled cameras",
            "with_model_extrapolation": self.extrapolation_px is not None,
            "samples": self.samples,
            "projection_px_median": float(np.median(p)) if p.size else None,
            "projection_px_max": float(np.max(p)) if p.size else None,
            "ground_cm_median": float(np.median(g)) if g.size else None,
            "ground_cm_p95": float(np.percentile(g, 95)) if g.size else None,
            "ground_fraction_of_image": float(np.isfinite(self.ground_cm).mean()),
            "no_ray_fraction_of_image": float(self.no_ray.mean()),
        }


def sample_cameras(camera: Camera, covariance: np.ndarray, samples: int, seed: int = 0) -> BatchState:
    """``samples`` cameras drawn from N(camera, covariance) (rotation as a left perturbation)."""
    cov = 0.5 * (covariance + covariance.T)
    w, V = np.linalg.eigh(cov)
    L = V * np.sqrt(np.clip(w, 0, None))
    rng = np.random.default_rng(seed)
    steps = rng.standard_normal((samples, cov.shape[0])) @ L.T
    return BatchState.from_camera(camera, samples).stepped(steps)


def uncertainty_maps(
    camera: Camera,
    covariance: np.ndarray,
    nu: int = 64,
    nv: int | None = None,
    samples: int = 0,
    seed: int = 0,
    ground_z: float = 0.0,
    richer: Camera | None = None,
    richer_covariance: np.ndarray | None = None,
) -> UncertaintyMaps:
    """Predicted projection and ground errors over a (nv, nu) grid of the image; see UncertaintyMaps.

    Parameters
    ----------
    camera : the calibrated camera (world = ENU)
    covariance : (15, 15) parameter covariance with the measured sigmas
    nu, nv : grid size (nv default: nu scaled by the image's aspect)
    samples : 0 (default) propagates the covariance to first order, smooth
        everywhere; > 0 draws that many cameras instead (seeded by ``seed``),
        a cross-check of the linearisation
    richer, richer_covariance : the next richer model fitted to the same
        points and its covariance (``validity.fit_richer``), adding the
        model-extrapolation term so the maps grow where the data stop
    """
    if nv is None:
        nv = max(int(round(nu * camera.height / camera.width)), 2)
    u = np.linspace(0.0, camera.width - 1.0, nu)
    v = np.linspace(0.0, camera.height - 1.0, nv)
    uv = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    e = pixel_errors(camera, covariance, uv, richer, richer_covariance, ground_z)
    std_px, std_cm = e.std_px, e.std_cm
    if samples > 0:
        std_px, std_cm = _sampled_std(camera, covariance, uv, e.ground_enu_m, samples, seed, ground_z)
        std_px[~e.has_ray] = np.inf
    proj = np.hypot(BOUND_FACTOR * std_px, e.extrapolation_px)
    ground_cm = np.hypot(BOUND_FACTOR * std_cm, e.extrapolation_cm)
    shape = (nv, nu)
    return UncertaintyMaps(
        u_px=u, v_px=v, projection_px=proj.reshape(shape), ground_cm=ground_cm.reshape(shape), samples=int(samples),
        std_px=std_px.reshape(shape),
        extrapolation_px=None if richer is None else e.extrapolation_px.reshape(shape),
        extrapolation_cm=None if richer is None else e.extrapolation_cm.reshape(shape),
    )


def _sampled_std(camera: Camera, covariance: np.ndarray, uv: np.ndarray, ground: np.ndarray, samples: int, seed: int, ground_z: float):
    """RMS projection (px) and ground (cm) errors over cameras drawn from the covariance, at pixels (M, 2)."""
    arrays = camera.batch_arrays()
    on_ground = np.all(np.isfinite(ground), axis=1)
    rays = pixel_rays_batch(arrays[0], arrays[1], arrays[2], uv[None])[0]
    probe = np.where(on_ground[:, None], ground, camera.pose.position_world + 15.0 * rays)
    state = sample_cameras(camera, covariance, samples, seed)
    args = (state.intrinsics, state.distortion, state.R, state.t)
    uv_k = project_batch(*args, probe[None])  # (K, M, 2)
    proj = np.sqrt(np.mean(np.sum((uv_k - uv[None]) ** 2, -1), 0))
    hits = intersect_plane_z(*args, uv[None], ground_z)  # (K, M, 3)
    err = np.linalg.norm(hits[..., :2] - ground[None, :, :2], axis=-1)
    # A sampled camera whose ray misses the ground is a miss, not an error of 0:
    # average over the samples that hit, and leave pixels no sample resolves NaN.
    hit = np.isfinite(err)
    n_hit = hit.sum(0)
    mean_sq = np.where(n_hit > 0, np.where(hit, err**2, 0.0).sum(0) / np.maximum(n_hit, 1), np.nan)
    ground_cm = 100.0 * np.sqrt(mean_sq)
    ground_cm[~on_ground | (n_hit < samples // 2)] = np.nan
    return proj, ground_cm


def ground_homography(camera: Camera, ground_z: float = 0.0) -> np.ndarray:
    """(3, 3) H with [u, v, 1] ~ H [E, N, 1] for ground points at z = ``ground_z`` (ENU metres).

    ``u, v`` are *undistorted* pixels (the pinhole part of the camera):
    undistort a measured pixel first (``cv2.undistortPoints(..., P=K)``), then
    ``inv(H)`` maps it to the ground. Normalised so H[2, 2] = 1.
    """
    K = camera.intrinsics.matrix
    R = np.asarray(camera.pose.R_cam_from_world, float)
    t = np.asarray(camera.pose.t_cam_from_world, float)
    # A point (E, N, z0) maps to K (E r1 + N r2 + z0 r3 + t).
    H = K @ np.column_stack([R[:, 0], R[:, 1], ground_z * R[:, 2] + t])
    return H / H[2, 2]
