"""The offline stage's files: camera.yaml, camera_info.yaml, report.json, report.html,
ground_homography.yaml, validity.geojson, detections.csv (and, on request, an
annotated copy of the run).

Writers only: every number comes from the CalibrationReport. Files are
written to a temporary name and renamed, so a reader never sees half a file.
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import math
import os
import re
from pathlib import Path

import numpy as np

from dronecal_field.core.camera import PARAM_NAMES
from dronecal_field.errors import InputError
from dronecal_field.pipeline.gnss_quality import gnss_quality_of_report

CAMERA_FILE = "camera.yaml"
CAMERA_INFO_FILE = "camera_info.yaml"
REPORT_JSON = "report.json"
REPORT_HTML = "report.html"
HOMOGRAPHY_FILE = "ground_homography.yaml"
VALIDITY_GEOJSON = "validity.geojson"
DETECTIONS_CSV = "detections.csv"
ANNOTATED_SUFFIX = ".annotated.mcap"
OUTPUT_FILES = (CAMERA_FILE, CAMERA_INFO_FILE, REPORT_JSON, REPORT_HTML, HOMOGRAPHY_FILE, VALIDITY_GEOJSON, DETECTIONS_CSV)


def _atomic_write(path: Path, data: bytes | str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        f.write(data.encode() if isinstance(data, str) else data)
    os.replace(tmp, path)


def _clean(value):
    """JSON-ready copy: numpy to lists/floats, NaN/inf to None (JSON has neither)."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return _clean(value.tolist())
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, Path):
        return str(value)
    return value


# --------------------------------------------------------------------------
# report.json


def _legs_section(report) -> dict:
    """The fly-through legs: where they came from, and the fix-by-fix pairs each one gave."""
    legs = list(getattr(report, "legs", None) or [])
    points = list(getattr(report, "leg_points", []))
    by_leg: dict[int, list] = {}
    for p in points:
        by_leg.setdefault(p.window.seq, []).append(p)  # a leg pair's window is its fix; seq is its leg
    rows = []
    for leg in legs:
        pts = by_leg.get(leg.index, [])
        used = [p for p in pts if p.used and p.marker_enu_m is not None]
        rows.append({
            "index": leg.index, "source": leg.source, "start_ns": leg.start_ns, "end_ns": leg.end_ns,
            "duration_s": round(leg.duration_s, 3), "speed_m_s": leg.speed_mps,
            "pairs": len(pts), "pairs_used": len(used),
            # a leg is straight: its first and last used pair span the volume it sampled
            "used_marker_enu_m": [[float(v) for v in used[0].marker_enu_m], [float(v) for v in used[-1].marker_enu_m]] if used else [],
        })
    return {
        "source": getattr(report, "leg_source", None),
        "count": len(legs),
        "pairs": len(points),
        "pairs_used": sum(1 for p in points if p.used),
        "pairing": "one pair per GNSS fix on a leg: the marker's ENU position with its pixel interpolated along the leg's "
                   "image track at the fix instant (after the camera-GNSS offset and the rolling shutter); each pair's sigma "
                   "includes its timing uncertainty",
        "legs": rows,
        "agreement": agreement.to_dict() if (agreement := getattr(report, "agreement", None)) is not None else None,
    }


