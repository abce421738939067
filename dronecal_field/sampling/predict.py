"""Predicted projection error over the ROI: the linearised noise term and the model-extrapolation term.

Two errors decide how well a calibration serves the ROI:

- *noise*: RTK and detection noise on the samples, propagated to the
  camera parameters to first order (``core.uncertainty.parameter_covariance``)
  and then to the projection of every ROI point. Milliseconds per candidate,
  so hundreds of layouts can be ranked. Each sample has its own sigma: RTK
  1 cm horizontal / 1.5 cm vertical and 2 px (the paper), plus for a fix taken
  in motion the timing term (speed x 0.01 s) along the horizontal.
- *extrapolation*: a first-order noise figure is tight wherever the
  parameters are, including where no sample was; but outside the sampled
  hull the *model* itself is extrapolated. The real lens is not the guess:
  plausible lenses of the guessed level are drawn (k1, k2, k3, p1, p2 around
  the level's nominal, k3 and a different k2 being what the lean model
  cannot express), the planned samples are projected through each, the model
  ``calibrate`` fits is fitted to those exact projections (batched
  Levenberg-Marquardt, no noise), and the ROI projection of the fit is
  compared with the draw's. The RMS over draws is the extrapolation term.

Both are combined per ROI point as a root-sum-square. Ground errors (cm) are
the ground displacement of a fixed pixel on the z = 0 ROI points.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from dronecal_field.core.calibrate import BatchState, levenberg_marquardt, resolve_model
from dronecal_field.core.camera import Camera, project_batch, project_batch_jacobians
from dronecal_field.sampling.lattice import PLAN_FOLD_MIN_SLOPE, fold_radius

N_LENS_DRAWS = 16
MAX_FIT_POINTS = 150  # samples used by the extrapolation fits (noise-free: more add nothing)


@dataclass(frozen=True)
class NoiseModel:
    """Noise of one sample (the paper's: RTK 1 cm / 1.5 cm vertical, 2 px) and the calibration model."""

    sigma_px: float = 2.0
    sigma_h_m: float = 0.01
    sigma_v_m: float = 0.015
    model: str = "auto"


def prediction_model(camera: Camera, samples: np.ndarray, roi_points: np.ndarray, model: str) -> str:
    """The distortion model ``calibrate --model auto`` is expected to fit to these samples.

    ``'auto'`` mirrors ``pipeline.maps.choose_model``'s cap: the samples'
    pixels reach r = the 90th percentile of their distance from the image
    centre over the half-diagonal; r < 0.3: no distortion, < 0.55: k1, < 0.6:
    k1k2p1p2, else the full model (k3 free). Any other name is kept.
    ``roi_points`` is unused by the rule (kept for callers that pass it).
    """
    if model != "auto":
        return model
    if len(samples) < 16:
        return "default"
    uv = camera.project(np.asarray(samples, float))
    centre = np.array([(camera.width - 1) / 2.0, (camera.height - 1) / 2.0])
    r = float(np.percentile(np.linalg.norm(uv - centre, axis=1), 90) / (0.5 * np.hypot(camera.width, camera.height)))
    if r < 0.3:
        return "none"
    if r < 0.55:
        return "k1"
    if r < 0.6:
        return "k1k2p1p2"
    return "full"


@dataclass(frozen=True, eq=False)
class RoiPrediction:
    """Predicted errors at the ROI evaluation points.

    ``px_lin``, ``px_extrap``, ``px_combined`` (M,) px per point;
    ``ground_cm_lin``, ``ground_cm_extrap``, ``ground_cm_combined`` (G,) cm on the
    ground points (``on_ground``, (M,) bool).
    """

    px_lin: np.ndarray
    px_extrap: np.ndarray
    px_combined: np.ndarray
    on_ground: np.ndarray
    ground_cm_lin: np.ndarray
    ground_cm_extrap: np.ndarray
    ground_cm_combined: np.ndarray
    n_samples: int
    model: str = "default"

    @property
    def combined_rms_px(self) -> float:
        return _rms(self.px_combined)

    def summary(self) -> dict:
        """JSON-ready figures (px over ROI points, cm over the ground part)."""
        return {
            "points": int(len(self.px_lin)), "ground_points": int(self.on_ground.sum()), "samples": self.n_samples, "model": self.model,
            "linearised_px": _stats(self.px_lin), "extrapolation_px": _stats(self.px_extrap), "combined_px": _stats(self.px_combined),
            "ground_linearised_cm": _stats(self.ground_cm_lin), "ground_extrapolation_cm": _stats(self.ground_cm_extrap),
            "ground_combined_cm": _stats(self.ground_cm_combined),
            "text": "projection error of the calibrated camera at the ROI points, px: linearised noise term (RTK + detection + timing), "
                    "model-extrapolation term (spread over plausible lenses of the guessed level), combined root-sum-square",
        }


def _rms(v: np.ndarray) -> float:
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    return float(np.sqrt(np.mean(v**2))) if v.size else float("nan")


def _stats(v: np.ndarray) -> dict:
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    if not v.size:
        return {"rms": None, "p95": None, "max": None}
    return {"rms": round(_rms(v), 4), "p95": round(float(np.percentile(v, 95)), 4), "max": round(float(v.max()), 4)}


def sample_sigmas(samples_sigma_h_m: np.ndarray, noise: NoiseModel, rtk_factor: np.ndarray | None = None) -> np.ndarray:
    """(S, 3) per-sample position std (m): RTK (times ``rtk_factor`` (S,), see
    ``sampling.design.Design``), with the timing term added in quadrature horizontally."""
    extra = np.asarray(samples_sigma_h_m, float)
    f = np.ones(len(extra)) if rtk_factor is None else np.asarray(rtk_factor, float)
    h = np.sqrt((noise.sigma_h_m * f) ** 2 + extra**2)
    return np.column_stack([h, h, noise.sigma_v_m * f])


def _ground_maps(camera: Camera, roi_points: np.ndarray, on_ground: np.ndarray) -> np.ndarray:
    """(G, 2, 2) maps from a pixel shift to the ground shift (m) of a fixed pixel, at the ground ROI points."""
    g = roi_points[on_ground]
    if not len(g):
        return np.zeros((0, 2, 2))
    _, _, Jx = project_batch_jacobians(*camera.batch_arrays(), g[None])
    Jg = Jx[0][:, :, :2]  # d(uv)/d(x, y) on the ground plane
    return np.linalg.pinv(Jg)


@dataclass(frozen=True, eq=False)
class _Linearisation:
    """What the noise term needs and no model changes, in the full 15-parameter space.

    ``JtJ`` = J^T J and ``JtSJ`` = J^T Sigma J (15, 15) over the samples (Sigma:
    each sample's image noise, its pixel noise plus its 3D noise pushed through
    the projection); a model's free parameters ``A`` (15, m) then only need
    A^T JtJ A and A^T JtSJ A. ``J_roi`` (M, 2, 15), ``ground_maps`` (G, 2, 2).
    """

    JtJ: np.ndarray
    JtSJ: np.ndarray
    J_roi: np.ndarray
    ground_maps: np.ndarray
    on_ground: np.ndarray  # (M,) bool


def _jacobians(camera: Camera, samples: np.ndarray, roi_points: np.ndarray, on_ground: np.ndarray) -> tuple:
    """Noise-independent pieces: sample Jacobians (u rows, v rows (S, 15), points (S, 2, 3)), J^T J, ROI Jacobians, ground maps."""
    P = np.asarray(samples, float)
    _, J, Jx = project_batch_jacobians(*camera.batch_arrays(), P[None])
    Ju, Jv = np.ascontiguousarray(J[0, :, 0]), np.ascontiguousarray(J[0, :, 1])  # (S, 15): the u and v rows
    _, Jr, _ = project_batch_jacobians(*camera.batch_arrays(), np.asarray(roi_points, float)[None], with_points=False)
    return Ju, Jv, Jx[0], Ju.T @ Ju + Jv.T @ Jv, Jr[0], _ground_maps(camera, roi_points, on_ground)


def _linearise(camera: Camera, samples: np.ndarray, sigma_3d: np.ndarray, sigma_2d: float, roi_points: np.ndarray,
               on_ground: np.ndarray, jac: tuple | None = None) -> _Linearisation:
    Ju, Jv, Jx, JtJ, Jr, G = _jacobians(camera, samples, roi_points, on_ground) if jac is None else jac
    s3 = np.broadcast_to(np.asarray(sigma_3d, float), (len(Ju), 3))
    B = (float(sigma_2d) ** 2) * np.eye(2)[None] + np.einsum("nij,nj,nkj->nik", Jx, s3**2, Jx)
    # sum_i J_i^T B_i J_i with the 2x2 blocks' entries: two BLAS products
    JtSJ = Ju.T @ (B[:, 0, 0, None] * Ju + B[:, 0, 1, None] * Jv) + Jv.T @ (B[:, 1, 0, None] * Ju + B[:, 1, 1, None] * Jv)
    return _Linearisation(JtJ=JtJ, JtSJ=JtSJ, J_roi=Jr, ground_maps=G, on_ground=np.asarray(on_ground, bool))


def _covariance(lin: _Linearisation, A: np.ndarray) -> np.ndarray:
    """(15, 15) (J^T J)^-1 J^T Sigma J (J^T J)^-1 over the free parameters ``A`` (15, m), mapped back."""
    JtJ_inv = np.linalg.pinv(A.T @ lin.JtJ @ A)
    return A @ (JtJ_inv @ (A.T @ lin.JtSJ @ A) @ JtJ_inv) @ A.T


def fast_parameter_covariance(camera: Camera, points: np.ndarray, sigma_3d: np.ndarray, sigma_2d: float, model: str) -> np.ndarray:
    """(15, 15) ``core.uncertainty.parameter_covariance`` with the sandwich as two matrix products.

    Same formula, (J^T J)^-1 J^T Sigma J (J^T J)^-1 with Sigma block-diagonal
    (pixel noise plus each point's 3D noise pushed through the projection); the
    middle term is J^T (Sigma J) as one BLAS product instead of a three-operand
    einsum, which is what makes thousands of leg samples affordable per candidate.
    """
    P = np.asarray(points, float)
    mdl = resolve_model(model, len(P))
    lin = _linearise(camera, P, sigma_3d, sigma_2d, P[:1], np.zeros(1, bool))
    return _covariance(lin, mdl.parameter_map(camera.intrinsics.fy / camera.intrinsics.fx))


def _roi_noise(camera: Camera, lin: _Linearisation, model: str, n_samples: int) -> tuple[np.ndarray, np.ndarray]:
    mdl = resolve_model(model, n_samples)
    cov = _covariance(lin, mdl.parameter_map(camera.intrinsics.fy / camera.intrinsics.fx))
    JC = lin.J_roi @ cov  # (M, 2, 15)
    C = np.einsum("mip,mjp->mij", JC, lin.J_roi)  # (M, 2, 2) pixel covariance
    px = np.sqrt(np.maximum(C[:, 0, 0] + C[:, 1, 1], 0.0))
    G = lin.ground_maps
    Cg = G @ C[lin.on_ground] @ G.transpose(0, 2, 1)
    cm = 100.0 * np.sqrt(np.maximum(Cg[:, 0, 0] + Cg[:, 1, 1], 0.0))
    return px, cm


def linearised_roi(camera: Camera, samples: np.ndarray, sigma_3d: np.ndarray, roi_points: np.ndarray, on_ground: np.ndarray,
                   noise: NoiseModel) -> tuple[np.ndarray, np.ndarray]:
    """Noise term: (M,) px and (G,) cm standard errors of the ROI projection, to first order.

    Parameters
    ----------
    camera : guessed camera (site frame)
    samples : (S, 3) marker centres of the samples, m
    sigma_3d : (S, 3) their position std, m
    roi_points : (M, 3) ROI evaluation points, m; ``on_ground`` (M,) bool
    """
    lin = _linearise(camera, samples, sigma_3d, noise.sigma_px, roi_points, on_ground)
    return _roi_noise(camera, lin, noise.model, len(samples))


def lens_draws(camera: Camera, nominal: np.ndarray, radius_needed: float, n: int = N_LENS_DRAWS, seed: int = 0) -> np.ndarray:
    """(n, 6) plausible lenses (k1, k2, p1, p2, k3, k4) around a guessed level's nominal coefficients.

    k1 within ±40 % of the nominal (±0.08 absolute when the nominal is 0),
    k2 nominal ± 0.08 (std), k3 ~ N(0, 0.03), p1, p2 ~ N(0, 5e-4), and an
    eighth-order radial term k4 ~ N(0, 0.01) that no model of ``calibrate``
    holds (real lenses are not exactly Brown-Conrady, so even the full model
    extrapolates). A draw whose radial map folds (slope 5 %) inside
    ``radius_needed`` (the normalised radius of the ROI's farthest point from
    the axis) is drawn again: no real lens shows the ROI folded.
    """
    rng = np.random.default_rng(seed)
    nominal = np.asarray(nominal, float)
    r = np.linspace(0.0, 1.02 * radius_needed, 400)
    out: list[np.ndarray] = []
    tries = 0
    while len(out) < n and tries < 50 * n:
        tries += 1
        k1 = nominal[0] * rng.uniform(0.6, 1.4) if abs(nominal[0]) > 1e-6 else rng.normal(0.0, 0.08)
        d = np.array([k1, nominal[1] + rng.normal(0.0, 0.08), nominal[2] + rng.normal(0.0, 5e-4),
                      nominal[3] + rng.normal(0.0, 5e-4), nominal[4] + rng.normal(0.0, 0.03), rng.normal(0.0, 0.01)])
        r2 = r * r
        slope = 1.0 + 3.0 * d[0] * r2 + 5.0 * d[1] * r2**2 + 7.0 * d[4] * r2**3 + 9.0 * d[5] * r2**4
        if np.all(slope > PLAN_FOLD_MIN_SLOPE):
            out.append(d)
    if not out:  # the level itself folds inside the ROI: keep the nominal only
        out.append(np.append(nominal, 0.0))
    return np.asarray(out)


def project_k4(camera: Camera, lenses: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(D, N, 2) pixels of points (N, 3) through ``camera`` with each lens (D, 6) (Brown-Conrady + k4 r^8)."""
    Xc = points @ camera.pose.R_cam_from_world.T + camera.pose.t_cam_from_world
    x = (Xc[:, 0] / Xc[:, 2])[None]
    y = (Xc[:, 1] / Xc[:, 2])[None]
    k1, k2, p1, p2, k3, k4 = (lenses[:, i : i + 1] for i in range(6))
    r2 = x * x + y * y
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * (k3 + r2 * k4)))
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    i = camera.intrinsics
    return np.stack([i.fx * xd + i.cx, i.fy * yd + i.cy], -1)


def normalised_radius(camera: Camera, points: np.ndarray) -> np.ndarray:
    """(N,) radius of points (N, 3) on the camera's z = 1 plane (undistorted)."""
    Xc = points @ camera.pose.R_cam_from_world.T + camera.pose.t_cam_from_world
    z = np.maximum(Xc[:, 2], 1e-6)
    return np.hypot(Xc[:, 0] / z, Xc[:, 1] / z)


def extrapolation_roi(camera: Camera, samples: np.ndarray, roi_points: np.ndarray, on_ground: np.ndarray, draws: np.ndarray,
                      model: str = "default") -> tuple[np.ndarray, np.ndarray]:
    """Model-extrapolation term: (M,) px and (G,) cm RMS over lens draws of (fit - draw) at the ROI points.

    For each draw (D, 6) the samples (S, 3) are projected through the camera
    with that lens, ``model`` is fitted to those exact pixels (batched
    Levenberg-Marquardt from the draw, so only what the model cannot express
    or the samples cannot pin moves), and the ROI points are projected
    through both.
    """
    S = np.asarray(samples, float)
    if len(S) > MAX_FIT_POINTS:
        S = S[np.linspace(0, len(S) - 1, MAX_FIT_POINTS).round().astype(int)]
    draws = np.asarray(draws, float)
    D = len(draws)
    pix = project_k4(camera, draws, S)
    mdl = resolve_model(model, len(S))
    A = mdl.parameter_map(camera.intrinsics.fy / camera.intrinsics.fx)
    start = BatchState.from_camera(camera, D)
    start.distortion[:] = draws[:, :5]
    for name, i in {"k1": 0, "k2": 1, "p1": 2, "p2": 3, "k3": 4}.items():
        if name not in mdl.free_names():
            start.distortion[:, i] = 0.0  # the fit cannot hold it: it starts (and stays) at 0
    fit, _, _ = levenberg_marquardt(start, S[None], pix, A, max_iterations=30, tolerance=1e-8)
    uv_true = project_k4(camera, draws, roi_points)
    uv_fit = project_batch(fit.intrinsics, fit.distortion, fit.R, fit.t, roi_points[None])
    diff = uv_fit - uv_true  # (D, M, 2)
    ok = np.all(np.isfinite(diff), axis=(0, 2))
    px = np.full(len(roi_points), np.nan)
    px[ok] = np.sqrt(np.mean(np.sum(diff[:, ok] ** 2, axis=2), axis=0))
    G = _ground_maps(camera, roi_points, on_ground)
    dg = np.einsum("gij,dgj->dgi", G, diff[:, on_ground])
    cm = 100.0 * np.sqrt(np.mean(np.sum(dg**2, axis=2), axis=0))
    return px, cm


def predict_roi(camera: Camera, samples: np.ndarray, samples_sigma_h_m: np.ndarray, roi_points: np.ndarray, on_ground: np.ndarray,
                noise: NoiseModel, draws: np.ndarray | None, rtk_factor: np.ndarray | None = None,
                extrap_cache: dict | None = None, cache_key: object = None) -> RoiPrediction:
    """Both terms and their root-sum-square at the ROI points (see the module docstring).

    The model is the one ``calibrate --model auto`` would fit (:func:`prediction_model`);
    when that allows the full model, k1k2p1p2 is scored too and the lower
    combined error is kept (``calibrate`` frees k3 only when the data support it).

    ``draws`` None leaves the extrapolation term out (zeros): only for tests
    of the noise term. ``extrap_cache`` (a dict) with ``cache_key`` reuses the
    extrapolation term of candidates with the same samples (the term is
    noise-free: it depends on the sample positions only).
    """
    s3 = sample_sigmas(samples_sigma_h_m, noise, rtk_factor)
    cap = prediction_model(camera, samples, roi_points, noise.model)
    # calibrate tries the models up to the cap and keeps a richer one only when the data support it:
    # with the full model allowed, both it and k1k2p1p2 are scored and the better prediction is the expected fit
    models = [cap, "k1k2p1p2"] if (noise.model == "auto" and cap == "full") else [cap]
    best = None
    jac = None
    if extrap_cache is not None:  # candidates with the same samples (through / mixed) share the Jacobians
        jac = extrap_cache.get((cache_key, "jacobians"))
        if jac is None:
            jac = extrap_cache[(cache_key, "jacobians")] = _jacobians(camera, samples, roi_points, on_ground)
    lin = _linearise(camera, samples, s3, noise.sigma_px, roi_points, on_ground, jac)
    for model in models:
        px_lin, cm_lin = _roi_noise(camera, lin, model, len(samples))
        if draws is None:
            px_ex, cm_ex = np.zeros_like(px_lin), np.zeros_like(cm_lin)
        elif extrap_cache is not None and (cache_key, model) in extrap_cache:
            px_ex, cm_ex = extrap_cache[(cache_key, model)]
        else:
            px_ex, cm_ex = extrapolation_roi(camera, samples, roi_points, on_ground, draws, model)
            if extrap_cache is not None:
                extrap_cache[(cache_key, model)] = (px_ex, cm_ex)
        score = _rms(np.hypot(px_lin, px_ex))
        if best is None or score < best[0]:
            best = (score, model, px_lin, cm_lin, px_ex, cm_ex)
    _, model, px_lin, cm_lin, px_ex, cm_ex = best
    return RoiPrediction(px_lin=px_lin, px_extrap=px_ex, px_combined=np.hypot(px_lin, px_ex), on_ground=np.asarray(on_ground, bool),
                         ground_cm_lin=cm_lin, ground_cm_extrap=cm_ex, ground_cm_combined=np.hypot(cm_lin, cm_ex), n_samples=int(len(samples)), model=model)
