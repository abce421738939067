"""HTTP MJPEG (``multipart/x-mixed-replace``): each part's JPEG bytes are passed through untouched."""

from __future__ import annotations

import threading
import time
from typing import Iterator

from dronecal_field.errors import VideoError
from dronecal_field.runfile.records import Frame
from dronecal_field.video.source import VideoSource


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
