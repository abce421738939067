#!/usr/bin/python3
"""A real RTSP server on loopback for the tests and the recorder benchmark (GStreamer's gst-rtsp-server).

Run with Debian's Python (``/usr/bin/python3``: python3-gi and the GStreamer
typelibs are Debian packages, not in the venv); ``make rtsp-deps`` installs
them. Prints ``READY rtsp://127.0.0.1:PORT/cam`` once it listens.

Each client gets its own pipeline: a live test pattern with the frame counter
and clock burnt in, encoded by x264 / x265 with no B-frames, paid out as RTP
with the parameter sets in front of every keyframe (``config-interval=-1``)
unless ``--params-out-of-band`` (then only the SDP carries them). RTCP sender
reports carry the host's wall clock (``ntp-time-source=clock-time``), as a
camera synchronised by NTP does.

Faults, for the tests that falling behind is reported, not hidden:
``--pause-at S --pause-for S`` stalls the server's streaming thread once (it
then sends the backlog in a burst, with the frames' own timestamps);
``--drop-every N`` drops every Nth frame before the payloader (never a
keyframe), a camera that loses frames.

``--log FILE`` writes one line per frame handed to the payloader:
``index pts_ns send_wall_ns payload_bytes keyframe capture_wall_ns`` (payload
bytes = the slices' NAL units: a fingerprint the recorded frames share;
capture = the frame's capture instant on the server's realtime clock, base time + running time, before overlay and encoding).
"""

import argparse
import sys
import threading
import time

def payload_bytes(data: bytes, h265: bool) -> int:
    """Bytes of the slices (VCL NAL units) of one frame, Annex B or 4-byte length-prefixed: a fingerprint."""
    if data[:3] == b"\x00\x00\x01" or data[:4] == b"\x00\x00\x00\x01":
        nals = []
        i = data.find(b"\x00\x00\x01")
        while i >= 0:
            j = data.find(b"\x00\x00\x01", i + 3)
            nal = data[i + 3 : (len(data) if j < 0 else j)]
            nals.append(nal.rstrip(b"\x00") if j >= 0 else nal)
            i = j
    else:
        nals, pos = [], 0
        while pos + 4 <= len(data):
            n = int.from_bytes(data[pos : pos + 4], "big")
            nals.append(data[pos + 4 : pos + 4 + n])
            pos += 4 + n
    total = 0
    for nal in nals:
        if nal:
            t = (nal[0] >> 1) & 0x3F if h265 else nal[0] & 0x1F
            if (t < 32) if h265 else (1 <= t <= 5):
                total += len(nal)
    return total


def stamp_errors_ns(sent, frames, h265: bool, at: str = "send") -> list[int]:
    """Recorded stamp minus the server's send time, per recorded frame matched in the server log.

    ``sent``: (index, pts_ns, send_wall_ns, payload_bytes, keyframe,
    capture_wall_ns) lines of the log; ``at``: ``send`` or ``capture``; ``frames``: recorded (pts_ns, timestamp_ns, annexb_bytes). The two
    pts clocks differ by one constant (the server's running time against the
    client's first packet): the constant most frames agree on, by payload
    size, pairs them. Usable from the venv (no GStreamer import here).
    """
    from collections import Counter

    by_size = {}
    for _, pts, wall, size, *_ in sent:
        by_size.setdefault(size, []).append((pts, wall))
    votes = Counter()
    sizes = []
    for pts, _, data in frames:
        size = payload_bytes(data, h265)
        sizes.append(size)
        for spts, _ in by_size.get(size, ()):
            votes[spts - pts] += 1
    if not votes:
        return []
    offset, _ = votes.most_common(1)[0]
    column = 2 if at == "send" else 5
    wall_of = {line[1]: line[column] for line in sent}
    return [t - wall_of[pts + offset] for (pts, t, _), size in zip(frames, sizes) if pts + offset in wall_of]


