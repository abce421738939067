"""Sampling designed in the image: target pixels over the ROI, two or more depths along each ray.

The paper samples a metric box (X 4-8 m, Y ±3 m); for most pole cameras that
box lands in a thin band of the image and the lens is extrapolated over the
ground users measure on. Here the design starts in the image:

1. *targets*: a lattice of ``n_u`` x ``n_v`` pixels spread over the ROI's
   image area; each row runs from the ROI's left edge to its right edge at
   that height, so the lattice hugs the ROI outline out to its corners;
2. *depths*: along each target's ray every distance is screened with the
   plan's rules (``lattice.screen_points``: drone AGL, keep-out, range,
   geofence, whole marker in the image with a margin, marker size); the
   nearest and the farthest allowed distance (at least ``MIN_DEPTH_RATIO``
   apart) are flown, and a middle one for three depths. A ray is sampled
   wherever it is allowed: the far ground near the horizon is reached by a
   point a few metres up at 10-15 m, not by flying 40 m out;
3. *legs*: per depth layer and lattice row, the row's points in order form
   one leg; ``hover`` holds at every point, ``through`` flies the legs at a
   constant speed with holds only where a leg ends, ``mixed`` holds at every
   point and also keeps the fixes taken between them.

Pure functions on the site frame (X along the camera azimuth, Y left, Z up,
origin at the pole's foot); the camera is the guessed one, in that frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from dronecal_field.core.camera import Camera, pixel_rays_batch
from dronecal_field.errors import PlanError
from dronecal_field.sampling.lattice import Limits, screen_points
from dronecal_field.sampling.roi import Roi

MIN_DEPTH_RATIO = 1.5  # far / near along one ray: enough depth spread to separate focal length from distance
# Targets keep this share of the image size from its border: a focal guess 2 % off or a tilt 1 deg off
# moves an edge target that much. Not more: the image's outer band is where the lens is least known, and
# a lattice held 4 % in left the 4K camera's k3 unseen (F-test power 7 %) and its far ground 1.1 px off.
GUESS_MARGIN = 0.02
# an edge target that gets too few depths moves this share of the way to the centre per try, then halves back towards
# the edge: 15 % steps alone pulled the demo's 9x6 lattice's outer columns 90 px in under the guess band (predicted
# 5.8 px over the ROI against 2.2 px without a band)
INSET_STEP = 0.15
INSET_DEPTH_M = 8.0  # edge targets keep half a marker seen from this far inside the image; nearer depths are screened per point
DEPTH_GRID_M = np.geomspace(0.6, 120.0, 200)  # distances along a ray that are screened, m
TIMING_SIGMA_S = 0.01  # std of the offset between a frame's time and the GNSS fix time, s
RTK_CORRELATION_S = 5.0  # RTK errors drift over seconds: fixes within this time of each other share their error
LEG_END_HOLD_S = 1.0  # hold at each end of a fly-through leg, s (ArduCopter holds in whole seconds)
SAMPLINGS = ("hover", "through", "mixed")
REASON_TEXT = {
    "too_low": "the drone would have to fly below --min-agl {min_agl:g} m",
    "too_high": "the drone would have to fly above --max-agl {max_agl}",
    "keep_out": "the drone would have to enter --keep-out {keep_out:g} m around the pole",
    "out_of_range": "the drone would have to fly beyond --max-range {max_range}",
    "outside_geofence": "the drone would have to leave --geofence",
    "marker_too_small": "the {size:g} m marker would be under --min-marker-px {min_px:g} px there",
    "outside_image": "the whole marker does not fit in the image there (a {size:g} m marker with a {margin:g} px margin)",
    "behind_camera": "the ray does not reach a place the drone may fly",
    "depth_spread": "the allowed stretch of the ray is too short for two depths {ratio:g}x apart",
}


@dataclass(frozen=True)
class DesignParams:
    """One candidate layout.

    ``n_u`` x ``n_v`` target pixels; ``n_depths`` per target (2 or 3);
    ``depth_ratio``: far / near distance along the ray (None: the widest the
    ray allows); ``marker_size_m``; ``sampling`` one of :data:`SAMPLINGS`;
    ``min_depth_m``: keep the points at least this far from the camera where the
    ray allows two depths there (far points: less RTK noise in pixels, faster legs).
    """

    n_u: int = 7
    n_v: int = 5
    n_depths: int = 2
    depth_ratio: float | None = None
    marker_size_m: float = 0.3
    sampling: str = "hover"
    min_depth_m: float | None = None

    @property
    def name(self) -> str:
        ratio = "max" if self.depth_ratio is None else f"{self.depth_ratio:g}"
        near = "" if self.min_depth_m is None else f"-n{self.min_depth_m:g}"
        return f"image-{self.n_u}x{self.n_v}-d{self.n_depths}-r{ratio}{near}-m{self.marker_size_m:g}-{self.sampling}"

    def describe(self) -> str:
        ratio = "as far apart as allowed" if self.depth_ratio is None else f"{self.depth_ratio:g}x apart"
        near = "" if self.min_depth_m is None else f", none nearer than {self.min_depth_m:g} m where the ray allows"
        return (f"{self.n_u}x{self.n_v} target pixels over the ROI, {self.n_depths} depths per ray ({ratio}{near}), "
                f"{self.marker_size_m:g} m marker, {self.sampling}")


@dataclass(frozen=True)
class LegTiming:
    """What sets the leg speed (:func:`through_speed_m_s`): frame rate, exposure, GNSS rate (s, Hz) and the blur allowed (px)."""

    fps: float = 25.0
    exposure_s: float = 0.004
    gnss_hz: float = 10.0
    blur_px: float = 1.0
    max_speed_m_s: float = 3.0


@dataclass(frozen=True, eq=False)
class Design:
    """A designed sampling for one camera.

    Holds (the points the mission flies to), in flight order:
    ``marker_site`` / ``vehicle_site`` (N, 3) site metres, ``uv`` (N, 2) guessed
    pixels, ``marker_px`` (N,), ``target`` (N,) index into ``targets_uv``,
    ``depth_index`` (N,), ``hold_s`` (N,) seconds (0 = fly through), ``leg`` (N,)
    leg number. Samples for the prediction: ``samples_site`` (S, 3) marker
    centres (holds and fixes along legs), ``samples_sigma_h_m`` (S,) extra
    horizontal std from timing (0 at holds), ``samples_uv`` (S, 2),
    ``samples_rtk_factor`` (S,): the fixes of a leg taken within
    :data:`RTK_CORRELATION_S` share one RTK error, so treating them as
    independent would average it away; each gets the RTK std times
    sqrt(fixes sharing it), which gives their mean the right variance.
    ``unreachable`` lists the ROI parts no sample reaches, with the reason.
    """

    params: DesignParams
    targets_uv: np.ndarray
    target_ok: np.ndarray  # (T,) bool: the target got at least two depths
    target_reason: tuple[str | None, ...]  # (T,) why a target got fewer than two depths
    marker_site: np.ndarray
    vehicle_site: np.ndarray
    uv: np.ndarray
    marker_px: np.ndarray
    target: np.ndarray
    depth_index: np.ndarray
    hold_s: np.ndarray
    leg: np.ndarray
    speed_m_s: float
    samples_site: np.ndarray
    samples_uv: np.ndarray
    samples_sigma_h_m: np.ndarray
    samples_is_hold: np.ndarray
    samples_rtk_factor: np.ndarray  # (S,) RTK std multiplier: sqrt(fixes sharing one error) along legs, 1 at holds
    coverage: float
    unreachable: tuple[dict, ...] = field(default_factory=tuple)
    needed_marker_m: float | None = None

    @property
    def n_points(self) -> int:
        return int(len(self.marker_site))

    @property
    def n_leg_samples(self) -> int:
        return int((~self.samples_is_hold).sum())


def through_speed_m_s(
    focal_px: float,
    min_depth_m: float,
    fps: float,
    exposure_s: float,
    gnss_hz: float,
    blur_px: float = 1.0,
    max_speed_m_s: float = 3.0,
    max_fix_spacing_m: float = 0.3,
    marker_size_m: float = 0.3,
) -> float:
    """The constant speed (m/s) of fly-through legs: the smallest of four limits.

    - Motion blur: a marker at depth ``min_depth_m`` moving across the view at
      v smears ``v * exposure_s * focal_px / min_depth_m`` pixels in one
      exposure; kept under ``blur_px``. E.g. f 900 px, 5 m, 1/250 s:
      1 px at 1.39 m/s; f 2600 px, 5 m, 1/500 s: 0.96 m/s.
    - GNSS: a fix at least every ``max_fix_spacing_m`` along the leg, so the
      track between fixes stays short enough to interpolate: 10 Hz x 0.3 m =
      3 m/s, 5 Hz = 1.5 m/s.
    - Frames: the marker moves at most one marker width (``marker_size_m``)
      per frame, so consecutive detections overlap (25 fps x 0.3 m = 7.5 m/s).
    - ``max_speed_m_s``: what a calibration flight near a pole should fly at most.

    Parameters
    ----------
    focal_px : focal length, px
    min_depth_m : depth of the nearest sample along the camera axis, m
    fps : camera frame rate, 1/s
    exposure_s : exposure time (a guess: 1/250 s in daylight), s
    gnss_hz : rate of new GNSS fixes, 1/s
    blur_px : largest motion blur, px
    max_speed_m_s : upper bound, m/s
    max_fix_spacing_m : largest distance between two fixes along a leg, m
    marker_size_m : marker side, m
    """
    values = dict(focal_px=focal_px, min_depth_m=min_depth_m, fps=fps, exposure_s=exposure_s, gnss_hz=gnss_hz,
                  blur_px=blur_px, max_speed_m_s=max_speed_m_s, max_fix_spacing_m=max_fix_spacing_m, marker_size_m=marker_size_m)
    bad = [k for k, v in values.items() if not (math.isfinite(v) and v > 0)]
    if bad:
        raise PlanError(f"through_speed_m_s needs positive values; {', '.join(f'{k}={values[k]!r}' for k in bad)}: give the camera's focal, frame rate, exposure and the GNSS rate")
    blur = blur_px * min_depth_m / (exposure_s * focal_px)
    fixes = max_fix_spacing_m * gnss_hz
    frames = marker_size_m * fps
    return float(min(blur, fixes, frames, max_speed_m_s))


def through_speed(focal_px: float, min_depth_m: float, timing: LegTiming, marker_size_m: float = 0.3) -> float:
    """Leg speed, m/s, of :func:`through_speed_m_s` for these timings."""
    return through_speed_m_s(focal_px, min_depth_m, timing.fps, timing.exposure_s, timing.gnss_hz,
                             blur_px=timing.blur_px, max_speed_m_s=timing.max_speed_m_s, marker_size_m=marker_size_m)


def target_lattice(roi: Roi, n_u: int, n_v: int) -> np.ndarray:
    """(T, 2) target pixels: ``n_v`` rows over the ROI's image extent, ``n_u`` per row edge to edge.

    Each row spans the ROI pixels within half a cell of the row's height, so
    the lattice follows the ROI outline (a trapezoid of ground, a polygon).
    """
    uv = roi.uv
    du, dv = roi.cell_px
    v_lo, v_hi = float(uv[:, 1].min()), float(uv[:, 1].max())
    rows = np.linspace(v_lo, v_hi, n_v) if n_v > 1 else np.array([(v_lo + v_hi) / 2.0])
    out = []
    for v in rows:
        near = np.abs(uv[:, 1] - v) <= max(dv / 2.0, (v_hi - v_lo) / max(4 * n_v, 1))
        if not near.any():
            near = np.abs(uv[:, 1] - v) <= np.min(np.abs(uv[:, 1] - v)) + 1e-9
        u_lo, u_hi = float(uv[near, 0].min()), float(uv[near, 0].max())
        us = np.linspace(u_lo, u_hi, n_u) if n_u > 1 else np.array([(u_lo + u_hi) / 2.0])
        out.append(np.column_stack([us, np.full(n_u, v)]))
    return np.concatenate(out)


def _screen_rays(camera: Camera, uv: np.ndarray, limits: Limits) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Screen every distance of :data:`DEPTH_GRID_M` along the rays of pixels (T, 2).

    Returns rays (T, 3), points (T, D, 3) and the screen's arrays reshaped (T, D).
    """
    K, Dd, R, _ = camera.batch_arrays()
    rays = pixel_rays_batch(K, Dd, R, np.asarray(uv, float)[None])[0]
    c = camera.pose.position_world
    pts = c[None, None, :] + DEPTH_GRID_M[None, :, None] * rays[:, None, :]
    s = screen_points(camera, pts.reshape(-1, 3), limits)
    T, D = len(uv), len(DEPTH_GRID_M)
    out = {k: (v.reshape(T, D, *v.shape[1:]) if isinstance(v, np.ndarray) else v) for k, v in s.items()}
    return rays, pts, out


