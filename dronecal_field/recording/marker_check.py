"""A cheap "is the marker in view" probe for the live status line (not the calibration detector).

For an H.264/H.265 stream the recorder hands it keyframes only, each decoded
on its own by a fresh decoder, about once a second on the recorder's monitor
thread: never the whole stream.
"""

from __future__ import annotations


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

    def __init__(self, dictionary: str, marker_id: int | None = None, max_width: int = 960) -> None:
        import cv2

        from dronecal_field.errors import InputError

        if not hasattr(cv2.aruco, dictionary):
            raise InputError(f"marker dictionary {dictionary!r} unknown to OpenCV; use e.g. DICT_4X4_50")
        self._cv2 = cv2
        self.marker_id = marker_id
        self.max_width = max_width
        self._detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), cv2.aruco.DetectorParameters())

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
        if image is None:
            return False
        if image.shape[1] > self.max_width:
            scale = self.max_width / image.shape[1]
            image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        _corners, ids, _rejected = self._detector.detectMarkers(image)
        if ids is None:
            return False
        return self.marker_id is None or int(self.marker_id) in ids.ravel().tolist()
