"""The capture shell every video source shares: one capture thread, a bounded queue, ``read``, ``reopen``.

Each source stamps every frame the moment it arrives (or by the stream's own
clock: :mod:`dronecal_field.video.packets`) and hands it over through a
bounded queue: a live source drops the oldest frame when the consumer falls
behind (counted in ``frames_dropped``); a file source blocks instead.
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Iterator

from dronecal_field.runfile.records import Frame


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
