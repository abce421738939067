"""The paper's Figures 8, 9 and 10 from survey rows (matplotlib, Agg backend, PNG files only).

The survey's cameras are scattered (a Latin Hypercube), the paper's figures
are contours: values are averaged (or voted) in bins of the two plotted
factors, over all other factors, and the bins are contoured; each figure
also shows the cameras themselves as dots.
"""

from __future__ import annotations

import os

import numpy as np

from dronecal_field.survey.catalogue import COMPARISONS, RECOMMENDED
from dronecal_field.survey.findings import metric_by_strategy, paired


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def binned(x: np.ndarray, y: np.ndarray, v: np.ndarray, x_edges: np.ndarray, y_edges: np.ndarray, reduce: str = "mean", min_count: int = 1) -> np.ndarray:
    """(ny, nx) statistic of ``v`` in the bins of (x, y); NaN where fewer than ``min_count`` values.

    ``reduce`` is 'mean' or 'median'. x, y, v are (n,) arrays.
    """
    nx, ny = len(x_edges) - 1, len(y_edges) - 1
    ix = np.clip(np.searchsorted(x_edges, x, side="right") - 1, 0, nx - 1)
    iy = np.clip(np.searchsorted(y_edges, y, side="right") - 1, 0, ny - 1)
    out = np.full((ny, nx), np.nan)
    for j in range(ny):
        for i in range(nx):
            sel = (ix == i) & (iy == j)
            if sel.sum() >= min_count:
                out[j, i] = np.mean(v[sel]) if reduce == "mean" else np.median(v[sel])
    return out


def _bins(n_cameras: int) -> int:
    """Bins per axis: about 25 cameras per bin, between 4 and 14 per axis."""
    return int(np.clip(np.sqrt(n_cameras / 25.0), 4, 14))


def _columns(table) -> dict[str, list]:
    return table.to_pydict() if hasattr(table, "to_pydict") else table


def _factor(table, name: str) -> dict[int, float]:
    t = _columns(table)
    return {int(c): float(v) for c, v in zip(t["camera_id"], t[name])}


def _contour_panel(ax, x, y, v, x_range, y_range, n_bins, levels, cmap, label, reduce="mean"):
    """Binned statistic as filled cells over the full ranges, contour lines over the bin centres, cameras as dots."""
    xe = np.linspace(*x_range, n_bins + 1)
    ye = np.linspace(*y_range, n_bins + 1)
    grid = binned(x, y, v, xe, ye, reduce)
    levels = np.asarray(levels, float)
    from matplotlib.colors import BoundaryNorm

    norm = BoundaryNorm(levels, ncolors=256, extend="both")
    mesh = ax.pcolormesh(xe, ye, np.ma.masked_invalid(grid), cmap=cmap, norm=norm, shading="flat")
    ax.figure.colorbar(mesh, ax=ax, label=label)
    if np.isfinite(grid).sum() >= 4 and len(levels) > 3:
        xc, yc = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1])
        cs = ax.contour(xc, yc, np.ma.masked_invalid(grid), levels=levels[::2], colors="k", linewidths=0.6, alpha=0.6)
        ax.clabel(cs, fontsize=7, fmt="%.3g")
    ax.scatter(x, y, s=4, c="k", alpha=0.25, lw=0)
    ax.set_xlim(*x_range)
    ax.set_ylim(*y_range)


