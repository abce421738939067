"""What a calibration means over the image and on the ground.

- ``choose_model``: the distortion model the points can support, from their
  number (the engine's rule) and their spread over the image (distortion
  grows with the radius; points near the centre cannot pin k2 or p1, p2).
- (the parameter covariance under the measured per-point sigmas comes from
  ``core.uncertainty.parameter_covariance``, the linearised twin of the Monte-Carlo.)
- ``uncertainty_maps``: cameras drawn from that covariance, giving the
  projection uncertainty (px) of the ground point seen at each pixel and the
  ground-position uncertainty (cm) of each pixel's ray on the plane z = 0.
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
    intersect_plane_z,
    project_batch,
)

MAX_GROUND_RANGE_M = 200.0


def choose_model(uv_px: np.ndarray, width: int, height: int) -> tuple[CalibrationModel, str]:
    """(model, reason) for points observed at pixels (N, 2).

    The engine's ``auto`` rule bounds the model by the point count; the
    radius the points reach bounds the distortion further, because a
    distortion term is only determined where it is large.
    """
    from dataclasses import replace

    uv = np.asarray(uv_px, float)
    n = len(uv)
    by_count = resolve_model("auto", n)
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    half_diag = 0.5 * np.hypot(width, height)
    r = np.linalg.norm(uv - centre, axis=1) / half_diag
    r_max = float(np.percentile(r, 90)) if n else 0.0
    order = ("none", "k1", "k1k2", "k1k2p1p2")
    if r_max < 0.3:
        cap, why = "none", f"points reach only {r_max:.0%} of the half-diagonal: no distortion term is observable"
    elif r_max < 0.55:
        cap, why = "k1", f"points reach {r_max:.0%} of the half-diagonal: only k1 is observable"
    else:
        cap, why = "k1k2p1p2", f"points reach {r_max:.0%} of the half-diagonal"
    allowed = by_count.distortion if by_count.distortion in order else "k1k2p1p2"
    name = order[min(order.index(allowed), order.index(cap))]
    model = replace(by_count, distortion=name)
    return model, f"{n} points allow {by_count.name}; {why}"


def select_model(
    points_world: np.ndarray,
    pixels: np.ndarray,
    width: int,
    height: int,
    loss: str = "huber",
    loss_scale_px: float = 2.0,
    significance: float = 0.01,
    max_pp_inflation: float = 1.5,
):
    """Calibrate with the richest distortion model the data support: (CalibrationResult, reason).

    Climbs none -> k1 -> k1k2 -> k1k2p1p2 up to the cap of :func:`choose_model`
    and keeps a richer model only when it lowers the residual sum of squares
    significantly (an F-test at ``significance``). With few points a rich
    model fits the noise: it halves the RMS while moving the principal point
    by pixels, which the F-test refuses.

    Tangential terms (p1, p2) face a second test: they trade off almost
    exactly against the principal point, so a fit that takes them also
    scatters (cx, cy). They are kept only when the principal point's standard
    deviation grows by at most ``max_pp_inflation`` (measured: on a pinhole
    camera with 2 cm hover drift, p1 and p2 passed the F-test, inflated the
    principal point's std ~3x and moved it by 20 px).

    Parameters
    ----------
    points_world : (N, 3) metres, pixels : (N, 2)
    significance : float
        F-test level for each added group of terms.
    max_pp_inflation : float
        Largest accepted ratio of the principal point's std (the norm of
        std cx, std cy) with the tangential terms to without.
    """
    from dataclasses import replace

    from scipy import stats

    from dronecal_field.core.calibrate import calibrate

    cap, why = choose_model(pixels, width, height)
    ladder = ("none", "k1", "k1k2", "k1k2p1p2")
    ladder = ladder[: ladder.index(cap.distortion) + 1]
    n_obs = 2 * len(points_world)

    def fit(distortion: str):
        return calibrate(points_world, pixels, width, height, model=replace(cap, distortion=distortion), loss=loss, loss_scale_px=loss_scale_px)

    best = fit(ladder[0])
    rejected = []
    for name in ladder[1:]:
        try:
            candidate = fit(name)
        except Exception:  # noqa: BLE001 - a richer model that does not converge is simply not chosen
            rejected.append(f"{name} (no fit)")
            continue
        dp = candidate.model.n_free - best.model.n_free
        dof = n_obs - candidate.model.n_free
        rss_b = float(np.sum(best.residuals_px**2))
        rss_c = float(np.sum(candidate.residuals_px**2))
        if dof <= 0 or rss_c <= 0:
            if rss_c < rss_b:
                best = candidate
            continue
        F = ((rss_b - rss_c) / dp) / (rss_c / dof)
        p = float(stats.f.sf(F, dp, dof)) if F > 0 else 1.0
        if p >= significance:
            rejected.append(f"{name} (p={p:.2g})")
            continue
        if "p1" in candidate.model.free_names() and "p1" not in best.model.free_names():
            inflation = _pp_std(candidate) / max(_pp_std(best), 1e-12)
            if inflation > max_pp_inflation:
                rejected.append(f"{name} (p={p:.2g} but the principal point's std grows {inflation:.1f}x)")
                continue
        best = candidate
    reason = why + (f"; not significant: {', '.join(rejected)}" if rejected else "")
    return best, reason


def _pp_std(result) -> float:
    """Norm of the principal point's (cx, cy) standard deviations of a CalibrationResult, px."""
    cov = result.camera.covariance
    return float(np.hypot(np.sqrt(max(cov[2, 2], 0.0)), np.sqrt(max(cov[3, 3], 0.0))))


