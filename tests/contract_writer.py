"""An INDEPENDENT writer of run files, and the synthetic flights it writes.

The offline stage must accept every file that follows
shared/contracts/run-format.md, whoever wrote it. So the tests do not write
runs with our recorder's RunWriter: this module writes them from the contract
text alone, with the raw ``mcap.writer.Writer`` and the message classes of
``foxglove_schemas_protobuf``.

It also makes the flights: a seeded, truth-known scene (a camera on a pole, a
drone holding at waypoints with drift, RTK noise, a marker rendered into JPEG
frames through the true camera with a homography). The scene uses its own
geometry (scipy's Euler rotations) rather than the pipeline's, so a lever-arm
or frame mistake in the pipeline shows up as an error, not as agreement.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from dronecal_field.core.camera import Camera, CameraPose, Distortion, Intrinsics, look_rotation
from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic

T0_NS = 1_700_000_000_000_000_000  # run clock start (UTC ns)
ORIGIN = EnuOrigin(lat_deg=-35.363261, lon_deg=149.165230, h_m=603.0)


# --------------------------------------------------------------------------
# Scene


def pole_camera(
    width: int = 640,
    height: int = 480,
    f_px: float = 520.0,
    position_enu: tuple[float, float, float] = (0.0, 0.0, 4.0),
    azimuth_deg: float = 0.0,
    tilt_deg: float = 15.0,
    distortion: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0),
    principal_offset_px: tuple[float, float] = (6.0, -4.0),
) -> Camera:
    """A fixed camera on a pole looking along ``azimuth_deg`` (from north, clockwise), tilted down."""
    a, t = np.radians(azimuth_deg), np.radians(tilt_deg)
    forward = np.array([np.sin(a) * np.cos(t), np.cos(a) * np.cos(t), -np.sin(t)])
    R = look_rotation(forward)
    return Camera(
        intrinsics=Intrinsics(
            fx=f_px, fy=f_px * 1.002,
            cx=(width - 1) / 2 + principal_offset_px[0], cy=(height - 1) / 2 + principal_offset_px[1],
            width=width, height=height,
        ),
        distortion=Distortion.from_array(np.array(distortion)),
        pose=CameraPose.from_position(R, np.array(position_enu, float)),
        enu_origin=tuple(ORIGIN.as_list()),
    )


def grid_waypoints(
    east_m: tuple[float, ...] = (-2.5, 0.0, 2.5),
    north_m: tuple[float, ...] = (6.0, 8.5, 11.0),
    up_m: tuple[float, ...] = (1.5, 3.5),
) -> np.ndarray:
    """(M, 3) ENU antenna positions, flown boustrophedon per height."""
    points = []
    for k, z in enumerate(up_m):
        rows = north_m if k % 2 == 0 else north_m[::-1]
        for j, y in enumerate(rows):
            cols = east_m if (j + k) % 2 == 0 else east_m[::-1]
            points += [(x, y, z) for x in cols]
    return np.array(points, float)


@dataclass
class Flight:
    """Truth of one synthetic flight, sampled densely on the run clock."""

    t_ns: np.ndarray  # (T,) int64
    antenna_enu: np.ndarray  # (T, 3) metres
    rpy_rad: np.ndarray  # (T, 3) roll, pitch, yaw (yaw from north, clockwise)
    holds: list[tuple[int, int, int]]  # (start_ns, end_ns, mission seq)
    waypoints_enu: np.ndarray  # (M, 3)
    offset_frd_m: np.ndarray  # (3,)
    legs: list[tuple[int, int, int, int]] = field(default_factory=list)  # (start_ns, end_ns, seq_from, seq_to)

    def at(self, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Antenna ENU (N, 3) and roll/pitch/yaw (N, 3) interpolated at ``t_ns`` (N,)."""
        t = (np.asarray(t_ns, np.int64) - self.t_ns[0]).astype(float)
        tt = (self.t_ns - self.t_ns[0]).astype(float)
        pos = np.stack([np.interp(t, tt, self.antenna_enu[:, i]) for i in range(3)], -1)
        yaw = np.unwrap(self.rpy_rad[:, 2])
        rpy = np.stack([np.interp(t, tt, self.rpy_rad[:, 0]), np.interp(t, tt, self.rpy_rad[:, 1]), np.interp(t, tt, yaw)], -1)
        return pos, rpy

    def marker_centre(self, t_ns: np.ndarray) -> np.ndarray:
        """(N, 3) ENU marker centre: antenna + R_enu_from_body(attitude) @ offset_frd."""
        pos, rpy = self.at(t_ns)
        return pos + np.einsum("nij,j->ni", enu_from_frd(rpy), self.offset_frd_m)


def enu_from_frd(rpy_rad: np.ndarray) -> np.ndarray:
    """(N, 3, 3) body FRD -> ENU rotations from roll, pitch, yaw (N, 3), ZYX aerospace order."""
    ned_from_frd = Rotation.from_euler("ZYX", np.asarray(rpy_rad)[:, ::-1]).as_matrix()
    enu_from_ned = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    return enu_from_ned @ ned_from_frd


def _facing_attitude(camera: Camera, pos: np.ndarray, rng: np.random.Generator, rate_hz: float, tilt_rad: float) -> np.ndarray:
    """(N, 3) roll, pitch, yaw (rad) along positions (N, 3) sampled at ``rate_hz``: the nose towards the camera, smoothed,
    with ``tilt_rad`` of random roll and pitch."""
    cam = camera.pose.position_world
    yaw = np.arctan2(cam[0] - pos[:, 0], cam[1] - pos[:, 1])  # bearing to the camera, from north
    yaw = cv2.GaussianBlur(np.unwrap(yaw)[:, None], (1, 0), sigmaX=0, sigmaY=rate_hz * 0.2).ravel()
    roll = cv2.GaussianBlur(rng.normal(0, 1, (len(pos), 1)), (1, 0), sigmaX=0, sigmaY=rate_hz * 0.5).ravel()
    pitch = cv2.GaussianBlur(rng.normal(0, 1, (len(pos), 1)), (1, 0), sigmaX=0, sigmaY=rate_hz * 0.5).ravel()
    roll *= tilt_rad / max(roll.std(), 1e-12)
    pitch *= tilt_rad / max(pitch.std(), 1e-12)
    return np.stack([roll, pitch, (yaw + np.pi) % (2 * np.pi) - np.pi], -1)


