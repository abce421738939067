"""Leg layouts for the independent contract writer that reach the image corners (issue 20, the 4K plan).

``contract_writer.leg_waypoints`` flies rows at fixed depths and heights; on
the 4K pole camera (f 2600, 4.5 m up, tilt 35) its nearest row (3 m out, 1 m
up) stays 970 px above the bottom corners and its points reach 78 % of the
half-diagonal, while the ground 3-30 m fills the frame to 97 %. Beyond the
points the fitted distortion is an extrapolation: k3 (r^6) is not
determined there and the ground error grew from 0.8 px (radius 0.7-0.8) to
12.9 px (0.9-1.0) at full resolution. :func:`corner_leg_waypoints` adds two
rows placed through the image itself: one along the bottom edge at the lowest
height flown, one along the top edge, each from the left edge to the right
one, so the legs sample the corners the ground reaches.
"""

from __future__ import annotations

import numpy as np

from contract_writer import leg_waypoints
from dronecal_field.core.camera import Camera, intersect_plane_z


def edge_row(camera: Camera, v_px: float, height_m: float, margin_px: float) -> np.ndarray | None:
    """(2, 3) ENU ends of a leg at ``height_m`` whose ends the camera sees at row ``v_px``, ``margin_px`` in from the
    left and right edges; None when a ray of that row does not reach that height in front of the camera."""
    w = camera.intrinsics.width
    uv = np.array([[margin_px, v_px], [w - margin_px, v_px]], float)
    ends = intersect_plane_z(*camera.batch_arrays(), uv[None], height_m)[0]
    if not np.all(np.isfinite(ends)) or np.any(camera.depth(ends) <= 0.5):
        return None
    return ends


def corner_leg_waypoints(
    camera: Camera,
    depths_m: tuple[float, ...] = (3.0, 5.0, 8.0),
    heights_m: tuple[float, ...] = (1.0, 2.5, 4.0),
    edge_margin: float = 0.06,
    top_height_m: float = 2.5,
) -> np.ndarray:
    """(M, 3) waypoints: ``leg_waypoints``' rows, then a row along the top edge at ``top_height_m`` and one along the
    bottom edge at the lowest of ``heights_m``, ``edge_margin`` of the image size in from the edges (a 0.3 m marker
    4 m away spans 200 px of a 3840 px frame: it must stay whole in the image at the leg ends)."""
    rows = [np.asarray(leg_waypoints(camera, depths_m, heights_m), float)]
    w, h = camera.intrinsics.width, camera.intrinsics.height
    mu, mv = edge_margin * w, edge_margin * h
    reverse = len(rows[0]) // 2 % 2 == 1  # keep alternating the direction across the image
    for v, height in ((mv, top_height_m), (h - mv, min(heights_m))):
        ends = edge_row(camera, v, height, mu)
        if ends is None:
            continue
        rows.append(ends[::-1] if reverse else ends)
        reverse = not reverse
    return np.concatenate(rows)
