"""plan: intrinsics guess, camera guess, the paper's strategies, point order, flight-time model."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from conftest import REPLAYS as REPLAY, needs_replays
from dronecal_field.errors import InputError, PlanError
from dronecal_field.plan.route import FlightModel, detour, leg_time_s, order_points, plan_route
from dronecal_field.plan.site import CameraSite, LensGuess, guess_camera, load_site_file, resolve_focal_px
from dronecal_field.plan.strategies import evaluate_strategy
from dronecal_field.sampling.lattice import (
    Limits,
    alternatives,
    make_strategy,
    paper_strategies,
    recommended_strategy,
    sample_grid,
    screen_grid,
)

REPO = Path(__file__).resolve().parents[1]
CMAC = dict(lat_deg=-35.363261, lon_deg=149.165230, ground_h_m=584.0)


def paper_camera(distortion: str = "medium", azimuth: float = 0.0):
    site = CameraSite(**CMAC, mount_height_m=2.0, azimuth_deg=azimuth, tilt_deg=30.0)
    lens = LensGuess(width=1280, height=960, focal_px=1110.0, distortion_level=distortion, focal_source="test")
    return site, lens, guess_camera(site, lens, frame="site")


# --------------------------------------------------------------------------- intrinsics


def test_focal_from_lens_and_sensor_format():
    f, how = resolve_focal_px(3840, 2160, focal_mm=4.0, sensor_format='1/2.8"')
    # 1/2.8" is 6.46 mm diagonal; 16:9 gives 5.63 mm wide -> 4 / 5.63 * 3840
    assert f == pytest.approx(4.0 / (6.46 * 3840 / math.hypot(3840, 2160)) * 3840, rel=1e-9)
    assert 2700 < f < 2760
    assert "1/2.8" in how


@pytest.mark.parametrize(
    "kwargs, expected",
    [
        (dict(hfov_deg=90.0), 960.0),
        (dict(focal_mm=4.0, pixel_pitch_um=2.0), 2000.0),
        (dict(focal_mm=4.0, sensor_width_mm=5.76), 4.0 / 5.76 * 1920),
        (dict(focal_px=1234.0, hfov_deg=2 * math.degrees(math.atan(960 / 1234.0))), 1234.0),
    ],
)
def test_focal_forms(kwargs, expected):
    f, _ = resolve_focal_px(1920, 1080, **kwargs)
    assert f == pytest.approx(expected, rel=1e-9)


def test_focal_contradiction_and_missing_sensor_are_input_errors():
    with pytest.raises(InputError, match="disagrees"):
        resolve_focal_px(1920, 1080, focal_px=1000.0, hfov_deg=100.0)
    with pytest.raises(InputError, match="sensor"):
        resolve_focal_px(1920, 1080, focal_mm=4.0)
    with pytest.raises(InputError, match="no focal length"):
        resolve_focal_px(1920, 1080)


def test_guess_camera_looks_along_azimuth_and_tilt_in_both_frames():
    site, lens, cam_site = paper_camera("none", azimuth=37.0)
    cam_enu = guess_camera(site, lens, frame="enu")
    a, t = math.radians(37.0), math.radians(30.0)
    # 10 m along the optical axis from the camera projects to the principal point
    p_enu = np.array([0, 0, 2.0]) + 10 * np.array([math.sin(a) * math.cos(t), math.cos(a) * math.cos(t), -math.sin(t)])
    assert np.allclose(cam_enu.project(p_enu[None])[0], [640.0, 480.0], atol=1e-9)
    p_site = site.R_enu_from_site.T @ p_enu
    assert np.allclose(p_site, [10 * math.cos(t), 0.0, 2.0 - 10 * math.sin(t)], atol=1e-12)
    # the same physical points project identically through both
    pts = np.array([[5.0, 1.0, 0.5], [7.0, -2.0, 1.0]])
    assert np.allclose(cam_site.project(pts), cam_enu.project(pts @ site.R_enu_from_site.T), atol=1e-9)
    # a point to the camera's left (site +Y) is on the image's left
    assert cam_site.project(np.array([[6.0, 2.0, 0.5]]))[0, 0] < 640.0


def test_site_files_load_and_unknown_keys_are_named(tmp_path):
    values = load_site_file(REPO / "missions" / "security-4k.toml")
    assert values["image_size"] == "3840x2160" and values["mount_height"] == 4.0 and values["tilt"] == 25.0
    bad = tmp_path / "bad.toml"
    bad.write_text("lat = 1\nmount_hieght = 3\n")
    with pytest.raises(InputError, match="mount_hieght"):
        load_site_file(bad)


# --------------------------------------------------------------------------- strategies


def test_paper_strategies_and_recommendation():
    names = [s.name for s in paper_strategies()]
    assert len(names) == 18 and len(set(names)) == 18
    _, _, cam = paper_camera()
    rec = recommended_strategy(cam)
    assert (rec.name, rec.x_min_m, rec.x_max_m, rec.y_step_m, rec.n_heights) == ("far-y1-z2", 4.0, 8.0, 1.0, 2)
    alts = alternatives(rec)
    assert [s.name for s in alts] == ["far-y1-z2", "far-y0.5-z2", "far-y1-z3", "far-y1-z4", "near-y1-z2", "full-y1-z2"]
    wide = cam.with_(intrinsics=cam.intrinsics.__class__(fx=400.0, fy=400.0, cx=640.0, cy=480.0, width=1280, height=960))
    assert recommended_strategy(wide).name == "near-y0.5-z2"  # HFOV 116 deg: 0.5 m along Y, nearer


def test_sample_grid_points_are_seen_big_enough_and_allowed():
    _, _, cam = paper_camera("medium")
    limits = Limits(min_agl_m=0.5, keep_out_m=2.0, marker_size_m=0.3)
    screen = screen_grid(make_strategy("full", 1.0, 2), cam, limits)
    pts = screen.points
    assert np.array_equal(pts, sample_grid(make_strategy("full", 1.0, 2), cam, limits))
    assert len(pts) >= 30 and len(screen.heights_m) == 2
    uv = cam.project(pts)
    assert np.all((uv >= 10) & (uv <= [1269, 949]))
    assert screen.marker_px[screen.keep].min() >= 20.0
    veh = screen.vehicle_points
    assert np.hypot(veh[:, 0], veh[:, 1]).min() >= 2.0 and veh[:, 2].min() >= 0.5 - 1e-9
    # the near rows behind or under the camera are dropped, with the reason counted
    assert screen.reasons.get("outside_image", 0) + screen.reasons.get("behind_camera", 0) > 0
    assert sum(screen.reasons.values()) == len(screen.marker_site) - len(pts)


def test_marker_offset_moves_the_drone_not_the_marker():
    _, _, cam = paper_camera("none")
    limits = Limits(min_agl_m=0.5, marker_offset_frd_m=(0.2, 0.0, 0.3))
    screen = screen_grid(make_strategy("far"), cam, limits)
    d = screen.marker_site - screen.vehicle_site
    # marker 0.2 m ahead (towards the pole, horizontally) and 0.3 m below the drone
    assert np.allclose(d[:, 2], -0.3)
    towards_pole = -screen.vehicle_site[:, :2] / np.linalg.norm(screen.vehicle_site[:, :2], axis=1, keepdims=True)
    assert np.allclose(np.sum(d[:, :2] * towards_pole, axis=1), 0.2, atol=1e-6)


def test_small_marker_drops_points_and_names_the_size_that_works():
    _, _, cam = paper_camera("none")
    limits = Limits(min_agl_m=0.5, marker_size_m=0.08)
    screen = screen_grid(make_strategy("far"), cam, limits)
    need = screen.needed_marker_size_m(limits)
    assert screen.reasons["marker_too_small"] > 0
    assert need is not None and 0.08 < need < 0.3
    bigger = screen_grid(make_strategy("far"), cam, Limits(min_agl_m=0.5, marker_size_m=need + 0.005))
    assert bigger.reasons.get("marker_too_small", 0) == 0


def test_evaluate_strategy_predicts_uncertainty():
    _, _, cam = paper_camera("medium")
    score = evaluate_strategy(cam, make_strategy("far"), Limits(min_agl_m=0.5), trials=40, seed=1)
    assert score.usable and score.n_points >= 30
    # 2 px detection noise + 1 cm RTK at 4-8 m: the RMS reprojection error is a few pixels
    assert 2.0 < score.rms_mean_px < 8.0 and score.rms_p95_px >= score.rms_mean_px
    assert 0.5 < score.ground_error_15m_cm < 100.0
    assert 120 < score.flight_time_s < 900
    flat = evaluate_strategy(cam, make_strategy("far", n_heights=2), Limits(min_agl_m=0.5, max_agl_m=0.6), trials=40)
    assert not flat.usable and "height" in flat.problem


# --------------------------------------------------------------------------- route and time


def replay_grid() -> np.ndarray:
    """The replayed SITL mission's lattice: X 4..8, Y -3..3, Z 1.5 and 2.5 (site frame)."""
    X, Y, Z = np.meshgrid(np.arange(4.0, 9.0), np.arange(-3.0, 4.0), [1.5, 2.5], indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)


