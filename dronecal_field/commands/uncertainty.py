"""``dronecal-field uncertainty``: the paper's Monte-Carlo for a camera and a set of 3D points.

Perturbs the 3D points (default sigma 1 cm X/Y, 1.5 cm Z) and their pixels
(default 2 px), recalibrates ``--trials`` times and prints the statistics of
the RMS reprojection error, the spread of every parameter and the projection
error on the ground 15 m out. ``--linearised`` adds the first-order estimate.
"""

from __future__ import annotations

import argparse
import json
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "uncertainty",
        help="Monte-Carlo calibration uncertainty of a camera and sampled points",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("--camera", required=True, help="camera.yaml (the reference camera)")
    p.add_argument("--points", required=True, help="CSV with header x,y,z (metres, the camera's world frame)")
    p.add_argument("--trials", type=int, default=500, help="Monte-Carlo trials k (default 500, as the paper)")
    p.add_argument("--sigma-3d", default="0.01,0.01,0.015", help="3D sigma X,Y,Z in metres (default 0.01,0.01,0.015)")
    p.add_argument("--sigma-px", dest="sigma_2d", type=float, default=2.0, help="marker detection noise, pixels per axis (default 2, as plan's --sigma-px)")
    p.add_argument("--sigma-2d", dest="sigma_2d", type=float, help=argparse.SUPPRESS)  # the old name, for one release
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same numbers)")
    p.add_argument(
        "--model",
        default="default",
        help="calibration model: default (fx,fy,cx,cy,k1,k2,p1,p2; k3 fixed), none, k1, k1k2, k1k2p1p2, full",
    )
    p.add_argument("--linearised", action="store_true", help="also print the first-order (linearised) estimate")
    p.add_argument("--plot-convergence", metavar="PNG", help="write the running mean of the RMS against k (the paper's Figure 1)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    p.set_defaults(func=run)


# No calibration needs more: the Monte-Carlo holds trials x points pixels in memory.
MAX_POINTS = 100_000
MAX_TRIALS = 100_000


def parse_sigma_3d(text: str) -> tuple[float, float, float]:
    from dronecal_field.errors import InputError

    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) == 1:
        values = values * 3
    if len(values) != 3 or not all(0 <= v <= 100 for v in values):  # NaN fails too
        raise InputError(f"--sigma-3d {text!r} is not three numbers within 0-100 m: write it as 0.01,0.01,0.015")
    return values  # type: ignore[return-value]


def read_points_csv(path: str):
    """(N, 3) points from a CSV with header x,y,z."""
    from pathlib import Path

    from dronecal_field.errors import InputError

    p = Path(path)
    if not p.is_file():
        raise InputError(f"points file {path} does not exist: give a CSV with header x,y,z")
    try:
        return _read_points(p, path)
    except UnicodeDecodeError as exc:
        raise InputError(f"points file {path} is not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}): give a CSV with header x,y,z") from None


def _read_points(p, path: str):
    import csv

    import numpy as np

    from dronecal_field.errors import InputError

    with p.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        fields = [h.strip().lower() for h in (reader.fieldnames or [])]
        if not {"x", "y", "z"} <= set(fields):
            raise InputError(f"points file {path} needs the header x,y,z (found {','.join(fields) or 'nothing'})")
        rows = []
        for line_no, row in enumerate(reader, start=2):
            row = {k.strip().lower(): v for k, v in row.items() if k}
            try:
                rows.append([float(row["x"]), float(row["y"]), float(row["z"])])
            except (TypeError, ValueError):
                raise InputError(f"points file {path} line {line_no} is not three numbers: fix or delete it") from None
            if len(rows) > MAX_POINTS:
                raise InputError(f"points file {path} holds more than {MAX_POINTS} points: a calibration uses tens to thousands; thin the points out")
    if not rows:
        raise InputError(f"points file {path} holds no points")
    return np.asarray(rows, float)


