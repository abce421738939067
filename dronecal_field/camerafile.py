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


def read_camera(path: str | os.PathLike) -> Camera:
    """Read a camera file; a missing file or key is an InputError naming it."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError(f"camera file {path} does not exist: pass the camera.yaml written by calibrate or the simulator")
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

        width = int(fs.getNode("image_width").real())
        height = int(fs.getNode("image_height").real())
        if width <= 0 or height <= 0:
            raise InputError(f"camera file {path} needs positive image_width and image_height")
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