def test_order_is_boustrophedon_per_level_with_one_climb():
    pts = replay_grid()
    o = order_points(pts)
    p = pts[o]
    assert sorted(o.tolist()) == list(range(70))
    assert np.all(p[:35, 2] == 1.5) and np.all(p[35:, 2] == 2.5)  # one climb
    steps = np.linalg.norm(np.diff(p, axis=0), axis=1)
    assert np.allclose(steps, 1.0)  # every leg is 1 m, the climb included
    assert p[0, :2].tolist() == [4.0, -3.0] and p[6, :2].tolist() == [4.0, 3.0] and p[7, :2].tolist() == [5.0, 3.0]
    assert p[35, :2].tolist() == p[34, :2].tolist()  # the second level starts above the end of the first
    assert p[-1, 0] == 4.0


@needs_replays
def test_flight_time_model_matches_the_sitl_replay():
    checks = json.loads((REPLAY / "calib-grid-rtk.checks.json").read_text())
    reached = {int(r[0]): float(r[1]) for r in checks["reached"]}  # [seq, SITL s, ...]
    fm = FlightModel(speed_m_s=1.5, hover_s=3.0)
    cycle = float(leg_time_s(1.0, fm)) + fm.hover_s
    assert 6.9 <= cycle <= 7.2  # README: one seq every 6.9-7.2 s
    measured = reached[73] - reached[4]  # 69 cycles of a 1 m leg + 3 s hold
    assert measured == pytest.approx(479.3, abs=0.1)
    assert abs(69 * cycle - measured) / measured < 0.02


