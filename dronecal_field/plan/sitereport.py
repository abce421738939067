"""A site plan's report (plan.json), printed summary, GeoJSON and folder (``plan --site`` with several cameras).

plan.json keeps the single-camera plan's shared fields (``enu_origin``,
``site_frame``, ``home``, ``marker``, ``grid``, ``flight``, ``fence``) so
``fly`` reads it as before, and adds ``kind: "site"``, ``poles`` and
``cameras``: one entry per camera, named as the run's cameras
(``/cameras/<name>/...``), each with its own ``enu_origin`` / ``site_frame``
/ ``camera_guess`` / ``roi`` exactly as a single-camera plan.json has them
(so the readers of one camera's plan read one entry), plus its coverage and
predicted error from every sample it sees. docs/plan.md lists the fields.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from dronecal_field.errors import InputError
from dronecal_field.geodesy import enu_to_geodetic
from dronecal_field.plan import mission as msn

YAW_RULE = ("at every point the nose (and the marker on it) faces the pole of the camera the point was designed for: "
            "DO_SET_ROI at that camera where the camera group changes (yaw_mode roi) or CONDITION_YAW per point; "
            "another camera counts the point when the marker is turned at most 60 deg from it and still min_px across")


def _r(x, n: int = 4):
    return None if x is None or not math.isfinite(float(x)) else round(float(x), n)


def _camera_entry(plan, i: int) -> dict:
    from dronecal_field.plan.stage import _json_safe

    cam = plan.cameras[i]
    req = cam.request
    lens = req.lens
    ce = cam.camera_enu
    pts = plan.points
    pred = plan.predictions[i]
    own_h = pts.owner == i
    layout = plan.chosen[i]
    enu_pos = plan.base.site.R_enu_from_site @ cam.camera_ref.pose.position_world
    entry = {
        "name": cam.name,
        "pole": cam.pole,
        "enu_origin": {"lat_deg": req.site.lat_deg, "lon_deg": req.site.lon_deg, "h_m": req.site.ground_h_m,
                       "text": "this camera's pole foot (its camera_guess and roi are in this frame)"},
        "site_frame": {"azimuth_deg": req.site.azimuth_deg, "R_enu_from_site": np.round(req.site.R_enu_from_site, 12).tolist(),
                       "text": "this camera's site frame: X along its azimuth, Y left, Z up, origin at its pole's foot"},
        "position_site_enu_m": [round(float(v), 4) for v in enu_pos],
        "camera_guess": {
            "file": f"camera_guess-{cam.name}.yaml", "width": lens.width, "height": lens.height, "focal_px": round(ce.intrinsics.fx, 2),
            "focal_source": lens.focal_source, "cx": ce.intrinsics.cx, "cy": ce.intrinsics.cy,
            "hfov_deg": round(lens.hfov_deg, 2), "vfov_deg": round(lens.vfov_deg, 2), "distortion_level": lens.distortion_level,
            "distortion_k1_k2_p1_p2_k3": ce.distortion.as_array().tolist(), "mount_height_m": req.site.mount_height_m,
            "azimuth_deg": req.site.azimuth_deg, "tilt_deg": req.site.tilt_deg, "roll_deg": req.site.roll_deg,
            "position_enu_m": ce.pose.position_world.tolist(), "rotation_world_to_camera": np.round(ce.pose.R_cam_from_world, 12).tolist(),
            "fps": lens.fps, "exposure_s": req.timing.exposure_s,
        },
        "roi": cam.roi.to_dict() if cam.roi is not None else None,
        "layout": layout.row(),
        "holds_owned": int(own_h.sum()),
        "holds_seen": int(plan.seen_holds[i].sum()),
        "holds_from_other_cameras": int((plan.seen_holds[i] & ~own_h).sum()),
        "samples_seen": int(plan.seen_samples[i].sum()),
        "samples_from_other_cameras": int((plan.seen_samples[i] & (pts.samples_owner != i)).sum()),
        "coverage": {"pct": round(100.0 * plan.coverage[i], 1), "own_layout_pct": round(100.0 * layout.design.coverage, 1),
                     "text": "share of this camera's ROI image cells (16-column grid) within one cell of a sample it sees, every camera's samples counted"},
        "prediction": None if pred is None else pred.summary(),
        "predicted_ground_cm_rms": None if pred is None else _r(pred.summary()["ground_combined_cm"]["rms"], 2),
        "predicted_roi_px_rms": None if pred is None else _r(pred.combined_rms_px, 3),
        "guess_band": req.band.to_dict(),
    }
    return _json_safe(entry)


def site_summary(plan) -> dict:
    """plan.json of a site plan (see the module docstring and docs/plan.md)."""
    from dronecal_field import __version__
    from dronecal_field.plan.stage import FENCE_MARGIN_M, _json_safe

    base = plan.base
    site = base.site
    R, origin = site.R_enu_from_site, site.origin
    pts = plan.points
    names = plan.mission_names()
    home_h = plan.missions[0].home_h_m
    veh_enu = pts.vehicle @ R.T
    geo = enu_to_geodetic(veh_enu, origin)
    alt = (geo[:, 2] - home_h) if base.alt_frame == "relative" else geo[:, 2] - (site.geoid_separation_m or 0.0)
    seq_by_flight = [{it.grid_index: seq for seq, it in enumerate(m.items, start=1) if it.label.startswith("grid")} for m in plan.missions]
    order_by_flight = [{int(g): k for k, g in enumerate(r.grid_order)} for r in plan.routes]
    offsets = np.cumsum([0] + [len(r.grid_order) for r in plan.routes])
    from dronecal_field.plan.multiplan import facing, marker_seen

    face = facing(plan.cameras, pts.marker, pts.owner)
    seen = [marker_seen(c.camera_ref, pts.marker, face, plan.marker_size_m, base.limits.min_marker_px) for c in plan.cameras]
    cam_enu = np.array([R @ c.camera_ref.pose.position_world for c in plan.cameras])
    grid = []
    for i in range(len(pts.marker)):
        k = int(plan.point_flight[i])
        o = int(pts.owner[i])
        yaw = float(msn.bearing_deg(veh_enu[i, :2][None], cam_enu[o, :2])[0])
        grid.append({
            "index": i, "flight": k + 1, "order": int(offsets[k] + order_by_flight[k][i]), "mission_seq": seq_by_flight[k].get(i),
            "marker_site_m": [round(float(v), 4) for v in pts.marker[i]], "drone_site_m": [round(float(v), 4) for v in pts.vehicle[i]],
            "drone_enu_m": [round(float(v), 4) for v in veh_enu[i]],
            "lat_deg": float(geo[i, 0]), "lon_deg": float(geo[i, 1]), "h_m": round(float(geo[i, 2]), 4), "alt_m": round(float(alt[i]), 3),
            "camera": plan.cameras[o].name, "faces": plan.cameras[o].name, "yaw_deg": round(yaw, 2),
            "pixel": [round(float(v), 1) for v in seen[o][1][i]], "marker_px": round(float(pts.marker_px[i]), 1),
            "hold_s": float(np.round(pts.hold_s[i])), "leg": int(pts.leg[i]),
            "seen_by": {c.name: {"pixel": [round(float(v), 1) for v in seen[j][1][i]], "marker_px": round(float(seen[j][2][i]), 1)}
                        for j, c in enumerate(plan.cameras) if plan.seen_holds[j, i]},
        })
    flights = [{"file": f"{n}.plan", "flight_time_s": round(r.flight_time_s, 1), "path_length_m": round(r.path_length_m, 1),
                "points": int(len(r.grid_order)), "battery_pct": round(100.0 * r.flight_time_s / base.endurance_s, 1),
                "mission_items": len(m.items) + 1} for n, r, m in zip(names, plan.routes, plan.missions)]
    total = sum(r.flight_time_s for r in plan.routes)
    t_geo = enu_to_geodetic((plan.routes[0].takeoff_site @ R.T)[None], origin)[0]
    fence_geo = enu_to_geodetic(np.column_stack([plan.fence_site, np.zeros(len(plan.fence_site))]) @ R.T, origin)
    max_alt = float(max(np.max(r.points[:, 2] - r.takeoff_site[2]) for r in plan.routes))
    poles = {}
    for c in plan.cameras:
        if c.pole not in poles:
            s = c.request.site
            poles[c.pole] = {"name": c.pole, "lat_deg": s.lat_deg, "lon_deg": s.lon_deg, "h_m": s.ground_h_m,
                             "position_enu_m": [round(float(v), 4) for v in R @ c.t_ref_from_own],
                             "keep_out_m": c.request.limits.keep_out_m, "cameras": []}
        poles[c.pole]["cameras"].append(c.name)
    top_mount = max(c.request.site.mount_height_m for c in plan.cameras)
    return _json_safe({
        "format": "dronecal-field plan summary, version 2",
        "kind": "site",
        "created_by": f"dronecal-field {__version__} plan --site",
        "name": plan.request.name,
        "altitude_frame": base.alt_frame,
        "altitude_frame_text": plan.missions[0].alt_frame_text,
        "heights_text": "h_m values are WGS84 ellipsoidal heights; alt_m values are the mission altitudes in altitude_frame",
        "enu_origin": {"lat_deg": site.lat_deg, "lon_deg": site.lon_deg, "h_m": site.ground_h_m,
                       "text": f"the site's ENU frame (east, north, up, m) at the foot of pole {plan.cameras[0].pole!r}; h is ellipsoidal"},
        "site_frame": {"azimuth_deg": site.azimuth_deg, "R_enu_from_site": np.round(R, 12).tolist(),
                       "text": f"the site frame of grid *_site_m: camera {plan.cameras[0].name!r}'s (X along its azimuth, Y left, Z up)"},
        "geoid_separation_m": site.geoid_separation_m,
        "home": {"lat_deg": plan.missions[0].home_lat_deg, "lon_deg": plan.missions[0].home_lon_deg, "h_m": round(home_h, 3),
                 "alt_written_m": round(plan.missions[0].home_alt_m, 3), "alt_written_is_amsl": plan.missions[0].home_alt_is_amsl,
                 "text": "home = take-off and landing point; the vehicle replaces it with where it arms"},
        "poles": list(poles.values()),
        "cameras": [_camera_entry(plan, i) for i in range(len(plan.cameras))],
        "yaw": {"mode": base.yaw_mode, "rule": YAW_RULE, "max_facing_deg": 60.0},
        "marker": {"size_m": plan.marker_size_m, "sizes_offered_m": list(base.marker_sizes_m), "dictionary": base.marker.dictionary,
                   "id": base.marker.marker_id, "offset_frd_m": list(base.marker.offset_frd_m), "min_px": base.limits.min_marker_px,
                   "mounting": "upright on the drone's nose, facing forward: at each point the nose faces the camera the point serves (grid 'faces')",
                   "px_min": round(float(pts.marker_px.min()), 1), "px_max": round(float(pts.marker_px.max()), 1)},
        "limits": {"min_agl_m": base.limits.min_agl_m, "max_agl_m": base.limits.max_agl_m, "max_range_m": base.limits.max_range_m,
                   "keep_out_m": base.limits.keep_out_m, "geofence": None if base.geofence_latlon is None else [list(p) for p in base.geofence_latlon]},
        "points": len(pts.marker),
        "samples": {"holds": int(np.sum(pts.hold_s > 0)), "pass_through_points": int(np.sum(pts.hold_s <= 0)),
                    "leg_samples": int(len(pts.samples) - len(pts.marker)),
                    "leg_speed_m_s": None if pts.leg_speed_m_s is None else round(pts.leg_speed_m_s, 3),
                    "merged_holds": int(sum(len(a) for a in pts.also))},
        "grid": grid,
        "flight": {
            "flight_time_s": round(total, 1), "path_length_m": round(sum(r.path_length_m for r in plan.routes), 1),
            "battery_pct": round(100.0 * max(r.flight_time_s for r in plan.routes) / base.endurance_s, 1),
            "endurance_min": base.endurance_s / 60.0, "reserve_pct": round(100 * base.reserve), "budget_s": round(plan.budget_s, 1),
            "fits_one_flight": plan.fits_budget, "flights": flights, "n_flights": len(flights),
            "hover_s": base.flight.hover_s, "speed_m_s": base.flight.speed_m_s, "end": base.end, "yaw_mode": base.yaw_mode,
            "takeoff": {"lat_deg": float(t_geo[0]), "lon_deg": float(t_geo[1]), "h_m": round(float(t_geo[2]), 3),
                        "site_m": [round(float(v), 3) for v in plan.routes[0].takeoff_site], "alt_m": plan.routes[0].takeoff_alt_m},
            "mission_items": sum(f["mission_items"] for f in flights), "max_alt_m": round(max_alt, 2),
        },
        "uncertainty": {"sigma_px": base.evaluation.sigma_px, "sigma_3d_m": [base.evaluation.sigma_h_m, base.evaluation.sigma_h_m, base.evaluation.sigma_v_m],
                        "text": "per camera: cameras[].prediction (linearised noise + model extrapolation over its ROI)"},
        "fence": {"inclusion_polygon_latlon": fence_geo[:, :2].tolist(), "margin_m": FENCE_MARGIN_M,
                  "exclusion_circle": {"lat_deg": site.lat_deg, "lon_deg": site.lon_deg, "radius_m": base.limits.keep_out_m},
                  "exclusion_circles": [{"pole": p["name"], "lat_deg": p["lat_deg"], "lon_deg": p["lon_deg"], "radius_m": p["keep_out_m"]}
                                        for p in poles.values()]},
        "ardupilot_advice": {"RTL_ALT_cm": int(max(200, math.ceil(top_mount + 2.0) * 100)), "FENCE_ENABLE": 1, "FENCE_TYPE": 7,
                             "FENCE_ALT_MAX_m": math.ceil(max_alt + 5.0),
                             "text": "set RTL_ALT to clear the highest camera (mount height + 2 m); the fence polygon and keep-out circles are in mission.plan"},
        "warnings": list(plan.warnings),
        "files": {
            **{f"{n}.plan": "QGroundControl plan (upload with QGC or dronecal-field fly)" for n in names},
            **{f"{n}.waypoints": "Mission Planner QGC WPL 110, home as item 0" for n in names},
            "mission.geojson": "map features; coordinates [lon, lat, h ellipsoidal]",
            "preview.png": "top view of the site (poles, footprints, route, per-camera coverage) and each camera's image",
            "plan.json": "this summary",
            **{f"camera_guess-{c.name}.yaml": f"camera {c.name!r} as guessed (OpenCV FileStorage, world = ENU at its pole's foot)" for c in plan.cameras},
        },
    })


def format_site_report(plan, out: str) -> str:
    """What ``plan --site`` prints: per camera its layout, coverage and predicted error; then the flight."""
    s = plan.summary
    lines = [f"site: {len(plan.cameras)} cameras on {len(s['poles'])} poles; marker {plan.marker_size_m:g} m", "",
             f"{'camera':<14} {'pole':<6} {'image':>10} {'f px':>6} {'layout':<34} {'own':>4} {'seen':>5} {'cover':>6} {'ROI px':>7} {'ground':>7}",
             f"{'':<14} {'':<6} {'':>10} {'':>6} {'':<34} {'holds':>4} {'holds':>5} {'%':>6} {'RMS':>7} {'cm RMS':>7}"]
    for c in s["cameras"]:
        g = c["camera_guess"]
        px = "-" if c["predicted_roi_px_rms"] is None else f"{c['predicted_roi_px_rms']:.2f}"
        cm = "-" if c["predicted_ground_cm_rms"] is None else f"{c['predicted_ground_cm_rms']:.1f}"
        lines.append(f"{c['name']:<14} {c['pole']:<6} {str(g['width']) + 'x' + str(g['height']):>10} {g['focal_px']:>6.0f} "
                     f"{c['layout']['candidate']:<34} {c['holds_owned']:>4} {c['holds_seen']:>5} {c['coverage']['pct']:>6.0f} {px:>7} {cm:>7}")
    f = s["flight"]
    per = ", ".join(f"{x['file']} {x['flight_time_s'] / 60:.1f} min" for x in f["flights"])
    lines += ["", f"points: {s['samples']['holds']} holds, {s['samples']['pass_through_points']} fly-through points, "
                  f"{s['samples']['leg_samples']} fixes along legs; {s['samples']['merged_holds']} holds merged between cameras",
              f"flight: {f['flight_time_s'] / 60:.1f} min in {f['n_flights']} flight(s) ({per}); budget {f['budget_s'] / 60:.1f} min; "
              f"longest {f['battery_pct']:.0f} % of {f['endurance_min']:g} min",
              f"yaw: {s['yaw']['mode']}: each point faces the camera it was designed for; a camera also counts the points of others it reads",
              f"take-off/landing (home): {f['takeoff']['lat_deg']:.7f}, {f['takeoff']['lon_deg']:.7f}; {s['altitude_frame_text']}"]
    return "\n".join(lines)


def site_geojson(plan) -> dict:
    """GeoJSON: poles, cameras, take-off, points (with their camera), paths, fence, keep-outs, footprints."""
    from dronecal_field.plan.stage import footprint_site

    base = plan.base
    R, origin = base.site.R_enu_from_site, base.site.origin

    def geo(p_ref: np.ndarray) -> np.ndarray:
        p = np.atleast_2d(np.asarray(p_ref, float))
        if p.shape[1] == 2:
            p = np.column_stack([p, np.zeros(len(p))])
        return enu_to_geodetic(p @ R.T, origin)

    feats = []
    for p in plan.summary["poles"]:
        feats.append(msn.point_feature(p["lon_deg"], p["lat_deg"], p["h_m"], {"kind": "pole", "name": p["name"], "cameras": p["cameras"]}))
        ang = np.linspace(0, 2 * np.pi, 33)[:-1]
        c = next(cam for cam in plan.cameras if cam.pole == p["name"]).t_ref_from_own
        ring = geo(c[None, :2] + p["keep_out_m"] * np.stack([np.cos(ang), np.sin(ang)], 1))
        if p["keep_out_m"] > 0:
            feats.append(msn.polygon_feature(ring[:, [1, 0]], {"kind": "keep_out", "pole": p["name"], "radius_m": p["keep_out_m"]}))
    for cam in plan.cameras:
        g = geo(cam.camera_ref.pose.position_world[None])[0]
        feats.append(msn.point_feature(g[1], g[0], g[2], {"kind": "camera", "name": cam.name, "pole": cam.pole,
                                                          "azimuth_deg": cam.request.site.azimuth_deg, "tilt_deg": cam.request.site.tilt_deg}))
        fp = cam.to_ref(np.column_stack([footprint_site(cam.camera_site), np.zeros(len(footprint_site(cam.camera_site)))]))
        feats.append(msn.polygon_feature(geo(fp)[:, [1, 0]], {"kind": "footprint", "camera": cam.name}))
    t = geo(plan.routes[0].takeoff_site[None])[0]
    feats.append(msn.point_feature(t[1], t[0], t[2], {"kind": "takeoff", "text": "home: take-off and landing"}))
    for g in plan.summary["grid"]:
        feats.append(msn.point_feature(g["lon_deg"], g["lat_deg"], g["h_m"], {
            "kind": "grid", "index": g["index"], "order": g["order"], "flight": g["flight"], "mission_seq": g["mission_seq"], "alt_m": g["alt_m"],
            "hold_s": g["hold_s"], "camera": g["camera"], "seen_by": sorted(g["seen_by"])}))
    for k, r in enumerate(plan.routes):
        path = np.vstack([r.takeoff_site[None], r.takeoff_site[None] + [0, 0, r.takeoff_alt_m], r.points] + ([r.takeoff_site[None]] if r.end == "land" else []))
        feats.append(msn.line_feature(geo(path)[:, [1, 0, 2]], {"kind": "path", "flight": k + 1, "length_m": round(r.path_length_m, 1)}))
    feats.append(msn.polygon_feature(geo(plan.fence_site)[:, [1, 0]], {"kind": "geofence", "inclusion": True}))
    return msn.geojson(feats, "dronecal-field site plan; coordinates are [lon, lat, h] with h the WGS84 ellipsoidal height in metres; "
                              f"properties.alt_m are mission altitudes: {plan.missions[0].alt_frame_text}")


_SITE_OUTPUT = re.compile(r"^mission(-\d+)?(-px4)?\.(plan|waypoints)$|^(mission\.geojson|plan\.json|camera_guess(-[a-z0-9_-]+)?\.yaml|preview\.png)$")


def write_site_plan(plan, out_dir: str | os.PathLike) -> list[Path]:
    """Write the site plan folder atomically (as ``stage.write_plan`` does); returns the written paths."""
    from dronecal_field.camerafile import write_camera
    from dronecal_field.outfolder import replace_folder, staged_folder
    from dronecal_field.plan.preview import render_site_preview
    from dronecal_field.plan.px4 import px4_plan, px4_plan_name
    from dronecal_field.plan.schema import validate_plan

    out = Path(out_dir)
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not (out / "plan.json").is_file())):
        raise InputError(f"--out {out} exists and is not a plan folder: choose a new folder")
    base = plan.base
    fence = np.asarray(plan.summary["fence"]["inclusion_polygon_latlon"])
    ko = (base.site.lat_deg, base.site.lon_deg, base.limits.keep_out_m) if base.limits.keep_out_m > 0 else None
    plans = []
    for m in plan.missions:
        q = msn.qgc_plan(m, fence, ko, base.flight.speed_m_s)
        # every pole's keep-out circle, not only the first's
        circles = q.get("geoFence", {}).get("circles")
        if circles is not None:
            have = {(round(c["circle"]["center"][0], 7), round(c["circle"]["center"][1], 7)) for c in circles}
            for p in plan.summary["poles"]:
                key = (round(p["lat_deg"], 7), round(p["lon_deg"], 7))
                if p["keep_out_m"] > 0 and key not in have:
                    circles.append({"circle": {"center": [float(p["lat_deg"]), float(p["lon_deg"])], "radius": float(p["keep_out_m"])},
                                    "inclusion": False, "version": 1})
        validate_plan(q)
        plans.append(q)
    names = plan.mission_names()
    with staged_folder(out) as tmp:
        for name, q, m in zip(names, plans, plan.missions):
            (tmp / f"{name}.plan").write_text(msn.dumps(q), encoding="utf-8")
            (tmp / f"{px4_plan_name(name)}.plan").write_text(msn.dumps(px4_plan(q)), encoding="utf-8")
            (tmp / f"{name}.waypoints").write_text(msn.waypoints_text(m), encoding="utf-8")
        (tmp / "mission.geojson").write_text(msn.dumps(site_geojson(plan)), encoding="utf-8")
        (tmp / "plan.json").write_text(msn.dumps(plan.summary), encoding="utf-8")
        for cam in plan.cameras:
            write_camera(tmp / f"camera_guess-{cam.name}.yaml", cam.camera_enu,
                         comment=f"dronecal-field plan --site: camera {cam.name}, GUESSED (not calibrated): {cam.request.lens.focal_source}")
        render_site_preview(plan, tmp / "preview.png")
        replace_folder(tmp, out, lambda n: bool(_SITE_OUTPUT.match(n)))
    files = [f"{n}.{ext}" for n in names for ext in ("plan", "waypoints")] + [f"{px4_plan_name(n)}.plan" for n in names]
    files += ["mission.geojson", "preview.png", "plan.json"] + [f"camera_guess-{c.name}.yaml" for c in plan.cameras]
    return [out / f for f in files]
