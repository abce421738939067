"""Issue 23: the scout flight. A two-minute mission whose marker every camera of the range sees (counted with each camera)."""

from __future__ import annotations

import itertools
import json
import math
from dataclasses import replace

import pytest

from dronecal_field.cli import main
from dronecal_field.plan.route import FlightModel
from dronecal_field.plan.scout import MAX_SCOUT_S, ScoutSpec, make_scout, scout_seen
from dronecal_field.plan.site import CameraSite, LensGuess, guess_camera
from dronecal_field.sampling.band import turned
from dronecal_field.sampling.lattice import Limits

SITE = CameraSite(lat_deg=-35.363261, lon_deg=149.16523, ground_h_m=584.0, mount_height_m=4.0, azimuth_deg=30.0, tilt_deg=0.0, geoid_separation_m=0.0)
LIMITS = Limits(min_agl_m=1.0, keep_out_m=2.0, marker_offset_frd_m=(0.1, 0.0, 0.05), quiet_zone_frac=1 / 6, max_search_height_m=7.0)


def test_plan_scout_writes_a_two_minute_mission(tmp_path):
    out = tmp_path / "scout"
    rc = main(["plan", "--scout", "--lat=-35.363261", "--lon", "149.16523", "--ground-alt", "584", "--mount-height", "4",
               "--azimuth", "30", "--out", str(out)])
    assert rc == 0
    s = json.loads((out / "plan.json").read_text())
    assert s["kind"] == "scout" and s["flight"]["flight_time_s"] <= MAX_SCOUT_S
    items = json.loads((out / "mission.plan").read_text())["mission"]["items"]
    waypoints = [it for it in items if it["command"] == 16]
    assert len(waypoints) >= 3 * len(s["scout"]["rows"])  # start, middle, end of each row (+ above the take-off point)
    assert all(it["params"][0] == 0 for it in waypoints[1:-2])  # one continuous pass: no hold between the first and the last
    assert all(g["mission_seq"] is not None for g in s["grid"])


def test_every_camera_of_the_range_sees_the_scout():
    """HFOV 30-110 deg, tilt 0-50 deg (60 from HFOV 50 up), azimuth within 30 deg of the given one: the marker, whole with its
    quiet zone, at GNSS fixes along the legs (10 Hz), counted with each camera."""
    scout = make_scout(SITE, ScoutSpec(), LIMITS, FlightModel())
    assert scout.route.flight_time_s <= MAX_SCOUT_S
    seen_min = {}
    for hfov, tilt, daz in itertools.product((30, 50, 70, 90, 110), (0, 10, 20, 30, 40, 50, 60), (-30, 0, 30)):
        f = 1920 / 2 / math.tan(math.radians(hfov / 2))
        lens = LensGuess(width=1920, height=1080, focal_px=f, distortion_level="strong" if hfov >= 90 else "medium", focal_source="")
        cam = turned(guess_camera(replace(SITE, tilt_deg=float(tilt)), lens, frame="site"), 0.0, float(daz))
        _, seen = scout_seen(cam, scout, LIMITS)
        seen_min[(hfov, tilt)] = min(seen_min.get((hfov, tilt), 10**9), int(seen.sum()))
    print(sorted(seen_min.items()))
    # the narrowest lens at the steepest tilts sees the short rows just outside the keep-out: 3 fixes (4 with the
    # old parallel rows, which a low pole's scout left coplanar)
    assert all(n >= 3 for (hfov, tilt), n in seen_min.items() if tilt <= 50 or hfov >= 50)
    assert all(n >= 40 for (hfov, tilt), n in seen_min.items() if hfov >= 70 and tilt <= 50)
    # a 30 deg lens tilted 60 deg down looks at ground inside the keep-out from a 4 m pole: the scout says so
    assert seen_min[(30, 60)] == 0 and any("depression 60 deg" in n and "--keep-out" in n for n in scout.notes)


def test_from_run_estimates_the_camera_of_a_scout_written_by_the_independent_writer(tmp_path):
    """The scout of a camera known only by its pole (height 0.2 m off, azimuth 15 deg off), flown in the independent
    writer's world (tests/contract_writer.py), estimated by ``plan --from-run``'s library call; the estimate against the truth."""
    import numpy as np
    from contract_writer import ORIGIN, MarkerLook, RunSpec, make_leg_flight, pole_camera, write_run

    from dronecal_field.plan.fromrun import axis_angles_deg, estimate_from_run

    truth = pole_camera(width=960, height=540, f_px=450.0, position_enu=(0.0, 0.0, 4.0), azimuth_deg=30.0, tilt_deg=25.0,
                        distortion=(-0.28, 0.07, 0.0, 0.0, 0.0))
    site = replace(SITE, lat_deg=ORIGIN.lat_deg, lon_deg=ORIGIN.lon_deg, ground_h_m=ORIGIN.h_m, mount_height_m=4.2, azimuth_deg=45.0)
    offset = (0.25, 0.0, 0.10)
    scout = make_scout(site, ScoutSpec(), replace(LIMITS, marker_offset_frd_m=offset), FlightModel())
    grid = np.array([k == "grid" for k in scout.route.kind])
    wps_enu = scout.route.points[grid] @ site.R_enu_from_site.T
    flight = make_leg_flight(truth, wps_enu, hold_s=scout.route.hold_s[grid], speed_mps=ScoutSpec().speed_m_s, offset_frd_m=offset, seed=3)
    path = tmp_path / "scout.mcap"
    write_run(path, truth, flight, MarkerLook(size_m=0.4), RunSpec(site_origin=ORIGIN, fps=10.0, gnss_hz=5.0, seed=5))
    est = estimate_from_run(path)
    az_t, tilt_t = axis_angles_deg(truth.pose.R_cam_from_world)
    i = est.camera.intrinsics
    print(f"scout estimate: f {i.fx:.1f} (truth 450) +- {est.sigma['focal_px']:.1f}, azimuth {est.azimuth_deg:.2f} ({az_t:.2f}), tilt {est.tilt_deg:.2f} "
          f"({tilt_t:.2f}), pp ({i.cx:.1f}, {i.cy:.1f}) ({truth.intrinsics.cx:.1f}, {truth.intrinsics.cy:.1f}), k1 {est.camera.distortion.k1:.3f}; "
          f"{est.points} points; band {est.tolerances()}")
    tol = est.tolerances()
    assert abs(i.fx / 450.0 - 1.0) * 100 < tol["focal_pct"]
    assert abs(est.azimuth_deg - az_t) < tol["azimuth_deg"] and abs(est.tilt_deg - tilt_t) < tol["tilt_deg"]
    assert abs(est.camera.distortion.k1 + 0.28) < 0.28 * tol["distortion_share"] + 0.03
