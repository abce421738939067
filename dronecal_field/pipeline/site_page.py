"""The files of a site (several cameras in one run): ``site.json`` and the site's ``report.html``.

Each camera's own files (camera.yaml, report.json, report.html, ...) are
written by ``pipeline.report.write_outputs`` into ``<out>/<name>/``; this
module writes, beside those folders, what relates the cameras: every pair's
relative pose with its uncertainty, and a top view of the site (poles, each
camera's ground footprint 3-30 m, the flight track) as an inline SVG.
"""

from __future__ import annotations

import html
import json
import os
import tempfile
from pathlib import Path

import numpy as np

from dronecal_field.pipeline.site import GROUND_RANGE_M, POSE_SAMPLES, footprints, hull_xy, pose_samples

SITE_JSON = "site.json"
SITE_HTML = "report.html"
COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#8c564b", "#e377c2")


def site_dict(site) -> dict:
    """site.json: the run(s), the ENU frame, each camera (its folder, where it is, how well), every pair."""
    cameras = []
    for name, report in site.cameras.items():
        cam = report.camera
        mc = report.monte_carlo or report.linearised
        _, centres = pose_samples(cam, report.covariance_measured, POSE_SAMPLES, np.random.default_rng(0))
        pos_std = centres.std(axis=0, ddof=1).tolist() if report.covariance_measured is not None else None
        cameras.append({
            "name": name,
            "folder": name,
            "camera_yaml": f"{name}/camera.yaml",
            "report_html": f"{name}/report.html",
            "image_size": [int(cam.width), int(cam.height)],
            "position_enu_m": cam.pose.position_world.tolist(),
            "rotation_world_to_camera": cam.pose.R_cam_from_world.tolist(),
            "position_std_enu_m": pos_std,
            "model": report.result.model.name,
            "rms_px": float(report.result.rms_px),
            "points_used": len(report.used_points),
            "time_offset_s": float(report.offset.offset_s),
            "time_offset_std_s": report.offset.std_s,
            "ground_error_15m_cm": None if mc is None else float(mc.ground_error_15m_cm),
            "error": None,
        })
    cameras += [{"name": name, "folder": name, "error": error} for name, error in site.failed.items()]
    return {
        "runs": [str(p) for p in site.run_paths],
        "enu_origin": None if site.origin is None else site.origin.as_list(),
        "frame": "ENU at enu_origin (lat deg, lon deg, h m); every camera.yaml of the site is in it",
        "cameras": cameras,
        "pairs": [p.to_dict() for p in site.pairs],
        "timings_s": {k: round(v, 3) for k, v in site.timings_s.items()},
    }


