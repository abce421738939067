"""A site: every camera of one run (or of the runs of one plan) in one ENU frame, and how they sit to each other.

Pure numerics on calibrated cameras, no I/O: the relative pose of every pair
of cameras with its uncertainty, and the ground each camera sees (for the
site's top view and to say which pairs share ground). The orchestration is
``pipeline.run.calibrate_runs``; the files are ``pipeline.site_page``.

The relative pose of B to A is B's centre in A's camera frame,
``t_a_b = R_a (C_b - C_a)`` (metres), and the rotation ``R_b_from_a = R_b R_a^T``
(degrees, its angle). Its uncertainty is propagated by sampling each camera's
pose from its own (15, 15) parameter covariance (the left rotation
perturbation and the translation of docs/conventions.md) and pairing the
samples: the two cameras are treated as independent. Their errors share the
GNSS noise of the points both saw, which moves both cameras together and
cancels in the difference, so independence leans towards over-stating the
spread of the relative pose. Measured (benchmarks/bench_site.py, six runs of the
independent writer): translation error / 1-sigma mean 0.81, max 1.28; rotation
mean 0.62, max 0.92.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecal_field.core.camera import ROTATION_SLICE, TRANSLATION_SLICE, Camera, rotation_from_vector, vector_from_rotation

POSE_SAMPLES = 4000  # pose samples per camera for the relative pose's spread
GROUND_RANGE_M = (3.0, 30.0)  # the ground a camera's footprint covers, horizontal distance from its pole
GROUND_STEP_M = 0.5  # the footprint grid's spacing


@dataclass(frozen=True, eq=False)
class RelativePose:
    """Camera ``b`` relative to camera ``a``, with its 1-sigma uncertainty.

    Attributes
    ----------
    a, b : camera names.
    baseline_enu_m : (3,) C_b - C_a, ENU metres.
    baseline_std_m : (3,) its std per ENU axis, metres.
    distance_m, distance_std_m : |C_b - C_a| and its std, metres.
    translation_in_a_m : (3,) t_a_b = R_a (C_b - C_a): B's centre in A's camera frame (x right, y down, z forward), metres.
    translation_in_a_std_m : (3,) its std per axis, metres.
    rotation_b_from_a : (3, 3) R_b R_a^T (A's camera frame to B's).
    rotation_deg : its angle, degrees.
    rotation_std_deg : RMS angle of the sampled relative rotations about it, degrees (the 3-axis spread).
    translation_std_m : RMS distance of the sampled t_a_b from it, metres (the 3-axis spread).
    shared_ground_m2 : ground 3-30 m from either pole that both cameras see, square metres.
    """

    a: str
    b: str
    baseline_enu_m: np.ndarray
    baseline_std_m: np.ndarray
    distance_m: float
    distance_std_m: float
    translation_in_a_m: np.ndarray
    translation_in_a_std_m: np.ndarray
    rotation_b_from_a: np.ndarray
    rotation_deg: float
    rotation_std_deg: float
    translation_std_m: float
    shared_ground_m2: float

    @property
    def shares_ground(self) -> bool:
        return self.shared_ground_m2 > 0.0

    def to_dict(self) -> dict:
        return {
            "a": self.a,
            "b": self.b,
            "shares_ground": self.shares_ground,
            "shared_ground_m2": round(self.shared_ground_m2, 2),
            "baseline_enu_m": self.baseline_enu_m.tolist(),
            "baseline_std_m": self.baseline_std_m.tolist(),
            "distance_m": self.distance_m,
            "distance_std_m": self.distance_std_m,
            "translation_in_a_m": self.translation_in_a_m.tolist(),
            "translation_in_a_std_m": self.translation_in_a_std_m.tolist(),
            "translation_std_m": self.translation_std_m,
            "rotation_b_from_a": self.rotation_b_from_a.tolist(),
            "rotation_vector_deg": np.degrees(vector_from_rotation(self.rotation_b_from_a)).tolist(),
            "rotation_deg": self.rotation_deg,
            "rotation_std_deg": self.rotation_std_deg,
            "uncertainty": "each camera's pose sampled from its parameter covariance, the two taken as independent "
                           f"({POSE_SAMPLES} samples); 1 sigma",
        }


def pose_samples(camera: Camera, covariance: np.ndarray | None, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3, 3) R_cam_from_world and (n, 3) centres (ENU m) of ``camera`` perturbed by its (15, 15) covariance.

    Without a covariance (None or not finite) every sample is the camera itself.
    """
    R, t = camera.pose.R_cam_from_world, camera.pose.t_cam_from_world
    idx = np.r_[np.arange(15)[ROTATION_SLICE], np.arange(15)[TRANSLATION_SLICE]]
    delta = np.zeros((n, 6))
    if covariance is not None:
        cov = np.asarray(covariance, float)[np.ix_(idx, idx)]
        if np.all(np.isfinite(cov)):
            vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
            delta = rng.standard_normal((n, 6)) * np.sqrt(np.clip(vals, 0.0, None)) @ vecs.T
    Rs = rotation_from_vector(delta[:, :3]) @ R
    ts = t + delta[:, 3:]
    centres = -np.einsum("kji,kj->ki", Rs, ts)
    return Rs, centres


