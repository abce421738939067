"""``dronecal-field sim camera``: a simulated pole camera that watches a MAVLink vehicle.

It follows a MAVLink vehicle at its true position (SIMSTATE, else
GLOBAL_POSITION_INT and ATTITUDE), asking for them on its own link as a ground
station does, renders the ArUco marker the vehicle carries through the true
camera model (distortion included) and serves the frames as MJPEG over HTTP.
The true camera comes from --camera, or is made from --site-* flags and saved
with --write-truth. See docs/simulators.md.

Example:
  dronecal-field sim camera --connect udpin:127.0.0.1:14551 --camera truth.yaml \\
      --serve http://127.0.0.1:8554/stream.mjpg --fps 10 --noise-dn 2
"""

from __future__ import annotations

import argparse
import sys
import time


def _floats(text: str, n: int, flag: str) -> tuple[float, ...]:
    from dronecal_field.errors import InputError

    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != n:
        raise InputError(f"{flag} {text!r} needs {n} comma-separated numbers")
    return values


def _seqs(text: str | None) -> frozenset[int]:
    from dronecal_field.errors import InputError

    if not text:
        return frozenset()
    try:
        seqs = frozenset(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        seqs = frozenset({-1})
    if not seqs or min(seqs) < 1:
        raise InputError(f"--hide-marker-at {text!r}: give mission seqs (whole numbers from 1), e.g. --hide-marker-at 3,7,12")
    return seqs


def register(sims: argparse._SubParsersAction) -> None:
    parser = sims.add_parser(
        "camera",
        help="simulated pole camera: follows a MAVLink vehicle, serves MJPEG",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--connect", required=True, help="MAVLink address with explicit scheme: udpin:HOST:PORT, tcp:HOST:PORT, udpout:, serial:DEV:BAUD")
    parser.add_argument("--camera", help="truth camera.yaml (world frame ENU at its enu_origin)")
    parser.add_argument("--write-truth", metavar="PATH", help="write the truth camera made from the --site-* flags here")
    parser.add_argument("--serve", default="http://127.0.0.1:8554/stream.mjpg",
                        help="URL to serve: http://HOST:PORT/PATH (MJPEG) or rtsp://HOST:PORT/PATH (H.264/H.265 from GStreamer's RTSP server "
                             "with RTCP sender reports, as an IP camera; needs `make rtsp-deps`); port 0 picks a free one (default %(default)s)")
    parser.add_argument("--codec", choices=("h264", "h265"), default="h264", help="codec of an rtsp:// stream (default %(default)s)")
    parser.add_argument("--fps", type=float, default=10.0, help="frames per second (default %(default)s)")
    parser.add_argument("--latency-s", type=float, default=0.0, help="frames show the vehicle this many seconds late (default %(default)s)")
    parser.add_argument("--noise-dn", dest="noise_px", type=float, default=2.0, metavar="DN",
                        help="Gaussian image noise, standard deviation in 8-bit grey levels (default %(default)s)")
    parser.add_argument("--noise-px", dest="noise_px", type=float, help=argparse.SUPPRESS)  # the old name (it is not pixels), for one release
    parser.add_argument("--jpeg-quality", type=int, default=90, help="JPEG quality 0..100 (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="background and noise seed (default %(default)s)")
    parser.add_argument("--marker-dictionary", default="DICT_4X4_50", help="OpenCV ArUco dictionary (default %(default)s)")
    parser.add_argument("--marker-id", type=int, default=0, help="marker id (default %(default)s)")
    parser.add_argument("--marker-size", type=float, default=0.3, metavar="M", help="side of the black square, metres (default %(default)s)")
    parser.add_argument("--marker-offset", default="0,0,0", metavar="F,R,D",
                        help="marker centre from the GNSS antenna, body frame forward,right,down, metres (default %(default)s)")
    parser.add_argument("--altitude-datum", choices=("auto", "as-reported"), default="auto",
                        help="auto: turn GLOBAL_POSITION_INT's MSL heights into ellipsoidal ones with GPS_RAW_INT.alt_ellipsoid when the vehicle "
                             "reports it; as-reported: use them as they are. The truth camera's enu_origin height must be in the resulting datum.")
    parser.add_argument("--vehicle-sysid", type=int, help="follow this MAVLink system id (default: the first that reports a position)")
    parser.add_argument("--hide-marker-at", metavar="SEQ,SEQ,...",
                        help="cover the marker while the vehicle flies to and holds at these mission seqs (MISSION_CURRENT; "
                             "the numbers fly's verdict and calibrate's report use), to rehearse missed waypoints")
    parser.add_argument("--duration-s", type=float, help="stop after this many seconds (default: run until Ctrl-C)")
    site = parser.add_argument_group("truth camera from a site (with --write-truth, when --camera is absent)")
    site.add_argument("--site-lat", type=float, help="pole foot latitude, WGS84 degrees")
    site.add_argument("--site-lon", type=float, help="pole foot longitude, WGS84 degrees")
    site.add_argument("--site-h", type=float, help="pole foot height, metres, in the datum of the vehicle's heights (see --altitude-datum)")
    site.add_argument("--site-mount-height", type=float, default=3.0, help="camera height above the pole foot, m (default %(default)s)")
    site.add_argument("--site-azimuth", type=float, default=0.0, help="view direction, degrees clockwise from north (default %(default)s)")
    site.add_argument("--site-tilt", type=float, default=30.0, help="view direction below horizontal, degrees (default %(default)s)")
    site.add_argument("--site-focal-px", type=float, default=1000.0, help="focal length, pixels (default %(default)s)")
    site.add_argument("--site-image-size", default="1280x960", help="WIDTHxHEIGHT pixels (default %(default)s)")
    site.add_argument("--site-distortion", default="-0.25,0.08,0.001,-0.0005,0", help="k1,k2,p1,p2,k3 (default %(default)s)")
    parser.set_defaults(func=run)


def _check_flags(args: argparse.Namespace) -> None:
    """Numbers, names, addresses and the truth file's folder, before anything is served."""
    from urllib.parse import urlsplit

    from dronecal_field.cli import check_address, check_marker, check_number, check_numbers, check_out_file, check_seed
    from dronecal_field.errors import InputError
    from dronecal_field.sim.camera import MAVLINK_SCHEMES

    scheme, sep, rest = args.connect.partition(":")
    if not sep or scheme not in MAVLINK_SCHEMES or not rest:
        raise InputError(f"--connect {args.connect!r} needs an explicit scheme: one of {', '.join(s + ':' for s in MAVLINK_SCHEMES)} (e.g. udpin:127.0.0.1:14551)")
    if scheme != "serial":
        check_address("--connect", args.connect, MAVLINK_SCHEMES)
    try:
        parts = urlsplit(args.serve)
        parts.port  # noqa: B018 - raises ValueError for a port outside 0-65535
    except ValueError as exc:
        raise InputError(f"--serve {args.serve!r} is not a valid URL ({exc}): write e.g. http://127.0.0.1:8554/stream.mjpg") from None
    if parts.scheme not in ("http", "rtsp") or not parts.hostname:
        raise InputError(f"--serve {args.serve!r}: the simulated camera serves MJPEG over http or H.264/H.265 over rtsp: "
                         "write e.g. http://127.0.0.1:8554/stream.mjpg or rtsp://127.0.0.1:8554/cam")
    check_number("--fps", args.fps, 0, 240, low_open=True, hint="give frames per second, e.g. 10")
    check_number("--latency-s", args.latency_s, 0, 10, hint="give seconds, e.g. 0.2")
    check_number("--noise-dn", args.noise_px, 0, 255, hint="give a grey-level standard deviation, e.g. 2")
    check_number("--jpeg-quality", args.jpeg_quality, 0, 100, hint="give 0..100, e.g. 90")
    check_marker(args.marker_dictionary, args.marker_id)
    check_number("--marker-size", args.marker_size, 0, 10, low_open=True, hint="give the side of the black square in metres, e.g. 0.3")
    check_numbers("--marker-offset", args.marker_offset, 3, low=-5, high=5, hint="write F,R,D in metres, e.g. 0.1,0,0.05")
    check_number("--duration-s", args.duration_s, 0, 30 * 86_400, low_open=True, hint="give seconds, or leave it out to run until Ctrl-C")
    check_number("--vehicle-sysid", args.vehicle_sysid, 1, 255, hint="give the vehicle's MAVLink system id, 1..255 (SYSID_THISMAV)")
    check_seed("--seed", args.seed)
    check_number("--site-lat", args.site_lat, -90, 90, hint="give WGS84 degrees")
    check_number("--site-lon", args.site_lon, -180, 180, hint="give WGS84 degrees")
    check_number("--site-h", args.site_h, -1000, 10_000, hint="give metres")
    check_number("--site-mount-height", args.site_mount_height, 0, 1000, low_open=True, hint="give metres above the pole foot, e.g. 3")
    check_number("--site-azimuth", args.site_azimuth, -360, 360, hint="give degrees clockwise from north")
    check_number("--site-tilt", args.site_tilt, -89, 89, hint="give degrees below horizontal, e.g. 30")
    check_number("--site-focal-px", args.site_focal_px, 0, 1e6, low_open=True, hint="give the focal length in pixels, e.g. 1000")
    check_numbers("--site-distortion", args.site_distortion, 5, low=-100, high=100, hint="write k1,k2,p1,p2,k3, e.g. -0.25,0.08,0.001,-0.0005,0")
    if args.write_truth:
        check_out_file("--write-truth", args.write_truth)


def _truth_camera(args: argparse.Namespace):
    from dronecal_field.camerafile import read_camera, write_camera
    from dronecal_field.core.camera import Distortion
    from dronecal_field.errors import InputError
    from dronecal_field.sim.scene import make_truth_camera

    if args.camera:
        camera = read_camera(args.camera)
    elif args.site_lat is not None or args.site_lon is not None or args.site_h is not None:
        if args.site_lat is None or args.site_lon is None or args.site_h is None:
            raise InputError("a site needs all of --site-lat, --site-lon and --site-h")
        try:
            width, height = (int(v) for v in args.site_image_size.lower().split("x"))
        except ValueError:
            raise InputError(f"--site-image-size {args.site_image_size!r} must be WIDTHxHEIGHT, e.g. 1280x960") from None
        if not (16 <= width <= 20_000 and 16 <= height <= 20_000):
            raise InputError(f"--site-image-size {args.site_image_size!r} is outside 16..20000 pixels a side: give e.g. 1280x960")
        camera = make_truth_camera(
            (args.site_lat, args.site_lon, args.site_h),
            mount_height_m=args.site_mount_height,
            azimuth_deg=args.site_azimuth,
            tilt_deg=args.site_tilt,
            focal_px=args.site_focal_px,
            width=width,
            height=height,
            distortion=Distortion.from_array(_floats(args.site_distortion, 5, "--site-distortion")),
        )
    else:
        raise InputError("no truth camera: pass --camera truth.yaml, or --site-lat/--site-lon/--site-h (and --write-truth to keep it)")
    if args.write_truth:
        write_camera(args.write_truth, camera, comment="dronecal-field sim camera: ground truth")
    return camera


def run(args: argparse.Namespace) -> int:
    """Run the simulated camera until --duration-s or Ctrl-C."""
    from dronecal_field.sim.camera import SimCamera
    from dronecal_field.sim.scene import MarkerSpec

    _check_flags(args)
    hide = _seqs(args.hide_marker_at)  # refused before any work
    camera = _truth_camera(args)
    marker = MarkerSpec(
        dictionary=args.marker_dictionary,
        marker_id=args.marker_id,
        size_m=args.marker_size,
        offset_frd_m=_floats(args.marker_offset, 3, "--marker-offset"),
    )
    sim = SimCamera(
        camera,
        marker,
        connect=args.connect,
        serve_url=args.serve,
        codec=args.codec,
        fps=args.fps,
        latency_s=args.latency_s,
        noise_sigma_dn=args.noise_px,
        jpeg_quality=args.jpeg_quality,
        seed=args.seed,
        use_ellipsoid=args.altitude_datum == "auto",
        vehicle_sysid=args.vehicle_sysid,
        hide_marker_at=hide,
    )
    with sim:
        print(f"sim camera: serving {sim.url} ({camera.width}x{camera.height} @ {args.fps:g} fps), following {args.connect}", flush=True)
        deadline = None if args.duration_s is None else time.monotonic() + args.duration_s
        try:
            while deadline is None or time.monotonic() < deadline:
                time.sleep(0.2)
                if sim.error is not None:
                    from dronecal_field.errors import LinkError

                    raise LinkError(f"sim camera stopped: {sim.error}")
        except KeyboardInterrupt:
            pass
        hidden = f", marker covered in {sim.frames_hidden} (seqs {','.join(map(str, sorted(hide)))})" if hide else ""
        print(f"sim camera: {sim.frames_rendered} frames{hidden}, {sim.messages_received} MAVLink messages", file=sys.stderr, flush=True)
    return 0
