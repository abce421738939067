"""``dronecal-field plan``: a calibration mission for one pole camera, with its predicted uncertainty.

Give the camera as flags or as a TOML site file with the same keys
(``--site missions/security-4k.toml``; flags override the file). The plan
samples the paper's grid where the camera sees the marker, compares the
paper's alternatives with the engine's Monte-Carlo, orders the points for the
shortest flight, and writes mission.plan (QGroundControl), mission.waypoints
(Mission Planner), mission.geojson, preview.png, plan.json and
camera_guess.yaml into --out. See docs/plan.md for the field procedure.

Negative coordinates need '=': --lat=-35.3633 --takeoff=-35.3634,149.1653.
"""

from __future__ import annotations

import argparse
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    from dronecal_field.plan.site import OPTIONS

    parser = subparsers.add_parser(
        "plan",
        help="plan the calibration flight for a camera and predict its accuracy",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--site", metavar="TOML", help="site file with the same keys as the flags (examples in missions/)")
    parser.add_argument("--out", metavar="DIR", required=True, help="output folder (written atomically; a previous plan folder is replaced)")
    parser.add_argument("--scheduler", metavar="tcp://HOST:8786", help="score the candidates on this Dask scheduler's workers (default: in this process)")
    groups: dict[str, argparse._ArgumentGroup] = {}
    for spec in OPTIONS:
        group = groups.setdefault(spec.group, parser.add_argument_group(spec.group))
        default_text = "" if spec.default in (None, False) else f" (default {spec.default})"
        if spec.flag_only:
            group.add_argument(spec.flag, dest=spec.key, action="store_true", default=None, help=spec.help)
        else:
            group.add_argument(spec.flag, dest=spec.key, metavar=spec.metavar, default=None, help=spec.help + default_text)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dronecal_field.plan.site import OPTIONS, load_site_file, resolve_options
    from dronecal_field.plan.stage import make_plan, request_from_options, write_plan

    values: dict = load_site_file(args.site) if args.site else {}
    for spec in OPTIONS:
        v = getattr(args, spec.key, None)
        if v is not None:
            values[spec.key] = v
    request = request_from_options(resolve_options(values))
    if args.scheduler:
        from dronecal_field.cluster import dask_client

        with dask_client(args.scheduler) as client:
            result = make_plan(request, client)
    else:
        result = make_plan(request)
    paths = write_plan(result, args.out)
    print(format_report(result, args.out))
    for w in result.warnings:
        print(f"warning: {w}", file=sys.stderr)
    print(f"wrote {', '.join(p.name for p in paths)} to {args.out}")
    return 0


def format_report(result, out: str) -> str:
    """The candidate table and the chosen plan, as printed by the command."""
    s = result.summary
    lens = result.request.lens
    lines = [
        f"camera guess: {lens.width}x{lens.height}, f = {lens.focal_px:.0f} px ({lens.focal_source}), "
        f"HFOV {lens.hfov_deg:.1f} deg, distortion {lens.distortion_level}",
        f"prediction: {s['uncertainty']['trials']} Monte-Carlo trials per candidate, "
        f"noise {s['uncertainty']['sigma_px']:g} px / {s['uncertainty']['sigma_3d_m'][0] * 100:g} cm (h) / {s['uncertainty']['sigma_3d_m'][2] * 100:g} cm (v)",
        "",
        f"{'candidate':<15} {'points':>6} {'flight':>8} {'RMS mean':>9} {'RMS p95':>8} {'ground@15m':>11} {'p95':>7}",
        f"{'':<15} {'':>6} {'min':>8} {'px':>9} {'px':>8} {'cm':>11} {'cm':>7}",
    ]

    def num(v, f):
        return "-" if v is None else format(v, f)

    chosen = result.chosen.strategy.name
    for row in s["candidates"]:
        mark = " <" if row["candidate"] == chosen else ""
        ft = None if row["flight_time_s"] is None else row["flight_time_s"] / 60.0
        lines.append(
            f"{row['candidate']:<15} {row['points']:>6} {num(ft, '8.1f')} {num(row['rms_mean_px'], '9.2f')} {num(row['rms_p95_px'], '8.2f')} "
            f"{num(row['ground_error_15m_cm'], '11.1f')} {num(row['ground_error_15m_cm_p95'], '7.1f')}{mark}"
            + (f"  ({row['problem']})" if row["problem"] else "")
        )
    f = s["flight"]
    lines += [
        "",
        f"chosen: {chosen} ({result.chosen.strategy.describe()}), heights {', '.join(f'{h:g}' for h in result.chosen.screen.heights_m)} m (marker), "
        f"{s['points']} points, {f['flight_time_s'] / 60:.1f} min, battery {f['battery_pct']:.0f} % of {f['endurance_min']:g} min",
        f"take-off/landing (home): {f['takeoff']['lat_deg']:.7f}, {f['takeoff']['lon_deg']:.7f}; {s['altitude_frame_text']}",
        f"marker {s['marker']['size_m']:g} m: {s['marker']['px_min']:.0f}-{s['marker']['px_max']:.0f} px in the image; "
        f"ArduPilot: RTL_ALT {s['ardupilot_advice']['RTL_ALT_cm']} cm, FENCE_ALT_MAX {s['ardupilot_advice']['FENCE_ALT_MAX_m']} m",
    ]
    return "\n".join(lines)
