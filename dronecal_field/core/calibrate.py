"""Calibration from non-coplanar 3D-2D pairs: normalised DLT -> RQ -> Levenberg-Marquardt.

Pure numerical core. The solver is batched over a leading axis of K problems
(same point count, same model) so the Monte-Carlo runs all its trials in one
vectorised loop; a single calibration is K = 1. Parameters and the rotation
perturbation follow docs/conventions.md.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from dronecal_field.core.camera import (
    N_PARAMS,
    PARAM_NAMES,
    Camera,
    project_batch,
    project_batch_jacobians,
    rotation_from_vector,
)
from dronecal_field.errors import CalibrationError, DegenerateGeometryError, InputError

DISTORTION_MODELS: dict[str, tuple[str, ...]] = {
    "none": (),
    "k1": ("k1",),
    "k1k2": ("k1", "k2"),
    "k1k2p1p2": ("k1", "k2", "p1", "p2"),
    "full": ("k1", "k2", "p1", "p2", "k3"),
}


@dataclass(frozen=True)
class CalibrationModel:
    """Which parameters are free.

    ``distortion`` names a model of DISTORTION_MODELS; ``fix_aspect_ratio``
    keeps fy/fx at its initial value (OpenCV's CALIB_FIX_ASPECT_RATIO);
    ``fix_principal_point`` keeps (cx, cy) at the initial value (image centre
    when starting from DLT). The pose is always free.
    """

    distortion: str = "k1k2p1p2"
    fix_aspect_ratio: bool = False
    fix_principal_point: bool = False
    # Set on the model of a calibration's result (``calibrate``): the model was fitted to data,
    # so its uncertainty figures carry the model term (``core.uncertainty.linearised``). Not part
    # of the name or of equality: the same parameters are free.
    fitted: bool = field(default=False, compare=False)

    def __post_init__(self) -> None:
        if self.distortion not in DISTORTION_MODELS:
            raise InputError(
                f"unknown distortion model {self.distortion!r}: use one of {', '.join(DISTORTION_MODELS)}"
            )

    @property
    def name(self) -> str:
        parts = [self.distortion]
        if self.fix_aspect_ratio:
            parts.append("fixed-aspect")
        if self.fix_principal_point:
            parts.append("fixed-pp")
        return "+".join(parts)

    def free_names(self) -> tuple[str, ...]:
        names = ["fx"] if self.fix_aspect_ratio else ["fx", "fy"]
        if not self.fix_principal_point:
            names += ["cx", "cy"]
        names += list(DISTORTION_MODELS[self.distortion])
        names += ["wx", "wy", "wz", "tx", "ty", "tz"]
        return tuple(names)

    @property
    def n_free(self) -> int:
        return len(self.free_names())

    def parameter_map(self, aspect: float = 1.0) -> np.ndarray:
        """(15, m) matrix A: a step of the free parameters d moves the full vector by A @ d."""
        free = self.free_names()
        A = np.zeros((N_PARAMS, len(free)))
        for j, name in enumerate(free):
            A[PARAM_NAMES.index(name), j] = 1.0
            if name == "fx" and self.fix_aspect_ratio:
                A[PARAM_NAMES.index("fy"), j] = aspect
        return A


# Next richer model in the family ``auto`` climbs; k3 last (it needs the corners).
_RICHER = {"none": "k1", "k1": "k1k2", "k1k2": "k1k2p1p2", "k1k2p1p2": "full"}


def richer_model(model: CalibrationModel) -> CalibrationModel | None:
    """The next model up from ``model`` (k1 -> k1k2 -> k1k2p1p2 -> full -> free aspect), None at the top."""
    nxt = _RICHER.get(model.distortion)
    if nxt is not None:
        return replace(model, distortion=nxt)
    if model.fix_aspect_ratio:
        return replace(model, fix_aspect_ratio=False)
    return None


def resolve_model(model: "str | CalibrationModel", n_points: int) -> CalibrationModel:
    """A CalibrationModel from a name ('auto', 'default', a distortion model name) or itself.

    'auto' picks the richest distortion model the point count supports with
    at least 2 observations (one point) per free parameter; 'default' is fx, fy, cx, cy,
    k1, k2, p1, p2 free with k3 fixed at 0 (OpenCV's CALIB_FIX_K3).
    """
    if isinstance(model, CalibrationModel):
        return model
    if model == "default":
        return CalibrationModel(distortion="k1k2p1p2")
    if model == "auto":
        for name in ("k1k2p1p2", "k1k2", "k1", "none"):
            candidate = CalibrationModel(distortion=name)
            if n_points >= candidate.n_free:
                return candidate
        return CalibrationModel(distortion="none", fix_aspect_ratio=True, fix_principal_point=True)
    return CalibrationModel(distortion=model)


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """A calibrated camera with its uncertainty and the evidence for it.

    ``camera.covariance`` is the (15, 15) covariance (fixed parameters have
    zero variance), from the Jacobian at the solution scaled by the residual
    variance. ``residuals_px`` (N, 2) are observed minus predicted pixels.
    ``outliers`` are indices whose residual exceeds 3 robust sigmas (and the
    loss scale) when a robust loss was used.
    """

    camera: Camera
    model: CalibrationModel
    rms_px: float
    residuals_px: np.ndarray
    outliers: tuple[int, ...]
    iterations: int
    residual_sigma_px: float
    points_world: np.ndarray = field(repr=False)
    pixels: np.ndarray = field(repr=False)
    loss: str = "linear"

    @property
    def parameter_std(self) -> dict[str, float]:
        cov = self.camera.covariance
        return {name: float(np.sqrt(max(cov[i, i], 0.0))) for i, name in enumerate(PARAM_NAMES)}


# --------------------------------------------------------------------------
# Input checks


def check_correspondences(points_world: np.ndarray, pixels: np.ndarray, n_free: int, min_thickness_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Validate shapes, finiteness and geometry; returns float arrays (N, 3), (N, 2)."""
    X = np.asarray(points_world, dtype=float)
    uv = np.asarray(pixels, dtype=float)
    if X.ndim != 2 or X.shape[1] != 3 or uv.ndim != 2 or uv.shape[1] != 2 or X.shape[0] != uv.shape[0]:
        raise InputError(
            f"need matching arrays of 3D points (N, 3) and pixels (N, 2), got {X.shape} and {uv.shape}"
        )
    bad = ~(np.all(np.isfinite(X), axis=1) & np.all(np.isfinite(uv), axis=1))
    if bad.any():
        idx = ", ".join(str(i) for i in np.flatnonzero(bad)[:5])
        raise InputError(f"{int(bad.sum())} correspondence(s) hold NaN or inf (index {idx}): drop or re-measure them")
    n = X.shape[0]
    needed = max(6, (n_free + 1) // 2 + 1)
    if n < needed:
        raise DegenerateGeometryError(
            f"{n} points cannot determine {n_free} parameters: need at least {needed} (fly more waypoints or choose a simpler --model)"
        )
    s = np.linalg.svd(X - X.mean(axis=0), compute_uv=False) / np.sqrt(n)
    if s[1] < 1e-3 * max(s[0], 1e-12) or s[1] < min_thickness_m:
        raise DegenerateGeometryError(
            f"the {n} points are collinear (spread {s[1] * 100:.1f} cm across the line): sample a grid in several planes"
        )
    if s[2] < min_thickness_m:
        raise DegenerateGeometryError(
            f"the {n} points are coplanar (RMS {s[2] * 100:.1f} cm off one plane): fly at least two heights, "
            f"or several distances, at least {min_thickness_m * 200:.0f} cm apart"
        )
    off = _points_off_main_plane(X, min_thickness_m)
    needed_off = max(3, int(np.ceil(0.1 * n)))
    if off < needed_off:
        raise DegenerateGeometryError(
            f"{n - off} of the {n} points lie in one plane and only {off} off it (need {needed_off}): "
            "fly a second height or distance with several waypoints"
        )
    return X, uv


def _points_off_main_plane(X: np.ndarray, min_thickness_m: float) -> int:
    """How many points lie farther than ``min_thickness_m`` from the plane most points share.

    The plane is fitted robustly (least squares, then refitted on the points
    within 3 MADs of it), so a single high point cannot make a flat grid look 3D.
    """
    inliers = np.ones(len(X), dtype=bool)
    for _ in range(3):
        c = X[inliers].mean(axis=0)
        normal = np.linalg.svd(X[inliers] - c, full_matrices=False)[2][-1]  # O(N) memory: no N x N U
        d = (X - c) @ normal
        med = np.median(d)
        mad = 1.4826 * np.median(np.abs(d - med))
        new = np.abs(d - med) <= max(3.0 * mad, min_thickness_m)
        if new.sum() < 3 or np.array_equal(new, inliers):
            break
        inliers = new
    return int(np.sum(np.abs(d) > min_thickness_m))


# --------------------------------------------------------------------------
# DLT


def _normalisation(points: np.ndarray) -> np.ndarray:
    """Hartley similarity (d+1, d+1) moving the centroid to 0 and the mean distance to sqrt(d)."""
    d = points.shape[1]
    c = points.mean(axis=0)
    scale = np.sqrt(d) / max(np.mean(np.linalg.norm(points - c, axis=1)), 1e-12)
    T = np.eye(d + 1)
    T[:d, :d] *= scale
    T[:d, d] = -scale * c
    return T


def dlt(points_world: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """(3, 4) projection matrix by the normalised DLT, scaled so det(P[:, :3]) > 0."""
    n = points_world.shape[0]
    T3 = _normalisation(points_world)
    T2 = _normalisation(pixels)
    Xh = (T3 @ np.c_[points_world, np.ones(n)].T).T
    uh = (T2 @ np.c_[pixels, np.ones(n)].T).T
    A = np.zeros((2 * n, 12))
    A[0::2, 0:4] = Xh
    A[0::2, 8:12] = -uh[:, 0:1] * Xh
    A[1::2, 4:8] = Xh
    A[1::2, 8:12] = -uh[:, 1:2] * Xh
    _, _, vt = np.linalg.svd(A, full_matrices=False)  # (2N, 12): O(N) memory
    P = np.linalg.inv(T2) @ vt[-1].reshape(3, 4) @ T3
    if np.linalg.det(P[:, :3]) < 0:
        P = -P
    return P


def decompose_projection(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """K (3, 3), R (3, 3), t (3,) with P ~ K [R | t], K upper triangular with positive diagonal."""
    from scipy.linalg import rq

    M = P[:, :3]
    K, R = rq(M)
    S = np.diag(np.sign(np.diag(K)))
    K, R = K @ S, S @ R
    if np.linalg.det(R) < 0:  # cannot happen when det(M) > 0, kept for safety
        R = -R
        K = -K
    t = np.linalg.solve(K, P[:, 3])  # K carries P's scale, so t needs none
    return K / K[2, 2], R, t


# --------------------------------------------------------------------------
# Batched Levenberg-Marquardt


@dataclass
class BatchState:
    """K camera estimates: intrinsics (K, 4), distortion (K, 5), R (K, 3, 3), t (K, 3)."""

    intrinsics: np.ndarray
    distortion: np.ndarray
    R: np.ndarray
    t: np.ndarray

    def copy(self) -> "BatchState":
        return BatchState(self.intrinsics.copy(), self.distortion.copy(), self.R.copy(), self.t.copy())

    def stepped(self, delta_full: np.ndarray) -> "BatchState":
        """A new state moved by (K, 15) full-parameter steps."""
        return BatchState(
            self.intrinsics + delta_full[:, 0:4],
            self.distortion + delta_full[:, 4:9],
            rotation_from_vector(delta_full[:, 9:12]) @ self.R,
            self.t + delta_full[:, 12:15],
        )

    def take(self, idx: np.ndarray) -> "BatchState":
        return BatchState(self.intrinsics[idx], self.distortion[idx], self.R[idx], self.t[idx])

    def put(self, idx: np.ndarray, other: "BatchState") -> None:
        self.intrinsics[idx] = other.intrinsics
        self.distortion[idx] = other.distortion
        self.R[idx] = other.R
        self.t[idx] = other.t

    @classmethod
    def from_camera(cls, camera: Camera, k: int = 1) -> "BatchState":
        i, d, R, t = camera.batch_arrays()
        return cls(np.repeat(i, k, 0), np.repeat(d, k, 0), np.repeat(R, k, 0), np.repeat(t, k, 0))


def _free_columns(A: np.ndarray) -> tuple[np.ndarray, int, float]:
    """The kernel's view of a parameter map: primary index per free column, tied fx column, aspect."""
    m = A.shape[1]
    sel = np.array([int(np.flatnonzero(A[:, j])[0]) for j in range(m)], dtype=np.int64)
    fx_col, aspect = -1, 0.0
    fy_index = PARAM_NAMES.index("fy")
    for j in range(m):
        if sel[j] == 0 and A[fy_index, j] != 0.0:
            fx_col, aspect = j, float(A[fy_index, j])
    return sel, fx_col, aspect


def levenberg_marquardt(
    state: BatchState,
    points: np.ndarray,  # (K, N, 3) or (1, N, 3)
    pixels: np.ndarray,  # (K, N, 2)
    A: np.ndarray,  # (15, m)
    max_iterations: int = 50,
    tolerance: float = 1e-12,
    loss: str = "linear",
    loss_scale: float = 2.0,
) -> tuple[BatchState, np.ndarray, int]:
    """Minimise the (robustified) reprojection error of K problems at once.

    Each problem runs its own Levenberg-Marquardt (Marquardt's diagonal
    scaling) in compiled code, in parallel over numba's threads, and stops
    when its relative cost decrease falls below ``tolerance`` or several steps
    in a row fail (at a minimum, round-off). Robust losses are iteratively
    reweighted; a step is judged with the weights it was computed with, so
    reweighting cannot fake progress.

    Returns the refined state, the per-problem cost (K,) (sum of squared
    residuals, unweighted) and the largest iteration count.
    """
    from dronecal_field.core.kernels import LOSS_CODES, announce_compile_once, solve_batch

    announce_compile_once()

    if loss not in LOSS_CODES:
        raise InputError(f"unknown loss {loss!r}: use linear, huber or cauchy")
    out = state.copy()
    K = out.R.shape[0]
    sel, fx_col, aspect = _free_columns(A)
    cost = np.empty(K)
    iterations = np.empty(K, dtype=np.int64)
    solve_batch(
        out.intrinsics, out.distortion, out.R, out.t,
        np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(pixels, dtype=float),
        np.ascontiguousarray(A, dtype=float), sel, fx_col, aspect,
        int(max_iterations), float(tolerance), LOSS_CODES[loss], float(loss_scale), cost, iterations,
    )
    return out, cost, int(iterations.max(initial=0))


def _loss_weight(sq: np.ndarray, loss: str, scale: float) -> np.ndarray:
    """The robust loss's IRLS weight of each squared residual (kernels._weight, vectorised)."""
    if loss == "linear":
        return np.ones_like(sq)
    r = np.sqrt(sq) / scale
    if loss == "huber":
        return np.where(r <= 1.0, 1.0, 1.0 / np.maximum(r, 1e-12))
    return 1.0 / (1.0 + r * r)


def weighted_levenberg_marquardt(
    state: BatchState,
    points: np.ndarray,  # (N, 3)
    pixels: np.ndarray,  # (N, 2)
    prior: np.ndarray,  # (N,) 1 / sigma^2 of each point, mean 1 (pixels of the typical point)
    A: np.ndarray,  # (15, m)
    max_iterations: int = 50,
    tolerance: float = 1e-12,
    loss: str = "linear",
    loss_scale: float = 2.0,
) -> tuple[BatchState, float, int]:
    """One problem's Levenberg-Marquardt with a weight per point (numpy; the compiled kernel has none).

    The same iteration as kernels._solve_one (Marquardt's diagonal scaling, a
    step judged with the weights it was computed with, four failures in a row
    at a minimum): only calibrations of pooled runs come here, once each, so
    the Python loop costs milliseconds; the unweighted path stays compiled.
    The robust loss sees the whitened residual (prior * squared residual), so a
    noisier run's points are not taken for outliers of a quieter one.
    Returns the refined state, the unweighted cost and the iteration count.
    """
    if loss not in ("linear", "huber", "cauchy"):
        raise InputError(f"unknown loss {loss!r}: use linear, huber or cauchy")
    out = state.copy()
    X = points[None]

    def residuals(s: BatchState) -> np.ndarray:
        return pixels - project_batch(s.intrinsics, s.distortion, s.R, s.t, X)[0]

    def normal(s: BatchState, w: np.ndarray):
        uv, J, _ = project_batch_jacobians(s.intrinsics, s.distortion, s.R, s.t, X, with_points=False)
        r = pixels - uv[0]
        Jm = J[0] @ A  # (N, 2, m)
        sw = np.sqrt(w)[:, None, None]
        Jw = (Jm * sw).reshape(-1, A.shape[1])
        rw = (r * sw[:, :, 0]).reshape(-1)
        return Jw.T @ Jw, Jw.T @ rw, np.sum(r * r, axis=1)

    sq = np.sum(residuals(out) ** 2, axis=1)
    w = prior * _loss_weight(prior * sq, loss, loss_scale)
    JtJ, g, sq = normal(out, w)
    cost = float(np.sum(w * sq))
    lam, fails, it = 1e-3, 0, 0
    for it in range(1, max_iterations + 1):
        H = JtJ + lam * np.diag(np.maximum(np.diag(JtJ), 1e-12))
        cost_t = np.inf
        try:
            delta = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            delta = None
        if delta is not None and np.all(np.isfinite(delta)):
            trial = out.stepped((A @ delta)[None])
            sq_t = np.sum(residuals(trial) ** 2, axis=1)
            cost_t = float(np.sum(w * sq_t))
        if np.isfinite(cost_t) and cost_t < cost:
            rel = (cost - cost_t) / max(cost, 1e-300)
            out, sq, cost = trial, sq_t, cost_t
            lam, fails = max(lam / 10.0, 1e-9), 0
            if rel < tolerance or cost <= 1e-24:
                break
            w = prior * _loss_weight(prior * sq, loss, loss_scale)
            JtJ, g, sq = normal(out, w)
            cost = float(np.sum(w * sq))
        else:
            lam *= 10.0
            fails += 1
            if fails >= 4 or lam > 1e10:
                break
    return out, float(np.sum(sq)), it


def _prior_weights(sigma_px, n: int) -> np.ndarray | None:
    """1 / sigma^2 per point scaled to mean 1 (None: every point alike), or InputError naming the problem."""
    if sigma_px is None:
        return None
    s = np.broadcast_to(np.asarray(sigma_px, dtype=float), (n,))
    if not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise InputError("every point's sigma_px must be a positive finite number of pixels: drop the point or give its noise")
    p = 1.0 / (s * s)
    return p / p.mean()


# --------------------------------------------------------------------------
# Single calibration


def initial_camera(points_world: np.ndarray, pixels: np.ndarray, width: int, height: int) -> Camera:
    """Pinhole camera (no distortion) from the normalised DLT and an RQ decomposition."""
    P = dlt(points_world, pixels)
    K, R, t = decompose_projection(P)
    depth = points_world @ R.T + t
    behind = depth[:, 2] <= 0
    if behind.any():
        if behind.all():
            raise DegenerateGeometryError("all points project from behind the camera: check the 3D-2D pairing and the world frame")
        raise DegenerateGeometryError(
            f"{int(behind.sum())} of {len(behind)} points lie behind the camera (index {int(np.flatnonzero(behind)[0])}): "
            "a 3D point is paired with the wrong pixel or the frame is mirrored"
        )
    f = np.array([abs(K[0, 0]), abs(K[1, 1]), K[0, 2], K[1, 2]])
    if not np.all(np.isfinite(f)) or f[0] <= 0 or f[1] <= 0:
        raise CalibrationError("the DLT gave no finite camera: the 3D-2D pairs are inconsistent")
    return Camera.from_arrays(f, np.zeros(5), R, t, width, height)


def calibrate(
    points_world: np.ndarray,
    pixels: np.ndarray,
    width: int,
    height: int,
    model: "str | CalibrationModel" = "auto",
    loss: str = "linear",
    loss_scale_px: float = 2.0,
    initial: Camera | None = None,
    min_thickness_m: float = 0.05,
    max_iterations: int = 200,
    sigma_px: "np.ndarray | None" = None,
) -> CalibrationResult:
    """Calibrate a camera from non-coplanar 3D-2D pairs; no initial guess needed.

    Parameters
    ----------
    points_world : (N, 3) world points, metres (any right-handed metric frame)
    pixels : (N, 2) observed pixels
    width, height : image size, pixels
    model : 'auto', 'default', 'none', 'k1', 'k1k2', 'k1k2p1p2', 'full' or a CalibrationModel
    loss : 'linear', 'huber' or 'cauchy'; robust losses downweight outliers beyond ``loss_scale_px``
    initial : start from this camera instead of the DLT (fixed parameters keep its values)
    min_thickness_m : RMS distance from the best plane below which the points count as coplanar
    sigma_px : (N,) each point's noise, pixels (pooled runs of different noise): the fit weights each point by
        1 / sigma^2 and the covariance follows; None (the default) weights every point alike (the compiled path)

    Raises
    ------
    InputError, DegenerateGeometryError, CalibrationError with a one-line reason.

    Examples
    --------
    >>> result = calibrate(points, pixels, 1280, 960, model="default")
    >>> result.camera.intrinsics.fx, result.rms_px
    """
    n = np.asarray(points_world).shape[0] if np.ndim(points_world) == 2 else 0
    mdl = resolve_model(model, n)
    X, uv = check_correspondences(points_world, pixels, mdl.n_free, min_thickness_m)
    prior = _prior_weights(sigma_px, X.shape[0])
    if prior is not None:
        return _calibrate_weighted(X, uv, width, height, mdl, loss, loss_scale_px, initial, max_iterations, prior)
    if initial is None:
        cam0 = initial_camera(X, uv, width, height)
        i = cam0.intrinsics
        f0 = np.array([i.fx, i.fy, i.cx, i.cy])
        if mdl.fix_aspect_ratio:  # square pixels unless an initial camera says otherwise
            f0[:2] = np.sqrt(i.fx * i.fy)
        if mdl.fix_principal_point:
            f0[2:] = (width - 1) / 2.0, (height - 1) / 2.0
        cam0 = Camera.from_arrays(f0, np.zeros(5), cam0.pose.R_cam_from_world, cam0.pose.t_cam_from_world, width, height)
        # pinhole first: the distortion terms are only meaningful near the right pose
        pin = CalibrationModel(distortion="none", fix_aspect_ratio=mdl.fix_aspect_ratio, fix_principal_point=mdl.fix_principal_point)
        state = BatchState.from_camera(cam0)
        state, _, _ = levenberg_marquardt(state, X[None], uv[None], pin.parameter_map(cam0.intrinsics.fy / cam0.intrinsics.fx), max_iterations=max_iterations, loss=loss, loss_scale=loss_scale_px)
    else:
        state = BatchState.from_camera(initial)
    aspect = float(state.intrinsics[0, 1] / state.intrinsics[0, 0])
    A = mdl.parameter_map(aspect)
    state, _, iters = levenberg_marquardt(state, X[None], uv[None], A, max_iterations=max_iterations, loss=loss, loss_scale=loss_scale_px)
    return _result_from_state(state, X, uv, width, height, mdl, A, iters, loss, loss_scale_px, initial)


def _calibrate_weighted(X, uv, width, height, mdl, loss, loss_scale_px, initial, max_iterations, prior) -> CalibrationResult:
    """``calibrate`` with a weight per point: the unweighted compiled solve starts it, the weighted one finishes."""
    start = initial
    if start is None:  # DLT + unweighted fit (the compiled path) is a start near the weighted minimum
        start = calibrate(X, uv, width, height, model=mdl, loss=loss, loss_scale_px=loss_scale_px, min_thickness_m=0.0,
                          max_iterations=max_iterations).camera
    state = BatchState.from_camera(start)
    aspect = float(state.intrinsics[0, 1] / state.intrinsics[0, 0])
    A = mdl.parameter_map(aspect)
    state, _, iters = weighted_levenberg_marquardt(state, X, uv, prior, A, max_iterations=max_iterations, loss=loss, loss_scale=loss_scale_px)
    return _result_from_state(state, X, uv, width, height, mdl, A, iters, loss, loss_scale_px, initial, prior)


def _result_from_state(state, X, uv, width, height, mdl, A, iters, loss, loss_scale_px, initial, prior=None) -> CalibrationResult:
    uv_hat, J, _ = project_batch_jacobians(state.intrinsics, state.distortion, state.R, state.t, X[None])
    depth = np.einsum("ij,nj->ni", state.R[0], X) + state.t[0]
    if np.any(depth[:, 2] <= 0) or not np.all(np.isfinite(uv_hat)):
        raise CalibrationError("the solver converged to a camera with points behind it: check the 3D-2D pairs or give --model none")
    if state.intrinsics[0, 0] <= 0 or state.intrinsics[0, 1] <= 0:
        raise CalibrationError("the solver reached a negative focal length: the 3D-2D pairs are inconsistent")
    res = uv - uv_hat[0]
    n = X.shape[0]
    m = A.shape[1]
    sq = np.sum(res * res, axis=1)
    outliers: tuple[int, ...] = ()
    inlier = np.ones(n, dtype=bool)
    if loss != "linear":
        norm = np.sqrt(sq if prior is None else prior * sq)  # weighted: outliers of their own run's noise
        robust_sigma = 1.4826 * np.median(norm) + 1e-12
        out = (norm > 3.0 * robust_sigma) & (norm > loss_scale_px)
        outliers = tuple(int(i) for i in np.flatnonzero(out))
        inlier = ~out
    dof = max(2 * int(inlier.sum()) - m, 1)
    if prior is None:
        sigma2 = float(np.sum(sq[inlier]) / dof)
        Jm = (J[0][inlier] @ A).reshape(-1, m)
    else:  # the typical point's variance (prior has mean 1) and J^T W J: cov = sigma2 (J^T W J)^-1
        sigma2 = float(np.sum((prior * sq)[inlier]) / dof)
        Jm = ((J[0][inlier] @ A) * np.sqrt(prior[inlier])[:, None, None]).reshape(-1, m)
    JtJ = Jm.T @ Jm
    try:
        cov_free = sigma2 * np.linalg.inv(JtJ)
    except np.linalg.LinAlgError:
        raise CalibrationError("the calibration is not determined by these points (singular normal matrix): sample more of the image and more depths") from None
    cov = A @ cov_free @ A.T
    enu_origin = initial.enu_origin if initial is not None else None
    camera = Camera.from_arrays(state.intrinsics[0], state.distortion[0], state.R[0], state.t[0], width, height, enu_origin=enu_origin, covariance=cov)
    return CalibrationResult(
        camera=camera,
        model=replace(mdl, fitted=True),
        rms_px=float(np.sqrt(np.mean(sq))),
        residuals_px=res,
        outliers=outliers,
        iterations=iters,
        residual_sigma_px=float(np.sqrt(sigma2 / 2.0)),
        points_world=X,
        pixels=uv,
        loss=loss,
    )


def reprojection_rms(camera: Camera, points_world: np.ndarray, pixels: np.ndarray) -> float:
    """RMS reprojection error (px) of pixels (N, 2) against world points (N, 3)."""
    uv = project_batch(*camera.batch_arrays(), np.asarray(points_world, float)[None])[0]
    return float(np.sqrt(np.mean(np.sum((np.asarray(pixels) - uv) ** 2, axis=1))))