def run(args: argparse.Namespace) -> int:
    from dronecal_field.camerafile import read_camera
    from dronecal_field.core.uncertainty import convergence_curve, linearised, monte_carlo
    from dronecal_field.errors import InputError

    from dronecal_field.cli import check_number, check_out_file, check_seed
    from dronecal_field.core.calibrate import check_correspondences, resolve_model

    # Every flag is checked before the (slow) Monte-Carlo, so a typo costs nothing.
    sigma_3d = parse_sigma_3d(args.sigma_3d)
    check_number("--sigma-px", args.sigma_2d, 0, 1000, hint="give a pixel standard deviation, e.g. 2")
    if not 2 <= args.trials <= MAX_TRIALS:
        raise InputError(f"--trials {args.trials} is outside 2..{MAX_TRIALS}: the paper uses 500")
    check_seed("--seed", args.seed)
    resolve_model(args.model, 1000)  # an unknown model name fails here
    if args.plot_convergence:
        check_out_file("--plot-convergence", args.plot_convergence)
    camera = read_camera(args.camera)
    points = read_points_csv(args.points)
    model = resolve_model(args.model, len(points))
    check_correspondences(points, camera.project(points), model.n_free, 0.05)
    behind = camera.depth(points) <= 0
    if behind.any():
        raise InputError(f"{int(behind.sum())} point(s) lie behind the camera (first: line {int(behind.argmax()) + 2}): the points must be in the camera's world frame")
    from dronecal_field.cli import announce_first_compile

    announce_first_compile()
    mc = monte_carlo(camera, points, trials=args.trials, sigma_3d=sigma_3d, sigma_2d=args.sigma_2d, seed=args.seed, model=model)
    lin = linearised(camera, points, sigma_3d=sigma_3d, sigma_2d=args.sigma_2d, model=model) if args.linearised else None
    if args.plot_convergence:
        from dronecal_field.plots import plot_convergence

        plot_convergence(convergence_curve(mc.rms), args.plot_convergence)
    if args.json:
        out = mc.to_dict()
        if lin is not None:
            out["linearised"] = lin.to_dict()
        json.dump(out, sys.stdout, indent=None)
        print()
        return 0
    print(format_report(mc, lin))
    return 0


def format_report(mc, lin=None) -> str:
    """A readable table of a Monte-Carlo result (and its linearised twin)."""
    cols = [("Monte-Carlo", mc)] + ([("linearised", lin)] if lin is not None else [])
    lines = [f"{mc.n_points} points, model {mc.model}, {mc.trials} trials" + (f" ({mc.failed_trials} failed)" if mc.failed_trials else "")]
    header = f"{'':34}" + "".join(f"{name:>14}" for name, _ in cols)
    lines.append(header)

    def row(label: str, getter, fmt: str = "{:14.3f}") -> None:
        lines.append(f"{label:34}" + "".join(fmt.format(getter(r)) for _, r in cols))

    row("RMS reprojection mean (px)", lambda r: r.rms_mean)
    row("RMS reprojection std (px)", lambda r: r.rms_var**0.5)
    row("RMS reprojection 95th pct (px)", lambda r: r.rms_percentiles[95])
    row("RMS reprojection max (px)", lambda r: r.rms_max)
    row("projection error, points (px)", lambda r: r.projection_error_px)
    row("projection error, ground (px)", lambda r: r.ground_projection_error_px)
    row("ground position error 15 m (cm)", lambda r: r.ground_error_15m_cm)
    row("speed error 15 m, 50 km/h (km/h)", lambda r: r.speed_error_15m_kmh)
    lines.append("parameter standard deviations:")
    units = {"fx": "px", "fy": "px", "cx": "px", "cy": "px", "pos_x": "m", "pos_y": "m", "pos_z": "m", "rot_x": "deg", "rot_y": "deg", "rot_z": "deg"}
    for key in mc.param_std:
        row(f"  {key} ({units.get(key, '-')})", lambda r, key=key: r.param_std.get(key, float("nan")), "{:14.5g}")
    return "\n".join(lines)
