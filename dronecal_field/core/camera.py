"""Pinhole + Brown-Conrady camera model with analytic Jacobians.

Pure numerical core: no I/O. Conventions (frames, parameter order, rotation
perturbation) are in docs/conventions.md. Everything is batched over a leading
axis of K cameras so the Monte-Carlo can run all its trials at once; a single
camera is K = 1.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

PARAM_NAMES: tuple[str, ...] = (
    "fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3",
    "wx", "wy", "wz", "tx", "ty", "tz",
)
N_PARAMS = len(PARAM_NAMES)
INTRINSIC_SLICE = slice(0, 4)
DISTORTION_SLICE = slice(4, 9)
ROTATION_SLICE = slice(9, 12)
TRANSLATION_SLICE = slice(12, 15)


@dataclass(frozen=True, eq=False)
class Intrinsics:
    """Pinhole intrinsics in pixels (no skew), and the image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    @property
    def matrix(self) -> np.ndarray:
        """(3, 3) camera matrix K."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def as_array(self) -> np.ndarray:
        return np.array([self.fx, self.fy, self.cx, self.cy], dtype=float)


@dataclass(frozen=True, eq=False)
class Distortion:
    """Brown-Conrady coefficients in OpenCV's order, on normalised coordinates."""

    k1: float = 0.0
    k2: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    k3: float = 0.0

    def as_array(self) -> np.ndarray:
        """(5,) array k1, k2, p1, p2, k3: OpenCV's ``distCoeffs``."""
        return np.array([self.k1, self.k2, self.p1, self.p2, self.k3], dtype=float)

    @classmethod
    def from_array(cls, d: np.ndarray) -> "Distortion":
        d = np.asarray(d, dtype=float).ravel()
        d = np.concatenate([d, np.zeros(max(0, 5 - d.size))])[:5]
        return cls(k1=float(d[0]), k2=float(d[1]), p1=float(d[2]), p2=float(d[3]), k3=float(d[4]))


@dataclass(frozen=True, eq=False)
class CameraPose:
    """World-to-camera rigid transform: X_cam = R_cam_from_world @ X_world + t_cam_from_world."""

    R_cam_from_world: np.ndarray  # (3, 3)
    t_cam_from_world: np.ndarray  # (3,) metres

    @property
    def position_world(self) -> np.ndarray:
        """(3,) camera centre in the world frame, metres."""
        return -self.R_cam_from_world.T @ self.t_cam_from_world

    @classmethod
    def from_position(cls, R_cam_from_world: np.ndarray, position_world: np.ndarray) -> "CameraPose":
        R = np.asarray(R_cam_from_world, dtype=float).reshape(3, 3)
        c = np.asarray(position_world, dtype=float).reshape(3)
        return cls(R_cam_from_world=R, t_cam_from_world=-R @ c)


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated (or guessed) camera: intrinsics, distortion, pose.

    ``enu_origin`` is [lat_deg, lon_deg, h_m] (WGS84 ellipsoidal) of the world
    frame's origin when the world frame is ENU, else None.
    ``covariance`` is the (15, 15) covariance over PARAM_NAMES when known.
    """

    intrinsics: Intrinsics
    distortion: Distortion
    pose: CameraPose
    enu_origin: tuple[float, float, float] | None = None
    covariance: np.ndarray | None = field(default=None, repr=False)

    @property
    def width(self) -> int:
        return self.intrinsics.width

    @property
    def height(self) -> int:
        return self.intrinsics.height

    def with_(self, **changes: object) -> "Camera":
        return replace(self, **changes)

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) of world points (N, 3)."""
        uv = project_batch(*self.batch_arrays(), np.asarray(points_world, float)[None])
        return uv[0]

    def depth(self, points_world: np.ndarray) -> np.ndarray:
        """(N,) z of the points in the camera frame (positive in front), metres."""
        X = np.asarray(points_world, float)
        return (X @ self.pose.R_cam_from_world.T + self.pose.t_cam_from_world)[:, 2]

    def batch_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(intrinsics (1,4), distortion (1,5), R (1,3,3), t (1,3)) for the batched functions."""
        return (
            self.intrinsics.as_array()[None],
            self.distortion.as_array()[None],
            np.asarray(self.pose.R_cam_from_world, float)[None],
            np.asarray(self.pose.t_cam_from_world, float)[None],
        )

    @classmethod
    def from_arrays(
        cls,
        intrinsics: np.ndarray,
        distortion: np.ndarray,
        R: np.ndarray,
        t: np.ndarray,
        width: int,
        height: int,
        enu_origin: tuple[float, float, float] | None = None,
        covariance: np.ndarray | None = None,
    ) -> "Camera":
        fx, fy, cx, cy = (float(v) for v in np.asarray(intrinsics).ravel()[:4])
        return cls(
            intrinsics=Intrinsics(fx=fx, fy=fy, cx=cx, cy=cy, width=int(width), height=int(height)),
            distortion=Distortion.from_array(distortion),
            pose=CameraPose(R_cam_from_world=np.asarray(R, float).reshape(3, 3), t_cam_from_world=np.asarray(t, float).reshape(3)),
            enu_origin=enu_origin,
            covariance=covariance,
        )


# --------------------------------------------------------------------------
# Rotations


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3, 3) cross-product matrices of (..., 3) vectors."""
    v = np.asarray(v, float)
    z = np.zeros(v.shape[:-1])
    return np.stack(
        [
            np.stack([z, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], z, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], z], -1),
        ],
        -2,
    )