def main() -> int:
    import gi

    gi.require_version("Gst", "1.0")
    gi.require_version("GstRtspServer", "1.0")
    from gi.repository import GLib, Gst, GstRtspServer

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--port", type=int, default=0)
    p.add_argument("--codec", choices=("h264", "h265"), default="h264")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--fps", type=int, default=25)
    p.add_argument("--bitrate-kbps", type=int, default=500)
    p.add_argument("--gop", type=int, default=25, help="keyframe interval, frames")
    p.add_argument("--pattern", default="ball")
    p.add_argument("--params-out-of-band", action="store_true")
    p.add_argument("--pause-at", type=float, default=None, metavar="S")
    p.add_argument("--pause-for", type=float, default=0.0, metavar="S")
    p.add_argument("--drop-every", type=int, default=0, metavar="N")
    p.add_argument("--log", default=None)
    p.add_argument("--rtcp-interval", type=float, default=None, metavar="S",
                   help="the sessions' minimum RTCP interval, seconds (GStreamer's default 5; the first report comes after a random 0.25-0.75 of it)")
    p.add_argument("--file", default=None, help="stream this Matroska file (H.264/H.265, encoded beforehand) in real time instead of encoding live")
    args = p.parse_args()

    Gst.init(None)
    log = open(args.log, "w", buffering=1) if args.log else None
    h265 = args.codec == "h265"
    config = -1 if not args.params_out_of_band else 0
    if args.codec == "h264":
        enc = (
            f"x264enc tune=zerolatency speed-preset=ultrafast bframes=0 key-int-max={args.gop} "
            f"bitrate={args.bitrate_kbps} byte-stream=true ! video/x-h264,profile=high ! "
            f"rtph264pay name=pay0 pt=96 config-interval={config}"
        )
    else:
        enc = (
            f"x265enc tune=zerolatency speed-preset=ultrafast key-int-max={args.gop} bitrate={args.bitrate_kbps} "
            f'option-string="bframes=0:repeat-headers=0:aud=0" ! video/x-h265,profile=main ! '
            f"rtph265pay name=pay0 pt=96 config-interval={config}"
        )
    overlay = "timeoverlay halignment=left valignment=top font-desc=\"Sans 24\" time-mode=running-time ! "
    if args.file:
        parse = "h265parse" if h265 else "h264parse"
        pay = "rtph265pay" if h265 else "rtph264pay"
        launch = f"( filesrc location={args.file} ! matroskademux ! {parse} name=src ! {pay} name=pay0 pt=96 config-interval={config} )"
    else:
        launch = (
            f"( videotestsrc name=src is-live=true pattern={args.pattern} ! "
            f"video/x-raw,width={args.width},height={args.height},framerate={args.fps}/1,format=I420 ! {overlay}{enc} )"
        )

    def rtcp_at_capture(_bin, _sub, element):
        # A camera's sender reports tie RTP time to its (NTP) wall clock at capture: the pipeline
        # clock is the realtime clock and the reports carry capture time, not send time.
        factory_name = element.get_factory().get_name() if element.get_factory() else ""
        if factory_name == "rtpbin":
            element.set_property("ntp-time-source", "ntp")
            element.set_property("rtcp-sync-send-time", False)
        elif factory_name == "rtpsession" and args.rtcp_interval is not None:
            element.set_property("rtcp-min-interval", int(args.rtcp_interval * 1e9))

    def configure(_factory, media):
        pipeline = media.get_element()
        top = pipeline.get_parent()
        if top is not None:
            top.connect("deep-element-added", rtcp_at_capture)
        pay = pipeline.get_by_name("pay0")
        state = {"index": 0, "paused": False, "captured": []}

        src = pipeline.get_by_name("src")

        def captured(_pad, info):
            # The frame's capture instant as the server's clock defines it (realtime pipeline clock):
            # base time + the buffer's running time, which is what its RTCP reports map.
            state["captured"].append(src.get_base_time() + info.get_buffer().pts)
            return Gst.PadProbeReturn.OK

        src.get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER, captured)

        def probe(_pad, info):
            buf = info.get_buffer()
            index = state["index"]
            state["index"] += 1
            key = not buf.has_flags(Gst.BufferFlags.DELTA_UNIT)
            if args.pause_at is not None and not state["paused"] and index >= args.pause_at * args.fps:
                state["paused"] = True
                time.sleep(args.pause_for)  # the streaming thread stalls: a camera that hangs
            if args.drop_every and not key and index % args.drop_every == args.drop_every - 1:
                return Gst.PadProbeReturn.DROP
            if log is not None:
                ok, info_map = buf.map(Gst.MapFlags.READ)
                size = payload_bytes(bytes(info_map.data), h265) if ok else -1
                if ok:
                    buf.unmap(info_map)
                capture = state["captured"][index] if index < len(state["captured"]) else 0
                log.write(f"{index} {buf.pts} {time.time_ns()} {size} {int(key)} {capture}\n")
            return Gst.PadProbeReturn.OK

        pay.get_static_pad("sink").add_probe(Gst.PadProbeType.BUFFER, probe)

    server = GstRtspServer.RTSPServer()
    server.set_address("127.0.0.1")
    server.set_service(str(args.port))
    factory = GstRtspServer.RTSPMediaFactory()
    factory.set_launch(launch)
    factory.set_shared(False)
    clock = Gst.SystemClock.obtain()
    clock.set_property("clock-type", Gst.ClockType.REALTIME)
    factory.set_clock(clock)
    factory.connect("media-configure", configure)
    server.get_mount_points().add_factory("/cam", factory)
    if server.attach(None) == 0:
        print("cannot listen", file=sys.stderr)
        return 1
    print(f"READY rtsp://127.0.0.1:{server.get_bound_port()}/cam", flush=True)
    loop = GLib.MainLoop()
    threading.Thread(target=lambda: (sys.stdin.read(), loop.quit()), daemon=True).start()  # ends when stdin closes
    loop.run()
    return 0


if __name__ == "__main__":
    sys.exit(main())
