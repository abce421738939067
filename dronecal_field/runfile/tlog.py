"""TlogWriter: the standard MAVLink telemetry log (.tlog) beside the run file.

Format (as QGroundControl, MAVProxy and pymavlink write it): each record is an
8-byte big-endian timestamp in microseconds since the Unix epoch followed by
one raw MAVLink frame, as sent or received. pymavlink's
``mavutil.mavlink_connection("x.tlog")`` reads it back.
"""

from __future__ import annotations

import os
import struct
import threading
import time
from pathlib import Path

from dronecal_field.errors import InputError


class TlogWriter:
    """Append MAVLink frames to a .tlog, flushed at least once a second.

    Parameters
    ----------
    path : output file (overwritten).
    flush_interval_s : flush to the OS at most this long after a write, seconds;
        a process killed with SIGKILL loses at most this much telemetry.

    Thread-safe: the link's receive thread and its send callback may both
    write. A background thread flushes records left in the buffer when
    traffic pauses.
    """

    def __init__(self, path: str | os.PathLike, flush_interval_s: float = 1.0) -> None:
        self.path = Path(path)
        self.flush_interval_s = float(flush_interval_s)
        self.records_written = 0
        self._lock = threading.Lock()
        self.failure: str | None = None  # the first write that failed (a full disk); the file keeps whole records only
        self.flushes_lost = 0
        self._buffer = bytearray()
        self._good_end = 0
        try:
            self._file = open(self.path, "wb", buffering=0)
        except OSError as exc:
            raise InputError(f"cannot create tlog {self.path}: {exc.strerror}; check the directory") from exc
        self._last_flush = time.monotonic()
        self._dirty = False
        # A pause in traffic must not leave the last records in the buffer.
        self._stop = threading.Event()
        self._flusher = threading.Thread(target=self._flush_loop, name="tlog-flush", daemon=True)
        self._flusher.start()

    def __enter__(self) -> "TlogWriter":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def write(self, msg_bytes: bytes, timestamp_us: int | None = None) -> None:
        """Append one MAVLink frame.

        Parameters
        ----------
        msg_bytes : the raw frame (pymavlink ``msg.get_msgbuf()``), v1 or v2.
        timestamp_us : record time, microseconds since the Unix epoch (host
            clock); now when None.
        """
        if timestamp_us is None:
            timestamp_us = time.time_ns() // 1000
        record = struct.pack(">Q", int(timestamp_us)) + bytes(msg_bytes)
        with self._lock:
            if self._file.closed:
                raise InputError(f"tlog {self.path} is closed; open a new TlogWriter to write more")
            self._buffer += record
            self.records_written += 1
            self._dirty = True
            now = time.monotonic()
            if now - self._last_flush >= self.flush_interval_s:
                self._flush_locked()

    def flush(self) -> None:
        """Flush buffered records to the OS."""
        with self._lock:
            if not self._file.closed:
                self._flush_locked()

    def close(self) -> None:
        """Flush, fsync and close (idempotent)."""
        self._stop.set()
        if self._flusher.is_alive() and self._flusher is not threading.current_thread():
            self._flusher.join()
        with self._lock:
            if self._file.closed:
                return
            self._flush_locked()
            try:
                os.fsync(self._file.fileno())
            except OSError:
                pass  # the flush reached the OS; fsync is best effort
            self._file.close()

    def _flush_locked(self) -> None:
        """Write the buffered records whole; a full disk cuts the file back to its last whole record and stops it."""
        self._dirty = False
        self._last_flush = time.monotonic()
        if not self._buffer:
            return
        view = memoryview(bytes(self._buffer))
        self._buffer.clear()
        try:
            while view:
                n = self._file.write(view)
                if not n:
                    raise OSError(28, os.strerror(28))
                view = view[n:]
            self._good_end = self._file.tell()
        except OSError as exc:
            # A full disk: the records that did not fit are lost (counted), the file stays whole records,
            # and the next flush tries again (space freed elsewhere keeps the telemetry going).
            self.flushes_lost += 1
            self.failure = self.failure or f"{exc.strerror or exc} at byte {self._good_end} of {self.path}"
            try:
                os.ftruncate(self._file.fileno(), self._good_end)
                self._file.seek(self._good_end)
            except OSError:
                pass

    def _flush_loop(self) -> None:
        while not self._stop.wait(self.flush_interval_s / 2.0):
            with self._lock:
                if self._file.closed:
                    return
                if self._dirty and time.monotonic() - self._last_flush >= self.flush_interval_s:
                    self._flush_locked()
