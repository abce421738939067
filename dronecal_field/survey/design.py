"""The paper's camera database: a seeded Latin Hypercube over five factors (section III.B).

Factors and ranges (paper): focal length 2-15 mm, image width 700-4,000 px
(height 3/4 of it), camera elevation 2-5 m, tilt 0 (horizontal) to 90
(straight down) deg, distortion none or "medium". What the paper leaves open,
and what we assume (docs/survey.md says why):

- **pixel pitch** (mm -> px): 7.5 um for every camera, so the narrowest
  camera (15 mm, 700 px) sees 20 deg and the widest (2 mm, 4,000 px) 165 deg,
  the paper's "few cameras have a field of view of 180 or 20 degrees";
- **medium distortion**: Table 1's distorted camera (k1 = -0.25, p1 = -28e-5,
  p2 = -5e-5 at f = 1110 px, 1280 x 960) displaces its image corner by 20 %;
  every "medium" camera gets the k1 that displaces *its* corner by the same
  20 % (k1 of Table 1 itself for Table 1's camera), and Table 1's p1, p2;
- the distortion factor is the fifth hypercube coordinate cut at 0.5.

Cameras live in the paper's (site) frame: on a pole at X = Y = 0 at the
elevation, looking along +X, tilted down; principal point at the image centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dronecal_field.core.camera import Camera, Distortion
from dronecal_field.errors import InputError

# Table 1 of the paper: the distorted camera, whose corner displacement defines "medium".
TABLE1_FOCAL_PX = 1110.0
TABLE1_SIZE_PX = (1280, 960)
TABLE1_DISTORTION = Distortion(k1=-0.25, p1=-28e-5, p2=-5e-5)
MAX_TILT_DEG = 89.99  # straight down leaves the image's roll undefined (core.camera.look_rotation)


def _corner_radius(focal_px: float, width: int, height: int) -> float:
    """Normalised radius of the image corner (distorted coordinates): half-diagonal / f."""
    return math.hypot(width / 2.0, height / 2.0) / focal_px


def _corner_displacement(k1: float, r_distorted: float) -> float:
    """Relative radial displacement k1 r_u^2 at the point whose distorted radius is ``r_distorted``.

    Solves r_u (1 + k1 r_u^2) = r_d on the monotonic branch by Newton's method.
    """
    r = r_distorted
    for _ in range(50):
        f = r * (1.0 + k1 * r * r) - r_distorted
        r -= f / (1.0 + 3.0 * k1 * r * r)
    return k1 * r * r


MEDIUM_CORNER_DISPLACEMENT = _corner_displacement(TABLE1_DISTORTION.k1, _corner_radius(TABLE1_FOCAL_PX, *TABLE1_SIZE_PX))


def medium_distortion(focal_px: float, width: int, height: int) -> Distortion:
    """The paper's "medium" distortion scaled to a camera's field of view.

    k1 moves the image corner radially by ``MEDIUM_CORNER_DISPLACEMENT``
    (about -20 %, as Table 1's distorted camera does): with D that fraction
    and r_c the corner's distorted normalised radius, the undistorted radius
    is r_c / (1 + D), so k1 = D (1 + D)^2 / r_c^2. Barrel distortion stays
    monotonic over the image (1 + 3 D > 0). p1, p2 are Table 1's.
    """
    D = MEDIUM_CORNER_DISPLACEMENT
    rc = _corner_radius(focal_px, width, height)
    return Distortion(k1=D * (1.0 + D) ** 2 / rc**2, p1=TABLE1_DISTORTION.p1, p2=TABLE1_DISTORTION.p2)


@dataclass(frozen=True)
class DesignSpace:
    """Ranges of the camera factors and the assumptions that turn them into cameras."""

    focal_mm: tuple[float, float] = (2.0, 15.0)
    width_px: tuple[int, int] = (700, 4000)
    height_ratio: float = 0.75
    elevation_m: tuple[float, float] = (2.0, 5.0)
    tilt_deg: tuple[float, float] = (0.0, 90.0)
    pixel_pitch_um: float = 7.5
    medium_share: float = 0.5  # share of cameras with medium distortion

    def __post_init__(self) -> None:
        for name in ("focal_mm", "width_px", "elevation_m", "tilt_deg"):
            lo, hi = getattr(self, name)
            if not lo <= hi:
                raise InputError(f"design range {name} = {lo}..{hi} is reversed: give low..high")
        if self.pixel_pitch_um <= 0:
            raise InputError(f"pixel pitch {self.pixel_pitch_um} um is not positive: give the sensor's pixel size")


@dataclass(frozen=True)
class SurveyCamera:
    """One camera of the database, by its design factors (the row's identity is ``camera_id``)."""

    camera_id: int
    focal_mm: float
    width_px: int
    height_px: int
    elevation_m: float
    tilt_deg: float
    distorted: bool
    pixel_pitch_um: float = 7.5

    @property
    def focal_px(self) -> float:
        """Focal length in pixels: focal_mm / pixel pitch."""
        return self.focal_mm * 1000.0 / self.pixel_pitch_um

    @property
    def hfov_deg(self) -> float:
        """Pinhole horizontal field of view, deg."""
        return 2.0 * math.degrees(math.atan(self.width_px / 2.0 / self.focal_px))

    def distortion(self) -> Distortion:
        return medium_distortion(self.focal_px, self.width_px, self.height_px) if self.distorted else Distortion()

    def camera(self) -> Camera:
        """The engine's camera, in the paper's frame (X forward, Y left, Z up, pole at the origin)."""
        from dronecal_field.core.synthetic import pole_camera

        return pole_camera(
            self.focal_px,
            self.width_px,
            self.height_px,
            (0.0, 0.0, self.elevation_m),
            min(self.tilt_deg, MAX_TILT_DEG),
            distortion=self.distortion(),
        )


def latin_hypercube(n_cameras: int, seed: int = 0, space: DesignSpace = DesignSpace()) -> tuple[SurveyCamera, ...]:
    """``n_cameras`` cameras from a seeded Latin Hypercube over the five factors.

    Every factor's range is cut into ``n_cameras`` equal strata and each
    stratum holds exactly one camera (scipy.stats.qmc.LatinHypercube). Widths
    are rounded to a multiple of 4 px so the height (3/4) is a whole number.
    The same ``n_cameras`` and ``seed`` give the same cameras on any machine;
    a different ``n_cameras`` gives a different design (not a superset).

    Returns
    -------
    tuple of SurveyCamera with ``camera_id`` 0 .. n_cameras - 1
    """
    from scipy.stats import qmc

    if n_cameras < 1:
        raise InputError(f"--cameras {n_cameras} must be at least 1 (the paper uses 5000)")
    u = qmc.LatinHypercube(d=5, rng=np.random.default_rng(seed)).random(n_cameras)

    def scale(col: int, lo: float, hi: float) -> np.ndarray:
        return lo + u[:, col] * (hi - lo)

    focal = scale(0, *space.focal_mm)
    width = np.round(scale(1, *space.width_px) / 4.0).astype(int) * 4
    elevation = scale(2, *space.elevation_m)
    tilt = scale(3, *space.tilt_deg)
    distorted = u[:, 4] >= 1.0 - space.medium_share
    return tuple(
        SurveyCamera(
            camera_id=i,
            focal_mm=float(focal[i]),
            width_px=int(width[i]),
            height_px=int(round(width[i] * space.height_ratio)),
            elevation_m=float(elevation[i]),
            tilt_deg=float(tilt[i]),
            distorted=bool(distorted[i]),
            pixel_pitch_um=space.pixel_pitch_um,
        )
        for i in range(n_cameras)
    )
