"""preview.png: the top view over the camera's footprint, and the predicted image.

Drawn with matplotlib's object API on an Agg canvas (no pyplot global state,
no display needed).
"""

from __future__ import annotations

import os

import numpy as np


def render_preview(result, path: str | os.PathLike) -> None:
    """Write the two-panel preview of a ``plan.stage.PlanResult`` to ``path`` (PNG)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Polygon

    from dronecal_field.sampling.lattice import marker_corners

    req, route, chosen = result.request, result.route, result.chosen
    R = req.site.R_enu_from_site  # plot the top view in ENU: east right, north up, like a map

    def en(p: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(np.asarray(p, float))
        if p.shape[1] == 2:
            p = np.column_stack([p, np.zeros(len(p))])
        return (p @ R.T)[:, :2]

    fig = Figure(figsize=(14, 6.4), dpi=100)
    FigureCanvasAgg(fig)
    ax, ai = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    pts = chosen.screen.points
    veh = chosen.screen.vehicle_points
    z = pts[:, 2]
    cmap = "viridis"

    ax.add_patch(Polygon(en(result.footprint_site), closed=True, facecolor="#cfe3ff", edgecolor="#6c9bd2", alpha=0.6, label="camera footprint (ground)"))
    ax.add_patch(Polygon(en(result.fence_site), closed=True, fill=False, edgecolor="orange", lw=1.5, ls="--", label="geofence"))
    if req.limits.keep_out_m > 0:
        ax.add_patch(Circle((0, 0), req.limits.keep_out_m, fill=True, facecolor="#ffd6d6", edgecolor="red", ls=":", label="keep-out"))
    track = np.vstack([route.takeoff_site[None], route.points] + ([route.takeoff_site[None]] if route.end == "land" else []))
    pe = en(track)
    ax.plot(pe[:, 0], pe[:, 1], "-", color="0.45", lw=0.8, label="path")
    sc = ax.scatter(*en(veh).T, c=z, cmap=cmap, s=22, zorder=3, label="grid (drone)")
    ve = en(veh)
    ax.annotate("first", ve[route.grid_order[0]], textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.annotate("last", ve[route.grid_order[-1]], textcoords="offset points", xytext=(4, -10), fontsize=8)
    te = en(route.takeoff_site)[0]
    ax.plot(*te, marker="*", color="green", ms=14, ls="none", label="take-off / land (home)")
    ax.plot(0, 0, marker="^", color="black", ms=10, ls="none", label="camera pole")
    axis = R @ np.array([3.0, 0.0, 0.0])
    ax.annotate("", xy=(axis[0], axis[1]), xytext=(0, 0), arrowprops={"arrowstyle": "->", "color": "black"})
    span = np.vstack([pe, en(result.fence_site), [[0, 0]]])
    lo, hi = span.min(axis=0) - 3, span.max(axis=0) + 3
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_xlabel("east of the pole (m)")
    ax.set_ylabel("north of the pole (m)")
    ax.set_title(f"top view (north up); heights {', '.join(f'{h:g}' for h in chosen.screen.heights_m)} m marker")
    ax.legend(loc="best", fontsize=7)
    fig.colorbar(sc, ax=ax, label="marker height above the pole's foot (m)", shrink=0.8)

    cam = result.camera_site
    w, h = cam.width, cam.height
    ai.add_patch(Polygon([[0, 0], [w, 0], [w, h], [0, h]], closed=True, fill=False, edgecolor="black"))
    d = -veh[:, :2]  # the nose, and the marker, face the pole
    n = np.linalg.norm(d, axis=1, keepdims=True)
    fwd = d / np.maximum(n, 1e-9)
    corners = marker_corners(pts, fwd, req.marker.size_m)
    cuv = cam.project(corners.reshape(-1, 3)).reshape(-1, 4, 2)
    norm = (z - z.min()) / max(float(np.ptp(z)), 1e-9)
    import matplotlib

    colours = matplotlib.colormaps[cmap](norm)
    for q, c in zip(cuv, colours):
        ai.add_patch(Polygon(q, closed=True, facecolor=c, edgecolor="black", lw=0.4))
    uv = cam.project(pts)
    ai.scatter(uv[:, 0], uv[:, 1], s=3, c="black", zorder=3)
    ai.set_xlim(-0.03 * w, 1.03 * w)
    ai.set_ylim(1.03 * h, -0.03 * h)
    ai.set_aspect("equal")
    mp = chosen.screen.marker_px[chosen.screen.keep]
    ai.set_title(f"predicted image {w}x{h}: {len(pts)} markers of {req.marker.size_m:g} m, {mp.min():.0f}-{mp.max():.0f} px")
    ai.set_xlabel("u (px)")
    ai.set_ylabel("v (px)")

    s = result.summary
    u = s["uncertainty"]
    fmt = lambda v, f: "n/a" if v is None else format(v, f)  # noqa: E731
    fig.suptitle(
        f"{req.name or 'dronecal-field plan'}: {chosen.strategy.name} ({chosen.strategy.describe()}), "
        f"{s['flight']['flight_time_s'] / 60:.1f} min, battery {s['flight']['battery_pct']:.0f} %\n"
        f"predicted RMS reprojection {fmt(u['rms_mean_px'], '.2f')} px (p95 {fmt(u['rms_p95_px'], '.2f')}), "
        f"ground error at 15 m {fmt(u['ground_error_15m_cm'], '.1f')} cm; {result.mission.alt_frame_text}",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(os.fspath(path), format="png")