def relative_pose(name_a: str, cam_a: Camera, cov_a: np.ndarray | None, name_b: str, cam_b: Camera, cov_b: np.ndarray | None,
                  shared_ground_m2: float = 0.0, seed: int = 0, n: int = POSE_SAMPLES) -> RelativePose:
    """Camera ``b`` relative to camera ``a`` (both in one ENU frame) and its spread (see the module docstring)."""
    rng = np.random.default_rng(seed)
    Ra, Ca = cam_a.pose.R_cam_from_world, cam_a.pose.position_world
    Rb, Cb = cam_b.pose.R_cam_from_world, cam_b.pose.position_world
    base = Cb - Ca
    t_ab = Ra @ base
    R_ba = Rb @ Ra.T
    Ras, Cas = pose_samples(cam_a, cov_a, n, rng)
    Rbs, Cbs = pose_samples(cam_b, cov_b, n, rng)
    bases = Cbs - Cas
    t_abs = np.einsum("kij,kj->ki", Ras, bases)
    R_bas = Rbs @ np.transpose(Ras, (0, 2, 1))
    dev = np.degrees(np.linalg.norm(vector_from_rotation(R_bas @ R_ba.T), axis=-1))
    return RelativePose(
        a=name_a, b=name_b, baseline_enu_m=base, baseline_std_m=bases.std(axis=0, ddof=1),
        distance_m=float(np.linalg.norm(base)), distance_std_m=float(np.linalg.norm(bases, axis=1).std(ddof=1)),
        translation_in_a_m=t_ab, translation_in_a_std_m=t_abs.std(axis=0, ddof=1),
        rotation_b_from_a=R_ba, rotation_deg=float(np.degrees(np.linalg.norm(vector_from_rotation(R_ba)))),
        rotation_std_deg=float(np.sqrt(np.mean(dev**2))),
        translation_std_m=float(np.sqrt(np.mean(np.sum((t_abs - t_ab) ** 2, axis=1)))),
        shared_ground_m2=float(shared_ground_m2),
    )


def relative_pose_error(estimate: RelativePose, truth_a: Camera, truth_b: Camera) -> tuple[float, float]:
    """(translation error m, rotation error deg) of an estimated relative pose against two true cameras."""
    Ra, Rb = truth_a.pose.R_cam_from_world, truth_b.pose.R_cam_from_world
    t_true = Ra @ (truth_b.pose.position_world - truth_a.pose.position_world)
    R_true = Rb @ Ra.T
    dt = float(np.linalg.norm(estimate.translation_in_a_m - t_true))
    dr = float(np.degrees(np.linalg.norm(vector_from_rotation(estimate.rotation_b_from_a @ R_true.T))))
    return dt, dr


def ground_grid(cameras: list[Camera], step_m: float = GROUND_STEP_M, reach_m: float = GROUND_RANGE_M[1]) -> np.ndarray:
    """(N, 3) ground points (z = 0) on a ``step_m`` grid over every camera's pole +- ``reach_m``."""
    poles = np.array([c.pose.position_world[:2] for c in cameras])
    lo, hi = poles.min(axis=0) - reach_m, poles.max(axis=0) + reach_m
    xs = np.arange(lo[0], hi[0] + step_m / 2, step_m)
    ys = np.arange(lo[1], hi[1] + step_m / 2, step_m)
    gx, gy = np.meshgrid(xs, ys)
    return np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]


def sees_ground(camera: Camera, points: np.ndarray, range_m: tuple[float, float] = GROUND_RANGE_M) -> np.ndarray:
    """(N,) which ground points (N, 3) the camera sees within ``range_m`` of its pole: in front, inside the image
    through its pinhole (so a distortion polynomial folding far rays back into the image does not count them) and
    through its lens."""
    pole = camera.pose.position_world[:2]
    r = np.hypot(points[:, 0] - pole[0], points[:, 1] - pole[1])
    Xc = points @ camera.pose.R_cam_from_world.T + camera.pose.t_cam_from_world
    front = Xc[:, 2] > 0.1
    i = camera.intrinsics
    with np.errstate(divide="ignore", invalid="ignore"):
        u = i.fx * Xc[:, 0] / Xc[:, 2] + i.cx
        v = i.fy * Xc[:, 1] / Xc[:, 2] + i.cy
    pin = front & (u >= 0) & (u <= i.width - 1) & (v >= 0) & (v <= i.height - 1)
    seen = np.zeros(len(points), bool)
    if pin.any():
        uv = camera.project(points[pin])
        seen[pin] = (uv[:, 0] >= 0) & (uv[:, 0] <= i.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= i.height - 1)
    return seen & (r >= range_m[0]) & (r <= range_m[1])


def footprints(cameras: dict[str, Camera], step_m: float = GROUND_STEP_M) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """The ground grid (N, 3) and, per camera, which of its points the camera sees (N,) bool."""
    grid = ground_grid(list(cameras.values()), step_m)
    return grid, {name: sees_ground(cam, grid) for name, cam in cameras.items()}


def hull_xy(points: np.ndarray) -> np.ndarray:
    """(K, 2) convex hull of ground points (N, >=2), counter-clockwise; the points themselves when fewer than 3."""
    pts = np.unique(np.asarray(points, float)[:, :2], axis=0)
    if len(pts) < 3:
        return pts
    pts = pts[np.lexsort((pts[:, 1], pts[:, 0]))]

    def turn(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
        # z of the 2D cross product (a - o) x (b - o): np.cross of 2-vectors is deprecated
        return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))

    def half(seq):
        out: list[np.ndarray] = []
        for p in seq:
            while len(out) >= 2 and turn(out[-2], out[-1], p) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def site_pairs(cameras: dict[str, Camera], covariances: dict[str, np.ndarray | None], seed: int = 0) -> list[RelativePose]:
    """The relative pose of every pair of cameras (in the given order), with the ground they share."""
    _, seen = footprints(cameras)
    cell = GROUND_STEP_M**2
    names = list(cameras)
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            shared = float(np.sum(seen[a] & seen[b]) * cell)
            out.append(relative_pose(a, cameras[a], covariances.get(a), b, cameras[b], covariances.get(b), shared, seed=seed))
    return out
