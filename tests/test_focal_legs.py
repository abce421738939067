"""Issue 20: the legs' shared errors inflate the principal point's and the position's std, not the focal length's."""

from __future__ import annotations

import numpy as np
import pytest

from dronecal_field.core.synthetic import paper_camera, paper_grid
from dronecal_field.core.uncertainty import linearised
from dronecal_field.pipeline.confidence import focal_from, leg_sigma_factors


def test_focal_std_of_leg_points_is_the_independent_points_one():
    """Every point on one 10 Hz leg: sigmas x2 (confidence.leg_sigma_factors); focal_from keeps fx, fy at the
    independent points' std and leaves the principal point and position doubled."""
    cam = paper_camera(True)
    X = paper_grid(cam)
    s3, s2 = np.full((len(X), 3), 0.01), np.full(len(X), 0.5)
    f = leg_sigma_factors(0.1 * np.arange(len(X)), np.zeros(len(X), int))
    white = linearised(cam, X, sigma_3d=s3, sigma_2d=s2)
    shared = linearised(cam, X, sigma_3d=s3 * f[:, None], sigma_2d=s2 * f)
    out = focal_from(shared, white)
    assert out.param_std["fx"] == pytest.approx(white.param_std["fx"], rel=1e-12)
    assert out.param_std["fy"] == pytest.approx(white.param_std["fy"], rel=1e-12)
    assert shared.param_std["fx"] / white.param_std["fx"] == pytest.approx(2.0, rel=1e-6)
    for key in ("cx", "cy", "pos_x", "pos_y", "pos_z", "k1"):
        assert out.param_std[key] == pytest.approx(2.0 * white.param_std[key], rel=1e-6), key
    assert out.ground_error_15m_cm == pytest.approx(shared.ground_error_15m_cm, rel=1e-12)
    # never larger than the shared figure (a white std above it is not taken)
    assert focal_from(white, shared).param_std["fx"] == pytest.approx(white.param_std["fx"], rel=1e-12)
