"""The ground 15 m out as calibrate reports it, honest where the lens is extrapolated (issue 20).

The uncertainty engine's "at 15 m" figures (``core.uncertainty.ground_probe``:
ONE ground point, 15 m from the pole on the camera's heading) hold the
parameters' covariance and the next richer model's excess covariance and
bias. Where that point lies outside the region of validity the lean model is
extrapolated there, and its error is the model's, not the noise's: the
region's model-extrapolation term (``validity.pixel_errors``) says how large.
Two figures follow:

- **on the heading**: the engine's 1-sigma (ground and speed error),
  root-sum-square with the extrapolation term at the probe when the probe
  lies outside the region (unchanged inside it: the term is under the
  region's 1 px threshold there and the noise figure stands);
- **across the view**: the predicted 1-sigma, RMS over the visible ground
  15 +- 0.5 m from the pole (``sim.compare``'s ring, what a user measuring
  "at 15 m" anywhere in the picture meets), with the share of that ring
  outside the region. The heading point can sit inside the region while the
  ring's ends, at the image's sides, are far outside it: the wide 1080p
  camera on the paper's grid (k1 fitted to 39 % of the half-diagonal) is
  ~1 cm off on the heading and tens of cm at the sides.

The extrapolation term is a 90 % bound (``validity.BOUND_FACTOR``: twice the
gap between the chosen and the richer model, with the richer model's excess
std), so it enters a 1-sigma figure divided by 1.645, as
benchmarks/bench_uncertainty_cover.py's ring figure does.

Pure numerical core on ``pipeline.validity``: no I/O, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from dronecal_field.core.camera import Camera
from dronecal_field.pipeline.validity import (
    BOUND_FACTOR, EXTRAPOLATION_FACTOR, ValidityRegion, ground_ring, pixel_errors, points_in_polygon, seen_on_ground,
)

if TYPE_CHECKING:  # the engine (numba) is imported where it runs
    from dronecal_field.core.uncertainty import UncertaintyResult

DISTANCE_M = 15.0  # core.uncertainty.GROUND_DISTANCE_M (not imported at load: it loads the numba engine)
RING_HALF_WIDTH_M = 0.5  # sim.compare's ring
RING_STEP_M = 0.25
P95_FACTOR = 1.96  # a model error lies along one direction (radial): its 95 % is 1.96 of its 1-sigma


@dataclass(frozen=True)
class AtFifteen:
    """The report's ground figures 15 m out; cm, 1-sigma unless named p95 or max.

    ``probe_inside``: the heading point inside the region of validity (None:
    the camera does not see it). ``parameter_cm``: the engine's figure at
    the heading point (noise and model covariance). ``extrapolation_cm``:
    the region's model-extrapolation term there as a 1-sigma (0 inside the
    region). ``ground_error_cm`` / ``ground_error_cm_p95``: what is reported
    on the heading. ``across_view_cm`` / ``across_view_max_cm``: predicted
    RMS / max over the visible ring 15 m from the pole (None: none seen);
    ``across_view_outside``: share of that ring outside the region;
    ``across_view_unbounded``: share where the model cannot say (a fold, a ray
    that misses the ground), left out of the RMS. ``image_without_ray``: share
    of the image beyond the distortion model's fold, where no pixel has a ray:
    the ground seen there is in neither figure (the wide camera on the
    paper's grid: 22 % of the truth's ring 15 m out, up to 32 m off).
    ``speed_extrapolation_kmh``: the extrapolation term of the speed error
    at 50 km/h on the heading, as a 1-sigma (0 inside the region).
    """

    probe_inside: bool | None
    parameter_cm: float
    extrapolation_cm: float
    ground_error_cm: float
    ground_error_cm_p95: float
    across_view_cm: float | None
    across_view_max_cm: float | None
    across_view_outside: float | None
    across_view_unbounded: float | None
    image_without_ray: float = 0.0
    speed_extrapolation_kmh: float = 0.0

    @property
    def extrapolated(self) -> bool:
        """The heading point lies outside the region: the reported figure includes the extrapolation term."""
        return self.probe_inside is False

    def to_dict(self) -> dict:
        return {
            "heading_inside_region_of_validity": self.probe_inside,
            "parameter_cm": self.parameter_cm,
            "extrapolation_cm": self.extrapolation_cm,
            "speed_extrapolation_kmh": self.speed_extrapolation_kmh,
            "across_view": None if self.across_view_cm is None else {
                "range_m": [DISTANCE_M - RING_HALF_WIDTH_M, DISTANCE_M + RING_HALF_WIDTH_M],
                "ground_position_error_cm_rms": self.across_view_cm,
                "ground_position_error_cm_max": self.across_view_max_cm,
                "outside_region_fraction": self.across_view_outside,
                "unbounded_fraction": self.across_view_unbounded,
            },
            "image_without_ray_fraction": self.image_without_ray,
        }

    def line(self) -> str:
        """The CLI's words after "at 15 m: X cm" (empty when the heading and the ring both lie inside the region)."""
        parts = []
        if self.extrapolated:
            parts.append(f"outside the region of validity, incl. {_cm(self.extrapolation_cm)} lens extrapolation")
        if self.across_view_cm is not None and (self.across_view_outside or 0.0) > 0.0:
            parts.append(f"across the view {_cm(self.across_view_cm)} RMS, max {_cm(self.across_view_max_cm)}, "
                         f"{self.across_view_outside:.0%} of it outside the region")
        if self.image_without_ray > 0.0:
            parts.append(f"the lens model has no ray at {self.image_without_ray:.0%} of the image (its edges): no ground figure there")
        return "; ".join(parts)


