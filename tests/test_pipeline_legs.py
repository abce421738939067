"""Fly-through legs: finding them, pairing each fix with the image track, rolling shutter, end to end."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from contract_writer import ORIGIN, MarkerLook, RunSpec, leg_waypoints, make_leg_flight, pole_camera, write_run
from dronecal_field.pipeline.legs import Leg, cubic_track_at, detection_times_ns, leg_points, legs_from_track, track_velocity
from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run
from dronecal_field.pipeline.sampling import FrameSelector, SamplingOptions


def test_cubic_track_is_exact_on_a_cubic_and_gives_its_rate():
    t = np.arange(0, 2_000_000_000, 100_000_000, dtype=np.int64)
    s = t * 1e-9
    values = np.c_[3 + 2 * s - s**2 + 0.5 * s**3, 10 * s]
    q = np.array([350_000_000, 1_230_000_000], np.int64)
    at, rate, valid = cubic_track_at(q, t, values)
    qs = q * 1e-9
    assert valid.all()
    np.testing.assert_allclose(at[:, 0], 3 + 2 * qs - qs**2 + 0.5 * qs**3, atol=1e-9)
    np.testing.assert_allclose(rate[:, 0], 2 - 2 * qs + 1.5 * qs**2, atol=1e-9)
    np.testing.assert_allclose(rate[:, 1], 10.0, atol=1e-9)
    # No four samples around the instant, or a gap: not valid.
    _, _, edge = cubic_track_at(np.array([50_000_000, 1_950_000_000]), t, values)
    _, _, gap = cubic_track_at(np.array([1_000_000_000]), np.r_[t[:10], t[10:] + 500_000_000], values)
    assert not edge.any() and not gap.any()


def test_legs_from_track_find_constant_velocity_stretches_not_holds():
    t = np.arange(0, 40_000_000_000, 200_000_000, dtype=np.int64)
    s = t * 1e-9
    x = np.clip(s - 5.0, 0, None) * 2.0  # hold 5 s, then 2 m/s east ...
    x = np.where(s > 15, 20.0, x)  # ... for 10 s, hold 5 s ...
    y = np.where(s > 20, (s - 20) * 1.5, 0.0)  # ... then 1.5 m/s north for 20 s
    y = np.minimum(y, 30.0)
    enu = np.c_[x, y, np.full_like(s, 3.0)] + np.random.default_rng(0).normal(0, 0.008, (len(s), 3))
    legs = legs_from_track(t, enu)
    assert len(legs) == 2
    assert [round(g.speed_mps, 1) for g in legs] == [2.0, 1.5]
    assert abs(legs[0].start_ns * 1e-9 - 5.2) < 0.5 and abs(legs[0].end_ns * 1e-9 - 14.8) < 0.5
    v = track_velocity(t, enu)
    assert np.nanmedian(np.linalg.norm(v[(s > 6) & (s < 14)], axis=1)) == pytest.approx(2.0, abs=0.05)


@settings(max_examples=25, deadline=None)
@given(
    offset_s=st.floats(-0.9, 0.9),
    readout_s=st.floats(0.0, 0.05),
    heading=st.floats(0, 2 * np.pi),
    height=st.floats(1.0, 5.0),
)
def test_leg_pairs_are_exact_under_offset_and_rolling_shutter(offset_s, readout_s, heading, height):
    # A marker crossing the view at 2 m/s; frames at 10 fps with a rolling shutter, stamped late by
    # the offset; GNSS fixes at 5 Hz. With the true offset and line time every fix's pixel is the
    # projection of its 3D position, to a fraction of a pixel.
    camera = pole_camera(width=1280, height=720, f_px=800, position_enu=(0, 0, 3.5), tilt_deg=20)
    start = np.array([0.0, 8.0, height])
    velocity = 2.0 * np.array([np.cos(heading), 0.3 * np.sin(heading), 0.0])

    def at(t_ns):
        return start + np.outer(np.asarray(t_ns) * 1e-9, velocity)

    frame_t = np.arange(0, 3_000_000_000, 100_000_000, dtype=np.int64)
    line = readout_s / camera.height
    row_t = frame_t.copy()
    for _ in range(3):  # the marker's row fixes when it was read out
        row_t = frame_t + np.round(camera.project(at(row_t))[:, 1] * line * 1e9).astype(np.int64)
    uv = camera.project(at(row_t))
    stamps = frame_t + int(round(offset_s * 1e9))
    fix_t = np.arange(0, 3_000_000_000, 200_000_000, dtype=np.int64)
    X = at(fix_t)
    V = np.repeat(velocity[None], len(fix_t), 0)
    leg = Leg(index=0, start_ns=0, end_ns=3_000_000_000, source="event")
    pts = leg_points(
        [leg], fix_t, X, V, np.full((len(fix_t), 3), 0.008), ["rtk_fixed"] * len(fix_t), stamps, uv,
        int(round(offset_s * 1e9)), line, 0.001, "rtk_fixed", first_index=3,
    )
    assert len(pts) >= 8
    err = np.array([np.linalg.norm(camera.project(p.marker_enu_m[None])[0] - p.uv_px) for p in pts])
    assert err.max() < 0.05
    assert [p.window.index for p in pts] == list(range(3, 3 + len(pts))) and {p.window.source for p in pts} == {"leg"}
    # The timing uncertainty enters each point's sigma: speed x time std in 3D.
    assert np.all([p.sigma_enu_m[0] >= 0.008 for p in pts])
    np.testing.assert_array_equal(detection_times_ns(stamps[:1], uv[:1, 1], int(round(offset_s * 1e9)), line), row_t[:1])


def test_frame_selector_decodes_along_legs():
    selector = FrameSelector([], SamplingOptions(leg_period_s=0.15, margin_s=0.5), legs=[(10_000_000_000, 14_000_000_000)])
    (a, b), = selector.read_windows()
    assert (a, b) == (9_500_000_000, 14_500_000_000)
    answers = [(t, *selector.wants(t)) for t in range(0, 20_000_000_000, 100_000_000)]
    decoded = [t for t, decode, _ in answers if decode]
    assert decoded[0] == 9_500_000_000 and decoded[-1] >= 14_300_000_000
    assert np.all(np.diff(decoded) == 200_000_000)  # every other frame of a 10 fps camera
    assert {g for _, decode, g in answers if decode} == {0}  # the legs' groups follow the (here no) windows


@pytest.fixture(scope="module")
def legs_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("legs")
    camera = pole_camera(width=960, height=540, f_px=450, position_enu=(0, 0, 3.5), tilt_deg=25, distortion=(-0.28, 0.07, 0, 0, 0))
    waypoints = leg_waypoints(camera, depths_m=(3.0, 5.0, 8.0), heights_m=(0.8, 2.0, 3.5, 5.0))
    flight = make_leg_flight(camera, waypoints, hold_s=0.0, speed_mps=2.0, seed=4)
    path = tmp / "legs.mcap"
    spec = RunSpec(site_origin=ORIGIN, latency_s=0.25, declared_latency="unknown", readout_s=0.03, exposure_s=0.004, gnss_hz=5.0, seed=8)
    write_run(path, camera, flight, MarkerLook(size_m=0.3), spec)
    quiet = tmp / "no-events.mcap"
    write_run(quiet, camera, flight, MarkerLook(size_m=0.3), RunSpec(**{**spec.__dict__, "with_events": False}))
    return camera, flight, path, quiet


def test_legs_alone_calibrate_with_rolling_shutter(legs_run):
    from dronecal_field.sim.compare import compare_cameras

    camera, flight, path, _ = legs_run
    report = calibrate_run(path, CalibrateOptions(trials=0))
    assert report.leg_source == "event" and len(report.legs) == len(flight.legs)
    assert not [p for p in report.hover_points if p.used]  # no hold in view (only the take-off spot, found in the track)
    assert len(report.leg_points) > 150
    # The offset and the 30 ms readout come from the motion itself.
    assert report.timing.rolling_shutter == "estimated"
    assert report.timing.readout_s == pytest.approx(0.03, abs=0.006)
    assert report.offset.offset_s == pytest.approx(0.25, abs=0.005)
    cmp = compare_cameras(camera, report.camera, sampled_enu_m=np.array([p.marker_enu_m for p in report.used_points]))
    assert cmp.focal_error_pct < 0.5 and cmp.principal_point_error_px < 3.0 and cmp.position_error_cm < 2.0
    assert cmp.sampled.rms_px < 0.5  # under 1 px over the sampled volume with a 30 ms readout at 2 m/s
    # The noise was measured on the residuals: white, about the 8-12 mm RTK noise plus the detector's.
    assert report.noise is not None and report.noise.sigma_corr_m < report.noise.sigma_white_m
    assert 0.005 < report.noise.sigma_white_m < 0.03
    data = report.offset.to_dict()
    assert data["rolling_shutter"]["rolling_shutter"] == "estimated" and data["gnss_fix_times"]["noise"]["n_residuals"] > 150
    # report.json gives each leg's used span, so the sampled volume is known without a hold (the demo printed nan)
    from dronecal_field.demo import used_marker_points
    from dronecal_field.pipeline.report import report_dict

    sampled = used_marker_points(json.loads(json.dumps(report_dict(report))), None, None)
    assert len(sampled) == 2 * sum(1 for g in report_dict(report)["legs"]["legs"] if g["pairs_used"])
    hull = compare_cameras(camera, report.camera, sampled_enu_m=sampled).sampled
    assert hull is not None and hull.rms_px < 0.5


def test_legs_without_events_are_found_in_the_track(legs_run):
    camera, flight, _, quiet = legs_run
    report = calibrate_run(quiet, CalibrateOptions(trials=0))
    assert report.leg_source == "gnss_track" and len(report.legs) >= len(flight.legs) // 2
    assert len(report.leg_points) > 100
    assert abs(report.camera.intrinsics.fx / camera.intrinsics.fx - 1) < 0.01


def test_a_global_shutter_is_found_to_be_one(tmp_path):
    camera = pole_camera(width=960, height=540, f_px=450, position_enu=(0, 0, 3.5), tilt_deg=25)
    waypoints = leg_waypoints(camera, depths_m=(3.0, 5.0, 8.0), heights_m=(0.8, 2.0, 3.5))
    flight = make_leg_flight(camera, waypoints, hold_s=0.0, speed_mps=2.0, seed=2)
    path = tmp_path / "global.mcap"
    write_run(path, camera, flight, MarkerLook(size_m=0.3), RunSpec(site_origin=ORIGIN, latency_s=-0.4, gnss_hz=10.0, seed=3))
    report = calibrate_run(path, CalibrateOptions(trials=0))
    assert report.timing.readout_s < 0.006
    assert report.offset.offset_s == pytest.approx(-0.4, abs=0.005)


def test_cubic_track_refuses_an_instant_where_the_cubic_swings_past_its_samples():
    """A jumpy image track (a marker close to the camera on a detour): the cubic there overshoots, so no pair is made.

    Measured on the demo's hover plan: 12 such pairs along the detours round the pole (pixels up to 500 px outside
    the image) pulled the whole calibration to 293 px RMS and a 7.5 % focal error; without them 1.50 px and 0.19 %.
    """
    t = np.arange(8, dtype=np.int64) * 100_000_000
    smooth = np.c_[100.0 + 40.0 * np.arange(8) + 2.0 * np.arange(8) ** 2, np.full(8, 50.0)]
    q = t[2:6] + 50_000_000
    at, _, valid = cubic_track_at(q, t, smooth)
    assert valid.all() and np.allclose(at[:, 0], 100.0 + 40.0 * (q / 1e8) + 2.0 * (q / 1e8) ** 2)
    # uneven frame times and a small jump: the cubic through samples 1-4 reaches 390 px at 0.2 s, its samples 100-160 px
    t = np.array([0, 100, 110, 400, 410, 700], np.int64) * 1_000_000
    jumpy = np.c_[[100.0, 100.0, 160.0, 100.0, 100.0, 100.0], np.full(6, 50.0)]
    q = np.array([200, 300, 350], np.int64) * 1_000_000
    c = np.polyfit(t[1:5] * 1e-9, jumpy[1:5, 0], 3)
    assert np.polyval(c, 0.2) == pytest.approx(389.66, abs=0.01)
    at, _, valid = cubic_track_at(q, t, jumpy)
    assert not valid[0] and not valid[1]  # 390 and 252 px: past 160 + 0.25 x 60 + 2 px
    assert valid[2] and at[2, 0] == pytest.approx(np.polyval(c, 0.35), abs=1e-6)  # 152 px: inside the span


def test_with_a_plan_attached_only_legs_between_its_sampling_points_are_paired(tmp_path):
    """A hover plan's detours and its way home are leg events too; only legs between two planned points are legs.

    Measured on the sim chain (the paper's Table 1 camera, 60 holds): 25 pairs on the transit and detour legs under
    the camera pulled the calibration to the full model and 12.99 px RMS over the ground 3-30 m; without them 0.74 px.
    """
    import json

    from dronecal_field.geodesy import EnuOrigin
    from dronecal_field.pipeline.run import _find_legs
    from dronecal_field.runfile.reader import open_run
    from dronecal_field.runfile.records import MarkerSpec, RunEvent, RunMetadata
    from dronecal_field.runfile.writer import RunWriter

    grid = [{"mission_seq": 4, "lat_deg": -35.3632, "lon_deg": 149.1652}, {"mission_seq": 5, "lat_deg": -35.36321, "lon_deg": 149.16525}]
    detour = (-35.36322, 149.16528)

    def nav(seq: int, lat: float, lon: float, hold: float) -> dict:
        return {"type": "SimpleItem", "command": 16, "doJumpId": seq, "frame": 3, "params": [hold, 0, 0, None, lat, lon, 2.0]}

    mission = {"fileType": "Plan", "mission": {"items": [nav(4, -35.3632, 149.1652, 3.0), nav(5, -35.36321, 149.16525, 0.0),
                                                         nav(6, *detour, 0.0), nav(7, -35.3632, 149.1652, 3.0)]}}
    t0 = 1_795_000_000_000_000_000
    md = RunMetadata(format_version=1, width=64, height=48, altitude_datum="ellipsoid", camera_latency_s=None,
                     marker=MarkerSpec(kind="aruco", dictionary="DICT_4X4_50", marker_id=0, size_m=0.3, offset_frd_m=(0.0, 0.0, 0.0)),
                     site_origin=EnuOrigin(lat_deg=-35.3632, lon_deg=149.1652, h_m=584.0))
    path = tmp_path / "run.mcap"
    with RunWriter(path, md) as w:
        w.attach("plan.json", json.dumps({"grid": grid}).encode(), "application/json")
        w.attach("mission.plan", json.dumps(mission).encode(), "application/json")
        for k, (a, b) in enumerate(((4, 5), (5, 6), (6, 7))):
            w.write_event(RunEvent(timestamp_ns=t0 + k * 2_000_000_000, duration_ns=1_500_000_000, type="leg",
                                   metadata={"seq_from": str(a), "seq_to": str(b)}))
    with open_run(path) as run:
        legs, source = _find_legs(run, None, [], CalibrateOptions())
    assert source == "event" and [(g.start_ns, g.end_ns) for g in legs] == [(t0, t0 + 1_500_000_000)]