def report_dict(report) -> dict:
    """Every number of the report, JSON-ready (the content of report.json)."""
    from dronecal_field import __version__
    from dronecal_field.geodesy import enu_to_geodetic

    md = report.metadata
    cam = report.camera
    res = report.result
    used = report.used_points
    residual_by_window = {p.window.index: res.residuals_px[i] for i, p in enumerate(used)}
    outlier_windows = {used[i].window.index for i in res.outliers}
    hover = getattr(report, "hover_points", report.points)
    windows = []
    for p in hover:
        w = p.window
        entry = {
            "index": w.index,
            "seq": w.seq,
            "source": w.source,
            "start_ns": w.start_ns,
            "end_ns": w.end_ns,
            "duration_s": w.duration_s,
            "stable_start_ns": p.stable_ns[0],
            "stable_end_ns": p.stable_ns[1],
            "n_fixes": p.n_fixes,
            "n_detections": p.n_detections,
            "worst_fix": p.worst_fix,
            "used": p.used,
            "dropped": p.dropped,
            "marker_enu_m": p.marker_enu_m,
            "sigma_enu_m": p.sigma_enu_m,
            "scatter_enu_m": p.scatter_enu_m,
            "uv_px": p.uv_px,
            "sigma_px": p.sigma_px,
            "scatter_px": p.scatter_px,
        }
        if w.index in residual_by_window:
            r = residual_by_window[w.index]
            entry["residual_px"] = r
            entry["residual_norm_px"] = float(np.linalg.norm(r))
            entry["outlier"] = w.index in outlier_windows
        windows.append(entry)
    position = cam.pose.position_world
    position_wgs84 = enu_to_geodetic(position[None], report.origin)[0]
    std_calib = {name: float(np.sqrt(max(report.result.camera.covariance[i, i], 0.0))) for i, name in enumerate(PARAM_NAMES)}
    std_measured = {name: float(np.sqrt(max(report.covariance_measured[i, i], 0.0))) for i, name in enumerate(PARAM_NAMES)}

    def unc(u):
        if u is None:
            return None
        d = u.to_dict()
        return d

    mc, lin = report.monte_carlo, report.linearised
    headline = mc if mc is not None else lin
    validity = getattr(report, "validity", None)
    out = {
        "tool": {"name": "dronecal-field", "version": __version__, "stage": "calibrate"},
        "run": {
            "path": str(report.run_path),
            "truncated": report.truncated,
            "reader_warnings": report.run_warnings,
            "format_version": md.format_version,
            "image_size": [md.width, md.height],
            "marker": {
                "kind": md.marker.kind,
                "dictionary": md.marker.dictionary,
                "id": md.marker.marker_id,
                "size_m": md.marker.size_m,
                "offset_frd_m": list(md.marker.offset_frd_m),
            },
            "camera_latency_s_declared": md.camera_latency_s,
            # a several-camera run: which of its cameras this report is of (one-camera runs have no such key)
            **({"camera": md.camera_name, "cameras": list(md.camera_names())} if getattr(md, "camera_name", None) else {}),
        },
        "frame": {
            "enu_origin": {"lat_deg": report.origin.lat_deg, "lon_deg": report.origin.lon_deg, "h_m": report.origin.h_m},
            "enu_origin_source": report.origin_source,
            "altitude_datum": report.altitude_datum,
            "note": "world frame is ENU at enu_origin; heights are metres above the stated datum",
        },
        "gnss": {
            "fixes_used": int(len(report.track.t_ns)),
            "fix_types": {t or "unknown": int(sum(1 for x in report.track.fix_types if x == t)) for t in sorted(set(report.track.fix_types), key=str)},
            "min_fix": report.options.min_fix,
            "attitude": report.attitude_source,
            "fix_rate_hz": _fix_rate_hz(report),
            "repeated_fixes_left_out": report.fixes_repeated,
            "fix_times": report.offset.gnss_times,
            "quality": list(gnss_quality_of_report(report).sentences),  # what the reported accuracy means (pipeline/gnss_quality.py)
        },
        "points": {
            "pairing": (
                "at each fix: the marker's ENU position with its pixel interpolated along the image track"
                if report.options.points.paired and report.options.points.pair_at == "fixes"
                else "at each detection: the GNSS track interpolated at the frame" if report.options.points.paired else "separate medians"
            ),
            "marker_centre": report.centres,
        },
        "hover_windows": {
            "source": report.window_source,
            "count": len(report.windows),
            "used": sum(1 for p in hover if p.used),
            "dropped": [{"index": p.window.index, "seq": p.window.seq, "reason": p.dropped} for p in hover if not p.used],
            "windows": windows,
        },
        "legs": _legs_section(report),
        "frames": report.frames.to_dict(),
        "time_offset": report.offset.to_dict(),
        "calibration": {
            "model": res.model.name,
            "model_reason": report.model_reason,
            "free_parameters": list(res.model.free_names()),
            "loss": res.loss,
            "loss_scale_px": report.options.loss_scale_px,
            "n_points": len(used),
            "rms_px": res.rms_px,
            "residual_sigma_px": res.residual_sigma_px,
            "iterations": res.iterations,
            "outliers": [
                {"window": used[i].window.index, "seq": used[i].window.seq, "residual_norm_px": float(np.linalg.norm(res.residuals_px[i]))}
                for i in res.outliers
            ],
            "camera": {
                "image_size": [cam.width, cam.height],
                "fx": cam.intrinsics.fx, "fy": cam.intrinsics.fy, "cx": cam.intrinsics.cx, "cy": cam.intrinsics.cy,
                "distortion": {k: float(v) for k, v in zip(("k1", "k2", "p1", "p2", "k3"), cam.distortion.as_array())},
                "rotation_world_to_camera": cam.pose.R_cam_from_world,
                "camera_position_enu_m": position,
                "camera_position_wgs84": {"lat_deg": position_wgs84[0], "lon_deg": position_wgs84[1], "h_m": position_wgs84[2], "datum": report.altitude_datum},
            },
            "parameter_std_from_residuals": std_calib,
            "parameter_std_from_measured_sigmas": std_measured,
        },
        "uncertainty": {
            "sigmas": {
                "sigma_3d_m_median": np.median(np.array([p.sigma_enu_m for p in used]), axis=0),
                "sigma_2d_px_median": float(np.median([p.sigma_px for p in used])),
                "scale": float(report.sigma_scale),  # applied to both for every uncertainty figure (run.sigma_scale)
            },
            "monte_carlo": unc(mc),
            "linearised": unc(lin),
            # the expected RMS scales with the sigmas: the headline's over the scale is what the measured ones predict
            "consistency": sigma_consistency(
                report.result.rms_px, None if headline is None else headline.rms_mean / report.sigma_scale,
                report.sigma_scale),
            "image_map": report.maps.summary(),
            "at_15m": None if headline is None else {
                "method": headline.method,
                "ground_position_error_cm": headline.ground_error_15m_cm,
                "ground_position_error_cm_p95": headline.ground_error_15m_cm_p95,
                "speed_error_kmh_at_50kmh": headline.speed_error_15m_kmh,
                "speed_error_kmh_p95": headline.speed_error_15m_kmh_p95,
                # the heading point against the region of validity, and the ring across the view (pipeline.ground15)
                **({} if getattr(validity, "at_15m", None) is None else validity.at_15m.to_dict()),
            },
            "over_validity_region": None if validity is None else {
                "method": "90 % bound: 1.645 x the linearised std (measured sigmas), root-sum-square with the "
                          "model extrapolation, over the visible ground 3-30 m inside the region",
                "ground_position_error_cm_rms": validity.inside_cm_rms,
                "ground_position_error_cm_max": validity.inside_cm_max,
                "projection_error_px_rms": validity.inside_px_rms,
                "projection_error_px_max": validity.inside_px_max,
            },
        },
        "validity": None if validity is None else validity.to_dict(),
        "ground_homography": {"H_image_from_ground": report.homography, "pixels": "undistorted"},
        "timings_s": report.timings_s,
        "warnings": all_warnings(report),
        "options": {
            "min_fix": report.options.min_fix, "model": report.options.model, "loss": report.options.loss,
            "trials": report.options.trials, "seed": report.options.seed, "hover_source": report.options.hover_source,
            "settle_s": report.options.points.settle_s, "tail_s": report.options.points.tail_s,
            "max_offset_s": report.options.max_offset_s,
            "max_frames_per_window": report.options.sampling.max_frames_per_window,
        },
        "outputs": dict(report.outputs),
    }
    if getattr(report, "runs", None):  # a joint calibration (pipeline/joint.py): which runs, and each one's part, first
        out = {"tool": out.pop("tool"), "joint": _joint_section(report), **out}
    return _clean(out)


