"""The live calibration around the recorder: an observer that only queues, and one worker thread.

::

    recorder video thread  --on_frame-->  frame ring (a few frames a second, bounded by count)
    recorder writer thread --on_record--> fixes, attitudes (bounded deques); hover / leg events -> job queue (bounded)
    worker thread (nice +10): each job: frames of the hold -> detector -> point -> running calibration
                              -> coverage, summary, verdict; and twice a second the Foxglove view

The observer's calls are O(1) appends and a ``put_nowait``: the recorder never
waits for the live work. When the worker falls behind, the job queue fills
and further waypoints are skipped (counted in ``jobs_dropped`` and named as
"not checked live"); frames the ring no longer holds are simply not used.
The recorder's own frame queue, its drops and its priority are untouched.
"""

from __future__ import annotations

import collections
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from dronecal_field.live.progress import (
    COMPRESSED,
    FixTrack,
    LiveEstimate,
    LiveOptions,
    Verdict,
    WaypointOutcome,
    constrained,
    coverage,
    detect_in_frames,
    expected_seqs,
    fix_track,
    guessed_camera,
    hold_outcome,
    image_roi,
    leg_outcome,
    pick_frames,
    solve,
    summary_line,
    verdict,
)
from dronecal_field.mavlink.missionfile import CMD_NAV_WAYPOINT
from dronecal_field.runfile.records import Attitude, GnssFix, RunEvent

RING_HZ = 16.0  # JPEG frames a second kept for the worker: all of a 15 fps stream, every other of 30 fps
RING_FRAMES = 4000  # and at most this many (H.264/H.265: every access unit, a decodable chain; ~2 min at 30 fps) ...
RING_BYTES = 96 << 20  # ... or this many bytes of JPEG (1080p30: the last ~20 s, longer than a hold)
GRACE_S = 0.3  # wait this long after a hold's end for its last frames to arrive


@dataclass(frozen=True, eq=False)
class LiveResult:
    """Everything the live pipeline concluded (``live.json`` beside the run holds it)."""

    outcomes: list[WaypointOutcome]
    expected: list[int]
    estimate: LiveEstimate | None
    history: list[dict]
    verdict: Verdict
    coverage: float | None
    offset: Any | None  # align.TimeOffset
    jobs_dropped: int
    unchecked: list[int]
    cpu_s: float
    wall_s: float
    summaries: list[str] = field(default_factory=list)
    constrained: bool = False  # the estimate passed progress.constrained (focal to 2 %, camera where the plan put it)

    def to_dict(self) -> dict:
        return {
            "verdict": {"good": self.verdict.good, "text": self.verdict.text, "refly_seqs": list(self.verdict.refly_seqs)},
            "waypoints": [
                {"seq": o.seq, "kind": o.kind, "frames_decoded": o.frames, "detections": len(o.detections), "good": o.good,
                 "problem": o.problem, "uv_px": None if o.point is None or o.point.uv_px is None else np.asarray(o.point.uv_px).tolist(),
                 "marker_enu_m": None if o.point is None or o.point.marker_enu_m is None else np.asarray(o.point.marker_enu_m).tolist()}
                for o in self.outcomes
            ],
            "expected_seqs": self.expected,
            "estimate": None if self.estimate is None else self.estimate.to_dict(),
            "estimate_constrained": self.constrained,
            "history": self.history,
            "coverage": self.coverage,
            "camera_offset": None if self.offset is None else self.offset.to_dict(),
            "jobs_dropped": self.jobs_dropped,
            "unchecked_seqs": self.unchecked,
            "worker_cpu_s": self.cpu_s,
            "wall_s": self.wall_s,
        }