def make_flight(
    camera: Camera,
    waypoints_enu: np.ndarray,
    hold_s: float = 3.0,
    move_s: float = 2.0,
    drift_m: float = 0.02,
    offset_frd_m: tuple[float, float, float] = (0.25, 0.0, 0.10),
    tilt_rad: float = 0.02,
    first_seq: int = 4,
    seed: int = 0,
    rate_hz: float = 50.0,
    transit_from_enu: tuple[float, float] | None = None,
    transit_speed_mps: float = 3.0,
) -> Flight:
    """A drone that takes off at the origin, holds at each waypoint with drift, nose towards the camera.

    Moves between holds follow a smooth (cosine) speed profile of ``move_s``;
    during a hold the antenna wanders by a low-passed random walk of about
    ``drift_m`` (std per axis) around the waypoint, and the body tilts by
    ``tilt_rad`` of random roll and pitch.

    With ``transit_from_enu`` (east, north of the take-off, metres) the drone
    takes off there, climbs to the first waypoint's height and flies to it in
    a straight line at ``transit_speed_mps`` (ramps of 2 m/s^2), and flies home
    the same way after the last hold: two transit legs a GNSS track shows as
    constant-speed stretches.
    """
    rng = np.random.default_rng(seed)
    dt = 1.0 / rate_hz
    start = np.array([0.0, 2.0, 0.0]) if transit_from_enu is None else np.array([*transit_from_enu, 0.0], float)
    segments_t, segments_p = [], []
    holds = []
    t = 0.0
    # 2 s on the ground, then climb to the first waypoint.
    prev = start
    n = int(round(2.0 / dt))
    segments_t.append(t + dt * np.arange(n))
    segments_p.append(np.repeat(prev[None], n, 0))
    t += n * dt
    wps = np.asarray(waypoints_enu, float)
    if transit_from_enu is not None:
        for a, b in ((start, np.array([*start[:2], wps[0, 2]])), (np.array([*start[:2], wps[0, 2]]), wps[0])):
            p = _straight(a, b, transit_speed_mps if a[2] == b[2] else 1.0, dt)
            segments_t.append(t + dt * np.arange(1, len(p) + 1))
            segments_p.append(p)
            t += len(p) * dt
        prev = wps[0]
    for k, wp in enumerate(wps):
        if k == 0 and transit_from_enu is not None:
            dur = 0.0
        else:
            dur = move_s if k else 2 * move_s
        n = int(round(dur / dt))
        s = 0.5 - 0.5 * np.cos(np.pi * np.arange(n) / max(n, 1))
        segments_t.append(t + dt * np.arange(n))
        segments_p.append(prev + s[:, None] * (wp - prev))
        t += n * dt
        n = int(round(hold_s / dt))
        walk = np.cumsum(rng.normal(size=(n, 3)), 0)
        walk = cv2.GaussianBlur(walk, (1, 0), sigmaX=0, sigmaY=rate_hz * 0.3)
        walk -= walk.mean(0)
        walk *= drift_m / max(walk.std(), 1e-9)
        walk[:, 2] *= 0.5
        # Blend from the arrival point so the path is continuous.
        walk *= np.clip(np.arange(n) / (0.3 * rate_hz), 0, 1)[:, None]
        segments_t.append(t + dt * np.arange(n))
        segments_p.append(wp + walk)
        holds.append((T0_NS + int(round(t * 1e9)), T0_NS + int(round((t + n * dt) * 1e9)), first_seq + k))
        t += n * dt
        prev = segments_p[-1][-1]
    if transit_from_enu is not None:
        above = np.array([*start[:2], prev[2]])
        for a, b in ((prev, above), (above, start)):
            p = _straight(a, b, transit_speed_mps if a[2] == b[2] else 1.0, dt)
            segments_t.append(t + dt * np.arange(1, len(p) + 1))
            segments_p.append(p)
            t += len(p) * dt
        prev = start
    n = int(round(3.0 / dt))
    segments_t.append(t + dt * np.arange(n))
    segments_p.append(prev + (0.5 - 0.5 * np.cos(np.pi * np.arange(n) / n))[:, None] * (start - prev))
    tt = np.concatenate(segments_t)
    pos = np.concatenate(segments_p)
    keep = np.r_[True, np.diff(tt) > 1e-9]
    tt, pos = tt[keep], pos[keep]
    rpy = _facing_attitude(camera, pos, rng, rate_hz, tilt_rad)
    return Flight(
        t_ns=T0_NS + np.round(tt * 1e9).astype(np.int64),
        antenna_enu=pos,
        rpy_rad=rpy,
        holds=holds,
        waypoints_enu=np.asarray(waypoints_enu, float),
        offset_frd_m=np.array(offset_frd_m, float),
    )


def _straight(a: np.ndarray, b: np.ndarray, speed_mps: float, dt: float, accel_mps2: float = 2.0) -> np.ndarray:
    """(n, 3) positions every ``dt`` after ``a`` up to ``b``: a straight line at ``speed_mps`` with ramps of ``accel_mps2``."""
    total = float(np.linalg.norm(b - a))
    if total < 1e-6:
        return np.zeros((0, 3))
    ss = np.linspace(0.0, total, max(2, int(total / 0.002)))
    v = np.minimum(speed_mps, np.sqrt(2 * accel_mps2 * np.minimum(ss, total - ss) + 0.05**2))
    tt = np.r_[0.0, np.cumsum(np.diff(ss) / (0.5 * (v[1:] + v[:-1])))]
    m = int(np.ceil(tt[-1] / dt))
    s_at = np.interp(dt * np.arange(1, m + 1), tt, ss)
    return a + (s_at / total)[:, None] * (b - a)


