"""What the offline stage is told and what it returns: ``CalibrateOptions``, ``CalibrationReport`` and the
values the stages hand each other (``TrackRead``, ``Detections``, ``Solved``, ``Uncertainty``).

Frozen dataclasses, no behaviour beyond checking the options: the stages are in ``pipeline.track``,
``pipeline.frames``, ``pipeline.solve``, ``pipeline.confidence``; ``pipeline.run`` runs them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dronecal_field.errors import InputError
from dronecal_field.geodesy import EnuOrigin
from dronecal_field.pipeline.align import TimeOffset, Timing
from dronecal_field.pipeline.detect import Detection
from dronecal_field.pipeline.fixes import DistinctFixes
from dronecal_field.pipeline.hover import HoverWindow, TrackThresholds
from dronecal_field.pipeline.legs import Leg, LegOptions
from dronecal_field.pipeline.points import FIX_TYPES, FixNoise, PointOptions, WaypointPoint
from dronecal_field.pipeline.sampling import SamplingOptions


HOVER_SOURCES = ("auto", "events", "reached", "track")


LEG_SOURCES = ("auto", "events", "track", "none")


MIN_POINTS = 6


@dataclass(frozen=True)
class CalibrateOptions:
    """Everything ``dronecal-field calibrate`` can be told (see its --help)."""

    out_dir: Path | None = None
    min_fix: str = "rtk_fixed"
    model: str = "auto"
    loss: str = "huber"
    loss_scale_px: float = 2.0
    trials: int = 500
    seed: int = 0
    annotate: bool = False
    hover_source: str = "auto"
    leg_source: str = "auto"  # fly-through legs: "leg" events, else the GNSS track; "none": holds only
    max_offset_s: float = 1.0
    max_readout_s: float = 0.06  # rolling-shutter readouts searched (0: assume a global shutter)
    recentre: bool = True  # marker centres again under the first calibration's distortion
    points: PointOptions = field(default_factory=PointOptions)
    legs: LegOptions = field(default_factory=LegOptions)
    sampling: SamplingOptions = field(default_factory=SamplingOptions)
    track: TrackThresholds = field(default_factory=TrackThresholds)

    def __post_init__(self) -> None:
        if self.min_fix not in FIX_TYPES:
            raise InputError(f"--min-fix {self.min_fix!r} is not a fix type: use one of {', '.join(FIX_TYPES)}")
        if self.hover_source not in HOVER_SOURCES:
            raise InputError(f"--hover-source {self.hover_source!r}: use one of {', '.join(HOVER_SOURCES)}")
        if self.leg_source not in LEG_SOURCES:
            raise InputError(f"--leg-source {self.leg_source!r}: use one of {', '.join(LEG_SOURCES)}")
        if self.trials < 0 or self.trials == 1:
            raise InputError(f"--trials {self.trials}: use 0 to skip the Monte-Carlo, or at least 2 (the paper uses 500)")
        if not (math.isfinite(self.loss_scale_px) and self.loss_scale_px > 0):
            raise InputError(f"--loss-scale-px {self.loss_scale_px:g}: give the robust loss scale in pixels, e.g. 2")
        if not (math.isfinite(self.max_readout_s) and 0 <= self.max_readout_s <= 0.2):
            raise InputError(f"--max-readout-s {self.max_readout_s:g}: give a rolling-shutter readout of 0-0.2 s (0 for a global shutter)")
        if not (math.isfinite(self.points.settle_s) and self.points.settle_s >= 0):
            raise InputError(f"--settle-s {self.points.settle_s:g}: give the seconds left out at the start of each hold, 0 or more")
        if self.sampling.max_frames_per_window < 1:
            raise InputError(f"--max-frames-per-window {self.sampling.max_frames_per_window}: give at least 1 (24 is the default)")


@dataclass(frozen=True, eq=False)
class FrameStats:
    """What the detection pass saw."""

    frames_read: int
    frames_decoded: int
    frames_corrupt: int
    frames_with_marker: int
    other_ids: tuple[int, ...]
    transitions_dense: int
    formats: tuple[str, ...]
    video_units_decoded: int | None = None  # /camera/video: access units the decoder ran through (the real cost), None for images
    frames_from_live: int = 0  # of frames_decoded, those whose outcome came from fly's live pass (not decoded again)

    def to_dict(self) -> dict:
        return {
            "frames_read": self.frames_read,
            "frames_decoded": self.frames_decoded,
            "frames_corrupt_skipped": self.frames_corrupt,
            "frames_with_marker": self.frames_with_marker,
            "other_marker_ids_seen": list(self.other_ids),
            "transitions_decoded_densely": self.transitions_dense,
            "formats": list(self.formats),
            "video_units_decoded": self.video_units_decoded,
            "frames_from_live_pass": self.frames_from_live,
        }


@dataclass(frozen=True, eq=False)
class Track:
    """The run's GNSS track in the report's ENU frame (arrays, for plots and the report)."""

    t_ns: np.ndarray  # (N,) int64
    antenna_enu_m: np.ndarray  # (N, 3)
    marker_enu_m: np.ndarray  # (N, 3)
    sigma_enu_m: np.ndarray  # (N, 3) receiver-reported std
    fix_types: list[str | None]
    velocity_enu_mps: np.ndarray | None = None  # (N, 3) the marker's velocity at each fix


@dataclass(frozen=True, eq=False)
class CalibrationReport:
    """Everything the offline stage measured and decided (report.json is its ``to_dict``)."""

    run_path: Path
    truncated: bool
    run_warnings: list[str]
    metadata: object  # runfile.RunMetadata
    origin: EnuOrigin
    origin_source: str
    altitude_datum: str
    windows: list[HoverWindow]
    window_source: str
    frames: FrameStats
    detections: list[Detection]
    detection_groups: list[int]
    offset: TimeOffset
    points: list[WaypointPoint]
    attitude_source: str
    model_reason: str
    result: object  # core.calibrate.CalibrationResult
    monte_carlo: object | None  # core.uncertainty.UncertaintyResult
    linearised: object | None
    covariance_measured: np.ndarray
    maps: object  # maps.UncertaintyMaps
    homography: np.ndarray
    track: Track
    timings_s: dict[str, float]
    warnings: list[str]
    options: CalibrateOptions
    background: np.ndarray | None = field(default=None, repr=False)  # (H, W) a frame with the marker
    outputs: dict[str, str] = field(default_factory=dict)
    fixes_repeated: int = 0  # messages left out as repeats of the fix before (see ``fix_identity``)
    centres: str = "diagonals' crossing"  # how marker centres were taken (report.json "points")
    legs: list[Leg] = field(default_factory=list)
    leg_source: str = "none"
    timing: Timing | None = None  # offset and rolling shutter refined through the calibrated camera
    fix_identity: DistinctFixes | None = None  # how fixes were told apart (rule, counts)
    gnss_latency_s: float | None = None  # subtracted from arrival-stamped fixes (metadata gnss.latency_s)
    validity: object | None = None  # the region of validity (filled by the uncertainty stage when available)
    noise: FixNoise | None = None  # the per-fix noise measured on the residuals (sets the points' sigmas)
    sigma_scale: float = 1.0  # the points' sigmas were scaled by this for every uncertainty figure (see sigma_scale)
    agreement: object | None = None  # agreement.Agreement: whether the legs agreed with the holds, what was left out
    notices: list[str] = field(default_factory=list)  # what the first printed line must name: sets left out, a flight not as planned

    @property
    def hover_points(self) -> list[WaypointPoint]:
        return [p for p in self.points if p.window.source != "leg"]

    @property
    def leg_points(self) -> list[WaypointPoint]:
        return [p for p in self.points if p.window.source == "leg"]

    @property
    def camera(self):
        return self.result.camera

    @property
    def used_points(self) -> list[WaypointPoint]:
        return [p for p in self.points if p.used]


@dataclass(frozen=True, eq=False)
class TrackRead:
    """What the read-track stage returns: the usable fixes, the ENU frame, the marker's track."""

    track: Track
    identity: DistinctFixes
    gnss_latency_s: float | None
    origin: EnuOrigin
    origin_source: str
    attitude: tuple  # (att_t_ns (K,), att_rpy_rad (K, 3)) or (None, None)
    attitude_source: str
    offset_frd_m: np.ndarray  # (3,)
    holds: dict[int, float] | None
    warnings: list[str]
    plan_roi: object | None = None  # validity.PlanRoi of the plan.json attached to the run, in this ENU frame
    planned_speed_mps: float | None = None  # the mission.plan's DO_CHANGE_SPEED (the slowest, where it changes)
    vehicle_clock_rate: float = 1.0  # vehicle seconds per run second (a sped-up simulator's; 1 for a real vehicle)


@dataclass(frozen=True, eq=False)
class Detections:
    """What the detection stage returns (arrays over the M detections, camera clock)."""

    items: list[Detection]
    groups: list[int]
    t_ns: np.ndarray  # (M,) int64
    uv_px: np.ndarray  # (M, 2)
    size_px: np.ndarray  # (M,)
    stats: FrameStats
    size_mismatch: bool
    background: np.ndarray | None


@dataclass(frozen=True, eq=False)
class Solved:
    """What the points-and-solve stage returns."""

    points: list[WaypointPoint]
    result: object  # core.calibrate.CalibrationResult
    model_reason: str
    track: Track  # with the marker track finally used (lever arm)
    attitude_source: str
    centres: str
    timing: Timing
    warnings: list[str]
    noise: FixNoise | None = None
    legs: list[Leg] | None = None  # the legs paired (None: all found); a leg that disagreed with the holds is not
    agreement: object | None = None  # agreement.Agreement: the holds against each leg


@dataclass(frozen=True, eq=False)
class Uncertainty:
    """What the uncertainty stage returns."""

    monte_carlo: object | None
    linearised: object | None
    covariance: np.ndarray
    maps: object
    homography: np.ndarray
    validity: object | None = None
    sigma_scale: float = 1.0
