"""Time alignment: the constant offset between the camera stream and the GNSS stream.

Frames stamped at the host on arrival are late by the camera's latency, which
may be unknown (shared/contracts/run-format.md: up to 1 s, either sign). The
offset is found from the data: the marker's image track must be a projection
of its GNSS track. For each candidate offset we interpolate the GNSS track at
the frames' corrected times, fit a projective camera (DLT, no distortion) to
all (3D, pixel) pairs and measure the reprojection error; while the drone
moves between waypoints a wrong offset pairs each pixel with a point the
marker was not at, so the error has a sharp minimum at the true offset.
Stationary detections do not move the minimum but anchor the fit.

Pure numpy. The uncertainty is a jackknife over hover windows (each left out
in turn), which also catches an offset that only one transition supports.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TimeOffset:
    """Camera stamps minus true capture times, in seconds (positive: frames stamped late).

    The GNSS position that belongs to a frame stamped ``t`` is the one at
    ``t - offset_s``. ``std_s`` is None when the data could not bound it;
    ``method`` says how it was obtained.
    """

    offset_s: float
    std_s: float | None
    method: str  # "image-vs-gnss", "declared", "none"
    n_points: int = 0
    n_moving: int = 0
    n_groups: int = 0
    cost_min_px: float | None = None
    cost_zero_px: float | None = None
    rolling_shutter: dict | None = None  # Timing.to_dict() when legs refined the timing
    gnss_times: dict | None = None  # how the fixes were timed and told apart (run.py)
    through_lens: bool = False  # scanned on pixels undistorted by a first calibration (solve.py)

    @property
    def offset_ns(self) -> int:
        return int(round(self.offset_s * 1e9))

    def to_dict(self) -> dict:
        return {
            "offset_s": self.offset_s,
            "std_s": self.std_s,
            "method": self.method,
            "n_points": self.n_points,
            "n_moving_points": self.n_moving,
            "n_groups": self.n_groups,
            "rms_at_offset_px": self.cost_min_px,
            "rms_at_zero_px": self.cost_zero_px,
            "rolling_shutter": self.rolling_shutter,
            "gnss_fix_times": self.gnss_times,
            "scanned_through_lens": self.through_lens,
        }


def interpolate_track(
    t_query_ns: np.ndarray,
    t_ns: np.ndarray,
    xyz: np.ndarray,
    max_gap_s: float = 0.6,
) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of a track (N, 3) at query times (M,), refusing to bridge gaps.

    Returns
    -------
    values : (M, 3), NaN where invalid
    valid : (M,) bool, False outside the track or inside a gap longer than ``max_gap_s``
    """
    t_ns = np.asarray(t_ns, np.int64)
    q = np.asarray(t_query_ns, np.int64)
    m = len(q)
    if len(t_ns) < 2 or m == 0:
        return np.full((m, 3), np.nan), np.zeros(m, bool)
    k = np.searchsorted(t_ns, q, side="right")
    valid = (k > 0) & (k < len(t_ns))
    k = np.clip(k, 1, len(t_ns) - 1)
    t0, t1 = t_ns[k - 1], t_ns[k]
    valid &= (t1 - t0) <= max_gap_s * 1e9
    w = ((q - t0) / np.maximum(t1 - t0, 1)).astype(float)[:, None]
    values = (1 - w) * xyz[k - 1] + w * xyz[k]
    values[~valid] = np.nan
    return values, valid


def _normaliser(x: np.ndarray) -> np.ndarray:
    """Hartley similarity (d+1, d+1) taking points (N, d) to zero mean and RMS distance sqrt(d)."""
    d = x.shape[1]
    c = x.mean(0)
    s = np.sqrt(d) / max(np.sqrt(((x - c) ** 2).sum(1).mean()), 1e-12)
    T = np.eye(d + 1)
    T[:d, :d] *= s
    T[:d, d] = -s * c
    return T


