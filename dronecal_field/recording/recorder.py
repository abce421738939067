"""Record a run: MAVLink telemetry and video into one MCAP (plus a .tlog), without losing GNSS.

Threads and queues::

    link reader thread --(every message, host-stamped)--> .tlog (both directions)
                       \\-> telemetry queue (unbounded: small, never dropped) --\\
    video thread per camera --> frame queue (bounded: a slow disk drops frames) --> writer thread -> RunWriter
    monitor thread (2 Hz): link loss / restore events, marker probe (one camera a probe)

Each camera is a :class:`~dronecal_field.recording.feed.CameraFeed` on its own
clock: a single-camera run has one (``/camera/...``), a several-camera run one
per ``--video NAME=URL`` (``/cameras/<name>/...``, events naming the camera).

The writer thread always drains the telemetry queue before taking the next
frame, so a slow disk costs frames (counted) and never fixes, and memory is
bounded by the frame queue.

Recording starts clean: a live source's queue filled up while nobody read it
(pre-flight, mission upload), so at the start the frames that arrived before
it are discarded (counted apart, not as drops) and the source's drop counter
is taken as the zero: ``dropped`` counts only frames lost while recording.

Every timestamp is the host's UTC clock at arrival (the run clock); frames
too, hence ``camera.latency_s`` in the metadata. GNSS fixes are the
exception the contract asks for: ``/gnss/fix`` is stamped at the fix's own
measurement time, ``GPS_RAW_INT.time_usec`` mapped onto the run clock
(:class:`FixClock`), and written once per fix (a new ``time_usec``) however
often the telemetry stream repeats it; ``/mavlink/GPS_RAW_INT`` keeps every
message as it arrived.

Events on ``/events``: ``hover`` (the hold that ends with each
MISSION_ITEM_REACHED: ArduCopter reports at the end of a hold), ``leg`` (from
one waypoint reached to the next when the drone flies through at least one of
them: hold 0), ``video_gap``,
``link_lost`` (with its duration) and ``link_restored``.

An optional ``observer`` (:class:`RecordingObserver`, e.g. the live
calibration's tap) sees every frame as it arrives and every fix and event as
it is written; its calls must return at once (it queues, never waits), and
an observer that raises is switched off rather than stopping the recording.
"""

from __future__ import annotations

import collections
import queue
import threading
import time
from dataclasses import dataclass
from typing import Any, Protocol

from dronecal_field.errors import RecordingStoppedError
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import px4
from dronecal_field.mavlink.control import vehicle_state
from dronecal_field.mavlink.link import MavLink
from dronecal_field.mavlink.missionfile import CMD_NAV_WAYPOINT, Mission
from dronecal_field.recording.feed import CameraFeed, CameraReport
from dronecal_field.recording.marker_check import MarkerCheck
from dronecal_field.recording.status import (
    ClockJumpMonitor,
    RecorderStatus,
    VehicleClock,
    attitude_from_mavlink,
    fix_from_gps_raw,
    hover_event,
    remaining_s,
)
from dronecal_field.runfile.records import Frame, RunEvent

# The marker probe takes an RTSP source's keyframe-check picture (every 5 s) while it is this close to the
# latest keyframe, instead of decoding that keyframe again: "marker yes/no" then follows the check's pace.
CHECKED_FRESH_NS = 6_000_000_000


class RecordingObserver(Protocol):
    """What the recorder tells a live consumer; every call must return at once (queue, never wait)."""

    def on_frame(self, frame: Frame) -> None:
        """A frame arrived (video thread), before it is queued for the disk."""

    def on_record(self, record: Any) -> None:
        """A GnssFix, Attitude or RunEvent was written (writer thread)."""


