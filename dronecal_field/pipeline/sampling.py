"""Which frames to decode: never every frame of a long run.

Decoding and detecting are the offline stage's cost. Frames are read in one
streaming pass over the hover windows only, and of those this selector
decodes:

- a few evenly spaced frames inside each window, widened by the largest
  camera offset (the offset is not known yet), which give the points: up to
  ``max_frames_per_window``, but never further apart than ``max_period_s``
  (each GNSS fix is paired with the image track between frames, which must
  bracket it closely; a long hold costs more frames), and every frame inside
  a hold shorter than ``short_hold_s``; and
- every frame around a dozen transitions between consecutive windows, where
  the marker moves and the time alignment finds its signal. A transition is
  taken only once the window before it has shown the marker, so the frames
  spent there are not wasted on a hold the camera cannot see.

- every frame along each fly-through leg (widened by the same margin), up
  to ``leg_period_s`` apart: each fix on a leg is paired with the image track
  around it, so the track must be dense there.

For a ``/camera/video`` run (``video=True``) a frame costs a decode of every
access unit from the keyframe before it, so the choice follows the GOP
instead of the clock:

- in a window, where the marker is still, the keyframes and the frames of a
  short burst after each (``video_burst_frames``, decoded in sequence from
  the keyframe: a few access units each) instead of frames every
  ``max_period_s`` (each of which would decode most of its GOP); a hold
  whose settled part got no keyframe gets a burst in its middle, and a
  stream whose keyframes are further apart than ``video_max_period_s`` one
  that often (decoded from the keyframe: the cost such a GOP imposes);
  pairing then interpolates the hold's image track across the gaps between
  bursts (``PointOptions.pair_across_gaps``);
- on transitions, where the marker moves and only the time alignment needs
  it, a longer burst after each keyframe (``video_motion_burst_frames``) at
  the zone's period;
- legs keep their frames every ``leg_period_s``, so the decoder runs through
  every access unit of a leg: each fix there is paired with the cubic
  through four detections around it (pipeline.legs), which a burst brackets
  for one or two fixes of a GOP at a third of its cost, so whole GOPs are
  the cheapest per leg point.

Decisions use only what was already seen, so the pass stays single and the
memory bounded. Times are frame stamps (camera clock), ns.
"""

from __future__ import annotations

from dataclasses import dataclass

from dronecal_field.pipeline.hover import HoverWindow


@dataclass(frozen=True)
class SamplingOptions:
    """How many frames to spend where."""

    max_frames_per_window: int = 24
    max_period_s: float = 0.4  # ... but frames in a window at most this far apart
    short_hold_s: float = 2.0  # every frame inside a hold shorter than this (a sped-up simulator's 1 s hold)
    margin_s: float = 1.2  # each side of a window: covers a camera offset up to 1 s
    dense_s: float = 2.0  # decode every frame this long into each transition
    dense_period_s: float = 1.0 / 15.0  # but no faster than this (15 Hz resolves a 1 s offset to ms)
    max_transitions: int = 10
    leg_period_s: float = 0.25  # frames on a leg at most this often (every third frame at 10 fps: a smooth path, a cubic through 4)
    leg_max_gap_s: float = 0.35  # ... but never further apart than this (pipeline.legs.LegOptions.max_frame_gap_s: the cubic's span)
    # /camera/video: frames follow the keyframes (a frame costs the access units since its keyframe).
    video_bursts: bool = True  # False: the clock-spaced choice above, each frame decoded from its keyframe
    video_burst_frames: int = 3  # in a window: the keyframe and the next two (a still marker: detector noise averages)
    video_motion_burst_frames: int = 8  # on transitions: the keyframe and the next 7, at the zone's period (legs: every leg_period_s)
    video_max_period_s: float = 4.5  # a GOP longer than this still gets a burst this often (from its keyframe: a long GOP costs)
    video_settle_s: float = 1.0  # a hold's first second (PointOptions.settle_s): past its middle with no frame since, a burst anyway


LEG_PERIOD_SLACK = 0.2  # of a frame interval: a leg frame this much early is on time (stamps jitter about the rate; 25 fps keeps every 7th)


