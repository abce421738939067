"""Marker detection on rendered frames: ArUco centre accuracy, misses, corrupt frames, LED blobs."""

from __future__ import annotations

import numpy as np
import pytest

from contract_writer import MarkerLook, Renderer, encode_jpeg, grid_waypoints, make_flight, pole_camera
from dronecal_field.pipeline.detect import (
    centres_under_distortion,
    decode_gray,
    detect_aruco,
    detect_led,
    diagonal_intersection,
    make_aruco_detector,
    roi_around,
)


@pytest.fixture(scope="module")
def scene():
    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints(), seed=4)
    return camera, flight, Renderer(camera=camera, flight=flight)


def _hold_times(flight, per_hold: int = 3) -> np.ndarray:
    return np.concatenate([np.linspace(a, b, per_hold).astype(np.int64) for a, b, _ in flight.holds])


def test_diagonal_intersection_is_the_projected_centre_not_the_corner_mean():
    # A strongly foreshortened square: the corner mean is off, the diagonals' crossing is exact.
    H = np.array([[1.0, 0.2, 10.0], [0.1, 1.3, 5.0], [0.004, 0.002, 1.0]])
    square = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float) * 20 + 50
    centre = np.array([50.0, 50.0])

    def apply(p):
        q = np.c_[p, np.ones(len(p))] @ H.T
        return q[:, :2] / q[:, 2:]

    corners = apply(square)
    truth = apply(centre[None])[0]
    assert np.linalg.norm(diagonal_intersection(corners) - truth) < 1e-9
    assert np.linalg.norm(corners.mean(0) - truth) > 0.5


def test_centre_under_distortion_is_the_projected_centre_where_the_plain_crossing_is_not():
    # A 0.4 m square tilted 30 degrees, 6 m away near the corner of a k1 = -0.2 camera.
    from scipy.spatial.transform import Rotation

    camera = pole_camera(width=1920, height=1080, f_px=1400.0, position_enu=(0.0, 0.0, 4.0), tilt_deg=15.0,
                         distortion=(-0.20, 0.05, -3e-4, -1e-4, 0.0))
    centres_world = np.array([[3.4, 5.8, 0.9], [-3.4, 5.8, 3.9], [0.0, 9.0, 2.0]])
    half = 0.2 * np.array([[-1, 0, 1], [1, 0, 1], [1, 0, -1], [-1, 0, -1]], float)
    tilt = Rotation.from_euler("z", 30, degrees=True).as_matrix()
    corners = np.stack([camera.project(c + half @ tilt.T) for c in centres_world])
    truth = camera.project(centres_world)
    i = camera.intrinsics
    refined = centres_under_distortion(corners, np.array([i.fx, i.fy, i.cx, i.cy]), camera.distortion.as_array())
    plain = np.array([diagonal_intersection(c) for c in corners])
    assert np.abs(refined - truth).max() < 1e-6
    assert np.linalg.norm(plain[0] - truth[0]) > 0.1  # the bent diagonals near the edge
    # Without distortion the two agree.
    zero = centres_under_distortion(corners, np.array([i.fx, i.fy, i.cx, i.cy]), np.zeros(5))
    np.testing.assert_allclose(zero, plain, atol=1e-9)


def test_aruco_centres_are_subpixel_on_small_markers(scene):
    camera, flight, renderer = scene
    detector = make_aruco_detector("DICT_4X4_50")
    errors, sizes = [], []
    for t in _hold_times(flight):
        image = decode_gray(encode_jpeg(renderer.render(int(t))))
        res = detect_aruco(image, detector, 7, int(t))
        assert res.detection is not None, f"marker missed at {t}"
        errors.append(res.detection.uv_px - renderer.true_centre_px(np.array([t]))[0])
        sizes.append(res.detection.size_px)
    errors = np.array(errors)
    rms = float(np.sqrt(np.mean(np.sum(errors**2, 1))))
    assert min(sizes) < 22  # the far waypoints really are small markers
    assert rms < 0.25, f"centre RMS {rms:.3f} px"
    assert np.abs(errors.mean(0)).max() < 0.08  # no bias


def test_aruco_roi_search_gives_the_same_centre(scene):
    camera, flight, renderer = scene
    detector = make_aruco_detector("DICT_4X4_50")
    t = int(_hold_times(flight)[10])
    image = renderer.render(t)
    full = detect_aruco(image, detector, 7, t).detection
    roi = roi_around(full, image.shape)
    boxed = detect_aruco(image, detector, 7, t, roi=roi).detection
    assert roi[2] - roi[0] < image.shape[1] / 3
    assert np.abs(boxed.uv_px - full.uv_px).max() < 0.05


def test_wrong_id_is_reported_and_empty_frame_gives_nothing(scene):
    camera, flight, renderer = scene
    detector = make_aruco_detector("DICT_4X4_50")
    t = int(_hold_times(flight)[5])
    image = renderer.render(t)
    res = detect_aruco(image, detector, 3, t)
    assert res.detection is None and res.other_ids == (7,)
    empty = detect_aruco(renderer.render(t, visible=False), detector, 7, t)
    assert empty.detection is None and empty.other_ids == ()


def test_corrupt_and_truncated_frames_decode_to_none(scene):
    camera, flight, renderer = scene
    data = encode_jpeg(renderer.render(int(flight.holds[0][0])))
    assert decode_gray(data).shape == (camera.height, camera.width)
    assert decode_gray(data[: len(data) // 2]) is None
    assert decode_gray(b"") is None
    assert decode_gray(b"\x00" * 500) is None


def test_unknown_dictionary_is_refused():
    with pytest.raises(ValueError, match="DICT_9X9"):
        make_aruco_detector("DICT_9X9_50")


def test_led_blob_centre_is_subpixel():
    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints(), seed=5)
    renderer = Renderer(camera=camera, flight=flight, look=MarkerLook(kind="led"), dark=True)
    errors = []
    for t in _hold_times(flight, 2):
        image = decode_gray(encode_jpeg(renderer.render(int(t))))
        det = detect_led(image, int(t)).detection
        assert det is not None
        errors.append(det.uv_px - renderer.true_centre_px(np.array([t]))[0])
    rms = float(np.sqrt(np.mean(np.sum(np.array(errors) ** 2, 1))))
    assert rms < 0.3, f"LED centre RMS {rms:.3f} px"
    dark = renderer.render(int(flight.holds[0][0]), visible=False)
    assert detect_led(dark, 0).detection is None