class FixClock:
    """Maps ``GPS_RAW_INT.time_usec`` (the fix's measurement time) onto the run clock.

    ``time_usec`` is boot time on ArduPilot (real ArduCopter 4.7: about 104 ms
    older than the message carrying it) or Unix time on other autopilots.
    Boot time maps through the pairs (host arrival, ``time_boot_ms``) of the
    vehicle's messages: ``host = c + boot / rate`` with ``c`` the smallest
    ``host - boot / rate`` over the last ``window`` pairs (arrival delays are
    never negative, so the minimum is the link's latency floor, as TIMESYNC
    takes it). Unix time goes to boot time through SYSTEM_TIME first. A fix
    time that cannot be mapped, or lands after its message's arrival or more
    than ``max_age_s`` before it, falls back to the arrival.
    """

    def __init__(self, window: int = 64, max_age_s: float = 2.0) -> None:
        self._pairs: collections.deque[tuple[int, int]] = collections.deque(maxlen=window)  # (host ns, boot ns)
        self._unix_minus_boot_ns: int | None = None
        self.max_age_ns = int(max_age_s * 1e9)
        self.mapped = 0
        self.fallbacks = 0

    def observe(self, host_ns: int, boot_ms: int) -> None:
        """One vehicle message's (host UTC ns at arrival, time_boot_ms), in arrival order."""
        if self._pairs and boot_ms * 1_000_000 < self._pairs[-1][1] - 1_000_000_000:
            self._pairs.clear()  # the vehicle rebooted
        self._pairs.append((int(host_ns), int(boot_ms) * 1_000_000))

    def observe_system_time(self, time_unix_usec: int, time_boot_ms: int) -> None:
        """SYSTEM_TIME: the vehicle's Unix clock against its boot clock."""
        if time_unix_usec > 0:
            self._unix_minus_boot_ns = int(time_unix_usec) * 1000 - int(time_boot_ms) * 1_000_000

    def to_run_ns(self, time_usec: int, arrival_ns: int, rate: float = 1.0) -> int:
        """Run-clock ns of a fix measured at ``time_usec``, carried by a message that arrived at ``arrival_ns``."""
        boot_ns = None
        if time_usec >= 1_000_000_000_000_000:  # microseconds since 1970, i.e. after 2001-09
            if self._unix_minus_boot_ns is not None:
                boot_ns = int(time_usec) * 1000 - self._unix_minus_boot_ns
        elif time_usec > 0:
            boot_ns = int(time_usec) * 1000
        if boot_ns is None or not self._pairs:
            self.fallbacks += 1
            return int(arrival_ns)
        rate = rate if rate > 0 else 1.0
        c = min(h - b / rate for h, b in self._pairs)
        t = int(round(c + boot_ns / rate))
        if t > arrival_ns or arrival_ns - t > self.max_age_ns:
            self.fallbacks += 1
            return int(arrival_ns)
        self.mapped += 1
        return t