@dataclass
class _Zone:
    start_ns: int
    end_ns: int
    period_ns: int
    group: int
    dense: bool
    last_ns: int | None = None
    every_from_ns: int | None = None  # every frame in [every_from_ns, every_to_ns] (a short hold)
    every_to_ns: int | None = None
    leg: bool = False  # a fly-through leg: every fix needs the image track around it
    settled_ns: int | None = None  # a hold: its settled part starts here (camera clock, offset unknown) ...
    mid_ns: int | None = None  # ... and a video hold with no frame since then gets a burst from here

    def covers_every(self, t_ns: int) -> bool:
        return self.every_from_ns is not None and self.every_from_ns <= t_ns <= self.every_to_ns  # type: ignore[operator]


class FrameSelector:
    """Online decision, per frame stamp, whether to decode it (and its group for the jackknife).

    Use: pass :meth:`read_windows` to ``Run.iter_frames``; for each frame call
    :meth:`wants`; after detecting, call :meth:`record` with the outcome.
    """

    def __init__(
        self,
        windows: list[HoverWindow],
        options: SamplingOptions = SamplingOptions(),
        legs: list[tuple[int, int]] | None = None,
        video: bool = False,
    ) -> None:
        """``legs``: (start_ns, end_ns) of fly-through legs (GNSS clock); their groups follow the windows'.
        ``video``: the frames are a ``/camera/video`` stream; pass each frame's ``keyframe`` to :meth:`wants`."""
        self.options = options
        self.video = bool(video) and options.video_bursts
        self._burst_left = 0  # /camera/video: frames of the current keyframe's burst still to come
        self.windows = sorted(windows, key=lambda w: w.start_ns)
        self.legs = sorted((int(a), int(b)) for a, b in (legs or []))
        m = int(options.margin_s * 1e9)
        self._zones: list[_Zone] = []
        for k, w in enumerate(self.windows):
            a, b = w.start_ns - m, w.end_ns + m
            period = min(max(1, (b - a) // max(1, options.max_frames_per_window)), int(options.max_period_s * 1e9))
            zone = _Zone(a, b, int(period), group=k, dense=False)
            half = (w.end_ns - w.start_ns) // 2
            zone.settled_ns, zone.mid_ns = w.start_ns + min(int(options.video_settle_s * 1e9), half), w.start_ns + half
            if w.end_ns - w.start_ns < options.short_hold_s * 1e9:
                # The budget follows the frames the window has: a short hold's settled part holds a handful of
                # frames, and skipping any leaves it without the three detections a point needs.
                # The camera offset is not known yet (up to margin_s): the whole widened window.
                zone.every_from_ns, zone.every_to_ns = a, b
            self._zones.append(zone)
        leg_period = max(1, int(options.leg_period_s * 1e9))
        for k, (a, b) in enumerate(self.legs):
            self._zones.append(_Zone(a - m, b + m, leg_period, group=len(self.windows) + k, dense=True, leg=True))
        self._zones.sort(key=lambda z: z.start_ns)
        self._detected = [0] * len(self.windows)
        n_trans = max(0, len(self.windows) - 1)
        self._stride = max(1, -(-n_trans // max(1, options.max_transitions)))  # ceil
        self._next_allowed = 0
        self._decided: set[int] = set()
        self.transitions_taken: list[int] = []
        self.n_decoded = 0
        self._last_stamp_ns: int | None = None  # the frame before (decoded or not): the stream's frame interval

    def read_windows(self) -> list[tuple[int, int]]:
        """[start_ns, end_ns] frame-stamp ranges to read: every window with its margin and transitions."""
        m = int(self.options.margin_s * 1e9)
        d = int(self.options.dense_s * 1e9)
        out = []
        for k, w in enumerate(self.windows):
            out.append((w.start_ns - m - d, w.end_ns + m + d))
        for a, b in self.legs:
            out.append((a - m, b + m))
        return out

    def _transition_zones(self, k: int) -> list[_Zone]:
        """Dense zones of the transition after window k (to window k + 1)."""
        o = self.options
        m, d = int(o.margin_s * 1e9), int(o.dense_s * 1e9)
        period = max(1, int(o.dense_period_s * 1e9))
        a = self.windows[k].end_ns - m
        b = self.windows[k + 1].start_ns + m
        if b - a <= 2 * (d + m):
            return [_Zone(a, b, period, group=k, dense=True)]
        return [
            _Zone(a, self.windows[k].end_ns + d, period, group=k, dense=True),
            _Zone(self.windows[k + 1].start_ns - d, b, period, group=k, dense=True),
        ]

    def _maybe_take_transitions(self, t_ns: int) -> None:
        m = int(self.options.margin_s * 1e9)
        for k in range(len(self.windows) - 1):
            if k in self._decided or t_ns < self.windows[k].end_ns - m:
                continue
            self._decided.add(k)
            if len(self.transitions_taken) >= self.options.max_transitions or k < self._next_allowed:
                continue
            if self._detected[k] == 0:
                continue  # the camera did not see this hold: its transition shows nothing either
            self.transitions_taken.append(k)
            self._next_allowed = k + self._stride
            self._zones.extend(self._transition_zones(k))

    def wants(self, t_ns: int, keyframe: bool = False) -> tuple[bool, int | None]:
        """(decode?, group) for a frame stamped ``t_ns``; frames arrive in time order.

        ``keyframe``: the frame starts a GOP (a ``/camera/video`` run; ignored otherwise).
        """
        in_burst = False  # /camera/video: this frame follows a burst's keyframe (whatever zone it is in now)
        dt_ns = None if self._last_stamp_ns is None or t_ns <= self._last_stamp_ns else t_ns - self._last_stamp_ns
        self._last_stamp_ns = t_ns
        if self.video:
            in_burst = not keyframe and self._burst_left > 0
            self._burst_left = max(0, self._burst_left - 1) if not keyframe else 0  # a burst never runs into the next GOP
        self._maybe_take_transitions(t_ns)
        # Frames come in time order: zones that ended are done.
        self._zones = [z for z in self._zones if z.end_ns >= t_ns]
        best: _Zone | None = None
        every = False  # inside a short hold (with its margin): every frame, whichever zone claims it
        for z in self._zones:
            if z.start_ns <= t_ns <= z.end_ns:
                every = every or z.covers_every(t_ns)
                if z.dense:
                    best = z
                    break
                best = best or z
        if best is None:
            return False, None
        if self.video and not every and not best.leg:
            return self._wants_video(best, t_ns, keyframe, in_burst)
        # A leg takes a frame once it is within LEG_PERIOD_SLACK of a frame interval of its period: 'at least 0.25 s' on
        # an 8 fps stream whose stamps come 0.1249 s apart skipped every other pair to 0.375 s, past the 0.35 s the legs'
        # cubic may span (pipeline.legs): a wide camera's 31 s leg gave 10 pairs of its 101 detections.
        slack = int(LEG_PERIOD_SLACK * min(dt_ns, best.period_ns)) if best.leg and dt_ns is not None else 0
        if not every and best.last_ns is not None and t_ns - best.last_ns < best.period_ns - slack:
            # ... and a leg never skips a frame whose skipping leaves the next past that span: a 5 fps stream (0.2 s apart)
            # took every other frame, 0.4 s, and a 4K main run's 31 legs gave 27 pairs (its ground 42 px RMS)
            if not (best.leg and dt_ns is not None and t_ns + dt_ns - best.last_ns > int(self.options.leg_max_gap_s * 1e9)):
                return False, best.group
        best.last_ns = t_ns
        self.n_decoded += 1
        return True, best.group

    def _wants_video(self, zone: _Zone, t_ns: int, keyframe: bool, in_burst: bool) -> tuple[bool, int | None]:
        """The GOP-following choice: a keyframe starts a burst; a long GOP still gets one every video_max_period_s,
        and a hold whose settled part saw no frame one in its middle."""
        o = self.options
        if keyframe:
            self._burst_left = max(1, o.video_motion_burst_frames if zone.dense else o.video_burst_frames) - 1
            take = True
        elif in_burst:
            # Inside a burst the access units decode in sequence anyway; a moving zone's period thins what is detected.
            take = not zone.dense or zone.last_ns is None or t_ns - zone.last_ns >= zone.period_ns
        else:
            since = t_ns - (zone.last_ns if zone.last_ns is not None else zone.start_ns)
            take = since >= int(o.video_max_period_s * 1e9)
            if not take and zone.mid_ns is not None and t_ns >= zone.mid_ns:
                # A hold shorter than the GOP may have no keyframe in its settled part: a burst in its middle
                # (decoded from the keyframe before: at most one GOP), so it still gets its detections.
                take = zone.last_ns is None or zone.last_ns < zone.settled_ns  # type: ignore[operator]
            if take:
                self._burst_left = max(1, o.video_burst_frames) - 1 if not zone.dense else 0
        if not take:
            return False, zone.group
        zone.last_ns = t_ns
        self.n_decoded += 1
        return True, zone.group

    def record(self, group: int | None, detected: bool) -> None:
        """Feed back whether a decoded frame of ``group`` showed the marker."""
        if detected and group is not None and 0 <= group < len(self._detected):
            self._detected[group] += 1