def _joint_section(report) -> dict:
    """report.json's ``joint``: the runs pooled into this one camera, the points each gave and each one's time offset."""
    runs = report.runs
    return {
        "runs": [r.to_dict() for r in runs],
        "n_runs": len(runs),
        "points_used": sum(r.used for r in runs),
        "frame": "every run's points in the ENU frame of the first run (frame.enu_origin); window numbers run on from one run to the next",
        "text": "one calibration from the points of every run: each run's points were paired on its own clock (its own time offset, "
                "rolling shutter and noise, from its own solve when it calibrates alone), then one solve and one uncertainty on all of them; "
                "run, time_offset and frames below are the first run's or the sum",
    }


def _joint_rows(report) -> str:
    """report.html's table of the pooled runs (empty for a single run)."""
    runs = getattr(report, "runs", None)
    if not runs:
        return ""
    rows = "".join(
        f"<tr><td>{html.escape(Path(r.path).name)}</td><td>{'' if r.flight is None else r.flight}</td><td>{r.used}</td>"
        f"<td>{len(r.windows)} / {len(r.legs)}</td>"
        f"<td>{offset_text(r.offset.offset_s, r.offset.std_s)} ({html.escape(str(r.offset.method))})</td>"
        f"<td>{'alone first, ' + _fmt(r.alone_rms_px, '.2f', ' px') if r.alone else html.escape('paired at its motion offset: ' + str(r.alone_reason))}</td></tr>"
        for r in runs
    )
    return ("<h2>Runs calibrated together</h2><table><tr><th>run</th><th>flight</th><th>points used</th><th>hover windows / legs</th>"
            f"<th>camera time offset</th><th>its own solve</th></tr>{rows}</table>"
            "<p style='font-size:13px'>Each run keeps its own camera clock; per-run windows, legs and frames are in report.json (joint.runs).</p>")


# --------------------------------------------------------------------------
# YAML files


def _yaml_matrix(name: str, m: np.ndarray, indent: str = "") -> str:
    m = np.atleast_2d(np.asarray(m, float))
    data = ", ".join(repr(float(v)) for v in m.ravel())
    return f"{indent}{name}:\n{indent}  rows: {m.shape[0]}\n{indent}  cols: {m.shape[1]}\n{indent}  data: [{data}]\n"


