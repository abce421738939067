"""``dronecal-field fly``: pre-flight checks, upload + verify the mission, record the run.

Steps: connect; open the video; print the pre-flight checklist (stops here
with --dry-run, or with exit code 2 if a check fails); upload the mission and
read it back; start recording RUN.mcap (and RUN.tlog beside it); then wait for
the pilot to arm and switch to AUTO, or with --start arm in GUIDED and send
MAV_CMD_MISSION_START (nothing else is ever commanded). Recording ends when the
mission ends (last item reached and landed/disarmed) or on Ctrl-C, which
finalises the file and commands nothing.

The marker comes from the --marker-* flags, else from plan.json beside the
mission (written by `dronecal-field plan`). See docs/fly.md.

Several cameras (a site: four on a pole, a car park's ring) record into one
run with --video NAME=URL, once per camera: each on its own topic
/cameras/NAME/..., its own clock, its own status line, video-loss alarm and
live check.

While recording, the live pipeline checks each hold as it ends (the marker
detected, the running calibration, coverage of the plan's ROI) and ends with
a verdict and, for missed waypoints, RUN's refly.plan; --live-port serves it
to Foxglove, --calibrate calibrates the run after landing. See docs/live.md.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

# The probe and the pre-flight video judgement live with the recording; these names are fly's own too.
from dronecal_field.recording.probe import judge_video as _judge_video  # noqa: F401
from dronecal_field.recording.probe import probe_video as _probe_video  # noqa: F401


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "fly",
        help="pre-flight, upload the mission, record the run (MCAP + tlog)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    link = parser.add_argument_group("vehicle")
    link.add_argument("--connect", required=True, metavar="URL", help="MAVLink: udp:HOST:PORT (we send), udpin:HOST:PORT (we listen), tcp:HOST:PORT, serial:DEVICE")
    link.add_argument("--baud", type=int, default=57600, help="serial baud rate (default 57600)")
    link.add_argument("--signing-key", metavar="KEY", help="MAVLink 2 signing key: 64 hex characters or a passphrase (SHA-256); never printed")
    link.add_argument("--heartbeat-timeout", type=float, default=10.0, metavar="S", help="wait this long for the vehicle's HEARTBEAT (default 10)")
    link.add_argument("--link-timeout", type=float, default=3.0, metavar="S", help="telemetry silence that counts as a lost link (default 3)")
    mission = parser.add_argument_group("mission")
    mission.add_argument("--mission", required=True, metavar="FILE", help="mission.plan (QGroundControl) or .waypoints (QGC WPL 110)")
    mission.add_argument("--dry-run", action="store_true", help="print the pre-flight checklist and stop: nothing is uploaded or recorded")
    mission.add_argument("--start", action="store_true", help="arm in GUIDED and send MISSION_START yourself (PX4: MISSION_START, which arms; default: wait for the pilot to arm and switch to AUTO)")
    mission.add_argument("--timeout-s", type=float, default=None, metavar="S", help="stop recording after S wall seconds if the mission has not ended (file finalised, exit code 2)")
    checks = parser.add_argument_group("pre-flight")
    checks.add_argument("--min-fix", choices=("rtk_fixed", "rtk_float", "3d"), default="rtk_fixed", help="weakest GNSS fix to fly with (default rtk_fixed; others warn loudly)")
    checks.add_argument("--min-battery", type=int, default=30, metavar="PCT", help="smallest battery charge, percent (default 30)")
    checks.add_argument("--max-home-distance", type=float, default=500.0, metavar="M", help="largest home-to-mission distance, metres (default 500)")
    checks.add_argument("--ready-timeout", type=float, default=60.0, metavar="S", help="wait this long for a booting vehicle to pass the checks (default 60)")
    video = parser.add_argument_group("video")
    video.add_argument("--video", required=True, action="append", metavar="[NAME=]URL",
                       help="camera stream: http://.../stream.mjpg (MJPEG, JPEG passed through), rtsp://... (H.264/H.265 passed through to /camera/video), "
                            "/dev/videoN or a file. Several cameras: NAME=URL once per camera (NAME: a-z 0-9 _ -, up to 32), "
                            "each recorded to /cameras/NAME/image or /cameras/NAME/video")
    video.add_argument("--rtsp-transport", choices=("tcp", "udp"), default="tcp", help="RTSP transport (default tcp: a slow reader delays, never corrupts; udp losses are counted and shown)")
    video.add_argument("--camera-width", type=int, metavar="PX", help="expected image width (default: from the first frame; one camera only)")
    video.add_argument("--camera-height", type=int, metavar="PX", help="expected image height (default: from the first frame; one camera only)")
    video.add_argument("--camera-latency", type=float, metavar="S", help="capture-to-arrival delay of the stream(s), seconds, if known (metadata camera.latency_s; default unknown)")
    video.add_argument("--frame-queue", type=int, default=64, metavar="N", help="frames buffered for the disk per camera before frames are dropped (default 64)")
    video.add_argument("--on-video-loss", choices=("alarm", "hold"), default="alarm",
                       help="when the camera's frames stop in flight: alarm (default: a red line and a bell, nothing commanded) or hold "
                            "(also switch the vehicle from AUTO to GUIDED, holding position, and back to AUTO when frames return; "
                            "with several cameras: while any camera is lost)")
    marker = parser.add_argument_group("marker (default: plan.json beside the mission)")
    marker.add_argument("--marker-kind", choices=("aruco", "led"), help="marker kind (default aruco)")
    marker.add_argument("--marker-dictionary", metavar="NAME", help="ArUco dictionary (default DICT_4X4_50)")
    marker.add_argument("--marker-id", type=int, metavar="ID", help="ArUco id (default 0)")
    marker.add_argument("--marker-size", type=float, metavar="M", help="side of the marker's black square, metres")
    marker.add_argument("--marker-offset", metavar="F,R,D", help="marker centre from the GNSS antenna, body frame forward,right,down, metres (default 0,0,0)")
    live = parser.add_argument_group("live (docs/live.md)")
    live.add_argument("--live-port", type=int, default=0, metavar="PORT",
                      help="serve the live view to Foxglove on this WebSocket port (8765 is Foxglove's usual one; default 0: no server)")
    live.add_argument("--live-host", default="127.0.0.1", metavar="ADDR", help="address of the live view (default 127.0.0.1: this machine only)")
    live.add_argument("--no-live", action="store_true", help="record only: no live detection, calibration or verdict")
    live.add_argument("--calibrate", action="store_true", help="after landing, calibrate the run into RUN-calibration/ beside it (calibrate's defaults)")
    parser.add_argument("--out", required=True, metavar="RUN.mcap", help="run file to write; the .tlog goes beside it")
    parser.set_defaults(func=run)


def _marker_spec(args: argparse.Namespace, plan_json: dict | None):
    from dronecal_field.errors import InputError
    from dronecal_field.runfile.records import MarkerSpec

    flags = (args.marker_kind, args.marker_dictionary, args.marker_id, args.marker_size, args.marker_offset)
    if any(v is not None for v in flags):
        offset = (0.0, 0.0, 0.0)
        if args.marker_offset:
            try:
                offset = tuple(float(v) for v in args.marker_offset.split(","))
            except ValueError:
                offset = ()
            if len(offset) != 3:
                raise InputError(f"--marker-offset {args.marker_offset!r} is not F,R,D in metres; e.g. --marker-offset 0.1,0,0.05")
        kind = args.marker_kind or "aruco"
        if kind == "aruco" and (args.marker_size is None or args.marker_size <= 0):
            raise InputError("an ArUco marker needs --marker-size (side of the black square, metres)")
        return MarkerSpec(
            kind=kind,
            dictionary=(args.marker_dictionary or "DICT_4X4_50") if kind == "aruco" else args.marker_dictionary,
            marker_id=(args.marker_id if args.marker_id is not None else 0) if kind == "aruco" else args.marker_id,
            size_m=args.marker_size,
            offset_frd_m=offset,  # type: ignore[arg-type]
        )
    from dronecal_field.runfile.records import marker_from_plan_json

    spec = marker_from_plan_json(plan_json or {})  # checked key by key: one line naming a bad one
    if spec is None:
        raise InputError("no marker given: pass --marker-size (and --marker-dictionary/--marker-id/--marker-offset) or keep plan.json beside the mission")
    return spec


def _check_flags(args: argparse.Namespace) -> None:
    """Every number, name and address, before the link opens: a typo costs nothing and commands nothing."""
    from urllib.parse import urlsplit

    from dronecal_field.cli import check_marker, check_number, check_numbers
    from dronecal_field.errors import InputError
    from dronecal_field.mavlink.link import parse_endpoint

    check_number("--baud", args.baud, 0, 10_000_000, low_open=True, hint="give the radio's baud rate, e.g. 57600")
    for flag, value in (("--heartbeat-timeout", args.heartbeat_timeout), ("--link-timeout", args.link_timeout),
                        ("--timeout-s", args.timeout_s), ("--ready-timeout", args.ready_timeout)):
        check_number(flag, value, 0, 86_400, low_open=flag != "--ready-timeout", hint="give seconds, e.g. 10")
    check_number("--min-battery", args.min_battery, 0, 100, hint="give a charge in percent, e.g. 30")
    check_number("--max-home-distance", args.max_home_distance, 0, 100_000, low_open=True, hint="give metres, e.g. 500")
    for flag, value in (("--camera-width", args.camera_width), ("--camera-height", args.camera_height)):
        check_number(flag, value, 16, 20_000, hint="give the stream's image size in pixels, or leave the flag out")
    check_number("--camera-latency", args.camera_latency, 0, 10, hint="give the capture-to-arrival delay in seconds, or leave the flag out")
    check_number("--frame-queue", args.frame_queue, 1, 100_000, hint="give a number of frames, e.g. 64")
    check_number("--marker-size", args.marker_size, 0, 10, low_open=True, hint="give the side of the black square in metres, e.g. 0.3")
    if args.marker_offset is not None:
        check_numbers("--marker-offset", args.marker_offset, 3, low=-5, high=5, hint="write F,R,D in metres, e.g. 0.1,0,0.05")
    if args.marker_dictionary is not None or args.marker_id is not None:
        check_marker(args.marker_dictionary or "DICT_4X4_50", args.marker_id)
    parse_endpoint(args.connect, args.baud)  # a malformed address fails here, before anything opens
    if args.connect.count("[") != args.connect.count("]"):
        raise InputError(f"--connect {args.connect!r} has an unclosed bracket: write an IPv6 host as udp:[::1]:14550")
    from dronecal_field.recording.cameras import parse_video_flags

    videos = parse_video_flags(list(args.video))
    for spec in videos:
        if "://" in spec.url:
            try:
                urlsplit(spec.url).port
            except ValueError as exc:
                raise InputError(f"{spec.flag} {spec.url!r} is not a valid URL ({exc}): write e.g. http://192.168.1.10/stream.mjpg or rtsp://camera/stream") from None
    if len(videos) > 1 or videos[0].name is not None:
        for flag, value in (("--camera-width", args.camera_width), ("--camera-height", args.camera_height)):
            if value is not None:
                raise InputError(f"{flag} is for a single camera; with named cameras (--video NAME=URL) each size is read from its stream: drop {flag}")
    args.videos = videos
    out = Path(args.out)
    if out.is_dir():
        raise InputError(f"--out {out} is a folder: give the run file's name, e.g. --out {out / 'run.mcap'}")


def _site_origin(plan_json: dict | None):
    from dronecal_field.runfile.records import site_origin_from_plan_json

    return site_origin_from_plan_json(plan_json or {})


def _wait_for_gnss_rate(meter, timeout_s: float) -> None:
    """Give the GNSS stream up to ``timeout_s`` to show its rate (a second of fixes at the asked rate)."""
    deadline = time.monotonic() + timeout_s
    while meter.rate_hz() is None and time.monotonic() < deadline:
        time.sleep(0.1)


def _mission_over(recorder, mission) -> bool:
    """The last item was reached (and the vehicle is down if it was a landing item), or it landed after flying."""
    from dronecal_field.mavlink.missionfile import CMD_NAV_LAND, CMD_NAV_RETURN_TO_LAUNCH

    last = mission.items[-1]
    reached_last = any(seq == last.seq for _t, seq in recorder.reached)
    if reached_last and (last.command not in (CMD_NAV_RETURN_TO_LAUNCH, CMD_NAV_LAND) or not recorder.armed):
        return True
    return recorder.airborne_then_disarmed


def run(args: argparse.Namespace) -> int:
    import json

    from dronecal_field import __version__
    from dronecal_field.errors import InputError, LinkError
    from dronecal_field.mavlink.control import StreamKeeper, arm_and_start_mission, describe_heartbeat, request_telemetry
    from dronecal_field.mavlink.link import open_link
    from dronecal_field.mavlink.mission import MissionWatch, upload_and_verify
    from dronecal_field.mavlink.missionfile import read_mission
    from dronecal_field.mavlink.preflight import GnssRateMeter, format_checklist, require_preflight, run_preflight

    _check_flags(args)
    mission_path = Path(args.mission)
    try:
        mission = read_mission(mission_path)
    except UnicodeDecodeError as exc:
        raise InputError(f"--mission {mission_path} is not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start}): give the .plan or .waypoints file") from None
    plan_json = None
    plan_json_path = mission_path.parent / "plan.json"
    if plan_json_path.is_file():
        try:
            plan_json = json.loads(plan_json_path.read_text(encoding="utf-8"))
        except (OSError, json.JSONDecodeError) as exc:
            raise InputError(f"{plan_json_path}: unreadable ({exc}); fix it or pass the --marker-* flags") from None
        if not isinstance(plan_json, dict):
            raise InputError(f"{plan_json_path}: not a JSON object (plan writes one); re-run plan or remove it and pass the --marker-* flags")
        _site_origin(plan_json)  # a bad enu_origin is named now, before the link opens
    marker = _marker_spec(args, plan_json)
    if not 0 <= args.live_port <= 65535:
        raise InputError(f"--live-port {args.live_port}: give a TCP port 1-65535 (8765 is Foxglove's usual one), or 0 for no live view")
    out = Path(args.out)
    tlog_path = out.with_suffix(".tlog")
    from dronecal_field.recording.claim import OutputClaim, check_outputs, claim_outputs

    inputs = {"--mission": mission_path, "plan.json": plan_json_path if plan_json is not None else None}
    for spec in args.videos:
        inputs[spec.flag] = Path(spec.url) if "://" not in spec.url and not spec.url.startswith("/dev/") else None
    check_outputs("--out", [out, tlog_path], inputs)
    from dronecal_field.recording.claim import free_space_note

    if (note := free_space_note(out)) is not None:  # before anything connects
        print(note, flush=True)  # also with --dry-run: the field laptop's disk is part of the checklist
    # A flight is the most expensive thing this tool makes: never write over one, and own the
    # files from now on (created exclusively), so a second fly with the same --out is refused.
    from dronecal_field.cli import stop_signals_deferred

    claim = OutputClaim()  # held before the files exist: a signal at any moment finds what to give back
    try:
        # Held back until the files are claimed and the link is open (then raised at once, below): a stop
        # must not land between creating a file and noting it, nor in pymavlink's imports, which swallow it.
        with stop_signals_deferred():
            if not args.dry_run:
                claim_outputs("--out", [out, tlog_path], suggestion=free_run_path(out), into=claim)
            from dronecal_field.recording.status import VehicleClock

            link = open_link(args.connect, baud=args.baud, signing_key=args.signing_key)
    except BaseException:
        claim.release()
        raise
    clock = VehicleClock()  # fed from now on, so hover windows are right from the first hold
    backlog: list[tuple[int, bytes]] = []  # the session before recording (pre-flight, upload) for the .tlog

    def before_recording(direction, stamp_ns, msg):
        if len(backlog) < 200_000:
            backlog.append((stamp_ns, msg.get_msgbuf()))
        if direction == "in" and hasattr(msg, "time_boot_ms") and msg.get_srcSystem() == link.target_system:
            clock.update(stamp_ns, int(msg.time_boot_ms))

    link.add_listener(before_recording)
    cams: list = []  # recording.probe.ProbedCamera, one per --video
    recorder = None
    live = None
    watch = None
    keeper = None
    closed_mono = None
    stopped_early = None
    try:
        hb = link.wait_heartbeat(args.heartbeat_timeout)
        print(f"vehicle: {describe_heartbeat(hb)} (sysid {link.target_system}) on {link.endpoint}", flush=True)
        request_telemetry(link)  # on this link only: ArduPilot 4.7 streams nothing on a link until asked
        keeper = StreamKeeper(link)  # asks again if a stream stops (a rebooted vehicle forgets)
        link.add_listener(keeper.feed)
        gnss_meter = GnssRateMeter()
        link.add_listener(lambda direction, _stamp_ns, msg: gnss_meter.feed(msg) if direction == "in" else None)
        from dronecal_field.recording.probe import camera_checks, probe_cameras

        cams = probe_cameras(args, plan_json)
        _wait_for_gnss_rate(gnss_meter, timeout_s=3.0)
        video_status = cams[0].status
        if cams[0].first is not None:
            for flag, expected, actual in (("--camera-width", args.camera_width, video_status.width), ("--camera-height", args.camera_height, video_status.height)):
                if expected is not None and expected != actual:
                    raise InputError(f"{flag} {expected} but the stream sends {video_status.width}x{video_status.height}; drop the flag or fix the stream")
        several = cams[0].spec.name is not None
        results = run_preflight(
            link,
            mission,
            next((c.status for c in cams if c.status.error or not c.status.frames), video_status),
            min_fix=args.min_fix,
            min_battery_pct=args.min_battery,
            max_home_distance_m=args.max_home_distance,
            wait_s=args.ready_timeout,
            gnss_meter=gnss_meter,
        )
        if several:
            results = camera_checks(results, cams)
        print("pre-flight:\n" + format_checklist(results), flush=True)
        require_preflight(results)
        if args.dry_run:
            print("dry run: nothing uploaded, nothing recorded")
            return 0
        if not args.no_live and several:  # before the upload: a --live-port that cannot be served stops fly with nothing uploaded
            from dronecal_field.live.site import SiteCamera, camera_live_plan, start_live_site

            live = start_live_site(mission, marker, [SiteCamera(c.spec.name, c.status.width, c.status.height, camera_live_plan(plan_json, c.spec.name))
                                                     for c in cams], _site_origin(plan_json), args.min_fix, args.camera_latency,
                                   args.live_host, args.live_port)
        elif not args.no_live:
            from dronecal_field.live.session import start_live

            live = start_live(mission, marker, video_status.width, video_status.height, plan_json, _site_origin(plan_json), args.min_fix,
                              args.camera_latency, args.live_host, args.live_port)
            if live.view is not None:
                print(f"live view: Foxglove, open connection ws://{args.live_host}:{live.view.port} (layout docs/foxglove-layout.json)", flush=True)

        watch = MissionWatch(len(mission.items), link.target_system)  # a ground station on another link may change it
        link.add_listener(watch.feed)
        report = upload_and_verify(link, mission.items)
        watch.uploaded()
        print(f"mission: {report.items} items uploaded and read back identical in {report.duration_s:.1f} s", flush=True)
        if report.storage_changes:
            more = f" (+{len(report.storage_changes) - 3} more)" if len(report.storage_changes) > 3 else ""
            print(f"note: {'PX4' if link.is_px4 else 'ArduCopter'} keeps some values differently, as expected: {'; '.join(report.storage_changes[:3])}{more}")

        link.remove_listener(before_recording)  # the recorder takes over the clock and the tlog
        recorder = _start_recorder(args, link, cams, mission, mission_path, marker, plan_json, out, tlog_path, __version__, clock, backlog, live)
        claim.keep()
        if args.start:
            arm_and_start_mission(link)
            print("started: MISSION_START accepted (PX4 armed itself, AUTO.MISSION)" if link.is_px4 else "started: GUIDED, armed, MISSION_START sent", flush=True)
        else:
            print("waiting for the pilot to arm and switch to AUTO (Ctrl-C ends the recording; nothing is commanded)", flush=True)
        from dronecal_field.recording.alarm import VideoLossAlarm

        loss = VideoLossAlarm(link, hold=args.on_video_loss == "hold", view=None if live is None else live.view)
        if not _record_until_done(recorder, mission, args.timeout_s, live, watch, keeper, loss):
            summary = recorder.stop().summary()
            recorder = None
            closed_mono = time.monotonic()
            raise LinkError(f"the mission did not end within --timeout-s {args.timeout_s:g}; {out} is finalised ({summary}); the vehicle was not commanded")
    except KeyboardInterrupt:
        if recorder is not None:
            summary = recorder.stop().summary()
            recorder = None
            print(f"\ninterrupted: {out} finalised ({summary}); the vehicle was not commanded", file=sys.stderr)
        raise
    finally:
        claim.release()  # nothing recorded: the empty claimed files go
        if recorder is not None:
            recording = recorder.stop()
            stopped_early = recording.stopped  # a full disk: finalised up to the cut, said loudly, exit 2
            summary = recording.summary()
            closed_mono = time.monotonic()
            print(f"\nrecorded {out} and {tlog_path.name}: {summary}", flush=True)
        if watch is not None and watch.changed:
            print(f"WARNING: {watch.describe()}", file=sys.stderr, flush=True)
        for cam in cams:
            if cam.source is not None:
                cam.source.close()
        link.close()
        if live is not None and hasattr(live, "cameras"):
            from dronecal_field.live.site import conclude_site

            _results, lines = conclude_site(live, out, mission)
            print("\n".join(lines), flush=True)
        elif live is not None:
            from dronecal_field.live.session import conclude

            _result, lines = conclude(live, out, mission)
            print("\n".join(lines), flush=True)
    if args.calibrate and closed_mono is not None:
        from dronecal_field.live.session import calibrate_after_landing

        several = bool(cams) and cams[0].spec.name is not None  # calibrate reads every camera from the file
        print("\n".join(calibrate_after_landing(out, args.min_fix, closed_mono, None if several else live)), flush=True)
    if stopped_early is not None:
        from dronecal_field.errors import RecordingStoppedError

        raise RecordingStoppedError(f"the recording stopped early ({stopped_early}); {out} is finalised up to there: free space and re-fly what is missing")
    return 0


def _start_recorder(args, link, cams, mission, mission_path, marker, plan_json, out, tlog_path, version, clock, backlog, observer=None):
    from dronecal_field.mavlink.missionfile import to_qgc_plan
    from dronecal_field.recording.feed import CameraFeed
    from dronecal_field.recording.marker_check import MarkerCheck
    from dronecal_field.recording.probe import run_camera, video_metadata
    from dronecal_field.recording.recorder import Recorder
    from dronecal_field.runfile.records import FORMAT_VERSION, RunMetadata
    from dronecal_field.runfile.tlog import TlogWriter
    from dronecal_field.runfile.writer import RunWriter

    tlog = TlogWriter(tlog_path)
    for stamp_ns, data in backlog:  # the whole session: connect, pre-flight, upload and read-back
        tlog.write(data, stamp_ns // 1000)
    check = MarkerCheck(marker.dictionary, marker.marker_id) if marker.kind == "aruco" and marker.dictionary else None
    # Frames that arrived before this instant (queued during pre-flight and upload) are not
    # recorded; taken after the slow steps above so that few fresh frames wait in the queue.
    start_ns = time.time_ns()
    gps = link.latest("GPS_RAW_INT")
    datum = "msl" if gps is not None and not gps.alt_ellipsoid else "ellipsoid"
    hb = link.vehicle_heartbeat
    several = cams[0].spec.name is not None
    metadata = RunMetadata(
        format_version=FORMAT_VERSION,
        width=int(cams[0].status.width),
        height=int(cams[0].status.height),
        marker=marker,
        altitude_datum=datum,
        camera_latency_s=args.camera_latency,
        site_origin=_site_origin(plan_json),
        extra={
            "recorder": f"dronecal-field {version} fly",
            "vehicle.sysid": str(link.target_system),
            "vehicle.autopilot": str(int(hb.autopilot)) if hb is not None else "unknown",
            "mission.items": str(len(mission.items)),
            "mission.file": mission_path.name,
            "recording.start_ns": str(start_ns),
        },
    )
    if several:
        run_cameras = [run_camera(cam, args) for cam in cams]
        writer = RunWriter(out, metadata, cameras=run_cameras)
        feeds = [CameraFeed(cam.spec.name, cam.source, cam.first, observer=None if observer is None else observer.camera(cam.spec.name))
                 for cam in cams]
    else:
        cam = cams[0]
        extra = {**metadata.extra, "video.url": cam.spec.url, "camera.timestamps": "host UTC at frame arrival"}
        metadata = replace(metadata, extra=extra)
        passthrough = cam.first is not None and cam.first.format in ("h264", "h265")
        if passthrough:
            metadata = video_metadata(metadata, cam.source, args)
        writer = RunWriter(out, metadata, camera="video" if passthrough else "image")
        feeds = None
    data = mission_path.read_bytes() if mission.source_format == "plan" else to_qgc_plan(mission).encode("utf-8")
    writer.attach("mission.plan", data, "application/json")
    if plan_json is not None:
        # The plan's region of interest and predictions travel with the run, for calibrate's validity check.
        writer.attach("plan.json", (mission_path.parent / "plan.json").read_bytes(), "application/json")
    return Recorder(
        link,
        cams[0].source,
        writer,
        tlog,
        mission,
        altitude_datum=datum,
        marker_check=check,
        first_frame=cams[0].first,
        frame_queue_size=args.frame_queue,
        link_timeout_s=args.link_timeout,
        clock=clock,
        start_ns=start_ns,
        observer=observer,
        feeds=feeds,
    ).start()


class _StatusBlock:
    """The status line (and a line per camera) printed each second: rewritten in place on a terminal, appended to a log.

    On a terminal the cursor is left at the top of the block, so a line printed in between (``\r`` + text + newline)
    overwrites its first row and the next block is drawn one row lower, over the rest: nothing stale stays.
    """

    def __init__(self, tty: bool) -> None:
        self.tty = tty
        self.rows = 0

    def show(self, lines: list[str]) -> None:
        if not self.tty:
            print("\n".join(lines), flush=True)
            return
        text = "\r" + "\n".join(line.ljust(120) for line in lines)
        up = f"\x1b[{len(lines) - 1}A\r" if len(lines) > 1 else ""
        print(text + up, end="", flush=True)
        self.rows = len(lines)

    def leave(self) -> None:
        """Move below the block (so what follows does not overwrite its camera lines)."""
        if self.tty and self.rows > 1:
            print(f"\x1b[{self.rows - 1}B", end="", flush=True)
        self.rows = 0


def _record_until_done(recorder, mission, timeout_s: float | None = None, live=None, watch=None, keeper=None, loss=None) -> bool:
    """Print the status line each second until the mission is over (True) or ``timeout_s`` passed (False).

    A mission changed by another client (``watch``, a MissionWatch) is said once, loudly; recording goes on.
    A stream that stopped while the vehicle talks is asked for again (``keeper``, a StreamKeeper).

    With the live pipeline, its part joins the status line and its summaries get lines of their own.
    Several cameras: a line per camera below the status line (its rate, drops, gaps, marker, live check).
    """
    from dronecal_field.recording.status import format_camera_status, format_status

    tty = sys.stdout.isatty()
    block = _StatusBlock(tty)
    last_print = 0.0
    done_since = None
    warned = False
    started = time.monotonic()
    while True:
        time.sleep(0.1)
        now = time.monotonic()
        if timeout_s is not None and now - started > timeout_s:
            block.leave()
            return False
        if watch is not None and watch.changed and not warned:
            warned = True
            print(f"\nWARNING: {watch.describe()}", file=sys.stderr, flush=True)
        if loss is not None and (not recorder.video_ok or loss.lost_since is not None):
            for text, alarm in loss.update(recorder.status(), now):
                line = ("\a\x1b[31m" + text + "\x1b[0m") if tty and alarm else text
                print(("\r" + line.ljust(120) + "\n") if tty else line, end="" if tty else "\n", file=sys.stderr if alarm else sys.stdout, flush=True)
        if now - last_print >= 1.0:
            late = now - last_print - 1.0 if last_print else 0.0
            last_print = now
            if keeper is not None and (again := keeper.check()):
                print(f"\nnote: asked the vehicle again for {', '.join(again)} (it had stopped sending them: rebooted, or a request lost)", flush=True)
            status = recorder.status()
            line = format_status(status, color=tty)
            if late > 1.0:  # the machine is too busy for a status a second: say so rather than look frozen
                line += f" | STATUS {late:.1f} s LATE"
            if live is not None:
                for summary in live.new_summaries():
                    print(("\r" + summary.ljust(120) + "\n") if tty else summary, end="" if tty else "\n", flush=True)
                if not status.cameras:
                    line += " | " + live.status_text()
            lines = [line] + [format_camera_status(c, color=tty, live="" if live is None else live.status_text(c.name)) for c in status.cameras]
            block.show(lines)
        if _mission_over(recorder, mission):
            done_since = done_since or now
            if now - done_since >= 1.0:  # a second more, to catch the final messages
                block.leave()
                return True


def free_run_path(out: Path) -> Path:
    """The first ``NAME-2.mcap``, ``NAME-3.mcap``... beside ``out`` whose run and .tlog are both free."""
    from dronecal_field.errors import InputError

    stem = out.stem
    for n in range(2, 10000):
        candidate = out.with_name(f"{stem}-{n}{out.suffix}")
        if not candidate.exists() and not candidate.with_suffix(".tlog").exists():
            return candidate
    raise InputError(f"--out {out}: no free name {stem}-N{out.suffix} left in {out.parent}: choose another folder")
