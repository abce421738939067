"""The live calibration around the recorder: an observer that only queues, and one worker thread.

::

    recorder video thread  --on_frame-->  frame ring (a few frames a second, bounded by count)
    recorder writer thread --on_record--> fixes, attitudes (bounded deques); hover / leg events -> job queue (bounded)
    worker thread (nice +10): each job: frames of the hold -> detector -> point -> running calibration
                              -> coverage, summary, verdict; legs -> a pair per GNSS fix (calibrate's pairing)
    view thread (with --live-port): twice a second the Foxglove view (status, GNSS, the latest image)
                              between jobs, every ring frame around each hold and leg -> detector
                              -> frame cache (calibrate after landing takes it: pipeline/framecache.py)

The observer's calls are O(1) appends and a ``put_nowait``: the recorder never
waits for the live work. When the worker falls behind, the job queue fills
and further waypoints are deferred (counted in ``jobs_dropped``), as are
waypoints whose frames the ring let go before the worker got to them: they are
"not checked yet", never "missed", and ``finish`` checks them after landing
from the ring or the closed run file, before the verdict.
The recorder's own frame queue, its drops and its priority are untouched.

The frame cache: each hover event opens a *zone* of frame stamps, the hold
widened as ``calibrate`` reads it (``SamplingOptions.margin_s`` + ``dense_s``
each side), each leg event one widened by ``margin_s``. Every ring frame in a
zone is detected once, in time order, with ``calibrate``'s detector; a zone
whose frames all got an outcome becomes a *covered* interval (from after the
last of its frames the ring evicted undetected). ``calibrate`` then decodes
only what lies outside. H.264/H.265 access units are pushed, in stream order,
to one decoder that decodes a GOP only up to a zone's frames (a GOP with no
zone frame is never decoded); after the ring let units go unpushed, it starts
again at the next keyframe, and what it cannot decode is left to ``calibrate``.
"""

from __future__ import annotations

