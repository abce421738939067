"""Fly-through legs: every GNSS fix taken while the marker crosses the image is a 3D-2D pair.

A leg is the straight flight from one waypoint to the next when the drone does
not stop there (NAV_WAYPOINT hold 0, constant speed). Two sources, best first:
``leg`` events on ``/events`` (the recorder's, or any writer's), and the GNSS
track alone (constant-velocity stretches of a few seconds).

Pairing: each fix on a leg (its own measurement time, GNSS clock) is paired
with the marker's pixel interpolated along the image track at that instant.
A frame stamped ``t`` on the camera clock shows row ``v`` as it was at
``t - offset_s + v * line_time_s`` on the GNSS clock (rolling shutter; the
offset holds the rest). The image track is interpolated by a cubic through the
four detections around the instant (the marker's image path is smooth over a
few tenths of a second; a straight line would cut its curve).

Each pair is weighted by its timing uncertainty as well as the detector's:
a time error ``dt`` moves the pixel by ``|image velocity| dt`` and the marker
by ``speed dt``, so ``sigma_px^2 = sigma_det^2 + (|du/dt| std_t)^2`` and
per axis ``sigma_m^2 = sigma_fix^2 + (v_axis std_t)^2``.

Pure numpy; times are integer nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from dronecal_field.pipeline.hover import HoverWindow
from dronecal_field.pipeline.points import NOISE_FLOOR_M, NOISE_FLOOR_PX, FixNoise, WaypointPoint, fix_rank

SOURCES = ("event", "gnss_track")


@dataclass(frozen=True)
class Leg:
    """One constant-speed stretch of flight, on the GNSS clock.

    ``index`` numbers the run's legs in time order; ``speed_mps`` is the
    median ground-plus-vertical speed of the fixes on it (None when unknown).
    """

    index: int
    start_ns: int
    end_ns: int
    source: str
    speed_mps: float | None = None

    @property
    def duration_s(self) -> float:
        return (self.end_ns - self.start_ns) * 1e-9


@dataclass(frozen=True)
class LegOptions:
    """Thresholds of leg finding and pairing (defaults for RTK at 1-3 m/s)."""

    trim_s: float = 0.3  # leave out each end of a leg (accelerating into and out of it)
    min_speed_mps: float = 0.5  # slower is not a leg (track source)
    max_speed_dev: float = 0.15  # speed within this fraction of the leg's median (track source)
    max_turn_deg: float = 15.0  # heading within this of the leg's median direction (track source)
    min_duration_s: float = 2.5  # shorter stretches are transitions, not legs (track source)
    max_frame_gap_s: float = 0.35  # the detections around a fix may be at most this far apart
    sigma_px: float = 0.3  # detector noise on a moving (blurred, smaller) marker, px
    sigma_m_floor: float = 0.005  # per-fix 3D floor, metres


def legs_from_intervals(intervals: Sequence[tuple[int, int]], source: str = "event") -> list[Leg]:
    """Legs from (start_ns, end_ns) intervals (e.g. ``leg`` events), sorted and numbered; empty ones skipped."""
    clean = sorted((int(a), int(b)) for a, b in intervals if b > a)
    return [Leg(index=k, start_ns=a, end_ns=b, source=source) for k, (a, b) in enumerate(clean)]


def track_velocity(t_ns: np.ndarray, enu_m: np.ndarray, baseline_s: float = 0.4, max_gap_s: float = 1.0) -> np.ndarray:
    """(N, 3) m/s velocity of a GNSS track by central differences over about ``baseline_s``.

    NaN where the neighbours are too far (a dropout) or missing.
    """
    t = np.asarray(t_ns, np.int64)
    p = np.asarray(enu_m, float).reshape(-1, 3)
    n = len(t)
    v = np.full((n, 3), np.nan)
    if n < 3:
        return v
    half = int(baseline_s * 0.5e9)
    lo = np.clip(np.searchsorted(t, t - half, side="left"), 0, n - 1)
    hi = np.clip(np.searchsorted(t, t + half, side="right") - 1, 0, n - 1)
    dt = (t[hi] - t[lo]).astype(float) * 1e-9
    ok = (dt > 0.5 * baseline_s) & (dt < max_gap_s + baseline_s)
    v[ok] = (p[hi[ok]] - p[lo[ok]]) / dt[ok, None]
    return v


CHORD_END_FIXES = 3  # a leg's ends are each averaged over this many fixes before its length is taken


def chord_speed(t_ns: np.ndarray, enu_m: np.ndarray) -> float | None:
    """A stretch's length over its duration (m/s on the fixes' clock), its ends each averaged over
    :data:`CHORD_END_FIXES` fixes; None when it has too few fixes.

    Not the fixes' differentiated speed: a GNSS without RTK (PX4 SITL: 0.56 m per fix at 5 Hz) differentiates
    to 3 m/s on legs flown at 1.3 m/s, while a leg's averaged ends are good to a fraction of its length.
    """
    if len(t_ns) < 2 * CHORD_END_FIXES:
        return None
    n = CHORD_END_FIXES
    dt = 1e-9 * float(np.mean(t_ns[-n:]) - np.mean(t_ns[:n]))
    if dt <= 0:
        return None
    return float(np.linalg.norm(np.mean(enu_m[-n:], axis=0) - np.mean(enu_m[:n], axis=0)) / dt)


def legs_from_track(t_ns: np.ndarray, enu_m: np.ndarray, options: LegOptions = LegOptions()) -> list[Leg]:
    """Constant-velocity stretches of a GNSS track (N,), (N, 3): speed above ``min_speed_mps``,
    within ``max_speed_dev`` of the stretch's reference (its first second's median velocity),
    heading within ``max_turn_deg`` of it, at least ``min_duration_s`` long. A turn at a
    fly-through waypoint ends one stretch and starts the next.
    """
    t = np.asarray(t_ns, np.int64)
    v = track_velocity(t, enu_m)
    speed = np.linalg.norm(v, axis=1)
    moving = np.isfinite(speed) & (speed > options.min_speed_mps)
    cos_turn = np.cos(np.radians(options.max_turn_deg))
    legs: list[Leg] = []
    n = len(t)
    i = 0
    while i < n:
        if not moving[i]:
            i += 1
            continue
        head = i + max(1, int(np.searchsorted(t[i:], t[i] + 1_000_000_000)))
        ref = np.median(v[i : min(head, n)][moving[i : min(head, n)]], axis=0)
        sref = float(np.linalg.norm(ref))
        j = i
        while j + 1 < n and moving[j + 1] and (t[j + 1] - t[j]) < 1_000_000_000:
            vj = v[j + 1]
            if abs(speed[j + 1] - sref) > options.max_speed_dev * sref or (vj @ ref) < cos_turn * speed[j + 1] * sref:
                break
            j += 1
        if (t[j] - t[i]) * 1e-9 >= options.min_duration_s:
            chord = chord_speed(t[i : j + 1], enu_m[i : j + 1])
            sm = chord if chord is not None else float(np.median(speed[i : j + 1]))
            legs.append(Leg(index=len(legs), start_ns=int(t[i]), end_ns=int(t[j]), source="gnss_track", speed_mps=sm))
            i = j + 1
        else:
            i += 1  # an acceleration or a turn: try from the next fix
    return legs


OVERSHOOT_FRACTION = 0.25  # a cubic may pass its bracketing samples by this share of its four samples' span ...
OVERSHOOT_PX = 2.0  # ... plus this, else the instant is not paired


def cubic_track_at(
    t_query_ns: np.ndarray,
    t_ns: np.ndarray,
    values: np.ndarray,
    max_gap_s: float = 0.35,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A sampled track interpolated by the cubic through the four samples around each instant.

    Parameters
    ----------
    t_query_ns : (M,) int64
    t_ns : (N,) int64 increasing (distinct), values : (N, D)
    max_gap_s : float
        The four samples must be consecutive gaps no longer than this.

    An instant is also invalid when the cubic there leaves the span of the
    two samples around it by more than ``OVERSHOOT_FRACTION`` of the four
    samples' span plus ``OVERSHOOT_PX`` (a jumpy track, not a smooth one).

    Returns
    -------
    at : (M, D), rate : (M, D) per second (derivative of the cubic), valid : (M,) bool
    """
    q = np.asarray(t_query_ns, np.int64)
    t = np.asarray(t_ns, np.int64)
    y = np.asarray(values, float)
    y = y.reshape(len(t), -1) if y.size else np.zeros((len(t), y.shape[-1] if y.ndim > 1 else 1))
    m, d = len(q), y.shape[1]
    at = np.full((m, d), np.nan)
    rate = np.full((m, d), np.nan)
    valid = np.zeros(m, bool)
    if len(t) < 4 or m == 0:
        return at, rate, valid
    k = np.searchsorted(t, q, side="right")  # t[k-1] <= q < t[k]
    valid = (k >= 2) & (k <= len(t) - 2)
    kk = np.clip(k, 2, len(t) - 2)
    idx = kk[:, None] + np.arange(-2, 2)[None, :]  # (M, 4)
    tt = (t[idx] - q[:, None]).astype(float) * 1e-9  # sample times relative to the instant, s
    gaps = np.diff(tt, axis=1)
    valid &= np.all((gaps > 0) & (gaps <= max_gap_s), axis=1)
    # Lagrange weights at 0 and their derivatives.
    w = np.ones((m, 4))
    dw = np.zeros((m, 4))
    for i in range(4):
        others = [j for j in range(4) if j != i]
        denom = np.ones(m)
        for j in others:
            denom *= tt[:, i] - tt[:, j]
        num = np.ones(m)
        for j in others:
            num *= -tt[:, j]
        dnum = np.zeros(m)
        for j in others:
            prod = np.ones(m)
            for l in others:
                if l != j:
                    prod *= -tt[:, l]
            dnum += prod
        w[:, i] = num / np.where(denom == 0, 1.0, denom)
        dw[:, i] = dnum / np.where(denom == 0, 1.0, denom)
    yy = y[idx]  # (M, 4, D)
    at = np.einsum("mi,mid->md", w, yy)
    rate = np.einsum("mi,mid->md", dw, yy)
    # A smooth track stays near the span of its two bracketing samples; a cubic swinging far past it is fitting
    # jitter or a jump (a marker close to the camera, a false detection), and its pair would be wrong by as much.
    lo, hi = np.minimum(yy[:, 1], yy[:, 2]), np.maximum(yy[:, 1], yy[:, 2])
    slack = OVERSHOOT_FRACTION * (yy.max(axis=1) - yy.min(axis=1)) + OVERSHOOT_PX
    valid &= np.all((at >= lo - slack) & (at <= hi + slack), axis=1)
    at[~valid] = np.nan
    rate[~valid] = np.nan
    return at, rate, valid