def make_leg_flight(
    camera: Camera,
    waypoints_enu: np.ndarray,
    hold_s: np.ndarray | float,
    speed_mps: float = 2.0,
    accel_mps2: float = 2.0,
    drift_m: float = 0.02,
    offset_frd_m: tuple[float, float, float] = (0.25, 0.0, 0.10),
    tilt_rad: float = 0.02,
    first_seq: int = 4,
    seed: int = 0,
    rate_hz: float = 50.0,
) -> Flight:
    """A drone that flies straight legs at constant ``speed_mps`` through waypoints with hold 0 and holds at the others.

    Between two holds the path is the polyline through the fly-through
    waypoints between them, flown at ``speed_mps`` with ramps of
    ``accel_mps2`` out of and into the holds (corners are taken at speed). A
    hold wanders like :func:`make_flight`'s. ``Flight.legs`` gets one
    (start_ns, end_ns, seq_from, seq_to) per waypoint-to-waypoint segment.
    """
    rng = np.random.default_rng(seed)
    wps = np.asarray(waypoints_enu, float)
    holds_s = np.broadcast_to(np.asarray(hold_s, float), (len(wps),)).copy()
    holds_s[-1] = max(holds_s[-1], 0.0)
    dt = 1.0 / rate_hz
    start = np.array([0.0, 2.0, 0.0])
    seg_t: list[np.ndarray] = []
    seg_p: list[np.ndarray] = []
    holds, legs = [], []
    t = 0.0
    n = int(round(2.0 / dt))
    seg_t.append(t + dt * np.arange(n))
    seg_p.append(np.repeat(start[None], n, 0))
    t += n * dt
    # Climb to the first waypoint (cosine profile), as make_flight.
    n = int(round(4.0 / dt))
    s = 0.5 - 0.5 * np.cos(np.pi * np.arange(n) / n)
    seg_t.append(t + dt * np.arange(n))
    seg_p.append(start + s[:, None] * (wps[0] - start))
    t += n * dt
    prev_end = wps[0]

    def hold(k: int, at: np.ndarray) -> np.ndarray:
        m = int(round(holds_s[k] / dt))
        walk = np.cumsum(rng.normal(size=(m, 3)), 0)
        walk = cv2.GaussianBlur(walk, (1, 0), sigmaX=0, sigmaY=rate_hz * 0.3)
        walk -= walk.mean(0)
        walk *= drift_m / max(walk.std(), 1e-9)
        walk[:, 2] *= 0.5
        walk *= np.clip(np.arange(m) / (0.3 * rate_hz), 0, 1)[:, None]
        return at + walk

    k = 0
    while k < len(wps):
        if holds_s[k] > 0:
            p = hold(k, prev_end)
            seg_t.append(t + dt * np.arange(len(p)))
            seg_p.append(p)
            holds.append((T0_NS + int(round(t * 1e9)), T0_NS + int(round((t + len(p) * dt) * 1e9)), first_seq + k))
            t += len(p) * dt
            prev_end = p[-1]
        if k == len(wps) - 1:
            break
        # The stretch to the next hold (or the last waypoint): a polyline flown at speed.
        j = k + 1
        while j < len(wps) - 1 and holds_s[j] <= 0:
            j += 1
        poly = np.vstack([prev_end[None], wps[k + 1 : j + 1]])
        seg_len = np.linalg.norm(np.diff(poly, axis=0), axis=1)
        cum = np.r_[0.0, np.cumsum(seg_len)]
        total = float(cum[-1])
        ss = np.linspace(0.0, total, max(2, int(total / 0.002)))
        v = np.minimum(speed_mps, np.sqrt(2 * accel_mps2 * np.minimum(ss, total - ss) + 0.05**2))
        tt = np.r_[0.0, np.cumsum(np.diff(ss) / (0.5 * (v[1:] + v[:-1])))]
        m = int(np.floor(tt[-1] / dt))
        s_at = np.interp(dt * np.arange(1, m + 1), tt, ss)
        pts = np.stack([np.interp(s_at, cum, poly[:, i]) for i in range(3)], -1)
        t_corner = np.interp(cum, ss, tt)
        for q in range(len(poly) - 1):
            legs.append((
                T0_NS + int(round((t + t_corner[q]) * 1e9)), T0_NS + int(round((t + t_corner[q + 1]) * 1e9)),
                first_seq + k + q, first_seq + k + q + 1,
            ))
        seg_t.append(t + dt * np.arange(1, m + 1))
        seg_p.append(pts)
        t += m * dt
        prev_end = pts[-1] if m else prev_end
        k = j
    n = int(round(4.0 / dt))
    seg_t.append(t + dt * np.arange(1, n + 1))
    seg_p.append(prev_end + (0.5 - 0.5 * np.cos(np.pi * np.arange(1, n + 1) / n))[:, None] * (start - prev_end))
    tt = np.concatenate(seg_t)
    pos = np.concatenate(seg_p)
    keep = np.r_[True, np.diff(tt) > 1e-9]
    tt, pos = tt[keep], pos[keep]
    rpy = _facing_attitude(camera, pos, rng, rate_hz, tilt_rad)
    return Flight(
        t_ns=T0_NS + np.round(tt * 1e9).astype(np.int64),
        antenna_enu=pos,
        rpy_rad=rpy,
        holds=holds,
        waypoints_enu=wps,
        offset_frd_m=np.array(offset_frd_m, float),
        legs=legs,
    )


def leg_waypoints(
    camera: Camera,
    depths_m: tuple[float, ...] = (5.0, 8.0, 12.0),
    heights_m: tuple[float, ...] = (1.5, 3.5, 5.5),
    half_width_frac: float = 0.9,
) -> np.ndarray:
    """(M, 3) ENU waypoints of legs across the camera's view: for each depth and height whose
    centre the camera sees, one waypoint at each side of the image (``half_width_frac`` of the
    horizontal field of view at that depth, pulled in until the marker is in the image with a
    5 % margin), alternating direction, so the marker crosses the image left-right and
    right-left at several rows.
    """
    R = camera.pose.R_cam_from_world
    c = camera.pose.position_world
    fwd = R[2] * np.array([1.0, 1.0, 0.0])
    fwd /= np.linalg.norm(fwd)
    right = np.array([fwd[1], -fwd[0], 0.0])
    i = camera.intrinsics
    margin = 0.05 * np.array([i.width, i.height])

    def inside(p: np.ndarray) -> bool:
        if camera.depth(p[None])[0] <= 0.5:
            return False
        uv = camera.project(p[None])[0]
        return bool(np.all(uv >= margin) and np.all(uv <= np.array([i.width, i.height]) - margin))

    points = []
    k = 0
    for h in heights_m:
        for d in depths_m:
            centre = c * np.array([1.0, 1.0, 0.0]) + d * fwd
            centre[2] = h
            if not inside(centre):
                continue
            half = half_width_frac * (i.width / 2) / i.fx * d
            while half > 0.5 and not (inside(centre - half * right) and inside(centre + half * right)):
                half *= 0.95
            if half <= 0.5:
                continue
            ends = [-1.0, 1.0] if k % 2 == 0 else [1.0, -1.0]
            points += [tuple(centre + e * half * right) for e in ends]
            k += 1
    return np.array(points, float)


# --------------------------------------------------------------------------
# Rendering


@dataclass
class MarkerLook:
    """The physical marker: ArUco (dictionary, id, black-square side) or an LED."""

    kind: str = "aruco"
    dictionary: str = "DICT_4X4_50"
    marker_id: int = 7
    size_m: float = 0.4
    led_radius_m: float = 0.03


