"""A cheap "is the marker in view" probe for the live status line (not the calibration detector).

For an H.264/H.265 stream the recorder hands it keyframes only, each decoded
on its own by a fresh decoder, on the recorder's monitor thread: never the
whole stream. :meth:`MarkerCheck.probe` keeps the probe within a CPU budget
(``cpu_budget``, a fraction of one core, over every camera it serves): a
frame probed before is not decoded again, and after each probe the next waits
at least ``min_period_s`` or the probe's own CPU time over the budget. A 4K
H.265 keyframe costs ~0.07 s of CPU to decode and detect
(benchmarks/bench_recorder_rtsp.py, 2026-11-27: 7 probes, 0.52 s): the recorder
of one 4K25 H.265 stream measured 15.8 % of a core probing every second, 12.0 %
within the budget (one probe every ~2.5 s).
"""

from __future__ import annotations

import time
from typing import Any


class MarkerCheck:
    """Detect one ArUco marker in a JPEG, on a copy scaled down to ``max_width`` pixels.

    Parameters
    ----------
    dictionary : str
        OpenCV dictionary name, e.g. ``DICT_4X4_50``.
    marker_id : int or None
        Only this id counts; ``None`` = any.
    max_width : int
        Frames wider than this are scaled down first (speed over reach).
    """

    def __init__(self, dictionary: str, marker_id: int | None = None, max_width: int = 960,
                 cpu_budget: float = 0.03, min_period_s: float = 1.0) -> None:
        import cv2

        from dronecal_field.errors import InputError

        if not hasattr(cv2.aruco, dictionary):
            raise InputError(f"marker dictionary {dictionary!r} unknown to OpenCV; use e.g. DICT_4X4_50")
        self._cv2 = cv2
        self.marker_id = marker_id
        self.max_width = max_width
        self._detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), cv2.aruco.DetectorParameters())
        self.cpu_budget = float(cpu_budget)
        self.min_period_s = float(min_period_s)
        self.next_due = 0.0  # monotonic s
        self.probes = 0
        self.cpu_s = 0.0  # CPU time spent probing (the calling thread's)
        self._seen: dict[int, tuple[Any, bool]] = {}  # caller's key -> (frame probed last, its result)

    def due(self, now: float) -> bool:
        """True when the budget allows the next probe at monotonic ``now``."""
        return now >= self.next_due

    def probe(self, frame: Any, key: int = 0, now: float | None = None, image: Any = None) -> bool | None:
        """The marker in ``frame`` (a Frame), or None when not due yet; the frame probed last for ``key`` (one per
        camera) is answered from memory, without decoding it again. ``image``: ``frame``'s (H, W) uint8 picture
        decoded already (an RTSP source's keyframe check), so only the detector runs."""
        now = time.monotonic() if now is None else now
        last = self._seen.get(key)
        if last is not None and last[0] is frame:
            return last[1]
        if not self.due(now):
            return None
        t0 = time.thread_time()
        try:
            result = self.seen(frame.data, frame.format) if image is None else self.seen_in(image)
        finally:
            cost = time.thread_time() - t0
            self.cpu_s += cost
            self.probes += 1
            self.next_due = now + max(self.min_period_s, cost / max(self.cpu_budget, 1e-6))
        self._seen[key] = (frame, result)
        return result

    def seen(self, data: bytes, format: str = "jpeg") -> bool:
        """True if the marker is found in this frame (False for undecodable data).

        ``format`` ``jpeg``/``png``, or ``h264``/``h265`` for a keyframe access
        unit with its parameter sets (Annex B), decoded on its own.
        """
        import numpy as np

        cv2 = self._cv2
        if format in ("h264", "h265"):
            from dronecal_field.video.decode import decode_keyframe_gray

            image = decode_keyframe_gray(data, format)
        else:
            image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_GRAYSCALE)
        return self.seen_in(image)

    def seen_in(self, image: Any) -> bool:
        """True if the marker is found in a decoded (H, W) uint8 ``image`` (False for None)."""
        cv2 = self._cv2
        if image is None:
            return False
        if image.shape[1] > self.max_width:
            scale = self.max_width / image.shape[1]
            image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        _corners, ids, _rejected = self._detector.detectMarkers(image)
        if ids is None:
            return False
        return self.marker_id is None or int(self.marker_id) in ids.ravel().tolist()
