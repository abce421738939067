"""Marker detection on decoded frames: ArUco (sub-pixel corners) and LED blobs.

Pure functions on images (numpy arrays); decoding bytes is the one I/O-ish
helper here (``decode_gray``), kept so that a corrupt frame is a ``None`` the
caller counts, never an exception that stops a run.

The marker centre of an ArUco detection is the intersection of the diagonals
of its four refined corners: under a perspective projection that is exactly
the image of the square's centre (a homography maps the diagonals' crossing
to the crossing), which the mean of the corners is not. Lens distortion
bends the diagonals, so once a calibration has estimated it the crossing is
taken again in the undistorted image (:func:`centres_under_distortion`):
measured on a k1 = -0.2 camera, markers of 60-100 px near the image edge
moved 0.1-0.3 px inwards with the plain crossing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ARUCO_DICTIONARIES: tuple[str, ...] = (
    "DICT_4X4_50", "DICT_4X4_100", "DICT_4X4_250", "DICT_4X4_1000",
    "DICT_5X5_50", "DICT_5X5_100", "DICT_5X5_250", "DICT_5X5_1000",
    "DICT_6X6_50", "DICT_6X6_100", "DICT_6X6_250", "DICT_6X6_1000",
    "DICT_7X7_50", "DICT_7X7_100", "DICT_7X7_250", "DICT_7X7_1000",
    "DICT_ARUCO_ORIGINAL", "DICT_ARUCO_MIP_36h12",
    "DICT_APRILTAG_16h5", "DICT_APRILTAG_25h9", "DICT_APRILTAG_36h10", "DICT_APRILTAG_36h11",
)


@dataclass(frozen=True, eq=False)
class Detection:
    """One marker seen in one frame.

    ``timestamp_ns`` is the frame's stamp on the run clock as recorded (the
    camera clock, before the time offset is applied). ``corners_px`` is (4, 2)
    for ArUco (OpenCV's corner order) and None for an LED blob; ``size_px`` is
    the mean side length (ArUco) or the blob's equivalent diameter (LED).
    """

    timestamp_ns: int
    u_px: float
    v_px: float
    size_px: float
    kind: str
    corners_px: np.ndarray | None = None

    @property
    def uv_px(self) -> np.ndarray:
        """(2,) the marker centre in pixels."""
        return np.array([self.u_px, self.v_px])


@dataclass(frozen=True)
class FrameResult:
    """What one frame gave: the wanted marker (or None) and any other ArUco ids seen."""

    detection: Detection | None
    other_ids: tuple[int, ...] = ()


def decode_gray(data: bytes) -> np.ndarray | None:
    """Decode a JPEG or PNG frame to an (H, W) uint8 grey image; None if the bytes are corrupt.

    A truncated JPEG that libjpeg can still partly decode is rejected too: a
    frame with a grey lower half would give wrong detections, not missing ones.
    """
    import cv2

    if not data:
        return None
    buf = np.frombuffer(data, dtype=np.uint8)
    # JPEG must end with EOI (FF D9); libjpeg silently pads a cut-off stream.
    if data[:2] == b"\xff\xd8" and data.rstrip(b"\x00")[-2:] != b"\xff\xd9":
        return None
    try:
        image = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
    except cv2.error:
        return None
    if image is None or image.size == 0:
        return None
    return image


class FrameDecoder:
    """Grey images of a run's frames, JPEG/PNG or H.264/H.265 access units alike.

    Push every frame the reader returns, in order; ask :meth:`gray` only for
    the frames to detect in. Images decode on their own; an access unit needs
    the ones since its keyframe, which are kept (not decoded) until a picture
    is asked for (dronecal_field.video.decode.VideoFrameDecoder), so frames no
    one asks for after the last wanted one of a GOP cost nothing.
    """

    def __init__(self) -> None:
        self._video = None
        self._last = None

    def push(self, frame) -> None:
        """The next frame of the stream (``Frame``)."""
        if frame.format in ("h264", "h265"):
            if self._video is None or self._video.format != frame.format:
                from dronecal_field.video.decode import VideoFrameDecoder

                self._video = VideoFrameDecoder(frame.format)
            self._video.push(frame)
        self._last = frame

    def gray(self) -> np.ndarray | None:
        """(H, W) uint8 grey image of the frame pushed last; None when corrupt or undecodable."""
        if self._last is None:
            return None
        if self._last.format in ("h264", "h265"):
            return self._video.gray()
        return decode_gray(self._last.data)

    @property
    def video_stats(self) -> tuple[int, int] | None:
        """(access units decoded, access units never decoded) of a video run; None for images."""
        return None if self._video is None else (self._video.decoded, self._video.skipped)


def diagonal_intersection(corners_px: np.ndarray) -> np.ndarray:
    """(2,) crossing of the diagonals 0-2 and 1-3 of a quadrilateral ``corners_px`` (4, 2) pixels.

    Falls back to the corners' mean for a degenerate (parallel-diagonal) quad.
    """
    return _diagonal_crossings(np.asarray(corners_px, float).reshape(1, 4, 2))[0]


def _diagonal_crossings(quads: np.ndarray) -> np.ndarray:
    """(M, 2) crossings of the diagonals 0-2 and 1-3 of quadrilaterals (M, 4, 2); the corners' mean where they are parallel."""
    q = np.concatenate([quads, np.ones(quads.shape[:2] + (1,))], -1)  # homogeneous corners
    # Homogeneous lines through opposite corners; their cross product is the crossing.
    x = np.cross(np.cross(q[:, 0], q[:, 2]), np.cross(q[:, 1], q[:, 3]))
    flat = np.abs(x[:, 2]) < 1e-12
    out = quads.mean(axis=1)
    out[~flat] = x[~flat, :2] / x[~flat, 2:]
    return out


def centres_under_distortion(corners_px: np.ndarray, intrinsics: np.ndarray, distortion: np.ndarray) -> np.ndarray:
    """(M, 2) marker centres from corners (M, 4, 2): the diagonals' crossing in the undistorted image, distorted back.

    ``intrinsics`` (4,) fx, fy, cx, cy and ``distortion`` (5,) k1, k2, p1,
    p2, k3 of a calibration of this camera.
    """
    from dronecal_field.core.camera import _distort, undistort_normalised

    c = np.asarray(corners_px, float).reshape(-1, 4, 2)
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    dist = np.asarray(distortion, float).reshape(1, 5)
    x, y = undistort_normalised(((c[..., 0] - cx) / fx).reshape(1, -1), ((c[..., 1] - cy) / fy).reshape(1, -1), dist)
    m = _diagonal_crossings(np.stack([x.reshape(-1, 4), y.reshape(-1, 4)], -1))
    xd, yd, _, _ = _distort(m[:, 0][None], m[:, 1][None], dist)
    return np.c_[fx * xd[0] + cx, fy * yd[0] + cy]


def make_aruco_detector(dictionary: str):
    """A ``cv2.aruco.ArucoDetector`` tuned for small, distant markers with sub-pixel corners.

    Parameters
    ----------
    dictionary : str
        OpenCV's dictionary name, e.g. ``"DICT_4X4_50"``.

    Raises
    ------
    ValueError
        For a name OpenCV does not know (the caller turns it into a ContractError).
    """
    import cv2

    if dictionary not in ARUCO_DICTIONARIES or not hasattr(cv2.aruco, dictionary):
        raise ValueError(f"unknown ArUco dictionary {dictionary!r}")
    params = cv2.aruco.DetectorParameters()
    # A marker 15 m away is ~10-20 px wide: accept perimeters down to ~1% of the
    # image's larger side (the default 3% throws those away).
    params.minMarkerPerimeterRate = 0.01
    params.polygonalApproxAccuracyRate = 0.05
    params.minCornerDistanceRate = 0.05
    params.minDistanceToBorder = 2
    # Threshold windows 3, 13, 23, 33 px: one more than OpenCV's default for
    # near markers whose cells are larger than 23 px (each window costs a pass).
    params.adaptiveThreshWinSizeMin = 3
    params.adaptiveThreshWinSizeMax = 33
    params.adaptiveThreshWinSizeStep = 10
    # Sample each bit cell with more pixels and a smaller ignored margin: at
    # small scales a cell is only 2-3 image pixels.
    params.perspectiveRemovePixelPerCell = 8
    params.perspectiveRemoveIgnoredMarginPerCell = 0.2
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    params.cornerRefinementWinSize = 3
    # Half a bit cell: measured best on rendered 18-38 px markers (0.09 px RMS centre error
    # against 0.19 px at OpenCV's 0.3).
    params.relativeCornerRefinmentWinSize = 0.5
    params.cornerRefinementMaxIterations = 50
    params.cornerRefinementMinAccuracy = 0.01
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params)


