"""Calibration uncertainty: the paper's Monte-Carlo (section II.B), batched, and its linearised twin.

For k trials, every 3D point is perturbed with N(0, diag(sigma_3d^2)) and
every 2D point with N(0, sigma_2d^2); the camera is re-estimated and
E(C), the RMS reprojection error over that trial's perturbed points (what
``cv2.calibrateCamera`` returns), is stored. Each chunk of trials is solved
in one compiled pass (``core.kernels.monte_carlo_trials``: the
Levenberg-Marquardt of ``core.calibrate.levenberg_marquardt``, warm-started
at the reference camera, parallel over trials), which also scores every
estimate against the reference. Chunks keep memory bounded for any k.

Beyond the paper, the same trials give the spread of every parameter and the
*projection error*: how far each estimated camera projects world points from
where the reference camera does (pixels, over the sampled volume and over
the ground), and what that means on the ground 15 m out (position error in
cm, speed error in km/h). The RMS reprojection error alone rewards
overfitting; the projection error does not.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dronecal_field.core.calibrate import BatchState, CalibrationModel, _free_columns, resolve_model, richer_model
from dronecal_field.core.camera import (
    PARAM_NAMES,
    Camera,
    intersect_plane_z,
    project_batch,
    project_batch_jacobians,
    vector_from_rotation,
)
from dronecal_field.errors import InputError

DEFAULT_SIGMA_3D = (0.01, 0.01, 0.015)
DEFAULT_SIGMA_2D = 2.0
GROUND_DISTANCE_M = 15.0
VEHICLE_SPEED_KMH = 50.0
SPEED_BASE_S = 0.5  # a speed camera measures displacement over about half a second


@dataclass(frozen=True)
class GroundProbe:
    """Ground points 15 m out along the camera's heading, for user-facing error figures.

    ``point`` (3,) lies on the ground plane at horizontal distance 15 m from
    the camera along its heading; ``track`` (2, 3) are a vehicle's positions
    ``SPEED_BASE_S`` apart at 50 km/h driving along the line of sight, centred
    on ``point``.
    """

    point: np.ndarray
    track: np.ndarray


def ground_probe(camera: Camera, ground_z: float = 0.0, distance_m: float = GROUND_DISTANCE_M) -> GroundProbe:
    """The ground probe of ``camera`` (its optical axis projected on the ground plane gives the heading)."""
    # on Python floats: a dozen numpy calls on 3-vectors cost 0.4 ms when the interpreter's caches are cold
    R = camera.pose.R_cam_from_world.tolist()
    c = camera.pose.position_world.tolist()
    hx, hy = R[2][0], R[2][1]
    if math.hypot(hx, hy) < 1e-9:  # looking straight down: use the image's up direction
        hx, hy = -R[1][0], -R[1][1]
    norm = math.hypot(hx, hy)
    hx, hy = hx / norm, hy / norm
    px, py = c[0] + distance_m * hx, c[1] + distance_m * hy
    half = 0.5 * VEHICLE_SPEED_KMH / 3.6 * SPEED_BASE_S
    point = np.array([px, py, ground_z], dtype=float)
    track = np.array([[px - half * hx, py - half * hy, ground_z], [px + half * hx, py + half * hy, ground_z]], dtype=float)
    return GroundProbe(point=point, track=track)


@dataclass(frozen=True, eq=False)
class UncertaintyResult:
    """Statistics of the calibration uncertainty for one camera and one set of points.

    RMS reprojection error (px) statistics as in the paper; parameter standard
    deviations (``param_std``: fx, fy, cx, cy, k1..k3 in their units, camera
    position in metres as ``pos_x/y/z``, orientation in degrees as
    ``rot_x/y/z``); projection error RMS (px) against the reference camera
    over the sampled points and over ground points in view; ground position
    error (cm) and speed error (km/h) 15 m out. ``rms`` holds the k trial
    values for Monte-Carlo, None for the linearised estimate; ``covariance``
    the (15, 15) parameter covariance of the linearised estimate.
    """

    method: str
    trials: int
    model: str
    rms_mean: float
    rms_max: float
    rms_var: float
    rms_percentiles: dict[int, float]
    param_std: dict[str, float]
    projection_error_px: float
    ground_projection_error_px: float
    ground_error_15m_cm: float
    ground_error_15m_cm_p95: float
    speed_error_15m_kmh: float
    speed_error_15m_kmh_p95: float
    n_points: int
    rms: np.ndarray | None = field(default=None, repr=False)
    failed_trials: int = 0
    covariance: np.ndarray | None = field(default=None, repr=False)  # (15, 15), linearised only
    model_term: str | None = None  # the richer model whose excess covariance the derived figures include (None: noise only)

    def to_dict(self) -> dict:
        d = {
            "method": self.method,
            "trials": self.trials,
            "model": self.model,
            "n_points": self.n_points,
            "rms_mean": self.rms_mean,
            "rms_max": self.rms_max,
            "rms_var": self.rms_var,
            "rms_std": float(np.sqrt(self.rms_var)),
            "rms_percentiles": {str(k): v for k, v in self.rms_percentiles.items()},
            "param_std": self.param_std,
            "projection_error_px": self.projection_error_px,
            "ground_projection_error_px": self.ground_projection_error_px,
            "ground_error_15m_cm": self.ground_error_15m_cm,
            "ground_error_15m_cm_p95": self.ground_error_15m_cm_p95,
            "speed_error_15m_kmh": self.speed_error_15m_kmh,
            "speed_error_15m_kmh_p95": self.speed_error_15m_kmh_p95,
            "failed_trials": self.failed_trials,
            "model_term": self.model_term,
        }
        return d


PERCENTILES = (5, 50, 95, 99)


def _sigmas(points: np.ndarray, sigma_3d, sigma_2d) -> tuple[np.ndarray, np.ndarray]:
    n = points.shape[0]
    if isinstance(sigma_3d, (tuple, list)) and len(sigma_3d) == 3 and isinstance(sigma_2d, (int, float)):
        # the common call (one sigma per axis, one pixel sigma), checked on the Python numbers: the general path's
        # numpy calls cost up to 0.5 ms when cold
        s = [float(v) for v in sigma_3d] + [float(sigma_2d)]
        if not all(np.isfinite(v) and v >= 0 for v in s):
            raise InputError("noise sigmas must be finite and non-negative: check --sigma-3d and --sigma-px")
        s3 = np.empty((n, 3))
        s3[:] = s[:3]
        return s3, np.full(n, s[3])
    s3 = np.broadcast_to(np.asarray(sigma_3d, float), (n, 3)).copy()
    s2 = np.broadcast_to(np.asarray(sigma_2d, float).reshape(-1), (n,)).copy() if np.ndim(sigma_2d) else np.full(n, float(sigma_2d))
    if np.any(s3 < 0) or np.any(s2 < 0) or not (np.all(np.isfinite(s3)) and np.all(np.isfinite(s2))):
        raise InputError("noise sigmas must be finite and non-negative: check --sigma-3d and --sigma-px")
    return s3, s2


def _ground_pixels(camera: Camera, ground_z: float, nu: int = 10, nv: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (M, 2) of a grid over the image whose rays meet the ground in front of the camera, and those ground points (M, 3)."""
    from dronecal_field.core.mc_setup import ground_grid  # compiled: the numpy version's calls cost up to 1 ms when cold

    intr, dist, R, t = camera.batch_arrays()
    return ground_grid(intr[0], dist[0], R[0], t[0], int(camera.width), int(camera.height), float(ground_z), nu, nv, 200.0)


