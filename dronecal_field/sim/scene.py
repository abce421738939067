"""Scene geometry shared by the simulated camera, the tests and the calibrator.

Pure numerics, no I/O. One definition of where the marker is: the vehicle
reports the GNSS antenna position and its attitude (MAVLink ATTITUDE: roll,
pitch, yaw of the FRD body relative to NED, radians); the marker centre is the
antenna plus ``R_enu_from_frd @ offset_frd_m``; the marker lies in the body's
right/down plane and faces forward (the nose), which DO_SET_ROI points at the
camera. Frames and conventions: docs/conventions.md; the mount: docs/simulators.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecal_field.core.camera import Camera, CameraPose, Distortion, Intrinsics, look_rotation
from dronecal_field.errors import InputError
from dronecal_field.geodesy import EnuOrigin, site_to_enu_rotation

# NED -> ENU swaps the horizontal axes and flips the vertical one.
R_ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


@dataclass(frozen=True)
class MarkerSpec:
    """The ArUco marker carried by the drone.

    ``size_m`` is the side of the black square (what the detector's corners
    span, and ``marker.size_m`` of the run contract); the printed board adds a
    white quiet zone of ``quiet_zone_bits`` marker cells on every side, which
    detection needs against the dark drone body. ``offset_frd_m`` is the marker
    centre relative to the GNSS antenna phase centre, body frame (forward,
    right, down), metres.
    """

    dictionary: str = "DICT_4X4_50"
    marker_id: int = 0
    size_m: float = 0.4
    offset_frd_m: tuple[float, float, float] = (0.1, 0.0, 0.1)
    quiet_zone_bits: int = 1

    def __post_init__(self) -> None:
        if not self.size_m > 0:
            raise InputError(f"marker size {self.size_m} m must be positive: pass the side of the black square")
        if len(self.offset_frd_m) != 3:
            raise InputError(f"marker offset {self.offset_frd_m} needs three values x,y,z (forward, right, down) in metres")
        if self.quiet_zone_bits < 1:
            raise InputError(f"quiet zone of {self.quiet_zone_bits} cells cannot be detected: use at least 1")


@dataclass(frozen=True, eq=False)
class VehiclePose:
    """Where the vehicle is: antenna position in the world (ENU, metres) and FRD attitude (radians)."""

    antenna_enu_m: np.ndarray  # (3,) metres
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    yaw_rad: float = 0.0  # heading of the nose, clockwise from north

    @property
    def R_enu_from_frd(self) -> np.ndarray:
        """(3, 3) rotation of body vectors (FRD) into ENU."""
        return R_enu_from_frd(self.roll_rad, self.pitch_rad, self.yaw_rad)


def R_enu_from_frd(roll_rad: np.ndarray | float, pitch_rad: np.ndarray | float, yaw_rad: np.ndarray | float) -> np.ndarray:
    """(..., 3, 3) body (FRD) -> ENU rotations from MAVLink Euler angles.

    Parameters
    ----------
    roll_rad, pitch_rad, yaw_rad : float or (N,) arrays, radians
        MAVLink ATTITUDE angles: the body is yawed, then pitched, then rolled
        (intrinsic Z-Y-X) from NED. Yaw 0 = nose north, pi/2 = nose east.

    Returns
    -------
    (3, 3) or (N, 3, 3): ``R_enu_from_ned @ Rz(yaw) @ Ry(pitch) @ Rx(roll)``.
    """
    r, p, y = np.broadcast_arrays(np.asarray(roll_rad, float), np.asarray(pitch_rad, float), np.asarray(yaw_rad, float))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    R_ned = np.stack(
        [
            np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
            np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
            np.stack([-sp, cp * sr, cp * cr], -1),
        ],
        -2,
    )
    return R_ENU_FROM_NED @ R_ned


def marker_centre_world(
    antenna_enu_m: np.ndarray,
    roll_rad: np.ndarray | float,
    pitch_rad: np.ndarray | float,
    yaw_rad: np.ndarray | float,
    offset_frd_m: np.ndarray | tuple[float, float, float],
) -> np.ndarray:
    """Marker centre in ENU: antenna + R_enu_from_frd(attitude) @ offset_frd_m.

    Parameters
    ----------
    antenna_enu_m : (3,) or (N, 3) metres
    roll_rad, pitch_rad, yaw_rad : float or (N,) radians (MAVLink ATTITUDE)
    offset_frd_m : (3,) metres, forward/right/down from the antenna

    Returns
    -------
    (3,) or (N, 3) metres, ENU.
    """
    R = R_enu_from_frd(roll_rad, pitch_rad, yaw_rad)
    offset = np.asarray(offset_frd_m, float).reshape(3)
    return np.asarray(antenna_enu_m, float) + R @ offset


def marker_frame_world(
    antenna_enu_m: np.ndarray,
    roll_rad: np.ndarray | float,
    pitch_rad: np.ndarray | float,
    yaw_rad: np.ndarray | float,
    offset_frd_m: np.ndarray | tuple[float, float, float],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Centre and axes of the marker as a viewer in front of the nose sees it.

    Returns
    -------
    centre : (..., 3) ENU metres
    right : (..., 3) unit vector along the marker image's columns (the body's LEFT,
        because a viewer facing the nose sees the body's left on their right)
    down : (..., 3) unit vector along the marker image's rows (the body's down)
    normal : (..., 3) unit vector out of the printed face (the body's forward)
    """
    R = R_enu_from_frd(roll_rad, pitch_rad, yaw_rad)
    offset = np.asarray(offset_frd_m, float).reshape(3)
    centre = np.asarray(antenna_enu_m, float) + R @ offset
    return centre, -R[..., :, 1], R[..., :, 2], R[..., :, 0]