def rotation_from_vector(w: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotation matrices exp([w]x) of (..., 3) rotation vectors (radians), Rodrigues."""
    w = np.asarray(w, float)
    theta = np.linalg.norm(w, axis=-1)[..., None, None]
    K = skew(w)
    small = theta < 1e-8
    theta_safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(theta_safe) / theta_safe)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(theta_safe)) / theta_safe**2)
    eye = np.broadcast_to(np.eye(3), K.shape)
    return eye + a * K + b * (K @ K)


def vector_from_rotation(R: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors of (..., 3, 3) rotation matrices (inverse of rotation_from_vector)."""
    from scipy.spatial.transform import Rotation

    R = np.asarray(R, float)
    flat = R.reshape(-1, 3, 3)
    return Rotation.from_matrix(flat).as_rotvec().reshape(R.shape[:-2] + (3,))


def look_rotation(forward_world: np.ndarray, up_world: np.ndarray = np.array([0.0, 0.0, 1.0]), roll_deg: float = 0.0) -> np.ndarray:
    """R_cam_from_world for a camera looking along ``forward_world`` with image-up near ``up_world``.

    Camera z = forward, x = right, y = down (OpenCV). ``roll_deg`` turns the
    image clockwise about the optical axis.
    """
    z = np.asarray(forward_world, float)
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up_world, float))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError("forward direction is parallel to up: roll is undefined")
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    if roll_deg:
        R = rotation_from_vector(np.array([0.0, 0.0, np.radians(roll_deg)])) @ R
    return R


# --------------------------------------------------------------------------
# Projection (batched over K cameras)


def _distort(xn: np.ndarray, yn: np.ndarray, dist: np.ndarray):
    """Distorted normalised coordinates and the radial factor pieces; dist (K,5), xn (K,N)."""
    k1, k2, p1, p2, k3 = (dist[:, i : i + 1] for i in range(5))
    r2 = xn * xn + yn * yn
    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xy = xn * yn
    xd = xn * radial + 2.0 * p1 * xy + p2 * (r2 + 2.0 * xn * xn)
    yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xy
    return xd, yd, r2, radial


def project_batch(
    intrinsics: np.ndarray,  # (K, 4) fx, fy, cx, cy
    distortion: np.ndarray,  # (K, 5)
    R: np.ndarray,  # (K, 3, 3)
    t: np.ndarray,  # (K, 3)
    points: np.ndarray,  # (K, N, 3) or (1, N, 3) world metres
) -> np.ndarray:
    """Pixels (K, N, 2) of world points through K cameras."""
    Xc = np.matmul(points, R.transpose(0, 2, 1)) + t[:, None, :]
    z = Xc[..., 2]
    xn = Xc[..., 0] / z
    yn = Xc[..., 1] / z
    xd, yd, _, _ = _distort(xn, yn, distortion)
    u = intrinsics[:, 0:1] * xd + intrinsics[:, 2:3]
    v = intrinsics[:, 1:2] * yd + intrinsics[:, 3:4]
    return np.stack([u, v], -1)


