"""The simulated camera's renderer and scene geometry (dronecal_field.sim.render / scene).

Truth is the camera model itself: every check compares what a real ArUco
detector finds in the rendered image with where core.camera projects the
marker's corners, or checks the geometry against hand-derived values.
"""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest

from dronecal_field.core.camera import Camera, CameraPose, Distortion, Intrinsics, look_rotation, pixel_rays_batch
from dronecal_field.errors import InputError
from dronecal_field.sim.render import (
    FrameRenderer,
    make_background,
    marker_board_image,
    render_frame,
    subpixel_offsets,
)
from dronecal_field.sim.scene import (
    MarkerSpec,
    R_enu_from_frd,
    VehiclePose,
    make_truth_camera,
    marker_centre_world,
    marker_corners_world,
    yaw_towards,
)

ORIGIN = (-35.363261, 149.165230, 584.0)
DISTORTION = Distortion(k1=-0.25, k2=0.08, p1=0.001, p2=-0.0005)
OFFSET = (0.1, 0.0, 0.1)


def detector() -> cv2.aruco.ArucoDetector:
    """ArUco with sub-pixel corners; a refinement window of half a marker cell (see docs/simulators.md)."""
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.relativeCornerRefinmentWinSize = 0.5
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50), params)


def diagonal_intersection(c: np.ndarray) -> np.ndarray:
    """(2,) where the straight lines corner0-corner2 and corner1-corner3 cross; c is (4, 2)."""
    A = np.array([c[2] - c[0], c[1] - c[3]]).T
    s = np.linalg.solve(A, c[1] - c[0])
    return c[0] + s[0] * (c[2] - c[0])


@pytest.fixture(scope="module")
def pole_camera() -> Camera:
    # The ArduCopter replay's site: a 3 m pole looking north, 30 deg down.
    return make_truth_camera(ORIGIN, 3.0, 0.0, 30.0, 1000.0, 1280, 960, DISTORTION)


@pytest.fixture(scope="module")
def clean_renderer(pole_camera: Camera) -> FrameRenderer:
    return FrameRenderer(pole_camera, MarkerSpec(offset_frd_m=OFFSET), noise_sigma_dn=0.0, seed=3)


def grid_poses(camera: Camera):
    """The replay's grid (4..8 m north, -2..2 m east, 1.5/2.5 m up), nose at the camera, small tilts."""
    for i, (north, east, up) in enumerate(itertools.product((4.0, 6.0, 8.0), (-2.0, 0.0, 2.0), (1.5, 2.5))):
        ant = np.array([east, north, up])
        yaw = yaw_towards(ant, camera.pose.position_world) + 0.02 * np.sin(3 * i)
        yield VehiclePose(antenna_enu_m=ant, roll_rad=0.03 * np.sin(i), pitch_rad=0.03 * np.cos(i), yaw_rad=yaw)


def true_corners(camera: Camera, v: VehiclePose, size_m: float = 0.4) -> np.ndarray:
    return camera.project(marker_corners_world(v.antenna_enu_m, v.roll_rad, v.pitch_rad, v.yaw_rad, OFFSET, size_m))


def fully_inside(camera: Camera, uv: np.ndarray, margin_px: float = 40.0) -> bool:
    return bool(np.all(uv >= margin_px) and np.all(uv[:, 0] < camera.width - margin_px) and np.all(uv[:, 1] < camera.height - margin_px))


# ---------------------------------------------------------------- geometry


