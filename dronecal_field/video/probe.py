"""The pre-flight look at an H.264/H.265 stream: its real frame rate and whether its keyframes decode.

``fly`` probes the camera before take-off. For a packet stream
(:class:`~dronecal_field.video.packets.PacketSource`) two things are easy to
get wrong:

- the frame rate: FFmpeg reads the first second or so of the stream while
  opening it and hands it over at once (the *opening burst*), so counting
  arrivals shows 38-55 fps for a 25 fps camera. The rate here is the stream's
  own: access units per second of their presentation times, which the burst
  does not change (a camera that loses frames shows fewer);
- damaged keyframes: a server whose buffer is smaller than a keyframe (live555's
  stock 100 KB at 4K) sends every keyframe cut short. The demuxer does not
  notice; a decoder does. The probe decodes the first keyframe on its own and
  adds what the source's keyframe checker found meanwhile.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from dronecal_field.video.decode import keyframe_error


@dataclass(frozen=True)
class StreamProbe:
    """What a packet stream showed in the probe.

    Attributes
    ----------
    frames : access units read.
    fps : access units per second of presentation time, or None (fewer than 2).
    nominal_fps : the rate the stream's parameters declare, or None.
    burst_frames : access units of the opening burst (held, stamped by the pacing).
    keyframes_decoded : keyframes decoded on their own (the probe's and the checker's).
    keyframes_undecodable : those that did not decode cleanly.
    decode_error : the decoder's word on the first bad one, or None.
    """

    frames: int
    fps: float | None
    nominal_fps: float | None
    burst_frames: int
    keyframes_decoded: int
    keyframes_undecodable: int
    decode_error: str | None = None

    @property
    def warning(self) -> str | None:
        """A line for the pre-flight checklist when keyframes do not decode, else None."""
        if not self.keyframes_undecodable:
            return None
        return (
            f"{self.keyframes_undecodable} of {self.keyframes_decoded} keyframes do not decode ({self.decode_error}): "
            "cut short by the camera or its RTSP server (a send buffer smaller than a keyframe, e.g. live555's "
            "OutPacketBuffer::maxSize), or corrupt; the recording would hold damaged frames: lower the bitrate or "
            "resolution, or raise the server's buffer"
        )


def stream_rate_fps(pts_ns: list[int]) -> float | None:
    """Access units per second of presentation time: (n - 1) / (last - first); None for fewer than 2 or no span."""
    if len(pts_ns) < 2:
        return None
    span = max(pts_ns) - min(pts_ns)
    return (len(pts_ns) - 1) * 1e9 / span if span > 0 else None


def probe_packet_stream(source, first, probe_s: float = 1.0, rtcp_wait_s: float = 6.0) -> StreamProbe:
    """Read a packet stream for ``probe_s`` (longer, up to ``rtcp_wait_s``, until an RTSP camera's first RTCP report).

    Parameters
    ----------
    source : an open :class:`~dronecal_field.video.packets.PacketSource`.
    first : the access unit already read from it (a keyframe: sessions start at one).
    probe_s : seconds of reading at least.
    rtcp_wait_s : seconds to wait at most for the first RTCP sender report (RTSP).
    """
    pts = [first.pts_ns] if first.pts_ns is not None else []
    frames = 1
    decoded = bad = 0
    error = None
    if first.keyframe:
        error = keyframe_error(first.data, first.format)
        decoded, bad = 1, int(error is not None)
    t0 = time.monotonic()
    while time.monotonic() - t0 < probe_s or (source.live and source.clock != "rtcp" and time.monotonic() - t0 < rtcp_wait_s):
        frame = source.read(timeout_s=probe_s)
        if frame is None:
            if source.ended:
                break
            continue
        frames += 1
        if frame.pts_ns is not None:
            pts.append(frame.pts_ns)
    # What the source's own checker decoded meanwhile (every keyframe it was not too busy for, the first one too).
    checked = int(getattr(source, "keyframes_checked", 0))
    if checked > 1:
        decoded, bad = checked, int(getattr(source, "units_undecodable", 0))
        error = error or getattr(source, "last_decode_error", None)
    return StreamProbe(
        frames=frames,
        fps=stream_rate_fps(pts),
        nominal_fps=source.fps,
        burst_frames=int(getattr(source, "burst_frames", 0)),
        keyframes_decoded=decoded,
        keyframes_undecodable=bad,
        decode_error=error,
    )
