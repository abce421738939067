"""``survey report``: the paper's findings and Figures 8-10 from stored results, as PNG, HTML and JSON.

A stage: reads a results directory (or exported file), writes files into an
output directory and returns what it wrote. Figure 10 is not in the survey
table (it varies the sampling distance of one camera), so it is computed
here with the engine: a few dozen Monte-Carlo runs, seconds.
"""

from __future__ import annotations

import html
import json
import os
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dronecal_field.survey.catalogue import RECOMMENDED, PaperLattice
from dronecal_field.survey.evaluate import STATUS_OK, MonteCarloSettings, evaluate_camera
from dronecal_field.survey.findings import Finding, format_findings, near_winners_fov, paper_findings, status_counts

# The paper's Figure 10 camera: f = 1,000 px, 1,200 px images (square, as its Figure 1), 45 deg, 4 m.
FIG10_FOCAL_PX = 1000.0
FIG10_SIZE_PX = (1200, 1200)
FIG10_TILT_DEG = 45.0
FIG10_ELEVATION_M = 4.0
FIG10_DISTANCES_M = tuple(float(d) for d in range(3, 13))


@dataclass(frozen=True)
class DistanceCurve:
    """Figure 10's data: mean RMS reprojection error (px) per maximum sampling distance (m); NaN where degenerate."""

    distances_m: np.ndarray  # (D,)
    with_gnss_px: np.ndarray  # (D,)
    image_only_px: np.ndarray  # (D,)
    n_points: np.ndarray  # (D,)


def distance_curve(distances_m=FIG10_DISTANCES_M, settings: MonteCarloSettings = MonteCarloSettings()) -> DistanceCurve:
    """The paper's Figure 10: error against the maximum sampling distance, with and without GNSS noise.

    Points every 1 m along X from 0 to the distance and along Y within
    +-3 m, at the paper lattice's two heights, those the camera sees; the
    curve without GNSS noise sets sigma_3d to 0 (2D detection noise only).
    """
    from dronecal_field.sampling.lattice import Strategy

    from dronecal_field.core.synthetic import pole_camera

    cam = pole_camera(FIG10_FOCAL_PX, *FIG10_SIZE_PX, (0.0, 0.0, FIG10_ELEVATION_M), FIG10_TILT_DEG)
    lattice = PaperLattice()
    no_gnss = replace(settings, sigma_3d=(0.0, 0.0, 0.0))
    d = np.asarray(distances_m, float)
    gnss, image, n = np.full(len(d), np.nan), np.full(len(d), np.nan), np.zeros(len(d), int)
    for k, dist in enumerate(d):
        points = lattice.points(Strategy(name=f"0-{dist:g}", x_min_m=0.0, x_max_m=dist), cam)
        n[k] = len(points)
        a = evaluate_camera(cam, points, settings, settings.seed)
        b = evaluate_camera(cam, points, no_gnss, settings.seed)
        if a["status"] == STATUS_OK and b["status"] == STATUS_OK:
            gnss[k], image[k] = a["rms_mean"], b["rms_mean"]
    return DistanceCurve(distances_m=d, with_gnss_px=gnss, image_only_px=image, n_points=n)


@dataclass(frozen=True)
class ReportFiles:
    """What ``write_report`` wrote, and the findings it computed."""

    html: Path
    json: Path
    figures: dict[str, Path]
    findings: tuple[Finding, ...]
    text: str


def write_report(results: str | os.PathLike, out_dir: str | os.PathLike, fig10_trials: int | None = None) -> ReportFiles:
    """Findings table and Figures 8, 9, 10 of a survey, into ``out_dir``.

    Parameters
    ----------
    results : survey results directory or exported parquet file
    out_dir : created if needed; receives figure8.png, figure9.png,
        figure10.png, findings.json and index.html as one set (written into a
        temporary sibling that replaces the folder; other files in it are kept)
    fig10_trials : Monte-Carlo trials of Figure 10 (default: the survey's)
    """
    from dronecal_field.outfolder import replace_folder, staged_folder
    from dronecal_field.survey.store import load_results, read_config

    table = load_results(results)
    config = read_config(results) or {}
    mc_cfg = config.get("monte_carlo", {})
    settings = MonteCarloSettings(
        trials=int(fig10_trials if fig10_trials is not None else mc_cfg.get("trials", 500)),
        sigma_3d=tuple(mc_cfg.get("sigma_3d", (0.01, 0.01, 0.015))),  # type: ignore[arg-type]
        sigma_2d=float(mc_cfg.get("sigma_2d", 2.0)),
        model=str(mc_cfg.get("model", "default")),
        seed=int(mc_cfg.get("seed", 0)),
    )
    final = Path(out_dir)
    with staged_folder(final) as out:
        files = _write_report_files(table, config, settings, results, out)
        replace_folder(out, final, ours=lambda name: name in REPORT_FILES)
    return replace(files, html=final / files.html.name, json=final / files.json.name,
                   figures={k: final / p.name for k, p in files.figures.items()})