def figure8(table, path: str | os.PathLike, focal_range=(2.0, 15.0), width_range=(700.0, 4000.0)) -> int:
    """Figure 8: the preferred Y step over focal length x image width.

    Top, as the paper: each bin's majority choice (1 = 1 m, 2 = 0.5 m, by
    mean RMS reprojection error). Bottom: by how much (%) the 0.5 m step's
    error exceeds the 1 m step's, which shows where 0.5 m comes closest.
    Returns the number of cameras compared.
    """
    plt = _plt()
    v = metric_by_strategy(table, "rms_mean")
    ids, m = paired(v, COMPARISONS["y_step"])
    focal, width = _factor(table, "focal_mm"), _factor(table, "width_px")
    x = np.array([focal[i] for i in ids])
    y = np.array([width[i] for i in ids])
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(6.4, 8.4), dpi=100)
    if len(ids):
        choice = np.where(m[:, 0] <= m[:, 1], 1.0, 2.0)
        n = _bins(len(ids))
        _contour_panel(top, x, y, choice, focal_range, width_range, n, [0.5, 1.5, 2.5], "coolwarm", "preferred Y step (1: 1 m, 2: 0.5 m)", reduce="median")
        if (choice == 2).any():
            top.scatter(x[choice == 2], y[choice == 2], s=12, c="red", marker="x", lw=0.8, label="0.5 m better")
            top.legend(loc="upper right", fontsize=8)
        margin = 100.0 * (m[:, 1] / m[:, 0] - 1.0)
        hi = max(float(np.percentile(margin, 95)), 1e-3)
        _contour_panel(bottom, x, y, margin, focal_range, width_range, n, np.linspace(min(0.0, float(margin.min())), hi, 11), "magma",
                       "error of 0.5 m step over 1 m step (%)")
    for ax in (top, bottom):
        ax.set_xlabel("focal length (mm)")
        ax.set_ylabel("image width (px)")
    top.set_title(f"Fig. 8: Y step 1 m vs 0.5 m ({len(ids)} cameras)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return len(ids)


def figure9(table, path: str | os.PathLike, strategy: str = RECOMMENDED, metric: str = "rms_mean",
            focal_range=(2.0, 15.0), width_range=(700.0, 4000.0), tilt_range=(0.0, 90.0), elevation_range=(2.0, 5.0)) -> int:
    """Figure 9: mean error of ``strategy`` over width x focal (top) and tilt x elevation (bottom).

    Returns the number of cameras with an 'ok' row for the strategy.
    """
    plt = _plt()
    values = metric_by_strategy(table, metric).get(strategy, {})
    ids = np.array(sorted(values), dtype=int)
    v = np.array([values[i] for i in ids])
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(6.4, 8.4), dpi=100)
    label = "mean RMS reprojection error (px)" if metric == "rms_mean" else "projection error (px)"
    if len(ids):
        f, w = _factor(table, "focal_mm"), _factor(table, "width_px")
        t, e = _factor(table, "tilt_deg"), _factor(table, "elevation_m")
        hi = float(np.percentile(v, 95))
        levels = np.linspace(float(v.min()), max(hi, float(v.min()) + 1e-6), 12)
        n = _bins(len(ids))
        _contour_panel(top, np.array([w[i] for i in ids]), np.array([f[i] for i in ids]), v, width_range, focal_range, n, levels, "viridis", label)
        _contour_panel(bottom, np.array([t[i] for i in ids]), np.array([e[i] for i in ids]), v, tilt_range, elevation_range, n, levels, "viridis", label)
    top.set_xlabel("image width (px)")
    top.set_ylabel("focal length (mm)")
    top.set_title(f"Fig. 9: {strategy}, {len(ids)} cameras")
    bottom.set_xlabel("tilt below horizontal (deg)")
    bottom.set_ylabel("camera elevation (m)")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return len(ids)


def figure10(distances_m: np.ndarray, with_gnss: np.ndarray, image_only: np.ndarray, path: str | os.PathLike, title: str) -> None:
    """Figure 10: mean RMS reprojection error (px) against the maximum sampling distance (m), with and without GNSS noise."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.4, 4.0), dpi=100)
    ax.plot(distances_m, with_gnss, "o-", label="GNSS/altimeter + 2D noise")
    ax.plot(distances_m, image_only, "s--", label="2D noise only")
    ax.fill_between(distances_m, image_only, with_gnss, alpha=0.15, label="GNSS share")
    ax.set_xlabel("maximum sampling distance along X (m)")
    ax.set_ylabel("mean RMS reprojection error (px)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