def camera_info_yaml(camera, camera_name: str = "dronecal") -> str:
    """ROS ``sensor_msgs/CameraInfo`` YAML (camera_calibration_parsers' format), plumb_bob model."""
    K = camera.intrinsics.matrix
    P = np.c_[K, np.zeros(3)]
    return (
        f"image_width: {int(camera.width)}\n"
        f"image_height: {int(camera.height)}\n"
        f"camera_name: {camera_name}\n"
        + _yaml_matrix("camera_matrix", K)
        + "distortion_model: plumb_bob\n"
        + _yaml_matrix("distortion_coefficients", camera.distortion.as_array()[None])
        + _yaml_matrix("rectification_matrix", np.eye(3))
        + _yaml_matrix("projection_matrix", P)
    )


def homography_yaml(report) -> str:
    """ground_homography.yaml: H (image from ground z = 0 ENU), its inverse, and how to use them."""
    H = np.asarray(report.homography, float)
    Hinv = np.linalg.inv(H)
    Hinv /= Hinv[2, 2]
    o = report.origin
    cam = report.camera
    return (
        "# Image <-> ground plane z = 0 of the ENU frame at enu_origin (metres).\n"
        "# [u, v, 1] ~ H_image_from_ground [E, N, 1] for UNDISTORTED pixels: undistort a measured\n"
        "# pixel with camera_matrix and distortion_coefficients first (cv2.undistortPoints(..., P=K)).\n"
        "# Speed: map two image positions dt apart to the ground, distance / dt.\n"
        f"enu_origin: [{o.lat_deg!r}, {o.lon_deg!r}, {o.h_m!r}]\n"
        f"altitude_datum: {report.altitude_datum}\n"
        "ground_z_m: 0.0\n"
        f"image_width: {cam.width}\nimage_height: {cam.height}\n"
        + _yaml_matrix("H_image_from_ground", H)
        + _yaml_matrix("H_ground_from_image", Hinv)
        + _yaml_matrix("camera_matrix", cam.intrinsics.matrix)
        + _yaml_matrix("distortion_coefficients", cam.distortion.as_array()[None])
        + _validity_yaml(getattr(report, "validity", None))
    )


def _validity_yaml(validity) -> str:
    """The region of validity for ground_homography.yaml: pixel polygon and its ground footprint (ENU)."""
    if validity is None:
        return ""
    out = (
        "# Region of validity: measure only inside validity_polygon_px (DISTORTED pixels, as measured;\n"
        "# cv2.pointPolygonTest), i.e. on the ground inside validity_ground_enu_m (E, N, z metres).\n"
        + _yaml_matrix("validity_polygon_px", validity.polygon_px)
    )
    if validity.ground_polygon_enu_m is not None:
        out += _yaml_matrix("validity_ground_enu_m", validity.ground_polygon_enu_m)
    return out


def detections_csv(report) -> str:
    """detections.csv: one row per detection, the hover window it falls in (if any), and its use.

    ``capture_ns`` is the frame stamp corrected by the estimated camera
    offset (GNSS clock); ``window`` is the window containing that time.
    """
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    header = ["timestamp_ns", "capture_ns", "window", "seq", "kind", "u_px", "v_px", "size_px", "in_settled_part", "window_used"]
    runs = getattr(report, "runs", None)
    if runs:  # a joint calibration: each run's detections on its own clock, with its own offset (a first column names the run)
        writer.writerow(["run", *header])
        for run in runs:
            for row in _detection_rows(run):
                writer.writerow([Path(run.path).name, *row])
        return buf.getvalue()
    writer.writerow(header)
    for row in _detection_rows(report):
        writer.writerow(row)
    return buf.getvalue()


def _detection_rows(report):
    """detections.csv's rows of one run (``report``: a CalibrationReport, or a joint report's JointRun)."""
    offset = report.offset.offset_ns
    points = sorted(report.points, key=lambda p: p.window.start_ns)
    starts = np.array([p.window.start_ns for p in points], np.int64)
    for d in report.detections:
        capture = d.timestamp_ns - offset
        k = int(np.searchsorted(starts, capture, side="right")) - 1
        p = points[k] if k >= 0 and capture <= points[k].window.end_ns else None
        settled = bool(p is not None and p.stable_ns[0] <= capture <= p.stable_ns[1])
        yield [
            d.timestamp_ns, capture, "" if p is None else p.window.index,
            "" if p is None or p.window.seq is None else p.window.seq, d.kind,
            f"{d.u_px:.4f}", f"{d.v_px:.4f}", f"{d.size_px:.2f}", int(settled), int(bool(p is not None and p.used)),
        ]


# --------------------------------------------------------------------------
# report.html


def _img(png: bytes | None, alt: str) -> str:
    if png is None:
        return ""
    return f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}"><figcaption>{html.escape(alt)}</figcaption></figure>'


def _table(rows: list[tuple[str, str]]) -> str:
    return "<table>" + "".join(f"<tr><th>{html.escape(k)}</th><td>{html.escape(v)}</td></tr>" for k, v in rows) + "</table>"