def detect_aruco(
    image: np.ndarray,
    detector,
    marker_id: int,
    timestamp_ns: int,
    roi: tuple[int, int, int, int] | None = None,
) -> FrameResult:
    """Find marker ``marker_id`` in a grey ``image`` (H, W) uint8.

    Parameters
    ----------
    image : (H, W) uint8
    detector : cv2.aruco.ArucoDetector
        From :func:`make_aruco_detector`.
    marker_id : int
        The id to keep; other ids are reported in ``FrameResult.other_ids``.
    timestamp_ns : int
        Copied into the detection.
    roi : (x0, y0, x1, y1) pixels, optional
        Search only this rectangle (tracking a marker found nearby in time);
        coordinates in the result are always full-image pixels.
    """
    x0, y0 = 0, 0
    sub = image
    if roi is not None:
        x0, y0, x1, y1 = _clip_roi(roi, image.shape)
        sub = image[y0:y1, x0:x1]
        if sub.size == 0:
            return FrameResult(detection=None)
    corners, ids, _ = detector.detectMarkers(sub)
    if ids is None or len(ids) == 0:
        return FrameResult(detection=None)
    ids = [int(i) for i in np.asarray(ids).ravel()]
    wanted = [k for k, i in enumerate(ids) if i == marker_id]
    others = tuple(sorted({i for i in ids if i != marker_id}))
    if not wanted:
        return FrameResult(detection=None, other_ids=others)
    # Two copies of our id in one frame is a reflection or a second marker:
    # keep the largest, which is the nearer and better-measured one.
    quads = [np.asarray(corners[k], float).reshape(4, 2) + (x0, y0) for k in wanted]
    sizes = [_mean_side(q) for q in quads]
    best = int(np.argmax(sizes))
    quad = quads[best]
    centre = diagonal_intersection(quad)
    return FrameResult(
        detection=Detection(
            timestamp_ns=int(timestamp_ns),
            u_px=float(centre[0]),
            v_px=float(centre[1]),
            size_px=float(sizes[best]),
            kind="aruco",
            corners_px=quad,
        ),
        other_ids=others,
    )