def test_attitude_rotation_maps_body_axes_to_enu() -> None:
    # Nose east (yaw 90 deg): forward -> east, right -> south, down -> -up.
    R = R_enu_from_frd(0.0, 0.0, np.pi / 2)
    np.testing.assert_allclose(R @ [1, 0, 0], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [0, 1, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(R @ [0, 0, 1], [0, 0, -1], atol=1e-12)
    # Pitch up 10 deg, nose north: forward gains +sin(10 deg) up.
    R = R_enu_from_frd(0.0, np.radians(10.0), 0.0)
    np.testing.assert_allclose(R @ [1, 0, 0], [0, np.cos(np.radians(10)), np.sin(np.radians(10))], atol=1e-12)
    # Roll right 10 deg: the right wing goes down.
    R = R_enu_from_frd(np.radians(10.0), 0.0, 0.0)
    assert (R @ [0, 1, 0])[2] == pytest.approx(-np.sin(np.radians(10.0)), abs=1e-12)


def test_marker_corners_are_the_square_in_front_of_the_nose() -> None:
    ant = np.array([1.0, 5.0, 2.0])
    # Nose north, level: offset 0.1 forward, 0.1 down -> centre 0.1 m north and 0.1 m lower.
    centre = marker_centre_world(ant, 0.0, 0.0, 0.0, OFFSET)
    np.testing.assert_allclose(centre, [1.0, 5.1, 1.9], atol=1e-12)
    c = marker_corners_world(ant, 0.0, 0.0, 0.0, OFFSET, 0.4)
    # Seen from the north (from in front of the nose), top-left is the body's right (east) and up.
    np.testing.assert_allclose(c[0], [1.2, 5.1, 2.1], atol=1e-12)
    np.testing.assert_allclose(c[2], [0.8, 5.1, 1.7], atol=1e-12)
    np.testing.assert_allclose(c.mean(axis=0), centre, atol=1e-12)
    sides = np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)
    np.testing.assert_allclose(sides, 0.4, atol=1e-12)
    # Batched over N poses gives the same corners.
    batch = marker_corners_world(np.stack([ant, ant]), np.zeros(2), np.zeros(2), np.zeros(2), OFFSET, 0.4)
    assert batch.shape == (2, 4, 3)
    np.testing.assert_allclose(batch[1], c, atol=1e-12)


def test_yaw_towards_points_the_nose_at_the_camera() -> None:
    assert yaw_towards(np.array([0.0, 5.0, 2.0]), np.array([0.0, 0.0, 3.0])) == pytest.approx(np.pi)
    assert yaw_towards(np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])) == pytest.approx(np.pi / 2)
    with pytest.raises(InputError):
        yaw_towards(np.zeros(3), np.array([0.0, 0.0, 5.0]))


def test_truth_camera_looks_along_azimuth_and_tilt() -> None:
    cam = make_truth_camera(ORIGIN, 4.0, 90.0, 20.0, 800.0, 640, 480)
    np.testing.assert_allclose(cam.pose.position_world, [0.0, 0.0, 4.0], atol=1e-12)
    axis = cam.pose.R_cam_from_world[2]  # optical axis in ENU
    np.testing.assert_allclose(axis, [np.cos(np.radians(20)), 0.0, -np.sin(np.radians(20))], atol=1e-12)
    # A point on the optical axis projects to the principal point (319.5, 239.5).
    np.testing.assert_allclose(cam.project((cam.pose.position_world + 10 * axis)[None])[0], [319.5, 239.5], atol=1e-9)
    assert cam.enu_origin == ORIGIN


# ---------------------------------------------------------------- rays and texture


def test_subpixel_rays_follow_the_exact_inverse_distortion(pole_camera: Camera, clean_renderer: FrameRenderer) -> None:
    rays = clean_renderer.rays
    rng = np.random.default_rng(0)
    ui = rng.integers(0, pole_camera.width, 400)
    vi = rng.integers(0, pole_camera.height, 400)
    offsets = subpixel_offsets(3)
    du, dv = offsets[rng.integers(0, 9, 400)].T
    x = rays.x[vi, ui] + rays.dx_du[vi, ui] * du + rays.dx_dv[vi, ui] * dv
    y = rays.y[vi, ui] + rays.dy_du[vi, ui] * du + rays.dy_dv[vi, ui] * dv
    # The same sub-pixel points through pixel_rays_batch (20 Newton steps) ...
    uv = np.stack([ui + du, vi + dv], -1)[None]
    exact = pixel_rays_batch(pole_camera.intrinsics.as_array()[None], pole_camera.distortion.as_array()[None], np.eye(3)[None], uv)[0]
    # ... and back through the forward model: both land on the sample to well under 1e-3 px.
    cam_frame = Camera(intrinsics=pole_camera.intrinsics, distortion=pole_camera.distortion, pose=CameraPose(np.eye(3), np.zeros(3)))
    back = cam_frame.project(np.stack([x, y, np.ones_like(x)], -1))
    assert np.abs(back - uv[0]).max() < 1e-3
    np.testing.assert_allclose(x, exact[:, 0] / exact[:, 2], atol=1e-6)


def test_subpixel_pattern_has_one_sample_per_row_and_column() -> None:
    off = subpixel_offsets(3)
    assert off.shape == (9, 2)
    assert len(np.unique(np.round(off[:, 0], 9))) == 9 and len(np.unique(np.round(off[:, 1], 9))) == 9
    assert np.abs(off).max() < 0.5
    np.testing.assert_allclose(off.mean(axis=0), 0.0, atol=1e-12)


