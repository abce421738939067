"""Issue 20: the 4K plan's legs reach the image corners the ground 3-30 m fills (tests/contract_writer_4k.py)."""

from __future__ import annotations

import numpy as np

from contract_writer import leg_waypoints
from contract_writer_4k import corner_leg_waypoints
from dronecal_field.core.camera import Camera, CameraPose, Distortion, Intrinsics, look_rotation
from dronecal_field.pipeline.validity import visible_ground


def camera_4k() -> Camera:
    """bench_perturbation's 4K row: 3840x2160, f 2600, 4.5 m pole looking north, tilt 35."""
    t = np.radians(35.0)
    R = look_rotation(np.array([0.0, np.cos(t), -np.sin(t)]))
    return Camera(
        intrinsics=Intrinsics(fx=2600.0, fy=2600.0, cx=1920.0, cy=1080.0, width=3840, height=2160),
        distortion=Distortion(k1=-0.32, k2=0.12, p1=4e-4, p2=-3e-4, k3=-0.02),
        pose=CameraPose.from_position(R, np.array([0.0, 0.0, 4.5])),
    )


def reach(camera: Camera, uv: np.ndarray) -> np.ndarray:
    i = camera.intrinsics
    return np.linalg.norm(uv - np.array([(i.width - 1) / 2, (i.height - 1) / 2]), axis=1) / (0.5 * np.hypot(i.width, i.height))


def test_corner_legs_reach_the_radius_of_the_ground():
    """The rows-only legs reach 78 % of the half-diagonal where the visible ground (1 m grid) reaches 95 %; the
    corner rows 88 %, with every waypoint in the image and at least 1 m above the ground."""
    cam = camera_4k()
    rows = leg_waypoints(cam, (3.0, 5.0, 8.0), (1.0, 2.5, 4.0))
    corners = corner_leg_waypoints(cam)
    _, ground_uv = visible_ground(cam, step_m=1.0)
    assert len(corners) == len(rows) + 4
    assert np.max(reach(cam, cam.project(rows))) < 0.80
    assert np.max(reach(cam, ground_uv)) > 0.94
    uv = cam.project(corners)
    assert np.max(reach(cam, uv)) > 0.87
    assert np.all((uv > 0) & (uv < [3840, 2160]))
    assert np.min(corners[:, 2]) >= 1.0 - 1e-9
    # the bottom row sees the bottom corners: within 300 px of them
    for corner in ([0.0, 2160.0], [3840.0, 2160.0]):
        assert np.min(np.linalg.norm(uv - np.array(corner), axis=1)) < 300.0