import bisect
import collections
import contextlib
import os
import queue
import threading
import time
from dataclasses import dataclass, field, replace
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
    expected_seqs,
    fix_track,
    guessed_camera,
    hold_outcome,
    image_roi,
    NO_FRAMES,
    leg_outcome,
    live_leg_points,
    thin,
    pick_frames,
    scout_verdict,
    plan_flight,
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
MAX_LEG_POINTS = 300  # leg pairs in the running solve (evenly thinned: it must stay well under a second)
LEG_MIN_DETECTIONS = 3  # as progress.leg_outcome
MAX_LEG_FRAMES = 120  # a marginal leg is looked at whole, up to this many frames
VIEW_PERIOD_S = 0.5  # the live view's status, GNSS and image: twice a second (docs/live.md)
ZONE_BATCH = 8  # ring frames detected between two looks at the job queue (~0.05-0.2 s at 720p-1080p)


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
    frames: Any = None  # pipeline.framecache.FrameResults of the zone pass (None for H.264/H.265 or --no-live)
    checked_after_landing: list[int] = field(default_factory=list)  # waypoints the worker could not reach in flight
    view_errors: dict[str, int] = field(default_factory=dict)  # live view publish failures by kind

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
            "checked_after_landing_seqs": self.checked_after_landing,
            "leg_points": None if self.estimate is None else self.estimate.n_points,
            "worker_cpu_s": self.cpu_s,
            "view_errors": self.view_errors,
            "wall_s": self.wall_s,
            "frame_cache": None if self.frames is None else {
                "frames_detected": len(self.frames), "covered_s": round(self.frames.covered_s, 3), "covered_intervals": len(self.frames.covered),
            },
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
    ring_frames, ring_bytes : the frame ring's bounds (RING_FRAMES, RING_BYTES).
    camera : the camera's name in a several-camera run (its frames read back from ``/cameras/<camera>/...``), else None.
    job_lock : a lock shared by several cameras' workers: one waypoint job at a time among them (None: its own pace).
    cpu_share : after each job, rest (holding ``job_lock``) so that jobs take at most this share of one core.
    after_landing_max : at most this many waypoints checked by ``finish`` (the latest); the rest are left to
        ``calibrate`` ("not checked"). None: all of them.
    """

    def __init__(
        self, mission: Any, marker: Any, width: int, height: int, plan: dict | None = None, origin: Any = None,
        options: LiveOptions = LiveOptions(), view: Any = None, camera_latency_s: float | None = None, job_queue: int = 8,
        ring_frames: int = RING_FRAMES, ring_bytes: int = RING_BYTES, camera: str | None = None,
        job_lock: Any = None, cpu_share: float = 1.0, after_landing_max: int | None = None,
    ) -> None:
        self.after_landing_max = after_landing_max
        self.camera = camera
        self._job_lock = job_lock
        self.cpu_share = min(1.0, max(0.05, float(cpu_share)))
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
        self._ring_max = (int(ring_frames), int(ring_bytes))
        self._last_kept_ns = 0
        self._last_seen_ns = 0
        self._period_ns: float | None = None  # the stream's mean frame interval (running average)
        self._latest_frame: Any = None
        self._fixes: collections.deque[GnssFix] = collections.deque(maxlen=200_000)
        self._attitudes: collections.deque[Attitude] = collections.deque(maxlen=200_000)
        self._jobs: queue.Queue = queue.Queue(maxsize=max(1, job_queue))
        self.jobs_dropped = 0  # waypoints the worker could not reach in flight (checked after landing)
        self.unchecked: list[int] = []
        self._deferred: list[RunEvent] = []
        self.checked_after_landing: list[int] = []
        self._evicted_ns = -1  # newest frame the ring has let go (the worker can no longer look at it)
        self._leg_points: list = []  # pipeline.points.WaypointPoint per GNSS fix on the legs, as calibrate pairs them
        self._legs_seen = 0
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
        self._view_stop = threading.Event()
        self._current_event: RunEvent | None = None  # the job the worker is in
        self._batch = False  # checking after landing: outcomes are collected, the estimate refreshed once at the end
        self._thread: threading.Thread | None = None
        self._view_thread: threading.Thread | None = None
        self._cpu_s = 0.0
        self._started = time.monotonic()
        self._lock = threading.Lock()  # outcomes/estimate read by the status line
        # The frame cache (docs/live.md "From landing to the final result"): outcomes by frame stamp, zones, covered spans.
        self._outcomes: dict[int, Any] = {}  # stamp -> detect.FrameResult, or None (did not decode)
        self._zones: list[list[int]] = []  # pending [start_ns, end_ns] (frame stamps)
        self._covered: list[tuple[int, int]] = []
        self._evicted_undone_ns = -1  # newest ring frame evicted before the worker detected it (written by on_frame)
        self._cache_on: bool | None = None  # JPEG/PNG: True; H.264/H.265: False; None until the first frame
        self.view_errors: dict[str, int] = {}  # live view publish failures by kind (live.json)
        self._video: Any = None  # H.264/H.265: the zone pass's decoder (video.decode.VideoFrameDecoder), fed in stream order
        self._video_last_ns: int | None = None  # the last access unit pushed to it
        self._keyframes_ns: list[int] = []  # keyframes pushed to it, in order (a covered span must hold one: _cover)
        self._last_det: Any = None  # tracking in the zone pass (calibrate's search box)
        self._before_det: Any = None
        self.finish_started: tuple[float, float] | None = None  # (monotonic, process CPU) s when finish() began
        self._batch_track: FixTrack | None = None  # after landing every fix is in: the track is made once, not per waypoint

    # ----- observer (recorder threads): O(1), never waits -----
    def on_frame(self, frame: Any) -> None:
        compressed = frame.format in COMPRESSED
        if not compressed:
            self._latest_frame = frame
        elif self.view is not None:
            self.view.offer_video(frame)  # a keyframe kept for the view's low-rate image, nothing decoded here
        # A stream at up to ~RING_HZ keeps every frame, however jittered (two frames 12 ms apart are both in the
        # file, and calibrate takes both): only a faster one (mean interval from a running average) is thinned.
        dt = frame.timestamp_ns - self._last_seen_ns
        self._last_seen_ns = frame.timestamp_ns
        if 0 < dt < 1_000_000_000:
            self._period_ns = dt if self._period_ns is None else 0.95 * self._period_ns + 0.05 * dt
        gap = int(0.8e9 / RING_HZ)
        if compressed or (self._period_ns or 0) >= gap or frame.timestamp_ns - self._last_kept_ns >= gap:
            self._last_kept_ns = frame.timestamp_ns
            self._frames.append(frame)
            self._ring_bytes += len(frame.data)
            while len(self._frames) > self._ring_max[0] or self._ring_bytes > self._ring_max[1]:
                old = self._frames.popleft()
                self._ring_bytes -= len(old.data)
                self._evicted_ns = max(self._evicted_ns, old.timestamp_ns)
                if old.timestamp_ns not in self._outcomes and old.timestamp_ns > self._evicted_undone_ns:
                    self._evicted_undone_ns = old.timestamp_ns  # a zone holding it is covered only after it

    def on_record(self, record: Any) -> None:
        if isinstance(record, GnssFix):
            self._fixes.append(record)
        elif isinstance(record, Attitude):
            self._attitudes.append(record)
        elif isinstance(record, RunEvent) and record.type in ("hover", "leg"):
            try:
                self._jobs.put_nowait((time.monotonic() + GRACE_S, record))
            except queue.Full:
                self._defer(record)  # checked later from the ring, or from the closed run file after landing

    # ----- lifecycle -----
    def start(self) -> "LiveCalibration":
        self._thread = threading.Thread(target=self._run, name="live-calibration", daemon=True)
        self._thread.start()
        if self.view is not None:
            # Its own thread at normal priority: the view keeps its rates while the worker (nice +10) is deep in a job.
            self._view_thread = threading.Thread(target=self._view_loop, name="live-view", daemon=True)
            self._view_thread.start()
        return self

    def _view_loop(self) -> None:
        while not self._view_stop.wait(VIEW_PERIOD_S):
            try:
                self._publish_view()
            except Exception:  # noqa: BLE001 - the view is cosmetic
                pass

    def finish(self, timeout_s: float = 30.0, run_path: Any = None) -> LiveResult:
        """Stop the worker, check every waypoint it had not reached, and conclude.

        The worker stops after its current job (up to ``timeout_s``); the
        waypoints still queued or deferred (the worker was behind: their frames
        left the ring) are then checked here, from the ring or, with
        ``run_path`` (the closed run file), from the recording, so the verdict
        never calls "missed" a waypoint whose frames nobody looked at.
        """
        self.finish_started = (time.monotonic(), time.process_time())  # for fly's "calibration ready" breakdown
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=timeout_s)
        pending = self._drain_jobs() + list(self._deferred)
        self._deferred.clear()
        busy_with = self._current_event
        if self._thread is not None and self._thread.is_alive() and busy_with is not None:
            pending.append(busy_with)  # a starved worker (nice +10 on a loaded machine) may never finish it: checked here too
        if self.after_landing_max is not None and len(pending) > self.after_landing_max:
            pending.sort(key=lambda e: e.timestamp_ns)
            keep = max(0, int(self.after_landing_max))
            self._deferred.extend(pending[: len(pending) - keep])  # left to calibrate: the pilot does not wait for them
            pending = pending[len(pending) - keep :]
        self._check_after_landing(pending, run_path)
        pending = list(self._deferred)
        self._view_stop.set()  # the view went on saying how the check after landing went
        if self._view_thread is not None:
            self._view_thread.join(timeout=timeout_s)
        unchecked = sorted({_event_seq(e) for e in pending if _event_seq(e) is not None})
        frames = self.frame_results()
        with self._lock:
            if isinstance(self.plan, dict) and self.plan.get("kind") == "scout":
                v = scout_verdict(self.outcomes)
            else:
                v = verdict(self.outcomes, [s for s in self.expected if s not in unchecked], self.estimate, self.coverage, self.prior,
                            plan_flight(self.mission, self.plan))
            result = LiveResult(
                outcomes=list(self.outcomes), expected=list(self.expected), estimate=self.estimate, history=list(self.history),
                verdict=v, coverage=self.coverage, offset=self.offset, jobs_dropped=self.jobs_dropped,
                unchecked=unchecked, cpu_s=self._cpu_s, wall_s=time.monotonic() - self._started,
                summaries=list(self.summaries), constrained=constrained(self.estimate, self.prior),
                frames=frames, checked_after_landing=sorted(set(self.checked_after_landing)), view_errors=dict(self.view_errors),
            )
        if self.view is not None:
            try:
                self.view.publish_status({"verdict": v.text, "good": v.good, "refly_seqs": list(v.refly_seqs)})
            except Exception:  # noqa: BLE001 - the view is cosmetic
                pass
        return result

    def _defer(self, event: RunEvent) -> None:
        """A waypoint the worker cannot look at now (queue full, frames gone from the ring): "not checked yet"."""
        self.jobs_dropped += 1
        if len(self._deferred) < 100_000:
            self._deferred.append(event)
        seq = _event_seq(event)
        if seq is not None:
            self.unchecked.append(seq)

    def _drain_jobs(self) -> list[RunEvent]:
        out = []
        while True:
            try:
                out.append(self._jobs.get_nowait()[1])
            except queue.Empty:
                return out

    def _check_after_landing(self, events: list[RunEvent], run_path: Any) -> None:
        """The deferred waypoints, in time order: from the ring where it still holds their frames, else from the run file."""
        if not events:
            return
        events = sorted(events, key=lambda e: e.timestamp_ns)
        if self._detector is None and self.marker.kind == "aruco":
            self._prepare()  # the worker never got to start
        ring = list(self._frames)
        from_file: list[RunEvent] = []
        self._batch = True  # outcomes only; one refresh at the end
        self._batch_track = self._track()  # 0.09 s a waypoint from 3500 fixes: 6.7 s of 65 checks after landing
        if self._cache_on is None:
            self._cache_on = self.options.frame_cache  # the worker never ran: what is decoded here still serves calibrate
        for event in events:
            if self._ring_holds(event, ring):
                self._check(event, ring, after_landing=True)
            else:
                from_file.append(event)
        if not from_file:
            return
        frames = self._frames_from_file(from_file, run_path)
        if frames is None:
            self._deferred.extend(from_file)  # no file to read: calibrate checks them
        else:
            for event in from_file:
                self._check(event, frames, after_landing=True)
        if self.outcomes:
            self._refresh(self.outcomes[-1], self._track())  # once for them all: a solve per waypoint would take minutes

    def _frames_from_file(self, events: list[RunEvent], run_path: Any) -> list | None:
        """The recorded frames around ``events`` (camera clock), or None without a readable run file."""
        if run_path is None:
            return None
        from dronecal_field.runfile.reader import open_run

        m = int(self.options.sampling.margin_s * 1e9)  # calibrate's margins: its leg frames start there (pick_leg_grid)
        windows = [(int(e.timestamp_ns) + min(0, self.camera_offset_ns) - m, int(e.timestamp_ns + e.duration_ns) + max(0, self.camera_offset_ns) + m)
                   for e in events]
        try:
            with (open_run(run_path) if self.camera is None else open_run(run_path, camera=self.camera)) as run:
                return list(run.iter_frames(windows))
        except Exception as exc:  # noqa: BLE001 - a damaged file: the verdict says they were not checked
            with self._lock:
                self.summaries.append(f"live: could not read {run_path} to check {len(events)} waypoints after landing ({exc})")
            return None

    def _check(self, event: RunEvent, frames: list, after_landing: bool = False) -> None:
        """One job; a failure of one waypoint never ends the live pass."""
        try:
            self._process(event, frames)
            if after_landing and _event_seq(event) is not None:
                self.checked_after_landing.append(_event_seq(event))
        except Exception as exc:  # noqa: BLE001 - one bad waypoint must not end the live view
            with self._lock:
                self.summaries.append(f"live: waypoint skipped ({type(exc).__name__}: {exc})")

    def _ring_holds(self, event: RunEvent, ring: list) -> bool:
        """The ring still holds every frame of ``event``'s window (none evicted from it)."""
        start = int(event.timestamp_ns) + self.camera_offset_ns
        return bool(ring) and start > self._evicted_ns

    def frame_results(self):
        """The zone pass's outcomes and covered intervals (``pipeline.framecache.FrameResults``); None when nothing is cached."""
        from dronecal_field.pipeline.framecache import FrameResults

        if not self._cache_on:
            return None
        outcomes = dict(self._outcomes)  # one C-level copy: safe while a late worker still adds
        with self._lock:
            covered = list(self._covered)
        ring = list(self._frames)
        return FrameResults.build(outcomes, covered, source="live pass", formats=(ring[-1].format,) if ring else ())

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
        waiting = len(self._deferred)
        if waiting:
            text += f" | {waiting} to check after landing"
        return text

    # ----- worker thread -----
    def _run(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 10)  # below the recorder's threads
        except (AttributeError, OSError):
            pass
        t_cpu = time.thread_time()
        self._prepare()
        busy = False  # the zone pass has frames waiting: look at the job queue without waiting
        while True:
            busy = busy and bool(self._zones) and not self._stop.is_set()
            try:
                ready, event = self._jobs.get(timeout=0.0 if busy else 0.1)
            except queue.Empty:
                ready = event = None
            if event is not None:
                self._open_zone(event)
                wait = ready - time.monotonic()
                if wait > 0 and not self._stop.is_set():
                    time.sleep(wait)
                try:
                    self._zone_pass(until_ns=int(event.timestamp_ns + event.duration_ns) + self.camera_offset_ns)  # the job then reads the cache
                except Exception as exc:  # noqa: BLE001 - the cache is an optimisation: calibrate reads the file instead
                    self._zones.clear()
                    with self._lock:
                        self.summaries.append(f"live: frame cache stopped ({type(exc).__name__}: {exc})")
                ring = list(self._frames)
                if self._ring_holds(event, ring):
                    self._current_event = event
                    self._paced_check(event, ring)
                    self._current_event = None
                else:
                    self._defer(event)  # its frames are gone from the ring: not "missed", checked after landing
                busy = True
            elif self._zones and not self._stop.is_set():
                try:
                    busy = self._zone_pass(budget=ZONE_BATCH) > 0
                except Exception as exc:  # noqa: BLE001 - the cache is an optimisation: calibrate reads the file instead
                    self._zones.clear()
                    with self._lock:
                        self.summaries.append(f"live: frame cache stopped ({type(exc).__name__}: {exc})")
            self._cpu_s = time.thread_time() - t_cpu
            if self._stop.is_set():
                break  # finish() checks what is still queued, after landing
        self._close_zones()
        self._cpu_s = time.thread_time() - t_cpu

    def _paced_check(self, event: RunEvent, ring: list) -> None:
        """One job in flight: alone among the cameras sharing ``job_lock``, then a rest that keeps the jobs within
        ``cpu_share`` of a core (a resting worker holds no interpreter lock: the recorder's threads run)."""
        if self._job_lock is None and self.cpu_share >= 1.0:
            self._check(event, ring)
            return
        with self._job_lock if self._job_lock is not None else contextlib.nullcontext():
            t0 = time.thread_time()
            self._check(event, ring)
            rest = (time.thread_time() - t0) * (1.0 / self.cpu_share - 1.0)
            if rest > 0:
                self._stop.wait(min(rest, 10.0))

    def _prepare(self) -> None:
        from dronecal_field.pipeline.detect import make_aruco_detector

        if self.marker.kind == "aruco":
            self._detector = make_aruco_detector(self.marker.dictionary)
        self._roi = image_roi(self.plan) if self.plan is not None else None
        if self.view is not None:
            self.view.set_plan(self.mission, self._roi, self.plan, self.origin)

    def _track(self) -> FixTrack:
        fixes = list(self._fixes)
        if self.origin is None and fixes:
            from dronecal_field.geodesy import EnuOrigin

            f = fixes[0]
            self.origin = EnuOrigin(lat_deg=f.lat_deg, lon_deg=f.lon_deg, h_m=f.alt_m)
        return fix_track(fixes, list(self._attitudes), self.origin, np.asarray(self.marker.offset_frd_m, float))

    def _process(self, event: RunEvent, frames: list) -> None:
        """One flown waypoint, judged on what ``calibrate`` will use: a hold long enough to settle gives a hover
        point; a leg gives a pair per GNSS fix; a leg's short end hold (``points.SHORT_SETTLED_S``) serves its leg."""
        from dronecal_field.pipeline.hover import HoverWindow
        from dronecal_field.pipeline.points import SHORT_SETTLED_S

        start, end = int(event.timestamp_ns), int(event.timestamp_ns + event.duration_ns)
        track = self._batch_track if self._batch and self._batch_track is not None else self._track()
        off = self.camera_offset_ns
        if event.type == "hover":
            seq = int(event.metadata.get("seq", -1))
            po = self.options.points
            a, b = HoverWindow(0, start, end, "event", seq).stable(po.settle_s, po.tail_s)
            if (b - a) * 1e-9 < SHORT_SETTLED_S:
                # A leg's end: calibrate pairs its frames with the leg's fixes, never as a hover point.
                picked = pick_frames(frames, start + off, end + off, self.options.frames_per_leg)
                dets = self._leg_detections_in(start + off, end + off, self._detect_picked(picked, frames), frames)
                self.leg_detections.extend(dets)
                outcome = leg_outcome(seq, end, len(picked), dets)
            else:
                picked = pick_hold_frames(frames, a + off, b + off, self.options.frames_per_hold)
                dets = self._detect_picked(picked, frames)
                size = self.marker.size_m if self.marker.kind == "aruco" else None
                outcome = hold_outcome(seq, len(self.outcomes), start, end, len(picked), dets, track, off, size, self.options)
        else:
            seq = int(event.metadata.get("seq_to", -1))
            if self._batch:
                # After landing: calibrate's own choice on the leg (SamplingOptions.leg_period_s from its margin on), all
                # decoded here once, so calibrate takes them from the frame cache instead of decoding them again.
                s = self.options.sampling
                grid = pick_leg_grid(frames, start - int(s.margin_s * 1e9), end + int(s.margin_s * 1e9), int(s.leg_period_s * 1e9))
                self._detect_picked(grid, frames)
                picked = [f for f in grid if start + off <= f.timestamp_ns <= end + off]
            else:
                picked = pick_frames(frames, start + off, end + off, self.options.frames_per_leg)
            dets = self._leg_detections_in(start + off, end + off, self._detect_picked(picked, frames), frames)
            self._add_leg_points(start, end, dets, track)
            self.leg_detections.extend(dets)
            item = self.mission.items[seq] if 0 <= seq < len(self.mission.items) else None
            if item is None or item.command != CMD_NAV_WAYPOINT:
                return
            if item.hold_s - self.options.points.settle_s - self.options.points.tail_s >= SHORT_SETTLED_S:
                return  # the hold at its end speaks for that waypoint
            outcome = leg_outcome(seq, end, len(picked), dets)
        if not picked:
            outcome = replace(outcome, problem=NO_FRAMES)  # the recording has no frame there: video lost
        self._conclude(outcome, track)
        if self.view is not None and picked:
            self._publish_waypoint_frame(picked, dets)

    def _leg_detections_in(self, a_ns: int, b_ns: int, picked_dets: list, frames: list) -> list:
        """Every detection of the leg's frames (camera clock [a_ns, b_ns]): the frame cache's where it has them, else the
        job's; a leg whose sparse pick saw the marker on too few frames is looked at whole (up to MAX_LEG_FRAMES frames),
        so a marker seen briefly, which calibrate pairs, is not called "missed" on a sample."""
        cached = [r.detection for t, r in list(self._outcomes.items()) if a_ns <= t <= b_ns and r is not None and r.detection is not None]
        dets = cached if len(cached) > len(picked_dets) else picked_dets
        if 0 < len(dets) < LEG_MIN_DETECTIONS:
            every = pick_frames(frames, a_ns, b_ns, MAX_LEG_FRAMES)
            if len(every) > self.options.frames_per_leg:
                dets = self._detect_picked(every, frames)
        return sorted(dets, key=lambda d: d.timestamp_ns)

    def _add_leg_points(self, start_ns: int, end_ns: int, dets: list, track: FixTrack) -> None:
        """The leg's 3D-2D pairs, as calibrate makes them (``pipeline.legs.leg_points``) at the current camera offset."""
        if len(dets) < 4 or len(track.t_ns) < 4:
            return
        offset_ns = self.offset.offset_ns if self.offset is not None and self.offset.method != "none" else self.camera_offset_ns
        points = live_leg_points(start_ns, end_ns, dets, track, offset_ns, self.options.min_fix, index=self._legs_seen)
        self._legs_seen += 1
        with self._lock:
            self._leg_points.extend(points)

    # ----- the frame cache: every ring frame around the holds and legs, detected once -----
    def _open_zone(self, event: RunEvent) -> None:
        """A hover or leg event: the span of frame stamps calibrate reads around it (SamplingOptions' margins)."""
        if self._cache_on is None and self._frames:
            self._cache_on = self.options.frame_cache
        if not self._cache_on:
            return
        s = self.options.sampling
        widen = int((s.margin_s + (s.dense_s if event.type == "hover" else 0.0)) * 1e9)
        self._zones.append([int(event.timestamp_ns) - widen, int(event.timestamp_ns + event.duration_ns) + widen])

    def _zone_pass(self, until_ns: int | None = None, budget: int | None = None) -> int:
        """Detect ring frames inside pending zones not detected yet, in time order (up to ``until_ns``,
        at most ``budget`` of them); close the zones the stream has passed. Stops at once on finish()."""
        if not self._zones:
            return 0
        frames = list(self._frames)
        done = 0
        for frame in frames:
            t = frame.timestamp_ns
            if self._stop.is_set() or (until_ns is not None and t > until_ns) or (budget is not None and done >= budget):
                break
            if frame.format in COMPRESSED:
                done += self._video_step(frame)
                continue
            if t in self._outcomes or not any(a <= t <= b for a, b in self._zones):
                continue
            self._detect_one(frame)
            done += 1
        newest = frames[-1].timestamp_ns if frames else None
        for zone in list(self._zones):
            if newest is not None and newest > zone[1] and all(f.timestamp_ns in self._outcomes or f.timestamp_ns <= self._evicted_undone_ns
                                                               for f in frames if zone[0] <= f.timestamp_ns <= zone[1]):
                self._zones.remove(zone)
                self._cover(zone[0], zone[1])
        return done

    def _video_step(self, unit: Any) -> int:
        """One H.264/H.265 access unit of the ring, in stream order: pushed to the zone pass's decoder (cheap: a GOP
        with nothing wanted is never decoded) and, inside a zone, decoded and detected. 1 when it was detected."""
        from dronecal_field.video.decode import VideoFrameDecoder
        from dronecal_field.video.nal import video_frame_of

        t = unit.timestamp_ns
        if self._video_last_ns is not None and t <= self._video_last_ns:
            return 0  # pushed already
        if self._video is None or (self._video_last_ns is not None and self._evicted_ns > self._video_last_ns):
            self._video = VideoFrameDecoder(unit.format, threads=1)  # the ring let units go unpushed: start again at a keyframe
        unit = video_frame_of(unit)
        self._video.push(unit)
        self._video_last_ns = t
        if unit.keyframe:
            self._keyframes_ns.append(t)
        if t in self._outcomes or not any(a <= t <= b for a, b in self._zones):
            return 0
        image = self._video.gray()
        if image is None:
            # no keyframe before it in what the ring held (or a damaged unit): calibrate decodes it from the file
            self._evicted_undone_ns = max(self._evicted_undone_ns, t)
            return 0
        self._outcomes[t] = self._detect_tracked(image, t)
        return 1

    def _cover(self, a: int, b: int) -> None:
        """[a, b] had every ring frame detected, except those the ring evicted first: covered after the last of them."""
        start = a if self._evicted_undone_ns < a else self._evicted_undone_ns + 1
        if self._video is not None:
            # H.264/H.265: calibrate reads the file around a covered span and decodes what follows it from the last
            # keyframe the reader passed; a span with none inside leaves the next read window without its chain
            # (measured: 164 of 547 wanted units undecodable, skipped as corrupt). Its outcomes still serve by stamp.
            k = bisect.bisect_left(self._keyframes_ns, start)
            if k >= len(self._keyframes_ns) or self._keyframes_ns[k] > b:
                return
        if start <= b:
            with self._lock:
                self._covered.append((start, b))

    def _close_zones(self) -> None:
        """At the end: each pending zone is covered up to its first frame not detected (calibrate reads the rest)."""
        frames = list(self._frames)
        for a, b in self._zones:
            last = None
            for f in frames:
                if f.timestamp_ns < a or f.timestamp_ns <= self._evicted_undone_ns:
                    continue  # before the zone, or left to calibrate (the cover starts after it)
                if f.timestamp_ns > b or f.timestamp_ns not in self._outcomes:
                    break
                last = f.timestamp_ns
            if last is not None:
                self._cover(a, last)
        self._zones.clear()

    def _detect_one(self, frame: Any) -> Any:
        """calibrate's search on one JPEG/PNG frame (its tracking box from the last detection); kept by stamp."""
        from dronecal_field.pipeline.detect import decode_gray

        t = frame.timestamp_ns
        if t in self._outcomes:
            return self._outcomes[t]
        image = decode_gray(frame.data)
        result = None if image is None else self._detect_tracked(image, t)
        self._outcomes[t] = result
        return result

    def _detect_tracked(self, image: np.ndarray, t: int) -> Any:
        """calibrate's search on a decoded (H, W) image stamped ``t``, boxed by the zone pass's last detections."""
        from dronecal_field.pipeline.detect import TRACK_NS, detect_marker, predicted, roi_around

        last = self._last_det
        roi = None
        if last is not None and abs(t - last.timestamp_ns) < TRACK_NS:
            roi = roi_around(predicted(last, self._before_det, t), image.shape)
        result = detect_marker(image, self.marker, self._detector, t, roi)
        if result.detection is not None and (last is None or t > last.timestamp_ns):
            self._before_det, self._last_det = last, result.detection
        return result

    def _detect_picked(self, picked: list, frames: list) -> list:
        """A job's detections: from the cache where the zone pass got there first (never a frame twice)."""
        if not picked:
            return []
        if picked[0].format in COMPRESSED:
            if not all(f.timestamp_ns in self._outcomes for f in picked):  # else the zone pass decoded them in stream order
                self._decode_units(picked, frames)
            results = [self._outcomes.get(f.timestamp_ns) for f in sorted(picked, key=lambda f: f.timestamp_ns)]
            return [r.detection for r in results if r is not None and r.detection is not None]
        found = []
        for frame in sorted(picked, key=lambda f: f.timestamp_ns):
            result = self._detect_one(frame)
            if result is not None and result.detection is not None:
                found.append(result.detection)
        return found

    def _decode_units(self, picked: list, stream: list) -> None:
        """The ``picked`` H.264/H.265 access units of ``stream`` (every unit around them, in order), decoded by one
        decoder from the keyframe before the first: each GOP once, only up to its last picked unit. Their outcomes go
        to the frame cache, where ``calibrate`` takes any frame it wants of them instead of decoding it again. A unit
        that does not decode (no keyframe before it here, a damaged chain) is left out of the cache: it is no corrupt
        frame of the file, and ``calibrate`` decodes it from there."""
        from dronecal_field.video.decode import VideoFrameDecoder
        from dronecal_field.video.nal import video_frame_of

        want = {f.timestamp_ns for f in picked if f.timestamp_ns not in self._outcomes}
        if not want:
            return
        units = sorted(stream, key=lambda f: f.timestamp_ns)
        first, last = min(want), max(want)
        k = bisect.bisect_right([u.timestamp_ns for u in units], first) - 1
        while k > 0 and not video_frame_of(units[k]).keyframe:  # back to the keyframe before (a GOP at most)
            k -= 1
        k = max(k, 0)
        decoder = VideoFrameDecoder(picked[0].format, threads=1)
        for unit in units[k:]:
            t = unit.timestamp_ns
            if t > last:
                break
            decoder.push(video_frame_of(unit))
            if t in want:
                image = decoder.gray()
                if image is not None:
                    self._outcomes[t] = self._detect_tracked(image, t)

    def _conclude(self, outcome: WaypointOutcome, track: FixTrack) -> None:
        with self._lock:
            self.outcomes.append(outcome)
        if not self._batch:
            self._refresh(outcome, track)

    def _refresh(self, outcome: WaypointOutcome, track: FixTrack) -> None:
        """The running calibration, camera offset, coverage and summary after ``outcome`` (seconds of CPU with many legs)."""
        from dronecal_field.pipeline.align import estimate_time_offset

        with self._lock:
            outcomes = list(self.outcomes)
        with self._lock:
            leg_points = list(self._leg_points)
        points = [o.point for o in outcomes if o.point is not None] + thin(leg_points, MAX_LEG_POINTS)
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
        """Each topic on its own: one that fails (counted in ``view_errors``) never holds back the others; status first."""
        view = self.view
        with self._lock:
            statuses = {o.seq: ("good" if o.good else (o.problem or "missed")) for o in self.outcomes}
            est = self.estimate
        self._view_step("status", lambda: view.publish_status({"status": self.status_text(), "summary": self.summaries[-1] if self.summaries else ""}))
        self._view_step("gnss", lambda: view.publish_fixes(list(self._fixes)))
        frame = self._latest_frame if self._latest_frame is not None else view.video_image()
        if frame is not None:
            self._view_step("image", lambda: view.publish_image(frame, None, self._reprojection(frame.timestamp_ns), self._all_uv()))
        self._view_step("waypoints", lambda: view.publish_waypoints(statuses))
        if est is not None:
            self._view_step("calibration", lambda: view.publish_calibration(est, time.time_ns()))

    def _view_step(self, name: str, publish) -> None:
        try:
            publish()
        except Exception as exc:  # noqa: BLE001 - the view is cosmetic: counted, never fatal
            key = f"{name}: {type(exc).__name__}: {exc}"[:200]
            self.view_errors[key] = self.view_errors.get(key, 0) + 1

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