def _intersect_ground(camera: Camera, uv: np.ndarray, ground_z: float) -> np.ndarray:
    """World points (M, 3) where the camera's rays of pixels uv (M, 2) meet the plane z = ground_z (NaN if they miss)."""
    from dronecal_field.core import kernels

    out = np.empty((1, len(uv), 3))
    kernels.intersect_plane_z(*camera.batch_arrays(), np.ascontiguousarray(uv, float), float(ground_z), out)
    return out[0]


@dataclass(frozen=True, eq=False)
class _Probes:
    points_world: np.ndarray  # (N, 3) the sampled points
    uv_ref_points: np.ndarray  # (N, 2)
    ground_world: np.ndarray  # (M, 3)
    uv_ref_ground: np.ndarray  # (M, 2)
    probe: GroundProbe
    uv_probe: np.ndarray  # (3, 2) pixels of the probe point and the two track points

    def by_coordinate(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """points (3, N), their pixels (2, N), ground (3, M), its pixels (2, M): one row per coordinate, as the kernels take them."""
        return tuple(np.ascontiguousarray(a.T) for a in (self.points_world, self.uv_ref_points, self.ground_world, self.uv_ref_ground))


def _make_probes(camera: Camera, points: np.ndarray, ground_z: float) -> _Probes:
    from dronecal_field.core.mc_setup import project  # compiled: camera.project's numpy calls cost ms when cold

    uv_g, g = _ground_pixels(camera, ground_z)
    probe = ground_probe(camera, ground_z)
    probe_pts = np.vstack([probe.point[None], probe.track])
    intr, dist, R, t = camera.batch_arrays()
    points = np.ascontiguousarray(points, float)
    return _Probes(
        points_world=points,
        uv_ref_points=project(intr[0], dist[0], R[0], t[0], points),
        ground_world=g.reshape(-1, 3),
        uv_ref_ground=uv_g.reshape(-1, 2),
        probe=probe,
        uv_probe=project(intr[0], dist[0], R[0], t[0], probe_pts),
    )


def _ground_metrics(hits: np.ndarray, probe: GroundProbe) -> dict[str, np.ndarray]:
    """Per-trial ground position error 15 m out (cm) and speed error (km/h) from where each camera's probe rays meet the ground (K, 3, 3)."""
    from dronecal_field.core.mc_figures import ground_errors

    pos_err_cm, speed_err = np.empty(len(hits)), np.empty(len(hits))
    ground_errors(np.ascontiguousarray(hits), probe.point, float(np.linalg.norm(probe.track[1] - probe.track[0])), SPEED_BASE_S,
                  pos_err_cm, speed_err)
    return {"pos15": pos_err_cm, "speed15": speed_err}


def _solve_trials(
    camera: Camera, key: np.uint64, trials: range, P: np.ndarray, s3: np.ndarray, pixels: np.ndarray, s2: np.ndarray,
    A: np.ndarray, probes: _Probes, ground_z: float, max_iterations: int, tolerance: float,
) -> tuple[np.ndarray, dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Calibrate every trial of a chunk from the reference camera and score it: (cost (K,) px^2, per-trial metrics, per-trial parameters).

    Trial j (of ``trials``, consecutive indices) sees the points P + Z3 * s3 and the pixels
    ``pixels`` + Z2 * s2, Z3 (N, 3) and Z2 (N, 2) its standard normal draws
    (``core.trial_noise.trial_normals(seed, j, N)``). One compiled pass,
    parallel over trials: the draws, the noise, the Levenberg-Marquardt of
    ``core.calibrate.levenberg_marquardt`` (linear loss), then each estimate's
    projection error against the reference, its rays to the ground probe,
    its centre and its rotation from the reference.
    """
    from dronecal_field.core import kernels

    kernels.announce_compile_once()
    K = len(trials)
    state = BatchState.from_camera(camera, K)
    sel, fx_col, aspect = _free_columns(A)
    cost, iterations = np.empty(K), np.empty(K, dtype=np.int64)
    proj, gproj, hits = np.empty(K), np.empty(K), np.empty((K, len(probes.uv_probe), 3))
    centre, rotation = np.empty((K, 3)), np.empty((K, 3))
    kernels.monte_carlo_trials(
        state.intrinsics, state.distortion, state.R, state.t, np.uint64(key), int(trials.start), P, s3, pixels, s2,
        np.ascontiguousarray(A, dtype=float), sel, fx_col, aspect, int(max_iterations), float(tolerance),
        *_reference_step_matrix(camera, P, sel, fx_col, aspect), *probes.by_coordinate(), probes.uv_probe, float(ground_z),
        cost, iterations, proj, gproj, hits, centre, rotation,
    )
    params = {name: state.intrinsics[:, i] for i, name in enumerate(PARAM_NAMES[0:4])}
    params.update({name: state.distortion[:, i] for i, name in enumerate(PARAM_NAMES[4:9])})
    rotation = np.degrees(rotation)
    for i, axis in enumerate("xyz"):
        params[f"pos_{axis}"] = centre[:, i]
    for i, axis in enumerate("xyz"):
        params[f"rot_{axis}"] = rotation[:, i]
    return cost, {"projection": proj, "ground_projection": gproj, **_ground_metrics(hits, probes.probe)}, params


def _reference_step_matrix(camera: Camera, P: np.ndarray, sel: np.ndarray, fx_col: int, aspect: float,
                           damping: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """The matrix of every trial's first step from the reference camera: (J^T J + damping diag(J^T J))^-1 J^T, as (Pu, Pv) (m, N) each.

    J (2N, m) is the reference camera's Jacobian at the unperturbed points;
    a trial's first step is then Pu @ ru + Pv @ rv for its residuals (ru, rv)
    at the reference (Marquardt's damping, as the solver's first iteration).
    When the points cannot fix the camera (not positive definite) both are
    zero: no trial takes that step (``core.mc_setup.step_matrix``).
    """
    from dronecal_field.core.mc_setup import step_matrix

    Pu, Pv = np.empty((len(sel), len(P))), np.empty((len(sel), len(P)))
    intr, dist, R, t = camera.batch_arrays()
    step_matrix(intr[0], dist[0], R[0], t[0], np.ascontiguousarray(P, float), sel, int(fx_col), float(aspect), float(damping), Pu, Pv)
    return Pu, Pv


def _param_samples(state: BatchState, reference: Camera) -> dict[str, np.ndarray]:
    """Per-trial parameter values (K,) including camera position (m) and orientation error (deg)."""
    out = {name: state.intrinsics[:, i] for i, name in enumerate(PARAM_NAMES[0:4])}
    out.update({name: state.distortion[:, i] for i, name in enumerate(PARAM_NAMES[4:9])})
    centres = -np.einsum("kji,kj->ki", state.R, state.t)
    for i, axis in enumerate("xyz"):
        out[f"pos_{axis}"] = centres[:, i]
    dR = state.R @ reference.pose.R_cam_from_world.T
    rot = np.degrees(vector_from_rotation(dR))
    for i, axis in enumerate("xyz"):
        out[f"rot_{axis}"] = rot[:, i]
    return out


def _nan_stat(fn, values: np.ndarray) -> float:
    values = values[np.isfinite(values)]
    return float(fn(values)) if values.size else float("nan")


# A chunk holds ~300 bytes per (trial, point): 1e6 of them is ~300 MB, however many points there are.
MAX_TRIAL_POINTS_PER_CHUNK = 1_000_000


def trials_per_chunk(chunk_size: int, n_points: int) -> int:
    """Trials solved together: at most ``chunk_size``, fewer for many points so memory stays O(N), not O(trials x N)."""
    return max(1, min(chunk_size, MAX_TRIAL_POINTS_PER_CHUNK // max(n_points, 1)))


def monte_carlo(
    camera: Camera,
    points_world: np.ndarray,
    trials: int = 500,
    sigma_3d=DEFAULT_SIGMA_3D,
    sigma_2d=DEFAULT_SIGMA_2D,
    seed: int = 0,
    model: "str | CalibrationModel" = "default",
    chunk_size: int = 2000,
    ground_z: float = 0.0,
    max_iterations: int = 30,
    mc_tolerance: float = 1e-5,
    observed_pixels: np.ndarray | None = None,
    model_term: bool | None = None,
    fitted_pixels: np.ndarray | None = None,
) -> UncertaintyResult:
    """The paper's Monte-Carlo estimate of calibration uncertainty, all trials batched.

    Parameters
    ----------
    camera : the reference camera C (truth in simulation, the calibrated camera from a flight)
    points_world : (N, 3) sampled 3D points P_i, world metres
    trials : k, the number of trials (the paper uses 500)
    sigma_3d : (3,) or (N, 3) standard deviations along world X, Y, Z, metres
    sigma_2d : scalar or (N,) pixel standard deviation per axis
    seed : keys every trial's noise stream (core.trial_noise): the same seed gives the same
        statistics, whatever the chunking or the number of threads
    model : calibration model re-estimated in each trial ('default' = OpenCV's CALIB_FIX_K3)
    chunk_size : trials solved together at most; fewer when N is large, so that memory
        (~ chunk_size * N * 300 bytes) stays under ~300 MB
    observed_pixels : (N, 2) p_i; default the reference camera's projection of P_i
    mc_tolerance : a trial stops when its cost drops by less than this fraction in an
        iteration. The large-residual problem converges linearly (the cost's drop shrinks
        20-40x per iteration), so 1e-5 leaves 99 % of the trials' RMS within 2e-5 of the
        converged value and their parameters within 0.03 std of it: the spreads move by
        0.1 % (paper grid, k = 500), 30x less than the Monte-Carlo's own noise at k = 500,
        and it saves one iteration in six against 1e-6 (benchmarks/README.md)
    model_term, fitted_pixels : the model term of :func:`linearised` (default: for a model
        fitted to data), added root-sum-square to every derived figure; the trials
        themselves re-estimate the chosen model only

    Returns
    -------
    UncertaintyResult with rms_mean/max/var/percentiles (px), parameter spreads
    and projection errors.
    """
    P = np.ascontiguousarray(points_world, float)
    if trials < 2:
        raise InputError(f"--trials {trials} is too few for statistics: use at least 2 (the paper uses 500)")
    s3, s2 = _sigmas(P, sigma_3d, sigma_2d)
    mdl = resolve_model(model, P.shape[0])
    A = mdl.parameter_map(camera.intrinsics.fy / camera.intrinsics.fx)
    probes = _make_probes(camera, P, ground_z)
    uv_ref = probes.uv_ref_points if observed_pixels is None else np.ascontiguousarray(observed_pixels, float)
    # the kernel draws each trial's noise from its own stream (core.trial_noise): the same seed gives the
    # same trials whatever the chunking or the thread count
    from dronecal_field.core.trial_noise import seed_key

    key = seed_key(seed)

    chunk_size = trials_per_chunk(chunk_size, P.shape[0])
    rms_all, metrics_all, params_all, failed = [], [], [], 0
    for start in range(0, trials, chunk_size):
        chunk = range(start, min(start + chunk_size, trials))
        cost, metrics, params = _solve_trials(camera, key, chunk, P, s3, uv_ref, s2, A, probes, ground_z, max_iterations, mc_tolerance)
        rms = np.sqrt(cost / P.shape[0])
        ok = np.isfinite(rms)
        failed += int((~ok).sum())
        rms_all.append(rms)
        metrics_all.append(metrics)
        params_all.append(params)

    one = len(rms_all) == 1
    rms = rms_all[0] if one else np.concatenate(rms_all)
    metrics = metrics_all[0] if one else {key: np.concatenate([m[key] for m in metrics_all]) for key in metrics_all[0]}
    params = params_all[0] if one else {key: np.concatenate([p[key] for p in params_all]) for key in params_all[0]}
    out = _figures(rms, metrics, params)
    richer = _model_term_model(mdl, P.shape[0], model_term)
    if richer is not None:
        out = _add_model_term(out, camera, P, s3, s2, mdl, richer, probes, ground_z, fitted_pixels)
    return UncertaintyResult(
        method="monte-carlo",
        trials=trials,
        model=mdl.name,
        n_points=P.shape[0],
        rms=rms,
        failed_trials=failed,
        model_term=None if richer is None else richer.name,
        **out,
    )


def _figures(rms: np.ndarray, metrics: dict[str, np.ndarray], params: dict[str, np.ndarray]) -> dict:
    """The result's figures from the per-trial values (K,): one compiled call when every trial finished, numpy's NaN-aware path otherwise."""
    from dronecal_field.core.mc_figures import summary

    rms_of = lambda v: np.sqrt(np.mean(v**2))  # noqa: E731
    values = np.stack(list(params.values()))
    series = (rms, metrics["projection"], metrics["pos15"], metrics["speed15"])
    if rms.size >= 2 and np.all(np.isfinite(values)) and all(np.all(np.isfinite(v)) for v in series):
        gproj = metrics["ground_projection"]
        finite_ground = bool(np.all(np.isfinite(gproj)))
        std, pct = np.empty(len(values)), np.empty((3, len(PERCENTILES)))
        mean, top, var, proj, gp, pos, speed, _ = summary(
            rms, metrics["projection"], gproj if finite_ground else np.zeros(1), metrics["pos15"], metrics["speed15"],
            values, np.asarray(PERCENTILES, float), std, pct)
        return dict(
            param_std=dict(zip(params, (float(v) for v in std))),
            projection_error_px=float(proj),
            ground_projection_error_px=float(gp) if finite_ground else _nan_stat(rms_of, gproj),
            ground_error_15m_cm=float(pos),
            speed_error_15m_kmh=float(speed),
            ground_error_15m_cm_p95=float(pct[1, PERCENTILES.index(95)]),
            speed_error_15m_kmh_p95=float(pct[2, PERCENTILES.index(95)]),
            rms_mean=float(mean), rms_max=float(top), rms_var=float(var),
            rms_percentiles={p: float(v) for p, v in zip(PERCENTILES, pct[0])},
        )
    rms_pct, pos_pct, speed_pct = _percentiles_of((rms, metrics["pos15"], metrics["speed15"]), PERCENTILES)
    return dict(
        param_std=_param_std(params),
        projection_error_px=_nan_stat(rms_of, metrics["projection"]),
        ground_projection_error_px=_nan_stat(rms_of, metrics["ground_projection"]),
        ground_error_15m_cm=_nan_stat(rms_of, metrics["pos15"]),
        speed_error_15m_kmh=_nan_stat(rms_of, metrics["speed15"]),
        ground_error_15m_cm_p95=float(pos_pct[PERCENTILES.index(95)]),
        speed_error_15m_kmh_p95=float(speed_pct[PERCENTILES.index(95)]),
        rms_mean=_nan_stat(np.mean, rms),
        rms_max=_nan_stat(np.max, rms),
        rms_var=_nan_stat(lambda v: np.var(v, ddof=1), rms),
        rms_percentiles={p: float(v) for p, v in zip(PERCENTILES, rms_pct)},
    )


def _param_std(params: dict[str, np.ndarray]) -> dict[str, float]:
    """Each parameter's sample standard deviation over the finite trials (one numpy pass for all when every trial is finite)."""
    values = np.stack(list(params.values()))
    if np.all(np.isfinite(values)):
        return dict(zip(params, (float(v) for v in np.std(values, axis=1, ddof=1))))
    return {key: _nan_stat(lambda v: np.std(v, ddof=1), val) for key, val in params.items()}


def _percentiles_of(series: tuple[np.ndarray, ...], q) -> list[np.ndarray]:
    """Percentiles ``q`` of the finite values of each (K,) series: one numpy call for all when every value is finite."""
    values = np.stack(series)
    if np.all(np.isfinite(values)) and values.shape[1] > 1:
        return list(_linear_percentiles(np.sort(values, axis=1), q))
    return [_nan_percentiles(v, q) for v in series]


def _linear_percentiles(sorted_values: np.ndarray, q) -> np.ndarray:
    """Percentiles q of each sorted row (S, K), K >= 2, as np.percentile's default 'linear' method computes them (its lerp too).

    (S, len(q)). One sort for all rows: np.percentile's own call took 90 us
    of the Monte-Carlo's ~1 ms of Python per call.
    """
    n = sorted_values.shape[1]
    pos = np.asarray(q, float) / 100.0 * (n - 1)
    lo = np.minimum(np.floor(pos).astype(np.int64), n - 2)
    frac = pos - lo
    a, b = sorted_values[:, lo], sorted_values[:, lo + 1]
    diff = b - a
    return np.where(frac >= 0.5, b - diff * (1.0 - frac), a + diff * frac)


def _nan_percentiles(values: np.ndarray, q) -> np.ndarray:
    """Percentiles ``q`` of the finite values, one sort for all (NaN when none is finite)."""
    values = values[np.isfinite(values)]
    return np.percentile(values, list(q)) if values.size else np.full(len(q), np.nan)


def _add_model_term(out: dict, camera: Camera, P: np.ndarray, s3: np.ndarray, s2: np.ndarray, mdl: CalibrationModel,
                    richer: CalibrationModel, probes: "_Probes", ground_z: float, fitted_pixels: np.ndarray | None) -> dict:
    """The Monte-Carlo's derived figures with the model term of :func:`linearised` added root-sum-square."""
    from scipy import stats

    A = mdl.parameter_map(camera.intrinsics.fy / camera.intrinsics.fx)
    Jm, blocks = _jacobian_and_noise(camera, P, s3, s2, A)
    chosen = _derived_variances(camera, probes, _sandwich(Jm, blocks, np.linalg.pinv(Jm.T @ Jm)), A, ground_z)
    rich = model_variances(camera, P, s3, s2, richer, ground_z, probes)
    extra = {key: _psd_excess(np.nan_to_num(rich[key], nan=0.0), np.nan_to_num(v, nan=0.0)) for key, v in chosen.items()}
    if fitted_pixels is not None:
        extra = _with_bias(extra, model_bias(camera, P, fitted_pixels, richer, ground_z, probes))
    rss = lambda a, b: float(np.sqrt(a**2 + max(b, 0.0)))  # noqa: E731
    out = dict(out)
    out["param_std"] = {key: rss(v, extra[f"param:{key}"][0, 0]) for key, v in out["param_std"].items()}
    out["projection_error_px"] = rss(out["projection_error_px"], float(np.sum(extra["points"])) / max(len(P), 1))
    if len(probes.ground_world):
        out["ground_projection_error_px"] = rss(out["ground_projection_error_px"], float(np.sum(extra["ground"])) / len(probes.ground_world))
    pos = extra["pos15"]
    out["ground_error_15m_cm"] = rss(out["ground_error_15m_cm"], 1e4 * float(np.trace(pos)))
    out["ground_error_15m_cm_p95"] = rss(out["ground_error_15m_cm_p95"], 1e4 * stats.chi2.ppf(0.95, 2) * float(np.max(np.linalg.eigvalsh(pos))))
    out["speed_error_15m_kmh"] = rss(out["speed_error_15m_kmh"], float(extra["speed15"][0, 0]))
    out["speed_error_15m_kmh_p95"] = rss(out["speed_error_15m_kmh_p95"], 1.96**2 * float(extra["speed15"][0, 0]))
    return out


def convergence_curve(rms: np.ndarray) -> np.ndarray:
    """(k,) running mean of the RMS after 1..k trials: the paper's Figure 1."""
    rms = np.asarray(rms, float)
    return np.cumsum(rms) / np.arange(1, rms.size + 1)


def linearised(
    camera: Camera,
    points_world: np.ndarray,
    sigma_3d=DEFAULT_SIGMA_3D,
    sigma_2d=DEFAULT_SIGMA_2D,
    model: "str | CalibrationModel" = "default",
    ground_z: float = 0.0,
    model_term: bool | None = None,
    fitted_pixels: np.ndarray | None = None,
) -> UncertaintyResult:
    """First-order propagation of the same noise: the Monte-Carlo's figures in milliseconds.

    Each observation's noise, as seen in the image, is Sigma_i = s_i^2 I +
    J_X,i S_i J_X,i^T (the 3D noise pushed through the projection). The
    unweighted least-squares estimate then has covariance
    (J^T J)^-1 J^T Sigma J (J^T J)^-1, and the residual sum of squares has
    mean tr((I - H) Sigma) and variance 2 tr(((I - H) Sigma)^2), H being the
    hat matrix; the RMS statistics follow from a scaled chi-square fit.
    Derived quantities (projection errors, ground errors) are propagated with
    their Jacobians by central differences over the free parameters.

    ``model_term`` (default: when the model was fitted to data,
    ``CalibrationModel.fitted``) adds the *model term* to every derived figure
    (parameter std, projection errors, ground and speed errors 15 m out): what
    the next richer model's covariance (``core.calibrate.richer_model``) holds
    beyond the chosen one's. A lean model's covariance only spans the
    directions it can move in, so a k1 fit to points in the image's middle
    claims a focal length to 0.6 px when an unmodelled k2 moves it by 2 px;
    the RMS statistics (what the paper's Monte-Carlo measures) are unchanged.
    With ``fitted_pixels`` (N, 2), the pixels ``camera`` was fitted to, the
    richer model is also fitted to them and its departure from ``camera``
    (squared) joins the term: the spread between two models that fit the
    points about equally, which is what an unmodelled lens term does to the
    focal length and to the ground beyond the points.
    """
    from scipy import special, stats

    P = np.asarray(points_world, float)
    n = P.shape[0]
    s3, s2 = _sigmas(P, sigma_3d, sigma_2d)
    mdl = resolve_model(model, n)
    aspect = camera.intrinsics.fy / camera.intrinsics.fx
    A = mdl.parameter_map(aspect)
    Jm, blocks = _jacobian_and_noise(camera, P, s3, s2, A)
    JtJ_inv = np.linalg.pinv(Jm.T @ Jm)
    cov = _sandwich(Jm, blocks, JtJ_inv)
    ssr_mean, ssr_var = _ssr_moments(Jm, blocks, JtJ_inv)
    # SSR ~ a * chi2(nu): match mean and variance
    a = ssr_var / (2.0 * ssr_mean)
    nu = 2.0 * ssr_mean**2 / ssr_var
    dist = stats.chi2(nu, scale=a)
    # E[sqrt(S/n)] in closed form (sqrt(2a/n) G((nu+1)/2) / G(nu/2)): dist.expect integrates numerically and warned
    # "the integral is probably divergent" on a PX4 flight's noisy points
    rms_mean = float(np.sqrt(2.0 * a / n) * np.exp(special.gammaln(0.5 * (nu + 1.0)) - special.gammaln(0.5 * nu)))
    rms_sq_mean = ssr_mean / n
    rms_var = max(rms_sq_mean - rms_mean**2, 0.0)
    percentiles = {p: float(np.sqrt(dist.ppf(p / 100.0) / n)) for p in PERCENTILES}

    probes = _make_probes(camera, P, ground_z)
    var = _derived_variances(camera, probes, cov, A, ground_z)
    richer = _model_term_model(mdl, n, model_term)
    if richer is not None:
        var = _with_model_term(var, model_variances(camera, P, s3, s2, richer, ground_z, probes))
        if fitted_pixels is not None:
            var = _with_bias(var, model_bias(camera, P, fitted_pixels, richer, ground_z, probes))
    param_std = {key[6:]: float(np.sqrt(max(v[0, 0], 0.0))) for key, v in var.items() if key.startswith("param:")}
    # Projection error RMS over points: sqrt(mean_i tr(C_i)).
    proj = float(np.sqrt(np.sum(var["points"]) / max(len(P), 1)))
    gproj = float(np.sqrt(np.sum(var["ground"]) / max(len(probes.ground_world), 1))) if len(probes.ground_world) else float("nan")
    pos_cov = var["pos15"]
    pos_rms = float(100.0 * np.sqrt(np.trace(pos_cov)))
    speed_sd = float(np.sqrt(max(var["speed15"][0, 0], 0.0)))
    return UncertaintyResult(
        method="linearised",
        trials=0,
        model=mdl.name,
        rms_mean=rms_mean,
        rms_max=float(np.sqrt(dist.ppf(0.999) / n)),
        rms_var=rms_var,
        rms_percentiles=percentiles,
        param_std=param_std,
        projection_error_px=proj,
        ground_projection_error_px=gproj,
        ground_error_15m_cm=pos_rms,
        ground_error_15m_cm_p95=float(100.0 * np.sqrt(stats.chi2.ppf(0.95, 2) * np.max(np.linalg.eigvalsh(pos_cov)))),
        speed_error_15m_kmh=speed_sd,
        speed_error_15m_kmh_p95=float(1.96 * speed_sd),
        n_points=n,
        covariance=A @ cov @ A.T,
        model_term=None if richer is None else richer.name,
    )


def _ssr_moments(Jm: np.ndarray, blocks: np.ndarray, JtJ_inv: np.ndarray) -> tuple[float, float]:
    """Mean tr((I - H) Sigma) and variance 2 tr(((I - H) Sigma)^2) of the residual sum of squares.

    Sigma is block diagonal (N blocks of 2 x 2) and H = J G J^T (G = (J^T J)^-1),
    so both traces reduce to m x m products, O(N m^2) instead of the (2N, 2N)
    matrices (4K leg runs: 6600 x 6600): with B = J^T Sigma J and
    C = J^T Sigma^2 J, tr(M) = tr(Sigma) - tr(G B) and
    tr(M^2) = tr(Sigma^2) - 2 tr(G C) + tr((G B)^2).
    """
    n, m = blocks.shape[0], Jm.shape[1]
    Jb = Jm.reshape(n, 2, m)
    blocks2 = blocks @ blocks
    B = np.einsum("nia,nij,njb->ab", Jb, blocks, Jb)
    C = np.einsum("nia,nij,njb->ab", Jb, blocks2, Jb)
    GB = JtJ_inv @ B
    tr_sigma = float(np.trace(blocks, axis1=1, axis2=2).sum())
    tr_sigma2 = float(np.trace(blocks2, axis1=1, axis2=2).sum())
    mean = tr_sigma - float(np.trace(GB))
    var = 2.0 * (tr_sigma2 - 2.0 * float(np.sum(JtJ_inv * C)) + float(np.sum(GB * GB.T)))
    return mean, var


def _derived_variances(camera: Camera, probes: "_Probes", cov: np.ndarray, A: np.ndarray, ground_z: float) -> dict[str, np.ndarray]:
    """First-order covariance of every derived quantity under the free-parameter covariance ``cov`` (m, m).

    Central differences over the free parameters (steps of 1e-3 std), all
    cameras in one batch. ``points`` and ``ground`` hold only each
    coordinate's variance (2M,) (their RMS figures need no more); the rest
    their (d, d) covariance.
    """
    m = A.shape[1]
    std_free = np.sqrt(np.maximum(np.diag(cov), 1e-30))
    h = 1e-3 * std_free
    steps = np.concatenate([np.diag(h), -np.diag(h)]) @ A.T  # (2m, 15)
    state = BatchState.from_camera(camera, 2 * m).stepped(steps)
    vals = _derived_vectors(state, probes, camera, ground_z)
    out: dict[str, np.ndarray] = {}
    for key, v in vals.items():
        D = (v[:m] - v[m:]) / (2.0 * h[:, None])  # (m, dims)
        out[key] = np.einsum("ai,ab,bi->i", D, cov, D) if key in ("points", "ground") else D.T @ cov @ D
    return out


def _model_term_model(mdl: CalibrationModel, n_points: int, model_term: bool | None) -> CalibrationModel | None:
    """The richer model whose covariance the model term takes, or None (no term, or no richer model the points support)."""
    if model_term is None:
        model_term = bool(getattr(mdl, "fitted", False))
    if not model_term:
        return None
    richer = richer_model(mdl)
    if richer is None or 2 * n_points <= richer.n_free:
        return None
    return richer


def model_variances(
    camera: Camera, points_world: np.ndarray, sigma_3d, sigma_2d, richer: CalibrationModel, ground_z: float = 0.0,
    probes: "_Probes | None" = None,
) -> dict[str, np.ndarray]:
    """The derived quantities' first-order variances under ``richer`` (see :func:`linearised`), at ``camera``.

    ``camera`` stands in for the richer model's fit: its extra terms at 0
    are a point of the richer family, and to first order the covariance
    there is the fit's.
    """
    P = np.asarray(points_world, float)
    s3, s2 = _sigmas(P, sigma_3d, sigma_2d)
    A = richer.parameter_map(camera.intrinsics.fy / camera.intrinsics.fx)
    Jm, blocks = _jacobian_and_noise(camera, P, s3, s2, A)
    cov = _sandwich(Jm, blocks, np.linalg.pinv(Jm.T @ Jm))
    return _derived_variances(camera, probes if probes is not None else _make_probes(camera, P, ground_z), cov, A, ground_z)


def model_bias(
    camera: Camera, points_world: np.ndarray, pixels: np.ndarray, richer: CalibrationModel, ground_z: float = 0.0,
    probes: "_Probes | None" = None, loss_scale_px: float = 2.0,
) -> dict[str, np.ndarray] | None:
    """How far ``richer``, fitted to the same points and pixels from ``camera``, moves every derived quantity.

    (dims,) differences richer - camera per key of :func:`_derived_vectors`;
    None when the richer fit fails (then only its covariance counts). The
    fit uses the Huber loss at ``loss_scale_px`` like calibrate's, so an
    outlier the chosen fit shrugged off does not become a model term.
    """
    from dronecal_field.core.calibrate import calibrate
    from dronecal_field.errors import DronecalError

    P = np.asarray(points_world, float)
    try:
        fit = calibrate(P, np.asarray(pixels, float), camera.width, camera.height, model=richer, loss="huber",
                        loss_scale_px=loss_scale_px, initial=camera)
    except DronecalError:
        return None
    r = fit.camera
    state = BatchState(
        np.vstack([camera.batch_arrays()[0], r.batch_arrays()[0]]), np.vstack([camera.batch_arrays()[1], r.batch_arrays()[1]]),
        np.concatenate([camera.batch_arrays()[2], r.batch_arrays()[2]]), np.vstack([camera.batch_arrays()[3], r.batch_arrays()[3]]),
    )
    vals = _derived_vectors(state, probes if probes is not None else _make_probes(camera, P, ground_z), camera, ground_z)
    return {key: v[1] - v[0] for key, v in vals.items()}


def _with_bias(var: dict[str, np.ndarray], bias: dict[str, np.ndarray] | None) -> dict[str, np.ndarray]:
    """Variances with each quantity's model bias added (squared; outer product for the (d, d) ones)."""
    if bias is None:
        return var
    out = {}
    for key, v in var.items():
        b = np.nan_to_num(bias[key], nan=0.0)
        out[key] = v + (b * b if v.ndim == 1 else np.outer(b, b))
    return out


def _psd_excess(richer: np.ndarray, chosen: np.ndarray) -> np.ndarray:
    """The part of ``richer`` beyond ``chosen``: elementwise for variances (k,), the positive part of the difference for (d, d)."""
    d = richer - chosen
    if d.ndim == 1:
        return np.maximum(d, 0.0)
    w, V = np.linalg.eigh(0.5 * (d + d.T))
    return (V * np.maximum(w, 0.0)) @ V.T


def _with_model_term(chosen: dict[str, np.ndarray], richer: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each derived quantity's variance with the model term added (the richer model's excess over the chosen one)."""
    return {key: v + _psd_excess(np.nan_to_num(richer[key], nan=0.0), np.nan_to_num(v, nan=0.0)) for key, v in chosen.items()}


def _jacobian_and_noise(camera: Camera, P: np.ndarray, s3: np.ndarray, s2: np.ndarray, A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Free-parameter Jacobian (2N, m) and each observation's image noise (N, 2, 2).

    The image noise of point i is s_i^2 I + J_X,i diag(S_i^2) J_X,i^T: its
    pixel noise plus its 3D noise pushed through the projection.
    """
    n = P.shape[0]
    _, J, Jx = project_batch_jacobians(*camera.batch_arrays(), P[None])
    Jm = (J[0] @ A).reshape(2 * n, A.shape[1])
    blocks = s2[:, None, None] ** 2 * np.eye(2) + np.einsum("nij,nj,nkj->nik", Jx[0], s3**2, Jx[0])
    return Jm, blocks


def _sandwich(Jm: np.ndarray, blocks: np.ndarray, JtJ_inv: np.ndarray) -> np.ndarray:
    """(J^T J)^-1 J^T Sigma J (J^T J)^-1 for a block-diagonal Sigma, without forming it."""
    Jb = Jm.reshape(blocks.shape[0], 2, -1)
    middle = np.einsum("nia,nij,njb->ab", Jb, blocks, Jb)
    return JtJ_inv @ middle @ JtJ_inv


def parameter_covariance(
    camera: Camera,
    points_world: np.ndarray,
    sigma_3d=DEFAULT_SIGMA_3D,
    sigma_2d=DEFAULT_SIGMA_2D,
    model: "str | CalibrationModel" = "default",
) -> np.ndarray:
    """(15, 15) first-order covariance of the least-squares camera under per-point noise.

    Parameters
    ----------
    points_world : (N, 3) metres
    sigma_3d : (3,) or (N, 3) metres, per axis
    sigma_2d : scalar or (N,) pixels, per axis
    model : the free parameters; fixed ones get zero variance

    The unweighted estimate has covariance (J^T J)^-1 J^T Sigma J (J^T J)^-1
    over the free parameters, Sigma holding each observation's image noise.
    """
    P = np.asarray(points_world, float)
    s3, s2 = _sigmas(P, sigma_3d, sigma_2d)
    mdl = resolve_model(model, P.shape[0])
    A = mdl.parameter_map(camera.intrinsics.fy / camera.intrinsics.fx)
    Jm, blocks = _jacobian_and_noise(camera, P, s3, s2, A)
    return A @ _sandwich(Jm, blocks, np.linalg.pinv(Jm.T @ Jm)) @ A.T


def _derived_vectors(state: BatchState, probes: _Probes, reference: Camera, ground_z: float) -> dict[str, np.ndarray]:
    """(K, dims) derived quantities of K cameras, for finite-difference Jacobians."""
    args = (state.intrinsics, state.distortion, state.R, state.t)
    K = state.R.shape[0]
    out = {"points": project_batch(*args, probes.points_world[None]).reshape(K, -1)}
    if len(probes.ground_world):
        out["ground"] = project_batch(*args, probes.ground_world[None]).reshape(K, -1)
    hits = intersect_plane_z(*args, probes.uv_probe[None], ground_z)
    out["pos15"] = hits[:, 0, :2]
    out["speed15"] = (np.linalg.norm(hits[:, 2] - hits[:, 1], axis=-1) / SPEED_BASE_S * 3.6)[:, None]
    for key, v in _param_samples(state, reference).items():
        out[f"param:{key}"] = v[:, None]
    return out
