"""Per-waypoint 3D-2D points: robust positions, measured sigmas, and why a window was dropped.

For each hover window, over its settled part:
- 3D and 2D over the same instants: the marker's ENU position (GNSS antenna
  + the ``marker.offset_frd_m`` lever arm rotated by the vehicle's attitude)
  at EACH FIX of the settled part, paired with the marker centre's pixel at
  that fix's capture time (the image track between decoded frames,
  :func:`track_at`); the point is the mean of the paired samples without the
  wild ones (:func:`paired_centre`). The 3D scatter (1.4826 MAD) is measured
  on the fixes, the 2D scatter on the detections.
Pairing matters because the drone drifts by centimetres during a hold: the
median of the fixes and the median of the detections are taken at different
instants, so they describe slightly different marker positions, and that
mismatch (not the RTK noise) limited the principal point. Pairing at the
fixes rather than at the decoded frames (``pair_at="detections"``, the GNSS
track interpolated at each frame) keeps every fix: where the RTK noise is
white the 3D centre's error falls with the number of fixes averaged, and a few
evenly spaced frames are enough to follow a drift that is smooth over
tenths of a second (measured on the issue 5 benchmark: the principal point
error of the worst run 11.5 -> 6.8 px, projection error 0.33 -> 0.19 px).
Without a usable pairing the window falls back to the two separate medians.
The scatter becomes the point's sigma for the Monte-Carlo, floored by the
receiver's own reported accuracy (an RTK bias is invisible in the scatter)
and by the detector's sub-pixel precision.

A window is dropped, with the reason kept for the report, when it has too
few fixes (a GNSS dropout), a fix worse than ``min_fix``, too few detections,
or a scatter far above the other windows'.

Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from dronecal_field.pipeline.hover import HoverWindow

# Worst to best; "unknown" (a writer that did not say) ranks just below "3d".
FIX_TYPES: tuple[str, ...] = ("no_fix", "2d", "unknown", "3d", "dgps", "rtk_float", "rtk_fixed")
MAD_TO_STD = 1.4826
NOISE_FLOOR_M = 0.0005  # with a measured noise model: the 3D sigma of a point is at least this
NOISE_FLOOR_PX = 0.05  # ... and its own 2D sigma this (the detector's noise is in the measured white part)


def fix_rank(fix_type: str | None) -> int:
    """Rank of a fix type in FIX_TYPES (None and unrecognised values count as "unknown")."""
    if fix_type is None or fix_type not in FIX_TYPES:
        return FIX_TYPES.index("unknown")
    return FIX_TYPES.index(fix_type)


def enu_from_frd(rpy_rad: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations from the vehicle body (FRD) to ENU.

    Parameters
    ----------
    rpy_rad : (N, 3)
        Roll, pitch, yaw in radians as MAVLink ATTITUDE gives them: yaw from
        north, clockwise; the body-to-NED rotation is Rz(yaw) Ry(pitch) Rx(roll).
    """
    rpy = np.atleast_2d(np.asarray(rpy_rad, float))
    cr, sr = np.cos(rpy[:, 0]), np.sin(rpy[:, 0])
    cp, sp = np.cos(rpy[:, 1]), np.sin(rpy[:, 1])
    cy, sy = np.cos(rpy[:, 2]), np.sin(rpy[:, 2])
    ned = np.empty((len(rpy), 3, 3))
    ned[:, 0, 0] = cy * cp
    ned[:, 0, 1] = cy * sp * sr - sy * cr
    ned[:, 0, 2] = cy * sp * cr + sy * sr
    ned[:, 1, 0] = sy * cp
    ned[:, 1, 1] = sy * sp * sr + cy * cr
    ned[:, 1, 2] = sy * sp * cr - cy * sr
    ned[:, 2, 0] = -sp
    ned[:, 2, 1] = cp * sr
    ned[:, 2, 2] = cp * cr
    # NED -> ENU swaps the first two axes and flips the third.
    return ned[:, [1, 0, 2], :] * np.array([1.0, 1.0, -1.0])[None, :, None]


