"""Sampling design in the image (issue 10): ROI, target rays, limits, depths, coverage; property tests on the geometry."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dronecal_field.core.camera import pixel_rays_batch
from dronecal_field.plan.site import CameraSite, LensGuess, guess_camera
from dronecal_field.sampling.design import MIN_DEPTH_RATIO, DesignParams, LegTiming, design_sampling, target_lattice
from dronecal_field.sampling.lattice import Limits, make_strategy, recommended_strategy, screen_grid
from dronecal_field.sampling.roi import Roi, RoiSpec, build_roi

CMAC = dict(lat_deg=-35.363261, lon_deg=149.165230, ground_h_m=584.0)


def camera(w=1920, h=1080, f=900.0, mount=3.5, tilt=25.0, distortion="strong"):
    site = CameraSite(**CMAC, mount_height_m=mount, azimuth_deg=90.0, tilt_deg=tilt)
    lens = LensGuess(width=w, height=h, focal_px=f, distortion_level=distortion, focal_source="test")
    return guess_camera(site, lens, frame="site")


cameras = st.builds(
    camera,
    w=st.sampled_from([1280, 1920, 3840]),
    h=st.sampled_from([720, 960, 1080]),
    f=st.floats(700.0, 2800.0),
    mount=st.floats(2.0, 8.0),
    tilt=st.floats(10.0, 50.0),
    distortion=st.sampled_from(["none", "medium", "strong"]),
)
limits = st.builds(
    Limits,
    min_agl_m=st.floats(0.5, 2.0),
    keep_out_m=st.floats(1.0, 4.0),
    max_range_m=st.one_of(st.none(), st.floats(12.0, 40.0)),
    min_marker_px=st.floats(15.0, 40.0),
    max_search_height_m=st.floats(5.0, 10.0),
)
params = st.builds(
    DesignParams,
    n_u=st.integers(3, 8), n_v=st.integers(2, 6), n_depths=st.sampled_from([2, 3]),
    depth_ratio=st.sampled_from([None, 1.5, 2.5]), marker_size_m=st.sampled_from([0.3, 0.6]),
    sampling=st.sampled_from(["hover", "through", "mixed"]), min_depth_m=st.sampled_from([None, 4.0]),
)


@settings(max_examples=40, deadline=None)
@given(cam=cameras, lim=limits, p=params)
def test_designed_points_lie_on_their_target_rays_and_respect_every_limit(cam, lim, p):
    try:
        roi = build_roi(cam, RoiSpec())
    except Exception:  # a camera that sees none of the ROI is refused with a PlanError (tested below)
        return
    d = design_sampling(cam, roi, p, lim, LegTiming())
    if d.n_points == 0:
        return
    c = cam.pose.position_world
    # on the ray of its target pixel: the direction from the camera matches the pixel's ray
    K, D, R, _ = cam.batch_arrays()
    rays = pixel_rays_batch(K, D, R, d.targets_uv[d.target][None])[0]
    v = d.marker_site - c
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    assert np.degrees(np.arccos(np.clip(np.sum(v * rays, axis=1), -1, 1))).max() < 0.01
    # drone height, keep-out, range (the drone, not the marker)
    assert d.vehicle_site[:, 2].min() >= lim.min_agl_m - 1e-9
    assert np.hypot(d.vehicle_site[:, 0], d.vehicle_site[:, 1]).min() >= lim.keep_out_m - 1e-9
    if lim.max_range_m is not None:
        assert np.hypot(d.vehicle_site[:, 0], d.vehicle_site[:, 1]).max() <= lim.max_range_m + 1e-9
    # the marker is read: at least min_marker_px, and the whole marker in the image with the margin
    assert d.marker_px.min() >= lim.min_marker_px - 1e-9
    assert (d.uv >= 0).all() and (d.uv[:, 0] <= cam.width - 1).all() and (d.uv[:, 1] <= cam.height - 1).all()
    # every target with two depths has them at least MIN_DEPTH_RATIO apart along its ray
    dist = np.linalg.norm(d.marker_site - c, axis=1)
    for t in np.flatnonzero(d.target_ok):
        mine = dist[d.target == t]
        assert len(mine) >= 2 and mine.max() / mine.min() >= MIN_DEPTH_RATIO - 1e-6
    # holds where legs end; pass-through points only inside legs
    if p.sampling == "through":
        ends = np.r_[True, d.leg[1:] != d.leg[:-1]] | np.r_[d.leg[1:] != d.leg[:-1], True]
        assert (d.hold_s[ends] > 0).all() and (d.hold_s[~ends] == 0).all()
    else:
        assert (d.hold_s > 0).all()
    assert 0.0 <= d.coverage <= 1.0


def test_the_wide_camera_is_sampled_over_the_whole_roi_not_a_band():
    """Issue 10's wide 1080p camera: the paper's grid covers about half the ROI, the image design nearly all of it."""
    cam = camera()
    roi = build_roi(cam, RoiSpec())
    lim = Limits(max_search_height_m=6.5)
    d = design_sampling(cam, roi, DesignParams(n_u=7, n_v=5), lim)
    paper = screen_grid(recommended_strategy(cam), cam, lim)
    paper_cov = roi.coverage(cam.project(paper.points))
    assert d.coverage >= 0.9 and paper_cov < 0.6
    # the samples reach the image's lower third and both side thirds (the paper's band did not)
    assert d.uv[:, 1].max() > 2 * cam.height / 3 and d.uv[:, 0].min() < cam.width / 3 and d.uv[:, 0].max() > 2 * cam.width / 3
    # the far ground near the horizon is reached by points a few metres up, not by flying 40 m out
    top = d.uv[:, 1] < np.percentile(d.uv[:, 1], 20)
    assert np.hypot(d.vehicle_site[top, 0], d.vehicle_site[top, 1]).max() < 20.0


def test_unreachable_parts_are_named_with_the_rule():
    """The paper's Table 1 camera (2 m, tilt 30): the image centre sees ground 3-5 m that needs the drone below 1 m."""
    cam = camera(w=1280, h=960, f=1110.0, mount=2.0, tilt=30.0, distortion="medium")
    roi = build_roi(cam, RoiSpec())
    d = design_sampling(cam, roi, DesignParams(n_u=9, n_v=6), Limits(max_search_height_m=5.0))
    low = [p for p in d.unreachable if p["reason"] == "too_low"]
    assert low and sum(p["share_pct"] for p in low) > 10.0
    assert all("--min-agl 1 m" in p["text"] and p["ground_m"][0] >= 3.0 - 1e-9 for p in low)
    assert d.coverage < 0.9
    # lowering --min-agl reaches more of it
    d2 = design_sampling(cam, roi, DesignParams(n_u=9, n_v=6), Limits(min_agl_m=0.3, max_search_height_m=5.0))
    assert d2.coverage > d.coverage


