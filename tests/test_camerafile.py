"""camera.yaml round trips, with and without the region of validity."""

from __future__ import annotations

import numpy as np
import pytest

from dronecal_field.camerafile import read_camera, read_validity_polygon, write_camera
from dronecal_field.core.camera import Distortion
from dronecal_field.core.synthetic import pole_camera
from dronecal_field.errors import InputError


def test_camera_and_validity_polygon_round_trip(tmp_path):
    cam = pole_camera(900.0, 1920, 1080, (1.0, -2.0, 4.0), 20.0, distortion=Distortion(k1=-0.28, k2=0.07))
    cam = cam.with_(enu_origin=(46.5, 6.5, 420.0), covariance=np.diag(np.arange(1.0, 16.0)))
    poly = np.array([[100.5, 200.25], [1800.0, 210.0], [1700.0, 1000.0], [120.0, 990.0]])
    path = tmp_path / "camera.yaml"
    write_camera(path, cam, comment="test", validity_polygon_px=poly)
    back = read_camera(path)
    assert np.allclose(back.intrinsics.as_array(), cam.intrinsics.as_array())
    assert np.allclose(back.distortion.as_array(), cam.distortion.as_array())
    assert np.allclose(back.pose.position_world, cam.pose.position_world)
    assert np.allclose(back.covariance, cam.covariance)
    assert np.array_equal(read_validity_polygon(path), poly)
    # OpenCV reads the same polygon, ready for cv2.pointPolygonTest.
    import cv2

    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    m = fs.getNode("validity_polygon_px").mat()
    fs.release()
    assert cv2.pointPolygonTest(m.astype(np.float32), (960.0, 600.0), False) > 0
    assert cv2.pointPolygonTest(m.astype(np.float32), (10.0, 10.0), False) < 0


def test_camera_without_polygon_reads_none_and_a_bad_polygon_is_refused(tmp_path):
    cam = pole_camera(900.0, 1920, 1080, (0.0, 0.0, 4.0), 20.0)
    path = tmp_path / "camera.yaml"
    write_camera(path, cam)
    assert read_validity_polygon(path) is None
    write_camera(path, cam, validity_polygon_px=np.array([[0.0, 0.0], [1.0, 1.0]]))
    with pytest.raises(InputError, match="validity_polygon_px"):
        read_validity_polygon(path)


@pytest.mark.parametrize("case", ["binary", "broken_yaml", "zero_focal", "negative_focal"])
def test_a_bad_camera_file_is_one_input_error(tmp_path, case):
    import os

    from dronecal_field.camerafile import read_camera, write_camera
    from dronecal_field.core.synthetic import paper_camera
    from dronecal_field.errors import InputError

    path = tmp_path / "camera.yaml"
    if case == "binary":
        path.write_bytes(os.urandom(300))
    elif case == "broken_yaml":
        path.write_text("%YAML:1.0\n---\nimage_width: [1, 2\ncamera_matrix: {\n")
    else:
        write_camera(path, paper_camera(distorted=False))
        fx = "0." if case == "zero_focal" else "-1110."
        text = path.read_text()
        start = text.index("data: [", text.index("camera_matrix")) + len("data: [")
        path.write_text(text[:start] + fx + text[text.index(",", start):])
    with pytest.raises(InputError) as err:
        read_camera(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_writing_a_camera_into_a_missing_folder_is_one_input_error(tmp_path):
    from dronecal_field.camerafile import write_camera
    from dronecal_field.core.synthetic import paper_camera
    from dronecal_field.errors import InputError

    with pytest.raises(InputError, match="does not exist"):
        write_camera(tmp_path / "missing" / "camera.yaml", paper_camera(distorted=False))
    assert not (tmp_path / "missing").exists()


def _edited(tmp_path, name: str, count: int | None = None, values: str | None = None, **replace: str):
    """The written camera.yaml with its distortion vector and other text replaced."""
    cam = pole_camera(900.0, 1920, 1080, (0.0, 0.0, 4.0), 20.0, distortion=Distortion(k1=-0.2, k2=0.05))
    path = tmp_path / f"{name}.yaml"
    write_camera(path, cam)
    text = path.read_text()
    if count is not None:
        head, rest = text.split("distortion_coefficients:", 1)
        block, tail = rest.split("data:", 1)
        tail = tail.split("]", 1)[1]
        text = head + f"distortion_coefficients: !!opencv-matrix\n   rows: 1\n   cols: {count}\n   dt: d\n   data: [ {values} ]" + tail
    for old, new in replace.items():
        assert old in text, old
        text = text.replace(old, new)
    path.write_text(text)
    return path


@pytest.mark.parametrize("count, values, ok", [
    (4, "-0.2, 0.05, 0., 0.", True),
    (5, "-0.2, 0.05, 0., 0., 0.01", True),
    (8, "-0.2, 0.05, 0., 0., 0.01, 0., 0., 0.", True),   # rational model with k4..k6 = 0: the same camera
    (8, "-0.2, 0.05, 0., 0., 0.01, 0.3, 0., 0.", False),  # k4 != 0: not silently cut to 5
    (12, "-0.2, 0.05, 0., 0., 0.01, 0., 0., 0., 0.001, 0., 0., 0.", False),
    (14, "-0.2, 0.05, 0., 0., 0.01, 0., 0., 0., 0., 0., 0., 0., 0.01, 0.", False),
    (6, "-0.2, 0.05, 0., 0., 0.01, 0.", False),
])
def test_distortion_counts_are_read_or_refused_never_cut(tmp_path, count, values, ok):
    path = _edited(tmp_path, f"d{count}", count, values)
    if ok:
        assert read_camera(path).distortion.k1 == pytest.approx(-0.2)
    else:
        with pytest.raises(InputError, match="distortion_coefficients has"):
            read_camera(path)


def test_skew_a_scaled_matrix_and_absurd_sizes_are_refused(tmp_path):
    cam_path = _edited(tmp_path, "ok")
    K_line = next(line for line in cam_path.read_text().splitlines() if line.strip().startswith("data: [ 900."))
    skew = _edited(tmp_path, "skew", **{K_line: K_line.replace("900., 0.,", "900., 3.,", 1)})
    with pytest.raises(InputError, match="skew"):
        read_camera(skew)
    scaled = _edited(tmp_path, "k22", **{K_line: K_line.rstrip(" ]").rsplit(",", 1)[0] + ", 2. ]"})
    with pytest.raises(InputError, match=r"K\[2,2\] = 2"):
        read_camera(scaled)
    huge = _edited(tmp_path, "huge", **{"image_width: 1920": "image_width: 2000000000"})
    with pytest.raises(InputError, match="image_width"):
        read_camera(huge)


def test_the_tools_other_yaml_files_are_named_not_read(tmp_path):
    info = tmp_path / "camera_info.yaml"
    info.write_text("image_width: 1280\nimage_height: 720\ncamera_name: dronecal\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
                    "  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\ndistortion_model: plumb_bob\nprojection_matrix:\n  rows: 3\n  cols: 4\n  data: []\n")
    homography = tmp_path / "ground_homography.yaml"
    homography.write_text("# Image <-> ground plane\nenu_origin: [1, 2, 3]\nH_image_from_ground:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n")
    with pytest.raises(InputError, match="camera_info.yaml .*give the camera.yaml beside it"):
        read_camera(info)
    with pytest.raises(InputError, match="ground homography"):
        read_camera(homography)
    fifo = tmp_path / "fifo.yaml"
    import os

    os.mkfifo(fifo)
    with pytest.raises(InputError, match="not a regular file"):
        read_camera(fifo)
