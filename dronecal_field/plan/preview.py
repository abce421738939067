"""preview.png: the top view, the predicted image with the ROI, and the predicted error over the ROI.

Drawn with matplotlib's object API on an Agg canvas (no pyplot global state,
no display needed). Three panels:

- top view (north up): footprint, ROI ground points coloured by the
  predicted error, keep-out, fence, the flights' paths, holds and pass-through
  points, take-off;
- predicted image: the ROI outline (image cells), the markers at the holds
  (true size), the pass-through points and the legs between them;
- predicted error over the ROI in the image: combined (noise +
  extrapolation) projection error per ROI point, on a colour scale clipped
  at its 95th percentile so a few extreme corners do not wash out the rest.
"""

from __future__ import annotations

import os

import numpy as np


def render_preview(result, path: str | os.PathLike) -> None:
    """Write the preview of a ``plan.stage.PlanResult`` to ``path`` (PNG, 1800 x 640 px)."""
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Polygon

    from dronecal_field.sampling.lattice import marker_corners
    from dronecal_field.sampling.roi import evaluation_points

    req, chosen = result.request, result.chosen
    R = req.site.R_enu_from_site  # plot the top view in ENU: east right, north up, like a map

    def en(p: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(np.asarray(p, float))
        if p.shape[1] == 2:
            p = np.column_stack([p, np.zeros(len(p))])
        return (p @ R.T)[:, :2]

    fig = Figure(figsize=(18, 6.4), dpi=100)
    FigureCanvasAgg(fig)
    ax, ai, ae = fig.add_subplot(1, 3, 1), fig.add_subplot(1, 3, 2), fig.add_subplot(1, 3, 3)
    pts, veh = chosen.marker_site, chosen.vehicle_site
    hold = chosen.hold_s > 0
    pred = result.roi_prediction
    roi = result.roi
    err = None
    if pred is not None and roi is not None:
        roi_pts, _ = evaluation_points(roi)
        err = pred.px_combined
        vmax = float(np.nanpercentile(err, 95)) if np.isfinite(err).any() else 1.0
        norm = Normalize(vmin=0.0, vmax=max(vmax, 1e-3))
    cmap = matplotlib.colormaps["magma_r"]

    # --- top view
    ax.add_patch(Polygon(en(result.footprint_site), closed=True, facecolor="#e3eefc", edgecolor="#6c9bd2", alpha=0.6, label="camera footprint (ground, 40 m)"))
    if err is not None:
        g = roi_pts[:, 2] == 0.0
        ax.scatter(*en(roi_pts[g]).T, c=err[g], cmap=cmap, norm=norm, s=6, marker="s", alpha=0.7, zorder=2, label="ROI ground (predicted error)")
    if req.roi.kind == "polygon" and req.roi.polygon_site:
        ax.add_patch(Polygon(en(np.asarray(req.roi.polygon_site)), closed=True, fill=False, edgecolor="purple", lw=1.5, label="ROI polygon"))
    elif req.roi.kind == "range":
        r0, r1 = req.roi.range_m
        ax.add_patch(Circle((0, 0), r0, fill=False, edgecolor="purple", lw=1.2, ls="--", label=f"ROI: ground {r0:g}-{r1:g} m in the footprint"))
        ax.add_patch(Circle((0, 0), r1, fill=False, edgecolor="purple", lw=1.2, ls="--"))
    ax.add_patch(Polygon(en(result.fence_site), closed=True, fill=False, edgecolor="orange", lw=1.5, ls="--", label="geofence"))
    if req.limits.keep_out_m > 0:
        ax.add_patch(Circle((0, 0), req.limits.keep_out_m, fill=True, facecolor="#ffd6d6", edgecolor="red", ls=":", label="keep-out"))
    colours = ["0.35", "tab:blue", "tab:green", "tab:purple", "tab:brown"]
    for k, route in enumerate(result.routes):
        track = np.vstack([route.takeoff_site[None], route.points] + ([route.takeoff_site[None]] if route.end == "land" else []))
        pe = en(track)
        label = "path" if len(result.routes) == 1 else f"flight {k + 1}"
        ax.plot(pe[:, 0], pe[:, 1], "-", color=colours[k % len(colours)], lw=0.8, label=label, zorder=3)
    ve = en(veh)
    ax.scatter(*ve[hold].T, s=18, c="tab:cyan", edgecolors="black", linewidths=0.4, zorder=4, label="hold (drone)")
    if (~hold).any():
        ax.scatter(*ve[~hold].T, s=8, c="white", edgecolors="black", linewidths=0.4, zorder=4, label="fly-through point")
    te = en(result.route.takeoff_site)[0]
    ax.plot(*te, marker="*", color="green", ms=14, ls="none", label="take-off / land (home)", zorder=5)
    ax.plot(0, 0, marker="^", color="black", ms=10, ls="none", label="camera pole", zorder=5)
    axis = R @ np.array([3.0, 0.0, 0.0])
    ax.annotate("", xy=(axis[0], axis[1]), xytext=(0, 0), arrowprops={"arrowstyle": "->", "color": "black"})
    span = np.vstack([ve, en(result.fence_site), [[0, 0]], te[None]])
    lo, hi = span.min(axis=0) - 4, span.max(axis=0) + 4
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_xlabel("east of the pole (m)")
    ax.set_ylabel("north of the pole (m)")
    ax.set_title("top view (north up), zoomed on the flight")
    ax.legend(loc="best", fontsize=7, framealpha=0.5)

    # --- predicted image: ROI outline, markers, legs
    cam = result.camera_site
    w, h = cam.width, cam.height
    for a in (ai, ae):
        a.add_patch(Polygon([[0, 0], [w, 0], [w, h], [0, h]], closed=True, fill=False, edgecolor="black"))
        if roi is not None:
            for k, loop in enumerate(roi.outline_uv()):
                a.plot(loop[:, 0], loop[:, 1], "-", color="purple", lw=1.2, label="ROI" if k == 0 else None)
        a.set_xlim(-0.03 * w, 1.03 * w)
        a.set_ylim(1.03 * h, -0.03 * h)
        a.set_aspect("equal")
        a.set_xlabel("u (px)")
        a.set_ylabel("v (px)")
    uv = cam.project(pts)
    if chosen.leg_speed_m_s is not None:
        for leg in np.unique(chosen.leg):
            sel = chosen.leg == leg
            if sel.sum() > 1:
                # the straight leg in space, sampled, so its image follows the lens
                a3, b3 = pts[sel][:-1], pts[sel][1:]
                f = np.linspace(0, 1, 8)[None, :, None]
                line = (a3[:, None] + f * (b3 - a3)[:, None]).reshape(-1, 3)
                luv = cam.project(line)
                ai.plot(luv[:, 0], luv[:, 1], "-", color="tab:blue", lw=0.8, alpha=0.8)
    d = -veh[:, :2]  # the nose, and the marker, face the pole
    fwd = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    corners = marker_corners(pts, fwd, chosen.marker_size_m)
    cuv = cam.project(corners.reshape(-1, 3)).reshape(-1, 4, 2)
    depth = cam.depth(pts)
    dnorm = Normalize(vmin=float(depth.min()), vmax=float(max(depth.max(), depth.min() + 1e-6)))
    dcol = matplotlib.colormaps["viridis"](dnorm(depth))
    # the depths of one target share its pixel: draw the near (large) markers first so the far ones stay visible on top
    for k in np.argsort(depth):
        q, c, hd = cuv[k], dcol[k], hold[k]
        ai.add_patch(Polygon(q, closed=True, facecolor=c if hd else "none", edgecolor="black" if hd else c, lw=0.4 if hd else 1.0))
    ai.scatter(uv[:, 0], uv[:, 1], s=3, c="black", zorder=3)
    sm = matplotlib.cm.ScalarMappable(norm=dnorm, cmap="viridis")
    same_ray = "\n(a target's depths share its pixel)" if chosen.strategy == "image" else ""
    fig.colorbar(sm, ax=ai, label=f"marker distance from the camera (m){same_ray}", shrink=0.7)
    n_hold, n_pass = int(hold.sum()), int((~hold).sum())
    title = f"predicted image {w}x{h}: {n_hold} holds" + (f", {n_pass} fly-through points (open)" if n_pass else "")
    ai.set_title(title + f"\n{chosen.marker_size_m:g} m marker, {chosen.marker_px.min():.0f}-{chosen.marker_px.max():.0f} px; ROI outlined", fontsize=9)
    ai.legend(loc="lower right", fontsize=7)

    # --- predicted error over the ROI
    if err is not None:
        ruv = cam.project(roi_pts)
        order = np.argsort(err)
        sc = ae.scatter(ruv[order, 0], ruv[order, 1], c=err[order], cmap=cmap, norm=norm, s=10, marker="s")
        fig.colorbar(sc, ax=ae, label=f"predicted error, px (colour clipped at p95 {norm.vmax:.2f})", shrink=0.7, extend="max")
        ae.scatter(uv[:, 0], uv[:, 1], s=4, c="tab:cyan", edgecolors="none", zorder=3, label="samples (holds)")
        s = result.summary.get("prediction") or {}
        comb = s.get("combined_px", {})
        ae.set_title(f"predicted error over the ROI: {comb.get('rms', float('nan')):.2f} px RMS, max {comb.get('max', float('nan')):.1f} px\n"
                     f"(noise {s.get('linearised_px', {}).get('rms', float('nan')):.2f} + extrapolation {s.get('extrapolation_px', {}).get('rms', float('nan')):.2f} px RMS, root-sum-square)", fontsize=9)
        ae.legend(loc="lower right", fontsize=7)

    s = result.summary
    f = s["flight"]
    cov = (s.get("coverage") or {}).get("pct")
    cmp_ = (s.get("comparison") or {}).get("prediction")
    fig.suptitle(
        f"{req.name or 'dronecal-field plan'}: {chosen.name} ({chosen.text})\n"
        f"{f['n_flights']} flight(s), {f['flight_time_s'] / 60:.1f} min in all, longest {f['battery_pct']:.0f} % of the battery; "
        f"ROI coverage {cov if cov is not None else float('nan'):.0f} %"
        + (f"; paper-far on the same ROI: {cmp_['combined_px']['rms']:.2f} px RMS" if cmp_ else "")
        + f"; {result.mission.alt_frame_text}",
        fontsize=10,
    )
    fig.tight_layout()
    fig.savefig(os.fspath(path), format="png")


def render_site_preview(plan, path: str | os.PathLike) -> None:
    """Write the preview of a ``plan.multiplan.SitePlan`` to ``path`` (PNG).

    Left, the site from above (ENU at the first pole, north up): poles with
    their keep-out, each camera's ground footprint (cut at 40 m) in its colour,
    the route, and every hold coloured by the camera it faces, ringed when
    other cameras read it too. Right, one small panel per camera: its image
    with its ROI outline, the cells its samples reach (shaded: its coverage)
    and the samples it reads, its own filled, other cameras' open.
    """
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Polygon

    from dronecal_field.plan.stage import footprint_site

    base = plan.base
    R = base.site.R_enu_from_site
    cams = plan.cameras
    pts = plan.points
    colours = matplotlib.colormaps["tab10"]

    def en(p: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(np.asarray(p, float))
        if p.shape[1] == 2:
            p = np.column_stack([p, np.zeros(len(p))])
        return (p @ R.T)[:, :2]

    n = len(cams)
    cols = 2 if n > 1 else 1
    rows = int(np.ceil(n / cols))
    fig = Figure(figsize=(9 + 5.2 * cols, max(7.5, 3.4 * rows)), dpi=100)
    FigureCanvasAgg(fig)
    gs = fig.add_gridspec(rows, 1 + cols, width_ratios=[1.9] + [1.0] * cols)
    ax = fig.add_subplot(gs[:, 0])
    span = [en(pts.vehicle)]
    for i, cam in enumerate(cams):
        fp = cam.to_ref(np.column_stack([footprint_site(cam.camera_site), np.zeros(len(footprint_site(cam.camera_site)))]))
        cov = plan.coverage[i]
        ax.add_patch(Polygon(en(fp), closed=True, facecolor=colours(i), edgecolor=colours(i), alpha=0.12, lw=1.2,
                             label=f"{cam.name}: footprint; ROI covered {100 * cov:.0f} %"))
        c = en(cam.camera_ref.pose.position_world[None])[0]
        a = R @ cam.R_ref_from_own @ np.array([4.0, 0.0, 0.0])
        ax.annotate("", xy=(c[0] + a[0], c[1] + a[1]), xytext=(c[0], c[1]), arrowprops={"arrowstyle": "->", "color": colours(i), "lw": 1.8})
    for p in plan.summary["poles"]:
        e, nn = p["position_enu_m"][0], p["position_enu_m"][1]
        if p["keep_out_m"] > 0:
            ax.add_patch(Circle((e, nn), p["keep_out_m"], facecolor="#ffd6d6", edgecolor="red", ls=":", zorder=2))
        ax.plot(e, nn, marker="^", color="black", ms=11, ls="none", zorder=6)
        ax.annotate(f"pole {p['name']}", (e, nn), textcoords="offset points", xytext=(6, -12), fontsize=9, weight="bold")
        span.append(np.array([[e, nn]]))
    path_col = ["0.3", "tab:olive", "tab:cyan", "tab:pink"]
    for k, r in enumerate(plan.routes):
        track = np.vstack([r.takeoff_site[None], r.points] + ([r.takeoff_site[None]] if r.end == "land" else []))
        te = en(track)
        ax.plot(te[:, 0], te[:, 1], "-", color=path_col[k % len(path_col)], lw=0.7, zorder=3,
                label="route" if len(plan.routes) == 1 else f"flight {k + 1}")
    ve = en(pts.vehicle)
    shared = plan.seen_holds.sum(axis=0) > 1
    for i, cam in enumerate(cams):
        sel = pts.owner == i
        ax.scatter(*ve[sel].T, s=16, color=colours(i), edgecolors="black", linewidths=0.3, zorder=4)
    if shared.any():
        ax.scatter(*ve[shared].T, s=60, facecolors="none", edgecolors="black", linewidths=0.8, zorder=5, label="hold read by 2+ cameras")
    t = en(plan.routes[0].takeoff_site[None])[0]
    ax.plot(*t, marker="*", color="green", ms=14, ls="none", label="take-off / land", zorder=6)
    span = np.vstack(span + [t[None]])
    lo, hi = span.min(axis=0) - 6, span.max(axis=0) + 6
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_xlabel(f"east of pole {cams[0].pole} (m)")
    ax.set_ylabel(f"north of pole {cams[0].pole} (m)")
    ax.set_title("the site from above (north up): holds coloured by the camera they face", fontsize=10)
    ax.legend(loc="best", fontsize=7, framealpha=0.6)

    for i, cam in enumerate(cams):
        a = fig.add_subplot(gs[i // cols, 1 + i % cols])
        w, h = cam.camera_site.width, cam.camera_site.height
        a.add_patch(Polygon([[0, 0], [w, 0], [w, h], [0, h]], closed=True, fill=False, edgecolor="black"))
        S = cam.from_ref(pts.samples[plan.seen_samples[i]])
        own = pts.samples_owner[plan.seen_samples[i]] == i
        uv = cam.camera_site.project(S)
        roi = cam.roi
        if roi is not None:
            du, dv = roi.cell_px
            reached = np.zeros_like(roi.cells)
            ok = np.all(np.isfinite(uv), axis=1)
            if ok.any():
                r_, c_ = roi.cell_of(uv[ok])
                ny, nx = roi.cells.shape
                for dr in (-1, 0, 1):
                    for dc in (-1, 0, 1):
                        rr, cc = r_ + dr, c_ + dc
                        inside = (rr >= 0) & (rr < ny) & (cc >= 0) & (cc < nx)
                        reached[rr[inside], cc[inside]] = True
            for (rr, cc) in zip(*np.nonzero(reached & roi.cells)):
                a.add_patch(Polygon([[cc * du, rr * dv], [(cc + 1) * du, rr * dv], [(cc + 1) * du, (rr + 1) * dv], [cc * du, (rr + 1) * dv]],
                                    closed=True, facecolor=colours(i), alpha=0.18, edgecolor="none"))
            for k, loop in enumerate(roi.outline_uv()):
                a.plot(loop[:, 0], loop[:, 1], "-", color="purple", lw=1.0, label="ROI" if k == 0 else None)
        a.scatter(uv[own, 0], uv[own, 1], s=7, color=colours(i), edgecolors="black", linewidths=0.2, label="its own samples", zorder=3)
        if (~own).any():
            a.scatter(uv[~own, 0], uv[~own, 1], s=12, facecolors="none", edgecolors="black", linewidths=0.5, label="other cameras' samples", zorder=3)
        a.set_xlim(-0.03 * w, 1.03 * w)
        a.set_ylim(1.03 * h, -0.03 * h)
        a.set_aspect("equal")
        a.tick_params(labelsize=6)
        e = plan.summary["cameras"][i]
        px = e["predicted_roi_px_rms"]
        a.set_title(f"{cam.name} ({w}x{h}, f {cam.camera_site.intrinsics.fx:.0f} px): ROI covered {e['coverage']['pct']:.0f} %\n"
                    f"{e['holds_owned']} own holds, {e['holds_seen']} read; predicted {'-' if px is None else f'{px:.2f}'} px RMS, "
                    f"ground {e['predicted_ground_cm_rms'] if e['predicted_ground_cm_rms'] is not None else '-'} cm", fontsize=8)
        if i == 0:
            a.legend(loc="lower right", fontsize=6)
    f = plan.summary["flight"]
    fig.suptitle(f"{plan.request.name or 'dronecal-field site plan'}: {n} cameras, {f['n_flights']} flight(s), {f['flight_time_s'] / 60:.1f} min "
                 f"(budget {f['budget_s'] / 60:.1f} min), marker {plan.marker_size_m:g} m", fontsize=11)
    fig.tight_layout()
    fig.savefig(os.fspath(path), format="png")
