"""The simulated camera's RTSP output: rendered frames encoded to H.264/H.265 and served by GStreamer's RTSP server.

A real IP camera streams RTSP with RTCP sender reports that tie its RTP clock
to its wall clock; this is that, for the simulator. GStreamer's Python
bindings are Debian packages (``make rtsp-deps``), not in the venv, so the
server runs as a child process of Debian's Python (this same file run as a
script: it imports only the standard library and ``gi``) and
:class:`RtspOut` feeds it raw frames over a pipe:

``8-byte little-endian frame time (UTC ns) + width * height * 3 / 2 bytes (I420)``

The frames cross the pipe as I420, converted on the venv side by OpenCV
(7 ms of CPU a 4K frame here, against 33 ms in GStreamer's videoconvert, and
half the bytes through the pipe). One encoder for every client (a shared
media, as a camera has): appsrc -> x264enc / x265enc (no B-frames, a keyframe every ``gop``
frames, the parameter sets in front of each) -> rtph264pay / rtph265pay.
The pipeline runs on the realtime (UTC) clock and each buffer's timestamp
is its frame time, so the sender reports map RTP time to the instant the
frame shows (its capture), as a camera synchronised by NTP does. Frames that
come while nobody watches are dropped.
"""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import threading
from dataclasses import dataclass

CODECS = ("h264", "h265")
SYSTEM_PYTHON = "/usr/bin/python3"
_HEADER = struct.Struct("<q")


@dataclass(frozen=True)
class RtspAddress:
    """Where the RTSP stream is served: ``rtsp://host:port/path``."""

    host: str
    port: int
    path: str


class RtspOut:
    """The RTSP server child process and the pipe that feeds it (venv side: no GStreamer import here).

    Parameters
    ----------
    address : host, port (0: a free one) and mount path.
    width, height : frame size, pixels.
    fps : frames per second.
    codec : ``h264`` or ``h265``.
    gop : keyframe interval, frames (default: 2 s of frames).
    bitrate_kbps : encoder bitrate, kbit/s (default: ~0.1 bit per pixel per frame).
    """

    def __init__(self, address: RtspAddress, width: int, height: int, fps: float, codec: str = "h264",
                 gop: int | None = None, bitrate_kbps: int | None = None) -> None:
        from dronecal_field.errors import InputError

        if codec not in CODECS:
            raise InputError(f"--codec {codec!r}: use h264 or h265")
        if not os.path.exists(SYSTEM_PYTHON):
            raise InputError(f"RTSP serving needs Debian's Python with GStreamer ({SYSTEM_PYTHON}): run `make rtsp-deps`")
        self.width, self.height, self.fps, self.codec = int(width), int(height), float(fps), codec
        self.gop = int(gop) if gop else max(1, int(round(2 * fps)))
        self.bitrate_kbps = int(bitrate_kbps) if bitrate_kbps else max(500, int(0.1 * width * height * fps / 1000))
        if self.width % 2 or self.height % 2:
            raise InputError(f"{self.width}x{self.height}: RTSP serving needs an even width and height (4:2:0 video)")
        self._frame_bytes = self.width * self.height * 3 // 2
        self._lock = threading.Lock()
        self.frames_sent = 0
        self.proc = subprocess.Popen(
            [SYSTEM_PYTHON, os.path.abspath(__file__), address.host, str(address.port), address.path, str(self.width), str(self.height),
             f"{self.fps:g}", codec, str(self.gop), str(self.bitrate_kbps)],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, bufsize=0,
        )
        line = self.proc.stdout.readline().decode("utf-8", "replace").strip()
        if not line.startswith("READY "):
            err = self.proc.stderr.read().decode("utf-8", "replace") if self.proc.poll() is not None else ""
            self.close()
            raise InputError(f"the RTSP server did not start ({line or err.strip()[-300:]}); run `make rtsp-deps` (GStreamer's RTSP server)")
        self.url = line.split()[1]

    def send(self, frame_time_ns: int, bgr) -> bool:
        """One rendered frame ((H, W, 3) uint8 BGR) shown at ``frame_time_ns`` (UTC); False once the server is gone."""
        import cv2

        if bgr.shape != (self.height, self.width, 3):
            raise ValueError(f"frame of shape {bgr.shape}, expected ({self.height}, {self.width}, 3)")
        data = memoryview(cv2.cvtColor(bgr, cv2.COLOR_BGR2YUV_I420)).cast("B")
        with self._lock:
            try:
                self.proc.stdin.write(_HEADER.pack(int(frame_time_ns)))
                self.proc.stdin.write(data)
            except (BrokenPipeError, ValueError, OSError):
                return False
        self.frames_sent += 1
        return True

    def close(self) -> None:
        """End the server (its stdin closes) and wait for it."""
        try:
            if self.proc.stdin is not None:
                self.proc.stdin.close()
        except OSError:
            pass
        try:
            self.proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()


