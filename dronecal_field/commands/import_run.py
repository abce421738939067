"""``dronecal-field import``: build a run file from a flight log and a video recorded apart.

Takes the ground station's .tlog (or the vehicle's DataFlash .BIN) and the
camera's video file and writes an MCAP run that ``dronecal-field calibrate``
reads: GNSS fixes, attitude, every telemetry message, hover windows from the
mission, and the video frames on the vehicle's UTC clock. Timestamps come from
the vehicle's own clocks (time_boot_ms + SYSTEM_TIME, or DataFlash TimeUS +
GPS time), so a log recorded with a simulator speed-up still has true
durations. See docs/runfile.md.
"""

from __future__ import annotations

import argparse


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "import",
        help="build a run file from a flight log (.tlog/.BIN) and a video file",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    log = parser.add_mutually_exclusive_group(required=True)
    log.add_argument("--tlog", metavar="FILE", help="MAVLink telemetry log written by the ground station")
    log.add_argument("--bin", metavar="FILE", help="ArduPilot DataFlash log (.BIN) from the vehicle")
    parser.add_argument("--video", metavar="FILE", help="the camera's video file: H.264/H.265 (an NVR's MP4/MKV export) goes to /camera/video as recorded, never re-encoded; other formats OpenCV reads are stored as JPEG")
    parser.add_argument(
        "--video-start",
        metavar="ISO8601",
        help="UTC time of the video's first frame, e.g. 2025-07-21T10:00:00.250Z "
        "(default: the MP4 creation time, else the first GNSS fix)",
    )
    parser.add_argument("--image-size", metavar="WxH", help="image size when there is no --video, e.g. 1920x1080")
    parser.add_argument("--marker-kind", choices=("aruco", "led"), default="aruco", help="marker type (default aruco)")
    parser.add_argument("--marker-dictionary", metavar="DICT", help="OpenCV ArUco dictionary, e.g. DICT_4X4_50")
    parser.add_argument("--marker-id", type=int, metavar="N", help="ArUco marker id")
    parser.add_argument("--marker-size", type=float, metavar="M", help="side of the marker's black square, metres")
    parser.add_argument(
        "--marker-offset",
        default="0,0,0",
        metavar="F,R,D",
        help="marker centre from the GNSS antenna, body frame forward,right,down, metres (default 0,0,0)",
    )
    parser.add_argument(
        "--position-source",
        choices=("auto", "gps_raw", "global_position"),
        default="auto",
        help="tlog only: GPS_RAW_INT (receiver) or GLOBAL_POSITION_INT (EKF); auto prefers the receiver",
    )
    parser.add_argument("--max-fps", type=float, metavar="HZ", help="keep at most this many video frames per second")
    parser.add_argument("--video-reencode", action="store_true", help="decode an H.264/H.265 --video and store JPEG frames (/camera/image) instead of the stream itself")
    parser.add_argument("--jpeg-quality", type=int, default=95, metavar="Q", help="JPEG quality of stored frames (default 95)")
    parser.add_argument("--out", required=True, metavar="FILE", help="the run file to write (.mcap)")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from dronecal_field.errors import InputError
    from dronecal_field.runfile.importer import import_run, parse_iso8601_ns, read_dataflash, read_tlog

    marker = _marker(args)
    video_start_ns = parse_iso8601_ns(args.video_start) if args.video_start else None
    image_size = None
    if args.image_size:
        try:
            w, h = (int(v) for v in args.image_size.lower().split("x"))
        except ValueError:
            raise InputError(f"--image-size {args.image_size!r}: write WIDTHxHEIGHT, e.g. 1920x1080") from None
        if not (16 <= w <= 20_000 and 16 <= h <= 20_000):
            raise InputError(f"--image-size {args.image_size!r} is outside 16..20000 pixels a side: give the camera's resolution, e.g. 1920x1080")
        image_size = (w, h)
    if not (0 <= args.jpeg_quality <= 100):
        raise InputError(f"--jpeg-quality {args.jpeg_quality} must be within 0..100")
    _check_flags(args)
    log = read_tlog(args.tlog, position_source=args.position_source) if args.tlog else read_dataflash(args.bin)
    report = import_run(
        args.out,
        log,
        marker,
        video=args.video,
        video_start_ns=video_start_ns,
        max_fps=args.max_fps,
        jpeg_quality=args.jpeg_quality,
        reencode=args.video_reencode,
        image_size=image_size,
    )
    clock = report.clocks[0] if report.clocks else {}
    print(f"wrote {report.out}")
    print(f"  log      {report.log} ({report.log_kind}), {report.telemetry_messages} messages")
    print(
        f"  clock    {clock.get('method', '?')} ({clock.get('samples', 0)} pairs, "
        f"residual {clock.get('residual_ms', 0.0):.2f} ms)"
        + (
            f"; host ran at {report.host_seconds_per_vehicle_second:.3f} s per vehicle s"
            if report.host_seconds_per_vehicle_second
            else ""
        )
    )
    print(f"  fixes    {report.fixes} from {report.position_source} ({report.altitude_datum} heights)"
          + (f", {report.skipped_no_fix} without a fix skipped" if report.skipped_no_fix else ""))
    print(f"  hovers   {report.hovers}")
    if report.video:
        print(f"  frames   {report.frames} of {report.width}x{report.height}, start from {report.video_start_source}")
    for warning in report.warnings:
        print(f"  warning: {warning}")
    return 0


def _check_flags(args: argparse.Namespace) -> None:
    """Files, numbers and the output, before the log is read: a run file is never written over."""
    from dronecal_field.cli import check_input_file, check_number, check_out_file

    check_input_file("--tlog", args.tlog)
    check_input_file("--bin", args.bin)
    if args.video is not None and "://" not in args.video and not args.video.startswith("/dev/video"):
        check_input_file("--video", args.video)
    check_number("--marker-size", args.marker_size, 0, 10, low_open=True, hint="give the side of the black square in metres, e.g. 0.3")
    check_number("--max-fps", args.max_fps, 0, 1000, low_open=True, hint="give frames per second, e.g. 10, or leave the flag out")
    # A run may hold the only copy of a flight's frames: never replace one.
    check_out_file("--out", args.out, keep_existing=True)


def _marker(args: argparse.Namespace):
    from dronecal_field.errors import InputError
    from dronecal_field.runfile.records import MarkerSpec

    from dronecal_field.cli import check_marker, check_numbers

    offset = check_numbers("--marker-offset", args.marker_offset, 3, low=-5, high=5, hint="write F,R,D in metres, e.g. 0.1,0,0.05")
    if args.marker_kind == "aruco":
        missing = [
            flag
            for flag, value in (
                ("--marker-dictionary", args.marker_dictionary),
                ("--marker-id", args.marker_id),
                ("--marker-size", args.marker_size),
            )
            if value is None
        ]
        if missing:
            raise InputError(f"an ArUco marker needs {', '.join(missing)} (e.g. --marker-dictionary DICT_4X4_50 --marker-id 0 --marker-size 0.3)")
        check_marker(args.marker_dictionary, args.marker_id)
        if args.marker_size <= 0:
            raise InputError(f"--marker-size {args.marker_size} must be positive (metres)")
        if args.marker_id < 0:
            raise InputError(f"--marker-id {args.marker_id} must be >= 0")
    return MarkerSpec(
        kind=args.marker_kind,
        dictionary=args.marker_dictionary,
        marker_id=args.marker_id,
        size_m=args.marker_size,
        offset_frd_m=offset,  # type: ignore[arg-type]
    )
