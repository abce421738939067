"""V4L2 devices (and codecs PyAV does not pass through) via OpenCV; frames encoded to JPEG."""

from __future__ import annotations

import threading
import time
from typing import Iterator

from dronecal_field.errors import VideoError
from dronecal_field.runfile.records import Frame
from dronecal_field.video.source import VideoSource


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
