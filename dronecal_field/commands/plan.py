"""``dronecal-field plan``: a calibration mission for one pole camera, with its predicted uncertainty.

Give the camera as flags or as a TOML site file with the same keys
(``--site missions/security-4k.toml``; flags override the file). The plan
designs the sampling in the image (--strategy image, the default): target
pixels spread over the region of interest (--roi, --roi-range), two or more
depths along each pixel's ray, flown as holds or fly-through legs
(--sampling), ranked by the predicted projection error over the ROI (noise
and model extrapolation). The paper's metric grids stay available
(--strategy paper-far|paper-near|paper-full, --optimize). A plan longer than
75 % of --endurance is split into flights (mission-1.plan, ...). It writes mission.plan (QGroundControl), mission.waypoints
(Mission Planner), mission.geojson, preview.png, plan.json and
camera_guess.yaml into --out. See docs/plan.md for the field procedure.

Negative coordinates need '=': --lat=-35.3633 --takeoff=-35.3634,149.1653.
"""

from __future__ import annotations

import argparse
import sys


# Flags named as in every other command (fly, import, sim camera); the site-file keys keep their names.
RENAMED = {"--aruco-dict": "--marker-dictionary"}


def register(subparsers: argparse._SubParsersAction) -> None:
    from dronecal_field.plan.site import OPTIONS

    parser = subparsers.add_parser(
        "plan",
        help="plan the calibration flight for a camera and predict its accuracy",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--site", metavar="TOML", help="site file with the same keys as the flags (examples in missions/); "
                        "with [[pole]] and [[camera]] tables, one mission for every camera (missions/site-two-poles.toml)")
    parser.add_argument("--out", metavar="DIR", required=True, help="output folder (written atomically; a previous plan folder is replaced)")
    parser.add_argument("--scout", action="store_true", help="write the scout flight instead (issue 23): a 2-minute mission any camera "
                        "(HFOV 30-110 deg, tilt 0-60 deg, azimuth within 30 deg of --azimuth, or any without it) sees; needs only --lat, --lon, "
                        "--ground-alt, --mount-height")
    parser.add_argument("--from-run", metavar="SCOUT.mcap", help="estimate the camera from a flown scout (calibrate's pipeline) and plan the "
                        "main flight from that estimate, with the tolerances its uncertainty supports")
    parser.add_argument("--scheduler", metavar="tcp://HOST:8786", help="score the paper strategies' Monte-Carlo candidates on this Dask scheduler's workers (default: in this process; image layouts are scored here)")
    groups: dict[str, argparse._ArgumentGroup] = {}
    for spec in OPTIONS:
        group = groups.setdefault(spec.group, parser.add_argument_group(spec.group))
        default_text = "" if spec.default in (None, False) else f" (default {spec.default})"
        text = (spec.help + default_text).replace("%", "%%")  # argparse formats help strings with %
        flag = RENAMED.get(spec.flag, spec.flag)
        if spec.flag_only:
            group.add_argument(flag, dest=spec.key, action="store_true", default=None, help=text)
        else:
            group.add_argument(flag, dest=spec.key, metavar=spec.metavar, default=None, help=text)
        if flag != spec.flag:  # the old name, hidden, for one release
            group.add_argument(spec.flag, dest=spec.key, default=None, help=argparse.SUPPRESS)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dronecal_field.plan.site import OPTIONS, load_site_file, resolve_options
    from dronecal_field.plan.stage import make_plan, request_from_options, write_plan

    if args.site:
        from dronecal_field.plan.multisite import is_multi_site

        if is_multi_site(args.site):
            return run_site(args)
    values: dict = load_site_file(args.site) if args.site else {}
    for spec in OPTIONS:
        v = getattr(args, spec.key, None)
        if v is not None:
            values[spec.key] = v
    options = resolve_options(values)
    if getattr(args, "scout", False):
        from dronecal_field.cli import check_out_dir
        from dronecal_field.plan.scout import format_scout, scout_from_options, write_scout

        check_out_dir("--out", args.out)
        scout, keep_out = scout_from_options(options)
        paths = write_scout(scout, args.out, keep_out)
        print(format_scout(scout, args.out))
        print(f"wrote {', '.join(p.name for p in paths)} to {args.out}")
        return 0
    estimate = None
    if getattr(args, "from_run", None):
        from dronecal_field.plan.fromrun import estimate_from_run, format_estimate, request_from_estimate

        estimate = estimate_from_run(args.from_run)
        print(format_estimate(estimate))
        request = request_from_estimate(estimate, options)
    else:
        _check_options(options, args)
        request = request_from_options(options)
    from dronecal_field.cli import announce_first_compile

    announce_first_compile()
    if args.scheduler:
        from dronecal_field.cluster import dask_client

        with dask_client(args.scheduler) as client:
            result = make_plan(request, client)
    else:
        result = make_plan(request)
    if estimate is not None:
        from dataclasses import replace as _replace

        result = _replace(result, summary={**result.summary, "from_run": {"run": str(args.from_run), "estimate": estimate.to_dict()}})
    paths = write_plan(result, args.out)
    print(format_report(result, args.out))
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(f"wrote {', '.join(p.name for p in paths)} to {args.out}")
    return 0