def pick_leg_grid(frames: list, start_ns: int, end_ns: int, period_ns: int) -> list:
    """The frames of [start_ns, end_ns] calibrate takes on a leg (``sampling.FrameSelector``'s leg zone): the first,
    then each at least ``period_ns`` after the one taken before."""
    out: list = []
    for f in sorted(frames, key=lambda f: f.timestamp_ns):
        t = f.timestamp_ns
        if start_ns <= t <= end_ns and (not out or t - out[-1].timestamp_ns >= period_ns):
            out.append(f)
    return out


def pick_hold_frames(frames: list, start_ns: int, end_ns: int, n: int) -> list:
    """Up to ``n`` frames of a hold's [start_ns, end_ns]. H.264/H.265: each keyframe and the two units after it
    first (calibrate's own choice there, ``SamplingOptions.video_burst_frames``: a short decode, and calibrate then
    takes those outcomes from the frame cache), the rest spread evenly; JPEG/PNG: spread evenly (``pick_frames``)."""
    inside = [f for f in frames if start_ns <= f.timestamp_ns <= end_ns]
    if not inside or inside[0].format not in COMPRESSED:
        return pick_frames(frames, start_ns, end_ns, n)
    from dronecal_field.pipeline.sampling import SamplingOptions
    from dronecal_field.video.nal import video_frame_of

    burst = max(1, SamplingOptions().video_burst_frames)
    chosen: list = []
    left = 0
    for f in inside:
        if video_frame_of(f).keyframe:
            left = burst
        if left > 0:
            chosen.append(f)
            left -= 1
    if len(chosen) >= n:
        return chosen[:n]
    seen = {f.timestamp_ns for f in chosen}
    rest = [f for f in pick_frames(inside, start_ns, end_ns, n) if f.timestamp_ns not in seen]
    return sorted(chosen + rest[: n - len(chosen)], key=lambda f: f.timestamp_ns)


def _event_seq(event: RunEvent) -> int | None:
    seq = event.metadata.get("seq") or event.metadata.get("seq_to")
    try:
        return int(seq) if seq is not None else None
    except (TypeError, ValueError):
        return None


def _detections_only(dets: list) -> WaypointOutcome:
    """The legs' detections as one outcome, for the coverage only."""
    return WaypointOutcome(seq=-1, kind="leg", end_ns=0, frames=len(dets), detections=list(dets), point=None, problem=None)