def _background(width: int, height: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    noise = cv2.GaussianBlur(rng.normal(0, 1, (height, width)).astype(np.float32), (0, 0), 6)
    noise = (noise - noise.min()) / (np.ptp(noise) + 1e-9)
    ramp = np.linspace(0.35, 0.6, height, dtype=np.float32)[:, None]
    return np.clip(255 * (0.25 * noise + ramp), 0, 255).astype(np.uint8)


@dataclass
class Renderer:
    """Renders the marker into grey frames through a (distorted) camera."""

    camera: Camera
    flight: Flight
    look: MarkerLook = field(default_factory=MarkerLook)
    dark: bool = False

    def __post_init__(self) -> None:
        self.background = _background(self.camera.width, self.camera.height)
        if self.dark:
            self.background = (self.background // 6).astype(np.uint8)
        if self.look.kind == "aruco":
            dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.look.dictionary))
            bits = dictionary.markerSize + 2
            cell = 12
            inner = cv2.aruco.generateImageMarker(dictionary, self.look.marker_id, bits * cell)
            border = cell  # one cell of white quiet zone
            self.texture = cv2.copyMakeBorder(inner, border, border, border, border, cv2.BORDER_CONSTANT, value=255)
            b, s = border, bits * cell
            # Texture coordinates of the black square's corners (pixel edges, centres at integers).
            self.tex_square = np.array([[b - 0.5, b - 0.5], [b + s - 0.5, b - 0.5], [b + s - 0.5, b + s - 0.5], [b - 0.5, b + s - 0.5]])

    def marker_corners_world(self, t_ns: int) -> np.ndarray:
        """(4, 3) ENU corners of the black square in ArUco order (TL, TR, BR, BL seen from the front)."""
        pos, rpy = self.flight.at(np.array([t_ns]))
        R = enu_from_frd(rpy)[0]
        centre = pos[0] + R @ self.flight.offset_frd_m
        left, down = R @ np.array([0.0, -1.0, 0.0]), R @ np.array([0.0, 0.0, 1.0])
        h = self.look.size_m / 2
        return np.array([centre + h * (su * left + sv * down) for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))])

    def render(self, t_ns: int, visible: bool = True) -> np.ndarray:
        """(H, W) uint8 frame at capture time ``t_ns``."""
        image = self.background.copy()
        if not visible:
            return image
        if self.look.kind == "led":
            pos, rpy = self.flight.at(np.array([t_ns]))
            centre = pos[0] + enu_from_frd(rpy)[0] @ self.flight.offset_frd_m
            if self.camera.depth(centre[None])[0] <= 0:
                return image
            uv = self.camera.project(centre[None])[0]
            r_px = max(1.2, self.camera.intrinsics.fx * self.look.led_radius_m / self.camera.depth(centre[None])[0])
            half = int(np.ceil(4 * r_px)) + 2
            x0, y0 = max(int(uv[0]) - half, 0), max(int(uv[1]) - half, 0)
            x1, y1 = min(int(uv[0]) + half + 1, image.shape[1]), min(int(uv[1]) + half + 1, image.shape[0])
            if x1 <= x0 or y1 <= y0:
                return image
            ys, xs = np.mgrid[y0:y1, x0:x1]
            blob = 255.0 * np.exp(-((xs - uv[0]) ** 2 + (ys - uv[1]) ** 2) / (2 * (r_px / 1.5) ** 2))
            image[y0:y1, x0:x1] = np.clip(np.maximum(image[y0:y1, x0:x1].astype(float), blob), 0, 255).astype(np.uint8)
            return image
        corners = self.marker_corners_world(t_ns)
        if np.any(self.camera.depth(corners) <= 0):
            return image
        uv = self.camera.project(corners)
        # The texture's outer corners through the homography of the square.
        H = cv2.getPerspectiveTransform(self.tex_square.astype(np.float32), uv.astype(np.float32))
        th, tw = self.texture.shape
        outer = cv2.perspectiveTransform(np.array([[[-0.5, -0.5], [tw - 0.5, -0.5], [tw - 0.5, th - 0.5], [-0.5, th - 0.5]]], np.float32), H)[0]
        x0, y0 = np.floor(outer.min(0)).astype(int) - 2
        x1, y1 = np.ceil(outer.max(0)).astype(int) + 2
        x0, y0 = max(x0, 0), max(y0, 0)
        x1, y1 = min(x1, image.shape[1]), min(y1, image.shape[0])
        if x1 <= x0 or y1 <= y0:
            return image
        shift = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]])
        Hs = shift @ H
        # Pre-blur the texture to the scale it lands at (no aliasing when shrinking).
        scale = np.linalg.norm(uv[1] - uv[0]) / (self.tex_square[1, 0] - self.tex_square[0, 0])
        tex = self.texture if scale >= 0.7 else cv2.GaussianBlur(self.texture, (0, 0), 0.45 / scale)
        size = (x1 - x0, y1 - y0)
        warped = cv2.warpPerspective(tex, Hs, size, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        mask = cv2.warpPerspective(np.full(tex.shape, 255, np.uint8), Hs, size, flags=cv2.INTER_LINEAR, borderValue=0).astype(float) / 255
        roi = image[y0:y1, x0:x1].astype(float)
        image[y0:y1, x0:x1] = np.clip(mask * warped + (1 - mask) * roi, 0, 255).astype(np.uint8)
        return image

    def true_centre_px(self, t_ns: np.ndarray) -> np.ndarray:
        """(N, 2) the marker centre's true pixel at capture times ``t_ns`` (N,)."""
        return self.camera.project(self.flight.marker_centre(np.asarray(t_ns)))


def encode_jpeg(image: np.ndarray, quality: int = 92) -> bytes:
    ok, buf = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return buf.tobytes()


# --------------------------------------------------------------------------
# The run file, from the contract text


def _file_descriptor_set(message_class) -> bytes:
    """Serialized FileDescriptorSet of a protobuf message class and its imports (MCAP protobuf schema)."""
    from google.protobuf.descriptor_pb2 import FileDescriptorSet

    fds = FileDescriptorSet()
    seen: set[str] = set()

    def add(fd) -> None:
        if fd.name in seen:
            return
        seen.add(fd.name)
        for dep in fd.dependencies:
            add(dep)
        fd.CopyToProto(fds.file.add())

    add(message_class.DESCRIPTOR.file)
    return fds.SerializeToString()


def _stamp(msg_field, t_ns: int) -> None:
    msg_field.seconds = int(t_ns // 1_000_000_000)
    msg_field.nanos = int(t_ns % 1_000_000_000)


@dataclass
class RunSpec:
    """What to put in a synthetic run; every flag is one way field data gets messy."""

    fps: float = 10.0
    gnss_hz: float = 5.0
    latency_s: float = 0.0  # frames stamped this late (host arrival)
    declared_latency: str | None = None  # camera.latency_s metadata value
    gnss_sigma_m: tuple[float, float, float] = (0.008, 0.008, 0.012)
    jpeg_quality: int = 92
    with_events: bool = True
    with_reached: bool = False
    with_attitude: bool = True
    dropouts: list[tuple[int, int]] = field(default_factory=list)  # (start_ns, end_ns) with no fixes
    degraded_holds: dict[int, str] = field(default_factory=dict)  # hold index -> fix_type during it
    hidden: list[tuple[int, int]] = field(default_factory=list)  # capture-time ranges with no marker
    corrupt_every: int = 0  # every n-th frame is cut in half
    omit_metadata_keys: tuple[str, ...] = ()
    altitude_datum: str | None = None
    site_origin: EnuOrigin | None = None
    seed: int = 3
    chunk_size: int = 256 * 1024
    renderer: str = "homography"  # or "sim": the simulator's exact ray-traced renderer (ArUco only)
    fix_type: str = "rtk_fixed"
    repeat_fixes: int = 1  # each fix sent this many times, evenly between fixes (a stream faster than the receiver)
    gnss_noise_tau_s: float = 0.0  # RTK noise correlation time (first-order Gauss-Markov); 0: white
    readout_s: float = 0.0  # rolling shutter: row v captured at the frame's time + v / height * readout_s
    exposure_s: float = 0.0  # motion blur: the frame averages the marker over this long
    with_leg_events: bool = True  # a "leg" event per waypoint-to-waypoint segment of Flight.legs
    gnss_latency_s: float = 0.0  # fixes stamped this late (arrival); declared as gnss.latency_s when > 0
    quantise_fixes: bool = False  # lat/lon to 1e-7 deg and height to mm, as MAVLink GPS_RAW_INT carries them
    with_gps_raw: bool = False  # /mavlink/GPS_RAW_INT beside each /gnss/fix, same stamp, time_usec = the fix's own time
    fix_bias: list[tuple[int, int, tuple[float, float, float]]] = field(default_factory=list)  # (start_ns, end_ns, ENU m): a false RTK fix
    keep_span: tuple[float, float] = (0.0, 1.0)  # the share of the flight's time recorded (0.25, 1.0): the first quarter missing
    attachments: dict[str, bytes] = field(default_factory=dict)  # e.g. {"mission.plan": mission_plan(...)}


def write_run(path: str | Path, camera: Camera, flight: Flight, look: MarkerLook, spec: RunSpec) -> dict:
    """Write a contract-following MCAP run of ``flight`` seen by ``camera``; returns truth for the tests.

    Returns
    -------
    dict with ``frame_capture_ns`` (F,), ``frame_stamp_ns`` (F,), ``marker_centre_enu`` per hold
    (list of (3,)), ``n_frames``, ``n_fixes``, ``n_corrupt``.
    """
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.Event_pb2 import Event
    from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
    from mcap.writer import CompressionType, Writer

    rng = np.random.default_rng(spec.seed)
    renderer = Renderer(camera=camera, flight=flight, look=look, dark=look.kind == "led")
    render = renderer.render
    if spec.renderer == "sim":
        render = _sim_render(camera, flight, look, spec.seed)
    t_start, t_end = int(flight.t_ns[0]), int(flight.t_ns[-1])
    records: list[tuple[int, str, bytes]] = []  # (log_time_ns, topic, data), sorted later

    # GNSS fixes
    n_fix = int((t_end - t_start) * 1e-9 * spec.gnss_hz)
    fix_t = t_start + np.round(np.arange(n_fix) / spec.gnss_hz * 1e9).astype(np.int64)
    keep = np.ones(n_fix, bool)
    for a, b in spec.dropouts:
        keep &= ~((fix_t >= a) & (fix_t < b))
    fix_t = fix_t[keep]
    pos, _ = flight.at(fix_t)
    fix_type = np.array([spec.fix_type] * len(fix_t), dtype=object)
    sigma = np.tile(np.array(spec.gnss_sigma_m, float), (len(fix_t), 1))
    for hold_index, kind in spec.degraded_holds.items():
        a, b, _ = flight.holds[hold_index]
        inside = (fix_t >= a - 500_000_000) & (fix_t < b + 500_000_000)
        fix_type[inside] = kind
        sigma[inside] *= 25.0  # a float or DGPS fix wanders by decimetres
    white = rng.normal(size=pos.shape)
    if spec.gnss_noise_tau_s > 0 and len(fix_t) > 1:
        # Multipath and atmosphere make RTK errors wander over seconds: AR(1) with the same std.
        a = np.exp(-np.diff(fix_t, prepend=fix_t[0]).astype(float) * 1e-9 / spec.gnss_noise_tau_s)
        for k in range(1, len(white)):
            white[k] = a[k] * white[k - 1] + np.sqrt(1.0 - a[k] ** 2) * white[k]
    noise = white * sigma
    for a, b, bias in spec.fix_bias:  # still reported as the fix type above: the receiver does not know
        noise[(fix_t >= a) & (fix_t < b)] += np.asarray(bias, float)
    geo = enu_to_geodetic(pos + noise, ORIGIN)
    if spec.quantise_fixes:
        geo = np.c_[np.round(geo[:, :2] * 1e7) / 1e7, np.round(geo[:, 2] * 1e3) / 1e3]
    fix_usec = (fix_t - t_start) // 1000 + 10_000_000  # boot time of each fix (10 s after boot at the start)
    if spec.repeat_fixes > 1:
        period = int(round(1e9 / spec.gnss_hz / spec.repeat_fixes))
        idx = np.repeat(np.arange(len(fix_t)), spec.repeat_fixes)
        fix_t = fix_t[idx] + np.tile(np.arange(spec.repeat_fixes) * period, len(geo))
        geo, sigma, fix_type, fix_usec = geo[idx], sigma[idx], fix_type[idx], fix_usec[idx]
    fix_t = fix_t + int(round(spec.gnss_latency_s * 1e9))
    for k, t in enumerate(fix_t):
        msg = LocationFix()
        _stamp(msg.timestamp, int(t))
        msg.frame_id = "gnss"
        msg.latitude, msg.longitude, msg.altitude = (float(v) for v in geo[k])
        msg.position_covariance.extend(np.diag(sigma[k] ** 2).ravel().tolist())
        msg.position_covariance_type = 2
        kv = msg.metadata.add()
        kv.key, kv.value = "fix_type", str(fix_type[k])
        records.append((int(t), "/gnss/fix", msg.SerializeToString()))
        if spec.with_gps_raw:
            raw = {
                "time_usec": int(fix_usec[k]), "fix_type": 6, "lat": int(round(geo[k, 0] * 1e7)), "lon": int(round(geo[k, 1] * 1e7)),
                "alt": int(round(geo[k, 2] * 1000)), "alt_ellipsoid": int(round(geo[k, 2] * 1000)), "_time_unix_ns": int(t),
            }
            records.append((int(t), "/mavlink/GPS_RAW_INT", json.dumps(raw).encode()))

    # Frames: captured at capture_t, stamped latency later.
    n_frames = int((t_end - t_start) * 1e-9 * spec.fps)
    capture = t_start + np.round(np.arange(n_frames) / spec.fps * 1e9).astype(np.int64)
    stamp = capture + int(round(spec.latency_s * 1e9))
    n_corrupt = 0
    marker_row_t = np.zeros(n_frames, np.int64)  # when the marker's row was captured
    for k in range(n_frames):
        visible = not any(a <= capture[k] < b for a, b in spec.hidden)
        t_row = int(capture[k])
        if spec.readout_s > 0:
            # The marker spans few rows: render it as it was when its centre row was read out.
            for _ in range(2):
                v = float(renderer.true_centre_px(np.array([t_row]))[0, 1])
                t_row = int(capture[k]) + int(round(np.clip(v, 0, camera.height - 1) / camera.height * spec.readout_s * 1e9))
        marker_row_t[k] = t_row
        if spec.exposure_s > 0 and visible:
            subs = [render(t_row + int(round(f * spec.exposure_s * 1e9)), visible=True).astype(np.float32) for f in (-0.5, -1 / 6, 1 / 6, 0.5)]
            image = np.clip(np.mean(subs, axis=0) + 0.5, 0, 255).astype(np.uint8)
        else:
            image = render(t_row, visible=visible)
        data = encode_jpeg(image, spec.jpeg_quality)
        if spec.corrupt_every and k % spec.corrupt_every == spec.corrupt_every - 1:
            data = data[: len(data) // 2]
            n_corrupt += 1
        msg = CompressedImage()
        _stamp(msg.timestamp, int(stamp[k]))
        msg.frame_id = "camera"
        msg.format = "jpeg"
        msg.data = data
        records.append((int(stamp[k]), "/camera/image", msg.SerializeToString()))

    # Hover events, MISSION_ITEM_REACHED (at the END of a hold), attitude.
    if spec.with_events:
        for a, b, seq in flight.holds:
            msg = Event()
            _stamp(msg.start_time, a)
            _stamp(msg.end_time, b)
            for key, value in (("type", "hover"), ("seq", str(seq)), ("hold_s", f"{(b - a) * 1e-9:.3f}")):
                kv = msg.metadata.add()
                kv.key, kv.value = key, value
            records.append((b, "/events", msg.SerializeToString()))
    if spec.with_events and spec.with_leg_events:
        for a, b, seq_from, seq_to in flight.legs:
            msg = Event()
            _stamp(msg.start_time, a)
            _stamp(msg.end_time, b)
            for key, value in (("type", "leg"), ("seq_from", str(seq_from)), ("seq_to", str(seq_to))):
                kv = msg.metadata.add()
                kv.key, kv.value = key, value
            records.append((b, "/events", msg.SerializeToString()))
    if spec.with_reached:
        for a, b, seq in flight.holds:
            fields = {"seq": int(seq), "_time_unix_ns": int(b)}
            records.append((b, "/mavlink/MISSION_ITEM_REACHED", json.dumps(fields).encode()))
    if spec.with_attitude:
        att_t = np.arange(t_start, t_end, 100_000_000, dtype=np.int64)
        _, rpy = flight.at(att_t)
        for k, t in enumerate(att_t):
            yaw = (rpy[k, 2] + np.pi) % (2 * np.pi) - np.pi
            fields = {
                "time_boot_ms": int((t - t_start) // 1_000_000), "roll": float(rpy[k, 0]), "pitch": float(rpy[k, 1]),
                "yaw": float(yaw), "rollspeed": 0.0, "pitchspeed": 0.0, "yawspeed": 0.0, "_time_unix_ns": int(t),
            }
            records.append((int(t), "/mavlink/ATTITUDE", json.dumps(fields).encode()))

    records.sort(key=lambda r: r[0])
    if spec.keep_span != (0.0, 1.0):
        a, b = (t_start + int(f * (t_end - t_start)) for f in spec.keep_span)
        records = [r for r in records if a <= r[0] <= b]
    metadata = {
        "format_version": "1",
        "camera.width": str(camera.width),
        "camera.height": str(camera.height),
        "marker.kind": look.kind,
        "marker.offset_frd_m": ",".join(f"{v:.4f}" for v in flight.offset_frd_m),
    }
    if look.kind == "aruco":
        metadata.update({"marker.dictionary": look.dictionary, "marker.id": str(look.marker_id), "marker.size_m": f"{look.size_m:.4f}"})
    if spec.declared_latency is not None:
        metadata["camera.latency_s"] = spec.declared_latency
    if spec.altitude_datum is not None:
        metadata["gnss.altitude_datum"] = spec.altitude_datum
    if spec.gnss_latency_s > 0:
        metadata["gnss.latency_s"] = repr(float(spec.gnss_latency_s))
    for key in spec.omit_metadata_keys:
        metadata.pop(key, None)

    with open(path, "wb") as stream:
        writer = Writer(stream, chunk_size=spec.chunk_size, compression=CompressionType.NONE)
        writer.start(profile="", library="dronecal-tests-contract-writer")
        schema_ids = {
            "foxglove.CompressedImage": writer.register_schema("foxglove.CompressedImage", "protobuf", _file_descriptor_set(CompressedImage)),
            "foxglove.LocationFix": writer.register_schema("foxglove.LocationFix", "protobuf", _file_descriptor_set(LocationFix)),
            "foxglove.Event": writer.register_schema("foxglove.Event", "protobuf", _file_descriptor_set(Event)),
        }
        channels: dict[str, int] = {
            "/camera/image": writer.register_channel("/camera/image", "protobuf", schema_ids["foxglove.CompressedImage"]),
            "/gnss/fix": writer.register_channel("/gnss/fix", "protobuf", schema_ids["foxglove.LocationFix"]),
        }
        if spec.with_events:
            channels["/events"] = writer.register_channel("/events", "protobuf", schema_ids["foxglove.Event"])
        for name in ("MISSION_ITEM_REACHED", "ATTITUDE", "GPS_RAW_INT"):
            topic = f"/mavlink/{name}"
            if any(r[1] == topic for r in records):
                sid = writer.register_schema(f"mavlink.{name}", "jsonschema", b'{"type": "object"}')
                channels[topic] = writer.register_channel(topic, "json", sid)
        writer.add_metadata("dronecal.run", metadata)
        for name, data in spec.attachments.items():
            writer.add_attachment(create_time=0, log_time=0, name=name, media_type="application/json", data=data)
        if spec.site_origin is not None:
            o = spec.site_origin
            writer.add_metadata("dronecal.site", {"origin_lat": repr(o.lat_deg), "origin_lon": repr(o.lon_deg), "origin_h": repr(o.h_m)})
        sequence: dict[int, int] = {}
        for t, topic, data in records:
            cid = channels[topic]
            sequence[cid] = sequence.get(cid, 0) + 1
            writer.add_message(channel_id=cid, log_time=int(t), data=data, publish_time=int(t), sequence=sequence[cid])
        writer.finish()

    centres = [flight.marker_centre(np.array([(a + b) // 2]))[0] for a, b, _ in flight.holds]
    return {
        "frame_capture_ns": capture,
        "frame_stamp_ns": stamp,
        "marker_row_capture_ns": marker_row_t,
        "marker_centre_enu": centres,
        "n_frames": n_frames,
        "n_fixes": len(fix_t),
        "n_corrupt": n_corrupt,
        "renderer": renderer,
    }


def _sim_render(camera: Camera, flight: Flight, look: MarkerLook, seed: int):
    """A render(t_ns, visible) function using the simulator's ray-traced renderer (sensor noise included)."""
    from dronecal_field.sim.render import FrameRenderer
    from dronecal_field.sim.scene import MarkerSpec as SimMarker
    from dronecal_field.sim.scene import VehiclePose

    sim = FrameRenderer(
        camera,
        SimMarker(dictionary=look.dictionary, marker_id=look.marker_id, size_m=look.size_m, offset_frd_m=tuple(flight.offset_frd_m)),
        noise_sigma_dn=2.0,
        seed=seed,
    )

    def render(t_ns: int, visible: bool = True) -> np.ndarray:
        if not visible:
            return sim.render(None)
        pos, rpy = flight.at(np.array([t_ns]))
        return sim.render(VehiclePose(antenna_enu_m=pos[0], roll_rad=float(rpy[0, 0]), pitch_rad=float(rpy[0, 1]), yaw_rad=float(rpy[0, 2])))

    return render


def mission_plan(flight: Flight, speed_mps: float, camera: Camera | None = None, hold_s: float | None = None) -> bytes:
    """The QGroundControl mission of ``flight`` as a planner would have written it: DO_CHANGE_SPEED ``speed_mps``,
    DO_SET_ROI at the camera, a NAV_WAYPOINT per waypoint with its planned hold (``hold_s``, else the holds of
    ``flight``; 0 for a fly-through)."""
    seqs = {seq: (b - a) * 1e-9 if hold_s is None else hold_s for a, b, seq in flight.holds}
    first = min([*seqs, *(leg[2] for leg in flight.legs)], default=4)
    items = [{"type": "SimpleItem", "command": 178, "doJumpId": first - 2, "params": [1, float(speed_mps), -1, 0, 0, 0, 0]}]
    if camera is not None:
        g = enu_to_geodetic(camera.pose.position_world[None], ORIGIN)[0]
        items.append({"type": "SimpleItem", "command": 201, "doJumpId": first - 1, "params": [0, 0, 0, 0, g[0], g[1], g[2] - ORIGIN.h_m]})
    for k, (g, wp) in enumerate(zip(enu_to_geodetic(flight.waypoints_enu, ORIGIN), flight.waypoints_enu)):
        items.append({"type": "SimpleItem", "command": 16, "doJumpId": first + k,
                      "params": [round(seqs.get(first + k, 0.0), 3), 0, 0, None, g[0], g[1], float(wp[2])]})
    return json.dumps({"fileType": "Plan", "version": 1, "mission": {"items": items, "cruiseSpeed": float(speed_mps)}}).encode()


def truncate(path: str | Path, fraction: float) -> Path:
    """Cut a file to ``fraction`` of its bytes in place (a recorder killed mid-write)."""
    path = Path(path)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    return path


def iter_detection_frames(renderer: Renderer, capture_ns: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """(capture_ns, grey image) for each time, for detector tests without a file."""
    for t in capture_ns:
        yield int(t), renderer.render(int(t))


# --------------------------------------------------------------------------
# Several cameras in one run (run-format.md, "Several cameras in one run")


@dataclass
class SiteCamera:
    """One camera of a several-camera run: its truth and how its frames are stamped.

    ``latency_s`` is the true lag of its stamps behind capture (its own clock offset to the GNSS stream);
    ``declared_latency`` what the writer puts in ``camera.<name>.latency_s`` (None: the key is left out);
    ``phase_s`` shifts its frame times against the other cameras' (cameras are not synchronised).
    """

    name: str
    camera: Camera
    latency_s: float = 0.0
    declared_latency: str | None = None
    clock: str | None = None
    phase_s: float = 0.0
    video: bool = False  # reserved: this writer writes JPEG frames (/cameras/<name>/image) only


def view_waypoints(
    camera: Camera,
    lateral_m: tuple[float, ...] = (-2.5, 0.0, 2.5),
    ahead_m: tuple[float, ...] = (6.0, 8.5, 11.0),
    up_m: tuple[float, ...] = (1.5, 3.5),
) -> np.ndarray:
    """(M, 3) ENU waypoints of ``grid_waypoints`` laid out in front of ``camera``: ``ahead_m`` along its
    horizontal viewing direction from its pole, ``lateral_m`` to its right, ``up_m`` above the ground."""
    forward = camera.pose.R_cam_from_world[2]
    f = np.array([forward[0], forward[1]]) / max(np.hypot(forward[0], forward[1]), 1e-9)
    right = np.array([f[1], -f[0]])
    pole = camera.pose.position_world[:2]
    grid = grid_waypoints(lateral_m, ahead_m, up_m)
    xy = pole + grid[:, :1] * right + grid[:, 1:2] * f
    return np.c_[xy, grid[:, 2]]


def site_waypoints(cameras: list[Camera], min_apart_m: float = 1.0, **grid) -> np.ndarray:
    """(M, 3) the union of each camera's ``view_waypoints`` (points closer than ``min_apart_m`` to one already
    taken are left out: they count for both), ordered per height by bearing from the cameras' centroid."""
    centre = np.mean([c.pose.position_world[:2] for c in cameras], axis=0)
    taken: list[np.ndarray] = []
    for cam in cameras:
        for p in view_waypoints(cam, **grid):
            if all(np.linalg.norm(p - q) >= min_apart_m for q in taken):
                taken.append(p)
    pts = np.array(taken)
    bearing = np.arctan2(pts[:, 0] - centre[0], pts[:, 1] - centre[1])
    dist = np.hypot(pts[:, 0] - centre[0], pts[:, 1] - centre[1])
    heights = sorted(set(np.round(pts[:, 2], 3)))
    out = []
    for k, z in enumerate(heights):
        idx = np.flatnonzero(np.isclose(pts[:, 2], z))
        idx = idx[np.lexsort((dist[idx], bearing[idx]))]
        out.append(pts[idx if k % 2 == 0 else idx[::-1]])
    return np.concatenate(out)


def facing_point(cameras: list[Camera]) -> Camera:
    """A stand-in camera at the cameras' mean position, for ``make_flight``: the drone's nose points there,
    so the marker faces every pole of a site (within the angle the poles subtend)."""
    c = cameras[0]
    return c.with_(pose=CameraPose.from_position(c.pose.R_cam_from_world, np.mean([k.pose.position_world for k in cameras], axis=0)))


def write_site_run(path: str | Path, cameras: list[SiteCamera], flight: Flight, look: MarkerLook, spec: RunSpec) -> dict:
    """Write a contract-following several-camera run: one ``/cameras/<name>/image`` topic per camera, metadata
    ``cameras`` and ``camera.<name>.width/height/latency_s/clock``, no ``/camera/...``, no ``camera.width``.

    The GNSS fixes, events and attitude are shared and written as :func:`write_run` writes them (``spec``'s
    fps, gnss_hz, gnss_sigma_m, gnss_noise_tau_s, jpeg_quality, with_events, with_attitude, site_origin,
    attachments, seed, chunk_size are used; the other messy-data flags are not).

    Returns
    -------
    dict with ``frames`` {name: (F,) capture ns}, ``stamps`` {name: (F,) stamp ns}, ``n_fixes``,
    ``truth`` {name: Camera}.
    """
    from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
    from foxglove_schemas_protobuf.Event_pb2 import Event
    from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
    from mcap.writer import CompressionType, Writer

    names = [c.name for c in cameras]
    assert len(set(names)) == len(names), "camera names must differ"
    rng = np.random.default_rng(spec.seed)
    t_start, t_end = int(flight.t_ns[0]), int(flight.t_ns[-1])
    records: list[tuple[int, str, bytes]] = []

    n_fix = int((t_end - t_start) * 1e-9 * spec.gnss_hz)
    fix_t = t_start + np.round(np.arange(n_fix) / spec.gnss_hz * 1e9).astype(np.int64)
    pos, _ = flight.at(fix_t)
    sigma = np.array(spec.gnss_sigma_m, float)
    white = rng.normal(size=pos.shape)
    if spec.gnss_noise_tau_s > 0 and len(fix_t) > 1:
        a = np.exp(-np.diff(fix_t, prepend=fix_t[0]).astype(float) * 1e-9 / spec.gnss_noise_tau_s)
        for k in range(1, len(white)):
            white[k] = a[k] * white[k - 1] + np.sqrt(1.0 - a[k] ** 2) * white[k]
    geo = enu_to_geodetic(pos + white * sigma, ORIGIN)
    for k, t in enumerate(fix_t):
        msg = LocationFix()
        _stamp(msg.timestamp, int(t))
        msg.frame_id = "gnss"
        msg.latitude, msg.longitude, msg.altitude = (float(v) for v in geo[k])
        msg.position_covariance.extend(np.diag(sigma**2).ravel().tolist())
        msg.position_covariance_type = 2
        kv = msg.metadata.add()
        kv.key, kv.value = "fix_type", spec.fix_type
        records.append((int(t), "/gnss/fix", msg.SerializeToString()))

    frames, stamps = {}, {}
    for sc in cameras:
        renderer = Renderer(camera=sc.camera, flight=flight, look=look)
        n_frames = int((t_end - t_start) * 1e-9 * spec.fps)
        capture = t_start + np.round((np.arange(n_frames) / spec.fps + sc.phase_s) * 1e9).astype(np.int64)
        capture = capture[capture <= t_end]
        stamp = capture + int(round(sc.latency_s * 1e9))
        for k in range(len(capture)):
            msg = CompressedImage()
            _stamp(msg.timestamp, int(stamp[k]))
            msg.frame_id = sc.name
            msg.format = "jpeg"
            msg.data = encode_jpeg(renderer.render(int(capture[k])), spec.jpeg_quality)
            records.append((int(stamp[k]), f"/cameras/{sc.name}/image", msg.SerializeToString()))
        frames[sc.name], stamps[sc.name] = capture, stamp

    if spec.with_events:
        for a, b, seq in flight.holds:
            msg = Event()
            _stamp(msg.start_time, a)
            _stamp(msg.end_time, b)
            for key, value in (("type", "hover"), ("seq", str(seq)), ("hold_s", f"{(b - a) * 1e-9:.3f}")):
                kv = msg.metadata.add()
                kv.key, kv.value = key, value
            records.append((b, "/events", msg.SerializeToString()))
    if spec.with_attitude:
        att_t = np.arange(t_start, t_end, 100_000_000, dtype=np.int64)
        _, rpy = flight.at(att_t)
        for k, t in enumerate(att_t):
            fields = {"time_boot_ms": int((t - t_start) // 1_000_000), "roll": float(rpy[k, 0]), "pitch": float(rpy[k, 1]),
                      "yaw": float((rpy[k, 2] + np.pi) % (2 * np.pi) - np.pi), "_time_unix_ns": int(t)}
            records.append((int(t), "/mavlink/ATTITUDE", json.dumps(fields).encode()))
    records.sort(key=lambda r: r[0])

    metadata = {
        "format_version": "1",
        "cameras": ",".join(names),
        "marker.kind": look.kind,
        "marker.offset_frd_m": ",".join(f"{v:.4f}" for v in flight.offset_frd_m),
        "marker.dictionary": look.dictionary, "marker.id": str(look.marker_id), "marker.size_m": f"{look.size_m:.4f}",
    }
    for sc in cameras:
        metadata[f"camera.{sc.name}.width"] = str(sc.camera.width)
        metadata[f"camera.{sc.name}.height"] = str(sc.camera.height)
        if sc.declared_latency is not None:
            metadata[f"camera.{sc.name}.latency_s"] = sc.declared_latency
        if sc.clock is not None:
            metadata[f"camera.{sc.name}.clock"] = sc.clock
    for key in spec.omit_metadata_keys:
        metadata.pop(key, None)

    with open(path, "wb") as stream:
        writer = Writer(stream, chunk_size=spec.chunk_size, compression=CompressionType.NONE)
        writer.start(profile="", library="dronecal-tests-contract-writer")
        image_schema = writer.register_schema("foxglove.CompressedImage", "protobuf", _file_descriptor_set(CompressedImage))
        channels = {f"/cameras/{n}/image": writer.register_channel(f"/cameras/{n}/image", "protobuf", image_schema) for n in names}
        channels["/gnss/fix"] = writer.register_channel(
            "/gnss/fix", "protobuf", writer.register_schema("foxglove.LocationFix", "protobuf", _file_descriptor_set(LocationFix)))
        if spec.with_events:
            channels["/events"] = writer.register_channel(
                "/events", "protobuf", writer.register_schema("foxglove.Event", "protobuf", _file_descriptor_set(Event)))
        if spec.with_attitude:
            sid = writer.register_schema("mavlink.ATTITUDE", "jsonschema", b'{"type": "object"}')
            channels["/mavlink/ATTITUDE"] = writer.register_channel("/mavlink/ATTITUDE", "json", sid)
        writer.add_metadata("dronecal.run", metadata)
        for name, data in spec.attachments.items():
            writer.add_attachment(create_time=0, log_time=0, name=name, media_type="application/json", data=data)
        if spec.site_origin is not None:
            o = spec.site_origin
            writer.add_metadata("dronecal.site", {"origin_lat": repr(o.lat_deg), "origin_lon": repr(o.lon_deg), "origin_h": repr(o.h_m)})
        sequence: dict[int, int] = {}
        for t, topic, data in records:
            cid = channels[topic]
            sequence[cid] = sequence.get(cid, 0) + 1
            writer.add_message(channel_id=cid, log_time=int(t), data=data, publish_time=int(t), sequence=sequence[cid])
        writer.finish()
    return {"frames": frames, "stamps": stamps, "n_fixes": len(fix_t), "truth": {sc.name: sc.camera for sc in cameras}}
