"""Video sources: HTTP MJPEG (JPEG pass-through), RTSP and files (H.264/H.265 pass-through), devices (OpenCV).

The transport is chosen by an explicit scheme, never guessed:

==========================  ================================================
``http://``, ``https://``   MJPEG (``multipart/x-mixed-replace``); each part's
                            JPEG bytes are passed through untouched
``rtsp://``, ``rtsps://``   PyAV packets, never decoded: H.264/H.265 access
                            units for ``/camera/video``
                            (:mod:`dronecal_field.videopackets`), over TCP or
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

import os
import queue
import struct
import threading
import time
from pathlib import Path
from typing import Iterator

from dronecal_field.errors import VideoError
from dronecal_field.runfile.records import Frame

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
        from dronecal_field.videopackets import open_packet_source

        return open_packet_source(url, timeout_s=timeout_s, rtsp_transport=rtsp_transport, queue_size=max(queue_size, 64))
    elif lowered.startswith("/dev/video"):
        source = OpenCvSource(url, live=True, timeout_s=timeout_s, queue_size=queue_size, jpeg_quality=jpeg_quality)
    elif lowered.startswith("file://") or "://" not in url:
        path = url[len("file://"):] if lowered.startswith("file://") else url
        if not Path(path).is_file():
            raise VideoError(f"video file {path!r} does not exist; give an existing file, /dev/videoN, rtsp:// or http:// URL")
        from dronecal_field.videopackets import open_packet_source

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


class VideoSource:
    """A stream of compressed frames stamped on arrival (host clock).

    Attributes
    ----------
    url : what was opened.
    live : True for cameras and streams (old frames are dropped when the
        consumer is slow), False for files.
    frames_received, frames_dropped, bytes_received : counters since creation.
    reconnects : how many times ``reopen`` succeeded.
    ended : the capture thread stopped (end of file, error or close).
    last_error : why it stopped on an error, else None.
    """

    def __init__(self, url: str, live: bool, timeout_s: float, queue_size: int) -> None:
        self.url = url
        self.live = live
        self.timeout_s = float(timeout_s)
        self.frames_received = 0
        self.frames_dropped = 0
        self.bytes_received = 0
        self.reconnects = 0
        self.last_error: str | None = None
        self._queue: queue.Queue[Frame] = queue.Queue(maxsize=max(1, int(queue_size)))
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # -- public --------------------------------------------------------------

    @property
    def ended(self) -> bool:
        return self._thread is None or not self._thread.is_alive()

    def read(self, timeout_s: float = 1.0) -> Frame | None:
        """The next frame, or None when none arrives within ``timeout_s`` or the source has ended.

        Check ``ended`` after a None: a live source that ended can be
        ``reopen()``-ed.
        """
        deadline = time.monotonic() + max(0.0, timeout_s)
        while True:
            try:
                return self._queue.get(timeout=min(0.05, max(0.0, deadline - time.monotonic())) or 0.001)
            except queue.Empty:
                if self.ended and self._queue.empty():
                    return None
                if time.monotonic() >= deadline:
                    return None

    def open(self) -> None:
        """Connect and start the capture thread; raise VideoError when it cannot."""
        self._connect()
        self._stop.clear()
        self.last_error = None
        self._thread = threading.Thread(target=self._run, name=f"video:{self.url}", daemon=True)
        self._thread.start()

    def reopen(self) -> None:
        """Close and connect again (after a dropped stream); frames already queued are kept."""
        self._halt()
        self.open()
        self.reconnects += 1

    def close(self) -> None:
        """Stop the capture thread and release the source (idempotent)."""
        self._halt()

    def __enter__(self) -> "VideoSource":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- for subclasses --------------------------------------------------------

    def _connect(self) -> None:
        raise NotImplementedError

    def _disconnect(self) -> None:
        """Unblock the capture thread; release the source when no thread owns it."""
        raise NotImplementedError

    def _frames(self) -> Iterator[Frame]:
        """Frames of the connection made by _connect; releases it when done."""
        raise NotImplementedError

    # -- internals ---------------------------------------------------------

    def _halt(self) -> None:
        self._stop.set()
        self._disconnect()  # unblocks a capture thread waiting on the socket
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=max(2.0, self.timeout_s))

    def _run(self) -> None:
        try:
            for frame in self._frames():
                if self._stop.is_set():
                    return
                self.frames_received += 1
                self.bytes_received += len(frame.data)
                self._deliver(frame)
        except Exception as exc:  # noqa: BLE001 - reported through last_error / ended
            if not self._stop.is_set():
                self.last_error = f"{type(exc).__name__}: {exc}"

    def _deliver(self, frame: Frame) -> None:
        if not self.live:
            while not self._stop.is_set():
                try:
                    self._queue.put(frame, timeout=0.1)
                    return
                except queue.Full:
                    continue
            return
        while True:
            try:
                self._queue.put_nowait(frame)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                    self.frames_dropped += 1
                except queue.Empty:
                    pass


class MjpegHttpSource(VideoSource):
    """HTTP ``multipart/x-mixed-replace`` MJPEG, parsed here; JPEG bytes passed through."""

    def __init__(self, url: str, timeout_s: float = 5.0, queue_size: int = 16) -> None:
        super().__init__(url, live=True, timeout_s=timeout_s, queue_size=queue_size)
        self._response = None
        self._boundary = b""

    def _connect(self) -> None:
        import urllib.error
        import urllib.request

        request = urllib.request.Request(self.url, headers={"User-Agent": "dronecal-field"})
        try:
            response = urllib.request.urlopen(request, timeout=self.timeout_s)
        except urllib.error.HTTPError as exc:
            raise VideoError(f"MJPEG source {self.url}: HTTP {exc.code} {exc.reason}; check the URL path") from exc
        except (urllib.error.URLError, OSError) as exc:
            reason = getattr(exc, "reason", exc)
            raise VideoError(f"MJPEG source {self.url}: cannot connect ({reason}); check the address and that the camera is on") from exc
        content_type = response.headers.get("Content-Type", "")
        boundary = _multipart_boundary(content_type)
        if boundary is None:
            response.close()
            raise VideoError(
                f"MJPEG source {self.url}: Content-Type is {content_type!r}, not multipart/x-mixed-replace; "
                "give the camera's MJPEG stream URL"
            )
        self._response = response
        self._boundary = b"--" + boundary.encode("latin-1").removeprefix(b"--")

    def _disconnect(self) -> None:
        response, self._response = self._response, None
        _close_response(response)

    def _frames(self) -> Iterator[Frame]:
        response = self._response
        if response is None:
            return
        try:
            yield from _mjpeg_parts(response, self._boundary, self._stop)
        finally:
            _close_response(response)
            if self._response is response:
                self._response = None


def _mjpeg_parts(response, boundary: bytes, stop: threading.Event) -> Iterator[Frame]:
    """Frames of a multipart/x-mixed-replace body; each part's bytes are passed through.

    Parts with a Content-Length are read by length; parts without one end at
    the next boundary. A frame is stamped when its part headers have arrived.
    """
    buf = bytearray()

    def fill() -> bool:
        data = response.read1(65536)
        if not data:
            return False
        buf.extend(data)
        return True

    while not stop.is_set():
        # Find the next boundary line.
        while True:
            i = buf.find(boundary)
            if i >= 0:
                del buf[: i + len(boundary)]
                break
            del buf[: max(0, len(buf) - len(boundary))]
            if not fill():
                return
        # Part headers end with an empty line.
        while True:
            crlf, lf = buf.find(b"\r\n\r\n"), buf.find(b"\n\n")
            if crlf >= 0 or lf >= 0:
                break
            if not fill():
                return
        arrival_ns = time.time_ns()
        if crlf >= 0 and (lf < 0 or crlf < lf):
            head, body_at = bytes(buf[:crlf]), crlf + 4
        else:
            head, body_at = bytes(buf[:lf]), lf + 2
        del buf[:body_at]
        if head.strip().startswith(b"--"):
            return  # the closing boundary "--boundary--"
        headers = _parse_headers(head)
        length = headers.get("content-length", "")
        if length.isdigit():
            n = int(length)
            while len(buf) < n:
                if not fill():
                    return
            data = bytes(buf[:n])
            del buf[:n]
        else:
            while True:
                j = buf.find(boundary)
                if j >= 0:
                    break
                if not fill():
                    return
            data = bytes(buf[:j]).removesuffix(b"\r\n").removesuffix(b"\n")
            del buf[:j]
        kind = headers.get("content-type", "image/jpeg").lower()
        fmt = "png" if "png" in kind else "jpeg"
        yield Frame(timestamp_ns=arrival_ns, format=fmt, data=data)


def _close_response(response) -> None:
    """Close an HTTP response, shutting its socket first so a blocked read returns."""
    if response is None:
        return
    try:
        raw = getattr(getattr(response, "fp", None), "raw", None)
        sock = getattr(raw, "_sock", None)
        if sock is not None:
            import socket

            sock.shutdown(socket.SHUT_RDWR)
    except OSError:
        pass
    try:
        response.close()
    except Exception:  # noqa: BLE001 - closing a broken stream
        pass


def _multipart_boundary(content_type: str) -> str | None:
    """The boundary parameter of a multipart/x-mixed-replace Content-Type, or None."""
    parts = [p.strip() for p in content_type.split(";")]
    if not parts or parts[0].lower() != "multipart/x-mixed-replace":
        return None
    for p in parts[1:]:
        if p.lower().startswith("boundary="):
            return p.split("=", 1)[1].strip().strip('"')
    return None


def _parse_headers(block: bytes) -> dict[str, str]:
    out = {}
    for line in block.decode("latin-1").splitlines():
        if ":" in line:
            k, v = line.split(":", 1)
            out[k.strip().lower()] = v.strip()
    return out


class OpenCvSource(VideoSource):
    """RTSP streams, V4L2 devices and files through cv2.VideoCapture; frames encoded to JPEG."""

    def __init__(self, url: str, live: bool, timeout_s: float = 5.0, queue_size: int = 16, jpeg_quality: int = 95) -> None:
        super().__init__(url, live=live, timeout_s=timeout_s, queue_size=queue_size)
        self.jpeg_quality = int(jpeg_quality)
        self._cap = None
        self._cap_lock = threading.Lock()

    def _connect(self) -> None:
        import cv2

        if self.url.startswith("/dev/video"):
            cap = cv2.VideoCapture(self.url, cv2.CAP_V4L2)
        elif self.url.lower().startswith(("rtsp://", "rtsps://")):
            ms = int(self.timeout_s * 1000)
            params = [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, ms, cv2.CAP_PROP_READ_TIMEOUT_MSEC, ms]
            cap = cv2.VideoCapture(self.url, cv2.CAP_FFMPEG, params)
        else:
            cap = cv2.VideoCapture(self.url)
        if not cap.isOpened():
            cap.release()
            raise VideoError(f"video source {self.url}: OpenCV cannot open it; check the path/URL and the codec")
        with self._cap_lock:
            self._cap = cap

    def _disconnect(self) -> None:
        # A capture thread releases its own capture when it exits (a read may be
        # blocked inside it); only a capture no thread owns is released here.
        if self._thread is None or not self._thread.is_alive():
            with self._cap_lock:
                cap, self._cap = self._cap, None
            if cap is not None:
                cap.release()

    def _frames(self) -> Iterator[Frame]:
        import cv2

        with self._cap_lock:
            cap = self._cap
        if cap is None:
            return
        params = [int(cv2.IMWRITE_JPEG_QUALITY), self.jpeg_quality]
        try:
            while not self._stop.is_set():
                ok, image = cap.read()
                arrival_ns = time.time_ns()
                if not ok or image is None:
                    return
                ok, jpeg = cv2.imencode(".jpg", image, params)
                if not ok:
                    raise VideoError(f"video source {self.url}: JPEG encoding failed")
                yield Frame(timestamp_ns=arrival_ns, format="jpeg", data=jpeg.tobytes())
        finally:
            with self._cap_lock:
                if self._cap is cap:
                    self._cap = None
            cap.release()


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