def _fmt(v, spec: str = ".3g", unit: str = "") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:{spec}}{unit}"


def report_html(report, data: dict) -> str:
    """A self-contained HTML page: summary tables and the figures embedded as base64 PNG."""
    from dronecal_field.pipeline import figures

    cam = report.camera
    cal = data["calibration"]
    unc = data["uncertainty"]
    mc = unc["monte_carlo"] or {}
    at15 = unc["at_15m"] or {}
    region = unc.get("over_validity_region") or {}
    validity = getattr(report, "validity", None)
    off = data["time_offset"]
    runs = getattr(report, "runs", None)
    names = ", ".join(Path(r.path).name for r in runs) if runs else report.run_path.name
    summary = _table([
        ("runs (joint calibration)" if runs else "run", f"{names}{' (cut off)' if report.truncated else ''}"),
        ("model", f"{cal['model']} ({cal['model_reason']})"),
        ("hover points used / windows", f"{data['hover_windows']['used']} / {len(report.windows)} (from {report.window_source})"),
        ("leg pairs used / legs", f"{data['legs']['pairs_used']} fix-by-fix pairs on {data['legs']['count']} legs"
                                  + (f" (from {data['legs']['source']})" if data['legs']['count'] else "")),
        ("RMS reprojection", _fmt(cal["rms_px"], ".3f", " px")),
        ("fx, fy", f"{cam.intrinsics.fx:.2f}, {cam.intrinsics.fy:.2f} px"),
        ("cx, cy", f"{cam.intrinsics.cx:.2f}, {cam.intrinsics.cy:.2f} px"),
        ("distortion k1 k2 p1 p2 k3", " ".join(f"{v:.4g}" for v in cam.distortion.as_array())),
        ("camera position ENU", " ".join(f"{v:.3f}" for v in cam.pose.position_world) + " m"),
        ("ENU origin", f"{report.origin.lat_deg:.8f}, {report.origin.lon_deg:.8f}, {report.origin.h_m:.3f} m ({report.altitude_datum}; {report.origin_source})"),
        ("camera time offset", "; ".join(f"{Path(r.path).name} {_fmt(r.offset.offset_s, '+.3f', ' s')}" for r in runs) if runs
         else f"{offset_text(off['offset_s'], off['std_s'])} ({off['method']})"),
        ("fit vs measured sigmas", (unc.get("consistency") or {}).get("note", "-")),
        ("MC RMS mean / p95", f"{_fmt(mc.get('rms_mean'), '.3f')} / {_fmt((mc.get('rms_percentiles') or {}).get('95'), '.3f')} px ({mc.get('trials', 0)} trials)"),
        ("ground position error at 15 m", f"{_fmt(at15.get('ground_position_error_cm'), '.2f', ' cm')} RMS, p95 {_fmt(at15.get('ground_position_error_cm_p95'), '.2f', ' cm')}"
         + ("" if getattr(validity, "at_15m", None) is None or not validity.at_15m.line() else f" ({validity.at_15m.line()})")),
        ("speed error at 15 m (50 km/h)", f"{_fmt(at15.get('speed_error_kmh_at_50kmh'), '.3f', ' km/h')} RMS, p95 {_fmt(at15.get('speed_error_kmh_p95'), '.3f', ' km/h')}"),
        *_validity_rows(validity, region),
        ("frames decoded / read", f"{report.frames.frames_decoded} / {report.frames.frames_read} ({report.frames.frames_corrupt} corrupt"
                                  + (f"; {report.frames.frames_from_live} detected in flight by the live pass" if report.frames.frames_from_live else "") + ")"),
    ])
    std_rows = [(k, f"{cal['parameter_std_from_measured_sigmas'][k]:.4g}") for k in PARAM_NAMES[:9] if cal["parameter_std_from_measured_sigmas"][k] > 0]
    resid_rows = [(k, f"{cal['parameter_std_from_residuals'][k]:.4g}") for k in PARAM_NAMES[:9] if cal["parameter_std_from_residuals"][k] > 0]
    mc_std = mc.get("param_std") or {}
    mc_rows = [(k, f"{v:.4g}") for k, v in mc_std.items() if v is not None]
    dropped = "".join(
        f"<tr><td>{', '.join(windows)}</td><td>{', '.join(seqs)}</td><td>{html.escape(reason)}</td></tr>"
        for reason, (windows, seqs) in _dropped_groups(getattr(report, "hover_points", report.points)).items()
    ) or "<tr><td colspan=3>none</td></tr>"
    warning_list = data["warnings"]
    warnings = "".join(f"<li>{html.escape(w)}</li>" for w in warning_list) or "<li>none</li>"
    figs = [
        _img(figures.residuals_figure(report, getattr(report, "background", None)), "detected waypoints and residual vectors (scaled up)"),
        _img(figures.coverage_figure(report), "coverage of the image"),
        _img(figures.monte_carlo_figure(report), "Monte-Carlo RMS reprojection error"),
        _img(figures.uncertainty_map_figure(report), "predicted error over the image: where the calibration can be trusted"),
        _img(figures.validity_ground_figure(report), "the region of validity on the ground (plan view, ENU)"),
        _img(figures.track_figure(report), "GNSS track over the hover windows"),
    ]
    style = (
        "body{font-family:sans-serif;max-width:1100px;margin:1em auto;color:#222}"
        "table{border-collapse:collapse;margin:.5em 0}th,td{border:1px solid #ccc;padding:2px 8px;text-align:left;font-size:14px}"
        "th{background:#f4f4f4}img{max-width:100%}figure{margin:1em 0}figcaption{font-size:13px;color:#555}"
        ".warn{background:#fff4e5;border-left:5px solid #e67e00;padding:.4em 1em;margin:.8em 0}"
        ".ok{background:#eef8ee;border-left:5px solid #2e8b2e;padding:.4em 1em;margin:.8em 0}"
    )
    return (
        "<!DOCTYPE html><html><head><meta charset='utf-8'><title>dronecal-field calibration report</title>"
        f"<style>{style}</style></head><body>"
        f"<h1>{'Joint calibration' if runs else 'Calibration'} of {html.escape(names)}</h1>"
        + _overall_verdict(report, data, warning_list, validity)
        + _verdict(validity, warning_list)
        + summary + _joint_rows(report) + f"<h2>Warnings</h2><ul>{warnings}</ul>"
        f"<h2>Dropped hover windows</h2><table><tr><th>window</th><th>seq</th><th>reason</th></tr>{dropped}</table>"
        "<h2>Parameter standard deviations</h2><div style='display:flex;gap:2em'>"
        f"<div><h3>from the fit's residuals</h3>{_table(resid_rows)}</div>"
        f"<div><h3>linearised, measured sigmas{_scaled(report)}</h3>{_table(std_rows)}</div>"
        f"<div><h3>Monte-Carlo</h3>{_table(mc_rows) if mc_rows else '<p>not run (--trials 0)</p>'}</div></div>"
        "<h2>Figures</h2>" + "".join(figs)
        + "<p style='font-size:12px;color:#777'>All numbers are in report.json.</p></body></html>"
    )