def test_detour_goes_round_the_keep_out():
    a, b = np.array([1.0, -3.0, 1.0]), np.array([1.0, 3.0, 2.0])
    pts = detour(a, b, 2.0)
    assert len(pts) >= 2
    poly = np.vstack([a, *pts, b])
    for p, q in zip(poly[:-1], poly[1:]):
        t = np.linspace(0, 1, 200)[:, None]
        seg = p[None, :2] + t * (q[:2] - p[:2])[None]
        assert np.hypot(seg[:, 0], seg[:, 1]).min() >= 2.0 - 1e-9
    assert pts[0][2] == pytest.approx(1.0) and pts[-1][2] == pytest.approx(2.0)
    assert detour(np.array([4.0, -3.0, 1.0]), np.array([4.0, 3.0, 1.0]), 2.0) == []


def test_route_takes_off_beside_the_grid_and_lands_there():
    pts = replay_grid()
    r = plan_route(pts, pts, Limits(keep_out_m=2.0), FlightModel())
    assert np.hypot(*r.takeoff_site[:2]) >= 2.0
    assert r.kind[-1] == "home" and np.allclose(r.points[-1, :2], r.takeoff_site[:2])
    assert (r.grid_index >= 0).sum() == 70 and np.all(r.hold_s[r.grid_index >= 0] == 3.0)
    assert r.takeoff_alt_m == 2.0
    # 70 holds of ~7 s plus take-off, first leg, return and landing
    assert 70 * 6.9 < r.flight_time_s < 70 * 7.2 + 60
    rtl = plan_route(pts, pts, Limits(keep_out_m=2.0), FlightModel(), end="rtl")
    assert rtl.flight_time_s > r.flight_time_s  # RTL climbs to 15 m first
    tight = ((3.5, -3.5), (8.5, -3.5), (8.5, 3.5), (3.5, 3.5))  # a geofence with no room beside the grid
    with pytest.raises(PlanError, match="--takeoff"):
        plan_route(pts, pts, Limits(keep_out_m=2.0, geofence_xy=tight), FlightModel())