class LiveCalibration:
    """The recorder's observer (``on_frame``, ``on_record``) and the worker thread behind it.

    Parameters
    ----------
    mission : mavlink.missionfile.Mission flown.
    marker : runfile.records.MarkerSpec of the run.
    width, height : image size, px.
    plan : plan.json (the ROI for coverage, the grid's seqs), or None.
    origin : geodesy.EnuOrigin of the live ENU frame (plan's site origin); None: the first fix.
    options : LiveOptions.
    view : live.view.LiveView or None (no Foxglove).
    camera_latency_s : the stream's declared latency (the camera offset until one is estimated).
    job_queue : waypoints waiting for the worker before further ones are skipped.
    """

    def __init__(
        self, mission: Any, marker: Any, width: int, height: int, plan: dict | None = None, origin: Any = None,
        options: LiveOptions = LiveOptions(), view: Any = None, camera_latency_s: float | None = None, job_queue: int = 8,
    ) -> None:
        self.mission = mission
        self.marker = marker
        self.width, self.height = int(width), int(height)
        self.plan = plan
        self.origin = origin
        self.options = options
        self.view = view
        self.camera_offset_ns = int(round((camera_latency_s or 0.0) * 1e9))
        self.expected = expected_seqs(mission, plan)
        # The plan's guess is in the plan's ENU frame: a start and a sanity check only when the live frame is that one.
        self.prior = guessed_camera(plan) if plan is not None and origin is not None else None
        self._frames: collections.deque = collections.deque()
        self._ring_bytes = 0
        self._last_kept_ns = 0
        self._latest_frame: Any = None
        self._fixes: collections.deque[GnssFix] = collections.deque(maxlen=200_000)
        self._attitudes: collections.deque[Attitude] = collections.deque(maxlen=200_000)
        self._jobs: queue.Queue = queue.Queue(maxsize=max(1, job_queue))
        self.jobs_dropped = 0
        self.unchecked: list[int] = []
        self.outcomes: list[WaypointOutcome] = []
        self.leg_detections: list = []
        self.estimate: LiveEstimate | None = None
        self.history: list[dict] = []
        self.coverage: float | None = None
        self.offset: Any = None
        self.summaries: list[str] = []  # printed by fly as they come
        self._printed = 0
        self._roi: Any = None
        self._detector: Any = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._cpu_s = 0.0
        self._started = time.monotonic()
        self._lock = threading.Lock()  # outcomes/estimate read by the status line

    # ----- observer (recorder threads): O(1), never waits -----
    def on_frame(self, frame: Any) -> None:
        compressed = frame.format in COMPRESSED
        if not compressed:
            self._latest_frame = frame
        if compressed or frame.timestamp_ns - self._last_kept_ns >= int(1e9 / RING_HZ):
            self._last_kept_ns = frame.timestamp_ns
            self._frames.append(frame)
            self._ring_bytes += len(frame.data)
            while len(self._frames) > RING_FRAMES or self._ring_bytes > RING_BYTES:
                self._ring_bytes -= len(self._frames.popleft().data)

    def on_record(self, record: Any) -> None:
        if isinstance(record, GnssFix):
            self._fixes.append(record)
        elif isinstance(record, Attitude):
            self._attitudes.append(record)
        elif isinstance(record, RunEvent) and record.type in ("hover", "leg"):
            try:
                self._jobs.put_nowait((time.monotonic() + GRACE_S, record))
            except queue.Full:
                self.jobs_dropped += 1
                seq = record.metadata.get("seq") or record.metadata.get("seq_to")
                if seq is not None:
                    self.unchecked.append(int(seq))

    # ----- lifecycle -----
    def start(self) -> "LiveCalibration":
        self._thread = threading.Thread(target=self._run, name="live-calibration", daemon=True)
        self._thread.start()
        return self

    def finish(self, timeout_s: float = 30.0) -> LiveResult:
        """Work off the queued waypoints (up to ``timeout_s``), stop the worker, and conclude."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
        with self._lock:
            v = verdict(self.outcomes, [s for s in self.expected if s not in self.unchecked], self.estimate, self.coverage, self.prior)
            result = LiveResult(
                outcomes=list(self.outcomes), expected=list(self.expected), estimate=self.estimate, history=list(self.history),
                verdict=v, coverage=self.coverage, offset=self.offset, jobs_dropped=self.jobs_dropped,
                unchecked=sorted(set(self.unchecked)), cpu_s=self._cpu_s, wall_s=time.monotonic() - self._started,
                summaries=list(self.summaries), constrained=constrained(self.estimate, self.prior),
            )
        if self.view is not None:
            try:
                self.view.publish_status({"verdict": v.text, "good": v.good, "refly_seqs": list(v.refly_seqs)})
            except Exception:  # noqa: BLE001 - the view is cosmetic
                pass
        return result

    def new_summaries(self) -> list[str]:
        """Summary lines not handed out before (fly prints them between status lines)."""
        with self._lock:
            lines = self.summaries[self._printed :]
            self._printed = len(self.summaries)
        return lines

    def status_text(self) -> str:
        """A short part for fly's status line: ``live 7 ok 1 missed | 2.3 cm@15m``."""
        with self._lock:
            good = len({o.seq for o in self.outcomes if o.good})
            missed = len({o.seq for o in self.outcomes if not o.good} - {o.seq for o in self.outcomes if o.good})
            est = self.estimate
        text = f"live {good} ok {missed} missed"
        if constrained(est, self.prior):
            text += f" | {est.ground_error_15m_cm:.1f} cm@15m"
        if self.jobs_dropped:
            text += f" | {self.jobs_dropped} unchecked"
        return text

    # ----- worker thread -----
    def _run(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)  # below the recorder's threads
        except (AttributeError, OSError):
            pass
        t_cpu = time.thread_time()
        self._prepare()
        last_view = 0.0
        while True:
            try:
                ready, event = self._jobs.get(timeout=0.1)
            except queue.Empty:
                ready = event = None
            if event is not None:
                wait = ready - time.monotonic()
                if wait > 0 and not self._stop.is_set():
                    time.sleep(wait)
                try:
                    self._process(event)
                except Exception as exc:  # noqa: BLE001 - one bad waypoint must not end the live view
                    with self._lock:
                        self.summaries.append(f"live: waypoint skipped ({type(exc).__name__}: {exc})")
            now = time.monotonic()
            if self.view is not None and now - last_view >= 0.5:
                last_view = now
                try:
                    self._publish_view()
                except Exception:  # noqa: BLE001 - the view is cosmetic
                    pass
            self._cpu_s = time.thread_time() - t_cpu
            if self._stop.is_set() and self._jobs.empty():
                break
        self._cpu_s = time.thread_time() - t_cpu

    def _prepare(self) -> None:
        from dronecal_field.pipeline.detect import make_aruco_detector

        if self.marker.kind == "aruco":
            self._detector = make_aruco_detector(self.marker.dictionary)
        self._roi = image_roi(self.plan) if self.plan is not None else None
        if self.view is not None:
            self.view.set_plan(self.mission, self._roi)

    def _track(self) -> FixTrack:
        fixes = list(self._fixes)
        if self.origin is None and fixes:
            from dronecal_field.geodesy import EnuOrigin

            f = fixes[0]
            self.origin = EnuOrigin(lat_deg=f.lat_deg, lon_deg=f.lon_deg, h_m=f.alt_m)
        return fix_track(fixes, list(self._attitudes), self.origin, np.asarray(self.marker.offset_frd_m, float))

    def _process(self, event: RunEvent) -> None:
        from dronecal_field.pipeline.hover import HoverWindow

        start, end = int(event.timestamp_ns), int(event.timestamp_ns + event.duration_ns)
        frames = list(self._frames)
        track = self._track()
        if event.type == "hover":
            seq = int(event.metadata.get("seq", -1))
            po = self.options.points
            a, b = HoverWindow(0, start, end, "event", seq).stable(po.settle_s, po.tail_s)
            picked = pick_frames(frames, a + self.camera_offset_ns, b + self.camera_offset_ns, self.options.frames_per_hold)
            dets = detect_in_frames(picked, self.marker, self._detector, frames)
            size = self.marker.size_m if self.marker.kind == "aruco" else None
            outcome = hold_outcome(seq, len(self.outcomes), start, end, len(picked), dets, track, self.camera_offset_ns, size, self.options)
        else:
            seq = int(event.metadata.get("seq_to", -1))
            picked = pick_frames(frames, start + self.camera_offset_ns, end + self.camera_offset_ns, self.options.frames_per_leg)
            dets = detect_in_frames(picked, self.marker, self._detector, frames)
            item = self.mission.items[seq] if 0 <= seq < len(self.mission.items) else None
            self.leg_detections.extend(dets)
            if item is None or item.command != CMD_NAV_WAYPOINT or item.hold_s > 0:
                return  # the hold at its end speaks for that waypoint
            outcome = leg_outcome(seq, end, len(picked), dets)
        self._conclude(outcome, track)
        if self.view is not None and picked:
            self._publish_waypoint_frame(picked, dets)

    def _conclude(self, outcome: WaypointOutcome, track: FixTrack) -> None:
        from dronecal_field.pipeline.align import estimate_time_offset

        with self._lock:
            self.outcomes.append(outcome)
            outcomes = list(self.outcomes)
        points = [o.point for o in outcomes if o.point is not None]
        estimate = solve(points, self.width, self.height, waypoints=len(outcomes), previous=self.estimate, prior=self.prior)
        every = max(1, self.options.summary_every)
        offset = self.offset
        if len(outcomes) % every == 0:
            # The marker moving across the image (legs) shows the offset; still holds do not (they only add noise to it).
            dets = list(self.leg_detections)
            if len(dets) >= 12 and len(track.t_ns) >= 4:
                t = np.array([d.timestamp_ns for d in dets], np.int64)
                uv = np.array([[d.u_px, d.v_px] for d in dets], float)
                order = np.argsort(t)
                offset = estimate_time_offset(t[order], uv[order], track.t_ns, track.marker_enu_m)
        cover = coverage(self._roi, outcomes + [_detections_only(self.leg_detections)])
        with self._lock:
            self.estimate = estimate
            self.coverage = cover
            self.offset = offset
            entry = {"waypoints": len(outcomes), "seq": outcome.seq, "good": outcome.good, "coverage": cover}
            if estimate is not None:
                entry.update(estimate.to_dict())
            self.history.append(entry)
            if len(outcomes) % every == 0:
                self.summaries.append(summary_line(outcomes, self.expected, estimate, cover, offset, self.prior))

    # ----- the Foxglove view -----
    def _publish_waypoint_frame(self, picked: list, dets: list) -> None:
        frame = picked[len(picked) // 2]
        det = min(dets, key=lambda d: abs(d.timestamp_ns - frame.timestamp_ns)) if dets else None
        if det is not None:
            frame = next((f for f in picked if f.timestamp_ns == det.timestamp_ns), frame)
        if frame.format not in COMPRESSED:  # an H.264 access unit is no CompressedImage: the view then shows no camera
            self.view.publish_image(frame, det, self._reprojection(frame.timestamp_ns), self._all_uv())
        if self.estimate is not None:
            self.view.publish_calibration(self.estimate, frame.timestamp_ns)

    def _publish_view(self) -> None:
        view = self.view
        fixes = list(self._fixes)
        view.publish_fixes(fixes)
        frame = self._latest_frame
        if frame is not None:
            view.publish_image(frame, None, self._reprojection(frame.timestamp_ns), self._all_uv())
        with self._lock:
            statuses = {o.seq: ("good" if o.good else (o.problem or "missed")) for o in self.outcomes}
            est = self.estimate
        view.publish_waypoints(statuses)
        if est is not None:
            view.publish_calibration(est, time.time_ns())
        view.publish_status({"status": self.status_text(), "summary": self.summaries[-1] if self.summaries else ""})

    def _reprojection(self, t_ns: int) -> np.ndarray | None:
        """(2,) where the current calibration puts the marker at ``t_ns`` (its GNSS position then), or None."""
        est = self.estimate
        if est is None or self.origin is None:
            return None
        fixes = [f for f in list(self._fixes)[-50:]]
        if not fixes:
            return None
        track = fix_track(fixes, list(self._attitudes)[-100:], self.origin, np.asarray(self.marker.offset_frd_m, float))
        k = int(np.argmin(np.abs(track.t_ns - (t_ns - self.camera_offset_ns))))
        X = track.marker_enu_m[k : k + 1]
        if est.camera.depth(X)[0] <= 0:
            return None
        return est.camera.project(X)[0]

    def _all_uv(self) -> np.ndarray:
        with self._lock:
            uv = [o.uv_px for o in self.outcomes if len(o.detections)]
        return np.concatenate(uv) if uv else np.zeros((0, 2))


def _detections_only(dets: list) -> WaypointOutcome:
    """The legs' detections as one outcome, for the coverage only."""
    return WaypointOutcome(seq=-1, kind="leg", end_ns=0, frames=len(dets), detections=list(dets), point=None, problem=None)