def project_batch_jacobians(
    intrinsics: np.ndarray,  # (K, 4)
    distortion: np.ndarray,  # (K, 5)
    R: np.ndarray,  # (K, 3, 3)
    t: np.ndarray,  # (K, 3)
    points: np.ndarray,  # (K, N, 3) or (1, N, 3)
    with_points: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Pixels and their analytic Jacobians.

    Returns
    -------
    uv : (K, N, 2) pixels
    J_params : (K, N, 2, 15) d(uv)/d(fx, fy, cx, cy, k1, k2, p1, p2, k3, wx, wy, wz, tx, ty, tz),
        w being the left rotation perturbation R' = exp([w]x) R (docs/conventions.md).
    J_points : (K, N, 2, 3) d(uv)/d(world point), or None when ``with_points`` is false
    """
    RX = np.einsum("kij,knj->kni", R, points)  # (K,N,3)
    Xc = RX + t[:, None, :]
    inv_z = 1.0 / Xc[..., 2]
    xn = Xc[..., 0] * inv_z
    yn = Xc[..., 1] * inv_z
    xd, yd, r2, radial = _distort(xn, yn, distortion)
    fx, fy = intrinsics[:, 0:1], intrinsics[:, 1:2]
    k1, k2, p1, p2, k3 = (distortion[:, i : i + 1] for i in range(5))
    u = fx * xd + intrinsics[:, 2:3]
    v = fy * yd + intrinsics[:, 3:4]
    r4 = r2 * r2
    xy2 = 2.0 * xn * yn
    zero = np.zeros_like(xn)
    one = np.ones_like(xn)

    # d(distorted)/d(normalised)
    drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
    dxd_dx = radial + 2.0 * xn * xn * drad + 2.0 * p1 * yn + 6.0 * p2 * xn
    dxd_dy = xy2 * drad + 2.0 * p1 * xn + 2.0 * p2 * yn
    dyd_dy = radial + 2.0 * yn * yn * drad + 6.0 * p1 * yn + 2.0 * p2 * xn
    # d(uv)/d(Xc) = diag(f) Jd Jn, with Jn = [[1/z,0,-x/z],[0,1/z,-y/z]]
    a00 = fx * dxd_dx * inv_z
    a01 = fx * dxd_dy * inv_z
    a10 = fy * dxd_dy * inv_z
    a11 = fy * dyd_dy * inv_z
    gu = (a00, a01, -(a00 * xn + a01 * yn))  # d u / d Xc
    gv = (a10, a11, -(a10 * xn + a11 * yn))  # d v / d Xc
    ax, ay, az = RX[..., 0], RX[..., 1], RX[..., 2]

    def rot(g):  # d/dw of g . Xc with dXc/dw = -[RX]x, i.e. (RX x g)
        return (ay * g[2] - az * g[1], az * g[0] - ax * g[2], ax * g[1] - ay * g[0])

    ju = (xd, zero, one, zero, fx * xn * r2, fx * xn * r4, fx * xy2, fx * (r2 + 2.0 * xn * xn), fx * xn * r4 * r2, *rot(gu), *gu)
    jv = (zero, yd, zero, one, fy * yn * r2, fy * yn * r4, fy * (r2 + 2.0 * yn * yn), fy * xy2, fy * yn * r4 * r2, *rot(gv), *gv)
    J = np.stack([np.stack(ju, -1), np.stack(jv, -1)], -2)
    uv = np.stack([u, v], -1)
    if not with_points:
        return uv, J, None
    J_xc = np.stack([np.stack(gu, -1), np.stack(gv, -1)], -2)
    return uv, J, J_xc @ R[:, None, :, :]


def undistort_normalised(
    xd: np.ndarray,  # (K, N) distorted normalised x
    yd: np.ndarray,  # (K, N)
    distortion: np.ndarray,  # (K, 5)
    iterations: int = 20,
) -> tuple[np.ndarray, np.ndarray]:
    """Invert the distortion by Newton's method; returns undistorted (x, y), each (K, N)."""
    x, y = xd.copy(), yd.copy()
    k1, k2, p1, p2, k3 = (distortion[:, i : i + 1] for i in range(5))
    for _ in range(iterations):
        fx_, fy_, r2, radial = _distort(x, y, distortion)
        drad = k1 + r2 * (2.0 * k2 + 3.0 * k3 * r2)
        a = radial + 2.0 * x * x * drad + 2.0 * p1 * y + 6.0 * p2 * x
        b = 2.0 * x * y * drad + 2.0 * p1 * x + 2.0 * p2 * y
        d = radial + 2.0 * y * y * drad + 6.0 * p1 * y + 2.0 * p2 * x
        ex, ey = fx_ - xd, fy_ - yd
        det = a * d - b * b
        det = np.where(np.abs(det) < 1e-12, 1e-12, det)
        x = x - (d * ex - b * ey) / det
        y = y - (a * ey - b * ex) / det
    return x, y


def pixel_rays_batch(
    intrinsics: np.ndarray,  # (K, 4)
    distortion: np.ndarray,  # (K, 5)
    R: np.ndarray,  # (K, 3, 3)
    uv: np.ndarray,  # (K, N, 2) or (1, N, 2)
) -> np.ndarray:
    """Unit ray directions (K, N, 3) in the world frame for pixels."""
    xd = (uv[..., 0] - intrinsics[:, 2:3]) / intrinsics[:, 0:1]
    yd = (uv[..., 1] - intrinsics[:, 3:4]) / intrinsics[:, 1:2]
    x, y = undistort_normalised(xd, yd, distortion)
    d_cam = np.stack([x, y, np.ones_like(x)], -1)
    d_world = np.einsum("kji,knj->kni", R, d_cam)
    return d_world / np.linalg.norm(d_world, axis=-1, keepdims=True)


def intersect_plane_z(
    intrinsics: np.ndarray,  # (K, 4)
    distortion: np.ndarray,  # (K, 5)
    R: np.ndarray,  # (K, 3, 3)
    t: np.ndarray,  # (K, 3)
    uv: np.ndarray,  # (K, N, 2) or (1, N, 2)
    z_plane: float = 0.0,
) -> np.ndarray:
    """World points (K, N, 3) where pixel rays meet the horizontal plane z = z_plane (NaN if they miss)."""
    rays = pixel_rays_batch(intrinsics, distortion, R, uv)
    centre = -np.einsum("kji,kj->ki", R, t)  # (K,3)
    s = (z_plane - centre[:, None, 2]) / rays[..., 2]
    s = np.where(s > 0, s, np.nan)
    return centre[:, None, :] + s[..., None] * rays