def projective_residuals(X: np.ndarray, uv: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """(N,) pixel residuals of the best projective map of points X (N, 3) to pixels uv (N, 2).

    A 3x4 DLT when the points span 3D; a 3x3 homography on the two principal
    axes when they are (nearly) coplanar, where a DLT is undetermined.
    ``weights`` (N,) scale each point's equations (robust reweighting).
    """
    X = np.asarray(X, float)
    uv = np.asarray(uv, float)
    centred = X - X.mean(0)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    if s[2] < 0.02 * s[0]:
        X = centred @ vt[:2].T  # in-plane coordinates (N, 2)
    d = X.shape[1]
    Tx, Tu = _normaliser(X), _normaliser(uv)
    Xh = np.c_[X, np.ones(len(X))] @ Tx.T
    uh = np.c_[uv, np.ones(len(uv))] @ Tu.T
    n = len(X)
    zeros = np.zeros((n, d + 1))
    A = np.empty((2 * n, 2 * (d + 1) + d + 1))
    A[0::2] = np.c_[Xh, zeros, -uh[:, 0:1] * Xh]
    A[1::2] = np.c_[zeros, Xh, -uh[:, 1:2] * Xh]
    if weights is not None:
        A *= np.repeat(np.asarray(weights, float), 2)[:, None]
    # The null vector from the (12, 12) normal matrix: with Hartley
    # normalisation it is well enough conditioned for a cost, and it is an
    # order of magnitude cheaper than the SVD of the (2N, 12) matrix.
    _, vecs = np.linalg.eigh(A.T @ A)
    P = vecs[:, 0].reshape(3, d + 1)
    proj = Xh @ P.T
    z = proj[:, 2:3]
    z = np.where(np.abs(z) < 1e-12, 1e-12, z)
    uvn = proj[:, :2] / z
    uv_fit = (np.c_[uvn, np.ones(n)] @ np.linalg.inv(Tu).T)[:, :2]
    return np.linalg.norm(uv_fit - uv, axis=1)


def _robust_cost(X: np.ndarray, uv: np.ndarray, scale_px: float) -> float:
    """RMS-like cost (px) of a projective fit, with one Cauchy reweighting so a stray detection cannot dominate."""
    r = projective_residuals(X, uv)
    w = 1.0 / np.sqrt(1.0 + (r / scale_px) ** 2)
    r = projective_residuals(X, uv, w)
    # Cauchy loss, expressed back in pixels.
    return float(scale_px * np.sqrt(np.mean(np.log1p((r / scale_px) ** 2))))


def _scan(
    det_t_ns: np.ndarray,
    det_uv: np.ndarray,
    fix_t_ns: np.ndarray,
    fix_xyz: np.ndarray,
    offsets_s: np.ndarray,
    scale_px: float,
    min_points: int,
) -> np.ndarray:
    costs = np.full(len(offsets_s), np.nan)
    for k, off in enumerate(offsets_s):
        X, valid = interpolate_track(det_t_ns - int(round(off * 1e9)), fix_t_ns, fix_xyz)
        if valid.sum() < min_points:
            continue
        costs[k] = _robust_cost(X[valid], det_uv[valid], scale_px)
    return costs


def _minimum(offsets_s: np.ndarray, costs: np.ndarray) -> tuple[float, float]:
    """Sub-step minimum of a sampled cost by a parabola through the best sample and its neighbours."""
    k = int(np.nanargmin(costs))
    if 0 < k < len(costs) - 1 and np.all(np.isfinite(costs[k - 1 : k + 2])):
        c0, c1, c2 = costs[k - 1 : k + 2]
        denom = c0 - 2 * c1 + c2
        if denom > 0:
            step = offsets_s[k + 1] - offsets_s[k]
            delta = 0.5 * (c0 - c2) / denom
            return float(offsets_s[k] + delta * step), float(c1 - 0.25 * (c0 - c2) * delta)
    return float(offsets_s[k]), float(costs[k])


def estimate_time_offset(
    det_t_ns: np.ndarray,
    det_uv: np.ndarray,
    fix_t_ns: np.ndarray,
    fix_xyz: np.ndarray,
    groups: np.ndarray | None = None,
    max_offset_s: float = 1.0,
    step_s: float = 0.01,
    scale_px: float = 2.0,
    min_moving_px: float = 1.0,
    min_points: int = 12,
    max_points: int = 900,
) -> TimeOffset:
    """Estimate the camera-vs-GNSS offset from detections and the marker's GNSS track.

    Parameters
    ----------
    det_t_ns : (M,) int64
        Frame stamps of the detections (camera clock as recorded).
    det_uv : (M, 2) pixels
        Marker centres.
    fix_t_ns : (N,) int64, fix_xyz : (N, 3) metres
        The marker's track in any metric frame (ENU), on the GNSS clock.
    groups : (M,) int, optional
        Hover window (or transition) of each detection, for the jackknife.
    max_offset_s : float
        Search range, both signs (the contract bounds it to 1 s).
    step_s : float
        Scan step; the minimum is refined below it by a parabola.
    scale_px : float
        Cauchy scale of the fit's robust cost.
    min_moving_px : float
        Detections whose pixel moves less than this per 0.1 s are "still";
        without moving detections the offset is unobservable.
    max_points : int
        At most this many moving detections (and a third as many still ones)
        enter the fit, evenly spaced in time; the cost stays bounded on long runs.

    Returns
    -------
    TimeOffset
        ``method`` "image-vs-gnss" when the data determined it, "none" (offset
        0, std None) when they could not (no motion seen, too few points).
    """
    det_t_ns = np.asarray(det_t_ns, np.int64)
    det_uv = np.asarray(det_uv, float)
    fix_t_ns = np.asarray(fix_t_ns, np.int64)
    fix_xyz = np.asarray(fix_xyz, float)
    order = np.argsort(det_t_ns, kind="stable")
    det_t_ns, det_uv = det_t_ns[order], det_uv[order]
    groups = np.zeros(len(det_t_ns), int) if groups is None else np.asarray(groups)[order]
    n = len(det_t_ns)
    moving = _moving_mask(det_t_ns, det_uv, min_moving_px)
    n_moving = int(moving.sum())
    # Bound the cost: all moving detections carry the signal (up to a cap),
    # still ones only anchor the fit, so an evenly spaced subset of them will do.
    keep = _subsample(moving, max_moving=max_points, max_still=max_points // 3)
    det_t_ns, det_uv, groups, moving = det_t_ns[keep], det_uv[keep], groups[keep], moving[keep]
    if n < min_points or n_moving < 4 or len(fix_t_ns) < 2:
        return TimeOffset(offset_s=0.0, std_s=None, method="none", n_points=n, n_moving=n_moving)

    # Coarse scan over the whole range, then a fine one around its minimum:
    # the cost's well is as wide as a transition (~1 s), so 40 ms finds it.
    coarse = np.arange(-max_offset_s, max_offset_s + step_s / 2, 4 * step_s)
    coarse_costs = _scan(det_t_ns, det_uv, fix_t_ns, fix_xyz, coarse, scale_px, min_points)
    if not np.any(np.isfinite(coarse_costs)):
        return TimeOffset(offset_s=0.0, std_s=None, method="none", n_points=n, n_moving=n_moving)
    centre = float(coarse[int(np.nanargmin(coarse_costs))])
    offsets = centre + np.arange(-6, 7) * (step_s / 2)
    costs = _scan(det_t_ns, det_uv, fix_t_ns, fix_xyz, offsets, scale_px, min_points)
    best, cost_min = _minimum(offsets, costs)
    best = float(np.clip(best, -max_offset_s, max_offset_s))
    zero_cost = _scan(det_t_ns, det_uv, fix_t_ns, fix_xyz, np.array([0.0]), scale_px, min_points)[0]

    # Jackknife over groups that contain motion (at most 12, contiguous groups
    # merged): leave one out, rescan near the optimum.
    moving_groups = np.unique(groups[moving])
    estimates = []
    if len(moving_groups) >= 3:
        buckets = np.array_split(moving_groups, min(12, len(moving_groups)))
        fine = best + np.arange(-5, 6) * step_s
        for bucket in buckets:
            keep = ~np.isin(groups, bucket)
            c = _scan(det_t_ns[keep], det_uv[keep], fix_t_ns, fix_xyz, fine, scale_px, min_points)
            if np.any(np.isfinite(c)):
                estimates.append(_minimum(fine, c)[0])
    if len(estimates) >= 3:
        e = np.asarray(estimates)
        std = float(np.sqrt((len(e) - 1) / len(e) * np.sum((e - e.mean()) ** 2)))
    else:
        std = _curvature_std(offsets, costs, best, cost_min, n)
    # A minimum on the edge of the range is a range too small or no signal.
    on_edge = abs(best) >= max_offset_s - step_s
    std = max(std, step_s / 10) if std is not None and np.isfinite(std) else None
    return TimeOffset(
        offset_s=float(best),
        std_s=None if on_edge else std,
        method="image-vs-gnss",
        n_points=n,
        n_moving=n_moving,
        n_groups=int(len(moving_groups)),
        cost_min_px=float(cost_min),
        cost_zero_px=None if not np.isfinite(zero_cost) else float(zero_cost),
    )


def _subsample(moving: np.ndarray, max_moving: int, max_still: int) -> np.ndarray:
    """(M,) bool: evenly spaced subsets of the moving and the still detections."""
    keep = np.zeros(len(moving), bool)
    for mask, cap in ((moving, max_moving), (~moving, max_still)):
        idx = np.flatnonzero(mask)
        if len(idx) > cap:
            idx = idx[np.linspace(0, len(idx) - 1, cap).round().astype(int)]
        keep[idx] = True
    return keep


def _moving_mask(t_ns: np.ndarray, uv: np.ndarray, min_px: float) -> np.ndarray:
    """(M,) True where the image track moves faster than ``min_px`` per 0.1 s (neighbour differences)."""
    if len(t_ns) < 2:
        return np.zeros(len(t_ns), bool)
    dt = np.diff(t_ns).astype(float) * 1e-9
    speed = np.linalg.norm(np.diff(uv, axis=0), axis=1) / np.maximum(dt, 1e-6) * 0.1  # px per 0.1 s
    ok = dt < 0.5  # neighbours across a long gap say nothing about motion
    fast = (speed > min_px) & ok
    mask = np.zeros(len(t_ns), bool)
    mask[:-1] |= fast
    mask[1:] |= fast
    return mask


def _curvature_std(offsets: np.ndarray, costs: np.ndarray, best: float, cost_min: float, n: int) -> float | None:
    """Std of the offset from the cost's curvature (Gauss-Newton: var = 2 sigma^2 / S'')."""
    k = int(np.nanargmin(costs))
    if not (0 < k < len(costs) - 1) or not np.all(np.isfinite(costs[k - 1 : k + 2])):
        return None
    step = offsets[1] - offsets[0]
    # The cost is an RMS; S = n * cost^2 is the sum of squares.
    S = n * costs[k - 1 : k + 2] ** 2
    curvature = (S[0] - 2 * S[1] + S[2]) / step**2
    if curvature <= 0:
        return None
    sigma2 = n * cost_min**2 / max(n - 12, 1)
    return float(np.sqrt(2 * sigma2 / curvature))


@dataclass(frozen=True)
class Timing:
    """The camera's timing against the GNSS clock, refined through a calibrated camera.

    A detection stamped ``t`` at image row ``v`` shows the marker where it was
    at ``t - offset_s + v * line_time_s`` (GNSS clock).

    Attributes
    ----------
    offset_s, offset_std_s : the first row's offset and its std, seconds.
    line_time_s : rolling-shutter time per row, seconds (0 for a global shutter or when not estimated).
    line_time_std_s : its std, None when the data do not observe it.
    readout_s : line_time_s times the image height (the frame's readout).
    rolling_shutter : "estimated", "not observable (bounded)" or "not estimated".
    bound_m : when not estimated, how far the marker can move during a readout of
        ``max_readout_s`` at the fastest pairing speed (the effect left unmodelled), metres.
    n_points : detections the refinement used.
    """

    offset_s: float
    offset_std_s: float | None
    line_time_s: float
    line_time_std_s: float | None
    readout_s: float
    rolling_shutter: str
    bound_m: float | None = None
    n_points: int = 0

    @property
    def offset_ns(self) -> int:
        return int(round(self.offset_s * 1e9))

    def to_dict(self) -> dict:
        return {
            "offset_s": self.offset_s,
            "offset_std_s": self.offset_std_s,
            "line_time_s": self.line_time_s,
            "line_time_std_s": self.line_time_std_s,
            "readout_s": self.readout_s,
            "rolling_shutter": self.rolling_shutter,
            "unmodelled_motion_bound_m": self.bound_m,
            "n_points": self.n_points,
        }


def _timing_cost(
    project, det_t_ns: np.ndarray, det_uv: np.ndarray, fix_t_ns: np.ndarray, fix_xyz: np.ndarray,
    offset_s: float, line_time_s: float, scale_px: float,
) -> tuple[float, int]:
    t = det_t_ns - int(round(offset_s * 1e9)) + np.round(det_uv[:, 1] * line_time_s * 1e9).astype(np.int64)
    X, valid = interpolate_track(t, fix_t_ns, fix_xyz)
    if valid.sum() < 8:
        return np.nan, 0
    r = np.linalg.norm(project(X[valid]) - det_uv[valid], axis=1)
    return float(scale_px * np.sqrt(np.mean(np.log1p((r / scale_px) ** 2)))), int(valid.sum())


def refine_timing(
    project,
    det_t_ns: np.ndarray,
    det_uv: np.ndarray,
    fix_t_ns: np.ndarray,
    fix_xyz: np.ndarray,
    offset_s: float,
    height_px: int,
    max_readout_s: float = 0.06,
    span_s: float = 0.06,
    step_s: float = 0.004,
    scale_px: float = 2.0,
    min_moving_px: float = 1.0,
    speed_mps: float | None = None,
) -> Timing:
    """The offset and the rolling-shutter line time that make a calibrated camera reproject the moving marker best.

    A scan over offsets within ``span_s`` of ``offset_s`` and readouts
    0..``max_readout_s``, each cost a robust RMS reprojection error of the
    GNSS track (interpolated at the detections' corrected instants) through
    ``project``; the minimum is refined by parabolas. The line time is
    observable when the moving marker is seen at different rows: a readout
    shift that a single offset cannot absorb. When its minimum is on the edge
    or its curvature cannot bound it, ``rolling_shutter`` says "not observable
    (bounded)" and ``bound_m`` is the motion during ``max_readout_s``.

    Parameters
    ----------
    project : callable (K, 3) ENU metres -> (K, 2) pixels (the calibrated camera)
    det_t_ns : (M,) int64, det_uv : (M, 2) px
        Detections (camera clock).
    fix_t_ns : (N,) int64, fix_xyz : (N, 3) m
        The marker's GNSS track.
    offset_s : the first estimate (:func:`estimate_time_offset`).
    height_px : image rows (the readout is the line time times this).
    speed_mps : the fastest pairing speed, for the bound.
    """
    det_t_ns = np.asarray(det_t_ns, np.int64)
    det_uv = np.asarray(det_uv, float)
    order = np.argsort(det_t_ns, kind="stable")
    det_t_ns, det_uv = det_t_ns[order], det_uv[order]
    moving = _moving_mask(det_t_ns, det_uv, min_moving_px)
    keep = _subsample(moving, max_moving=1500, max_still=300)
    det_t_ns, det_uv, moving = det_t_ns[keep], det_uv[keep], moving[keep]
    bound = None if speed_mps is None else float(speed_mps * max_readout_s)
    if moving.sum() < 8:
        return Timing(offset_s, None, 0.0, None, 0.0, "not estimated", bound, int(len(det_t_ns)))
    offsets = offset_s + np.arange(-span_s, span_s + step_s / 2, step_s)
    readouts = np.linspace(0.0, max_readout_s, 13) if max_readout_s > 0 else np.array([0.0])
    best_off = np.full(len(readouts), np.nan)
    best_cost = np.full(len(readouts), np.nan)
    n_used = 0
    for i, ro in enumerate(readouts):
        lt = ro / height_px
        costs = np.array([_timing_cost(project, det_t_ns, det_uv, fix_t_ns, fix_xyz, o, lt, scale_px)[0] for o in offsets])
        if not np.any(np.isfinite(costs)):
            continue
        best_off[i], best_cost[i] = _minimum(offsets, costs)
    if not np.any(np.isfinite(best_cost)):
        return Timing(offset_s, None, 0.0, None, 0.0, "not estimated", bound, 0)
    k = int(np.nanargmin(best_cost))
    readout, cost_min = (_minimum(readouts, best_cost) if len(readouts) > 1 else (0.0, best_cost[0]))
    readout = float(np.clip(readout, 0.0, max_readout_s))
    off = float(np.interp(readout, readouts, np.nan_to_num(best_off, nan=offset_s))) if len(readouts) > 1 else float(best_off[0])
    lt = readout / height_px
    # Stds from the cost's curvature (Gauss-Newton), one dimension at a time.
    n_used = _timing_cost(project, det_t_ns, det_uv, fix_t_ns, fix_xyz, off, lt, scale_px)[1]
    fine = off + np.array([-1.0, 0.0, 1.0]) * step_s
    c_off = np.array([_timing_cost(project, det_t_ns, det_uv, fix_t_ns, fix_xyz, o, lt, scale_px)[0] for o in fine])
    off_std = _curvature_std(fine, c_off, off, float(np.nanmin(c_off)), max(n_used, 13))
    if max_readout_s <= 0 or len(readouts) < 3:
        return Timing(off, off_std, 0.0, None, 0.0, "not estimated", bound, n_used)
    ro_std = _curvature_std(readouts, best_cost, readout, float(cost_min), max(n_used, 13))
    if k == 0 and np.all(np.isfinite(best_cost[:2])):
        # A minimum at zero (a global shutter): the curvature of a parabola with its vertex there.
        n = max(n_used, 13)
        S0, S1 = n * best_cost[0] ** 2, n * best_cost[1] ** 2
        curvature = 2 * (S1 - S0) / readouts[1] ** 2
        sigma2 = n * best_cost[0] ** 2 / max(n - 12, 1)
        ro_std = float(np.sqrt(2 * sigma2 / curvature)) if curvature > 0 else None
        readout, off = 0.0, float(best_off[0])
        lt = 0.0
    on_edge = k == len(readouts) - 1
    observable = ro_std is not None and not on_edge and ro_std < 0.5 * max_readout_s
    if not observable:
        # Keep the first row's offset at the best global-shutter fit.
        return Timing(float(best_off[0]) if np.isfinite(best_off[0]) else off, off_std, 0.0, None, 0.0, "not observable (bounded)", bound, n_used)
    return Timing(off, off_std, lt, ro_std / height_px, readout, "estimated", None, n_used)
