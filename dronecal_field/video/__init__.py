"""Video sources: HTTP MJPEG (JPEG pass-through), RTSP and files (H.264/H.265 pass-through), devices (OpenCV).

The transport is chosen by an explicit scheme, never guessed:

==========================  ================================================
``http://``, ``https://``   MJPEG (``multipart/x-mixed-replace``); each part's
                            JPEG bytes are passed through untouched
``rtsp://``, ``rtsps://``   PyAV packets, never decoded: H.264/H.265 access
                            units for ``/camera/video``
                            (:mod:`dronecal_field.video.packets`), over TCP or
                            UDP as ``rtsp_transport`` says
``/dev/videoN``             OpenCV (V4L2); frames encoded to JPEG
``file://PATH`` or a path   H.264/H.265 files as packets (as RTSP); other
                            codecs through OpenCV, frames encoded to JPEG
==========================  ================================================

Each source runs one capture thread that stamps every frame with the host
clock (``time.time_ns()``) the moment it arrives and hands it over through a
bounded queue: a live source drops the oldest frame when the consumer falls
behind (counted in ``frames_dropped``); a file source blocks instead.

For importing a recorded video, :func:`read_video_file` stamps frames with
their position in the file instead, and :func:`video_creation_time_ns` reads
the container's creation time.
"""

from __future__ import annotations

from pathlib import Path

from dronecal_field.errors import VideoError
from dronecal_field.video.device import OpenCvSource
from dronecal_field.video.files import read_video_file, video_creation_time_ns
from dronecal_field.video.mjpeg import MjpegHttpSource
from dronecal_field.video.packets import PacketSource, open_packet_source
from dronecal_field.video.source import VideoSource

__all__ = ["SCHEMES", "open_video", "VideoSource", "MjpegHttpSource", "OpenCvSource", "PacketSource", "open_packet_source",
           "read_video_file", "video_creation_time_ns"]

SCHEMES = ("http://", "https://", "rtsp://", "rtsps://", "file://", "/dev/video", "a file path")


def open_video(
    url: str,
    timeout_s: float = 5.0,
    queue_size: int = 16,
    jpeg_quality: int = 95,
    rtsp_transport: str = "tcp",
) -> "VideoSource":
    """Open a video source by explicit scheme (see the module docstring).

    Parameters
    ----------
    url : ``http(s)://`` MJPEG URL, ``rtsp(s)://`` URL, ``/dev/videoN``,
        ``file://PATH`` or a file path.
    timeout_s : connect / first-response timeout, seconds.
    queue_size : frames buffered between the capture thread and ``read``.
    jpeg_quality : JPEG quality (0-100) for sources OpenCV decodes.
    rtsp_transport : ``tcp`` (default: a slow reader delays, never corrupts)
        or ``udp`` (losses are counted by the stream monitor).

    Raises
    ------
    VideoError
        when the scheme is unknown or the source cannot be opened.
    """
    lowered = url.lower()
    if lowered.startswith(("http://", "https://")):
        source: VideoSource = MjpegHttpSource(url, timeout_s=timeout_s, queue_size=queue_size)
    elif lowered.startswith(("rtsp://", "rtsps://")):
        return open_packet_source(url, timeout_s=timeout_s, rtsp_transport=rtsp_transport, queue_size=max(queue_size, 64))
    elif lowered.startswith("/dev/video"):
        source = OpenCvSource(url, live=True, timeout_s=timeout_s, queue_size=queue_size, jpeg_quality=jpeg_quality)
    elif lowered.startswith("file://") or "://" not in url:
        path = url[len("file://"):] if lowered.startswith("file://") else url
        if not Path(path).is_file():
            raise VideoError(f"video file {path!r} does not exist; give an existing file, /dev/videoN, rtsp:// or http:// URL")
        try:
            return open_packet_source(path, timeout_s=timeout_s, queue_size=queue_size)
        except VideoError:
            pass  # not H.264/H.265 (MJPEG, VP9...): decoded by OpenCV and encoded to JPEG
        source = OpenCvSource(path, live=False, timeout_s=timeout_s, queue_size=queue_size, jpeg_quality=jpeg_quality)
    else:
        scheme = url.split("://", 1)[0]
        raise VideoError(f"video source {url!r}: scheme '{scheme}://' is not supported; use one of {', '.join(SCHEMES)}")
    source.open()
    return source
