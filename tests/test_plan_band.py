"""Issue 23: targets that survive the guess. Every planned marker (with its quiet zone) is counted in the image of the
TRUE camera, which differs from the plan's guess within the guess band."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from dronecal_field.core.camera import Distortion
from dronecal_field.plan.site import guess_camera, resolve_options
from dronecal_field.plan.stage import make_plan, request_from_options
from dronecal_field.sampling.band import GuessBand, corner_cameras, markers_in_view, quiet_zone_fraction, screen_cameras

SITE = dict(lat=-35.363261, lon=149.165230, ground_alt=584.0, azimuth=30.0)
# the paper's Table 1 camera (missions/paper-distorted.toml) and the 4K bench camera (benchmarks/bench_wholeview.py)
TABLE1 = dict(SITE, mount_height=2.0, tilt=30.0, image_size="1280x960", focal_px=1110.0, distortion="medium", min_agl=0.5)
K4 = dict(SITE, mount_height=4.5, tilt=35.0, image_size="3840x2160", focal_px=2600.0, distortion="medium")
FAST = dict(marker_size=0.3, sampling="hover", hover=3, trials=20)  # one marker, holds only: 20 candidates


def _plan_and_truth(opts: dict, truth_focal_px: float, truth_distortion: Distortion):
    req = request_from_options(resolve_options({**opts, **FAST}))
    result = make_plan(req)
    guess = guess_camera(req.site, req.lens, frame="site")
    truth = guess.with_(intrinsics=replace(guess.intrinsics, fx=truth_focal_px, fy=truth_focal_px), distortion=truth_distortion)
    limits = replace(req.limits, marker_size_m=result.chosen.marker_size_m)
    return result, truth, limits


def test_corner_cameras_span_the_band():
    req = request_from_options(resolve_options({**K4, "focal_tolerance": "10%", "tilt_tolerance": 1, "azimuth_tolerance": 2,
                                                "distortion_range": "none,medium"}))
    guess = guess_camera(req.site, req.lens, frame="site")
    cams = corner_cameras(guess, req.band)
    assert len(cams) == 16  # focal +-, tilt +-, azimuth +-, distortion none / medium
    assert sorted({round(c.intrinsics.fx) for c in cams}) == [2340, 2860]
    # the guess's optical axis lands f tan(1 deg) off centre in y; a 2 deg turn about the vertical moves it
    # f tan(2 deg) cos(tilt 35 deg) in x (the axis points 35 deg down)
    axis = guess.pose.position_world + 10.0 * guess.pose.R_cam_from_world[2]
    shift = np.array([c.project(axis[None])[0] - [1920.0, 1080.0] for c in cams])
    assert np.abs(shift[:, 1]).min() == pytest.approx(2340 * math.tan(math.radians(1.0)), rel=0.05)
    assert np.abs(shift[:, 0]).max() == pytest.approx(2860 * math.tan(math.radians(2.0)) * math.cos(math.radians(35.0)), rel=0.02)
    narrow = corner_cameras(guess, req.band, narrow_only=True)
    assert len(narrow) == 4 and all(c.intrinsics.fx == pytest.approx(2860) and c.distortion.k1 == 0.0 for c in narrow)
    assert quiet_zone_fraction("DICT_4X4_50") == pytest.approx(1 / 6)


def test_table1_plan_with_medium_distortion_flown_by_a_camera_without_distortion():
    """Issue 23: the Table 1 plan made with --distortion medium, flown by the same camera without distortion."""
    before, truth, limits = _plan_and_truth({**TABLE1, "focal_tolerance": 0, "tilt_tolerance": 0, "azimuth_tolerance": 0,
                                             "distortion_range": "1"}, 1110.0, Distortion())
    seen_before = markers_in_view(truth, before.chosen.marker_site, limits)
    after, truth, limits = _plan_and_truth({**TABLE1, "distortion_range": "none,medium"}, 1110.0, Distortion())
    seen = markers_in_view(truth, after.chosen.marker_site, limits)
    print(f"Table 1 by a pinhole: {seen_before.sum()}/{len(seen_before)} markers in view planned on the guess alone, "
          f"{seen.sum()}/{len(seen)} with the band")
    assert (~seen_before).sum() >= 5  # the guess alone plans markers the undistorted camera does not see
    assert seen.all() and len(seen) >= 30
    # every screen camera (each factor of the band at its full tolerance alone) sees every marker; a marker only an
    # extreme corner (several factors at their ends together) loses is kept, and plan.json names it
    for cam in screen_cameras(after.camera_site, after.request.band):
        assert markers_in_view(cam, after.chosen.marker_site, limits).all()
    lost = np.zeros(len(seen), bool)
    for cam in corner_cameras(after.camera_site, after.request.band):
        lost |= ~markers_in_view(cam, after.chosen.marker_site, limits)
    band = after.summary["guess_band"]
    print(f"may be lost by an extreme corner: {lost.sum()}/{len(seen)}")
    assert band["may_be_lost"] == [int(i) for i in np.flatnonzero(lost)]
    assert band["holds_in_view_of_all"] == len(seen) - lost.sum()


def test_4k_plan_flown_by_the_4k_truth():
    """Issue 23: the 4K plan (nominal focal, medium distortion guessed) flown by the 4K truth (k1 -0.32, k2 0.12, k3 -0.02, p1, p2)."""
    truth_d = Distortion(k1=-0.32, k2=0.12, p1=4e-4, p2=-3e-4, k3=-0.02)
    result, truth, limits = _plan_and_truth(K4, 2600.0, truth_d)
    seen = markers_in_view(truth, result.chosen.marker_site, limits)
    print(f"4K by its truth: {seen.sum()}/{len(seen)} markers in view; coverage {result.summary['coverage']['pct']} %")
    assert seen.all() and len(seen) >= 30
    # the same truth 5 % longer in focal (a datasheet 5 % off): still every marker
    longer = truth.with_(intrinsics=replace(truth.intrinsics, fx=2730.0, fy=2730.0))
    assert markers_in_view(longer, result.chosen.marker_site, limits).all()


def test_screen_cameras_are_each_factor_alone():
    """The screen: focal x (1 + tol), tilt -+, azimuth -+, the weakest distortion, each with the other factors as guessed;
    no band, no screen. band_cost is None when every corner sees every sample."""
    req = request_from_options(resolve_options({**K4, "focal_tolerance": "10%", "tilt_tolerance": 1, "azimuth_tolerance": 2,
                                                "distortion_range": "none,medium"}))
    guess = guess_camera(req.site, req.lens, frame="site")
    cams = screen_cameras(guess, req.band)
    assert len(cams) == 6
    assert sorted(round(c.intrinsics.fx) for c in cams) == [2600] * 5 + [2860]
    assert sum(c.distortion.k1 == 0.0 for c in cams) == 1 and sum(c.distortion.k1 == guess.distortion.k1 for c in cams) == 5
    axis = guess.pose.position_world + 10.0 * guess.pose.R_cam_from_world[2]
    shift = np.array([c.project(axis[None])[0] - [1920.0, 1080.0] for c in cams])
    assert np.abs(shift[:, 1]).max() == pytest.approx(2600 * math.tan(math.radians(1.0)), rel=0.05)
    assert screen_cameras(guess, GuessBand(focal_tolerance=0.0, tilt_tolerance_deg=0.0, azimuth_tolerance_deg=0.0, distortions=())) == ()
    from dronecal_field.sampling.band import band_cost

    ahead = guess.pose.position_world + 8.0 * guess.pose.R_cam_from_world[2]
    limits = replace(req.limits, marker_size_m=0.3)
    assert band_cost(guess, req.band, ahead[None], limits, lambda keep: 1.0) is None