def offset_text(offset_s: float | None, std_s: float | None) -> str:
    """'+0.143 ± 0.016 s'; a std under a millisecond in microseconds ('± 0.000 s' read as exact)."""
    if offset_s is None:
        return "-"
    if std_s is None or not math.isfinite(std_s):
        return f"{offset_s:+.3f} s"
    return f"{offset_s:+.3f} s ± " + (f"{std_s:.3f} s" if std_s >= 0.001 else f"{1e6 * std_s:.0f} µs")


def _dropped_groups(points) -> dict[str, tuple[list[str], list[str]]]:
    """Dropped hover windows by reason, one row each: a fly-through plan's 24 leg-end holds are one line, not 24."""
    groups: dict[str, tuple[list[str], list[str]]] = {}
    for p in points:
        if p.used:
            continue
        reason = p.dropped
        leg_end = re.search(r"an? [\d.]+ s hold \(a leg's end\).*", reason)
        if leg_end:  # the count of detections differs per hold; the cause does not
            reason = "too few settled detections: " + leg_end.group(0)
        windows, seqs = groups.setdefault(reason, ([], []))
        windows.append(str(p.window.index))
        if p.window.seq is not None:
            seqs.append(str(p.window.seq))
    return groups


def _validity_rows(validity, region: dict) -> list[tuple[str, str]]:
    """Summary rows on the region of validity (none without one)."""
    if validity is None:
        return []
    v = validity
    frac = "n/a" if v.visible_ground_fraction is None else f"{v.visible_ground_fraction:.0%}"
    rows = [
        ("ground position error over the region of validity",
         f"{_fmt(region.get('ground_position_error_cm_rms'), '.1f', ' cm')} RMS, max {_fmt(region.get('ground_position_error_cm_max'), '.1f', ' cm')} "
         "(predicted 90 % bound over the visible ground 3-30 m inside the region)"),
        ("region of validity",
         f"{v.image_fraction:.0%} of the image (the points' hull: {v.hull_fraction:.0%}), {frac} of the visible ground 3-30 m"
         + (f"; outside it the predicted error reaches {_reach_px(v.outside_px_max)}" if v.outside_px_max is not None else "")),
        ("model extrapolation", f"{v.chosen_model} against {v.richer_model or 'no richer model'} fitted to the same points"),
    ]
    g = v.geometry
    rows.append(("geometry", f"focal std {100 * g.focal_std_rel:.2f} %, principal point std {g.principal_point_std_px:.1f} px, "
                             f"focal/distance correlation {g.focal_distance_correlation:.2f}, points over {g.image_coverage:.0%} of the image, "
                             f"heights spanning {g.thickness_m:.1f} m"))
    return rows


