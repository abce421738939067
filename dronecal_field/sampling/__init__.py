"""Sampling design: where the marker must be for a calibration (one home for ``plan`` and ``survey``).

- ``lattice``: the paper's metric strategies (X range, Y step, heights), the
  point screen (``screen_points``: drone limits, image, marker size, the
  distortion fold) and the limits themselves.
- ``roi``: the region of interest the user measures in, as 3D points with
  their guessed pixels and the image cells they cover.
- ``design``: sampling designed in the image: target pixels over the ROI's
  image area, two or more depths along each target's ray, holds and legs.
- ``predict``: the predicted projection error over the ROI, linearised
  (fast, for ranking) plus the model-extrapolation term.

Nothing here imports ``plan`` or ``survey``; both import this package.
"""

from dronecal_field.sampling.lattice import (
    GridScreen,
    Limits,
    Strategy,
    fold_radius,
    make_strategy,
    paper_strategies,
    recommended_strategy,
    sample_grid,
    screen_grid,
    screen_points,
)

__all__ = [
    "GridScreen", "Limits", "Strategy", "fold_radius", "make_strategy", "paper_strategies",
    "recommended_strategy", "sample_grid", "screen_grid", "screen_points",
]
