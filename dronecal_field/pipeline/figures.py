"""The report's figures, as PNG bytes (matplotlib, Agg backend, no display needed)."""

from __future__ import annotations

import io

import numpy as np


def _figure(width_in: float = 7.0, height_in: float = 4.5):
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    # A bare Figure (not pyplot): no global state, safe in threads and tests.
    return Figure(figsize=(width_in, height_in), dpi=100)


def _png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    return buf.getvalue()


def residuals_figure(report, background: np.ndarray | None = None, scale: float | None = None) -> bytes:
    """The image with each waypoint's detected centre and its residual vector scaled up."""
    cam = report.camera
    w, h = cam.width, cam.height
    res = np.asarray(report.result.residuals_px)
    used = report.used_points
    uv = np.array([p.uv_px for p in used])
    norms = np.linalg.norm(res, axis=1)
    if scale is None:
        typical = float(np.percentile(norms, 90)) if len(norms) else 1.0
        scale = float(max(1.0, min(500.0, 0.06 * max(w, h) / max(typical, 1e-6))))
    fig = _figure(7.0, 7.0 * h / w + 0.6)
    ax = fig.add_subplot(1, 1, 1)
    if background is not None:
        ax.imshow(background, cmap="gray", extent=(-0.5, w - 0.5, h - 0.5, -0.5), alpha=0.6)
    outliers = set(report.result.outliers)
    colours = ["tab:red" if i in outliers else "tab:blue" for i in range(len(used))]
    ax.scatter(uv[:, 0], uv[:, 1], s=14, c=colours, zorder=3)
    # Residual = observed - predicted: the arrow goes from the prediction towards the observation.
    ax.quiver(uv[:, 0], uv[:, 1], res[:, 0] * scale, res[:, 1] * scale, angles="xy", scale_units="xy", scale=1,
              color=colours, width=0.003, zorder=4)
    dropped = [p for p in report.points if not p.used and p.uv_px is not None]
    if dropped:
        d = np.array([p.uv_px for p in dropped])
        ax.scatter(d[:, 0], d[:, 1], s=18, marker="x", c="0.4", label="dropped window", zorder=3)
        ax.legend(loc="lower right", fontsize=8)
    for p, (u, v) in zip(used, uv):
        ax.annotate(str(p.window.index), (u, v), fontsize=6, xytext=(3, 3), textcoords="offset points")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title(f"waypoints and residuals x{scale:.0f} (RMS {report.result.rms_px:.2f} px, red: outliers)", fontsize=10)
    ax.set_xlabel("u (px)")
    ax.set_ylabel("v (px)")
    return _png(fig)


def coverage_figure(report) -> bytes:
    """Coverage of the image by the used points: positions, convex hull, radial distribution."""
    from scipy.spatial import ConvexHull, QhullError

    cam = report.camera
    w, h = cam.width, cam.height
    uv = np.array([p.uv_px for p in report.used_points])
    fig = _figure(9.0, 3.8)
    ax = fig.add_subplot(1, 2, 1)
    ax.add_patch(__import__("matplotlib.patches", fromlist=["Rectangle"]).Rectangle((-0.5, -0.5), w, h, fill=False, lw=1))
    area = 0.0
    try:
        hull = ConvexHull(uv)
        loop = np.r_[hull.vertices, hull.vertices[:1]]
        ax.fill(uv[loop, 0], uv[loop, 1], alpha=0.2, color="tab:green")
        area = hull.volume / (w * h)
    except (QhullError, ValueError):
        pass
    ax.scatter(uv[:, 0], uv[:, 1], s=10, color="tab:green")
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_aspect("equal")
    ax.set_title(f"coverage: hull {area:.0%} of the image", fontsize=10)
    ax2 = fig.add_subplot(1, 2, 2)
    centre = np.array([(w - 1) / 2, (h - 1) / 2])
    r = np.linalg.norm(uv - centre, axis=1) / (0.5 * np.hypot(w, h))
    ax2.hist(r, bins=np.linspace(0, 1, 11), color="tab:green", edgecolor="k")
    ax2.set_xlabel("radius / half-diagonal")
    ax2.set_ylabel("points")
    ax2.set_title("radial coverage (distortion needs the edges)", fontsize=10)
    return _png(fig)


