"""A cheap "is the marker in view" probe for the live status line (not the calibration detector)."""

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

    def seen(self, jpeg: bytes) -> bool:
        """True if the marker is found in this JPEG (False for undecodable data)."""
        import numpy as np

        cv2 = self._cv2
        image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
        if image is None:
            return False
        if image.shape[1] > self.max_width:
            scale = self.max_width / image.shape[1]
            image = cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        _corners, ids, _rejected = self._detector.detectMarkers(image)
        if ids is None:
            return False
        return self.marker_id is None or int(self.marker_id) in ids.ravel().tolist()