def write_site(site, out_dir: Path) -> dict[str, str]:
    """Write site.json and the site's report.html into ``out_dir`` (each atomically); returns their paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = site_dict(site)
    outputs = {"site_json": str(out_dir / SITE_JSON), "report_html": str(out_dir / SITE_HTML)}
    _atomic_write(out_dir / SITE_JSON, json.dumps(data, indent=2, allow_nan=False, default=_plain))
    _atomic_write(out_dir / SITE_HTML, site_html(site, data))
    return outputs


def _plain(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    raise TypeError(f"{type(value).__name__} is not JSON")


def _atomic_write(path: Path, text: str) -> None:
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=".tmp")
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, path)


def top_view_svg(site, size_px: int = 640) -> str:
    """An SVG top view of the site: each camera's ground footprint (3-30 m), its pole and viewing direction, the flight."""
    cams = {name: r.camera for name, r in site.cameras.items()}
    grid, seen = footprints(cams)
    track = next(iter(site.cameras.values())).track.antenna_enu_m
    hulls = {name: hull_xy(grid[s]) for name, s in seen.items() if s.any()}
    xy = [c.pose.position_world[:2][None] for c in cams.values()] + [h for h in hulls.values()] + [track[:, :2]]
    allxy = np.concatenate([a for a in xy if len(a)])
    lo, hi = allxy.min(axis=0) - 2.0, allxy.max(axis=0) + 2.0
    scale = (size_px - 20) / float(max(hi - lo))
    h_px = int((hi[1] - lo[1]) * scale) + 20

    def xy_px(p) -> tuple[float, float]:
        return 10 + (p[0] - lo[0]) * scale, h_px - 10 - (p[1] - lo[1]) * scale

    def pt(p) -> str:
        x, y = xy_px(p)
        return f"{x:.1f},{y:.1f}"

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{size_px}" height="{h_px}" style="background:#fafafa;border:1px solid #ccc">']
    for k, (name, hull) in enumerate(hulls.items()):
        colour = COLOURS[list(cams).index(name) % len(COLOURS)]
        parts.append(f'<polygon points="{" ".join(pt(p) for p in hull)}" fill="{colour}" fill-opacity="0.18" stroke="{colour}"/>')
    if len(track):
        step = max(1, len(track) // 2000)
        parts.append(f'<polyline points="{" ".join(pt(p) for p in track[::step])}" fill="none" stroke="#555" stroke-width="0.8"/>')
    labelled: list[np.ndarray] = []
    for k, (name, cam) in enumerate(cams.items()):
        colour = COLOURS[k % len(COLOURS)]
        c = cam.pose.position_world
        on_pole = sum(1 for q in labelled if np.hypot(*(q[:2] - c[:2])) < 1.0)  # cameras of one pole: labels stacked, not overprinted
        labelled.append(np.asarray(c, float))
        f = cam.pose.R_cam_from_world[2]
        (x0, y0), (x1, y1) = xy_px(c), xy_px(c[:2] + 4.0 * f[:2] / max(np.hypot(f[0], f[1]), 1e-9))
        parts.append(f'<line x1="{x0:.1f}" y1="{y0:.1f}" x2="{x1:.1f}" y2="{y1:.1f}" stroke="{colour}" stroke-width="2"/>')
        parts.append(f'<circle cx="{x0:.1f}" cy="{y0:.1f}" r="4" fill="{colour}"/>')
        parts.append(f'<text x="{x0 + 6:.1f}" y="{y0 - 6 - 14 * on_pole:.1f}" font-size="12" fill="{colour}">{html.escape(name)}</text>')
    metres = 10.0 if max(hi - lo) > 25 else 5.0
    parts.append(f'<line x1="10" y1="{h_px - 5}" x2="{10 + metres * scale:.1f}" y2="{h_px - 5}" stroke="#000" stroke-width="2"/>')
    parts.append(f'<text x="{14 + metres * scale:.1f}" y="{h_px - 3}" font-size="11">{metres:g} m (north up)</text>')
    parts.append("</svg>")
    return "".join(parts)


def site_html(site, data: dict) -> str:
    """The site's report.html: the top view, a table of cameras (linking their reports) and of every pair."""
    def cell(v) -> str:
        return f"<td>{html.escape(str(v))}</td>"

    rows = []
    for c in data["cameras"]:
        if c.get("error"):
            rows.append(f"<tr>{cell(c['name'])}<td colspan='6'>not calibrated: {html.escape(c['error'])}</td></tr>")
            continue
        p = c["position_enu_m"]
        rows.append(
            f"<tr><td><a href='{html.escape(c['report_html'])}'>{html.escape(c['name'])}</a></td>"
            + cell(f"{c['image_size'][0]}x{c['image_size'][1]}") + cell(f"{p[0]:.3f}, {p[1]:.3f}, {p[2]:.3f}")
            + cell(c["model"]) + cell(f"{c['rms_px']:.3f}") + cell(f"{c['time_offset_s']:+.3f}")
            + cell("-" if c["ground_error_15m_cm"] is None else f"{c['ground_error_15m_cm']:.1f}") + "</tr>"
        )
    pairs = []
    for p in site.pairs:
        t = p.translation_in_a_m
        pairs.append(
            "<tr>" + cell(f"{p.b} from {p.a}") + cell(f"{p.distance_m:.3f} \u00b1 {1000 * p.distance_std_m:.1f} mm")
            + cell(f"{t[0]:.3f}, {t[1]:.3f}, {t[2]:.3f} (\u00b1 {1000 * p.translation_std_m:.1f} mm)")
            + cell(f"{p.rotation_deg:.3f}\u00b0 \u00b1 {p.rotation_std_deg:.3f}\u00b0")
            + cell(f"{p.shared_ground_m2:.0f} m\u00b2" if p.shares_ground else "none") + "</tr>"
        )
    runs = ", ".join(html.escape(Path(r).name) for r in data["runs"])
    return (
        "<!doctype html><html><head><meta charset='utf-8'><title>dronecal-field site</title>"
        "<style>body{font-family:sans-serif;margin:2em}td,th{padding:3px 8px;border-bottom:1px solid #ddd}</style></head><body>"
        f"<h1>Site: {len(data['cameras'])} cameras from {runs}"
        + (f", {len(site.cameras)} calibrated" if len(site.cameras) != len(data["cameras"]) else "") + "</h1>"
        f"<p>Every camera is in one ENU frame (origin {_origin_text(data['enu_origin'])}). Top view: each camera's ground footprint "
        f"{GROUND_RANGE_M[0]:g}-{GROUND_RANGE_M[1]:g} m from its pole, the pole and viewing direction, the flight track.</p>"
        + top_view_svg(site)
        + "<h2>Cameras</h2><table><tr><th>camera</th><th>image</th><th>position ENU (m)</th><th>model</th><th>RMS (px)</th>"
          "<th>time offset (s)</th><th>ground error at 15 m (cm)</th></tr>" + "".join(rows) + "</table>"
        + "<h2>Relative poses</h2><p>B's centre in A's camera frame (x right, y down, z forward) and the rotation from A's "
          "frame to B's, with 1-sigma uncertainties from each camera's pose covariance (the two taken as independent: their "
          "shared GNSS noise cancels in the difference, so this leans towards over-stating the spread).</p><table><tr><th>pair</th><th>distance</th><th>B in A's frame (m)</th>"
          "<th>rotation</th><th>ground both see</th></tr>" + "".join(pairs) + "</table>"
        + "</body></html>"
    )


def _origin_text(origin) -> str:
    """'-35.36326100, 149.16523000, 584.004 m' (lat, lon in degrees, height), not a list of 17-digit floats."""
    try:
        lat, lon, h = (float(v) for v in origin)
    except (TypeError, ValueError):
        return str(origin)
    return f"{lat:.8f}, {lon:.8f}, {h:.3f} m"
