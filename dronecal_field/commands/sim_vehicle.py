"""``dronecal-field sim vehicle``: a SITL-style simulated ArduCopter (or PX4, --autopilot px4) speaking MAVLink 2.

It behaves like ArduCopter 4.7 SITL as recorded from a real SITL session
(mission protocol, modes, arming rules, takeoff, holds, ROI yaw, RTL), with
RTK-fixed GNSS noise and a centimetre of hover wander. Like ArduPilot 4.7, every
link streams only HEARTBEAT until its client asks for telemetry (or --param
MAVn_* sets the link's rates); GPS fixes come at 5 Hz (--gps-rate-ms). Vehicle time runs
--speedup times faster than the wall clock. Ctrl-C stops it.

Example:
  dronecal-field sim vehicle --listen udp:127.0.0.1:14550 --out udp:127.0.0.1:14551 \\
      --home -35.363261,149.165230,584 --speedup 5
"""

from __future__ import annotations

import argparse
import re
import sys


def register(sims: argparse._SubParsersAction) -> None:
    parser = sims.add_parser(
        "vehicle",
        help="simulated ArduCopter (MAVLink 2 over UDP/TCP)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--listen", action="append", default=[], metavar="URL", help="listen here: udp:HOST:PORT or tcp:HOST:PORT (port 0 = any free port); repeatable")
    parser.add_argument("--out", action="append", default=[], metavar="URL", help="also send everything to udp:HOST:PORT (e.g. the simulated camera); repeatable")
    parser.add_argument("--home", required=True, metavar="LAT,LON,H", help="home: degrees, degrees, metres above mean sea level (as SITL's --home)")
    parser.add_argument("--speedup", type=float, default=1.0, metavar="N", help="vehicle seconds per wall second (default 1)")
    parser.add_argument("--autopilot", choices=("ardupilot", "px4"), default="ardupilot",
                        help="whose firmware to behave as: ardupilot (ArduCopter 4.7 SITL, the default) or px4 (PX4 1.16 SITL with SIH: "
                        "its modes, mission from seq 0, MISSION_START arms, 3D-fix GNSS with 0.2 m / 0.5 m noise; sim/vehicle_px4.py)")
    parser.add_argument("--gnss", choices=("auto", "rtk"), default="auto",
                        help="with --autopilot px4: auto = the SITL's 3D fix (h_acc 0.9 m, 0.2 m / 0.5 m noise), rtk = RTK fixed (7 mm / 15 mm)")
    parser.add_argument("--boot-s", type=float, default=41.8, metavar="S", help="vehicle seconds until ready to arm (EKF healthy); uploads before that get MISSION_ACK NO_SPACE (default 41.8, as ArduCopter 4.7 SITL)")
    parser.add_argument("--geoid-separation", dest="geoid_sep", type=float, default=0.0, metavar="M",
                        help="ellipsoidal minus AMSL height reported in GPS_RAW_INT.alt_ellipsoid, metres (default 0; the same flag as plan's)")
    parser.add_argument("--geoid-sep", dest="geoid_sep", type=float, help=argparse.SUPPRESS)  # the old name, for one release
    parser.add_argument("--heading", type=float, default=353.0, metavar="DEG", help="initial heading on the ground (default 353, as SITL's CMAC)")
    parser.add_argument("--wp-speed", type=float, default=5.0, metavar="M/S", help="waypoint speed before any DO_CHANGE_SPEED (default 5)")
    parser.add_argument("--rtl-alt", type=float, default=15.0, metavar="M", help="RTL climb height above home (RTL_ALT, default 15)")
    parser.add_argument("--gps-rate-ms", type=float, default=200.0, metavar="MS",
                        help="the receiver's fix interval, as ArduPilot's GPS_RATE_MS (default 200 = 5 Hz, ArduPilot's default; "
                        "a faster GPS_RAW_INT stream repeats the last fix). docs/fly.md sets 100 for a 10 Hz RTK receiver")
    parser.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                        help="a stream-rate parameter at boot, as a defaults file: MAVn_POSITION, MAVn_EXTRA1, MAVn_EXT_STAT, MAVn_EXTRA3... "
                        "in Hz, n = link number + 1 (MAV1_* the first --listen). Without any, every link streams only HEARTBEAT "
                        "until a client asks (SET_MESSAGE_INTERVAL / REQUEST_DATA_STREAM), as ArduPilot 4.7; repeatable")
    parser.add_argument("--max-items", type=int, default=700, metavar="N", help="mission capacity including home (default 700)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed (default 0)")
    parser.add_argument("--signing-key", metavar="KEY", help="MAVLink 2 signing: 64 hex characters or a passphrase; unsigned messages are then ignored")
    parser.add_argument("--duration-s", dest="duration", type=float, default=None, metavar="S", help="stop after this many wall seconds (default: run until Ctrl-C)")
    parser.add_argument("--duration", dest="duration", type=float, help=argparse.SUPPRESS)  # the old name, for one release
    # "--home -35.36,149.16,584" (southern latitudes) must read as a value, not an option: teach
    # argparse that a leading minus followed by digits and commas is a number
    parser._negative_number_matcher = re.compile(r"^-\d+$|^-\d*\.\d+$|^-\d[\d.]*(,-?[\d.]+)+$")
    parser.set_defaults(func=run)


