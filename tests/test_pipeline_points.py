"""Per-waypoint points: lever arm, attitude interpolation, robust centres, sigmas, drop reasons."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dronecal_field.pipeline.hover import HoverWindow
from dronecal_field.pipeline.points import (
    PointOptions,
    attitude_at,
    drop_outlying_scatter,
    enu_from_frd,
    lever_arm_enu,
    marker_track_at,
    robust_centre,
    track_at,
    window_point,
)
from dronecal_field.sim.scene import R_enu_from_frd as sim_R_enu_from_frd

S = 1_000_000_000


def test_body_to_enu_matches_scipy_and_the_simulator():
    rpy = np.random.default_rng(0).uniform(-3, 3, (40, 3))
    ned = Rotation.from_euler("ZYX", rpy[:, ::-1]).as_matrix()
    enu = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]]) @ ned
    assert np.abs(enu_from_frd(rpy) - enu).max() < 1e-12
    assert np.abs(enu_from_frd(rpy) - sim_R_enu_from_frd(rpy[:, 0], rpy[:, 1], rpy[:, 2])).max() < 1e-12


@pytest.mark.parametrize(
    "yaw_deg, expected",
    [(0.0, [0.0, 0.3, -0.1]), (90.0, [0.3, 0.0, -0.1]), (180.0, [0.0, -0.3, -0.1]), (-90.0, [-0.3, 0.0, -0.1])],
)
def test_lever_arm_forward_and_down_in_enu(yaw_deg, expected):
    # 0.3 m forward, 0.1 m down of the antenna: north when facing north, east when facing east.
    arm = lever_arm_enu(np.array([0.3, 0.0, 0.1]), np.array([[0.0, 0.0, np.radians(yaw_deg)]]))
    assert np.allclose(arm[0], expected, atol=1e-12)


def test_attitude_interpolation_unwraps_yaw_across_north():
    t = np.array([0, 1 * S], np.int64)
    rpy = np.array([[0.0, 0.0, np.radians(179.0)], [0.1, 0.0, np.radians(-179.0)]])
    mid = attitude_at(np.array([S // 2]), t, rpy)[0]
    assert abs(abs(np.degrees(mid[2])) - 180.0) < 1e-9  # through 180, not through 0
    assert abs(mid[0] - 0.05) < 1e-12


def test_robust_centre_ignores_a_few_wild_samples():
    rng = np.random.default_rng(3)
    v = rng.normal([1.0, 2.0, 3.0], 0.01, (60, 3))
    v[:5] += 5.0
    med, std = robust_centre(v)
    assert np.abs(med - [1, 2, 3]).max() < 0.01
    assert np.all((std > 0.007) & (std < 0.016))


def _window_data(n_fix=15, n_det=20, fix_type="rtk_fixed", seed=0):
    rng = np.random.default_rng(seed)
    w = HoverWindow(index=0, start_ns=0, end_ns=3 * S, source="event", seq=5)
    fix_t = np.linspace(0, 3 * S, n_fix).astype(np.int64)
    xyz = np.array([1.0, 8.0, 2.5]) + rng.normal(0, 0.01, (n_fix, 3))
    sig = np.full((n_fix, 3), 0.008)
    types = [fix_type] * n_fix
    det_t = np.linspace(0, 3 * S, n_det).astype(np.int64) + 500_000_000  # camera stamps 0.5 s late
    uv = np.array([320.0, 200.0]) + rng.normal(0, 0.3, (n_det, 2))
    return w, fix_t, xyz, sig, types, det_t, uv


def test_window_point_uses_the_settled_part_and_the_camera_offset():
    w, fix_t, xyz, sig, types, det_t, uv = _window_data()
    p = window_point(w, w.stable(1.0, 0.2), fix_t, xyz, sig, types, det_t, uv, 500_000_000, PointOptions())
    assert p.used and p.dropped is None
    assert p.n_fixes == 9 and p.n_detections == 11  # fixes at 1.07..2.79 s, frames at 1.11..2.68 s
    assert np.abs(p.marker_enu_m - [1.0, 8.0, 2.5]).max() < 0.012
    assert np.abs(p.uv_px - [320, 200]).max() < 0.3
    # Sigma: the larger of the measured scatter and the receiver's own figure.
    assert np.all(p.sigma_enu_m >= 0.008)
    assert 0.1 <= p.sigma_px < 0.6


def test_window_point_drop_reasons():
    w, fix_t, xyz, sig, types, det_t, uv = _window_data(fix_type="rtk_float")
    stable = w.stable(1.0, 0.2)
    p = window_point(w, stable, fix_t, xyz, sig, types, det_t, uv, 500_000_000, PointOptions())
    assert not p.used and "rtk_float is worse than --min-fix rtk_fixed" in p.dropped
    p = window_point(w, stable, fix_t, xyz, sig, types, det_t, uv, 500_000_000, PointOptions(min_fix="rtk_float"))
    assert p.used
    p = window_point(w, stable, fix_t[:3], xyz[:3], sig[:3], types[:3], det_t, uv, 500_000_000, PointOptions())
    assert not p.used and "dropout" in p.dropped and p.n_fixes == 0
    p = window_point(w, stable, fix_t, xyz, sig, ["rtk_fixed"] * len(fix_t), det_t[:4], uv[:4], 500_000_000, PointOptions())
    assert not p.used and "detections" in p.dropped


def test_outlying_scatter_is_dropped_in_metres_at_the_marker():
    points = []
    for k in range(8):
        w, fix_t, xyz, sig, types, det_t, uv = _window_data(seed=k)
        if k == 5:
            uv = uv + np.random.default_rng(9).normal(0, 6.0, uv.shape)  # a detector flipping between corners
        sizes = np.full(len(det_t), 25.0 if k != 2 else 80.0)
        if k == 2:
            uv = np.array([320.0, 200.0]) + (uv - uv.mean(0)) * 3.0  # near: 3x the pixels, same metres
        p = window_point(w, w.stable(1.0, 0.2), fix_t, xyz, sig, types, det_t, uv, 500_000_000, PointOptions(), sizes, 0.4)
        points.append(p)
    out = drop_outlying_scatter(points, PointOptions())
    dropped = [k for k, p in enumerate(out) if not p.used]
    assert dropped == [5]
    assert "image scatter" in out[5].dropped


def test_paired_point_follows_the_drift_where_separate_medians_do_not():
    # The marker drifts 4 cm east over the hold; the camera sees u = 100 px per metre east.
    # Fixes at 5 Hz and frames at 10 Hz sample the drift at different instants and cover
    # different parts of it, so separate medians disagree; paired samples keep u = 100 x.
    w = HoverWindow(index=0, start_ns=0, end_ns=5 * S, source="event", seq=1)
    fix_t = np.arange(0, 5 * S + 1, S // 5, dtype=np.int64)
    east = lambda t: 0.04 * (t / (5 * S)) ** 3  # noqa: E731 - slow then fast: medians differ
    antenna = np.c_[east(fix_t), np.full(len(fix_t), 8.0), np.full(len(fix_t), 2.0)]
    det_capture = np.arange(int(1.05 * S), int(4.0 * S), S // 10, dtype=np.int64)
    uv = np.c_[100.0 * east(det_capture), np.full(len(det_capture), 200.0)]
    offset = 250_000_000
    det_marker, ok = marker_track_at(det_capture, fix_t, antenna, np.zeros(3), None, None)
    assert ok.all() and np.abs(det_marker[:, 0] - east(det_capture)).max() < 2e-4  # linear between 0.2 s fixes
    args = (w, w.stable(1.0, 0.2), fix_t, antenna, np.full((len(fix_t), 3), 0.008), ["rtk_fixed"] * len(fix_t),
            det_capture + offset, uv, offset)
    paired = window_point(*args, PointOptions(), det_marker_enu_m=det_marker)
    unpaired = window_point(*args, PointOptions(paired=False))
    assert abs(paired.uv_px[0] - 100.0 * paired.marker_enu_m[0]) < 0.01
    assert abs(unpaired.uv_px[0] - 100.0 * unpaired.marker_enu_m[0]) > 0.1


def test_pairing_at_the_fixes_uses_every_fix_with_the_image_track_between_frames():
    # RTK noise is white, so the 3D centre is best as the mean of every fix in the
    # settled part; frames decoded sparsely (0.4 s apart) give the image track at
    # each fix by interpolation, following the same drift.
    rng = np.random.default_rng(3)
    w = HoverWindow(index=0, start_ns=0, end_ns=5 * S, source="event", seq=1)
    fix_t = np.arange(0, 5 * S + 1, S // 10, dtype=np.int64)
    east = lambda t: 0.03 * np.sin(t / S)  # noqa: E731 - a slow drift
    antenna = np.c_[east(fix_t), np.full(len(fix_t), 8.0), np.full(len(fix_t), 2.0)] + rng.normal(0, 0.008, (len(fix_t), 3))
    det_capture = np.arange(int(0.7 * S), int(5.2 * S), 2 * S // 5, dtype=np.int64)
    uv = np.c_[100.0 * east(det_capture), np.full(len(det_capture), 200.0)]
    offset = 250_000_000
    det_marker, ok = marker_track_at(det_capture, fix_t, antenna, np.zeros(3), None, None)
    det_marker[~ok] = np.nan
    args = (w, w.stable(1.0, 0.2), fix_t, antenna, np.full((len(fix_t), 3), 0.008), ["rtk_fixed"] * len(fix_t),
            det_capture + offset, uv, offset)
    at_fixes = window_point(*args, PointOptions(pair_at="fixes"), det_marker_enu_m=det_marker)
    at_detections = window_point(*args, PointOptions(pair_at="detections"), det_marker_enu_m=det_marker)
    settled = (fix_t >= 1 * S) & (fix_t <= 4.8 * S)
    assert at_fixes.n_fixes == settled.sum() == 39
    np.testing.assert_allclose(at_fixes.marker_enu_m, antenna[settled].mean(0), atol=1e-12)
    # The image track at the fixes is the drift there (interpolation error < 0.05 px on 3 px of drift).
    assert abs(at_fixes.uv_px[0] - 100.0 * east(fix_t[settled]).mean()) < 0.05
    # Against the truth of the mean drift: the noise of 39 fixes, not of the 10 frame instants.
    truth_err = abs(at_fixes.marker_enu_m[2] - 2.0)
    assert truth_err < 3 * 0.008 / np.sqrt(39)
    assert at_detections.n_detections == 10


def test_track_at_interpolates_and_says_where_samples_bracket_the_instant():
    t = np.array([0, 1, 2, 4], np.int64) * S
    v = np.array([[0.0, 0.0], [1.0, 10.0], [2.0, 20.0], [4.0, 40.0]])
    at, ok = track_at(np.array([-1, 0, 0.5 * S, 3 * S, 4 * S, 5 * S], np.int64), t[::-1], v[::-1], max_gap_s=0.9)
    np.testing.assert_allclose(at[1:5, 0], [0.0, 0.5, 3.0, 4.0])
    assert ok.tolist() == [False, True, True, False, True, False]  # 3 s lies 1 s from the samples either side


@pytest.mark.parametrize("tau_s", [0.0, 5.0, 20.0])
def test_fix_noise_splits_white_and_correlated_parts(tau_s):
    # Residual series of 40 holds (3 s at 5 Hz): 6 mm white (detector, jitter) plus, when tau_s > 0,
    # 8 mm first-order Gauss-Markov RTK noise. The split decides how a hold's mean averages down.
    from dronecal_field.pipeline.points import FixNoise, estimate_fix_noise

    rng = np.random.default_rng(1)
    segments = []
    for s in range(60):
        t = np.arange(15, dtype=np.int64) * 200_000_000 + s * 10_000_000_000
        r = rng.normal(size=(15, 2)) * 0.006
        if tau_s:
            a = np.exp(-0.2 / tau_s)
            c = np.zeros((15, 2))
            c[0] = rng.normal(size=2) * 0.008
            for k in range(1, 15):
                c[k] = a * c[k - 1] + np.sqrt(1 - a * a) * rng.normal(size=2) * 0.008
            r = r + c
        segments.append((t, r))
    noise = estimate_fix_noise(segments)
    assert noise.sigma_white_m == pytest.approx(0.006, rel=0.2)
    if tau_s:
        assert noise.sigma_corr_m == pytest.approx(0.008, rel=0.25) and noise.tau_s > 2.0
    else:
        assert noise.sigma_corr_m == 0.0 and noise.tau_s is None
    # The mean of a hold's 15 fixes: white noise averages down, correlated noise hardly does.
    t15 = np.arange(15) * 0.2
    white = FixNoise(sigma_white_m=0.006, sigma_corr_m=0.0, tau_s=None, fix_interval_s=0.2, n_residuals=0)
    assert white.mean_variance(t15) == pytest.approx(0.006**2 / 15)
    slow = FixNoise(sigma_white_m=0.0, sigma_corr_m=0.008, tau_s=30.0, fix_interval_s=0.2, n_residuals=0)
    assert slow.mean_variance(t15) == pytest.approx(0.008**2, rel=0.05)
    assert estimate_fix_noise(segments[:1]) is None  # 15 residuals: too few to say


def test_a_leg_end_hold_too_short_to_settle_says_so():
    """A 1 s hold (the end of a fly-through leg) leaves 0.3 s after the settle time: its drop says it is a leg's end."""
    from dataclasses import replace

    from dronecal_field.pipeline.points import PointOptions, _too_few_detections

    w = HoverWindow(index=0, seq=4, source="event", start_ns=0, end_ns=1_000_000_000)
    short = _too_few_detections(1, w, (667_000_000, 1_000_000_000), PointOptions())
    assert "a 1.0 s hold (a leg's end) leaves 0.3 s after --settle-s 1" in short
    long = _too_few_detections(1, replace(w, end_ns=4_000_000_000), (1_000_000_000, 4_000_000_000), PointOptions())
    assert long == "1 marker detections in the settled part; need 3"