def _cm(v: float | None) -> str:
    return "-" if v is None else "over 10 m" if not np.isfinite(v) or v > 1000 else f"{v:.1f} cm"


def _one_sigma_cm(e) -> np.ndarray:
    """(M,) predicted 1-sigma ground error, cm: the linearised std, root-sum-square with the extrapolation bound / 1.645."""
    return np.hypot(e.std_cm, e.extrapolation_cm / BOUND_FACTOR)


def at_15m(camera: Camera, covariance: np.ndarray, region: ValidityRegion, parameter_cm: float, parameter_cm_p95: float,
           ground_z: float = 0.0) -> AtFifteen:
    """The report's figures 15 m out for ``camera`` (see the module docstring).

    covariance : (15, 15) the parameter covariance the region was assessed with;
    region : ``validity.assess_validity``'s result (its richer fit and covariance);
    parameter_cm, parameter_cm_p95 : the engine's figure at the heading point
    (``UncertaintyResult.ground_error_15m_cm`` and its p95).
    """
    richer, richer_cov = region.richer_camera, region.richer_covariance
    inside = region.probe_15m_inside
    extra = speed = 0.0
    if inside is False:
        speed = _speed_extrapolation_kmh(camera, richer, ground_z)
        from dronecal_field.core.uncertainty import ground_probe

        uv = camera.project(ground_probe(camera, ground_z).point[None])
        e = pixel_errors(camera, covariance, uv, richer, richer_cov, ground_z)
        # a ray the richer model does not bring to the ground is no bound at all
        extra = float(e.extrapolation_cm[0] / BOUND_FACTOR) if np.isfinite(e.extrapolation_cm[0]) else float("inf")
    sigma = float(np.hypot(parameter_cm, extra))
    p95 = float(np.hypot(parameter_cm_p95, P95_FACTOR * extra))
    view = _across_view(camera, covariance, region, ground_z)
    return AtFifteen(probe_inside=inside, parameter_cm=float(parameter_cm), extrapolation_cm=extra, ground_error_cm=sigma,
                     ground_error_cm_p95=p95, **view, image_without_ray=_without_ray(camera, covariance),
                     speed_extrapolation_kmh=speed)