@dataclass(frozen=True, eq=False)
class UncertaintyMaps:
    """Per-pixel uncertainty over a grid of the image.

    ``u_px`` (nu,), ``v_px`` (nv,) grid coordinates; ``projection_px``
    (nv, nu) RMS pixel error of the ground point each grid pixel sees (the
    ray's point 15 m out where it misses the ground); ``ground_cm`` (nv, nu)
    RMS horizontal position error of that ground point, cm (NaN where the ray
    misses the ground in front of the camera or lands beyond 200 m).
    """

    u_px: np.ndarray
    v_px: np.ndarray
    projection_px: np.ndarray
    ground_cm: np.ndarray
    samples: int

    def summary(self) -> dict:
        g = self.ground_cm[np.isfinite(self.ground_cm)]
        p = self.projection_px[np.isfinite(self.projection_px)]
        return {
            "grid": [int(len(self.u_px)), int(len(self.v_px))],
            "samples": self.samples,
            "projection_px_median": float(np.median(p)) if p.size else None,
            "projection_px_max": float(np.max(p)) if p.size else None,
            "ground_cm_median": float(np.median(g)) if g.size else None,
            "ground_cm_p95": float(np.percentile(g, 95)) if g.size else None,
            "ground_fraction_of_image": float(np.isfinite(self.ground_cm).mean()),
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
    nu: int = 32,
    nv: int = 24,
    samples: int = 400,
    seed: int = 0,
    ground_z: float = 0.0,
) -> UncertaintyMaps:
    """Projection and ground uncertainty over a (nv, nu) grid of the image; see UncertaintyMaps."""
    u = np.linspace(0.0, camera.width - 1.0, nu)
    v = np.linspace(0.0, camera.height - 1.0, nv)
    uv = np.stack(np.meshgrid(u, v), -1).reshape(-1, 2)
    arrays = camera.batch_arrays()
    ground = intersect_plane_z(*arrays, uv[None], ground_z)[0]  # (M, 3)
    centre = camera.pose.position_world
    reach = np.linalg.norm(ground[:, :2] - centre[:2], axis=1)
    on_ground = np.all(np.isfinite(ground), axis=1) & (reach < MAX_GROUND_RANGE_M)
    # Where the ray misses the ground, probe the point 15 m along it instead.
    from dronecal_field.core.camera import pixel_rays_batch

    rays = pixel_rays_batch(arrays[0], arrays[1], arrays[2], uv[None])[0]
    probe = np.where(on_ground[:, None], ground, centre + 15.0 * rays)
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
    return UncertaintyMaps(
        u_px=u, v_px=v, projection_px=proj.reshape(nv, nu), ground_cm=ground_cm.reshape(nv, nu), samples=samples
    )


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