def _blocker(s: dict[str, np.ndarray], i: int) -> str:
    """The rule that leaves target ``i`` without an allowed distance: the one whose removal alone frees most of the ray."""
    rules = ("too_low", "too_high", "keep_out", "out_of_range", "outside_geofence", "marker_too_small", "outside_image")
    best, best_n = "behind_camera", 0
    for rule in rules:
        others = [r for r in rules if r != rule]
        free = ~s["behind_camera"][i] & ~np.any([s[r][i] for r in others], axis=0)
        n = int(free.sum())
        if n > best_n:
            best, best_n = rule, n
    return best


def _pick_depths(ok: np.ndarray, n_depths: int, ratio: float | None) -> tuple[list[int], str | None]:
    """Indices into DEPTH_GRID_M of the depths to fly along one ray, or a reason there are fewer than two."""
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return [], "none"
    t = DEPTH_GRID_M[idx]
    near = int(idx[0])
    t_far_max = float(t[-1])
    if t_far_max / t[0] < MIN_DEPTH_RATIO - 1e-9:
        return [int(idx[len(idx) // 2])], "depth_spread"
    want = t_far_max if ratio is None else min(t_far_max, max(ratio, MIN_DEPTH_RATIO) * float(t[0]))
    far = int(idx[np.searchsorted(t, want * (1 - 1e-9))] if np.any(t >= want * (1 - 1e-9)) else idx[-1])
    if DEPTH_GRID_M[far] / DEPTH_GRID_M[near] < MIN_DEPTH_RATIO - 1e-9:
        far = int(idx[np.searchsorted(t, MIN_DEPTH_RATIO * float(t[0]) * (1 - 1e-9))])
    chosen = [near, far]
    if n_depths >= 3:
        mid_t = math.sqrt(DEPTH_GRID_M[near] * DEPTH_GRID_M[far])
        between = idx[(DEPTH_GRID_M[idx] > DEPTH_GRID_M[near]) & (DEPTH_GRID_M[idx] < DEPTH_GRID_M[far])]
        if between.size:
            chosen.insert(1, int(between[np.argmin(np.abs(np.log(DEPTH_GRID_M[between] / mid_t)))]))
    return chosen, None


def _edge_short(s: dict) -> np.ndarray:
    """(T,) bool: targets with fewer than two usable depths because the whole marker leaves the image."""
    ok = s["in_view"] & s["reachable"] & s["big_enough"]
    short = np.array([_pick_depths(o, 2, None)[1] is not None for o in ok])
    cut = (s["outside_image"] & ~s["behind_camera"] & s["reachable"] & s["big_enough"]).any(axis=1)
    return short & cut


def _inset_targets(camera: Camera, targets: np.ndarray, limits: Limits, tries: int = 6,
                   refine: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Pull targets whose marker leaves the image inwards until their rays allow two depths.

    The lattice first keeps half a marker seen from :data:`INSET_DEPTH_M`, the margin and
    :data:`GUESS_MARGIN` of the image size from the image border (the camera
    is a guess: a marker planned on the guessed image's edge is off the real
    one when the focal length is 2 % longer); a target that still gets fewer than two depths because
    the whole marker does not fit moves :data:`INSET_STEP` of the way to the lattice centre,
    up to ``tries`` times, then halves back towards the edge ``refine`` times (to 2 % of the way: the outermost
    targets are what sample the lens's outer band). Returns targets (T, 2), rays (T, 3), points (T, D, 3)
    and the screen (T, D).
    """
    targets = np.asarray(targets, float).copy()
    e = limits.margin_px + 0.5 * camera.intrinsics.fx * limits.marker_size_m / INSET_DEPTH_M
    eu, ev = e + GUESS_MARGIN * camera.width, e + GUESS_MARGIN * camera.height
    targets[:, 0] = np.clip(targets[:, 0], eu, camera.width - 1 - eu)
    targets[:, 1] = np.clip(targets[:, 1], ev, camera.height - 1 - ev)
    centre = targets.mean(axis=0)
    start = targets.copy()
    rays, pts, s = _screen_rays(camera, targets, limits)

    def move(which: np.ndarray, pull: np.ndarray) -> np.ndarray:
        """Place targets ``which`` (bool) ``pull`` of the way to the centre, screen them; returns their edge flags."""
        targets[which] = centre + (1.0 - pull[which, None]) * (start[which] - centre)
        r2, p2, s2 = _screen_rays(camera, targets[which], limits)
        rays[which], pts[which] = r2, p2
        for k in s:
            if isinstance(s[k], np.ndarray) and s[k].shape[:1] == (len(targets),):
                s[k][which] = s2[k]
        return _edge_short(s2)

    good = np.zeros(len(targets))  # pull that works (0: none needed)
    bad = np.full(len(targets), -1.0)  # largest pull known not to (-1: none tried)
    edge = _edge_short(s)
    for _ in range(tries):
        if not edge.any():
            break
        bad[edge] = good[edge]
        good[edge] = np.minimum(1.0, good[edge] + INSET_STEP)
        still = np.zeros(len(targets), bool)
        still[edge] = move(edge, good)
        edge = still
    for _ in range(refine):
        moved = (bad >= 0) & ~edge
        if not moved.any():
            break
        trial = good.copy()
        trial[moved] = 0.5 * (good[moved] + bad[moved])
        fails = np.zeros(len(targets), bool)
        fails[moved] = move(moved, trial)
        bad[moved & fails] = trial[moved & fails]
        good[moved & ~fails] = trial[moved & ~fails]
    back = (bad >= 0) & ~edge
    if back.any():  # the last halving may have failed: every moved target ends at a pull that works
        move(back, good)
    return targets, rays, pts, s


@dataclass(frozen=True, eq=False)
class TargetScreen:
    """The target pixels of one lattice and every screened distance along their rays (shared by candidates).

    ``targets`` (T, 2) px, ``points`` (T, D, 3) site metres along the rays at
    :data:`DEPTH_GRID_M`, ``screen`` the arrays of ``lattice.screen_points``
    reshaped (T, D).
    """

    n_u: int
    n_v: int
    marker_size_m: float
    targets: np.ndarray
    points: np.ndarray
    screen: dict


def screen_targets(camera: Camera, roi: Roi, n_u: int, n_v: int, limits: Limits) -> TargetScreen:
    """Target lattice over the ROI, pulled in from the image edge, with its rays screened (``limits.marker_size_m``)."""
    targets, _, pts, s = _inset_targets(camera, target_lattice(roi, n_u, n_v), limits)
    return TargetScreen(n_u=n_u, n_v=n_v, marker_size_m=limits.marker_size_m, targets=targets, points=pts, screen=s)


def design_sampling(camera: Camera, roi: Roi, params: DesignParams, limits: Limits, timing: LegTiming = LegTiming(),
                    hover_s: float = 3.0, screened: TargetScreen | None = None, legs_cache: dict | None = None) -> Design:
    """The holds, legs and prediction samples of ``params`` for ``camera`` over ``roi``.

    Parameters
    ----------
    camera : the guessed camera, site frame
    roi : the region of interest of that camera (``roi.build_roi``)
    params : the layout (lattice, depths, marker size, sampling)
    limits : the plan's limits; ``marker_size_m`` is replaced by ``params.marker_size_m``
    timing : frame rate, exposure and GNSS rate, for the leg speed and the timing noise
    hover_s : hold at a hold point, s
    screened : the lattice's rays already screened (``screen_targets`` with the same
        ``n_u``, ``n_v`` and marker size), so candidates differing only in depths or
        sampling share the work
    legs_cache : a dict shared by candidates: the fixes along the legs of one
        layout are computed once for ``through`` and ``mixed`` (same legs)

    Returns
    -------
    Design (points in flight order, see :class:`Design`).
    """
    lim = replace(limits, marker_size_m=params.marker_size_m)
    if screened is None:
        screened = screen_targets(camera, roi, params.n_u, params.n_v, lim)
    targets, pts, s = screened.targets, screened.points, screened.screen
    ok = s["in_view"] & s["reachable"] & s["big_enough"]
    T = len(targets)
    picks: list[list[int]] = []
    reasons: list[str | None] = []
    for i in range(T):
        ok_i = ok[i]
        if params.min_depth_m is not None:
            far_enough = ok_i & (DEPTH_GRID_M >= params.min_depth_m)
            if _pick_depths(far_enough, 2, None)[1] is None:
                ok_i = far_enough
        chosen, why = _pick_depths(ok_i, params.n_depths, params.depth_ratio)
        if why == "none":
            why = _blocker(s, i)
        picks.append(chosen)
        reasons.append(why)
    # flight order: per depth layer, rows of the lattice back and forth; layers near -> far
    n_layers = max((len(p) for p in picks), default=0)
    order: list[tuple[int, int, int]] = []  # (target, depth grid index, layer)
    leg_of: list[int] = []
    leg = 0
    direction = 1
    for layer in range(n_layers):
        rows = range(params.n_v) if layer % 2 == 0 else range(params.n_v - 1, -1, -1)
        for r in rows:
            row_targets = [r * params.n_u + j for j in range(params.n_u)][::direction]
            row = [(t, picks[t][layer], layer) for t in row_targets if len(picks[t]) > layer]
            if not row:
                continue
            order.extend(row)
            leg_of.extend([leg] * len(row))
            leg += 1
            direction = -direction
    if not order:
        return replace(_empty_design(params, targets, reasons, roi), needed_marker_m=_needed_marker(s, lim, reasons))
    ti = np.array([o[0] for o in order], int)
    di = np.array([o[1] for o in order], int)
    layer_of = np.array([o[2] for o in order], int)
    marker = pts[ti, di]
    vehicle = s["vehicle"][ti, di]
    uv = s["uv"][ti, di]
    mpx = s["marker_px"][ti, di]
    leg_arr = np.asarray(leg_of, int)
    depth_cam = camera.depth(marker)
    speed = through_speed(camera.intrinsics.fx, float(depth_cam.min()), timing, params.marker_size_m)
    last_of_leg = np.r_[leg_arr[1:] != leg_arr[:-1], True]
    first_of_leg = np.r_[True, leg_arr[1:] != leg_arr[:-1]]
    if params.sampling == "through":
        # a leg starts and ends at rest (its speed differs from the transit's); a second stops the drone, the leg's
        # fixes carry the samples, so a full hover there would only lengthen the flight (11.0 vs 12.2 min, camera (a))
        hold = np.where(last_of_leg | first_of_leg, min(hover_s, LEG_END_HOLD_S), 0.0)
    else:
        hold = np.full(len(marker), float(hover_s))
    # prediction samples: the holds, plus for through/mixed a fix every speed / gnss_hz metres along each leg
    samples = [marker]
    sig = [np.zeros(len(marker))]
    is_hold = [hold > 0]
    rtk = [np.ones(len(marker))]
    if params.sampling in ("through", "mixed"):
        step = speed / timing.gnss_hz
        seg_a, seg_b = [], []
        for k in range(len(marker) - 1):
            if leg_arr[k] == leg_arr[k + 1]:
                seg_a.append(marker[k])
                seg_b.append(marker[k + 1])
        key = (params.n_u, params.n_v, params.n_depths, params.depth_ratio, params.min_depth_m, params.marker_size_m)
        if legs_cache is not None and key in legs_cache:
            E = legs_cache[key]
        else:
            extra = [np.zeros((0, 3))]
            for a, b in zip(seg_a, seg_b):
                n = int(np.linalg.norm(b - a) // step)
                if n >= 1:
                    f = (np.arange(1, n + 1) / (n + 1))[:, None]
                    extra.append(a + f * (b - a))
            E = np.concatenate(extra)
            if len(E):
                se = screen_points(camera, E, lim)
                E = E[se["in_view"] & se["reachable"] & se["big_enough"]]
            if legs_cache is not None:
                legs_cache[key] = E
        if len(E):
            samples.append(E)
            sig.append(np.full(len(E), speed * TIMING_SIGMA_S))
            is_hold.append(np.zeros(len(E), bool))
            shared = max(1.0, min(timing.gnss_hz * RTK_CORRELATION_S, len(E) / max(leg_arr.max() + 1, 1)))
            rtk.append(np.full(len(E), math.sqrt(shared)))
        # a through point is itself a fix taken in motion
        sig[0] = np.where(hold > 0, 0.0, speed * TIMING_SIGMA_S)
    S = np.concatenate(samples)
    S_uv = camera.project(S)
    coverage = roi.coverage(S_uv)
    target_ok = np.array([len(p) >= 2 for p in picks])
    needed = _needed_marker(s, lim, reasons)
    design = Design(
        params=params, targets_uv=targets, target_ok=target_ok, target_reason=tuple(reasons), marker_site=marker,
        vehicle_site=vehicle, uv=uv, marker_px=mpx, target=ti, depth_index=layer_of, hold_s=hold, leg=leg_arr,
        speed_m_s=speed, samples_site=S, samples_uv=S_uv, samples_sigma_h_m=np.concatenate(sig),
        samples_is_hold=np.concatenate(is_hold), samples_rtk_factor=np.concatenate(rtk), coverage=coverage, needed_marker_m=needed,
    )
    return replace(design, unreachable=tuple(unreachable_parts(roi, design, limits)))


def _needed_marker(s: dict[str, np.ndarray], lim: Limits, reasons: list[str | None]) -> float | None:
    """Marker side (m) that would free the targets blocked only by the marker size, or None."""
    need = []
    for i, why in enumerate(reasons):
        if why != "marker_too_small":
            continue
        cand = s["in_view"][i] & s["reachable"][i] & (s["marker_px"][i] > 0)
        if cand.any():
            need.append(float(np.min(lim.marker_size_m * lim.min_marker_px / s["marker_px"][i][cand])))
    return max(need) if need else None


def _empty_design(params: DesignParams, targets: np.ndarray, reasons: list[str | None], roi: Roi) -> Design:
    z3, z2, z1 = np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0)
    d = Design(params=params, targets_uv=targets, target_ok=np.zeros(len(targets), bool), target_reason=tuple(reasons),
               marker_site=z3, vehicle_site=z3, uv=z2, marker_px=z1, target=z1.astype(int), depth_index=z1.astype(int),
               hold_s=z1, leg=z1.astype(int), speed_m_s=0.0, samples_site=z3, samples_uv=z2, samples_sigma_h_m=z1,
               samples_is_hold=z1.astype(bool), samples_rtk_factor=z1, coverage=0.0)
    return d


def _region_name(u: float, v: float, w: int, h: int) -> str:
    col = ("left", "centre", "right")[min(2, int(3 * u / w))]
    row = ("top", "middle", "bottom")[min(2, int(3 * v / h))]
    return "centre" if (row, col) == ("middle", "centre") else f"{row}-{col}" if col != "centre" else f"{row} centre"


def unreachable_parts(roi: Roi, design: Design, limits: Limits) -> list[dict]:
    """The ROI cells no sample reaches, grouped by reason and image region, in plain words.

    A cell out of reach takes the reason of the nearest target that got
    fewer than two depths; cells whose nearest target is fine are "between
    samples" (a denser lattice reaches them). Each entry: ``region`` (e.g.
    'bottom-left'), ``share_pct`` of the ROI cells, ``ground_m`` [min, max]
    distance from the pole of the ROI ground there (or None), ``reason``
    (a rule name), ``text``.
    """
    n_roi = int(roi.cells.sum())
    if n_roi == 0:
        return []
    reached = np.zeros_like(roi.cells)
    if len(design.samples_uv):
        r, c = roi.cell_of(design.samples_uv)
        ny, nx = roi.cells.shape
        for dr in (-1, 0, 1):
            for dc in (-1, 0, 1):
                rr, cc = r + dr, c + dc
                inside = (rr >= 0) & (rr < ny) & (cc >= 0) & (cc < nx)
                reached[rr[inside], cc[inside]] = True
    missing = roi.cells & ~reached
    if not missing.any():
        return []
    du, dv = roi.cell_px
    rows, cols = np.nonzero(missing)
    centres = np.column_stack([(cols + 0.5) * du, (rows + 0.5) * dv])
    tgt = design.targets_uv
    nearest = np.argmin(np.linalg.norm(centres[:, None, :] - tgt[None], axis=2), axis=1)
    why = [design.target_reason[k] or "between_samples" for k in nearest]
    regions = [_region_name(u, v, roi.width, roi.height) for u, v in centres]
    pr, pc = roi.cell_of(roi.uv)
    out: dict[tuple[str, str], list[int]] = {}
    for k, key in enumerate(zip(why, regions)):
        out.setdefault(key, []).append(k)
    fmt = {"min_agl": limits.min_agl_m, "max_agl": "unset" if limits.max_agl_m is None else f"{limits.max_agl_m:g} m",
           "keep_out": limits.keep_out_m, "max_range": "unset" if limits.max_range_m is None else f"{limits.max_range_m:g} m",
           "size": design.params.marker_size_m, "min_px": limits.min_marker_px, "margin": limits.margin_px, "ratio": MIN_DEPTH_RATIO}
    parts = []
    for (reason, region), ks in sorted(out.items(), key=lambda kv: -len(kv[1])):
        cell_ids = rows[ks] * roi.cells.shape[1] + cols[ks]
        in_cells = np.isin(pr * roi.cells.shape[1] + pc, cell_ids) & roi.on_ground
        ground = None
        if in_cells.any():
            d = np.hypot(roi.points_site[in_cells, 0], roi.points_site[in_cells, 1])
            ground = [round(float(d.min()), 1), round(float(d.max()), 1)]
        share = 100.0 * len(ks) / n_roi
        text_reason = "a denser target lattice would reach it" if reason == "between_samples" else REASON_TEXT.get(reason, reason).format(**fmt)
        g = f" (ground {ground[0]:g}-{ground[1]:g} m)" if ground else ""
        parts.append({"region": region, "share_pct": round(share, 1), "ground_m": ground, "reason": reason,
                      "text": f"the image's {region} {share:.0f} % of the ROI{g}: {text_reason}"})
    return parts