def test_every_flag_is_documented():
    from dronecal_field.plan.site import OPTIONS

    doc = (REPO / "docs" / "plan.md").read_text()
    missing = [o.flag for o in OPTIONS if f"`{o.flag}`" not in doc and f"{o.flag}`" not in doc]
    assert missing == []
    assert len(OPTIONS) == 54  # issue 23 added --focal-tolerance, --tilt-tolerance, --azimuth-tolerance, --distortion-range; issue 10 added --marker-sizes, --exposure-s, --gnss-hz, --strategy, --sampling, --roi, --roi-range


@pytest.mark.parametrize("origin", [(-35.363261, 149.165230, 584.0), (0.0, 0.0, 0.0), (64.1, -21.9, 40.0), (-0.5, 179.9999, 10.0)])
def test_site_enu_wgs84_round_trip_within_a_millimetre(origin):
    from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic, geodetic_to_enu
    from dronecal_field.plan.site import latlon_to_site

    site = CameraSite(lat_deg=origin[0], lon_deg=origin[1], ground_h_m=origin[2], mount_height_m=3.0, azimuth_deg=123.0, tilt_deg=20.0)
    rng = np.random.default_rng(3)
    pts_site = rng.uniform([-50, -50, 0], [50, 50, 20], size=(200, 3))
    geo = enu_to_geodetic(pts_site @ site.R_enu_from_site.T, site.origin)
    back = latlon_to_site(site, geo[:, :2], geo[:, 2])
    assert np.abs(back - pts_site).max() < 1e-3
    assert np.abs(geodetic_to_enu(geo[:, 0], geo[:, 1], geo[:, 2], EnuOrigin(*origin)) @ site.R_enu_from_site - pts_site).max() < 1e-3


