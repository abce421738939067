"""Decoding access units (PyAV): lazily from the keyframe before a wanted frame, or one keyframe alone."""

from __future__ import annotations

from dronecal_field.runfile.records import Frame
from dronecal_field.video.nal import CODEC_OF_FORMAT, VideoFrame, is_keyframe, join_annexb, nal_type, split_annexb


class VideoFrameDecoder:
    """Decode an access-unit stream lazily: only from the keyframe before a wanted frame up to it.

    Feed every access unit in order with :meth:`push`; ask for the picture of
    the last one pushed with :meth:`gray`. Access units are kept, not decoded,
    until a picture is asked for; a keyframe drops what was kept, so a GOP
    with no wanted frame is never decoded and a GOP is decoded only up to its
    last wanted frame. Slice threads only: frame threads would hold pictures
    back, and the decoder could not hand out the one just pushed.
    """

    def __init__(self, fmt: str, threads: int = 2) -> None:
        import av

        self.format = fmt
        self._ctx = av.CodecContext.create(CODEC_OF_FORMAT[fmt], "r")
        self._ctx.thread_type = "SLICE"
        self._ctx.thread_count = max(1, int(threads))
        self._pending: list[bytes] = []
        self._have_key = False  # the decoder holds a decodable reference chain
        self.decoded = 0  # access units decoded
        self.skipped = 0  # access units never decoded (GOP tails with no wanted frame)
        self.errors = 0

    def push(self, frame: Frame) -> None:
        """The next access unit of the stream (in decode = presentation order)."""
        key = frame.keyframe if isinstance(frame, VideoFrame) else is_keyframe(frame.data, self.format)
        if key:
            self.skipped += len(self._pending) if self._have_key else 0
            self._pending = []
            self._have_key = True
        elif not self._have_key:
            self.skipped += 1
            return  # before the first keyframe: undecodable
        self._pending.append(frame.data)

    def gray(self):
        """(H, W) uint8 luma of the access unit pushed last, or None (no keyframe before it, corrupt data)."""
        import av

        if not self._have_key or not self._pending:
            return None
        pending, self._pending = self._pending, []
        last = None
        for data in pending:
            try:
                frames = self._ctx.decode(av.Packet(data))
            except av.FFmpegError:
                self.errors += 1
                frames = []
            self.decoded += 1
            # Only the last unit's own picture (no B-frames: each unit gives its picture at once). A unit that
            # gives none (damaged, cut) is None: never an earlier unit's picture under this unit's stamp.
            last = frames[-1] if frames else None
        if last is None:
            return None
        import numpy as np

        plane = last.planes[0]
        h, w = last.height, last.width
        arr = np.frombuffer(plane, np.uint8).reshape(h, plane.line_size)[:, :w]
        return np.ascontiguousarray(arr)


def decode_keyframe_gray(data: bytes, fmt: str):
    """(H, W) uint8 luma of one keyframe access unit decoded on its own, or None."""
    import av

    ctx = av.CodecContext.create(CODEC_OF_FORMAT[fmt], "r")
    try:
        frames = list(ctx.decode(av.Packet(data))) + list(ctx.decode(None))
    except av.FFmpegError:
        return None
    if not frames:
        return None
    import numpy as np

    f = frames[0]
    plane = f.planes[0]
    return np.ascontiguousarray(np.frombuffer(plane, np.uint8).reshape(f.height, plane.line_size)[:, : f.width])


def keyframe_error(data: bytes, fmt: str) -> str | None:
    """Why one keyframe access unit does not decode cleanly on its own, or None when it does (:func:`check_keyframe`)."""
    return check_keyframe(data, fmt)[0]


def check_keyframe(data: bytes, fmt: str):
    """(why one keyframe access unit does not decode cleanly on its own or None, its (H, W) uint8 luma or None).

    One decoder thread with FFmpeg's ``err_detect=explode``: an error the
    decoder finds (a slice that runs out of bits, as in a keyframe cut by a
    server's too-small buffer) fails the decode instead of being concealed.
    H.264 finds every cut slice this way (CABAC's end check); H.265 only those
    the decoder notices (a syntax element out of range), so a clean result is
    no proof for H.265. SEI units are left out: they carry no picture, and
    x265's (its options as text) would fail the check on their own.
    The picture comes with the check for the cost of a copy: the recorder's
    marker probe takes it instead of decoding the keyframe a second time
    (4K H.265: ~130 ms of CPU a decode).
    """
    import av
    import numpy as np

    sei = (6,) if fmt == "h264" else (39, 40)  # SEI says nothing about the picture (x265's options text trips explode)
    data = join_annexb([n for n in split_annexb(data) if nal_type(n, fmt) not in sei])
    ctx = av.CodecContext.create(CODEC_OF_FORMAT[fmt], "r")
    ctx.thread_count = 1
    ctx.options = {"err_detect": "explode"}
    try:
        frames = list(ctx.decode(av.Packet(data))) + list(ctx.decode(None))
    except av.FFmpegError as exc:
        return f"{type(exc).__name__}: {exc}", None
    if not frames:
        return "no picture decoded", None
    f = frames[0]
    plane = f.planes[0]
    return None, np.ascontiguousarray(np.frombuffer(plane, np.uint8).reshape(f.height, plane.line_size)[:, : f.width])