def detect_led(
    image: np.ndarray,
    timestamp_ns: int,
    roi: tuple[int, int, int, int] | None = None,
    min_peak: int = 160,
    min_contrast: float = 60.0,
    max_area_px: int = 2500,
) -> FrameResult:
    """Find the brightest compact blob (an LED marker) in a grey ``image`` (H, W) uint8.

    The centre is the intensity-weighted centroid of the blob above a
    threshold halfway between the local background and the peak, which is
    sub-pixel and insensitive to a saturated core.

    Parameters
    ----------
    min_peak : int
        Grey level the LED must reach (0-255).
    min_contrast : float
        Peak minus the image median it must exceed: a bright sky is not an LED.
    max_area_px : int
        Larger bright regions (windows, sky) are not the LED.
    """
    import cv2

    x0, y0 = 0, 0
    sub = image
    if roi is not None:
        x0, y0, x1, y1 = _clip_roi(roi, image.shape)
        sub = image[y0:y1, x0:x1]
        if sub.size == 0:
            return FrameResult(detection=None)
    blurred = cv2.GaussianBlur(sub, (3, 3), 0)
    # A distant LED is a pixel or two: test the raw peak (it saturates), but
    # segment on the blurred image so single hot pixels do not form blobs.
    peak = float(sub.max())
    background = float(np.median(blurred))
    if peak < min_peak or peak - background < min_contrast:
        return FrameResult(detection=None)
    threshold = 0.5 * (float(blurred.max()) + background)
    mask = (blurred > threshold).astype(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    best_label, best_score = -1, -np.inf
    for label in range(1, n):
        area = int(stats[label, cv2.CC_STAT_AREA])
        if area > max_area_px:
            continue
        x, y, w, h = (int(stats[label, k]) for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
        # Compact: an LED is round, a lit edge or wire is long and thin.
        if max(w, h) > 4 * max(1, min(w, h)) and area > 4:
            continue
        patch = blurred[y : y + h, x : x + w].astype(float)
        inside = labels[y : y + h, x : x + w] == label
        score = float(patch[inside].sum())
        if score > best_score:
            best_label, best_score = label, score
    if best_label < 0:
        return FrameResult(detection=None)
    x, y, w, h = (int(stats[best_label, k]) for k in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP, cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
    # Weighted centroid over the blob grown by one pixel, weights above background.
    xa, ya = max(0, x - 1), max(0, y - 1)
    xb, yb = min(sub.shape[1], x + w + 1), min(sub.shape[0], y + h + 1)
    weights = np.clip(sub[ya:yb, xa:xb].astype(float) - threshold, 0.0, None)
    if weights.sum() <= 0:
        weights = (labels[ya:yb, xa:xb] == best_label).astype(float)
    ys, xs = np.mgrid[ya:yb, xa:xb]
    u = float((weights * xs).sum() / weights.sum())
    v = float((weights * ys).sum() / weights.sum())
    area = float(stats[best_label, cv2.CC_STAT_AREA])
    return FrameResult(
        detection=Detection(
            timestamp_ns=int(timestamp_ns),
            u_px=u + x0,
            v_px=v + y0,
            size_px=float(2.0 * np.sqrt(area / np.pi)),
            kind="led",
        )
    )


def roi_around(detection: Detection, shape: tuple[int, ...], margin_sizes: float = 2.5, min_half_px: int = 40) -> tuple[int, int, int, int]:
    """Search rectangle (x0, y0, x1, y1) around a previous detection, for tracking."""
    half = int(max(min_half_px, margin_sizes * detection.size_px))
    return _clip_roi(
        (int(detection.u_px) - half, int(detection.v_px) - half, int(detection.u_px) + half + 1, int(detection.v_px) + half + 1),
        shape,
    )


def _clip_roi(roi: tuple[int, int, int, int], shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    x0, y0, x1, y1 = roi
    h, w = shape[:2]
    return max(0, x0), max(0, y0), min(w, x1), min(h, y1)


def _mean_side(quad: np.ndarray) -> float:
    return float(np.mean(np.linalg.norm(quad - np.roll(quad, -1, axis=0), axis=1)))


COARSE_SEARCH_PX = 4_000_000  # frames this large (4K) are searched at half size first
TRACK_NS = 500_000_000  # a detection this recent predicts where to search the next frame


def coarse_roi(image: np.ndarray, detector, marker_id: int) -> tuple[int, int, int, int] | None:
    """A search box (full-size pixels) around the marker found in the half-size ``image`` (H, W), or None."""
    import cv2
    from dataclasses import replace

    half = cv2.resize(image, (image.shape[1] // 2, image.shape[0] // 2), interpolation=cv2.INTER_AREA)
    found = detect_aruco(half, detector, marker_id, 0, None).detection
    if found is None:
        return None
    return roi_around(replace(found, u_px=2.0 * found.u_px + 0.5, v_px=2.0 * found.v_px + 0.5, size_px=2.0 * found.size_px), image.shape)


def predicted(last: Detection, before: Detection | None, t_ns: int) -> Detection:
    """Where the marker will be at ``t_ns``: ``last`` moved on at the image velocity of the last two
    detections (a marker crossing the image on a leg leaves a box centred where it was)."""
    from dataclasses import replace

    if before is None or not 0 < last.timestamp_ns - before.timestamp_ns < TRACK_NS:
        return last
    k = (t_ns - last.timestamp_ns) / (last.timestamp_ns - before.timestamp_ns)
    return replace(last, u_px=last.u_px + k * (last.u_px - before.u_px), v_px=last.v_px + k * (last.v_px - before.v_px))


def detect_marker(image: np.ndarray, marker, detector, timestamp_ns: int, roi: tuple[int, int, int, int] | None = None) -> FrameResult:
    """The run's marker in a grey ``image`` (H, W): ``calibrate``'s search, which the live pass shares.

    In the tracking box ``roi`` first (full-size pixels), then the whole frame if it is lost there; a 4K
    frame with no box is searched at half size first (a whole 4K frame costs ~0.7 s of ArUco, at half
    size a quarter), then in the box found there at full size.

    Parameters
    ----------
    marker : runfile.records.MarkerSpec (``kind``, ``marker_id``)
    detector : from :func:`make_aruco_detector` (None for an LED marker)
    """
    coarse = marker.kind == "aruco" and image.size >= COARSE_SEARCH_PX
    while True:
        if roi is None and coarse:
            coarse = False
            roi = coarse_roi(image, detector, int(marker.marker_id))
        if marker.kind == "aruco":
            res = detect_aruco(image, detector, int(marker.marker_id), timestamp_ns, roi)
        else:
            res = detect_led(image, timestamp_ns, roi)
        if res.detection is not None or (roi is None and not coarse):
            return res
        roi = None  # lost in the tracking box: search the whole frame