def monte_carlo_figure(report) -> bytes | None:
    """Histogram of the Monte-Carlo RMS reprojection errors with mean and percentiles."""
    mc = report.monte_carlo
    if mc is None or mc.rms is None:
        return None
    rms = np.asarray(mc.rms)
    rms = rms[np.isfinite(rms)]
    fig = _figure(6.0, 3.6)
    ax = fig.add_subplot(1, 1, 1)
    ax.hist(rms, bins=40, color="tab:purple", alpha=0.8)
    ax.axvline(mc.rms_mean, color="k", lw=1.5, label=f"mean {mc.rms_mean:.3f} px")
    for p, style in ((5, ":"), (95, "--")):
        if p in mc.rms_percentiles:
            ax.axvline(mc.rms_percentiles[p], color="k", ls=style, lw=1, label=f"p{p} {mc.rms_percentiles[p]:.3f} px")
    ax.axvline(report.result.rms_px, color="tab:red", lw=1.5, label=f"this flight {report.result.rms_px:.3f} px")
    ax.set_xlabel("RMS reprojection error (px)")
    ax.set_ylabel("trials")
    ax.set_title(f"Monte-Carlo, {mc.trials} trials with the measured sigmas", fontsize=10)
    ax.legend(fontsize=8)
    return _png(fig)


def uncertainty_map_figure(report) -> bytes:
    """Projection uncertainty (px) and ground-position uncertainty (cm) over the image."""
    m = report.maps
    cam = report.camera
    extent = (-0.5, cam.width - 0.5, cam.height - 0.5, -0.5)
    fig = _figure(10.0, 3.9)
    for k, (data, title, unit) in enumerate(
        ((m.projection_px, "projection uncertainty", "px"), (m.ground_cm, "ground position uncertainty (z = 0)", "cm"))
    ):
        ax = fig.add_subplot(1, 2, k + 1)
        shown = np.ma.masked_invalid(data)
        vmax = float(np.nanpercentile(data, 95)) if np.any(np.isfinite(data)) else 1.0
        im = ax.imshow(shown, extent=extent, origin="upper", cmap="viridis", vmin=0, vmax=max(vmax, 1e-9), interpolation="bilinear")
        uv = np.array([p.uv_px for p in report.used_points])
        ax.scatter(uv[:, 0], uv[:, 1], s=6, c="w", edgecolors="k", linewidths=0.3)
        ax.set_title(f"{title} ({unit})", fontsize=10)
        ax.set_aspect("equal")
        fig.colorbar(im, ax=ax, shrink=0.8)
    return _png(fig)


def track_figure(report) -> bytes:
    """The GNSS track (plan view and height over time) with the hover windows and the camera."""
    tr = report.track
    t = (tr.t_ns - tr.t_ns[0]) * 1e-9
    fig = _figure(10.0, 4.0)
    ax = fig.add_subplot(1, 2, 1)
    ax.plot(tr.antenna_enu_m[:, 0], tr.antenna_enu_m[:, 1], lw=0.6, color="0.5")
    for p in report.points:
        a, b = p.stable_ns
        sel = (tr.t_ns >= a) & (tr.t_ns <= b)
        colour = "tab:green" if p.used else "tab:red"
        ax.plot(tr.marker_enu_m[sel, 0], tr.marker_enu_m[sel, 1], ".", ms=2, color=colour)
    c = report.camera.pose.position_world
    ax.plot([c[0]], [c[1]], "k^", ms=8, label="camera")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.set_title("track; hover windows used (green) / dropped (red)", fontsize=10)
    ax.legend(fontsize=8)
    ax2 = fig.add_subplot(1, 2, 2)
    ax2.plot(t, tr.antenna_enu_m[:, 2], lw=0.8, color="0.3")
    for p in report.points:
        a, b = ((np.array(p.stable_ns) - tr.t_ns[0]) * 1e-9)
        ax2.axvspan(a, b, color="tab:green" if p.used else "tab:red", alpha=0.25, lw=0)
    ax2.set_xlabel("time (s)")
    ax2.set_ylabel(f"up (m, {report.altitude_datum} datum)")
    ax2.set_title(f"height; {len(report.windows)} windows from {report.window_source}", fontsize=10)
    return _png(fig)