def test_roi_image_covers_the_image_and_range_roi_is_the_ground_band():
    cam = camera(distortion="none")
    whole = build_roi(cam, RoiSpec(kind="image", range_m=(3.0, 40.0)))
    assert whole.cells.all()
    band = build_roi(cam, RoiSpec(range_m=(3.0, 40.0)))
    g = band.points_site[band.on_ground]
    r = np.hypot(g[:, 0], g[:, 1])
    assert r.min() >= 3.0 - 1e-9 and r.max() <= 40.0 + 1e-9 and np.allclose(g[:, 2], 0.0)
    assert set(np.round(np.unique(band.points_site[:, 2]), 6)) <= {0.0, 1.0, 2.0}
    assert 0.5 < band.area_fraction < 1.0  # the sky and the ground under 3 m are not in it


def test_coverage_on_a_hand_made_case():
    cells = np.ones((4, 4), bool)
    roi = Roi(spec=RoiSpec(), width=400, height=400, points_site=np.zeros((1, 3)), uv=np.zeros((1, 2)),
              on_ground=np.ones(1, bool), cells=cells)
    assert roi.coverage(np.array([[10.0, 10.0]])) == pytest.approx(4 / 16)  # a corner cell reaches its 2x2 block
    assert roi.coverage(np.array([[150.0, 150.0]])) == pytest.approx(9 / 16)  # an inner cell its 3x3 block
    assert roi.coverage(np.array([[150.0, 150.0], [350.0, 350.0]])) == pytest.approx(12 / 16)
    half = cells.copy()
    half[:, 2:] = False  # only the left half is ROI: samples on the right reach only the ROI cells beside them
    roi2 = replace(roi, cells=half)
    assert roi2.coverage(np.array([[250.0, 50.0]])) == pytest.approx(2 / 8)
    assert roi2.coverage(np.zeros((0, 2))) == 0.0


