"""Time alignment of the camera stream against the GNSS stream, from the data alone."""

from __future__ import annotations

import numpy as np
import pytest

from contract_writer import grid_waypoints, make_flight, pole_camera
from dronecal_field.pipeline.align import estimate_time_offset, interpolate_track, projective_residuals


@pytest.fixture(scope="module")
def scene():
    camera = pole_camera(distortion=(-0.15, 0.03, 0.0, 0.0, 0.0))
    flight = make_flight(camera, grid_waypoints(), seed=7)
    return camera, flight


def _streams(camera, flight, latency_s, fps=10.0, gnss_hz=5.0, seed=0, px_sigma=0.2, still_only=False):
    rng = np.random.default_rng(seed)
    capture = np.arange(flight.t_ns[0], flight.t_ns[-1], int(1e9 / fps))
    if still_only:
        capture = np.concatenate([capture[(capture > a) & (capture < b)] for a, b, _ in flight.holds])
    uv = camera.project(flight.marker_centre(capture)) + rng.normal(0, px_sigma, (len(capture), 2))
    stamp = capture + int(round(latency_s * 1e9))
    fix_t = np.arange(flight.t_ns[0], flight.t_ns[-1], int(1e9 / gnss_hz))
    fix = flight.marker_centre(fix_t) + rng.normal(0, 0.01, (len(fix_t), 3))
    mids = np.array([(a + b) // 2 for a, b, _ in flight.holds])
    groups = np.argmin(np.abs(stamp[:, None] - mids[None]), 1)
    return stamp, uv, fix_t, fix, groups


@pytest.mark.parametrize("latency_s", [0.5, -0.3, 0.0, 0.93])
def test_offset_is_recovered_within_its_reported_uncertainty(scene, latency_s):
    camera, flight = scene
    stamp, uv, fix_t, fix, groups = _streams(camera, flight, latency_s)
    off = estimate_time_offset(stamp, uv, fix_t, fix, groups=groups)
    assert off.method == "image-vs-gnss"
    assert off.std_s is not None and 0 < off.std_s < 0.03
    err = abs(off.offset_s - latency_s)
    assert err < 0.02, off
    assert err < 4 * off.std_s + 0.003, off
    if latency_s:
        # The right offset explains the track far better than none does.
        assert off.cost_min_px < 0.6 * off.cost_zero_px


def test_still_marker_gives_no_offset_rather_than_a_guess(scene):
    camera, _ = scene
    flight = make_flight(camera, grid_waypoints(), drift_m=0.0, seed=7)
    stamp, uv, fix_t, fix, groups = _streams(camera, flight, 0.4, still_only=True, px_sigma=0.05)
    off = estimate_time_offset(stamp, uv, fix_t, fix, groups=groups, min_moving_px=1.0)
    assert off.method == "none" and off.std_s is None and off.offset_s == 0.0


def test_interpolation_refuses_to_bridge_gaps():
    t = np.array([0, 100, 200, 2_000_000_000, 2_000_000_100], np.int64)
    xyz = np.arange(15, dtype=float).reshape(5, 3)
    values, valid = interpolate_track(np.array([50, 150, 1_000_000_000, 3_000_000_000]), t, xyz)
    assert valid.tolist() == [True, True, False, False]
    assert np.allclose(values[0], [1.5, 2.5, 3.5])


def test_projective_fit_is_exact_for_a_pinhole_and_handles_coplanar_points():
    camera = pole_camera()
    rng = np.random.default_rng(1)
    X = np.c_[rng.uniform(-3, 3, 40), rng.uniform(5, 12, 40), rng.uniform(0.5, 4, 40)]
    assert projective_residuals(X, camera.project(X)).max() < 1e-6
    X[:, 2] = 2.0  # one plane: a homography, not a DLT
    assert projective_residuals(X, camera.project(X)).max() < 1e-6


def test_offset_scan_through_a_strong_lens_finds_the_latency_the_raw_scan_misses():
    """The 4K pole camera (k1 -0.32, k2, k3, tangential) with legs into the image corners: the distortion-free scan
    is pulled off the latency, the same scan on pixels undistorted by the lens (pipeline.solve, after a first
    calibration) is not."""
    from contract_writer import make_leg_flight
    from contract_writer_4k import corner_leg_waypoints
    from dronecal_field.pipeline.solve import undistorted_pixels

    camera = pole_camera(width=3840, height=2160, f_px=2600.0, position_enu=(0.0, 0.0, 4.5), tilt_deg=35.0,
                         distortion=(-0.32, 0.12, 4e-4, -3e-4, -0.02), principal_offset_px=(12.0, -8.0))
    waypoints = corner_leg_waypoints(camera, (3.0, 5.0, 8.0), (1.0, 2.5, 4.0))
    flight = make_leg_flight(camera, waypoints, hold_s=np.full(len(waypoints), 3.0), speed_mps=0.18, accel_mps2=1.0, seed=0)
    rng = np.random.default_rng(0)
    latency = 0.35
    # frames 37 ms out of phase with the fixes: a scan against fixes phase-locked to the frames prefers the offsets
    # that interpolate between two noisy fixes (less variance), a test artefact a real camera's own clock does not have
    capture = int(0.037e9) + np.arange(flight.t_ns[0] + int(1e9), flight.t_ns[-1] - int(1e9), int(1e8))
    X = flight.marker_centre(capture)
    uv = camera.project(X)
    seen = (uv[:, 0] > 0) & (uv[:, 0] < 3840) & (uv[:, 1] > 0) & (uv[:, 1] < 2160) & (camera.depth(X) > 0)
    stamp, uv = capture[seen] + int(latency * 1e9), uv[seen] + rng.normal(0, 0.3, (int(seen.sum()), 2))
    fix_t = np.arange(flight.t_ns[0], flight.t_ns[-1], int(1e8))
    fix = flight.marker_centre(fix_t) + rng.normal(0, 0.01, (len(fix_t), 3))
    raw = estimate_time_offset(stamp, uv, fix_t, fix)
    lens = estimate_time_offset(stamp, undistorted_pixels(uv, camera), fix_t, fix)
    assert abs(lens.offset_s - latency) < 0.02  # measured 0.008
    assert abs(raw.offset_s - latency) > 0.05  # measured 0.098: why solve.py scans again through the lens
    # through the lens the minimum is clear: its cost well under the cost at 0 s
    assert lens.cost_zero_px > 1.5 * lens.cost_min_px
