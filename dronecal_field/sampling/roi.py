"""The region of interest (ROI): where the user measures, as 3D points and as image cells.

A calibration is only trusted where its points reach. The ROI says where
that must be: by default the ground the guessed camera sees from 3 to 40 m
from the pole plus a layer up to 2 m above it (vehicles, people); a WGS84
polygon (a road, a car park, given already in the site frame here); or the
whole image (every ray up to a range).

It is built by casting rays through a fine pixel lattice of the *guessed*
camera (site frame) and keeping the intersections with the planes z = 0, 1,
2 m that fall in the ROI's ground area. A ROI point only counts if the guessed
camera sees it: in front, inside the image, before the distortion model
folds (``lattice.fold_radius``). The image is divided into square-ish cells;
a cell belongs to the ROI when a ROI point's pixel falls in it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecal_field.core.camera import Camera, pixel_rays_batch
from dronecal_field.errors import PlanError
from dronecal_field.sampling.lattice import PLAN_FOLD_FRACTION, PLAN_FOLD_MIN_SLOPE, fold_radius

DEFAULT_RANGE_M = (3.0, 40.0)
LAYER_HEIGHTS_M = (0.0, 1.0, 2.0)  # the ground and the layer above it where vehicles and people are
CELLS_ACROSS = 16  # image cells along u (120 px at 1080p); rows follow the aspect ratio
RAYS_PER_CELL = 6  # rays per cell side when building the ROI


@dataclass(frozen=True)
class RoiSpec:
    """What the user asked for.

    ``kind`` is ``'range'`` (ground between ``range_m`` from the pole),
    ``'polygon'`` (ground inside ``polygon_site``, (K, 2) site XY metres) or
    ``'image'`` (every ray up to ``range_m[1]``). ``source`` says where it came
    from (a file name, a flag) for the report.
    """

    kind: str = "range"
    range_m: tuple[float, float] = DEFAULT_RANGE_M
    polygon_site: tuple[tuple[float, float], ...] | None = None
    layer_heights_m: tuple[float, ...] = LAYER_HEIGHTS_M
    source: str = "default"

    def describe(self) -> str:
        """One line for the report."""
        if self.kind == "image":
            return f"the whole image, every ray up to {self.range_m[1]:g} m from the pole"
        top = max(self.layer_heights_m)
        layer = f" and up to {top:g} m above it" if top > 0 else ""
        if self.kind == "polygon":
            return f"the ground inside {self.source} ({len(self.polygon_site or ())} vertices){layer}, seen by the guessed camera"
        return f"the ground {self.range_m[0]:g}-{self.range_m[1]:g} m from the pole{layer}, seen by the guessed camera"

    def to_dict(self) -> dict:
        return {"kind": self.kind, "range_m": list(self.range_m), "layer_heights_m": list(self.layer_heights_m), "source": self.source,
                "polygon_site_m": None if self.polygon_site is None else [list(p) for p in self.polygon_site], "text": self.describe()}


@dataclass(frozen=True, eq=False)
class Roi:
    """A ROI for one guessed camera.

    ``points_site`` (M, 3) site-frame metres and ``uv`` (M, 2) their guessed
    pixels; ``on_ground`` (M,) marks the z = 0 points (ground error in cm is
    computed there). ``cells`` (ny, nx) bool: image cells holding ROI points;
    a cell is ``cell_px`` = (width / nx, height / ny) pixels.
    """

    spec: RoiSpec
    width: int
    height: int
    points_site: np.ndarray
    uv: np.ndarray
    on_ground: np.ndarray
    cells: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """(ny, nx) cells."""
        return self.cells.shape  # type: ignore[return-value]

    @property
    def cell_px(self) -> tuple[float, float]:
        """(du, dv) cell size, px."""
        ny, nx = self.cells.shape
        return self.width / nx, self.height / ny

    @property
    def area_fraction(self) -> float:
        """Share of the image's cells that hold the ROI."""
        return float(self.cells.mean())

    def cell_of(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) cell indices (each (N,)) of pixels (N, 2), clipped to the image."""
        du, dv = self.cell_px
        ny, nx = self.cells.shape
        uv = np.atleast_2d(np.asarray(uv, float))
        col = np.clip(np.floor(uv[:, 0] / du), 0, nx - 1).astype(int)
        row = np.clip(np.floor(uv[:, 1] / dv), 0, ny - 1).astype(int)
        return row, col

    def cell_centres(self) -> np.ndarray:
        """(K, 2) pixel centres of the ROI cells, row by row."""
        du, dv = self.cell_px
        rows, cols = np.nonzero(self.cells)
        return np.column_stack([(cols + 0.5) * du, (rows + 0.5) * dv])

    def coverage(self, sample_uv: np.ndarray, reach_cells: int = 1) -> float:
        """Share of the ROI's image area within reach of samples.

        Defined as: ROI cells within ``reach_cells`` cells (Chebyshev distance,
        i.e. the 3x3 block around a sample's cell for 1) of a sample pixel,
        divided by all ROI cells. Samples outside the ROI still reach the ROI
        cells around them.
        """
        n_roi = int(self.cells.sum())
        if n_roi == 0:
            return 0.0
        sample_uv = np.asarray(sample_uv, float).reshape(-1, 2)
        ok = np.all(np.isfinite(sample_uv), axis=1)
        reached = np.zeros_like(self.cells)
        if ok.any():
            r, c = self.cell_of(sample_uv[ok])
            ny, nx = self.cells.shape
            for dr in range(-reach_cells, reach_cells + 1):
                for dc in range(-reach_cells, reach_cells + 1):
                    rr, cc = r + dr, c + dc
                    inside = (rr >= 0) & (rr < ny) & (cc >= 0) & (cc < nx)
                    reached[rr[inside], cc[inside]] = True
        return float((reached & self.cells).sum() / n_roi)

    def outline_uv(self) -> list[np.ndarray]:
        """Closed pixel outlines (each (K, 2)) of the ROI cells, for drawing."""
        return _cell_outlines(self.cells, *self.cell_px)

    def to_dict(self) -> dict:
        ny, nx = self.cells.shape
        return {**self.spec.to_dict(), "points": int(len(self.points_site)), "ground_points": int(self.on_ground.sum()),
                "cells": [int(nx), int(ny)], "cells_in_roi": int(self.cells.sum()),
                "image_area_pct": round(100.0 * self.area_fraction, 1)}


def seen_by(camera: Camera, points: np.ndarray, margin_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(N,) mask of points (N, 3) the guessed camera sees, and their pixels (N, 2).

    Seen = in front (depth > 0.3 m), inside the image with ``margin_px``, and
    within 97 % of the radius where the radial distortion's slope falls to 5 %
    (``plan``'s fold rule, so the ROI and the screen agree).
    """
    P = np.atleast_2d(np.asarray(points, float))
    Xc = P @ camera.pose.R_cam_from_world.T + camera.pose.t_cam_from_world
    front = Xc[:, 2] > 0.3
    z = np.where(front, Xc[:, 2], 1.0)
    rn = np.hypot(Xc[:, 0] / z, Xc[:, 1] / z)
    before_fold = rn < PLAN_FOLD_FRACTION * fold_radius(camera.distortion.as_array(), PLAN_FOLD_MIN_SLOPE)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        uv = camera.project(np.where(front[:, None], P, np.nan))
    m = margin_px
    inside = (uv[:, 0] >= m) & (uv[:, 0] <= camera.width - 1 - m) & (uv[:, 1] >= m) & (uv[:, 1] <= camera.height - 1 - m)
    ok = front & before_fold & np.nan_to_num(inside, nan=0).astype(bool)
    return ok, uv


def build_roi(camera: Camera, spec: RoiSpec, cells_across: int = CELLS_ACROSS, rays_per_cell: int = RAYS_PER_CELL) -> Roi:
    """The ROI of ``spec`` for the guessed ``camera`` (site frame: pole foot at the origin, Z up).

    Raises PlanError when the camera sees none of it.
    """
    w, h = camera.width, camera.height
    nx = int(cells_across)
    ny = max(2, int(round(nx * h / w)))
    us = (np.arange(nx * rays_per_cell) + 0.5) * w / (nx * rays_per_cell)
    vs = (np.arange(ny * rays_per_cell) + 0.5) * h / (ny * rays_per_cell)
    uv = np.stack(np.meshgrid(us, vs), -1).reshape(-1, 2)
    K, D, R, _ = camera.batch_arrays()
    rays = pixel_rays_batch(K, D, R, uv[None])[0]
    c = camera.pose.position_world
    pts: list[np.ndarray] = []
    ground: list[np.ndarray] = []
    r_min, r_max = spec.range_m
    horiz = np.hypot(rays[:, 0], rays[:, 1])
    if spec.kind == "image":
        # each ray: where it meets the ground if within range, else at the range; and half way there
        s_ground = np.where(rays[:, 2] < -1e-9, -c[2] / np.where(rays[:, 2] < -1e-9, rays[:, 2], -1.0), np.inf)
        s_range = r_max / np.maximum(horiz, 1e-9)
        s_end = np.minimum(s_ground, s_range)
        for frac in (1.0, 0.5):
            p = c + (frac * s_end)[:, None] * rays
            pts.append(p)
            ground.append(np.isclose(p[:, 2], 0.0, atol=1e-6))
    else:
        for z in spec.layer_heights_m:
            dz = rays[:, 2]
            with np.errstate(divide="ignore", invalid="ignore"):
                s = (z - c[2]) / dz
            ok = np.isfinite(s) & (s > 0)
            p = c + np.where(ok, s, np.nan)[:, None] * rays
            r = np.hypot(p[:, 0], p[:, 1])
            ok &= (r >= r_min) & (r <= r_max)
            if spec.kind == "polygon":
                from matplotlib.path import Path as MplPath

                ok &= MplPath(np.asarray(spec.polygon_site, float)).contains_points(np.nan_to_num(p[:, :2], nan=1e9))
            pts.append(p[ok])
            ground.append(np.full(int(ok.sum()), z == 0.0))
    P = np.concatenate(pts) if pts else np.zeros((0, 3))
    G = np.concatenate(ground) if ground else np.zeros(0, bool)
    ok, uv_p = seen_by(camera, P) if len(P) else (np.zeros(0, bool), np.zeros((0, 2)))
    P, G, uv_p = P[ok], G[ok], uv_p[ok]
    if len(P) == 0:
        raise PlanError(f"the guessed camera sees none of the region of interest ({spec.describe()}): check --tilt/--azimuth, or widen --roi-range / --roi")
    cells = np.zeros((ny, nx), bool)
    col = np.clip(np.floor(uv_p[:, 0] / (w / nx)), 0, nx - 1).astype(int)
    row = np.clip(np.floor(uv_p[:, 1] / (h / ny)), 0, ny - 1).astype(int)
    cells[row, col] = True
    return Roi(spec=spec, width=w, height=h, points_site=P, uv=uv_p, on_ground=G, cells=cells)


def evaluation_points(roi: Roi, per_cell: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A thinned set of ROI points for scoring: at most ``per_cell`` per image cell and plane.

    Returns (points (K, 3) site metres, on_ground (K,) bool). Thinning keeps
    the prediction's cost independent of the ray density while every cell
    and every height layer keeps a say.
    """
    row, col = roi.cell_of(roi.uv)
    z_key = np.round(roi.points_site[:, 2], 2)
    key = (row * roi.cells.shape[1] + col) * 1000 + np.round(z_key * 10).astype(int)
    order = np.argsort(key, kind="stable")
    keep = np.zeros(len(key), bool)
    k_sorted = key[order]
    start = np.r_[0, np.flatnonzero(np.diff(k_sorted)) + 1]
    counts = np.diff(np.r_[start, len(k_sorted)])
    for s, n in zip(start, counts):
        idx = order[s : s + n]
        keep[idx[np.linspace(0, n - 1, min(per_cell, n)).round().astype(int)]] = True
    return roi.points_site[keep], roi.on_ground[keep]


def _cell_outlines(cells: np.ndarray, du: float, dv: float) -> list[np.ndarray]:
    """Boundary segments of the True cells chained into closed pixel polylines."""
    ny, nx = cells.shape
    padded = np.pad(cells, 1)
    edges: dict[tuple[int, int], list[tuple[int, int]]] = {}

    def add(a: tuple[int, int], b: tuple[int, int]) -> None:
        edges.setdefault(a, []).append(b)

    for r in range(ny):
        for c in range(nx):
            if not cells[r, c]:
                continue
            pr, pc = r + 1, c + 1
            # corners as (col, row) lattice points; edges oriented so the cell is on the left
            if not padded[pr - 1, pc]:
                add((c + 1, r), (c, r))
            if not padded[pr + 1, pc]:
                add((c, r + 1), (c + 1, r + 1))
            if not padded[pr, pc - 1]:
                add((c, r), (c, r + 1))
            if not padded[pr, pc + 1]:
                add((c + 1, r + 1), (c + 1, r))
    loops: list[np.ndarray] = []
    while edges:
        start = next(iter(edges))
        loop = [start]
        cur = start
        while True:
            nxt_list = edges.get(cur)
            if not nxt_list:
                break
            nxt = nxt_list.pop()
            if not nxt_list:
                del edges[cur]
            if nxt == start:
                break
            loop.append(nxt)
            cur = nxt
        loop.append(start)
        loops.append(np.asarray(loop, float) * np.array([du, dv]))
    return loops