REPORT_FILES = ("figure8.png", "figure9.png", "figure10.png", "findings.json", "index.html")


def _write_report_files(table, config: dict, settings: MonteCarloSettings, results, out: Path) -> ReportFiles:
    """The figures, findings.json and index.html of a survey, into the folder ``out``."""
    from dronecal_field.survey import figures

    found = paper_findings(table)
    near = near_winners_fov(table)
    counts = status_counts(table)
    paths = {name: out / f"{name}.png" for name in ("figure8", "figure9", "figure10")}
    n8 = figures.figure8(table, paths["figure8"])
    n9 = figures.figure9(table, paths["figure9"])
    curve = distance_curve(settings=settings)
    figures.figure10(
        curve.distances_m, curve.with_gnss_px, curve.image_only_px, paths["figure10"],
        f"Fig. 10: f {FIG10_FOCAL_PX:.0f} px, {FIG10_SIZE_PX[0]} px, tilt {FIG10_TILT_DEG:.0f} deg, {FIG10_ELEVATION_M:.0f} m",
    )
    n_cameras = len(set(table.column("camera_id").to_pylist()))
    summary = {
        "results": str(results),
        "cameras": n_cameras,
        "rows": table.num_rows,
        "status_by_strategy": counts,
        "config": config,
        "findings": [f.to_dict() for f in found],
        "near_winners_fov": near,
        "figure8_cameras": n8,
        "figure9_cameras": n9,
        "figure10": {
            "distances_m": curve.distances_m.tolist(),
            "with_gnss_px": [None if not np.isfinite(v) else float(v) for v in curve.with_gnss_px],
            "image_only_px": [None if not np.isfinite(v) else float(v) for v in curve.image_only_px],
            "n_points": curve.n_points.tolist(),
            "trials": settings.trials,
        },
    }
    json_path = out / "findings.json"
    json_path.write_text(json.dumps(summary, indent=2))
    html_path = out / "index.html"
    html_path.write_text(_html(summary, found, paths))
    text = format_findings(found)
    return ReportFiles(html=html_path, json=json_path, figures=paths, findings=tuple(found), text=text)


def _fmt(v: float | None, unit: str) -> str:
    if v is None:
        return "&ndash;"
    return f"{v:.0f}&nbsp;%" if unit == "%" else f"{v:.2f}&nbsp;{html.escape(unit)}"


def _html(summary: dict, found: list[Finding], paths: dict[str, Path]) -> str:
    rows = "\n".join(
        f"<tr><td>{html.escape(f.claim)}</td><td>{_fmt(f.paper, f.unit)}</td><td>{_fmt(f.ours_rms, f.unit)}</td>"
        f"<td>{_fmt(f.ours_projection, f.unit)}</td><td>{f.n}</td><td><code>{html.escape(', '.join(f.strategies))}</code></td></tr>"
        for f in found
    )
    status_rows = "\n".join(
        f"<tr><td><code>{html.escape(s)}</code></td>" + "".join(f"<td>{c.get(k, 0)}</td>" for k in ("ok", "degenerate", "failed")) + "</tr>"
        for s, c in sorted(summary["status_by_strategy"].items())
    )
    near = summary["near_winners_fov"]
    near_txt = (
        f"{near['near_winners']} cameras prefer near sampling; {near['extreme_fov_share']:.0f}&nbsp;% of them have a horizontal field of view "
        f"outside the middle half of the survey's ({near['fov_q25']:.0f}&ndash;{near['fov_q75']:.0f}&nbsp;deg); 50&nbsp;% would mean the FOV does not matter."
        if near.get("extreme_fov_share") is not None else "No camera was compared near against far."
    )
    cfg = html.escape(json.dumps(summary["config"], indent=1))
    imgs = "\n".join(f'<h2>{name.replace("figure", "Figure ")}</h2><img src="{p.name}" alt="{name}">' for name, p in paths.items())
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>dronecal-field survey report</title>
<style>body{{font-family:sans-serif;max-width:60em;margin:2em auto}}table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:.3em .6em;text-align:right}}td:first-child{{text-align:left}}img{{max-width:100%}}</style></head>
<body><h1>Camera-by-path survey</h1>
<p>{summary['cameras']} cameras, {summary['rows']} rows from <code>{html.escape(summary['results'])}</code>.
Ours by the paper's metric (mean over trials of the RMS reprojection error) and by the projection error
(distance between where the estimated and the true camera project the sampled points). Only cameras where
all compared strategies calibrate are counted.</p>
<table><tr><th>finding</th><th>paper</th><th>ours (RMS)</th><th>ours (projection)</th><th>cameras</th><th>strategies</th></tr>
{rows}</table>
<p>{near_txt}</p>
<h2>Rows by status</h2>
<table><tr><th>strategy</th><th>ok</th><th>degenerate</th><th>failed</th></tr>{status_rows}</table>
{imgs}
<h2>Configuration</h2><pre>{cfg}</pre>
<p>Recommended strategy of Figure 9: <code>{RECOMMENDED}</code>. Assumptions: docs/survey.md.</p>
</body></html>
"""
