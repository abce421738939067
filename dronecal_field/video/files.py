"""Recorded video files for ``import``: frames stamped by their position in the file, the container's creation time.

JPEG re-encoding through OpenCV (:func:`read_video_file`), H.264/H.265
access units as recorded (:func:`read_video_packets`), and the MP4
``mvhd`` creation time (:func:`video_creation_time_ns`).
"""

from __future__ import annotations

import os
import struct
from typing import Iterator

from dronecal_field.errors import VideoError
from dronecal_field.runfile.records import Frame
from dronecal_field.video.nal import FORMAT_OF_CODEC, VideoFrame, access_unit, is_keyframe, parameter_sets, video_format


def read_video_file(
    path: str | os.PathLike,
    start_ns: int,
    jpeg_quality: int = 95,
    max_fps: float | None = None,
) -> Iterator[tuple[int, Frame, tuple[int, int]]]:
    """Frames of a video file stamped by their position in it.

    Parameters
    ----------
    path : the video file.
    start_ns : UTC ns of the file's first frame.
    jpeg_quality : JPEG quality (0-100).
    max_fps : keep at most this many frames per second of video; None keeps all.

    Yields
    ------
    (index, frame, (width, height)) : ``frame.timestamp_ns`` = start_ns + the
        frame's presentation time (OpenCV ``CAP_PROP_POS_MSEC``, or index/fps).

    Raises
    ------
    VideoError
        when OpenCV cannot open the file.
    """
    import cv2

    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        cap.release()
        raise VideoError(f"video file {path}: OpenCV cannot open it; check the file and its codec")
    try:
        fps = cap.get(cv2.CAP_PROP_FPS) or 0.0
        params = [int(cv2.IMWRITE_JPEG_QUALITY), int(jpeg_quality)]
        min_step_ns = int(1e9 / max_fps) if max_fps else 0
        last_kept: int | None = None
        index = 0
        while True:
            ok, image = cap.read()
            if not ok or image is None:
                return
            pos_ms = cap.get(cv2.CAP_PROP_POS_MSEC)
            if fps > 0 and (pos_ms is None or pos_ms <= 0) and index > 0:
                offset_ns = int(round(index * 1e9 / fps))
            elif pos_ms is not None and pos_ms >= 0:
                offset_ns = int(round(pos_ms * 1e6))
            else:
                offset_ns = int(round(index * 1e9 / fps)) if fps > 0 else 0
            t_ns = int(start_ns) + offset_ns
            if last_kept is None or t_ns - last_kept >= min_step_ns:
                ok, jpeg = cv2.imencode(".jpg", image, params)
                if not ok:
                    raise VideoError(f"video file {path}: JPEG encoding failed at frame {index}")
                last_kept = t_ns
                h, w = image.shape[:2]
                yield index, Frame(timestamp_ns=t_ns, format="jpeg", data=jpeg.tobytes()), (w, h)
            index += 1
    finally:
        cap.release()


_MP4_EPOCH_TO_UNIX_S = 2_082_844_800  # seconds from 1904-01-01 to 1970-01-01


def video_creation_time_ns(path: str | os.PathLike) -> int | None:
    """Creation time (UTC ns) from an MP4/MOV ``moov/mvhd`` box, or None when absent or zero.

    Cameras write the recording start there; a zero value (common for
    software encoders) means unknown.
    """
    try:
        with open(path, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            moov = _find_box(f, 0, size, b"moov")
            if moov is None:
                return None
            mvhd = _find_box(f, moov[0], moov[1], b"mvhd")
            if mvhd is None:
                return None
            f.seek(mvhd[0])
            version = f.read(4)[0]
            raw = f.read(8 if version == 1 else 4)
            seconds = int.from_bytes(raw, "big")
    except (OSError, IndexError):
        return None
    if seconds == 0:
        return None
    return (seconds - _MP4_EPOCH_TO_UNIX_S) * 1_000_000_000


def _find_box(f, start: int, end: int, kind: bytes) -> tuple[int, int] | None:
    """(payload start, payload end) of the first ISO-BMFF box of this type in [start, end)."""
    pos = start
    while pos + 8 <= end:
        f.seek(pos)
        head = f.read(8)
        if len(head) < 8:
            return None
        size, box = struct.unpack(">I4s", head)
        header = 8
        if size == 1:
            big = f.read(8)
            if len(big) < 8:
                return None
            size = struct.unpack(">Q", big)[0]
            header = 16
        elif size == 0:
            size = end - pos
        if size < header:
            return None
        if box == kind:
            return pos + header, pos + size
        pos += size
    return None


def read_video_packets(path: str, start_ns: int) -> Iterator[tuple[int, VideoFrame, tuple[int, int]]]:
    """Access units of an H.264/H.265 file (MP4, MKV, TS...) as recorded, stamped by position.

    Yields
    ------
    (index, frame, (width, height)) : ``frame.timestamp_ns`` = ``start_ns`` +
        the presentation time since the first frame; Annex B with the
        parameter sets in front of every keyframe.

    Raises
    ------
    VideoError
        when the file cannot be opened, is not H.264/H.265, or has B-frames
        (frames out of presentation order cannot be a ``/camera/video`` run).
    """
    import av

    try:
        container = av.open(str(path))
    except (av.FFmpegError, OSError) as exc:
        raise VideoError(f"video file {path}: cannot open it ({exc}); check the file") from exc
    try:
        if not container.streams.video:
            raise VideoError(f"video file {path}: no video stream in it")
        stream = container.streams.video[0]
        fmt = video_format(stream.codec_context.name)
        params, length_size = parameter_sets(stream.codec_context.extradata, fmt)
        size = (int(stream.codec_context.width), int(stream.codec_context.height))
        tb = stream.time_base
        first: int | None = None
        last: int | None = None
        index = 0
        for packet in container.demux(stream):
            if packet.size == 0 or packet.pts is None:
                continue
            if (packet.dts is not None and packet.pts != packet.dts) or (last is not None and packet.pts <= last):
                raise VideoError(
                    f"video file {path}: frames out of order at frame {index} (B-frames); "
                    "/camera/video needs a stream without B-frames: import with --video-reencode (JPEG frames)"
                )
            last = packet.pts
            first = packet.pts if first is None else first
            data = bytes(packet)
            key = bool(packet.is_keyframe) or (length_size is None and is_keyframe(data, fmt))
            au = access_unit(data, fmt, key, params, length_size)
            t_ns = int(start_ns) + int((packet.pts - first) * tb * 1_000_000_000)
            yield index, VideoFrame(timestamp_ns=t_ns, format=fmt, data=au, keyframe=key, pts_ns=t_ns - int(start_ns)), size
            index += 1
    finally:
        container.close()


def probe_video_format(path: str) -> str | None:
    """``h264`` / ``h265`` when the file's first video stream is one of them, else None (or unreadable)."""
    import av

    try:
        with av.open(str(path)) as container:
            if not container.streams.video:
                return None
            return FORMAT_OF_CODEC.get(container.streams.video[0].codec_context.name.lower())
    except (av.FFmpegError, OSError):
        return None
