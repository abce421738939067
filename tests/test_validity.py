"""Region of validity, model extrapolation, degenerate geometry and model choice, against synthetic truth.

The cameras of issue 14: a wide 1080p camera (f 900, k1 -0.28, k2 0.07) on
a 4 m pole flown on the paper's 4-8 m grid (the points reach 42 % of the
half-diagonal, so ``auto`` keeps k1); the paper's Table 1 distorted camera
(2 m pole, tilt 30, f 1110) with its grid at heights 1.0 and 1.4 m; a
distorted 4K camera. Per-point noise: 0.3 px and half the 1 cm (1.5 cm up)
RTK sigma the covariance is given, as a hold's average has.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dronecal_field.core.camera import Distortion, intersect_plane_z
from dronecal_field.core.synthetic import paper_camera, paper_grid, pole_camera, sampling_grid, visible
from dronecal_field.core.uncertainty import parameter_covariance
from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu
from dronecal_field.pipeline import validity as V
from dronecal_field.pipeline.maps import select_model

ORIGIN = EnuOrigin(lat_deg=46.5197, lon_deg=6.5663, h_m=420.0)
WIDE = dict(focal_px=900.0, width=1920, height=1080, position=(0.0, 0.0, 4.0), tilt_deg=20.0,
            distortion=Distortion(k1=-0.28, k2=0.07))
K4 = dict(focal_px=2600.0, width=3840, height=2160, position=(0.0, 0.0, 5.0), tilt_deg=20.0,
          distortion=Distortion(k1=-0.32, k2=0.12, k3=-0.02, p1=4e-4, p2=-3e-4))


def _flight(truth, X, seed):
    """(calibration, covariance, s3, s2) of a synthetic flight over points X (N, 3)."""
    rng = np.random.default_rng(seed)
    s3 = np.tile([0.01, 0.01, 0.015], (len(X), 1))
    s2 = np.full(len(X), 0.3)
    Xn = X + rng.normal(0.0, 1.0, X.shape) * s3 * 0.5
    uv = truth.project(X) + rng.normal(0.0, 0.3, (len(X), 2))
    result, _ = select_model(Xn, uv, truth.width, truth.height)
    cov = parameter_covariance(result.camera, Xn, s3, s2, result.model)
    return result, cov, s3, s2


def _ground_truth_errors(truth, cam, region, cov, step_px=10):
    """Over the pixels whose ray meets the ground 3-30 m out: true error (px), predicted error (px), inside mask.

    The true error at a pixel is how far the truth projects the ground point
    the calibrated camera sees there: what a speed camera using it gets.
    """
    u, v = np.meshgrid(np.arange(0, cam.width, step_px), np.arange(0, cam.height, step_px))
    uv = np.c_[u.ravel(), v.ravel()].astype(float)
    G = intersect_plane_z(*cam.batch_arrays(), uv[None], 0.0)[0]
    rho = np.hypot(*(G[:, :2] - cam.pose.position_world[:2]).T)
    ok = np.isfinite(rho) & (rho >= 3.0) & (rho <= 30.0)
    uv, G = uv[ok], G[ok]
    true = np.linalg.norm(truth.project(G) - uv, axis=1)
    pred = V.pixel_errors(cam, cov, uv, region.richer_camera, region.richer_covariance).total_px
    return true, pred, V.points_in_polygon(uv, region.polygon_px)


def _assess(truth, X, seed):
    result, cov, s3, s2 = _flight(truth, X, seed)
    return result, cov, V.assess_validity(result, cov, s3, s2, origin=ORIGIN)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_wide_camera_on_the_paper_grid_region_holds_against_truth(seed):
    truth = pole_camera(**WIDE)
    result, cov, region = _assess(truth, paper_grid(truth), seed)
    assert result.model.distortion == "k1" and result.model.fix_aspect_ratio
    true, pred, inside = _ground_truth_errors(truth, result.camera, region, cov)
    # Inside the region the calibration is good to a pixel...
    rms_inside = float(np.sqrt(np.mean(true[inside] ** 2)))
    assert rms_inside < 1.0, rms_inside
    # ...outside it the truth is far off (84 px RMS in the issue), and the
    # predicted error says so for at least 90 % of the ground pixels.
    assert np.percentile(true[~inside], 75) > 20.0
    covered = float(np.mean(pred[~inside] >= true[~inside]))
    assert covered >= 0.9, covered
    # The region is more than the hull, but far from the whole view: a warning says how much.
    assert region.hull_fraction <= region.image_fraction < 0.3
    assert region.visible_ground_fraction < 0.5
    assert any("of the visible ground 3-30 m" in w and "plan --strategy image" in w for w in region.warnings)
    assert region.outside_px_max > 50.0


def test_covered_wide_camera_has_a_large_region_and_no_warning():
    truth = pole_camera(**WIDE)
    G = sampling_grid(np.arange(2.0, 16.0, 1.5), np.arange(-8.0, 8.1, 1.5), [0.5, 2.0, 3.5, 5.0])
    result, cov, region = _assess(truth, G[visible(truth, G, 20.0)], 0)
    assert result.model.distortion in ("k1k2", "k1k2p1p2", "full")
    true, pred, inside = _ground_truth_errors(truth, result.camera, region, cov)
    assert np.sqrt(np.mean(true[inside] ** 2)) < 1.0
    assert region.visible_ground_fraction > 0.95 and region.image_fraction > 0.8
    assert region.warnings == () and not region.geometry.degenerate


def test_table1_band_is_flagged_as_degenerate_and_a_covered_flight_is_not():
    truth = paper_camera(distorted=True)
    X = paper_grid(truth, heights=(1.0, 1.4))
    result, cov, s3, s2 = _flight(truth, X, 0)
    d = V.diagnose_geometry(result.camera, cov, result.points_world, result.pixels)
    # Large, honest standard deviations from the measured sigmas...
    assert d.degenerate and d.focal_std_rel > 0.005 and d.principal_point_std_px > 15.0
    assert 0.15 < d.image_coverage < 0.25 and abs(d.thickness_m - 0.4) < 0.1
    # ...and the warning names the cause and the fix.
    assert "focal length" in d.message and "0.4 m" in d.message and "plan --strategy image" in d.message
    region = V.assess_validity(result, cov, s3, s2)
    assert d.message in region.warnings
    wide = pole_camera(**WIDE)
    G = sampling_grid(np.arange(2.0, 16.0, 1.5), np.arange(-8.0, 8.1, 1.5), [0.5, 2.0, 3.5, 5.0])
    result, cov, _, _ = _flight(wide, G[visible(wide, G, 20.0)], 0)
    good = V.diagnose_geometry(result.camera, cov, result.points_world, result.pixels)
    assert not good.degenerate and good.message is None and good.focal_std_rel < 0.002


def test_coverage_rich_4k_camera_gets_a_rich_model_with_square_pixels():
    truth = pole_camera(**K4)
    G = sampling_grid(np.arange(4.0, 30.0, 2.0), np.arange(-10.0, 10.1, 1.5), [0.5, 2.0, 3.5, 5.0, 6.5])
    X = G[visible(truth, G, 30.0)]
    result, _, _, _ = _flight(truth, X, 0)
    assert result.model.distortion in ("k1k2", "k1k2p1p2", "full"), result.model
    assert result.camera.intrinsics.fx == result.camera.intrinsics.fy
    assert abs(result.camera.intrinsics.fx - 2600.0) < 5.0
    true = np.linalg.norm(result.camera.project(X) - truth.project(X), axis=1)
    assert np.median(true) < 0.5 and np.percentile(true, 90) < 2.0, np.percentile(true, [50, 90, 100])


def test_aspect_ratio_is_freed_only_when_the_data_demand_it():
    G = sampling_grid(np.arange(2.0, 16.0, 1.5), np.arange(-8.0, 8.1, 1.5), [0.5, 2.0, 3.5, 5.0])
    square = pole_camera(**WIDE)
    X = G[visible(square, G, 20.0)]
    result, _, _, _ = _flight(square, X, 1)
    assert result.camera.intrinsics.fx == result.camera.intrinsics.fy
    # A sensor 1 % taller than wide: the F-test frees the aspect ratio and finds it.
    tall = pole_camera(**WIDE, fy=909.0)
    result, _, _, _ = _flight(tall, X, 1)
    assert not result.model.fix_aspect_ratio
    assert abs(result.camera.intrinsics.fy / result.camera.intrinsics.fx - 1.01) < 0.002


def test_footprint_geojson_round_trips_to_the_ground_the_region_sees():
    truth = pole_camera(**WIDE)
    result, cov, region = _assess(truth, paper_grid(truth), 0)
    gj = region.geojson()
    ring = np.array(gj["features"][0]["geometry"]["coordinates"][0])
    assert gj["type"] == "FeatureCollection" and np.all(ring[0] == ring[-1])
    back = geodetic_to_enu(ring[:-1, 1], ring[:-1, 0], np.full(len(ring) - 1, ORIGIN.h_m), ORIGIN)
    assert np.abs(back[:, :2] - region.ground_polygon_enu_m[:, :2]).max() < 1e-3
    # Every footprint vertex projects onto (or within a pixel of) the region in the image.
    uv = result.camera.project(region.ground_polygon_enu_m)
    near = V.points_in_polygon(uv, V.grow_region(lambda p: np.ones(len(p), bool), region.polygon_px, 1920, 1080, steps=2))
    assert near.mean() > 0.9
    d = region.to_dict()
    assert d["visible_ground_fraction"] == region.visible_ground_fraction and len(d["polygon_px"]) == V.DIRECTIONS


def test_roi_fraction_counts_the_roi_ground_the_region_sees():
    truth = pole_camera(**WIDE)
    result, cov, s3, s2 = _flight(truth, paper_grid(truth), 0)
    region = V.assess_validity(result, cov, s3, s2)
    # The footprint itself lies inside the region.
    own = V.PlanRoi(range_m=(3.0, 30.0), polygon_enu_m=region.ground_polygon_enu_m[:, :2], text="the footprint")
    r = V.assess_validity(result, cov, s3, s2, roi=own, richer=region.richer)
    assert r.roi_fraction > 0.9 and not any("plan's ROI" in w for w in r.warnings)
    # A plan's range ROI, 3-40 m: mostly outside.
    plan = {"roi": {"kind": "range", "range_m": [3.0, 40.0], "polygon_site_m": None, "text": "the ground 3-40 m from the pole"}}
    roi = V.roi_from_plan(plan)
    r = V.assess_validity(result, cov, s3, s2, roi=roi, richer=region.richer)
    assert r.roi_fraction < 0.5 and any("plan's ROI (the ground 3-40 m from the pole)" in w for w in r.warnings)


def test_roi_from_plan_turns_a_site_polygon_into_enu():
    # Site frame: X along azimuth 90 deg (east), Y left (north).
    plan = {
        "enu_origin": {"lat_deg": ORIGIN.lat_deg, "lon_deg": ORIGIN.lon_deg, "h_m": ORIGIN.h_m},
        "site_frame": {"azimuth_deg": 90.0, "R_enu_from_site": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]},
        "roi": {"kind": "polygon", "range_m": [3.0, 40.0], "polygon_site_m": [[5.0, -2.0], [20.0, -2.0], [20.0, 2.0]], "text": "road.geojson"},
    }
    same = V.roi_from_plan(plan, ORIGIN)
    assert np.allclose(same.polygon_enu_m, [[5.0, -2.0], [20.0, -2.0], [20.0, 2.0]], atol=1e-6)
    # A calibration frame 10 m east of the plan's: the polygon moves 10 m west in it.
    east = geodetic_to_enu(ORIGIN.lat_deg, ORIGIN.lon_deg, ORIGIN.h_m, ORIGIN)  # (0, 0, 0)
    from dronecal_field.geodesy import enu_to_geodetic

    llh = enu_to_geodetic(east + [10.0, 0.0, 0.0], ORIGIN)[0]
    moved = V.roi_from_plan(plan, EnuOrigin(lat_deg=float(llh[0]), lon_deg=float(llh[1]), h_m=float(llh[2])))
    assert np.allclose(moved.polygon_enu_m, same.polygon_enu_m - [10.0, 0.0], atol=1e-3)
    assert V.roi_from_plan({"roi": None}) is None
    image = V.roi_from_plan({"roi": {"kind": "image", "range_m": [3.0, 60.0], "text": "the whole image"}})
    assert image.range_m == (0.0, 60.0) and image.polygon_enu_m is None


def test_grow_region_reaches_the_frame_when_all_is_supported_and_keeps_the_hull_when_nothing_is():
    hull = np.array([[800.0, 500.0], [1100.0, 500.0], [1100.0, 700.0], [800.0, 700.0]])
    everything = V.grow_region(lambda p: np.ones(len(p), bool), hull, 1920, 1080)
    assert V.polygon_area(everything) / (1920 * 1080) > 0.95
    nothing = V.grow_region(lambda p: np.zeros(len(p), bool), hull, 1920, 1080)
    assert V.polygon_area(nothing) == pytest.approx(V.polygon_area(hull), rel=0.02)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(0, 1000), st.floats(0, 1000)), min_size=3, max_size=40), st.integers(0, 2**31))
def test_convex_hull_holds_its_points_and_point_in_polygon_agrees(points, seed):
    P = np.array(points)
    hull = V.convex_hull(P)
    if len(hull) < 3 or V.polygon_area(hull) < 1.0:
        return
    # Every point lies inside the hull or on its boundary (shrink the points towards the centroid a hair).
    c = hull.mean(0)
    assert V.points_in_polygon(c + 0.999 * (P - c), hull).all()
    # Random probes: inside the convex hull iff on the inner side of every edge.
    q = np.random.default_rng(seed).uniform(-100, 1100, (200, 2))
    e = np.roll(hull, -1, 0) - hull
    side = e[None, :, 0] * (q[:, None, 1] - hull[None, :, 1]) - e[None, :, 1] * (q[:, None, 0] - hull[None, :, 0])
    inner = np.all(side > 1e-6, axis=1)
    outer = np.any(side < -1e-6, axis=1)
    got = V.points_in_polygon(q, hull)
    assert np.all(got[inner]) and not np.any(got[outer])
