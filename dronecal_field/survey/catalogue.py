"""Which sampling strategies the survey runs, and how a strategy becomes 3D points for a camera.

The strategies themselves (X range, Y step, number of heights) are
``sampling.lattice.Strategy``: one definition for ``plan`` and the survey.
This module adds what the study needs on top:

- the *catalogue*: the strategies behind every comparison of the paper's
  section IV.B (heights 2/3/4, Y step 1/0.5 m, X near/far/full), or all 18,
  or names given on the command line;
- two *samplers*, i.e. how a strategy's heights are chosen:
  :class:`PaperLattice` reproduces the paper (levels every 0.5 m from 0.5 m
  up, section III.B's "every 50 centimeters along Z"; the first level is our
  assumption) and keeps the points the camera sees;
  :class:`PlanLattice` is what ``plan`` flies (levels spread over the band
  the camera sees, marker size, keep-out and height limits).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from dronecal_field.core.camera import Camera
from dronecal_field.errors import InputError
from dronecal_field.sampling.lattice import Limits, Strategy, fold_radius, make_strategy, paper_strategies, sample_grid, xy_lattice

# The paper's comparisons (section IV.B), each a tuple whose first entry is the paper's winner.
# The baseline lattice (section III.B) is 1 m along X and Y, X out to 8 m: 'full' here.
COMPARISONS: dict[str, tuple[str, ...]] = {
    "heights": ("full-y1-z2", "full-y1-z3", "full-y1-z4"),
    "y_step": ("full-y1-z2", "full-y0.5-z2"),
    "x_range": ("far-y1-z2", "near-y1-z2", "full-y1-z2"),
}
RECOMMENDED = "far-y1-z2"  # the paper's recommendation: X 4-8 m, 1 m along X and Y, two heights

_NAME = re.compile(r"^(near|far|full)-y([0-9]*\.?[0-9]+)-z([0-9]+)$")


def strategy_from_name(name: str) -> Strategy:
    """The strategy called ``'<near|far|full>-y<step m>-z<heights>'``, e.g. ``far-y1-z2``."""
    m = _NAME.match(name.strip())
    if not m:
        raise InputError(f"strategy {name!r} is not <near|far|full>-y<step>-z<heights>: write e.g. far-y1-z2 or full-y0.5-z3")
    y_step, n_z = float(m.group(2)), int(m.group(3))
    if y_step <= 0 or n_z < 1:
        raise InputError(f"strategy {name!r} needs a positive Y step and at least one height")
    return make_strategy(m.group(1), y_step, n_z)


def catalogue(spec: str = "paper") -> tuple[Strategy, ...]:
    """Strategies from a ``--strategies`` value.

    ``paper``: the six strategies of the paper's three comparisons;
    ``all``: the 18 of ``sampling.lattice.paper_strategies()``;
    ``recommended``: the paper's recommended one only;
    otherwise a comma-separated list of names (see :func:`strategy_from_name`).
    Order is kept and duplicates dropped.
    """
    spec = spec.strip()
    if spec == "paper":
        names = [n for group in COMPARISONS.values() for n in group]
        strategies = [strategy_from_name(n) for n in names]
    elif spec == "all":
        strategies = list(paper_strategies())
    elif spec == "recommended":
        strategies = [strategy_from_name(RECOMMENDED)]
    else:
        strategies = [strategy_from_name(n) for n in spec.split(",") if n.strip()]
    if not strategies:
        raise InputError(f"--strategies {spec!r} names no strategy: use paper, all, recommended or e.g. far-y1-z2,near-y1-z2")
    seen: dict[str, Strategy] = {}
    for s in strategies:
        seen.setdefault(s.name, s)
    return tuple(seen.values())


def in_view(camera: Camera, points: np.ndarray, margin_px: float = 10.0) -> np.ndarray:
    """(N,) mask of points (N, 3) the camera sees: in front, in the image with a margin, before the distortion folds.

    Beyond the fold radius a barrel model maps points back *into* the image;
    a real lens never shows them, so they are not seen.
    """
    from dronecal_field.core.synthetic import visible

    points = np.asarray(points, float)
    if len(points) == 0:
        return np.zeros(0, bool)
    Xc = points @ camera.pose.R_cam_from_world.T + camera.pose.t_cam_from_world
    z = np.where(Xc[:, 2] > 0.1, Xc[:, 2], 1.0)
    r = np.hypot(Xc[:, 0] / z, Xc[:, 1] / z)
    with np.errstate(invalid="ignore", over="ignore"):
        seen = visible(camera, points, margin_px)
    return seen & (r < 0.98 * fold_radius(camera.distortion.as_array()))


@dataclass(frozen=True)
class PaperLattice:
    """The paper's lattice: heights ``z0_m, z0_m + z_step_m, ...`` (one per level), visible points only."""

    z0_m: float = 0.5
    z_step_m: float = 0.5
    margin_px: float = 10.0
    name: str = field(default="paper", init=False)

    def heights(self, strategy: Strategy, camera: Camera) -> tuple[float, ...]:
        """Marker heights (m) of the strategy's levels (the same for every camera)."""
        return tuple(round(self.z0_m + i * self.z_step_m, 6) for i in range(strategy.n_heights))

    def points(self, strategy: Strategy, camera: Camera) -> np.ndarray:
        """(N, 3) lattice points (m, paper frame) that ``camera`` sees."""
        xy = xy_lattice(strategy)
        z = np.asarray(self.heights(strategy, camera), float)
        # X, then Y, then Z fastest: the order the stored survey rows were drawn in (noise is drawn per point)
        grid = np.column_stack([np.repeat(xy, len(z), axis=0), np.tile(z, len(xy))])
        return grid[in_view(camera, grid, self.margin_px)]


@dataclass(frozen=True)
class PlanLattice:
    """What ``plan`` would fly: ``sampling.lattice.sample_grid`` with these limits."""

    limits: Limits = Limits()
    name: str = field(default="plan", init=False)

    def heights(self, strategy: Strategy, camera: Camera) -> tuple[float, ...]:
        from dronecal_field.sampling.lattice import choose_heights

        return choose_heights(strategy, camera, self.limits)

    def points(self, strategy: Strategy, camera: Camera) -> np.ndarray:
        return sample_grid(strategy, camera, self.limits)


Sampler = PaperLattice | PlanLattice


def sampler_from_name(name: str) -> Sampler:
    """``paper`` (fixed 0.5 m levels from 0.5 m) or ``plan`` (the levels ``plan`` would fly)."""
    if name == "paper":
        return PaperLattice()
    if name == "plan":
        return PlanLattice()
    raise InputError(f"--heights {name!r} is unknown: use paper (0.5 m levels from 0.5 m) or plan (what plan flies)")
