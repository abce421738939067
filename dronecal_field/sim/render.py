"""Render what the simulated pole camera sees: background, drone body, ArUco marker, noise.

Pure numerics, no I/O. The image is formed EXACTLY through the true camera
model, distortion included: every pixel of the marker's bounding box is cast
back into the scene as a ray (``core.camera.pixel_rays_batch``, which inverts
the distortion), the ray meets the marker plane, and the marker texture is
looked up there. Each pixel is supersampled (S x S rays, default 3 x 3), so
edges are anti-aliased and the corners the detector finds sit where the model
projects them, to a small fraction of a pixel.

Speed: the inverse distortion is solved once per camera for every pixel centre
(``make_ray_map``, about 2 s for 1280 x 960); a sub-pixel ray is that pixel's
ray plus the map's first-order Taylor step (the map's local Jacobian times the
sub-pixel offset), whose error is ~1e-5 px for ordinary lenses. Per frame only
the marker's bounding box is traced, on top of a cached background, and the
Gaussian noise comes from a pre-drawn field at a random offset, so a frame
costs a few milliseconds plus the traced area.

A streaming camera (``FrameRenderer.render_in_place``) goes further: the
background is static, so it is made and noised once into a frame buffer, and
each frame only puts back the previous frame's box and draws the new one
(fresh noise inside it): a 4K frame costs its traced box, not 25 MB of
copies and noise (40-60 ms a 4K frame here). The box's pixels are the same
computation as ``render``'s; only the background's noise is frozen.

Colours are OpenCV's BGR, 8 bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecal_field.core.camera import Camera, pixel_rays_batch, project_batch
from dronecal_field.errors import InputError
from dronecal_field.sim.scene import MarkerSpec, VehiclePose, marker_frame_world

# Grey levels of the printed board and the body. White stays well below 255 so
# noise is not clipped on it (clipping would bias the edges).
MARKER_WHITE_DN = 215.0
MARKER_BLACK_DN = 30.0
BOARD_BACK_DN = 150.0
BODY_DN = 45.0
# The drone body seen from the front: an ellipse in the body's right/down plane
# through the antenna, (half-width, half-height) metres.
BODY_HALF_AXES_M = (0.5, 0.12)


@dataclass(frozen=True, eq=False)
class RayMap:
    """Undistorted normalised coordinates of every pixel centre, and their local Jacobian.

    A ray in the camera frame through pixel (u, v) is (x, y, 1); for a
    sub-pixel offset (du, dv): x + dx_du du + dx_dv dv, y + dy_du du + dy_dv dv.
    All arrays are (H, W).
    """

    x: np.ndarray  # (H, W) float64
    y: np.ndarray  # (H, W) float64
    dx_du: np.ndarray  # (H, W) float32, per pixel
    dx_dv: np.ndarray
    dy_du: np.ndarray
    dy_dv: np.ndarray


def make_ray_map(camera: Camera, rows_per_chunk: int = 96) -> RayMap:
    """Cast every pixel centre of ``camera`` through the inverse distortion, once.

    Parameters
    ----------
    camera : the true camera; only intrinsics and distortion matter here.
    rows_per_chunk : image rows solved per call, to bound memory.

    Returns
    -------
    RayMap with (H, W) arrays.
    """
    W, H = camera.width, camera.height
    intr = camera.intrinsics.as_array()[None]
    dist = camera.distortion.as_array()[None]
    x = np.empty((H, W))
    y = np.empty((H, W))
    u = np.arange(W, dtype=float)
    for r0 in range(0, H, rows_per_chunk):
        r1 = min(H, r0 + rows_per_chunk)
        uu, vv = np.meshgrid(u, np.arange(r0, r1, dtype=float))
        uv = np.stack([uu.ravel(), vv.ravel()], -1)[None]
        d = pixel_rays_batch(intr, dist, np.eye(3)[None], uv)[0]
        x[r0:r1] = (d[:, 0] / d[:, 2]).reshape(r1 - r0, W)
        y[r0:r1] = (d[:, 1] / d[:, 2]).reshape(r1 - r0, W)
    # Central differences of a smooth map over one pixel: the error is the
    # map's third derivative / 6, ~1e-9 of a pixel for real lenses.
    edge = 2 if min(H, W) >= 3 else 1
    dx_dv, dx_du = np.gradient(x, edge_order=edge)
    dy_dv, dy_du = np.gradient(y, edge_order=edge)
    f32 = np.float32
    return RayMap(x=x, y=y, dx_du=dx_du.astype(f32), dx_dv=dx_dv.astype(f32), dy_du=dy_du.astype(f32), dy_dv=dy_dv.astype(f32))


def marker_board_image(marker: MarkerSpec) -> np.ndarray:
    """The printed board at one pixel per marker cell: black square plus white quiet zone.

    Returns
    -------
    (n, n) uint8, 0 = black, 255 = white; n = bits + 2 (black border) + 2 * quiet_zone_bits.
    """
    import cv2

    name = marker.dictionary.upper()
    code = getattr(cv2.aruco, name, None) if name.startswith("DICT_") else None
    if not isinstance(code, int):
        raise InputError(f"unknown ArUco dictionary {marker.dictionary!r}: use an OpenCV name such as DICT_4X4_50")
    dictionary = cv2.aruco.getPredefinedDictionary(code)
    n_markers = dictionary.bytesList.shape[0]
    if not 0 <= marker.marker_id < n_markers:
        raise InputError(f"marker id {marker.marker_id} is not in {name} (ids 0..{n_markers - 1}): pick one in range")
    black = dictionary.markerSize + 2
    img = cv2.aruco.generateImageMarker(dictionary, int(marker.marker_id), black, borderBits=1)
    q = int(marker.quiet_zone_bits)
    return np.pad(img, q, constant_values=255)


def make_background(camera: Camera, seed: int = 0, rays: RayMap | None = None) -> np.ndarray:
    """A plausible static scene for ``camera``: sky above the horizon, textured ground below.

    The ground is the plane z = 0 of the ENU world (the pole's foot); the
    horizon and the ground texture come from the same rays as the marker, so
    the background is consistent with the camera model. The texture is
    band-limited per pixel (octaves finer than the pixel footprint fade out)
    so it does not alias into false corners.

    Parameters
    ----------
    camera : the true camera (world frame ENU, metres).
    seed : texture seed.
    rays : the camera's RayMap, if already made.

    Returns
    -------
    (H, W, 3) uint8 BGR.
    """
    import cv2

    rays = rays or make_ray_map(camera)
    rng = np.random.default_rng(seed)
    R = np.asarray(camera.pose.R_cam_from_world, float)
    centre = camera.pose.position_world
    # World direction of each pixel ray (not unit): R.T @ (x, y, 1).
    dx = R[0, 0] * rays.x + R[1, 0] * rays.y + R[2, 0]
    dy = R[0, 1] * rays.x + R[1, 1] * rays.y + R[2, 1]
    dz = R[0, 2] * rays.x + R[1, 2] * rays.y + R[2, 2]
    norm = np.sqrt(dx * dx + dy * dy + dz * dz)
    sin_elev = dz / norm

    # Sky: pale at the horizon, deeper blue towards the zenith.
    horizon_bgr = np.array([230.0, 212.0, 190.0])
    zenith_bgr = np.array([205.0, 150.0, 95.0])
    s = np.clip(sin_elev, 0.0, 1.0) ** 0.6
    img = horizon_bgr * (1.0 - s[..., None]) + zenith_bgr * s[..., None]

    ground = dz < -1e-9
    height = max(float(centre[2]), 0.05)  # a camera below ground still sees a ground
    dist = np.where(ground, height / np.where(ground, -dz, 1.0), 0.0)  # ray parameter to z = 0
    ge = (centre[0] + dist * dx).astype(np.float32)
    gn = (centre[1] + dist * dy).astype(np.float32)
    # Ground metres covered by one pixel: range / focal, stretched by the grazing angle.
    range_m = dist * norm
    footprint = np.maximum(range_m / camera.intrinsics.fx / np.maximum(-sin_elev, 0.02), 1e-6)

    lattice = 256
    tex = np.zeros(ground.shape, np.float32)
    soil = np.zeros(ground.shape, np.float32)
    for wavelength_m, amp in ((0.08, 0.35), (0.3, 0.45), (1.2, 0.6), (5.0, 0.7), (20.0, 0.8)):
        grid = rng.standard_normal((lattice, lattice)).astype(np.float32)
        mx = np.mod(ge / wavelength_m, lattice).astype(np.float32)
        my = np.mod(gn / wavelength_m, lattice).astype(np.float32)
        octave = cv2.remap(grid, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        # Fade an octave out as its wavelength approaches 3 pixel footprints.
        weight = np.clip(wavelength_m / (3.0 * footprint) - 1.0, 0.0, 1.0).astype(np.float32)
        tex += amp * weight * octave
        if wavelength_m >= 5.0:
            soil += weight * octave
    grass = np.array([70.0, 125.0, 95.0])
    dirt = np.array([95.0, 120.0, 140.0])
    mix = np.clip(0.5 + 0.35 * soil, 0.0, 1.0)[..., None]
    ground_bgr = grass * (1.0 - mix) + dirt * mix
    ground_bgr = ground_bgr * (1.0 + 0.25 * tex[..., None])
    # Aerial perspective, capped so the horizon stays visible as an edge.
    haze = (0.7 * (1.0 - np.exp(-range_m / 400.0)))[..., None]
    ground_bgr = ground_bgr * (1.0 - haze) + horizon_bgr * haze
    img = np.where(ground[..., None], ground_bgr, img)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


@dataclass(frozen=True, eq=False)
class NoiseField:
    """Pre-drawn Gaussian noise, split into its positive and negative parts for saturating adds."""

    positive: np.ndarray  # (H + pad, W + pad, 3) uint8
    negative: np.ndarray  # (H + pad, W + pad, 3) uint8
    sigma_dn: float


def make_noise_field(width: int, height: int, sigma_dn: float, seed: int = 0, pad: int = 61) -> NoiseField:
    """Gaussian noise of ``sigma_dn`` grey levels, larger than the image by ``pad`` so frames take random windows."""
    rng = np.random.default_rng(seed)
    n = rng.standard_normal((height + pad, width + pad, 3), dtype=np.float32) * np.float32(sigma_dn)
    n = np.rint(n)
    return NoiseField(
        positive=np.clip(n, 0, 255).astype(np.uint8),
        negative=np.clip(-n, 0, 255).astype(np.uint8),
        sigma_dn=float(sigma_dn),
    )


def add_noise(image: np.ndarray, noise_sigma_dn: float, rng: np.random.Generator, noise_field: NoiseField | None = None) -> np.ndarray:
    """``image`` (H, W, 3) uint8 plus Gaussian noise of ``noise_sigma_dn`` grey levels, saturated to 0..255.

    With a ``noise_field`` of the same sigma the noise is a random window of it
    (about 1 ms per frame); otherwise it is drawn afresh from ``rng``.
    """
    import cv2

    if noise_sigma_dn <= 0:
        return image
    H, W = image.shape[:2]
    if noise_field is not None and noise_field.sigma_dn == noise_sigma_dn and noise_field.positive.shape[0] >= H and noise_field.positive.shape[1] >= W:
        oy = int(rng.integers(0, noise_field.positive.shape[0] - H + 1))
        ox = int(rng.integers(0, noise_field.positive.shape[1] - W + 1))
        out = cv2.add(image, noise_field.positive[oy : oy + H, ox : ox + W])
        return cv2.subtract(out, noise_field.negative[oy : oy + H, ox : ox + W])
    noisy = image.astype(np.float32) + rng.standard_normal(image.shape, dtype=np.float32) * np.float32(noise_sigma_dn)
    return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)


def add_patch_noise(patch: np.ndarray, noise_sigma_dn: float, rng: np.random.Generator, noise_field: NoiseField | None = None) -> np.ndarray:
    """``patch`` (h, w, 3) uint8 plus Gaussian noise: a random window of ``noise_field`` when it fits, else fresh draws."""
    import cv2

    if noise_sigma_dn <= 0:
        return patch
    h, w = patch.shape[:2]
    if noise_field is not None and noise_field.sigma_dn == noise_sigma_dn and noise_field.positive.shape[0] >= h and noise_field.positive.shape[1] >= w:
        oy = int(rng.integers(0, noise_field.positive.shape[0] - h + 1))
        ox = int(rng.integers(0, noise_field.positive.shape[1] - w + 1))
        out = cv2.add(patch, noise_field.positive[oy : oy + h, ox : ox + w])
        return cv2.subtract(out, noise_field.negative[oy : oy + h, ox : ox + w])
    return add_noise(patch, noise_sigma_dn, rng)


def subpixel_offsets(supersample: int) -> np.ndarray:
    """(S*S, 2) sample offsets (du, dv) in pixels, within (-0.5, 0.5), for S x S supersampling.

    A multi-jittered (N-rooks) pattern rather than a square grid: each of the
    S*S samples has its own column AND its own row, so an edge along either
    image axis is resolved to 1/S^2 of a pixel instead of 1/S, while every
    S x S stratum still holds one sample.
    """
    S = int(supersample)
    if S < 1:
        raise InputError(f"supersample {S} must be at least 1")
    n = S * S
    i, j = np.meshgrid(np.arange(S), np.arange(S), indexing="ij")
    u_index = (i * S + j).ravel()
    v_index = (j * S + i).ravel()
    return np.stack([(u_index + 0.5) / n - 0.5, (v_index + 0.5) / n - 0.5], -1)


def _outline_world(vehicle: VehiclePose, marker: MarkerSpec, board_half_m: float) -> np.ndarray:
    """(M, 3) ENU points on the edges of the board and the body ellipse, for the bounding box."""
    centre, right, down, _ = marker_frame_world(vehicle.antenna_enu_m, vehicle.roll_rad, vehicle.pitch_rad, vehicle.yaw_rad, marker.offset_frd_m)
    s = np.linspace(-1.0, 1.0, 17)
    one = np.ones_like(s)
    edges = np.concatenate([np.stack([s, -one], -1), np.stack([one, s], -1), np.stack([s, one], -1), np.stack([-one, s], -1)])
    board = centre + board_half_m * (edges[:, :1] * right + edges[:, 1:] * down)
    a = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)
    rx, ry = BODY_HALF_AXES_M
    body = np.asarray(vehicle.antenna_enu_m, float) + (rx * np.cos(a))[:, None] * right + (ry * np.sin(a))[:, None] * down
    return np.concatenate([board, body])


@dataclass(frozen=True, eq=False)
class _DronePlanes:
    """The marker board and the body ellipse in the camera frame, for tracing rays (x, y, 1) against them."""

    n: np.ndarray  # (3,) the planes' shared normal
    r: np.ndarray  # (3,) board/body right axis
    d: np.ndarray  # (3,) board/body down axis
    n_dot_c: float  # board centre c, body centre b: dot products with the axes
    r_dot_c: float
    d_dot_c: float
    n_dot_b: float
    r_dot_b: float
    d_dot_b: float
    inv_2half: float  # 1 / board side, 1/m
    n_cells: int


# Labels of a traced sample besides a board cell's index (0..n_cells^2 - 1).
_BODY, _MISS = -1, -2
# The box is traced adaptively when the board's cells are at least this many pixels wide.
ADAPTIVE_MIN_CELL_PX = 3.0


def _trace_labels(xs: np.ndarray, ys: np.ndarray, p: _DronePlanes) -> np.ndarray:
    """What each ray (xs, ys, 1) (any shape) hits first: a board cell's index, ``_BODY`` or ``_MISS`` (int32, same shape)."""
    n, r, d = p.n, p.r, p.d
    rx, ry = BODY_HALF_AXES_M
    denom = xs * n[0] + ys * n[1] + n[2]
    ok = np.abs(denom) > 1e-12
    inv = np.where(ok, 1.0 / np.where(ok, denom, 1.0), 0.0)
    ray_r = xs * r[0] + ys * r[1] + r[2]
    ray_d = xs * d[0] + ys * d[1] + d[2]
    s_m = p.n_dot_c * inv  # ray length (in z units) to the marker plane
    a = (s_m * ray_r - p.r_dot_c) * p.inv_2half + 0.5
    bb = (s_m * ray_d - p.d_dot_c) * p.inv_2half + 0.5
    on_board = ok & (s_m > 0) & (a >= 0) & (a < 1) & (bb >= 0) & (bb < 1)
    s_b = p.n_dot_b * inv
    e1 = (s_b * ray_r - p.r_dot_b) / rx
    e2 = (s_b * ray_d - p.d_dot_b) / ry
    on_body = ok & (s_b > 0) & (e1 * e1 + e2 * e2 <= 1.0)
    board_wins = on_board & (~on_body | (s_m <= s_b))
    nc = p.n_cells
    col = np.clip((a * nc).astype(np.int32), 0, nc - 1)
    row = np.clip((bb * nc).astype(np.int32), 0, nc - 1)
    return np.where(board_wins, row * nc + col, np.where(on_body, _BODY, _MISS)).astype(np.int32)


def _supersample(x0: np.ndarray, y0: np.ndarray, jac: tuple[np.ndarray, ...], p: _DronePlanes, board_values: np.ndarray,
                 supersample: int) -> tuple[np.ndarray, np.ndarray]:
    """Summed grey level and hit count of S x S rays per pixel, each times 1/S^2: (value, coverage), float32, x0's shape."""
    jxu, jxv, jyu, jyv = jac
    value = np.zeros(x0.shape, np.float32)
    coverage = np.zeros(x0.shape, np.float32)
    for du, dv in subpixel_offsets(supersample):
        label = _trace_labels(x0 + (jxu * du + jxv * dv), y0 + (jyu * du + jyv * dv), p)
        sample = np.where(label >= 0, board_values[np.maximum(label, 0)], np.float32(BODY_DN))
        hit = label != _MISS
        value += np.where(hit, sample, np.float32(0.0))
        coverage += hit
    scale = np.float32(1.0 / supersample**2)
    return value * scale, coverage * scale


def _mixed_pixels(x0: np.ndarray, y0: np.ndarray, jac: tuple[np.ndarray, ...], p: _DronePlanes) -> tuple[np.ndarray, np.ndarray]:
    """Which pixels of the box need supersampling, and the label of the others.

    The rays through every pixel corner are traced once; a pixel whose four
    corners hit the same thing (one board cell, the body, nothing) is that
    thing throughout, unless an edge just grazes it or a region's vertex pokes
    into it between its corners: any such edge goes on to split the corners
    of a neighbouring pixel (cells and the body are >= 3 px wide here), so the
    mixed pixels grown by one pixel cover those too.

    Returns
    -------
    mixed : (h, w) bool; label : (h, w) int32, valid where not mixed.
    """
    import cv2

    jxu, jxv, jyu, jyv = jac
    h, w = x0.shape
    # Corner (i, j) is the top-left corner of pixel (i, j); the last row and column come from the last pixels' far corners.
    cx = np.empty((h + 1, w + 1))
    cy = np.empty((h + 1, w + 1))
    cx[:h, :w] = x0 - 0.5 * (jxu + jxv)
    cy[:h, :w] = y0 - 0.5 * (jyu + jyv)
    cx[h, :w] = x0[-1] + 0.5 * (jxv[-1] - jxu[-1])
    cy[h, :w] = y0[-1] + 0.5 * (jyv[-1] - jyu[-1])
    cx[:h, w] = x0[:, -1] + 0.5 * (jxu[:, -1] - jxv[:, -1])
    cy[:h, w] = y0[:, -1] + 0.5 * (jyu[:, -1] - jyv[:, -1])
    cx[h, w] = x0[-1, -1] + 0.5 * (jxu[-1, -1] + jxv[-1, -1])
    cy[h, w] = y0[-1, -1] + 0.5 * (jyu[-1, -1] + jyv[-1, -1])
    lab = _trace_labels(cx, cy, p)
    tl = lab[:-1, :-1]
    uniform = (tl == lab[1:, :-1]) & (tl == lab[:-1, 1:]) & (tl == lab[1:, 1:])
    mixed = cv2.dilate((~uniform).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    return mixed, tl


def render_marker_layer(
    camera: Camera,
    vehicle: VehiclePose,
    marker: MarkerSpec,
    board: np.ndarray,
    rays: RayMap,
    supersample: int = 3,
    adaptive: bool = True,
) -> tuple[tuple[int, int, int, int], np.ndarray, np.ndarray] | None:
    """Trace the drone body and the marker board through every pixel of their bounding box.

    Parameters
    ----------
    camera : the true camera (world ENU).
    vehicle : antenna position and attitude.
    marker : the marker spec; ``board`` its image from ``marker_board_image``.
    rays : the camera's RayMap.
    supersample : S; S x S rays per pixel.
    adaptive : supersample only the pixels an edge crosses (``_mixed_pixels``)
        when the board's cells are >= ``ADAPTIVE_MIN_CELL_PX`` wide; the others
        take the one thing their corners all hit. Same values as tracing every
        pixel (the uniform pixels' sums are exact), 5-10x faster on a near drone.

    Returns
    -------
    None when nothing is in view, else ``((u0, v0, u1, v1), value, coverage)``:
    the box (half-open pixel ranges), the summed grey level of the samples that
    hit the drone, divided by S^2, (h, w) float32, and the fraction of samples
    that hit it, (h, w) float32.
    """
    W, H = camera.width, camera.height
    R = np.asarray(camera.pose.R_cam_from_world, float)
    t = np.asarray(camera.pose.t_cam_from_world, float)
    n_cells = board.shape[0]
    n_black = n_cells - 2 * marker.quiet_zone_bits
    board_half_m = 0.5 * marker.size_m * n_cells / n_black

    # Bounding box from the outline, in pixels.
    outline_cam = _outline_world(vehicle, marker, board_half_m) @ R.T + t
    if np.all(outline_cam[:, 2] <= 1e-3):
        return None
    cell_px = 0.0  # narrowest board cell, pixels (0: unknown)
    if np.any(outline_cam[:, 2] <= 1e-3):
        u0, v0, u1, v1 = 0, 0, W, H  # partly behind the camera: trace everything
    else:
        uv = project_batch(camera.intrinsics.as_array()[None], camera.distortion.as_array()[None], np.eye(3)[None], np.zeros((1, 3)), outline_cam[None])[0]
        margin = 3
        u0 = max(0, int(np.floor(uv[:, 0].min())) - margin)
        v0 = max(0, int(np.floor(uv[:, 1].min())) - margin)
        u1 = min(W, int(np.ceil(uv[:, 0].max())) + margin + 1)
        v1 = min(H, int(np.ceil(uv[:, 1].max())) + margin + 1)
        # The outline's first 4 x 17 points walk the board's four sides.
        sides = uv[: 4 * 17].reshape(4, 17, 2)
        cell_px = float(np.linalg.norm(np.diff(sides, axis=1), axis=-1).sum(axis=1).min()) / n_cells
    if u1 <= u0 or v1 <= v0:
        return None

    centre_w, right_w, down_w, normal_w = marker_frame_world(vehicle.antenna_enu_m, vehicle.roll_rad, vehicle.pitch_rad, vehicle.yaw_rad, marker.offset_frd_m)
    c = R @ centre_w + t  # marker centre, camera frame
    b = R @ np.asarray(vehicle.antenna_enu_m, float) + t  # body centre, camera frame
    r, d, n = R @ right_w, R @ down_w, R @ normal_w
    front = float(-n @ c) > 0.0  # the camera (origin) is on the printed side
    planes = _DronePlanes(n=n, r=r, d=d, n_dot_c=float(n @ c), r_dot_c=float(r @ c), d_dot_c=float(d @ c),
                          n_dot_b=float(n @ b), r_dot_b=float(r @ b), d_dot_b=float(d @ b),
                          inv_2half=1.0 / (2.0 * board_half_m), n_cells=n_cells)
    board_values = np.where(board.ravel() > 127, MARKER_WHITE_DN, MARKER_BLACK_DN).astype(np.float32)
    if not front:
        board_values[:] = BOARD_BACK_DN

    sl = (slice(v0, v1), slice(u0, u1))
    x0, y0 = rays.x[sl], rays.y[sl]
    jac = (rays.dx_du[sl], rays.dx_dv[sl], rays.dy_du[sl], rays.dy_dv[sl])
    if not (adaptive and cell_px >= ADAPTIVE_MIN_CELL_PX and supersample > 1):
        value, coverage = _supersample(x0, y0, jac, planes, board_values, supersample)
        return (u0, v0, u1, v1), value, coverage
    mixed, label = _mixed_pixels(x0, y0, jac, planes)
    # Uniform pixels: S^2 equal samples summed (exact in float32) times 1/S^2, as _supersample makes them.
    s2 = np.float32(supersample**2)
    scale = np.float32(1.0 / supersample**2)
    full_value = np.concatenate([board_values, [np.float32(BODY_DN), np.float32(0.0)]]) * s2 * scale
    full_cover = np.float32(s2 * scale)
    # _BODY and _MISS index the two values appended after the board's.
    nb = board_values.size
    value = full_value[np.where(label >= 0, label, np.where(label == _BODY, nb, nb + 1))].astype(np.float32)
    coverage = np.where(label == _MISS, np.float32(0.0), full_cover).astype(np.float32)
    iy, ix = np.nonzero(mixed)
    if iy.size:
        mv, mc = _supersample(x0[iy, ix], y0[iy, ix], tuple(j[iy, ix] for j in jac), planes, board_values, supersample)
        value[iy, ix] = mv
        coverage[iy, ix] = mc
    return (u0, v0, u1, v1), value, coverage


def composite_patch(background: np.ndarray, layer: tuple[tuple[int, int, int, int], np.ndarray, np.ndarray]) -> np.ndarray:
    """The layer's box of ``background`` (H, W, 3) uint8 with the traced layer blended in by coverage: (h, w, 3) uint8."""
    (u0, v0, u1, v1), value, coverage = layer
    patch = background[v0:v1, u0:u1].astype(np.float32)
    patch = patch * (1.0 - coverage)[..., None] + value[..., None]
    return np.clip(np.rint(patch), 0, 255).astype(np.uint8)


def composite(background: np.ndarray, layer: tuple[tuple[int, int, int, int], np.ndarray, np.ndarray] | None) -> np.ndarray:
    """A copy of ``background`` (H, W, 3) uint8 with the traced layer blended in by coverage."""
    img = background.copy()
    if layer is None:
        return img
    u0, v0, u1, v1 = layer[0]
    img[v0:v1, u0:u1] = composite_patch(background, layer)
    return img


def render_frame(
    camera: Camera,
    background: np.ndarray,
    vehicle: VehiclePose | None,
    marker: MarkerSpec,
    noise_sigma_dn: float,
    rng: np.random.Generator,
    *,
    marker_image: np.ndarray | None = None,
    rays: RayMap | None = None,
    noise_field: NoiseField | None = None,
    supersample: int = 3,
) -> np.ndarray:
    """One camera frame: the drone (body + marker) over ``background``, plus Gaussian noise.

    Parameters
    ----------
    camera : the true camera (world ENU, metres).
    background : (H, W, 3) uint8 from ``make_background``.
    vehicle : antenna position and attitude, or None for an empty scene.
    marker : the marker mounted on the drone.
    noise_sigma_dn : standard deviation of the pixel noise, grey levels.
    rng : draws the noise.
    marker_image : ``marker_board_image(marker)``, if already made.
    rays : ``make_ray_map(camera)``, if already made (it is the slow part: reuse it).
    noise_field : ``make_noise_field(...)`` for the fast noise path.
    supersample : S x S rays per pixel.

    Returns
    -------
    (H, W, 3) uint8 BGR.
    """
    if background.shape[:2] != (camera.height, camera.width):
        raise InputError(f"background is {background.shape[1]}x{background.shape[0]} but the camera is {camera.width}x{camera.height}: remake it")
    layer = None
    if vehicle is not None:
        board = marker_image if marker_image is not None else marker_board_image(marker)
        layer = render_marker_layer(camera, vehicle, marker, board, rays or make_ray_map(camera), supersample)
    return add_noise(composite(background, layer), noise_sigma_dn, rng, noise_field)


class FrameRenderer:
    """Everything one camera needs to render frames quickly, made once.

    Example
    -------
    >>> renderer = FrameRenderer(camera, MarkerSpec(), noise_sigma_dn=2.0, seed=1)
    >>> frame = renderer.render(VehiclePose(antenna_enu_m=np.array([0.0, 6.0, 2.0]), yaw_rad=np.pi))
    """

    def __init__(
        self,
        camera: Camera,
        marker: MarkerSpec,
        noise_sigma_dn: float = 2.0,
        seed: int = 0,
        supersample: int = 3,
        rays: RayMap | None = None,
    ) -> None:
        self.camera = camera
        self.marker = marker
        self.noise_sigma_dn = float(noise_sigma_dn)
        self.supersample = int(supersample)
        self.board = marker_board_image(marker)
        # The board with its marker covered (plain white): the drone is still drawn, no marker can be found.
        self.covered_board = np.full_like(self.board, 255)
        self.rays = rays if rays is not None else make_ray_map(camera)
        self.background = make_background(camera, seed, self.rays)
        self.noise_field = make_noise_field(camera.width, camera.height, noise_sigma_dn, seed + 1) if noise_sigma_dn > 0 else None
        self.rng = np.random.default_rng(seed + 2)
        # The streaming path's frame buffer: the background noised once, and the box drawn into it last.
        self._frame: np.ndarray | None = None
        self._noised_background: np.ndarray | None = None
        self._drawn_box: tuple[int, int, int, int] | None = None

    def render(self, vehicle: VehiclePose | None, show_marker: bool = True) -> np.ndarray:
        """(H, W, 3) uint8 BGR frame with the drone at ``vehicle`` (None: empty scene).

        ``show_marker=False`` draws the drone with its board covered (plain
        white): what a camera sees when the marker faces away or is occluded.
        """
        return render_frame(
            self.camera,
            self.background,
            vehicle,
            self.marker,
            self.noise_sigma_dn,
            self.rng,
            marker_image=self.board if show_marker else self.covered_board,
            rays=self.rays,
            noise_field=self.noise_field,
            supersample=self.supersample,
        )

    def render_in_place(self, vehicle: VehiclePose | None, show_marker: bool = True) -> np.ndarray:
        """Like ``render``, for a stream: the returned (H, W, 3) uint8 array is this renderer's own buffer, valid until the next call.

        The background's noise is drawn once (frozen); each call restores the
        previous frame's box from the noised background and draws the drone's
        box with fresh noise, so a frame costs the box, not the whole image.
        The box's pixels before noise are exactly ``render``'s.
        """
        if self._frame is None:
            self._noised_background = add_noise(self.background, self.noise_sigma_dn, self.rng, self.noise_field)
            self._frame = self._noised_background.copy()  # never the background itself (no noise: add_noise returns it)
        frame = self._frame
        if self._drawn_box is not None:
            u0, v0, u1, v1 = self._drawn_box
            frame[v0:v1, u0:u1] = self._noised_background[v0:v1, u0:u1]
            self._drawn_box = None
        if vehicle is None:
            return frame
        board = self.board if show_marker else self.covered_board
        layer = render_marker_layer(self.camera, vehicle, self.marker, board, self.rays, self.supersample)
        if layer is None:
            return frame
        u0, v0, u1, v1 = layer[0]
        frame[v0:v1, u0:u1] = add_patch_noise(composite_patch(self.background, layer), self.noise_sigma_dn, self.rng, self.noise_field)
        self._drawn_box = layer[0]
        return frame