def _speed_extrapolation_kmh(camera: Camera, richer: Camera | None, ground_z: float) -> float:
    """The speed error at 50 km/h on the heading between the chosen and the richer model, as a 1-sigma (km/h).

    The chosen camera's pixels of the probe's two track points, brought down
    to the ground by the richer camera: the gap in the distance travelled
    over ``SPEED_BASE_S``, counted as validity counts a ground gap (twice,
    a 90 % bound) and divided by 1.645.
    """
    if richer is None:
        return 0.0
    from dronecal_field.core.camera import intersect_plane_z
    from dronecal_field.core.uncertainty import SPEED_BASE_S, ground_probe

    track = ground_probe(camera, ground_z).track
    hits = intersect_plane_z(*richer.batch_arrays(), camera.project(track)[None], ground_z)[0]
    gap_m = abs(float(np.linalg.norm(hits[1, :2] - hits[0, :2])) - float(np.linalg.norm(track[1, :2] - track[0, :2])))
    return EXTRAPOLATION_FACTOR / BOUND_FACTOR * gap_m / SPEED_BASE_S * 3.6 if np.isfinite(gap_m) else float("inf")


def _without_ray(camera: Camera, covariance: np.ndarray, n: int = 48) -> float:
    """Share of the image (an n x n grid of pixels) where the distortion model has no ray (``PixelErrors.has_ray``)."""
    u = np.linspace(0.0, camera.width - 1.0, n)
    v = np.linspace(0.0, camera.height - 1.0, n)
    U, V = np.meshgrid(u, v)
    return float(1.0 - pixel_errors(camera, covariance, np.c_[U.ravel(), V.ravel()]).has_ray.mean())


def _across_view(camera: Camera, covariance: np.ndarray, region: ValidityRegion, ground_z: float) -> dict:
    """The ring's predicted RMS / max, share outside the region and share unbounded (None each when the camera sees none of it)."""
    none = dict.fromkeys(("across_view_cm", "across_view_max_cm", "across_view_outside", "across_view_unbounded"))
    lo, hi = DISTANCE_M - RING_HALF_WIDTH_M, DISTANCE_M + RING_HALF_WIDTH_M
    pts, _ = ground_ring(camera.pose.position_world[:2], (lo, hi), RING_STEP_M, ground_z)
    seen, uv = seen_on_ground(camera, pts, ground_z)
    if not seen.any():
        return none
    uv = uv[seen]
    e = pixel_errors(camera, covariance, uv, region.richer_camera, region.richer_covariance, ground_z)
    sigma = _one_sigma_cm(e)
    ok = np.isfinite(sigma)
    return {
        "across_view_cm": float(np.sqrt(np.mean(sigma[ok] ** 2))) if ok.any() else float("inf"),
        "across_view_max_cm": float(np.max(sigma[ok])) if ok.any() else float("inf"),
        "across_view_outside": float(1.0 - points_in_polygon(uv, region.polygon_px).mean()),
        "across_view_unbounded": float(1.0 - ok.mean()),
    }


def honest(result: UncertaintyResult | None, at: AtFifteen) -> UncertaintyResult | None:
    """``result`` with its ground and speed figures 15 m out root-sum-square with ``at``'s extrapolation terms (unchanged
    inside the region)."""
    if result is None or not at.extrapolated:
        return result
    return replace(
        result,
        ground_error_15m_cm=float(np.hypot(result.ground_error_15m_cm, at.extrapolation_cm)),
        ground_error_15m_cm_p95=float(np.hypot(result.ground_error_15m_cm_p95, P95_FACTOR * at.extrapolation_cm)),
        speed_error_15m_kmh=float(np.hypot(result.speed_error_15m_kmh, at.speed_extrapolation_kmh)),
        speed_error_15m_kmh_p95=float(np.hypot(result.speed_error_15m_kmh_p95, P95_FACTOR * at.speed_extrapolation_kmh)),
    )