def detection_times_ns(det_t_ns: np.ndarray, det_v_px: np.ndarray, offset_ns: int, line_time_s: float) -> np.ndarray:
    """(M,) GNSS-clock instants of detections (M,) at rows ``det_v_px`` (M,): stamp - offset + v * line_time."""
    return np.asarray(det_t_ns, np.int64) - int(offset_ns) + np.round(np.asarray(det_v_px, float) * line_time_s * 1e9).astype(np.int64)


def leg_points(
    legs: list[Leg],
    fix_t_ns: np.ndarray,
    marker_enu_m: np.ndarray,
    marker_velocity_mps: np.ndarray,
    fix_sigma_m: np.ndarray,
    fix_types: list[str | None],
    det_t_ns: np.ndarray,
    det_uv_px: np.ndarray,
    offset_ns: int,
    line_time_s: float,
    time_std_s: float,
    min_fix: str,
    first_index: int,
    options: LegOptions = LegOptions(),
    noise: FixNoise | None = None,
) -> list[WaypointPoint]:
    """One 3D-2D point per GNSS fix on the legs, weighted by its timing uncertainty.

    Parameters
    ----------
    legs : the legs (GNSS clock)
    fix_t_ns : (N,) int64, marker_enu_m : (N, 3) m, marker_velocity_mps : (N, 3) m/s,
    fix_sigma_m : (N, 3) m, fix_types : (N,)
        The marker track at its fixes, its velocity, the receiver's std, fix types.
    det_t_ns : (M,) int64, det_uv_px : (M, 2)
        Detections, stamped on the camera clock.
    offset_ns : int
        Camera stamp minus capture time of the first image row (``TimeOffset.offset_ns``).
    line_time_s : float
        Rolling-shutter time per image row, seconds (0: a global shutter).
    time_std_s : float
        Std of the pairing instant (the offset's and the line time's), seconds.
    min_fix : str
        Fixes worse than this are not paired.
    first_index : int
        ``window.index`` of the first point (after the hover windows).
    noise : FixNoise, optional
        The measured per-fix noise. Each point's 3D sigma is then its white
        part plus its correlated part inflated by the number of the leg's
        points it is correlated with (``sum_j rho(t_i - t_j)``): a correlated
        error shifts the whole leg, which carries no more information about it
        than one point. Without it: the receiver's std and ``options.sigma_px``.

    Returns
    -------
    list of WaypointPoint, each with a one-instant ``window`` of source ``"leg"``
    whose ``seq`` is the leg's index.
    """
    det_t = np.asarray(det_t_ns, np.int64)
    uv = np.asarray(det_uv_px, float).reshape(-1, 2)
    tc = detection_times_ns(det_t, uv[:, 1], offset_ns, line_time_s)
    order = np.argsort(tc, kind="stable")
    tc, uv = tc[order], uv[order]
    distinct = np.r_[True, np.diff(tc) > 0]
    tc, uv = tc[distinct], uv[distinct]
    fix_t = np.asarray(fix_t_ns, np.int64)
    X = np.asarray(marker_enu_m, float)
    V = np.nan_to_num(np.asarray(marker_velocity_mps, float))
    S = np.asarray(fix_sigma_m, float)
    trim = int(options.trim_s * 1e9)
    out: list[WaypointPoint] = []
    for leg in legs:
        inside = np.flatnonzero((fix_t >= leg.start_ns + trim) & (fix_t <= leg.end_ns - trim))
        if len(inside) == 0:
            continue
        near = (tc >= leg.start_ns) & (tc <= leg.end_ns)  # the cubic must not reach round the corner into the next leg
        at, rate, valid = cubic_track_at(fix_t[inside], tc[near], uv[near], options.max_frame_gap_s)
        good = np.array([valid[j] and fix_rank(fix_types[i]) >= fix_rank(min_fix) for j, i in enumerate(inside)], bool)
        t_leg = fix_t[inside[good]] * 1e-9
        for j, i in enumerate(inside):
            if not good[j]:
                continue
            t = int(fix_t[i])
            window = HoverWindow(index=first_index + len(out), start_ns=t, end_ns=t, source="leg", seq=leg.index)
            if noise is None:
                sig_fix = np.maximum(np.nan_to_num(S[i], nan=0.0), options.sigma_m_floor)
                sig_px = options.sigma_px
            else:
                shared = float(noise.rho(t * 1e-9 - t_leg).sum())
                sig_fix = np.full(3, max(float(np.sqrt(noise.sigma_white_m**2 + noise.sigma_corr_m**2 * shared)), NOISE_FLOOR_M))
                sig_px = NOISE_FLOOR_PX
            sigma_m = np.sqrt(sig_fix**2 + (V[i] * time_std_s) ** 2)
            sigma_px = float(np.sqrt(sig_px**2 + (np.linalg.norm(rate[j]) * time_std_s) ** 2 / 2.0))
            out.append(
                WaypointPoint(
                    window=window, stable_ns=(t, t), n_fixes=1, n_detections=4, worst_fix=fix_types[i],
                    marker_enu_m=X[i].copy(), sigma_enu_m=sigma_m, uv_px=at[j], sigma_px=sigma_px,
                    scatter_enu_m=np.zeros(3), scatter_px=0.0, scatter_image_m=None,
                )
            )
    return out