def marker_corners_world(
    antenna_enu_m: np.ndarray,
    roll_rad: np.ndarray | float,
    pitch_rad: np.ndarray | float,
    yaw_rad: np.ndarray | float,
    offset_frd_m: np.ndarray | tuple[float, float, float],
    size_m: float,
) -> np.ndarray:
    """Corners of the marker's black square in ENU, in ArUco's order.

    The order is the detector's: top-left, top-right, bottom-right,
    bottom-left of the marker image seen from the front, i.e. from a camera
    the nose points at. Top-left is therefore on the body's right and up.

    Returns
    -------
    (4, 3) or (N, 4, 3) metres, ENU.
    """
    centre, right, down, _ = marker_frame_world(antenna_enu_m, roll_rad, pitch_rad, yaw_rad, offset_frd_m)
    h = 0.5 * float(size_m)
    signs = np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])  # (col, row) of TL, TR, BR, BL
    return centre[..., None, :] + h * (signs[:, 0, None] * right[..., None, :] + signs[:, 1, None] * down[..., None, :])


def yaw_towards(from_enu_m: np.ndarray, to_enu_m: np.ndarray) -> float:
    """Heading (radians, clockwise from north) that points the nose from one ENU point at another.

    This is what DO_SET_ROI does to a multicopter's yaw.
    """
    d = np.asarray(to_enu_m, float) - np.asarray(from_enu_m, float)
    if np.hypot(d[0], d[1]) < 1e-9:
        raise InputError("the vehicle is directly above or below the point: the heading towards it is undefined, move it sideways")
    return float(np.arctan2(d[0], d[1]))


def make_truth_camera(
    enu_origin: EnuOrigin | tuple[float, float, float],
    mount_height_m: float,
    azimuth_deg: float,
    tilt_deg: float,
    focal_px: float,
    width: int,
    height: int,
    distortion: Distortion | None = None,
    roll_deg: float = 0.0,
    cx: float | None = None,
    cy: float | None = None,
    aspect: float = 1.0,
) -> Camera:
    """A camera on a pole, as the simulator's ground truth.

    Parameters
    ----------
    enu_origin : WGS84 [lat_deg, lon_deg, h_m] of the pole's foot; the world frame is ENU there.
        Its height must be in the same datum as the vehicle's reported heights (docs/simulators.md).
    mount_height_m : height of the camera centre above the pole's foot, metres.
    azimuth_deg : direction of the optical axis, clockwise from north, degrees.
    tilt_deg : optical axis below the horizontal, degrees (positive looks down).
    focal_px : fx in pixels; fy = aspect * fx.
    width, height : image size, pixels.
    distortion : Brown-Conrady coefficients (default none).
    roll_deg : image rotation about the optical axis, clockwise, degrees.
    cx, cy : principal point, pixels (default the image centre, (W-1)/2, (H-1)/2).

    Returns
    -------
    Camera with ``enu_origin`` set, world frame ENU.
    """
    if not focal_px > 0 or width <= 0 or height <= 0:
        raise InputError(f"truth camera needs a positive focal length and image size, got f={focal_px} px, {width}x{height}")
    if not -89.0 < tilt_deg < 89.0:
        raise InputError(f"tilt {tilt_deg} deg is too close to vertical for a pole camera: use -89..89")
    origin = enu_origin.as_list() if isinstance(enu_origin, EnuOrigin) else [float(v) for v in enu_origin]
    t = np.radians(tilt_deg)
    forward_site = np.array([np.cos(t), 0.0, -np.sin(t)])
    forward_enu = site_to_enu_rotation(azimuth_deg) @ forward_site
    R = look_rotation(forward_enu, roll_deg=roll_deg)
    intr = Intrinsics(
        fx=float(focal_px),
        fy=float(focal_px) * float(aspect),
        cx=(width - 1) / 2.0 if cx is None else float(cx),
        cy=(height - 1) / 2.0 if cy is None else float(cy),
        width=int(width),
        height=int(height),
    )
    return Camera(
        intrinsics=intr,
        distortion=distortion or Distortion(),
        pose=CameraPose.from_position(R, np.array([0.0, 0.0, float(mount_height_m)])),
        enu_origin=(origin[0], origin[1], origin[2]),
    )