# ----- the server side: Debian's Python with GStreamer (run as a script) -----


def _serve(host: str, port: int, path: str, width: int, height: int, fps: str, codec: str, gop: int, bitrate_kbps: int) -> int:
    import gi

    gi.require_version("Gst", "1.0")
    gi.require_version("GstRtspServer", "1.0")
    from gi.repository import GLib, Gst, GstRtspServer

    Gst.init(None)
    from fractions import Fraction

    rate = Fraction(fps).limit_denominator(1001)
    if codec == "h264":
        enc = (f"x264enc tune=zerolatency speed-preset=ultrafast bframes=0 key-int-max={gop} bitrate={bitrate_kbps} byte-stream=true ! "
               "video/x-h264,profile=high ! rtph264pay name=pay0 pt=96 config-interval=-1")
    else:
        enc = (f"x265enc tune=zerolatency speed-preset=ultrafast key-int-max={gop} bitrate={bitrate_kbps} "
               'option-string="bframes=0:repeat-headers=1:aud=0" ! video/x-h265,profile=main ! rtph265pay name=pay0 pt=96 config-interval=-1')
    caps = f"video/x-raw,format=I420,width={width},height={height},framerate={rate.numerator}/{rate.denominator}"
    launch = f"( appsrc name=src is-live=true format=time do-timestamp=false caps={caps} ! queue max-size-buffers=4 leaky=downstream ! {enc} )"
    state: dict = {"src": None, "pipeline": None}
    lock = threading.Lock()

    def rtcp_at_capture(_bin, _sub, element):
        factory = element.get_factory()
        if factory is not None and factory.get_name() == "rtpbin":
            element.set_property("ntp-time-source", "ntp")  # the pipeline's (realtime) clock
            element.set_property("rtcp-sync-send-time", False)  # RTP time <-> the buffer's time: capture, not send

    def configure(_factory, media):
        pipeline = media.get_element()
        top = pipeline.get_parent()
        if top is not None:
            top.connect("deep-element-added", rtcp_at_capture)
        with lock:
            state["src"], state["pipeline"] = pipeline.get_by_name("src"), pipeline
        media.connect("unprepared", lambda _m: forget(pipeline))

    def forget(pipeline) -> None:
        # Only this media's own pipeline: a client that reconnects gets a new media, configured before
        # the old one's "unprepared" comes; clearing then left the new media unfed (the stream went
        # silent for good after fly's first reconnect: "NO VIDEO" for the rest of a flight).
        with lock:
            if state["pipeline"] is pipeline:
                state.update(src=None, pipeline=None)

    server = GstRtspServer.RTSPServer()
    server.set_address(host)
    server.set_service(str(port))
    factory = GstRtspServer.RTSPMediaFactory()
    factory.set_launch(launch)
    factory.set_shared(True)  # one encoder for every client, as a camera has
    clock = Gst.SystemClock.obtain()
    clock.set_property("clock-type", Gst.ClockType.REALTIME)
    factory.set_clock(clock)
    factory.connect("media-configure", configure)
    server.get_mount_points().add_factory(path, factory)
    if server.attach(None) == 0:
        print(f"cannot listen on {host}:{port}", file=sys.stderr, flush=True)
        return 1
    loop = GLib.MainLoop()
    frame_bytes = width * height * 3 // 2

    def feed() -> None:
        stdin = sys.stdin.buffer
        while True:
            head = stdin.read(8)
            if len(head) < 8:
                break
            data = stdin.read(frame_bytes)
            if len(data) < frame_bytes:
                break
            with lock:
                src, pipeline = state["src"], state["pipeline"]
            if src is None or pipeline is None:
                continue  # nobody watches
            base = pipeline.get_base_time()
            (t_ns,) = _HEADER.unpack(head)
            if base == Gst.CLOCK_TIME_NONE or base == 0 or t_ns < base:
                continue  # not playing yet
            buf = Gst.Buffer.new_wrapped(data)
            buf.pts = buf.dts = t_ns - base  # running time of the frame's instant: RTCP maps it back to t_ns
            buf.duration = int(1e9 * rate.denominator / rate.numerator)
            src.emit("push-buffer", buf)
        loop.quit()

    threading.Thread(target=feed, daemon=True).start()
    print(f"READY rtsp://{host}:{server.get_bound_port()}{path}", flush=True)
    loop.run()
    return 0


if __name__ == "__main__":
    a = sys.argv[1:]
    sys.exit(_serve(a[0], int(a[1]), a[2], int(a[3]), int(a[4]), a[5], a[6], int(a[7]), int(a[8])))
