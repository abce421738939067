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
``index pts_ns wall_ns payload_bytes keyframe`` (payload bytes = the NAL units
without start codes, AUD and SEI; a fingerprint the recorded frames share).
"""

import argparse
import sys
import threading
import time

import gi

gi.require_version("Gst", "1.0")
gi.require_version("GstRtspServer", "1.0")
from gi.repository import GLib, Gst, GstRtspServer  # noqa: E402


def payload_bytes(data: bytes, h265: bool) -> int:
    total = 0
    i = data.find(b"\x00\x00\x01")
    while i >= 0:
        j = data.find(b"\x00\x00\x01", i + 3)
        nal = data[i + 3 : (len(data) if j < 0 else j)]
        if j >= 0:
            nal = nal.rstrip(b"\x00")
        if nal:
            t = (nal[0] >> 1) & 0x3F if h265 else nal[0] & 0x1F
            skip = (35, 39, 40) if h265 else (6, 9)
            if t not in skip:
                total += len(nal)
        i = j
    return total


def main() -> int:
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
    args = p.parse_args()

    Gst.init(None)
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
    launch = (
        f"( videotestsrc is-live=true pattern={args.pattern} ! "
        f"video/x-raw,width={args.width},height={args.height},framerate={args.fps}/1,format=I420 ! {overlay}{enc} )"
    )

    log = open(args.log, "w", buffering=1) if args.log else None
    h265 = args.codec == "h265"

    def configure(_factory, media):
        pipeline = media.get_element()
        pay = pipeline.get_by_name("pay0")
        state = {"index": 0, "paused": False}

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
                log.write(f"{index} {buf.pts} {time.time_ns()} {size} {int(key)}\n")
            return Gst.PadProbeReturn.OK

        pay.get_static_pad("sink").add_probe(Gst.PadProbeType.BUFFER, probe)

    server = GstRtspServer.RTSPServer()
    server.set_address("127.0.0.1")
    server.set_service(str(args.port))
    factory = GstRtspServer.RTSPMediaFactory()
    factory.set_launch(launch)
    factory.set_shared(False)
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
