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
    scale = report.sigma_scale
    sigmas = "the measured sigmas" if scale <= 1.0 else f"the measured sigmas x{scale:.2f} (to explain the fit)"
    ax.set_title(f"Monte-Carlo, {mc.trials} trials with {sigmas}", fontsize=10)
    ax.legend(fontsize=8)
    return _png(fig)


PROJECTION_CLIP_PX = 10.0  # colour scales stop here: beyond, one "over" colour
GROUND_CLIP_CM = 50.0


def uncertainty_map_figure(report) -> bytes:
    """Predicted projection error (px) and ground-position error (cm) over the image, with the region of validity.

    Filled contours on the maps' regular grid, colour scales clipped at 10 px
    and 50 cm (beyond: one red "over" colour, "> max" on the colour bar),
    the sky (rays that miss the ground within 200 m) hatched grey rather than
    left blank, the used points, their convex hull (dashed) and the region
    of validity (solid outline) when the report has one.
    """
    from matplotlib import colormaps
    from matplotlib.patches import Patch, Polygon

    m = report.maps
    cam = report.camera
    validity = getattr(report, "validity", None)
    U, V = np.meshgrid(m.u_px, m.v_px)
    no_ray = m.no_ray if hasattr(m, "no_ray") else np.zeros(m.projection_px.shape, bool)
    sky = ~np.isfinite(m.ground_cm) & ~no_ray
    uv = np.array([p.uv_px for p in report.used_points])
    cmap = colormaps["viridis"].with_extremes(over="#d62728")
    fig = _figure(12.0, 12.0 * cam.height / cam.width * 0.4 + 1.3)
    panels = (
        (m.projection_px, "projection error", "px", PROJECTION_CLIP_PX),
        (m.ground_cm, "ground position error (z = 0)", "cm", GROUND_CLIP_CM),
    )
    for k, (data, title, unit, vmax) in enumerate(panels):
        ax = fig.add_subplot(1, 2, k + 1)
        ax.set_facecolor("#e6e6e6")
        # Beyond the model's fold the error is unbounded: drawn in the "over" colour and hatched.
        shown = np.where(no_ray, 1e9, data)
        shown = np.ma.masked_invalid(np.where(sky, np.nan, shown) if k == 1 else shown)
        levels = np.linspace(0.0, vmax, 11)
        cs = ax.contourf(U, V, np.minimum(shown, 1e9), levels=levels, cmap=cmap, extend="max")
        if sky.any():
            # Sky: no ground point, so no ground error; hatched, never a white hole.
            ax.contourf(U, V, sky.astype(float), levels=[0.5, 1.5], colors="none", hatches=["//"])
            ax.contour(U, V, sky.astype(float), levels=[0.5], colors="0.35", linewidths=0.8, linestyles=":")
        if no_ray.any():
            ax.contourf(U, V, no_ray.astype(float), levels=[0.5, 1.5], colors="none", hatches=["xx"])
        cbar = fig.colorbar(cs, ax=ax, shrink=0.6, ticks=levels[::2])
        labels = [f"{t:g}" for t in levels[::2]]
        labels[-1] = f"{vmax:g}"
        cbar.ax.set_yticklabels(labels)
        cbar.set_label(f"{unit}; red: > {vmax:g} {unit}", fontsize=8)
        if len(uv):
            ax.scatter(uv[:, 0], uv[:, 1], s=6, c="w", edgecolors="k", linewidths=0.3, zorder=4)
        if validity is not None:
            hull = np.asarray(validity.hull_px)
            ax.add_patch(Polygon(hull, closed=True, fill=False, ec="w", lw=1.2, ls="--", zorder=5))
            ax.add_patch(Polygon(np.asarray(validity.polygon_px), closed=True, fill=False, ec="#ff7f0e", lw=2.0, zorder=6))
        ax.set_xlim(-0.5, cam.width - 0.5)
        ax.set_ylim(cam.height - 0.5, -0.5)
        ax.set_aspect("equal")
        ax.set_xlabel("u (px)", fontsize=8)
        ax.set_ylabel("v (px)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(f"predicted {title} ({unit})", fontsize=10)
    handles = [Patch(fc="w", ec="k", label="calibration points")]
    if validity is not None:
        handles += [
            Patch(fc="none", ec="#ff7f0e", lw=2.0, label="region of validity"),
            Patch(fc="#888888", ec="w", ls="--", label="points' hull (dashed)"),
        ]
    if sky.any():
        handles.append(Patch(fc="#e6e6e6", ec="0.35", hatch="//", label="sky: no ground within 200 m"))
    if no_ray.any():
        handles.append(Patch(fc="#d62728", ec="0.2", hatch="xx", label="no ray: the distortion model folds back here"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    note = "90 % bound; linearised, measured sigmas" if m.samples == 0 else f"90 % bound; {m.samples} sampled cameras"
    if getattr(m, "extrapolation_px", None) is not None:
        note += " + model extrapolation"
    fig.suptitle(f"where the calibration can be trusted ({note})", fontsize=10)
    return _png(fig)


def validity_ground_figure(report) -> bytes | None:
    """Plan view (ENU) of the ground: what the camera sees 3-30 m out, the region of validity's footprint, the points."""
    from matplotlib.patches import Circle, Patch, Polygon

    from dronecal_field.pipeline.validity import VISIBLE_GROUND_M, visible_ground

    validity = getattr(report, "validity", None)
    if validity is None:
        return None
    cam = report.camera
    c = cam.pose.position_world
    seen, _ = visible_ground(cam, step_m=0.5)
    fig = _figure(6.5, 6.0)
    ax = fig.add_subplot(1, 1, 1)
    handles = []
    if len(seen):
        ax.scatter(seen[:, 0], seen[:, 1], s=1.5, c="#bdbdbd", lw=0, zorder=1)
        handles.append(Patch(fc="#bdbdbd", label=f"ground the camera sees {VISIBLE_GROUND_M[0]:g}-{VISIBLE_GROUND_M[1]:g} m out"))
    if validity.ground_polygon_enu_m is not None:
        ax.add_patch(Polygon(validity.ground_polygon_enu_m[:, :2], closed=True, fc="#ff7f0e", alpha=0.35, ec="#ff7f0e", lw=2, zorder=2))
        frac = validity.visible_ground_fraction
        handles.append(Patch(fc="#ff7f0e", alpha=0.5, label="region of validity" + (f" ({frac:.0%} of it)" if frac is not None else "")))
    for r in VISIBLE_GROUND_M:
        ax.add_patch(Circle((c[0], c[1]), r, fill=False, ls="--", ec="0.5", lw=0.8))
    X = np.array([p.marker_enu_m for p in report.used_points])
    if len(X):
        ax.scatter(X[:, 0], X[:, 1], s=10, c="tab:blue", zorder=3)
        handles.append(Patch(fc="tab:blue", label="calibration points (flown above the ground)"))
    ax.plot([c[0]], [c[1]], "k^", ms=9, zorder=4)
    handles.append(Patch(fc="k", label="camera"))
    # Frame what the camera sees (and the camera), not the whole 30 m circle.
    reach = VISIBLE_GROUND_M[1] + 3.0
    shown = np.r_[c[None, :2], seen[:, :2]] if len(seen) else np.array([c[:2] - reach, c[:2] + reach])
    lo = np.maximum(shown.min(0), c[:2] - reach) - 2.0
    hi = np.minimum(shown.max(0), c[:2] + reach) + 2.0
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.set_xlabel("east (m)")
    ax.set_ylabel("north (m)")
    ax.legend(handles=handles, loc="lower left", fontsize=7, framealpha=0.85)
    ax.set_title("ground plane z = 0: region of validity (also validity.geojson)", fontsize=10)
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
