"""Stages 3-4 of one camera of a run: one pass over its frames of the hover windows and legs (the marker's
detections, the live pass's outcomes taken where it covered them), and the camera-GNSS time offset from the
marker's motion.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecal_field.errors import ContractError
from dronecal_field.pipeline.align import TimeOffset, estimate_time_offset
from dronecal_field.pipeline.detect import Detection
from dronecal_field.pipeline.hover import HoverWindow
from dronecal_field.pipeline.legs import Leg
from dronecal_field.pipeline.results import CalibrateOptions, Detections, FrameStats, Track
from dronecal_field.pipeline.sampling import SamplingOptions


def _one_image(run, t_ns: int):
    """(H, W) grey image of the frame stamped ``t_ns`` (an access unit decoded from its keyframe), or None."""
    from dronecal_field.pipeline.detect import FrameDecoder, decode_gray

    if not run.video:
        return next((decode_gray(f.data) for f in run.iter_frames([(t_ns, t_ns)])), None)
    decoder = FrameDecoder()
    for frame in run.iter_frames([(t_ns, t_ns)]):
        decoder.push(frame)
    return decoder.gray()


def detect_frames(run, windows: list[HoverWindow], legs: list[Leg], md, sampling: SamplingOptions, live=None) -> Detections:
    """Stage 3: one pass over the frames of the windows and the legs: the marker's detections.

    ``live`` (framecache.FrameResults, the live pass of ``fly``): inside its covered intervals its
    frames are the candidates and their stored outcomes are taken (no read, no decode); the rest
    is read from the file. The selector decides on the merged stream, in time order, as without.
    """
    import heapq

    from dronecal_field.pipeline.detect import TRACK_NS, FrameDecoder, decode_gray, detect_marker, make_aruco_detector, predicted, roi_around
    from dronecal_field.pipeline.sampling import FrameSelector

    marker = md.marker
    selector = FrameSelector(windows, sampling, legs=[(g.start_ns, g.end_ns) for g in legs], video=run.video)
    detector = None
    if marker.kind == "aruco":
        try:
            detector = make_aruco_detector(marker.dictionary)
        except ValueError:
            raise ContractError(
                f"marker.dictionary {marker.dictionary!r} is not an OpenCV ArUco dictionary: use a name like DICT_4X4_50"
            ) from None
    detections: list[Detection] = []
    groups: list[int] = []
    read = decoded = corrupt = found = from_live = 0
    others: set[int] = set()
    formats: set[str] = set()
    last: Detection | None = None
    before_last: Detection | None = None
    background = None  # one frame showing the marker, for the report's figure
    size_warned = False
    decoder = FrameDecoder()  # /camera/video: access units kept from the keyframe on, decoded only up to a wanted frame
    # /camera/video holds are decoded in keyframe bursts seconds apart: the last detection still boxes the search.
    track_ns = int(max(0.5, sampling.video_max_period_s) * 1e9) if run.video else TRACK_NS
    wanted = selector.read_windows()
    if live is not None:
        cached = (_CachedFrame(t, res) for t, res in live.items_in(wanted))
        frames = heapq.merge(cached, run.iter_frames(live.uncovered(wanted)), key=lambda f: f.timestamp_ns)
    else:
        frames = run.iter_frames(wanted)
    for frame in frames:
        read += 1
        stored = isinstance(frame, _CachedFrame)
        if not stored:
            decoder.push(frame)
            if live is not None and live.covered_at(frame.timestamp_ns):
                continue  # a keyframe run-up unit inside a covered span: the cache's own frame was chosen or not (never twice)
        # Decisions use what was detected so far (a transition is decoded once its hold showed the marker).
        decode, group = selector.wants(frame.timestamp_ns, keyframe=bool(getattr(frame, "keyframe", False)))
        if not decode:
            continue
        decoded += 1
        if not stored and live is not None:
            stored, res = live.lookup(frame.timestamp_ns)  # a frame the live pass detected outside its covered spans
            frame = _CachedFrame(frame.timestamp_ns, res) if stored else frame
        if stored:
            from_live += 1
            formats.update(live.formats)
            res = frame.result
            if res is None:
                corrupt += 1
                continue
        else:
            formats.add(frame.format)
            image = decoder.gray()
            if image is None:
                corrupt += 1
                continue
            if image.shape[:2] != (md.height, md.width) and not size_warned:
                size_warned = True
            roi = None
            if last is not None and abs(frame.timestamp_ns - last.timestamp_ns) < TRACK_NS:
                roi = roi_around(predicted(last, before_last, frame.timestamp_ns), image.shape)
            elif last is not None and abs(frame.timestamp_ns - last.timestamp_ns) < track_ns:
                roi = roi_around(last, image.shape)  # keyframe bursts seconds apart: a still hold's marker is where it was
            res = detect_marker(image, marker, detector, frame.timestamp_ns, roi)
        others.update(res.other_ids)
        selector.record(group, res.detection is not None)
        if res.detection is not None:
            found += 1
            detections.append(res.detection)
            groups.append(int(group))
            before_last, last = last, res.detection
            if not stored:
                background = image
    if background is None and live is not None and detections:
        # every detection came from the live pass: the report's figure still needs one frame with the marker
        t = detections[-1].timestamp_ns
        background = _one_image(run, t)
    stats = FrameStats(
        frames_read=read,
        frames_decoded=decoded,
        frames_corrupt=corrupt,
        frames_with_marker=found,
        other_ids=tuple(sorted(others)),
        transitions_dense=len(selector.transitions_taken),
        formats=tuple(sorted(formats)),
        video_units_decoded=decoder.video_stats[0] if decoder.video_stats is not None else None,
        frames_from_live=from_live,
    )
    return Detections(
        items=detections,
        groups=groups,
        t_ns=np.array([d.timestamp_ns for d in detections], np.int64),
        uv_px=np.array([[d.u_px, d.v_px] for d in detections], float).reshape(-1, 2),
        size_px=np.array([d.size_px for d in detections], float),
        stats=stats,
        size_mismatch=size_warned,
        background=background,
    )


@dataclass(frozen=True)
class _CachedFrame:
    """A frame the live pass already ran the detector on (stamp and outcome; None: it did not decode)."""

    timestamp_ns: int
    result: object  # detect.FrameResult | None


def align_offset(dets: Detections, track: Track, md, options: CalibrateOptions) -> tuple[TimeOffset, list[str]]:
    """Stage 4: the camera-GNSS offset from the marker's motion (legs and transitions)."""
    warnings: list[str] = []
    offset = estimate_time_offset(
        dets.t_ns, dets.uv_px, track.t_ns, track.marker_enu_m, groups=np.asarray(dets.groups), max_offset_s=options.max_offset_s
    )
    if offset.method == "none":
        if md.camera_latency_s is not None:
            offset = TimeOffset(offset_s=float(md.camera_latency_s), std_s=None, method="declared", n_points=offset.n_points, n_moving=offset.n_moving)
            warnings.append("the time offset is not observable from the data (no marker motion seen): using camera.latency_s")
        else:
            warnings.append("the time offset is not observable from the data (no marker motion seen) and camera.latency_s is unknown: assuming 0")
    elif offset.std_s is None:
        warnings.append(f"the time offset {offset.offset_s:+.3f} s is at the edge of the search range or unbounded: check camera.latency_s")
    return offset, warnings