def test_polygon_roi_keeps_only_the_polygon():
    cam = camera()
    poly = ((10.0, -6.0), (25.0, -6.0), (25.0, 6.0), (10.0, 6.0))
    roi = build_roi(cam, RoiSpec(kind="polygon", range_m=(0.0, 60.0), polygon_site=poly, source="road.geojson"))
    g = roi.points_site[roi.on_ground]
    assert g[:, 0].min() >= 10.0 - 1e-9 and g[:, 0].max() <= 25.0 + 1e-9 and np.abs(g[:, 1]).max() <= 6.0 + 1e-9
    full = build_roi(cam, RoiSpec())
    assert roi.cells.sum() < full.cells.sum()
    lattice = target_lattice(roi, 5, 4)
    # the target lattice stays on the polygon's image area
    r, c = roi.cell_of(lattice)
    assert roi.cells[r, c].mean() > 0.8


def test_paper_strategies_still_produce_the_old_grids():
    """The paper's Table 1 camera keeps its 40-point far grid at 1.0 and 1.4 m (issue 10's report)."""
    cam = camera(w=1280, h=960, f=1110.0, mount=2.0, tilt=30.0, distortion="medium")
    g = screen_grid(recommended_strategy(cam), cam, Limits(max_search_height_m=5.0))
    assert recommended_strategy(cam).name == "far-y1-z2" and g.heights_m == (1.0, 1.4) and len(g.points) == 40
    near = screen_grid(make_strategy("near", 1.0, 2), cam, Limits(max_search_height_m=5.0))
    assert near.points[:, 0].max() <= 4.0 and len(near.points) < 40


def test_leg_samples_are_spaced_by_speed_over_gnss_rate():
    cam = camera()
    roi = build_roi(cam, RoiSpec())
    timing = LegTiming(gnss_hz=10.0)
    d = design_sampling(cam, roi, DesignParams(sampling="through"), Limits(max_search_height_m=6.5), timing)
    legs = d.samples_site[~d.samples_is_hold]
    assert len(legs) > 10 * d.n_points
    # every leg starts and ends with a one-second stop (not a full hover: 11.0 instead of 12.2 min for camera (a))
    ends = np.r_[True, d.leg[1:] != d.leg[:-1]] | np.r_[d.leg[1:] != d.leg[:-1], True]
    assert np.all(d.hold_s[ends] == 1.0) and np.all(d.hold_s[~ends] == 0.0)
    # the leg speed keeps motion blur under a pixel at the nearest point
    nearest = float(cam.depth(d.marker_site).min())
    assert d.speed_m_s * timing.exposure_s * cam.intrinsics.fx / nearest <= 1.0 + 1e-6
    gaps = np.linalg.norm(np.diff(legs, axis=0), axis=1)
    assert np.median(gaps) <= d.speed_m_s / timing.gnss_hz + 1e-6
    assert math.isclose(float(d.samples_sigma_h_m[~d.samples_is_hold][0]), d.speed_m_s * 0.01)


def test_survey_and_sampling_do_not_import_plan():
    """One home for sampling design: survey -> sampling, plan -> sampling and survey, never survey -> plan."""
    import subprocess
    import sys

    code = ("import sys, dronecal_field.survey.catalogue, dronecal_field.survey.runner, dronecal_field.survey.report, "
            "dronecal_field.sampling.design, dronecal_field.sampling.predict; "
            "print(sorted(m for m in sys.modules if m.startswith('dronecal_field.plan')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"
