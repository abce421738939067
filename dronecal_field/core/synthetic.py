"""Seeded synthetic scenes: the paper's Table 1 cameras and its sampling grids.

The paper's world frame (Gazebo): X forward from the camera along the ground,
Y left, Z up, ground at Z = 0. Table 1: f = 1110 px, principal point
(640, 480), image 1280 x 960, rotated 30 deg about y (pitched down), camera
at (0.5, 0, 2) m; the distorted camera adds k1 = -0.25, p1 = -28e-5,
p2 = -5e-5.
"""

from __future__ import annotations

import numpy as np

from dronecal_field.core.camera import Camera, CameraPose, Distortion, Intrinsics, look_rotation


def pole_camera(
    focal_px: float,
    width: int,
    height: int,
    position: tuple[float, float, float],
    tilt_deg: float,
    azimuth_deg_from_x: float = 0.0,
    distortion: Distortion = Distortion(),
    cx: float | None = None,
    cy: float | None = None,
    fy: float | None = None,
) -> Camera:
    """A camera looking horizontally along +X (turned by ``azimuth_deg_from_x`` about Z, counter-clockwise) and tilted down."""
    a, t = np.radians(azimuth_deg_from_x), np.radians(tilt_deg)
    forward = np.array([np.cos(a) * np.cos(t), np.sin(a) * np.cos(t), -np.sin(t)])
    R = look_rotation(forward)
    return Camera(
        intrinsics=Intrinsics(
            fx=focal_px,
            fy=focal_px if fy is None else fy,
            cx=(width / 2.0) if cx is None else cx,
            cy=(height / 2.0) if cy is None else cy,
            width=width,
            height=height,
        ),
        distortion=distortion,
        pose=CameraPose.from_position(R, np.asarray(position, float)),
    )


def paper_camera(distorted: bool = False) -> Camera:
    """One of the paper's two Table 1 cameras."""
    dist = Distortion(k1=-0.25, p1=-28e-5, p2=-5e-5) if distorted else Distortion()
    return pole_camera(1110.0, 1280, 960, (0.5, 0.0, 2.0), 30.0, distortion=dist, cx=640.0, cy=480.0)


def sampling_grid(
    x_values: np.ndarray | list[float],
    y_values: np.ndarray | list[float],
    z_values: np.ndarray | list[float],
) -> np.ndarray:
    """(N, 3) points of the full X x Y x Z lattice, metres."""
    X, Y, Z = np.meshgrid(np.asarray(x_values, float), np.asarray(y_values, float), np.asarray(z_values, float), indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], axis=1)


def visible(camera: Camera, points: np.ndarray, margin_px: float = 10.0) -> np.ndarray:
    """(N,) mask of points in front of the camera and inside the image with a margin."""
    points = np.asarray(points, float)
    depth = camera.depth(points)
    uv = camera.project(points)
    w, h = camera.width, camera.height
    return (
        (depth > 0.1)
        & (uv[:, 0] >= margin_px)
        & (uv[:, 0] <= w - 1 - margin_px)
        & (uv[:, 1] >= margin_px)
        & (uv[:, 1] <= h - 1 - margin_px)
    )


def paper_grid(camera: Camera, heights: tuple[float, ...] = (0.5, 1.0), x_range: tuple[float, float] = (4.0, 8.0), y_step: float = 1.0, margin_px: float = 10.0) -> np.ndarray:
    """The paper's recommended sampling (1 m along X, ``y_step`` along Y, 3 m each side, two heights), visible points only."""
    xs = np.arange(x_range[0], x_range[1] + 1e-9, 1.0)
    ys = np.arange(-3.0, 3.0 + 1e-9, y_step)
    grid = sampling_grid(xs, ys, heights)
    return grid[visible(camera, grid, margin_px)]