def run_site(args: argparse.Namespace) -> int:
    """``plan --site`` with a site file of several cameras ([[camera]] tables): one mission for all of them."""
    from dataclasses import replace

    from dronecal_field.cli import check_marker, check_out_dir
    from dronecal_field.errors import InputError
    from dronecal_field.plan.multiplan import make_site_plan, site_request
    from dronecal_field.plan.multisite import CAMERA_EXTRA_KEYS, load_multi_site
    from dronecal_field.plan.site import OPTIONS, resolve_options
    from dronecal_field.plan.sitereport import format_site_report, write_site_plan

    if getattr(args, "scout", False) or getattr(args, "from_run", None):
        raise InputError("--scout/--from-run plan one camera; in a site file give from_run = \"scout.mcap\" in that camera's [[camera]] table")
    if args.scheduler:
        raise InputError("--scheduler scores the paper strategies of one camera; a site plans image layouts here: leave it out")
    flags = {o.key: getattr(args, o.key) for o in OPTIONS if getattr(args, o.key, None) is not None}
    per_camera = [o.flag for o in OPTIONS if o.key in flags and (o.group in ("camera", "intrinsics") or o.key in CAMERA_EXTRA_KEYS)]
    if per_camera:
        raise InputError(f"{', '.join(per_camera)} would set every camera of the site {args.site}: give it in the [[camera]] tables instead")
    spec = load_multi_site(args.site)
    spec = replace(spec, cameras=tuple(replace(c, values={**c.values, **flags}) for c in spec.cameras))
    shared = resolve_options({**spec.shared, **flags})
    if shared["strategy"] != "image" or shared["optimize"]:
        raise InputError("a site plans image-space layouts only: leave out strategy/optimize (paper grids are for one camera)")
    check_marker(shared["aruco_dict"], shared["marker_id"])
    check_out_dir("--out", args.out)
    site, distortions = site_request(spec)
    from dronecal_field.cli import announce_first_compile

    announce_first_compile()
    plan = make_site_plan(site, distortions)
    paths = write_site_plan(plan, args.out)
    print(format_site_report(plan, args.out))
    for w in plan.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(f"wrote {', '.join(p.name for p in paths)} to {args.out}")
    return 0


def _check_options(options: dict, args: argparse.Namespace) -> None:
    """What the site parser leaves open, before any design work: coordinates, the marker id, --out, --scheduler."""
    from dronecal_field.cli import check_address, check_marker, check_number, check_out_dir

    check_number("--lat", options.get("lat"), -90, 90, hint="give the pole's WGS84 latitude in degrees")
    check_number("--lon", options.get("lon"), -180, 180, hint="give the pole's WGS84 longitude in degrees")
    check_number("--focal-px", options.get("focal_px"), 0, 1e6, low_open=True, hint="give the focal length in pixels, or --focal-mm/--hfov")
    check_marker(options["aruco_dict"], options["marker_id"])
    if args.scheduler:
        check_address("--scheduler", args.scheduler, ("tcp", "tls", "inproc", "ucx"))
    check_out_dir("--out", args.out)


