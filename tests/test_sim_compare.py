"""sim/compare.py: an estimated camera against the truth, with cases whose answer is known exactly."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dronecal_field.core.camera import CameraPose, Distortion, Intrinsics, rotation_from_vector
from dronecal_field.core.synthetic import pole_camera
from dronecal_field.errors import InputError
from dronecal_field.sim.compare import (
    compare_cameras,
    error_stats,
    fold_radius,
    ground_error_m,
    image_volume_points,
    points_in_hull,
    rotation_error_deg,
    visible_ground_grid,
)

WIDE = Distortion(k1=-0.28, k2=0.07)


def wide(distortion: Distortion = WIDE):
    return pole_camera(900.0, 1920, 1080, (0.0, 0.0, 3.5), 25.0, distortion=distortion)


def moved(camera, shift_m):
    return camera.with_(pose=CameraPose.from_position(camera.pose.R_cam_from_world, camera.pose.position_world + np.asarray(shift_m, float)))


def with_focal(camera, f):
    i = camera.intrinsics
    return camera.with_(intrinsics=Intrinsics(fx=f, fy=f, cx=i.cx, cy=i.cy, width=i.width, height=i.height))


def test_identical_cameras_agree_everywhere():
    cam = wide()
    hull = np.array([[4, -3, 1], [8, -3, 1], [4, 3, 1], [8, 3, 1], [4, -3, 4], [8, -3, 4], [4, 3, 4], [8, 3, 4]], float)
    c = compare_cameras(cam, cam, hull)
    assert c.focal_error_pct == 0.0 and c.principal_point_error_px == 0.0 and c.position_error_cm == 0.0
    assert c.rotation_error_deg == pytest.approx(0.0, abs=1e-9)
    for stats in (c.ground, c.sampled, c.image):
        assert stats.rms_px == pytest.approx(0.0, abs=1e-9) and stats.max_px == pytest.approx(0.0, abs=1e-9)
    assert c.ground_error_cm_rms == pytest.approx(0.0, abs=1e-6) and c.ground_misses == 0
    assert all(v == pytest.approx(0.0, abs=1e-6) for v in c.ground_error_cm_at.values())
    # 0.25 m grid, 3-30 m, what a 94 deg wide camera tilted 25 deg on 3.5 m sees.
    assert 10_000 < c.ground.n_points < 20_000
    assert c.sampled.n_points > 1000 and c.image.n_points > 1000


def test_focal_change_gives_the_pinhole_pixel_error_at_a_known_point():
    truth = pole_camera(1000.0, 1280, 960, (0.0, 0.0, 4.0), 20.0)
    est = with_focal(truth, 1010.0)
    # A point at normalised (0.3, -0.2) in the truth camera: u - cx = f x, so 1 % of f moves it 1 % of f |(x, y)|.
    R, c = truth.pose.R_cam_from_world, truth.pose.position_world
    point = c + R.T @ np.array([0.3, -0.2, 1.0]) * 7.0
    stats = error_stats(truth, est, point[None])
    assert stats.rms_px == pytest.approx(10.0 * np.hypot(0.3, -0.2), rel=1e-9)
    assert stats.n_points == 1
    cmp = compare_cameras(truth, est)
    assert cmp.focal_error_pct == pytest.approx(1.0) and cmp.focal_error_px == pytest.approx(10.0)
    assert cmp.sampled is None


def test_horizontal_shift_moves_every_ground_point_by_the_shift():
    truth = wide()
    est = moved(truth, (0.03, -0.04, 0.0))  # 5 cm
    c = compare_cameras(truth, est)
    assert c.position_error_cm == pytest.approx(5.0)
    assert c.ground_error_cm_rms == pytest.approx(5.0, abs=1e-6)
    assert c.ground_error_cm_max == pytest.approx(5.0, abs=1e-6)
    assert c.ground_error_cm_at[15.0] == pytest.approx(5.0, abs=1e-6)
    assert c.ground_misses == 0


def test_height_error_scales_the_ground_error_with_range():
    truth = wide()
    est = moved(truth, (0.0, 0.0, 0.035))  # 1 % of the 3.5 m mount height
    pts, ranges = visible_ground_grid(truth)
    err = ground_error_m(truth, est, pts)
    # Same ray from a camera 1 % higher meets the ground 1 % further from the pole's foot.
    np.testing.assert_allclose(err, 0.01 * ranges, rtol=1e-6, atol=1e-9)
    c = compare_cameras(truth, est)
    assert c.ground_error_cm_at[15.0] == pytest.approx(15.0, rel=0.01)
    assert c.ground_error_cm_at[30.0] == pytest.approx(30.0, rel=0.01)


def test_rotation_error_is_the_angle_between_the_orientations():
    truth = wide()
    R = rotation_from_vector(np.array([0.0, np.radians(0.5), 0.0])) @ truth.pose.R_cam_from_world
    est = truth.with_(pose=CameraPose.from_position(R, truth.pose.position_world))
    assert rotation_error_deg(truth, est) == pytest.approx(0.5, rel=1e-9)


def test_fold_radius_of_a_k1_lens_and_none_without_fold():
    # r (1 + k1 r^2) stops growing where 1 + 3 k1 r^2 = 0.
    cam = pole_camera(1110.0, 1280, 960, (0.0, 0.0, 2.0), 30.0, distortion=Distortion(k1=-0.25))
    assert fold_radius(cam) == pytest.approx(1.0 / np.sqrt(0.75), abs=1e-4)
    assert fold_radius(wide()) == float("inf")  # 1 - 0.84 r^2 + 0.35 r^4 has no real root
    assert fold_radius(wide(Distortion())) == float("inf")


def test_ground_beyond_the_fold_is_left_out():
    # A lens that folds inside the image: the polynomial sends far ground back into the frame.
    folded = pole_camera(700.0, 1920, 1080, (0.0, 0.0, 3.5), 20.0, distortion=Distortion(k1=-0.45))
    pts, _ = visible_ground_grid(folded)
    R, t = folded.pose.R_cam_from_world, folded.pose.t_cam_from_world
    Xc = pts @ R.T + t
    assert np.hypot(Xc[:, 0] / Xc[:, 2], Xc[:, 1] / Xc[:, 2]).max() < fold_radius(folded)
    everything = np.stack(np.meshgrid(np.arange(-30, 30.1, 0.25), np.arange(-30, 30.1, 0.25)), -1).reshape(-1, 2)
    everything = np.column_stack([everything, np.zeros(len(everything))])
    r = np.hypot(everything[:, 0], everything[:, 1])
    everything = everything[(r >= 3) & (r <= 30)]
    uv = folded.project(everything)
    inside = (folded.depth(everything) > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] <= 1919) & (uv[:, 1] >= 0) & (uv[:, 1] <= 1079)
    assert inside.sum() > len(pts)  # some "visible" ground only lands in the image by folding


@settings(max_examples=25, deadline=None)
@given(
    height=st.floats(1.5, 8.0),
    tilt=st.floats(10.0, 50.0),
    focal=st.floats(500.0, 3000.0),
    k1=st.floats(-0.4, 0.0),
    azimuth=st.floats(-180.0, 180.0),
)
def test_ground_grid_is_what_the_truth_sees(height, tilt, focal, k1, azimuth):
    cam = pole_camera(focal, 1280, 720, (1.0, -2.0, height), tilt, azimuth_deg_from_x=azimuth, distortion=Distortion(k1=k1))
    try:
        pts, ranges = visible_ground_grid(cam, (3.0, 30.0), 0.5)
    except InputError:
        return
    if len(pts) == 0:
        return
    assert np.all(pts[:, 2] == 0.0)
    np.testing.assert_allclose(ranges, np.hypot(pts[:, 0] - 1.0, pts[:, 1] + 2.0))
    assert ranges.min() >= 3.0 and ranges.max() <= 30.0
    uv = cam.project(pts)
    assert np.all(cam.depth(pts) > 0) and uv.min() >= 0 and uv[:, 0].max() <= 1279 and uv[:, 1].max() <= 719
    # The grid is regular: every point is on the 0.5 m lattice around the pole.
    lattice = (pts[:, :2] - [1.0, -2.0]) / 0.5
    np.testing.assert_allclose(lattice, np.round(lattice), atol=1e-9)


def test_points_in_hull_fill_a_box_and_a_sixth_of_it_for_a_tetrahedron():
    box = np.array([[x, y, z] for x in (0, 2) for y in (0, 1) for z in (0, 3)], float)
    inside = points_in_hull(box, n=2000, seed=1)
    assert len(inside) == 2000
    tet = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    inside = points_in_hull(tet, n=6000, seed=1)
    assert np.all(inside.sum(axis=1) <= 1.0 + 1e-12) and np.all(inside >= 0)
    assert len(inside) / 6000 == pytest.approx(1 / 6, abs=0.02)
    flat = np.array([[0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]], float)
    np.testing.assert_array_equal(points_in_hull(flat), flat)  # no volume: the points themselves


def test_image_volume_points_come_back_to_their_pixels_at_4_to_12_m():
    cam = wide()
    pts = image_volume_points(cam, n=3000, seed=2)
    depth = cam.depth(pts)
    assert len(pts) > 1000
    assert depth.min() >= 4.0 - 1e-9 and depth.max() <= 12.0 + 1e-9
    uv = cam.project(pts)
    # They cover the image, corners included (the wide lens does not fold).
    assert uv[:, 0].min() < 100 and uv[:, 0].max() > 1820 and uv[:, 1].min() < 100


def test_no_visible_ground_is_refused_with_the_fix():
    up = pole_camera(900.0, 1920, 1080, (0.0, 0.0, 3.5), -60.0)  # looking at the sky
    with pytest.raises(InputError, match="sees no ground"):
        compare_cameras(up, up)