def _check_flags(args: argparse.Namespace) -> None:
    """Addresses and numbers, before a socket opens."""
    from dronecal_field.cli import check_address, check_number, check_seed

    for flag, urls in (("--listen", args.listen), ("--out", args.out)):
        for url in urls:
            check_address(flag, url, ("udp", "tcp"))
    check_number("--speedup", args.speedup, 0, 1000, low_open=True, hint="give vehicle seconds per wall second, e.g. 5")
    check_number("--boot-s", args.boot_s, 0, 3600, hint="give vehicle seconds until ready to arm, e.g. 10")
    check_number("--geoid-separation", args.geoid_sep, -200, 200, hint="give the geoid separation in metres (Earth's lies within -107..86)")
    check_number("--heading", args.heading, -360, 360, hint="give degrees clockwise from north, e.g. 353")
    check_number("--wp-speed", args.wp_speed, 0, 50, low_open=True, hint="give metres per second, e.g. 5")
    check_number("--rtl-alt", args.rtl_alt, 0, 1000, hint="give metres above home, e.g. 15")
    check_number("--gps-rate-ms", args.gps_rate_ms, 10, 10_000, hint="give the fix interval in milliseconds, e.g. 100 or 200")
    check_number("--max-items", args.max_items, 2, 65_535, hint="give the mission capacity including home, e.g. 700")
    check_number("--duration-s", args.duration, 0, 30 * 86_400, low_open=True, hint="give wall seconds, or leave it out to run until Ctrl-C")
    check_seed("--seed", args.seed)


def run(args: argparse.Namespace) -> int:
    import threading

    from dronecal_field.cli import check_number
    from dronecal_field.errors import InputError
    from dronecal_field.mavlink.link import signing_key_bytes
    from dronecal_field.sim.vehicle import SimVehicle, VehicleConfig, parse_home
    from dronecal_field.sim.vehicle_flight import CopterParams

    if not args.listen and not args.out:
        raise InputError("give at least one --listen or --out, e.g. --listen udp:127.0.0.1:14550")
    _check_flags(args)
    lat, lon, alt = parse_home(args.home)
    check_number("--home", alt, -1000, 10_000, hint="give LAT,LON,H with H in metres above mean sea level, e.g. -35.363261,149.165230,584")
    stream_params = []
    for text in args.param:
        name, sep, value = text.partition("=")
        try:
            stream_params.append((name.strip(), float(value)))
        except ValueError:
            sep = ""
        if not sep:
            raise InputError(f"--param {text!r} is not NAME=VALUE; e.g. --param MAV2_POSITION=10")
    config = VehicleConfig(
        home_lat_deg=lat,
        home_lon_deg=lon,
        home_alt_m=alt,
        geoid_sep_m=args.geoid_sep,
        speedup=args.speedup,
        boot_s=args.boot_s,
        seed=args.seed,
        max_items=args.max_items,
        heading_deg=args.heading,
        gps_rate_ms=args.gps_rate_ms,
        stream_params=tuple(stream_params),
        signing_key=signing_key_bytes(args.signing_key) if args.signing_key else None,
        params=CopterParams(wp_speed_mps=args.wp_speed, rtl_alt_m=args.rtl_alt),
        autopilot=args.autopilot,
        gnss=args.gnss,
    )
    if args.autopilot == "px4":
        from dataclasses import replace

        from dronecal_field.sim.vehicle_px4 import PX4_BOOT_S, PX4_GPS_RATE_MS, px4_params

        config = replace(config, params=replace(px4_params(args.wp_speed), rtl_alt_m=args.rtl_alt),
                         boot_s=PX4_BOOT_S if args.boot_s == 41.8 else args.boot_s,
                         gps_rate_ms=PX4_GPS_RATE_MS if args.gps_rate_ms == 200.0 else args.gps_rate_ms)
    sim = SimVehicle(config, listen=args.listen, out=args.out)
    print(f"sim vehicle: {', '.join(sim.addresses())}; home {lat:.7f},{lon:.7f},{alt:g} m AMSL; speedup {args.speedup:g}", flush=True)
    links = "; ".join(f"MAV{n}_* {address}" for n, address in enumerate(sim.addresses(), start=1))
    print(f"sim vehicle: links (stream-rate parameters): {links}; each streams only HEARTBEAT until its client asks; "
          f"GPS {1000.0 / config.gps_rate_ms:.3g} fixes/s (GPS_RATE_MS {config.gps_rate_ms:g}); "
          f"{'PX4 1.16 (SIH), GNSS ' + ('RTK fixed' if args.gnss == 'rtk' else '3D fix, h_acc 0.9 m') if args.autopilot == 'px4' else 'ArduCopter 4.7'}", flush=True)
    stop = threading.Event()
    if args.duration is not None:
        timer = threading.Timer(args.duration, stop.set)
        timer.daemon = True
        timer.start()
    try:
        sim.run(stop)
    except KeyboardInterrupt:
        pass  # Ctrl-C is how a simulator is stopped
    finally:
        stop.set()
        sim.stop()
    print(f"sim vehicle: stopped at vehicle time {sim.time_s:.1f} s", file=sys.stderr)
    return 0