def test_board_has_quiet_zone_and_rejects_bad_markers() -> None:
    board = marker_board_image(MarkerSpec(dictionary="DICT_4X4_50", marker_id=7))
    assert board.shape == (8, 8)  # 4 bits + black border + white quiet zone
    assert np.all(board[0] == 255) and np.all(board[:, -1] == 255)
    assert np.all(board[1, 1:-1] == 0) and np.all(board[1:-1, 1] == 0)
    assert marker_board_image(MarkerSpec(dictionary="DICT_6X6_250", marker_id=3, quiet_zone_bits=2)).shape == (12, 12)
    with pytest.raises(InputError, match="dictionary"):
        marker_board_image(MarkerSpec(dictionary="DICT_NOPE"))
    with pytest.raises(InputError, match="not in DICT_4X4_50"):
        marker_board_image(MarkerSpec(marker_id=50))


def test_fronto_parallel_marker_has_the_right_area_and_centroid() -> None:
    # A pinhole camera at the origin looking north; a level drone 6 m north, nose south.
    cam = Camera(
        intrinsics=Intrinsics(fx=1000.0, fy=1000.0, cx=319.5, cy=239.5, width=640, height=480),
        distortion=Distortion(),
        pose=CameraPose.from_position(look_rotation(np.array([0.0, 1.0, 0.0])), np.zeros(3)),
    )
    marker = MarkerSpec(marker_id=0, offset_frd_m=(0.0, 0.0, 0.0))
    # 6.137 m: cells of 10.86 px, so the cell edges fall at all sub-pixel phases
    # (at 6 m they would be 100/9 px and every edge would share one phase of the 1/9 px sampling).
    v = VehiclePose(antenna_enu_m=np.array([0.0123, 6.137, 0.0371]), yaw_rad=np.pi)
    background = np.full((480, 640, 3), 215, np.uint8)  # as white as the board: only black cells show
    img = render_frame(cam, background, v, marker, 0.0, np.random.default_rng(0)).astype(float)[..., 1]
    # The body (45) is hidden behind the board except at the sides; keep only the board's box.
    uv = cam.project(marker_corners_world(v.antenna_enu_m, 0.0, 0.0, np.pi, (0, 0, 0), 0.4))
    u0, v0 = np.floor(uv.min(0)).astype(int) - 2
    u1, v1 = np.ceil(uv.max(0)).astype(int) + 3
    dark = (215.0 - img[v0:v1, u0:u1]) / (215.0 - 30.0)
    board = marker_board_image(marker)[1:-1, 1:-1] == 0  # (6, 6) black cells
    cell_px = 1000.0 * (0.4 / 6) / 6.137
    expected_area = board.sum() * cell_px**2
    assert dark.sum() == pytest.approx(expected_area, rel=2e-3)
    rows, cols = np.nonzero(board)
    # Cell (r, c) centre in pixels: top-left corner + (c + 0.5, r + 0.5) cells.
    expected = uv[0] + cell_px * np.array([cols.mean() + 0.5, rows.mean() + 0.5])
    vv, uu = np.mgrid[v0:v1, u0:u1]
    centroid = np.array([(dark * uu).sum(), (dark * vv).sum()]) / dark.sum()
    np.testing.assert_allclose(centroid, expected, atol=0.02)


# ---------------------------------------------------------------- detection through the distorted camera


def test_detected_corners_match_the_projected_truth_without_noise(pole_camera: Camera, clean_renderer: FrameRenderer) -> None:
    det = detector()
    errors = []
    for v in grid_poses(pole_camera):
        truth = true_corners(pole_camera, v)
        if not fully_inside(pole_camera, truth):
            continue
        corners, ids, _ = det.detectMarkers(cv2.cvtColor(clean_renderer.render(v), cv2.COLOR_BGR2GRAY))
        assert ids is not None and ids.ravel().tolist() == [0], f"marker not found at {v.antenna_enu_m}"
        errors.append(np.abs(corners[0][0] - truth).max())
    assert len(errors) >= 12
    assert max(errors) < 0.3
    assert np.mean(errors) < 0.25