def lever_arm_enu(offset_frd_m: np.ndarray, rpy_rad: np.ndarray) -> np.ndarray:
    """(N, 3) ENU vector from the antenna to the marker centre for attitudes (N, 3)."""
    return np.einsum("nij,j->ni", enu_from_frd(rpy_rad), np.asarray(offset_frd_m, float))


def attitude_at(t_ns: np.ndarray, att_t_ns: np.ndarray, att_rpy_rad: np.ndarray, max_gap_s: float = 1.0) -> np.ndarray:
    """(N, 3) roll, pitch, yaw interpolated at ``t_ns`` (N,), yaw unwrapped so 359->1 deg is 2 deg.

    Times outside the attitude stream take the nearest sample; inside a gap
    longer than ``max_gap_s`` too (holds are still, so the nearest is close).
    """
    t = np.asarray(t_ns, np.int64)
    at = np.asarray(att_t_ns, np.int64)
    rpy = np.asarray(att_rpy_rad, float)
    if len(at) == 0:
        raise ValueError("no attitude samples")
    if len(at) == 1:
        return np.repeat(rpy[:1], len(t), 0)
    x = (t - at[0]).astype(float)
    xp = (at - at[0]).astype(float)
    yaw = np.unwrap(rpy[:, 2])
    out = np.stack([np.interp(x, xp, rpy[:, 0]), np.interp(x, xp, rpy[:, 1]), np.interp(x, xp, yaw)], -1)
    k = np.clip(np.searchsorted(at, t), 1, len(at) - 1)
    gap = (at[k] - at[k - 1]) > max_gap_s * 1e9
    nearest = np.where(np.abs(t - at[k - 1]) <= np.abs(at[k] - t), k - 1, k)
    out[gap] = np.c_[rpy[nearest[gap], :2], yaw[nearest[gap]]]
    out[:, 2] = (out[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return out


@dataclass(frozen=True)
class PointOptions:
    """Thresholds of the per-window stage (defaults for RTK and a few-second hold)."""

    settle_s: float = 1.0  # ignore the first second of a hold (arrival overshoot)
    tail_s: float = 0.2  # and the last moments before leaving
    min_fix: str = "rtk_fixed"
    min_fixes: int = 3
    min_detections: int = 3
    sigma_px_floor: float = 0.1  # the detector's sub-pixel precision on a still marker
    sigma_m_floor: float = 0.002
    outlier_factor: float = 4.0  # scatter above this many times the median window's is outlying
    outlier_floor_m: float = 0.05  # ... and above this (a calm hold is not an outlier)
    outlier_floor_px: float = 1.0
    paired: bool = True  # 3D and 2D over the same instants (False: separate medians of fixes and detections)
    pair_at: str = "fixes"  # "fixes": the image track at each fix; "detections": the GNSS track at each detection
    pair_max_gap_s: float = 0.5  # a sample pairs only when the other stream has samples this close on both sides
    pair_across_gaps: bool = False  # "fixes": every fix pairs with the image track interpolated across its gaps (sparse frames: keyframe bursts of /camera/video)

    def __post_init__(self) -> None:
        if self.pair_at not in ("fixes", "detections"):
            raise ValueError(f"pair_at {self.pair_at!r}: use 'fixes' or 'detections'")


@dataclass(frozen=True, eq=False)
class WaypointPoint:
    """One hover window's 3D-2D correspondence, or the reason it has none.

    ``marker_enu_m`` (3,) and ``uv_px`` (2,) are robust centres over the
    window's settled part; ``sigma_enu_m`` (3,) and ``sigma_px`` their
    per-axis standard deviations; ``dropped`` None for a usable point.
    """

    window: HoverWindow
    stable_ns: tuple[int, int]
    n_fixes: int
    n_detections: int
    worst_fix: str | None
    marker_enu_m: np.ndarray | None = None
    sigma_enu_m: np.ndarray | None = None
    uv_px: np.ndarray | None = None
    sigma_px: float | None = None
    scatter_enu_m: np.ndarray | None = None
    scatter_px: float | None = None
    scatter_image_m: float | None = None
    dropped: str | None = None

    @property
    def used(self) -> bool:
        return self.dropped is None

    def with_drop(self, reason: str) -> "WaypointPoint":
        from dataclasses import replace

        return replace(self, dropped=reason)


SHORT_SETTLED_S = 0.5  # a settled part this short is a hold at a leg's end, not a hover point


def _too_few_detections(n: int, window: HoverWindow, stable_ns: tuple[int, int], options: PointOptions) -> str:
    """Why a hold with too few detections gives no point; a fly-through leg's short end hold says it is one."""
    settled_s = max(stable_ns[1] - stable_ns[0], 0) * 1e-9
    if settled_s < SHORT_SETTLED_S:
        # ArduCopter holds whole seconds: a 1 s hold ends a leg (plan --sampling through), its frames serve the leg
        return (f"{n} marker detections in the settled part; need {options.min_detections}: a {window.duration_s:.1f} s hold "
                f"(a leg's end) leaves {settled_s:.1f} s after --settle-s {options.settle_s:g}; its frames serve the leg")
    return f"{n} marker detections in the settled part; need {options.min_detections}"


def robust_centre(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis median (D,) and robust std (D,) = 1.4826 MAD of ``values`` (N, D)."""
    v = np.asarray(values, float)
    med = np.median(v, axis=0)
    return med, MAD_TO_STD * np.median(np.abs(v - med), axis=0)


def paired_centre(xyz_m: np.ndarray, uv_px: np.ndarray, k: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """Centres (3,), (2,) of paired 3D/2D samples (K, 3), (K, 2): the mean of the samples that are not wild.

    A mean, not a per-axis median: the projection is nearly linear over a
    few centimetres of drift, so the means of paired samples correspond
    (medians per axis need not), and the mean uses every sample (measured
    on the issue 5 benchmark: half the principal point error of the
    medians). Samples beyond ``k`` robust std (1.4826 MAD) of the median on
    any axis, 3D or 2D, are left out (a detector flipping between corners).
    """
    v = np.c_[np.asarray(xyz_m, float), np.asarray(uv_px, float)]
    med, std = robust_centre(v)
    keep = np.all(np.abs(v - med) <= k * std + 1e-9, axis=1)
    centre = v[keep].mean(0) if keep.any() else med
    return centre[:3], centre[3:]


def marker_track_at(
    t_ns: np.ndarray,
    fix_t_ns: np.ndarray,
    antenna_enu_m: np.ndarray,
    offset_frd_m: np.ndarray,
    att_t_ns: np.ndarray | None,
    att_rpy_rad: np.ndarray | None,
    max_gap_s: float = 0.5,
) -> tuple[np.ndarray, np.ndarray]:
    """The marker's ENU position at arbitrary instants, and whether the fixes bracket each closely.

    The antenna track is interpolated linearly between fixes; the lever arm
    is rotated by the attitude interpolated at the same instant.

    Parameters
    ----------
    t_ns : (M,) int64
        Instants on the GNSS clock (e.g. detection stamps minus the camera offset).
    fix_t_ns : (N,) int64 increasing, antenna_enu_m : (N, 3) metres
        The GNSS antenna track.
    offset_frd_m : (3,) metres
        Antenna to marker centre in the body frame (FRD).
    att_t_ns : (K,) int64 increasing, att_rpy_rad : (K, 3), or None
        Attitude samples (roll, pitch, yaw); None: no lever-arm rotation
        (the marker is taken at the antenna).
    max_gap_s : float
        An instant is ``bracketed`` when fixes exist before and after it,
        each within this many seconds, or a fix falls on it (:func:`track_at`).

    Returns
    -------
    marker_enu_m : (M, 3) metres
    bracketed : (M,) bool
    """
    t = np.asarray(t_ns, np.int64)
    out, bracketed = track_at(t, fix_t_ns, np.asarray(antenna_enu_m, float).reshape(-1, 3), max_gap_s)
    if len(fix_t_ns) and att_t_ns is not None and att_rpy_rad is not None and len(att_t_ns):
        out = out + lever_arm_enu(offset_frd_m, attitude_at(t, att_t_ns, att_rpy_rad))
    return out, bracketed


def track_at(t_ns: np.ndarray, sample_t_ns: np.ndarray, values: np.ndarray, max_gap_s: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """A sampled track (e.g. the marker's pixel) interpolated linearly at ``t_ns``, and whether samples bracket each instant closely.

    Parameters
    ----------
    t_ns : (M,) int64
    sample_t_ns : (N,) int64 (any order), values : (N, D)
    max_gap_s : float
        An instant is ``bracketed`` when samples exist before and after it (or
        at it), each within this many seconds.

    Returns
    -------
    values_at : (M, D), bracketed : (M,) bool
    """
    t = np.asarray(t_ns, np.int64)
    st = np.asarray(sample_t_ns, np.int64)
    v = np.asarray(values, float).reshape(len(st), -1)
    if len(st) == 0:
        return np.full((len(t), v.shape[1]), np.nan), np.zeros(len(t), bool)
    order = np.argsort(st, kind="stable")
    st, v = st[order], v[order]
    x = (t - st[0]).astype(float)
    xp = (st - st[0]).astype(float)
    out = np.stack([np.interp(x, xp, v[:, k]) for k in range(v.shape[1])], -1)
    k = np.searchsorted(st, t, side="right")
    before = np.where(k > 0, t - st[np.clip(k - 1, 0, len(st) - 1)], np.iinfo(np.int64).max)
    after = np.where(k < len(st), st[np.clip(k, 0, len(st) - 1)] - t, np.iinfo(np.int64).max)
    after = np.where(before == 0, 0, after)  # a sample exactly at the instant brackets it
    limit = int(max_gap_s * 1e9)
    return out, (before <= limit) & (after <= limit)


def window_point(
    window: HoverWindow,
    stable_ns: tuple[int, int],
    fix_t_ns: np.ndarray,
    marker_enu_m: np.ndarray,
    fix_sigma_m: np.ndarray,
    fix_types: list[str | None] | np.ndarray,
    det_t_ns: np.ndarray,
    det_uv_px: np.ndarray,
    camera_offset_ns: int,
    options: PointOptions,
    det_size_px: np.ndarray | None = None,
    marker_size_m: float | None = None,
    det_marker_enu_m: np.ndarray | None = None,
    noise: "FixNoise | None" = None,
) -> WaypointPoint:
    """The correspondence of one window (before the across-window outlier test).

    Parameters
    ----------
    stable_ns : (start_ns, end_ns)
        The settled part, GNSS clock.
    fix_t_ns : (N,) int64, marker_enu_m : (N, 3) metres, fix_sigma_m : (N, 3) metres
        All fixes of the run (or a superset of the window): times, the
        marker's ENU position (lever arm applied), the receiver's reported std.
    fix_types : (N,) fix type strings or None
    det_t_ns : (M,) int64, det_uv_px : (M, 2)
        Detections, stamped on the camera clock.
    camera_offset_ns : int
        Camera stamp minus capture time (``align.TimeOffset.offset_ns``).
    det_size_px : (M,), optional, and marker_size_m : float, optional
        The marker's apparent and true size: they turn the image scatter into
        metres at the marker (``scatter_image_m``), comparable across
        distances and cameras.
    det_marker_enu_m : (M, 3) metres, optional
        The marker's position at each detection's capture time
        (:func:`marker_track_at`; NaN rows where it could not be paired).
        Used with ``options.pair_at == "detections"``: the 3D centre is
        taken over the detections' instants, paired with their pixels. With
        ``"fixes"`` (the default) the image track is interpolated at the
        fixes instead. Either way the fixes decide the drops, the scatter and
        the sigma.
    noise : FixNoise, optional
        The measured per-fix noise: the point's sigma is then that of the mean
        of its fixes (:meth:`FixNoise.mean_variance`: white noise averages
        down, correlated noise does not), all of it in 3D (the white part
        holds the detector's), instead of the scatter.
    """
    a, b = stable_ns
    fix_t_ns = np.asarray(fix_t_ns, np.int64)
    in_fix = (fix_t_ns >= a) & (fix_t_ns <= b)
    det_t = np.asarray(det_t_ns, np.int64) - int(camera_offset_ns)
    in_det = (det_t >= a) & (det_t <= b)
    types = [fix_types[k] for k in np.flatnonzero(in_fix)]
    worst = min(types, key=fix_rank) if types else None
    base = dict(window=window, stable_ns=(int(a), int(b)), n_fixes=int(in_fix.sum()), n_detections=int(in_det.sum()), worst_fix=worst)
    if in_fix.sum() < options.min_fixes:
        return WaypointPoint(**base, dropped=f"only {int(in_fix.sum())} GNSS fixes in the settled part (dropout); need {options.min_fixes}")
    if fix_rank(worst) < fix_rank(options.min_fix):
        return WaypointPoint(**base, dropped=f"fix {worst or 'unknown'} is worse than --min-fix {options.min_fix}")
    if in_det.sum() < options.min_detections:
        return WaypointPoint(**base, dropped=_too_few_detections(int(in_det.sum()), window, stable_ns, options))
    xyz, scatter_m = robust_centre(np.asarray(marker_enu_m, float)[in_fix])
    reported = np.median(np.asarray(fix_sigma_m, float)[in_fix], axis=0)
    sigma_m = np.maximum(np.maximum(scatter_m, np.nan_to_num(reported, nan=0.0)), options.sigma_m_floor)
    pick = in_det
    if options.paired and options.pair_at == "fixes":
        # The image track at each fix: every fix's 3D is used (the RTK noise
        # averages over all of them) and the 2D follows the same drift.
        fix_idx = np.flatnonzero(in_fix)
        gap = int(options.pair_max_gap_s * 1e9)
        near = (det_t >= a - gap) & (det_t <= b + gap)
        uv_at, bracketed = track_at(fix_t_ns[fix_idx], det_t[near], np.asarray(det_uv_px, float)[near], options.pair_max_gap_s)
        if options.pair_across_gaps:
            # A hold is still: between bursts 2 s apart the track is interpolated, beyond its ends held (np.interp).
            bracketed = np.ones_like(bracketed)
        if bracketed.sum() >= max(options.min_fixes, options.min_detections):
            xyz, uv = paired_centre(np.asarray(marker_enu_m, float)[fix_idx[bracketed]], uv_at[bracketed])
            _, scatter_uv = robust_centre(np.asarray(det_uv_px, float)[in_det])
            point = _point(base, xyz, sigma_m, uv, scatter_m, scatter_uv, in_det, det_size_px, marker_size_m, options)
            if noise is not None:
                sd = max(float(np.sqrt(noise.mean_variance(fix_t_ns[fix_idx[bracketed]] * 1e-9))), NOISE_FLOOR_M)
                point = replace(point, sigma_enu_m=np.full(3, sd), sigma_px=NOISE_FLOOR_PX)
            return point
    if options.paired and options.pair_at == "detections" and det_marker_enu_m is not None:
        paired = in_det & np.all(np.isfinite(np.asarray(det_marker_enu_m, float)), axis=1)
        if paired.sum() >= options.min_detections:
            # 3D and 2D over the same instants: the hover drift moves both alike.
            pick = paired
    uv, scatter_uv = robust_centre(np.asarray(det_uv_px, float)[pick])
    if pick is not in_det:
        xyz, uv = paired_centre(np.asarray(det_marker_enu_m, float)[pick], np.asarray(det_uv_px, float)[pick])
    return _point(base, xyz, sigma_m, uv, scatter_m, scatter_uv, pick, det_size_px, marker_size_m, options)


def _point(base: dict, xyz, sigma_m, uv, scatter_m, scatter_uv, pick, det_size_px, marker_size_m, options: PointOptions) -> WaypointPoint:
    """A used WaypointPoint from its centres and scatters (``pick``: the detections the image scatter in metres is sized on)."""
    scatter_px = float(np.sqrt(np.mean(scatter_uv**2)))
    scatter_image_m = None
    if det_size_px is not None and marker_size_m:
        size = float(np.median(np.asarray(det_size_px, float)[pick]))
        scatter_image_m = scatter_px * marker_size_m / size if size > 0 else None
    return WaypointPoint(
        **base,
        marker_enu_m=xyz,
        sigma_enu_m=sigma_m,
        uv_px=uv,
        sigma_px=max(scatter_px, options.sigma_px_floor),
        scatter_enu_m=scatter_m,
        scatter_px=scatter_px,
        scatter_image_m=scatter_image_m,
    )


def drop_outlying_scatter(points: list[WaypointPoint], options: PointOptions) -> list[WaypointPoint]:
    """Drop used points whose 3D or image scatter is far above the median used point's.

    A gust, a fix jump or a detector that flips between two corners shows as
    a scatter many times the typical hold's; such a point's median is not
    trustworthy even when its sigma would down-weight it. The image scatter
    is compared in metres at the marker when its size is known (a near
    marker's normal drift is many pixels, a far one's a fraction), else in
    pixels.
    """
    used = [p for p in points if p.used]
    if len(used) < 3:
        return points
    s3 = np.array([np.linalg.norm(p.scatter_enu_m) for p in used])
    lim3 = max(options.outlier_factor * float(np.median(s3)), options.outlier_floor_m)
    in_metres = all(p.scatter_image_m is not None for p in used)
    s2 = np.array([p.scatter_image_m if in_metres else p.scatter_px for p in used])
    floor2 = options.outlier_floor_m if in_metres else options.outlier_floor_px
    lim2 = max(options.outlier_factor * float(np.median(s2)), floor2)
    out = []
    for p in points:
        if p.used and np.linalg.norm(p.scatter_enu_m) > lim3:
            p = p.with_drop(f"3D scatter {100 * np.linalg.norm(p.scatter_enu_m):.1f} cm is outlying (limit {100 * lim3:.1f} cm)")
        elif p.used and in_metres and p.scatter_image_m > lim2:
            p = p.with_drop(
                f"image scatter {p.scatter_px:.2f} px ({100 * p.scatter_image_m:.1f} cm at the marker) is outlying (limit {100 * lim2:.1f} cm)"
            )
        elif p.used and not in_metres and p.scatter_px > lim2:
            p = p.with_drop(f"image scatter {p.scatter_px:.2f} px is outlying (limit {lim2:.2f} px)")
        out.append(p)
    return out


# --------------------------------------------------------------------------
# The per-point noise as it really is


@dataclass(frozen=True)
class FixNoise:
    """The per-fix noise of the 3D-2D pairs, measured on their residuals through the calibrated camera.

    Each paired fix's residual, in metres at the marker, is modelled as white
    noise (the detector, a receiver's fast jitter; averages down over a hold)
    plus a first-order Gauss-Markov part correlated over ``tau_s`` (RTK
    multipath and atmosphere; does not average down over a few seconds).

    Attributes
    ----------
    sigma_white_m, sigma_corr_m : per-axis std of the two parts, metres.
    tau_s : correlation time of the correlated part, seconds (None: none seen).
    fix_interval_s : median interval between paired fixes.
    n_residuals : paired fixes measured.
    method : how it was obtained.
    """

    sigma_white_m: float
    sigma_corr_m: float
    tau_s: float | None
    fix_interval_s: float
    n_residuals: int
    method: str = "residuals through the calibrated camera, autocovariance within holds and legs"

    def rho(self, dt_s: np.ndarray) -> np.ndarray:
        """Correlation of the correlated part over time differences ``dt_s`` (any shape)."""
        if self.tau_s is None or self.sigma_corr_m <= 0:
            return (np.asarray(dt_s) == 0).astype(float)
        return np.exp(-np.abs(np.asarray(dt_s, float)) / self.tau_s)

    def mean_variance(self, t_s: np.ndarray) -> float:
        """Per-axis variance (m^2) of the mean of the fixes at times ``t_s`` (K,)."""
        t = np.asarray(t_s, float)
        k = max(len(t), 1)
        g = float(self.rho(t[:, None] - t[None, :]).sum()) / k**2 if len(t) else 1.0
        return self.sigma_white_m**2 / k + self.sigma_corr_m**2 * g

    def to_dict(self) -> dict:
        return {
            "sigma_white_m": self.sigma_white_m,
            "sigma_corr_m": self.sigma_corr_m,
            "tau_s": self.tau_s,
            "fix_interval_s": self.fix_interval_s,
            "n_residuals": self.n_residuals,
            "method": self.method,
        }


def estimate_fix_noise(segments: list[tuple[np.ndarray, np.ndarray]], max_lag_s: float = 1.5, min_residuals: int = 30) -> FixNoise | None:
    """White and correlated parts of the per-fix noise from residual series.

    Parameters
    ----------
    segments : list of (t_ns (K,) int64 increasing, residual_m (K, 2))
        Each hold's settled part or leg: the residuals of its consecutive
        paired fixes, in metres at the marker (pixel residual x depth / focal).
    max_lag_s : the autocovariance is measured up to this lag.

    Returns
    -------
    FixNoise, or None with fewer than ``min_residuals`` residuals.

    The pooled autocovariance C(k) at lags of k fix intervals gives
    C(0) = s_w^2 + s_c^2 and C(k) = s_c^2 rho^k: rho from C(K)/C(1) over the
    longest lag measured, s_c^2 = C(1) / rho, s_w^2 = C(0) - s_c^2. The mean of
    each segment is NOT removed: a correlated error is exactly what shifts a
    whole hold or leg.
    """
    segs = [(np.asarray(t, np.int64), np.asarray(r, float).reshape(-1, 2)) for t, r in segments if len(t) >= 1]
    n = sum(len(t) for t, _ in segs)
    if n < min_residuals:
        return None
    diffs = np.concatenate([np.diff(t) for t, _ in segs if len(t) > 1]) if any(len(t) > 1 for t, _ in segs) else np.zeros(0)
    dt = float(np.median(diffs)) * 1e-9 if len(diffs) else 0.2
    every = np.concatenate([r for _, r in segs])
    # Robust scale: a few wild pairs (a detector flip) must not set the noise.
    c0 = float(np.mean(np.minimum(every**2, 25.0 * np.median(every**2))))
    max_lag = max(1, int(round(max_lag_s / max(dt, 1e-3))))
    cov = np.full(max_lag + 1, np.nan)
    for k in range(1, max_lag + 1):
        num, cnt = 0.0, 0
        for t, r in segs:
            if len(t) <= k:
                continue
            ok = np.abs((t[k:] - t[:-k]) * 1e-9 - k * dt) < 0.5 * dt  # regular spacing only
            num += float(np.sum(r[k:][ok] * r[:-k][ok]))
            cnt += 2 * int(ok.sum())
        cov[k] = num / cnt if cnt >= 20 else np.nan
    c1 = cov[1] if np.isfinite(cov[1]) else 0.0
    if c1 <= 0.05 * c0:
        return FixNoise(sigma_white_m=float(np.sqrt(c0)), sigma_corr_m=0.0, tau_s=None, fix_interval_s=dt, n_residuals=n)
    lags = [k for k in range(2, max_lag + 1) if np.isfinite(cov[k]) and cov[k] > 0]
    if lags:
        K = lags[-1]
        rho = float(np.clip((cov[K] / c1) ** (1.0 / (K - 1)), 0.05, 0.999))
    else:
        rho = 0.5
    s_c2 = min(c1 / rho, c0)
    return FixNoise(
        sigma_white_m=float(np.sqrt(max(c0 - s_c2, 0.0))),
        sigma_corr_m=float(np.sqrt(s_c2)),
        tau_s=float(-dt / np.log(rho)),
        fix_interval_s=dt,
        n_residuals=n,
    )