@dataclass(frozen=True)
class RecordingReport:
    """What was recorded.

    Attributes
    ----------
    frames_written : int
        Frames in ``/camera/image``.
    frames_dropped : int
        Frames the recorder dropped because the disk was slow.
    frames_dropped_source : int
        Frames the video source dropped, after the start, because the recorder was slow to read.
    frames_discarded_at_start : int
        Frames that arrived before the start (queued while nobody read the
        source), discarded rather than recorded; not drops.
    fixes_written : int
        Records in ``/gnss/fix``.
    fixes_without_position : int
        GPS_RAW_INT without a usable position (no fix, or no height in the run's datum).
    mavlink_messages : int
        Messages on ``/mavlink/*``.
    attitudes : int
        Records in ``/vehicle/attitude``.
    hover_events, video_gaps, link_losses : int
        Events written.
    duration_s : float
        Wall seconds recorded.
    clock_rate : float
        Vehicle seconds per host second (1 for a real vehicle).
    fixes_repeated : int
        GPS_RAW_INT messages that repeated the fix before (same ``time_usec``): not written again.
    fixes_at_arrival : int
        Fixes whose ``time_usec`` could not be mapped onto the run clock: stamped at arrival.
    leg_events : int
        ``leg`` events written.
    """

    frames_written: int
    frames_dropped: int
    frames_dropped_source: int
    frames_discarded_at_start: int
    fixes_written: int
    fixes_without_position: int
    mavlink_messages: int
    attitudes: int
    hover_events: int
    video_gaps: int
    link_losses: int
    duration_s: float
    clock_rate: float
    fixes_repeated: int = 0
    fixes_at_arrival: int = 0
    leg_events: int = 0
    video_lag_events: int = 0
    video_max_lag_s: float = 0.0
    frames_lost_stream: int = 0
    packets_corrupt: int = 0
    stopped: str | None = None
    frames_not_recorded: int = 0
    telemetry_not_recorded: int = 0
    cameras: tuple[CameraReport, ...] = ()  # each named camera of a several-camera run; () for a single camera

    def summary(self) -> str:
        """One line for the operator."""
        cut = ""
        if self.stopped is not None:
            cut = (f"RECORDING STOPPED EARLY ({self.stopped}); after it {self.frames_not_recorded} frames and "
                   f"{self.telemetry_not_recorded} telemetry records were not recorded; before it: ")
        return cut + (
            f"{self.frames_written} frames ({self.frames_dropped + self.frames_dropped_source} dropped), {self.fixes_written} GNSS fixes"
            + (f" ({self.fixes_repeated} repeats in the stream not written again)" if self.fixes_repeated else "")
            + f", {self.mavlink_messages} MAVLink messages, {self.hover_events} hover windows, {self.leg_events} legs, {self.video_gaps} video gaps, "
            f"{self.link_losses} link losses in {self.duration_s:.1f} s"
            + (f" ({self.frames_discarded_at_start} frames from before the start not recorded)" if self.frames_discarded_at_start else "")
            + (
                f"; VIDEO FELL BEHIND {self.video_lag_events} times (up to {self.video_max_lag_s:.2f} s), "
                f"{self.frames_lost_stream} frames lost in the stream, {self.packets_corrupt} corrupt packets"
                if self.video_lag_events or self.frames_lost_stream or self.packets_corrupt
                else ""
            )
            + ("; cameras: " + ", ".join(c.summary() for c in self.cameras) if self.cameras else "")
        )