def _reach_px(v: float) -> str:
    return "over 1000 px" if not math.isfinite(v) or v > 1000 else f"{v:.0f} px"


def _overall_verdict(report, data: dict, warnings: list[str], validity) -> str:
    """The page's first line: one verdict from what the tables below say (points used, warnings, validity)."""
    hover_used, hover_all = data["hover_windows"]["used"], len(report.windows)
    pairs = data["legs"]["pairs_used"] or 0
    frac = getattr(validity, "visible_ground_fraction", None) if validity is not None else None
    degenerate = bool(validity is not None and validity.geometry.degenerate)
    points = f"{hover_used} of {hover_all} hover windows" + (f" and {pairs} leg pairs" if pairs else "") + " used"
    if hover_used + pairs < 6:
        cls, text = "warn", f"NOT USABLE: {points}; re-fly (see the dropped windows below)"
    elif degenerate or warnings or (frac is not None and frac < 0.95) or (hover_all and hover_used < hover_all / 2 and not pairs):
        why = [f"{len(warnings)} warning(s)"] if warnings else []
        if frac is not None and frac < 0.95:
            why.append(f"valid over {frac:.0%} of the visible ground")
        if degenerate:
            why.append("focal length and principal point poorly determined")
        if hover_all and hover_used < hover_all / 2 and not pairs:
            why.append("fewer than half the hover windows used")
        cls, text = "warn", f"USE WITH CARE: {points}; " + ", ".join(why)
    else:
        cls, text = "ok", f"GOOD: {points}, RMS {_fmt(data['calibration']['rms_px'], '.2f', ' px')}, no warnings"
    return f"<p class='{cls}' id='verdict'><b>Verdict: {html.escape(text)}</b></p>"


def _verdict(validity, warnings: list[str]) -> str:
    """One box at the top: where this calibration may be used."""
    if validity is None:
        return ""
    v = validity
    frac = v.visible_ground_fraction
    where = f"{frac:.0%} of the visible ground 3-30 m" if frac is not None else f"{v.image_fraction:.0%} of the image"
    if v.geometry.degenerate or (frac is not None and frac < 0.95):
        return (f"<div class='warn'><b>Use this calibration only inside the region of validity</b> (the outlined area in the maps "
                f"below; <code>validity_polygon_px</code> in camera.yaml, <code>validity.geojson</code> on the ground): it covers {where}."
                + (" The geometry of the points leaves the focal length and principal point poorly determined." if v.geometry.degenerate else "")
                + " See the warnings.</div>")
    return f"<div class='ok'><b>The region of validity covers {where}.</b></div>"


# --------------------------------------------------------------------------


def write_outputs(report, out_dir: Path) -> dict[str, str]:
    """Write every output file into ``out_dir`` as one set; returns {kind: path}.

    The files are written into a temporary sibling folder that replaces
    ``out_dir`` at the end, so an interruption never leaves a new camera.yaml
    beside an old report; files in ``out_dir`` that calibrate did not write
    (the user's) are moved into the new folder.
    """
    from dronecal_field.outfolder import replace_folder, staged_folder

    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"--out {out_dir} is a file: give a folder for the calibration outputs")
    with staged_folder(out_dir) as tmp:
        outputs = _write_outputs_into(report, tmp, out_dir)
        ours = {Path(v).name for v in outputs.values()} | set(OUTPUT_FILES)
        # calibrate's own files of an earlier run are dropped even when this run writes no such file (no stale validity.geojson)
        replace_folder(tmp, out_dir, lambda name: name in ours)
    return outputs


