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
    assert all(n >= 4 for (hfov, tilt), n in seen_min.items() if tilt <= 50 or hfov >= 50)
    assert all(n >= 50 for (hfov, tilt), n in seen_min.items() if hfov >= 70 and tilt <= 50)
    # a 30 deg lens tilted 60 deg down looks at ground inside the keep-out from a 4 m pole: the scout says so
    assert seen_min[(30, 60)] == 0 and any("58 deg" in n for n in scout.notes)
