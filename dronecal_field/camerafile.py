"""camera.yaml: the camera file, an OpenCV FileStorage YAML.

Written by ``calibrate`` and by the simulator (as ground truth), read by every
command that takes ``--camera``. Keys: image_width, image_height,
camera_matrix (3x3), distortion_coefficients (1x5, OpenCV order),
enu_origin ([lat, lon, h], optional), rotation_world_to_camera (3x3),
camera_position_enu (3x1, m), and where known parameter_covariance (15x15,
order of core.camera.PARAM_NAMES), parameter_std (1x15) and parameter_names,
and validity_polygon_px (Kx2, pixels, OpenCV convention): the region of the
image the calibration is supported by (pipeline/validity.py); a consumer
should not measure outside it (``cv2.pointPolygonTest``).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from dronecal_field.core.camera import PARAM_NAMES, Camera, CameraPose, Distortion, Intrinsics
from dronecal_field.errors import InputError


def write_camera(
    path: str | os.PathLike,
    camera: Camera,
    comment: str | None = None,
    validity_polygon_px: np.ndarray | None = None,
) -> None:
    """Write ``camera`` atomically (a temporary file renamed into place).

    ``validity_polygon_px`` (K, 2) pixels, when given, is written as the
    region of validity (read it back with :func:`read_validity_polygon`).
    """
    import cv2

    path = Path(path)
    if not path.parent.is_dir():
        raise InputError(f"cannot write camera file {path}: folder {path.parent} does not exist; create it or choose another path")
    tmp = path.with_name(path.name + ".tmp.yaml")
    try:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE | cv2.FILE_STORAGE_FORMAT_YAML)
    except (cv2.error, SystemError) as exc:
        raise InputError(f"cannot write camera file {path} ({exc}): check the folder is writable") from None
    if not fs.isOpened():
        raise InputError(f"cannot write camera file {path}: check the folder is writable")
    try:
        if comment:
            for line in comment.splitlines():
                fs.writeComment(line)
        fs.write("image_width", int(camera.width))
        fs.write("image_height", int(camera.height))
        fs.write("camera_matrix", camera.intrinsics.matrix)
        fs.write("distortion_coefficients", camera.distortion.as_array().reshape(1, 5))
        if camera.enu_origin is not None:
            fs.write("enu_origin", np.asarray(camera.enu_origin, float).reshape(1, 3))
        fs.write("rotation_world_to_camera", np.asarray(camera.pose.R_cam_from_world, float))
        fs.write("camera_position_enu", camera.pose.position_world.reshape(3, 1))
        if camera.covariance is not None:
            cov = np.asarray(camera.covariance, float)
            fs.write("parameter_covariance", cov)
            fs.write("parameter_std", np.sqrt(np.clip(np.diag(cov), 0, None)).reshape(1, -1))
            fs.startWriteStruct("parameter_names", cv2.FILE_NODE_SEQ)
            for name in PARAM_NAMES:
                fs.write("", name)
            fs.endWriteStruct()
        if validity_polygon_px is not None:
            fs.write("validity_polygon_px", np.asarray(validity_polygon_px, float).reshape(-1, 2))
    finally:
        fs.release()
    os.replace(tmp, path)


MAX_CAMERA_FILE_BYTES = 10_000_000  # a camera.yaml is a few kB
MAX_IMAGE_SIDE_PX = 65536
# OpenCV's distortion vectors: 4 or 5 (Brown-Conrady, this tool's model), 8 (rational), 12 (thin prism), 14 (tilted).
OPENCV_DISTORTION_COUNTS = (4, 5, 8, 12, 14)


def _sniff_foreign(path: Path) -> None:
    """One line for the other YAML files ``calibrate`` writes beside camera.yaml, which are not camera files."""
    with path.open("rb") as f:
        head = f.read(65536).decode("utf-8", errors="replace")
    if "distortion_model:" in head and "projection_matrix:" in head:
        raise InputError(f"{path} is the ROS camera_info.yaml (for ROS drivers), not a camera file: give the camera.yaml beside it")
    if "H_image_from_ground" in head:
        raise InputError(f"{path} is the ground homography (image <-> ground plane), not a camera file: give the camera.yaml beside it")


def read_camera(path: str | os.PathLike) -> Camera:
    """Read a camera file; a missing file or key is an InputError naming it.

    Strict: an OpenCV distortion vector of 4/5 coefficients is read; 8, 12 or 14 only when the
    coefficients beyond the fifth are zero (this tool's model has five); a camera_matrix with
    skew or a last row other than (0, 0, 1), and image sizes outside 1..65536 px, are refused.
    """
    import cv2

    path = Path(path)
    if not path.exists():
        raise InputError(f"camera file {path} does not exist: pass the camera.yaml written by calibrate or the simulator")
    if not path.is_file():
        raise InputError(f"camera file {path} is not a regular file (a folder, pipe or device): pass the camera.yaml written by calibrate")
    if path.stat().st_size > MAX_CAMERA_FILE_BYTES:
        raise InputError(f"camera file {path} is {path.stat().st_size / 1e6:.0f} MB, far more than a camera.yaml: pass the camera.yaml written by calibrate")
    _sniff_foreign(path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # a binary or broken file surfaces as SystemError from the binding
        raise InputError(f"camera file {path} is not OpenCV FileStorage YAML ({exc.msg.strip() if hasattr(exc, 'msg') else exc}): regenerate it") from None
    try:
        def mat(key: str, shape: tuple[int, ...] | None, required: bool = True) -> np.ndarray | None:
            node = fs.getNode(key)
            if node.empty():
                if required:
                    raise InputError(f"camera file {path} has no '{key}': add it (see docs/conventions.md)")
                return None
            m = node.mat()
            if m is None:
                m = np.array([node.at(i).real() for i in range(node.size())]) if node.isSeq() else np.array(node.real())
            m = np.asarray(m, float)
            if shape is not None and m.size != int(np.prod(shape)):
                raise InputError(f"camera file {path}: '{key}' has {m.size} values, expected {int(np.prod(shape))}")
            return m.reshape(shape) if shape is not None else m

        w_real, h_real = fs.getNode("image_width").real(), fs.getNode("image_height").real()
        if not all(np.isfinite(v) and v == int(v) and 1 <= v <= MAX_IMAGE_SIDE_PX for v in (w_real, h_real)):
            raise InputError(f"camera file {path}: image_width {w_real:g}, image_height {h_real:g} must be whole pixels in 1..{MAX_IMAGE_SIDE_PX}: fix them")
        width, height = int(w_real), int(h_real)
        K = mat("camera_matrix", (3, 3))
        dist_node = fs.getNode("distortion_coefficients")
        dist = np.zeros(5) if dist_node.empty() else np.asarray(dist_node.mat(), float).ravel()
        R = mat("rotation_world_to_camera", (3, 3))
        position = mat("camera_position_enu", (3,))
        origin = mat("enu_origin", (3,), required=False)
        cov = mat("parameter_covariance", None, required=False)
    finally:
        fs.release()
    if not np.all(np.isfinite(K)) or not np.all(np.isfinite(R)) or not np.all(np.isfinite(position)):
        raise InputError(f"camera file {path} holds NaN or inf: regenerate it")
    if not (np.allclose(R @ R.T, np.eye(3), atol=1e-4) and np.linalg.det(R) > 0):
        raise InputError(f"camera file {path}: rotation_world_to_camera is not a rotation (R R^T != I or det < 0): regenerate it or fix the matrix")
    if not (K[0, 0] > 0 and K[1, 1] > 0):
        raise InputError(f"camera file {path}: focal length fx {K[0, 0]:g}, fy {K[1, 1]:g} px must be positive: fix camera_matrix")
    if abs(K[0, 1]) > 1e-9 * K[0, 0]:
        raise InputError(f"camera file {path}: camera_matrix has skew {K[0, 1]:g} (K[0,1]); this tool's model has none: recalibrate, or set it to 0 if it is negligible")
    if not (K[1, 0] == 0 and K[2, 0] == 0 and K[2, 1] == 0 and K[2, 2] == 1):
        raise InputError(f"camera file {path}: camera_matrix rows 2-3 must be [0, fy, cy] and [0, 0, 1] (found K[2,2] = {K[2, 2]:g}): "
                         "divide the matrix by K[2,2] or regenerate it")
    if not (max(K[0, 0], K[1, 1]) < 100 * MAX_IMAGE_SIDE_PX and abs(K[0, 2]) < 10 * width and abs(K[1, 2]) < 10 * height):
        raise InputError(f"camera file {path}: camera_matrix fx {K[0, 0]:g}, cx {K[0, 2]:g}, cy {K[1, 2]:g} px do not fit a {width}x{height} image: fix camera_matrix")
    dist = np.asarray(dist, float).ravel()
    if dist.size not in OPENCV_DISTORTION_COUNTS:
        raise InputError(f"camera file {path}: distortion_coefficients has {dist.size} values; OpenCV's are 4, 5, 8, 12 or 14 (k1 k2 p1 p2 [k3 ...]): fix it")
    if not np.all(np.isfinite(dist)):
        raise InputError(f"camera file {path}: distortion_coefficients hold NaN or inf: regenerate it")
    if dist.size > 5 and np.any(dist[5:] != 0):
        raise InputError(f"camera file {path}: distortion_coefficients has {dist.size} values with k4.. non-zero (OpenCV's rational/thin-prism/tilted model); "
                         "this tool's model has five (k1 k2 p1 p2 k3): recalibrate with it (calibrate) instead of dropping them")
    return Camera(
        intrinsics=Intrinsics(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], width=width, height=height),
        distortion=Distortion.from_array(dist),
        pose=CameraPose.from_position(R, position),
        enu_origin=None if origin is None else tuple(float(v) for v in origin),
        covariance=None if cov is None or cov.size != 225 else cov.reshape(15, 15),
    )


def read_validity_polygon(path: str | os.PathLike) -> np.ndarray | None:
    """(K, 2) region of validity in pixels from a camera file, None when the file has none."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(f"camera file {path} does not exist: pass the camera.yaml written by calibrate")
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    try:
        node = fs.getNode("validity_polygon_px")
        m = None if node.empty() else node.mat()
    finally:
        fs.release()
    if m is None:
        return None
    m = np.asarray(m, float)
    if m.ndim != 2 or m.shape[1] != 2 or len(m) < 3 or not np.all(np.isfinite(m)):
        raise InputError(f"camera file {path}: validity_polygon_px must be a K x 2 matrix of finite pixels (K >= 3): regenerate it")
    return m