class Recorder:
    """Record telemetry and video into an open RunWriter (and TlogWriter).

    Parameters
    ----------
    link : MavLink
        Open link to the vehicle.
    video : VideoSource
        Open video source (``read``, ``reopen``, ``frames_dropped``).
    writer : RunWriter
        Open run writer; the recorder writes and finally closes it.
    tlog : TlogWriter or None
        Telemetry log beside the run; closed at the end.
    mission : Mission
        The mission flown (hover windows, progress).
    altitude_datum : str
        ``ellipsoid`` or ``msl``: the run's datum for ``/gnss/fix`` heights.
    marker_check : MarkerCheck or None
        The once-a-second marker probe.
    first_frame : Frame or None
        A frame already read (to size the image); recorded first unless a
        live source's frame arrived before ``start_ns``.
    frame_queue_size : int
        Frames buffered for the disk; beyond that frames are dropped.
    link_timeout_s : float
        Seconds without telemetry before a ``link_lost`` event.
    video_timeout_s : float
        Seconds without a frame before a video gap starts and the source is reopened.
    clock : VehicleClock or None
        A vehicle clock already fed since the link opened (sharper hover windows
        early in the flight); the recorder keeps feeding it.
    start_ns : int or None
        UTC ns when recording starts (what the run's metadata says); frames of
        a live source that arrived before it are not recorded. Default: the
        moment :meth:`start` is called.
    observer : RecordingObserver or None
        Told of every frame, fix, attitude and event (the live calibration).
    feeds : list of CameraFeed or None
        The cameras of a several-camera run (each named, with its own source,
        first frame and frame observer); ``video``, ``first_frame`` and the
        observer's ``on_frame`` are then unused. None: one camera, ``video``.
    """

    def __init__(
        self,
        link: MavLink,
        video: Any,
        writer: Any,
        tlog: Any | None,
        mission: Mission,
        *,
        altitude_datum: str = "ellipsoid",
        marker_check: MarkerCheck | None = None,
        first_frame: Frame | None = None,
        frame_queue_size: int = 64,
        link_timeout_s: float = 3.0,
        video_timeout_s: float = 2.0,
        clock: VehicleClock | None = None,
        start_ns: int | None = None,
        observer: RecordingObserver | None = None,
        feeds: list[CameraFeed] | None = None,
    ) -> None:
        self.link = link
        self.observer = observer
        self.observer_errors = 0
        if feeds:
            names = [f.name for f in feeds]
            if None in names or len(set(names)) != len(names):
                raise ValueError(f"several cameras need distinct names, got {names}")
            self.feeds = list(feeds)
        else:
            self.feeds = [CameraFeed(None, video, first_frame, observer=observer, video_timeout_s=video_timeout_s)]
        self.video = self.feeds[0].video
        self.writer = writer
        self.tlog = tlog
        self.mission = mission
        self.altitude_datum = altitude_datum
        self.marker_check = marker_check
        self.link_timeout_s = link_timeout_s
        self.video_timeout_s = video_timeout_s
        self.clock = clock or VehicleClock()
        self._telemetry: queue.SimpleQueue[tuple] = queue.SimpleQueue()
        # (feed, frame); the bound grows with the cameras so that each keeps about frame_queue_size
        self._frames: queue.Queue[tuple[CameraFeed, Frame]] = queue.Queue(maxsize=max(1, frame_queue_size) * len(self.feeds))
        self._stop = threading.Event()
        self._writer_done = threading.Event()
        self._threads: list[threading.Thread] = []
        self._start_ns = start_ns
        self.started_ns = 0
        self._started_mono = 0.0
        self._link_lost_ns: int | None = None
        self._write_error: BaseException | None = None
        self.stopped: str | None = None  # the run file stopped taking data (a full disk): why
        self.frames_not_recorded = 0
        self.telemetry_not_recorded = 0
        # counters (written by one thread each, read by anyone); the frames' are the feeds'
        self.fixes_written = 0
        self.fixes_without_position = 0
        self.fixes_repeated = 0  # GPS_RAW_INT messages repeating the fix before (same time_usec): not written again
        self.fix_clock = FixClock()
        self.clock_jumps = ClockJumpMonitor()
        self.clock_jump_events = 0
        self._last_fix_usec: int | None = None
        self._last_nav: tuple[int, int] | None = None  # (seq, host ns) of the last NAV_WAYPOINT reached
        self.leg_events = 0
        self.mavlink_messages = 0
        self.attitudes = 0
        self.hover_events = 0
        self.link_losses = 0
        # vehicle progress, for the status line and the end of the mission
        self.reached: list[tuple[int, int]] = []  # (host ns, seq)
        # PX4 numbers from 0 without home and repeats MISSION_ITEM_REACHED for ~10 s: one report per file seq
        self._px4_reached = px4.ReachedFilter() if getattr(link, "is_px4", False) else None
        self.current_seq = 0
        self.armed = False
        self.was_armed = False
        self.max_rel_alt_m = 0.0
        self.airborne_then_disarmed = False

    # ----- the feeds' counts, summed (a single camera: its own) -----
    def _sum(self, attr: str) -> int:
        return sum(int(getattr(f, attr)) for f in self.feeds)

    @property
    def frames_written(self) -> int:
        return self._sum("frames_written")

    @property
    def frames_dropped(self) -> int:
        return self._sum("frames_dropped")

    @property
    def frames_discarded_at_start(self) -> int:
        return self._sum("frames_discarded_at_start")

    @property
    def video_gaps(self) -> int:
        return self._sum("video_gaps")

    @property
    def frames_lost_stream(self) -> int:
        return self._sum("frames_lost_stream")

    @property
    def packets_corrupt(self) -> int:
        return self._sum("packets_corrupt")

    @property
    def marker_seen(self) -> bool | None:
        """The marker in any camera's last probed frame (None: none probed yet)."""
        seen = [f.marker_seen for f in self.feeds if f.marker_seen is not None]
        return any(seen) if seen else None

    # ----- lifecycle -----
    def start(self) -> Recorder:
        """Start recording (threads), after discarding the frames that arrived before the start."""
        self._started_mono = time.monotonic()
        self.started_ns = self._start_ns if self._start_ns is not None else time.time_ns()
        for feed in self.feeds:
            fresh = feed.discard_stale(self.started_ns)
            if fresh is not None:
                self._offer_frame(feed, fresh)
        self.link.add_listener(self._on_message)
        self._start_thread(self._writer_loop, "recorder-writer")
        for feed in self.feeds:
            name = "recorder-video" if feed.name is None else f"recorder-video-{feed.name}"
            self._start_thread(lambda feed=feed: feed.run(self._stop, self._offer_frame, self._event), name)
        self._start_thread(self._monitor_loop, "recorder-monitor")
        return self

    def _start_thread(self, target: Any, name: str) -> None:
        thread = threading.Thread(target=target, name=name, daemon=True)
        thread.start()
        self._threads.append(thread)

    @property
    def frames_dropped_source(self) -> int:
        """Frames the video sources dropped since the start (they were not read fast enough)."""
        return self._sum("frames_dropped_source")

    def stop(self) -> RecordingReport:
        """Stop, write what is queued, close open events, close the files. Commands nothing."""
        self._stop.set()
        self.link.remove_listener(self._on_message)
        for thread in self._threads:
            if thread.name != "recorder-writer":
                thread.join(timeout=5.0)
        now_ns = time.time_ns()
        for feed in self.feeds:
            if (gap := feed.close_gap(now_ns)) is not None:
                self._event(gap)
        if self._link_lost_ns is not None:
            self._event(RunEvent(self._link_lost_ns, now_ns - self._link_lost_ns, "link_lost", {"open": "true"}))
            self.link_losses += 1
        self._telemetry.put(("end",))
        for thread in self._threads:
            if thread.name == "recorder-writer":
                thread.join(timeout=60.0)
        try:
            self.writer.close()
        finally:
            if self.tlog is not None:
                self.tlog.close()
        self.stopped = self.stopped or getattr(self.writer, "failure", None)
        if self._write_error is not None:
            raise self._write_error
        return RecordingReport(
            stopped=self.stopped,
            frames_not_recorded=self.frames_not_recorded,
            telemetry_not_recorded=self.telemetry_not_recorded,
            frames_written=self.frames_written,
            frames_dropped=self.frames_dropped,
            frames_dropped_source=self.frames_dropped_source,
            frames_discarded_at_start=self.frames_discarded_at_start,
            fixes_written=self.fixes_written,
            fixes_without_position=self.fixes_without_position,
            mavlink_messages=self.mavlink_messages,
            attitudes=self.attitudes,
            hover_events=self.hover_events,
            video_gaps=self.video_gaps,
            link_losses=self.link_losses,
            duration_s=time.monotonic() - self._started_mono,
            clock_rate=self.clock.rate,
            fixes_repeated=self.fixes_repeated,
            fixes_at_arrival=self.fix_clock.fallbacks,
            leg_events=self.leg_events,
            video_lag_events=self._sum("video_lag_events"),
            video_max_lag_s=max(f.video_max_lag_s for f in self.feeds),
            frames_lost_stream=self.frames_lost_stream,
            packets_corrupt=self.packets_corrupt,
            cameras=tuple(f.report() for f in self.feeds if f.name is not None),
        )

    # ----- link reader thread -----
    def _on_message(self, direction: str, stamp_ns: int, msg: Any) -> None:
        if self.tlog is not None:
            try:
                self.tlog.write(msg.get_msgbuf(), stamp_ns // 1000)
            except Exception as exc:  # noqa: BLE001 - a full disk must not kill the link thread
                self._write_error = self._write_error or exc
        if direction != "in":
            return
        mtype = msg.get_type()
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None and msg.get_srcSystem() == self.link.target_system:
            self.clock.update(stamp_ns, int(boot_ms))  # on the reader thread: in arrival order
            jump = self.clock_jumps.observe(stamp_ns, int(boot_ms), self.clock.rate)
            if jump is not None:
                self.clock_jump_events += 1
                self._event(RunEvent(jump[0], 0, "clock_jump", {"jump_s": f"{jump[1]:+.3f}"}))
        reached: list[int] = []
        if mtype == "MISSION_ITEM_REACHED":
            reached = [int(msg.seq)] if self._px4_reached is None else self._px4_reached.feed(int(msg.seq))
            self.reached.extend((stamp_ns, seq) for seq in reached)
        elif mtype == "MISSION_CURRENT":
            self.current_seq = int(msg.seq) + (0 if self._px4_reached is None else px4.SEQ_OFFSET)
        elif mtype == "GLOBAL_POSITION_INT":
            self.max_rel_alt_m = max(self.max_rel_alt_m, msg.relative_alt / 1000.0)
        elif mtype == "HEARTBEAT" and msg.get_srcSystem() == self.link.target_system and msg.type != ap.MAV_TYPE_GCS:
            armed = bool(msg.base_mode & ap.MAV_MODE_FLAG_SAFETY_ARMED)
            if armed:
                self.was_armed = True
            elif self.armed and self.max_rel_alt_m > 0.5:
                self.airborne_then_disarmed = True
            self.armed = armed
        self._telemetry.put(("msg", stamp_ns, msg))
        for seq in reached:  # in the mission file's numbering
            self._telemetry.put(("reached", stamp_ns, seq))

    # ----- writer thread -----
    def _event(self, event: RunEvent) -> None:
        self._telemetry.put(("event", event))

    def _write_telemetry(self, item: tuple) -> None:
        kind = item[0]
        if kind == "event":
            self.writer.write_event(item[1])
            self._observe(item[1])
            return
        if kind == "reached":
            self._write_reached(item[2], item[1])
            return
        _kind, stamp_ns, msg = item
        mtype = msg.get_type()
        fields = msg.to_dict()
        self.writer.write_mavlink(mtype, stamp_ns, fields)
        self.mavlink_messages += 1
        from_vehicle = msg.get_srcSystem() == self.link.target_system
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None and from_vehicle:
            self.fix_clock.observe(stamp_ns, int(boot_ms))
        if mtype == "SYSTEM_TIME" and from_vehicle:
            self.fix_clock.observe_system_time(int(msg.time_unix_usec), int(msg.time_boot_ms))
        if mtype == "GPS_RAW_INT":
            self._write_fix(msg, stamp_ns)
        elif mtype == "ATTITUDE":
            attitude = attitude_from_mavlink(msg, stamp_ns)
            self.writer.write_attitude(attitude)
            self.attitudes += 1
            self._observe(attitude)

    def _write_reached(self, seq: int, stamp_ns: int) -> None:
        """The hover and leg events of mission item ``seq`` (file numbering) reached at ``stamp_ns``."""
        event = hover_event(self.mission, seq, stamp_ns, self.clock.rate)
        if event is not None:
            self.writer.write_event(event)
            self.hover_events += 1
            self._observe(event)
        leg = self._leg_event(seq, stamp_ns)
        if leg is not None:
            self.writer.write_event(leg)
            self.leg_events += 1
            self._observe(leg)

    def _write_fix(self, msg: Any, arrival_ns: int) -> None:
        """One ``/gnss/fix`` per new fix (time_usec), stamped at the fix's own time on the run clock."""
        usec = int(getattr(msg, "time_usec", 0) or 0)
        if usec > 0 and usec == self._last_fix_usec:
            self.fixes_repeated += 1  # the stream is faster than the receiver: the same fix again
            return
        fix = fix_from_gps_raw(msg, self.fix_clock.to_run_ns(usec, arrival_ns, self.clock.rate), self.altitude_datum)
        if fix is None:
            self.fixes_without_position += 1
            return
        self._last_fix_usec = usec if usec > 0 else None
        self.writer.write_fix(fix)
        self.fixes_written += 1
        self._observe(fix)

    def _observe(self, record: Any) -> None:
        """Hand a written record to the observer; one that fails is switched off (the recording goes on)."""
        if self.observer is None:
            return
        try:
            self.observer.on_record(record)
        except Exception:  # noqa: BLE001 - a live view must never cost the recording
            self.observer_errors += 1
            self.observer = None

    def _leg_event(self, seq: int, reached_ns: int) -> RunEvent | None:
        """The leg that ends at NAV_WAYPOINT ``seq``: from the previous NAV_WAYPOINT reached, when the
        drone flew through at least one end (hold 0) and the two are consecutive in the mission."""
        items = self.mission.items
        if not 0 <= seq < len(items) or items[seq].command != CMD_NAV_WAYPOINT:
            return None
        last, self._last_nav = self._last_nav, (seq, int(reached_ns))
        if last is None or last[0] >= seq:
            return None
        between = [it for it in items[last[0] + 1 : seq] if it.command == CMD_NAV_WAYPOINT]
        if between or (items[last[0]].hold_s > 0 and items[seq].hold_s > 0):
            return None
        # ArduCopter reports the end of a hold: the leg starts when the previous one was reported.
        # ... and a hold at its end is reported when it ends: the leg ends that hold earlier.
        end_ns = int(reached_ns) - int(round(items[seq].hold_s / max(self.clock.rate, 1e-6) * 1e9))
        if end_ns <= last[1]:
            return None
        meta = {"seq_from": str(last[0]), "seq_to": str(seq), "vehicle_clock_rate": repr(float(self.clock.rate))}
        return RunEvent(timestamp_ns=last[1], duration_ns=end_ns - last[1], type="leg", metadata=meta)

    def _writer_loop(self) -> None:
        ending = False
        while True:
            try:
                while True:  # telemetry first: never lose GNSS to a slow disk
                    try:
                        item = self._telemetry.get_nowait()
                    except queue.Empty:
                        break
                    if item[0] == "end":
                        ending = True
                        continue
                    if self.stopped is not None:
                        self.telemetry_not_recorded += 1
                        continue
                    try:
                        self._write_telemetry(item)
                    except RecordingStoppedError as exc:
                        self.stopped = str(exc)
                        self.telemetry_not_recorded += 1
                try:
                    feed, frame = self._frames.get(timeout=0.02)
                except queue.Empty:
                    if ending:
                        return
                    continue
                if self.stopped is not None:
                    self.frames_not_recorded += 1  # drained, so the video threads never block
                    continue
                try:
                    if feed.name is None:
                        self.writer.write_frame(frame)
                    else:
                        self.writer.write_frame(frame, feed.name)
                except RecordingStoppedError as exc:
                    self.stopped = str(exc)  # the status line turns red at once; the file is cut at its last whole chunk
                    self.frames_not_recorded += 1
                    continue
                feed.frames_written += 1
            except Exception as exc:  # noqa: BLE001 - reported by stop(); keep draining so nothing blocks
                self._write_error = self._write_error or exc
                if ending:
                    return

    # ----- video threads (CameraFeed.run) -----
    def _offer_frame(self, feed: CameraFeed, frame: Frame) -> None:
        try:
            self._frames.put_nowait((feed, frame))
        except queue.Full:
            feed.frames_dropped += 1  # a slow disk costs frames, never memory

    @property
    def video_lag_s(self) -> float | None:
        """How far the recorder lags the stream's own clock now, seconds (the most behind H.264/H.265 camera); None otherwise."""
        lags = [lag for f in self.feeds if (lag := f.video_lag_s) is not None]
        return max(lags) if lags else None

    # ----- monitor thread -----
    def _monitor_loop(self) -> None:
        # The marker probe decodes one frame, within MarkerCheck's CPU budget (one probe a second at most, fewer
        # when a probe is dear: a 4K H.265 keyframe); with several cameras one camera a probe, in turn.
        probe_every_s = 1.0 if len(self.feeds) == 1 else 0.5
        if self.marker_check is not None:
            self.marker_check.min_period_s = min(self.marker_check.min_period_s, probe_every_s)
        turn = 0
        while not self._stop.wait(0.5):
            silent_s = self.link.seconds_since_receive()
            if self._link_lost_ns is None and silent_s > self.link_timeout_s:
                self._link_lost_ns = time.time_ns() - int(silent_s * 1e9)
            elif self._link_lost_ns is not None and silent_s < 1.0:
                lost = self._link_lost_ns
                self._link_lost_ns = None
                now_ns = time.time_ns()
                meta = {"reconnects": str(self.link.reconnects)}
                self._event(RunEvent(lost, now_ns - lost, "link_lost", meta))
                self._event(RunEvent(now_ns, 0, "link_restored", meta))
                self.link_losses += 1
            now = time.monotonic() + 0.05  # the tick's own jitter
            if self.marker_check is None or not self.marker_check.due(now):
                continue
            feed = self.feeds[turn % len(self.feeds)]
            turn += 1
            frame = feed.latest_keyframe
            if frame is None:
                continue
            image = None
            checked = getattr(feed.video, "last_checked", None)  # an RTSP source's keyframe check decoded this picture
            if checked is not None and frame.timestamp_ns - checked[0].timestamp_ns < CHECKED_FRESH_NS:
                frame, image = checked  # the probe then only detects: a 4K H.265 keyframe decode is ~130 ms of CPU
            try:
                seen = self.marker_check.probe(frame, key=id(feed), now=now, image=image)
            except Exception:  # noqa: BLE001 - the probe is cosmetic; never stop recording for it
                feed.marker_seen = None
                self.marker_check.next_due = now + 1.0
                continue
            if seen is not None:
                feed.marker_seen = seen

    # ----- status -----
    @property
    def link_ok(self) -> bool:
        return self._link_lost_ns is None and self.link.seconds_since_receive() < self.link_timeout_s

    @property
    def video_ok(self) -> bool:
        """Every camera's frames arriving."""
        return all(f.video_ok for f in self.feeds)

    def status(self) -> RecorderStatus:
        """A snapshot for the live status line."""
        now = time.monotonic()
        cameras = tuple(f.status(now) for f in self.feeds)
        waypoints = [item.seq for item in self.mission.items if item.command == CMD_NAV_WAYPOINT and item.seq > 0]
        done = sum(1 for seq in waypoints if seq < self.current_seq)
        current = min(len(waypoints), done + 1) if self.current_seq > 0 else 0
        gps = self.link.latest("GPS_RAW_INT")
        state = vehicle_state(self.link)
        gpi = self.link.latest("GLOBAL_POSITION_INT")
        position = None if gpi is None or gpi.lat == 0 else (gpi.lat * 1e-7, gpi.lon * 1e-7, gpi.relative_alt / 1000.0)
        left = None
        if self.current_seq > 0:
            left = remaining_s(self.mission, self.current_seq, position) / self.clock.rate
        return RecorderStatus(
            waypoint=current,
            waypoints=len(waypoints),
            mode="?" if state is None else state.mode_name,
            armed=bool(state and state.armed),
            fix="none" if gps is None else ap.FIX_TYPE_NAMES.get(int(gps.fix_type), "no_fix"),
            satellites=0 if gps is None else int(gps.satellites_visible),
            fps=sum(c.fps for c in cameras),
            frames=sum(c.frames for c in cameras),
            dropped=sum(c.dropped for c in cameras),
            marker_seen=self.marker_seen,
            link_ok=self.link_ok,
            video_ok=all(c.video_ok for c in cameras),
            elapsed_s=now - self._started_mono,
            remaining_s=left,
            video_lag_s=self.video_lag_s,
            video_lagging=any(c.video_lagging for c in cameras),
            video_lost=sum(c.video_lost for c in cameras),
            recording_stopped=self.stopped,
            cameras=cameras if self.feeds[0].name is not None else (),
        )
