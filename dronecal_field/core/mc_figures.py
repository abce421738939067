"""The Monte-Carlo's summary figures from its per-trial values, compiled (numba).

Every figure ``core.uncertainty.monte_carlo`` reports (parameter spreads,
RMS projection and ground errors, the RMS statistics, percentiles) in one
compiled call, with the arithmetic of the numpy expressions it replaces
(sample variances with ddof 1, np.percentile's 'linear' rule). The numpy
path took ~40 calls: 0.4 ms per Monte-Carlo warm, 1-2 ms when the
interpreter's caches are cold, as in a single ``uncertainty`` run or
right after other work (0.02 ms of every trial at k = 500). Only for
trials that all finished (finite values); the caller keeps numpy's NaN-aware
path for the others. Pure functions on arrays.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def ground_errors(
    hits: np.ndarray,  # (K, 3, 3) where each trial's rays of the probe point and the two track points meet the ground
    point: np.ndarray,  # (3,) the probe point
    track_length_m: float,  # the true distance between the two track points
    base_s: float,  # the time the vehicle takes between them
    pos_cm: np.ndarray,  # (K,) out: horizontal position error of the probe point, cm
    speed_kmh: np.ndarray,  # (K,) out: speed error along the track, km/h
) -> None:
    """Per-trial ground position error (cm) and speed error (km/h) 15 m out."""
    for k in range(hits.shape[0]):
        dx = hits[k, 0, 0] - point[0]
        dy = hits[k, 0, 1] - point[1]
        pos_cm[k] = 100.0 * np.sqrt(dx * dx + dy * dy)
        ex = hits[k, 2, 0] - hits[k, 1, 0]
        ey = hits[k, 2, 1] - hits[k, 1, 1]
        ez = hits[k, 2, 2] - hits[k, 1, 2]
        speed_kmh[k] = np.abs(np.sqrt(ex * ex + ey * ey + ez * ez) - track_length_m) / base_s * 3.6


@njit(cache=True, nogil=True)
def _std(v: np.ndarray) -> float:
    n = v.shape[0]
    mean = 0.0
    for i in range(n):
        mean += v[i]
    mean /= n
    s = 0.0
    for i in range(n):
        d = v[i] - mean
        s += d * d
    return np.sqrt(s / (n - 1))


@njit(cache=True, nogil=True)
def _rms(v: np.ndarray) -> float:
    s = 0.0
    for i in range(v.shape[0]):
        s += v[i] * v[i]
    return np.sqrt(s / v.shape[0])


@njit(cache=True, nogil=True)
def _percentiles(v: np.ndarray, q: np.ndarray, out: np.ndarray) -> None:
    """np.percentile(v, q) with the default 'linear' rule and its lerp, v (K,) with K >= 2."""
    s = np.sort(v)
    n = s.shape[0]
    for j in range(q.shape[0]):
        pos = q[j] / 100.0 * (n - 1)
        lo = min(int(np.floor(pos)), n - 2)
        frac = pos - lo
        a, b = s[lo], s[lo + 1]
        diff = b - a
        out[j] = b - diff * (1.0 - frac) if frac >= 0.5 else a + diff * frac


@njit(cache=True, nogil=True)
def summary(
    rms: np.ndarray,  # (K,) each trial's RMS reprojection error, px
    projection: np.ndarray,  # (K,) each trial's RMS projection difference over the points, px
    ground_projection: np.ndarray,  # (K,) the same over the ground
    pos_cm: np.ndarray,  # (K,)
    speed_kmh: np.ndarray,  # (K,)
    params: np.ndarray,  # (P, K) each parameter's value in every trial
    q: np.ndarray,  # (Q,) percentiles
    param_std: np.ndarray,  # (P,) out: sample standard deviations
    pct: np.ndarray,  # (3, Q) out: percentiles of rms, pos_cm, speed_kmh
) -> tuple[float, float, float, float, float, float, float, float]:
    """Summary of K >= 2 finished trials: (rms mean, max, variance (ddof 1), RMS of projection, ground projection, pos_cm, speed_kmh, 0)."""
    for p in range(params.shape[0]):
        param_std[p] = _std(params[p])
    _percentiles(rms, q, pct[0])
    _percentiles(pos_cm, q, pct[1])
    _percentiles(speed_kmh, q, pct[2])
    n = rms.shape[0]
    mean = 0.0
    top = rms[0]
    for i in range(n):
        mean += rms[i]
        top = max(top, rms[i])
    mean /= n
    sd = _std(rms)
    return mean, top, sd * sd, _rms(projection), _rms(ground_projection), _rms(pos_cm), _rms(speed_kmh), 0.0
