"""A site run's legs, per camera: a fly-through leg counts for the camera it was designed for only (issue 24).

The site plan chooses a leg's speed for its own camera's focal length and distance and counts its fixes for that
camera alone (plan.multiplan.cross_visibility). calibrate keeps, per camera of a run carrying the site's plan.json, the
legs between two of that camera's own grid points: on the four-camera simulator flight a-4k (a hover layout) paired
a-wide's legs it saw, 259 pairs whose 8 fps timing at a-wide's speed took it from 0.53 to 1.06 px over the ground.

The run is the independent writer's (write_site_run) with the committed site plan's mission.plan and plan.json
attached, as fly attaches them; a few frames only (the legs are read from the attachments).
"""

from __future__ import annotations

import json
from pathlib import Path

from contract_writer import ORIGIN, MarkerLook, RunSpec, SiteCamera, facing_point, make_flight, pole_camera, site_waypoints, write_site_run
from dronecal_field.pipeline.track import _planned_sample_seqs
from dronecal_field.runfile.reader import open_run

PLAN = Path(__file__).resolve().parents[1] / "missions" / "site-two-poles"


def test_each_camera_keeps_the_legs_of_its_own_grid_points(tmp_path):
    plan = json.loads((PLAN / "plan.json").read_text())
    cams = [pole_camera(azimuth_deg=-20, position_enu=(0.0, 0.0, 5.0)), pole_camera(azimuth_deg=20, position_enu=(0.0, 0.0, 5.0))]
    flight = make_flight(facing_point(cams), site_waypoints(cams, lateral_m=(0.0,), ahead_m=(6.0,), up_m=(2.0,)), hold_s=1.0, move_s=1.0)
    path = tmp_path / "site.mcap"
    attach = {"mission.plan": (PLAN / "mission.plan").read_bytes(), "plan.json": (PLAN / "plan.json").read_bytes()}
    write_site_run(path, [SiteCamera("a-wide", cams[0]), SiteCamera("a-4k", cams[1])], flight, MarkerLook(),
                   RunSpec(fps=1.0, seed=1, site_origin=ORIGIN, attachments=attach))
    own = {name: {g["mission_seq"] for g in plan["grid"] if g["camera"] == name} for name in ("a-wide", "a-4k")}
    seqs = {}
    for name in ("a-wide", "a-4k"):
        with open_run(path, camera=name) as run:
            seqs[name] = _planned_sample_seqs(run)
    assert seqs["a-wide"] == own["a-wide"] and len(seqs["a-wide"]) == 18  # the wide camera's fly-through layout
    assert seqs["a-4k"] == own["a-4k"] and len(seqs["a-4k"]) == 24  # the 4K's hover layout: none of a-wide's legs
    assert not seqs["a-wide"] & seqs["a-4k"]