def format_report(result, out: str) -> str:
    """The chosen plan, its predicted ROI error against paper-far, and the candidate table, as printed."""
    s = result.summary
    lens = result.request.lens

    def num(v, f):
        return "-" if v is None else format(v, f)

    lines = [
        f"camera guess: {lens.width}x{lens.height}, f = {lens.focal_px:.0f} px ({lens.focal_source}), "
        f"HFOV {lens.hfov_deg:.1f} deg, distortion {lens.distortion_level}",
    ]
    if s.get("roi"):
        lines.append(f"region of interest: {s['roi']['text']} ({s['roi']['image_area_pct']:.0f} % of the image)")
    lines.append("")
    chosen = s["strategy"]["name"]
    if s["strategy"]["kind"] == "image":
        lines += [
            f"{'candidate':<34} {'holds':>5} {'legpts':>6} {'cover':>6} {'flight':>7} {'lin':>6} {'extrap':>7} {'ROI px':>7} {'ground':>7}",
            f"{'':<34} {'':>5} {'':>6} {'%':>6} {'min':>7} {'px':>6} {'px':>7} {'RMS':>7} {'cm':>7}",
        ]
        rows = sorted(s["candidates"], key=lambda r: (r["problem"] is not None, r["roi_combined_rms_px"] if r["roi_combined_rms_px"] is not None else 1e9))
        shown = rows[:12] + [r for r in rows[12:] if r["candidate"] == chosen]
        for row in shown:
            mark = " <" if row["candidate"] == chosen else ""
            ft = None if row["flight_time_s"] is None else row["flight_time_s"] / 60.0
            lines.append(
                f"{row['candidate']:<34} {row['holds']:>5} {row['leg_samples']:>6} {num(row['coverage_pct'], '6.0f')} {num(ft, '7.1f')} "
                f"{num(row['roi_lin_rms_px'], '6.2f')} {num(row['roi_extrap_rms_px'], '7.2f')} {num(row['roi_combined_rms_px'], '7.2f')} "
                f"{num(row['ground_combined_rms_cm'], '7.1f')}{mark}" + (f"  ({row['problem']})" if row["problem"] else "")
            )
        if len(rows) > len(shown):
            lines.append(f"... {len(rows) - len(shown)} more candidates in plan.json")
    else:
        lines += [
            f"prediction: {s['uncertainty']['trials']} Monte-Carlo trials per candidate, "
            f"noise {s['uncertainty']['sigma_px']:g} px / {s['uncertainty']['sigma_3d_m'][0] * 100:g} cm (h) / {s['uncertainty']['sigma_3d_m'][2] * 100:g} cm (v)",
            f"{'candidate':<15} {'points':>6} {'flight':>8} {'RMS mean':>9} {'RMS p95':>8} {'ground@15m':>11} {'p95':>7}",
            f"{'':<15} {'':>6} {'min':>8} {'px':>9} {'px':>8} {'cm':>11} {'cm':>7}",
        ]
        for row in s["candidates"]:
            mark = " <" if row["candidate"] == chosen else ""
            ft = None if row["flight_time_s"] is None else row["flight_time_s"] / 60.0
            lines.append(
                f"{row['candidate']:<15} {row['points']:>6} {num(ft, '8.1f')} {num(row['rms_mean_px'], '9.2f')} {num(row['rms_p95_px'], '8.2f')} "
                f"{num(row['ground_error_15m_cm'], '11.1f')} {num(row['ground_error_15m_cm_p95'], '7.1f')}{mark}"
                + (f"  ({row['problem']})" if row["problem"] else "")
            )
    f = s["flight"]
    smp = s["samples"]
    lines += ["", f"chosen: {chosen} ({s['strategy']['text']})"]
    if s["strategy"].get("heights_m"):
        lines.append(f"heights {', '.join(f'{h:g}' for h in s['strategy']['heights_m'])} m (marker)")
    lines.append(
        f"points: {smp['holds']} holds, {smp['pass_through_points']} fly-through points, {smp['leg_samples']} fixes along legs"
        + (f" at {smp['leg_speed_m_s']:.2f} m/s" if smp["leg_speed_m_s"] else "")
    )
    per = ", ".join(f"{x['file']} {x['flight_time_s'] / 60:.1f} min" for x in f["flights"])
    lines.append(f"flight: {f['flight_time_s'] / 60:.1f} min in {f['n_flights']} flight(s) ({per}); longest {f['battery_pct']:.0f} % of {f['endurance_min']:g} min "
                 f"(at most {100 - f['reserve_pct']} %)")
    band = s.get("guess_band")
    if band:
        lines.append(f"guess band: {band['text']}: {band['holds_in_view_of_all']}/{band['holds']} planned markers in view of all "
                     f"{band['corner_cameras']} corner cameras (whole, with the quiet zone); they all see {band['image_share_pct']:.0f} % of the guessed image")
    if s.get("coverage") and s["coverage"]["pct"] is not None:
        lines.append(f"ROI coverage: {s['coverage']['pct']:.0f} % of the ROI's image area within one cell of a sample")
        for part in s["coverage"]["unreachable"][:6]:
            lines.append(f"  not reached: {part['text']}")
    p = s.get("prediction")
    if p:
        lines.append(
            f"predicted ROI error (model {p['model']}): linearised {p['linearised_px']['rms']:.2f} px RMS (p95 {p['linearised_px']['p95']:.2f}, max {p['linearised_px']['max']:.2f}), "
            f"extrapolation {p['extrapolation_px']['rms']:.2f} px RMS, combined {p['combined_px']['rms']:.2f} px RMS (max {p['combined_px']['max']:.1f}); "
            f"ground {p['ground_combined_cm']['rms']:.1f} cm RMS (max {p['ground_combined_cm']['max']:.0f})"
        )
    mc = s["uncertainty"].get("monte_carlo") or {}
    if mc.get("rms_mean") is not None:
        lines.append(f"Monte-Carlo of the chosen ({mc.get('trials')} trials, {mc.get('points_used')} points): RMS reprojection {mc['rms_mean']:.2f} px, "
                     f"projection over the samples {mc.get('projection_error_px', float('nan')):.2f} px, ground at 15 m {mc.get('ground_error_15m_cm', float('nan')):.1f} cm")
    c = s.get("comparison") or {}
    if c.get("prediction"):
        cp = c["prediction"]
        lines.append(f"paper-far ({c['strategy']}, {c['points']} holds, {num(None if c.get('flight_time_s') is None else c['flight_time_s'] / 60, '.1f')} min, "
                     f"coverage {c.get('coverage_pct', 0):.0f} %) on the same ROI: linearised {cp['linearised_px']['rms']:.2f}, extrapolation "
                     f"{cp['extrapolation_px']['rms']:.2f}, combined {cp['combined_px']['rms']:.2f} px RMS; ground {cp['ground_combined_cm']['rms']:.1f} cm")
    elif c:
        lines.append(f"paper-far on the same ROI: {c.get('problem')}")
    lines += [
        f"take-off/landing (home): {f['takeoff']['lat_deg']:.7f}, {f['takeoff']['lon_deg']:.7f}; {s['altitude_frame_text']}",
        f"marker {s['marker']['size_m']:g} m (offered {', '.join(f'{m:g}' for m in s['marker']['sizes_offered_m'])}): "
        f"{s['marker']['px_min']:.0f}-{s['marker']['px_max']:.0f} px in the image; "
        f"ArduPilot: RTL_ALT {s['ardupilot_advice']['RTL_ALT_cm']} cm, FENCE_ALT_MAX {s['ardupilot_advice']['FENCE_ALT_MAX_m']} m",
    ]
    return "\n".join(lines)