def test_every_leg_of_a_near_route_clears_the_keep_out():
    X, Y, Z = np.meshgrid(np.arange(0.0, 5.0), np.arange(-3.0, 4.0), [1.0, 2.0], indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    pts = pts[np.hypot(pts[:, 0], pts[:, 1]) >= 2.0]  # what the screening keeps
    r = plan_route(pts, pts, Limits(keep_out_m=2.0), FlightModel())
    path = np.vstack([r.takeoff_site + [0, 0, r.takeoff_alt_m], r.points])
    t = np.linspace(0.0, 1.0, 100)[None, :, None]
    seg = path[:-1, None, :2] + t * (path[1:, None, :2] - path[:-1, None, :2])
    assert np.hypot(seg[..., 0], seg[..., 1]).min() >= 2.0 - 1e-9
    assert r.kind.count("detour") >= 2  # rows at X = 0, 1 cross in front of the pole
    assert (r.grid_index >= 0).sum() == len(pts)


# --------------------------------------------------------------------------- one scoring path with the survey


@pytest.mark.parametrize(
    "k, min_slope, expected",
    [
        ((-0.25, 0.0, 0.0, 0.0, 0.0), 0.0, math.sqrt(1 / 0.75)),  # 1 - 3 * 0.25 r^2 = 0
        ((-0.25, 0.0, 0.0, 0.0, 0.0), 0.05, math.sqrt(0.95 / 0.75)),
        ((-0.01, 0.0, 0.0, 0.0, 0.0), 0.0, math.sqrt(1 / 0.03)),  # folds at r = 5.77, beyond any image
        ((-0.4, 0.15, 0.0, 0.0, 0.0), 0.0, math.inf),  # the 'strong' guess: the slope dips to 0.52 and climbs again
        ((0.1, 0.0, 0.0, 0.0, 0.0), 0.0, math.inf),
    ],
)
def test_fold_radius_is_where_the_radial_map_stops_growing(k, min_slope, expected):
    from dronecal_field.sampling.lattice import fold_radius

    r = fold_radius(np.array(k), min_slope)
    if math.isinf(expected):
        assert math.isinf(r)
    else:
        assert r == pytest.approx(expected, abs=1.1e-3)


def test_plan_candidates_are_the_survey_rows():
    """plan's scores are the survey's score_strategies rows for PlanLattice: same points, same numbers."""
    from dronecal_field.plan.strategies import score_candidates
    from dronecal_field.survey.catalogue import PlanLattice
    from dronecal_field.survey.evaluate import MonteCarloSettings
    from dronecal_field.survey.runner import score_strategies

    _, _, cam = paper_camera("medium")
    limits = Limits(min_agl_m=0.5)
    strategies = alternatives(make_strategy("far"))
    settings = MonteCarloSettings(trials=40, seed=3)
    scores = score_candidates(cam, strategies, limits, settings)
    rows = score_strategies(cam, strategies, PlanLattice(limits), settings)
    assert [s.strategy.name for s in scores] == [r["strategy"] for r in rows] == [s.name for s in strategies]
    usable = 0
    for score, row in zip(scores, rows):
        if score.usable:
            usable += 1
            assert row["status"] == "ok" and row["n_points"] == score.n_points
            assert score.rms_mean_px == row["rms_mean"] and score.ground_error_15m_cm == row["ground_error_15m_cm"]
            assert score.uncertainty["trials"] == 40 and score.uncertainty["n_points"] == score.n_points
            assert score.ground_error_15m_cm_p95 >= score.ground_error_15m_cm
    assert usable >= 4
    # the single-candidate form is the same path
    one = evaluate_strategy(cam, strategies[0], limits, trials=40, seed=3)
    assert one.rms_mean_px == scores[0].rms_mean_px and one.flight_time_s == scores[0].flight_time_s


def test_make_plan_on_a_local_cluster_gives_the_same_plan():
    from dronecal_field.cluster import dask_client
    from dronecal_field.plan.site import resolve_options
    from dronecal_field.plan.stage import make_plan, request_from_options

    values = load_site_file(REPO / "missions" / "paper-pinhole.toml")
    values.update(trials=30, optimize=True)
    req = request_from_options(resolve_options(values))
    here = make_plan(req)
    with dask_client(None, 2) as client:
        there = make_plan(req, client=client)
        assert len(client.scheduler_info()["workers"]) == 2
    assert len(here.candidates) == len(there.candidates) == 18
    # equal to round-off: a worker's numba threads split the engine's reductions differently (4.21129182229112 against
    # 4.2112918222911215 px in one CI run), the plan itself identical
    for a, b in zip(there.candidates, here.candidates):
        ra, rb = a.row(), b.row()
        assert ra.keys() == rb.keys()
        for key in ra:
            if isinstance(ra[key], float):
                assert ra[key] == pytest.approx(rb[key], rel=1e-9), (a.name, key)
            else:
                assert ra[key] == rb[key], (a.name, key)
    assert there.chosen.name == here.chosen.name
    assert np.array_equal(there.grid_site, here.grid_site)