def test_detected_corners_with_pixel_noise(pole_camera: Camera, clean_renderer: FrameRenderer) -> None:
    renderer = FrameRenderer(pole_camera, MarkerSpec(offset_frd_m=OFFSET), noise_sigma_dn=2.0, seed=11, rays=clean_renderer.rays)
    det = detector()
    corner_err, centre_err = [], []
    for v in grid_poses(pole_camera):
        truth = true_corners(pole_camera, v)
        if not fully_inside(pole_camera, truth):
            continue
        frame = renderer.render(v)
        corners, ids, _ = det.detectMarkers(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
        assert ids is not None
        c = corners[0][0].astype(float)
        corner_err.append(np.abs(c - truth).max())
        centre = pole_camera.project(marker_centre_world(v.antenna_enu_m, v.roll_rad, v.pitch_rad, v.yaw_rad, OFFSET)[None])[0]
        centre_err.append(np.linalg.norm(diagonal_intersection(c) - centre))
    assert len(corner_err) >= 12
    # The noise really is there: frame minus background has the requested sigma.
    assert (frame.astype(float) - renderer.background)[600:].std() == pytest.approx(2.0, rel=0.1)
    assert max(corner_err) < 1.0
    # Distortion bends the diagonals, so their straight-line crossing is off the
    # projected centre by up to ~0.6 px here (measured: see the next test).
    assert max(centre_err) < 1.0


def test_diagonal_crossing_is_the_centre_only_without_distortion(pole_camera: Camera) -> None:
    pinhole = pole_camera.with_(distortion=Distortion())
    worst_pinhole, worst_distorted = 0.0, 0.0
    for v in grid_poses(pole_camera):
        centre_w = marker_centre_world(v.antenna_enu_m, v.roll_rad, v.pitch_rad, v.yaw_rad, OFFSET)[None]
        for cam in (pinhole, pole_camera):
            err = np.linalg.norm(diagonal_intersection(true_corners(cam, v)) - cam.project(centre_w)[0])
            if cam is pinhole:
                worst_pinhole = max(worst_pinhole, err)
            else:
                worst_distorted = max(worst_distorted, err)
    assert worst_pinhole < 1e-6  # a projective map keeps the diagonals' crossing
    assert 0.05 < worst_distorted < 1.0


def test_marker_seen_from_behind_is_not_detected(pole_camera: Camera, clean_renderer: FrameRenderer) -> None:
    ant = np.array([0.0, 6.0, 2.0])
    away = VehiclePose(antenna_enu_m=ant, yaw_rad=0.0)  # nose north, away from the camera
    frame = clean_renderer.render(away)
    corners, ids, _ = detector().detectMarkers(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    assert ids is None
    # The drone is still drawn: its body (45) in front of the board's grey back (150),
    # which shows below the body (0.3 m under the antenna, 0.1 m behind it).
    body = pole_camera.project(ant[None])[0]
    board_back = pole_camera.project((ant + np.array([0.0, 0.1, -0.3]))[None])[0]
    assert float(frame[int(round(body[1])), int(round(body[0]))].mean()) == pytest.approx(45.0, abs=1.0)
    assert float(frame[int(round(board_back[1])), int(round(board_back[0]))].mean()) == pytest.approx(150.0, abs=1.0)


# ---------------------------------------------------------------- background and noise


def test_background_horizon_is_where_the_camera_puts_it() -> None:
    # Horizontal camera, no distortion: the horizon (far level points) is the row cy = 119.5.
    cam = make_truth_camera(ORIGIN, 3.0, 45.0, 0.0, 600.0, 320, 240)
    bg = make_background(cam, seed=1).astype(float)
    blue_minus_red = bg[..., 0] - bg[..., 2]
    for col in (10, 160, 310):
        sky_rows = np.nonzero(blue_minus_red[:, col] > 25)[0]
        assert sky_rows.min() == 0
        assert cam.intrinsics.cy - 2 < sky_rows.max() < cam.intrinsics.cy + 1  # sky down to the horizon, not below
        assert len(sky_rows) == sky_rows.max() + 1  # one sky region, no holes
    # Ground near the camera is textured: neighbouring pixels differ.
    assert np.abs(np.diff(bg[200:, :, 1], axis=1)).mean() > 0.3
    # Tilted down 30 deg with a 22 deg half field of view: no sky at all.
    down = make_background(make_truth_camera(ORIGIN, 3.0, 0.0, 30.0, 600.0, 320, 240), seed=1).astype(float)
    assert np.all(down[..., 0] - down[..., 2] < 25)


def test_noise_has_the_requested_sigma_and_empty_scene_is_background(pole_camera: Camera) -> None:
    small = make_truth_camera(ORIGIN, 3.0, 0.0, 30.0, 500.0, 320, 240)
    flat = np.full((240, 320, 3), 100, np.uint8)
    rng = np.random.default_rng(4)
    fresh = render_frame(small, flat, None, MarkerSpec(), 2.0, rng).astype(float)
    assert fresh.mean() == pytest.approx(100.0, abs=0.05)
    assert fresh.std() == pytest.approx(2.0, rel=0.05)
    clean = render_frame(small, flat, None, MarkerSpec(), 0.0, rng)
    assert np.array_equal(clean, flat)
    # The fast path (pre-drawn field, random window) has the same statistics.
    renderer = FrameRenderer(small, MarkerSpec(), noise_sigma_dn=2.0, seed=5)
    a = renderer.render(None).astype(float) - renderer.background
    b = renderer.render(None).astype(float) - renderer.background
    assert a.std() == pytest.approx(2.0, rel=0.1)
    assert not np.array_equal(a, b)  # a new window each frame


def test_background_size_mismatch_is_an_input_error() -> None:
    cam = make_truth_camera(ORIGIN, 3.0, 0.0, 30.0, 500.0, 320, 240)
    with pytest.raises(InputError, match="background"):
        render_frame(cam, np.zeros((10, 10, 3), np.uint8), None, MarkerSpec(), 0.0, np.random.default_rng(0))


# ---------------------------------------------------------------- the fast paths: adaptive tracing, the streaming frame buffer


def test_adaptive_trace_is_tracing_every_pixel(pole_camera: Camera, clean_renderer: FrameRenderer) -> None:
    from dronecal_field.sim.render import render_marker_layer

    poses = list(grid_poses(pole_camera))
    # Closer and more oblique than the grid: the body fills a large box, the board seen at 50 deg.
    poses.append(VehiclePose(antenna_enu_m=np.array([0.3, 2.5, 2.2]), roll_rad=0.1, yaw_rad=yaw_towards(np.array([0.3, 2.5, 2.2]), pole_camera.pose.position_world) + 0.9))
    marker = MarkerSpec(offset_frd_m=OFFSET)
    mixed_share = []
    for v in poses:
        full = render_marker_layer(pole_camera, v, marker, clean_renderer.board, clean_renderer.rays, 3, adaptive=False)
        fast = render_marker_layer(pole_camera, v, marker, clean_renderer.board, clean_renderer.rays, 3, adaptive=True)
        assert full is not None and fast is not None and fast[0] == full[0]
        # The same numbers, not close ones: uniform pixels' sums are exact and edge pixels are traced as before.
        assert np.array_equal(fast[1], full[1]) and np.array_equal(fast[2], full[2])
        edge = (full[2] > 0) & (full[2] < 1)
        mixed_share.append(edge.mean())
    # Most of each box is uniform (what makes the adaptive trace worth it): edge pixels are a small share.
    assert np.median(mixed_share) < 0.2


def test_render_in_place_draws_the_drone_over_a_frozen_background(pole_camera: Camera, clean_renderer: FrameRenderer) -> None:
    poses = list(grid_poses(pole_camera))[:4]
    # Without noise the stream's frames are exactly render()'s, also after an empty frame and a move.
    for v in [poses[0], poses[1], None, poses[2], poses[3], poses[3]]:
        assert np.array_equal(clean_renderer.render_in_place(v), clean_renderer.render(v))

    noisy = FrameRenderer(pole_camera, MarkerSpec(offset_frd_m=OFFSET), noise_sigma_dn=2.0, seed=11, rays=clean_renderer.rays)
    empty = noisy.render_in_place(None).copy()
    assert (empty.astype(float) - noisy.background).std() == pytest.approx(2.0, rel=0.1)
    a = noisy.render_in_place(poses[0]).copy()
    b = noisy.render_in_place(poses[0]).copy()
    changed = np.any(a != empty, axis=2)
    rows, cols = np.nonzero(changed)
    box_area = (np.ptp(rows) + 1) * (np.ptp(cols) + 1)
    assert 0 < changed.sum() <= box_area < 0.1 * changed.size  # only the drone's box differs from the empty frame
    assert not np.array_equal(a, b)  # fresh noise inside the box each frame
    assert np.array_equal(noisy.render_in_place(None), empty)  # the box is put back
    det = detector()
    truth = true_corners(pole_camera, poses[0])
    corners, ids, _ = det.detectMarkers(cv2.cvtColor(a, cv2.COLOR_BGR2GRAY))
    assert ids is not None and ids.ravel().tolist() == [0]
    assert np.abs(corners[0][0] - truth).max() < 1.0
    # The same frame through render() (full-frame noise): the detected corners agree to well under a pixel.
    ref, _, _ = det.detectMarkers(cv2.cvtColor(noisy.render(poses[0]), cv2.COLOR_BGR2GRAY))
    assert np.abs(corners[0][0] - ref[0][0]).max() < 0.3