def _write_outputs_into(report, tmp: Path, out_dir: Path) -> dict[str, str]:
    """Every output file into ``tmp``; the returned paths (and those inside report.json) name ``out_dir``."""
    from dronecal_field.camerafile import write_camera

    outputs = {
        "camera": str(out_dir / CAMERA_FILE),
        "camera_info": str(out_dir / CAMERA_INFO_FILE),
        "ground_homography": str(out_dir / HOMOGRAPHY_FILE),
        "detections": str(out_dir / DETECTIONS_CSV),
        "report_json": str(out_dir / REPORT_JSON),
        "report_html": str(out_dir / REPORT_HTML),
    }
    validity = getattr(report, "validity", None)
    o = report.origin
    write_camera(
        tmp / CAMERA_FILE,
        report.camera.with_(covariance=report.covariance_measured),
        comment=(
            f"dronecal-field calibrate {_run_names(report)}: model {report.result.model.name}, "
            f"RMS {report.result.rms_px:.3f} px over {len(report.used_points)} waypoints\n"
            f"world frame ENU at enu_origin {o.lat_deg:.8f} {o.lon_deg:.8f} {o.h_m:.3f} m ({report.altitude_datum} heights)\n"
            "parameter_covariance: linearised, from the measured per-waypoint sigmas"
            + ("\nvalidity_polygon_px: the image region the calibration is supported by; do not measure outside it"
               if validity is not None else "")
        ),
        validity_polygon_px=None if validity is None else validity.polygon_px,
    )
    _atomic_write(tmp / CAMERA_INFO_FILE, camera_info_yaml(report.camera))
    _atomic_write(tmp / HOMOGRAPHY_FILE, homography_yaml(report))
    _atomic_write(tmp / DETECTIONS_CSV, detections_csv(report))
    geojson = None if validity is None else validity.geojson()
    if geojson is not None:
        outputs["validity_geojson"] = str(out_dir / VALIDITY_GEOJSON)
        _atomic_write(tmp / VALIDITY_GEOJSON, json.dumps(_clean(geojson), indent=1, allow_nan=False))
    if report.options.annotate:
        from dronecal_field.pipeline.annotate import write_annotated_copy

        annotated = out_dir / (report.run_path.stem + ANNOTATED_SUFFIX)
        write_annotated_copy(report.run_path, tmp / annotated.name, report)
        outputs["annotated_run"] = str(annotated)
    report.outputs.update(outputs)
    data = report_dict(report)
    _atomic_write(tmp / REPORT_JSON, json.dumps(data, indent=1, allow_nan=False))
    _atomic_write(tmp / REPORT_HTML, report_html(report, data))
    return outputs


def _run_names(report) -> str:
    """The run's file name; a joint calibration's runs, ``--joint``."""
    runs = getattr(report, "runs", None)
    return " ".join(Path(r.path).name for r in runs) + " --joint" if runs else report.run_path.name


def all_warnings(report) -> list[str]:
    """The stage's warnings and the region of validity's (degenerate geometry, uncovered ground), once each."""
    validity = getattr(report, "validity", None)
    out = list(report.warnings)
    for w in () if validity is None else validity.warnings:
        if w not in out:
            out.append(w)
    return out


def _fix_rate_hz(report) -> float | None:
    """Median fixes per second over the used hover windows' settled parts (None without them)."""
    rates = [
        (p.n_fixes - 1) / ((p.stable_ns[1] - p.stable_ns[0]) * 1e-9)
        for p in report.used_points
        if p.stable_ns[1] > p.stable_ns[0] and p.n_fixes >= 2
    ]
    return float(np.median(rates)) if rates else None


def _scaled(report) -> str:
    """`` x1.36`` when the sigmas were scaled to explain the fit (run.sigma_scale), else nothing."""
    scale = report.sigma_scale
    return f" x{scale:.2f}" if scale > 1.0 else ""


def sigma_consistency(fit_rms_px: float, expected_rms_px: float | None, scale: float = 1.0) -> dict | None:
    """How the fit's RMS compares with the RMS the measured per-point sigmas predict, and what that means.

    The Monte-Carlo perturbs each point by its measured scatter; when the
    fit is much better than that predicts, the scatter overstates each
    point's error (hover drift is seen by GNSS and camera alike and pairs
    out), so the Monte-Carlo figures are conservative. Much worse points to
    an error the sigmas do not hold: lever arm, time offset, model.
    """
    if expected_rms_px is None or not np.isfinite(expected_rms_px) or expected_rms_px <= 0:
        return None
    ratio = fit_rms_px / expected_rms_px
    if ratio < 0.67:
        note = (f"fit RMS {fit_rms_px:.2f} px, {ratio:.2f}x the {expected_rms_px:.2f} px the measured sigmas predict: "
                "they overstate each point's error, so the Monte-Carlo figures are conservative (the std from the residuals is the tighter estimate)")
    elif ratio > 1.5:
        note = (f"fit RMS {fit_rms_px:.2f} px, {ratio:.2f}x the {expected_rms_px:.2f} px the measured sigmas predict: "
                "an error the sigmas do not hold (lever arm, time offset, distortion model); check the residual figure")
    elif scale > 1.0 + 1e-9:
        note = f"fit RMS {fit_rms_px:.2f} px against {expected_rms_px:.2f} px predicted by the measured sigmas: close, but above"
    else:
        note = f"fit RMS {fit_rms_px:.2f} px against {expected_rms_px:.2f} px predicted by the measured sigmas: consistent"
    if scale > 1.0 + 1e-9:
        note += f"; every uncertainty figure uses the sigmas scaled {scale:.2f}x, so that they explain the fit's inliers"
    return {"fit_rms_px": float(fit_rms_px), "expected_rms_px": float(expected_rms_px), "ratio": float(ratio), "sigma_scale": float(scale), "note": note}
