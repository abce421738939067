"""plan --site with several cameras (issue 24): one mission whose holds each camera reads, files that read back, one-line errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dronecal_field.cli import main
from dronecal_field.core.camera import Camera
from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu

# Two cameras on one pole, 90 deg apart, and a small search (one marker, holds only, ground 3-15 m): a test-sized site.
SITE = """
name = "test site"
geoid_separation = 0.0
marker_size = 0.3
marker_offset = [0.15, 0.0, 0.05]
sampling = "hover"
roi_range = [3.0, 15.0]
endurance = 20.0
trials = 20

[[pole]]
name = "p"
lat = -35.363261
lon = 149.165230
ground_alt = 584.0

[[camera]]
name = "east"
pole = "p"
mount_height = 3.0
azimuth = 90.0
tilt = 25.0
image_size = "1280x960"
focal_px = 1110
distortion = "medium"

[[camera]]
name = "north-wide"
pole = "p"
mount_height = 3.5
azimuth = 0.0
tilt = 25.0
image_size = "1920x1080"
focal_px = 900
distortion = [-0.28, 0.07]
"""


def _camera(entry: dict) -> Camera:
    """A plan.json camera entry's guessed camera, world = ENU at its pole's foot."""
    g = entry["camera_guess"]
    R = np.asarray(g["rotation_world_to_camera"], float)
    c = np.asarray(g["position_enu_m"], float)
    f = float(g["focal_px"])
    return Camera.from_arrays([f, f, g["cx"], g["cy"]], g["distortion_k1_k2_p1_p2_k3"], R, -R @ c, int(g["width"]), int(g["height"]))


@pytest.fixture(scope="module")
def site_plan(tmp_path_factory):
    d = tmp_path_factory.mktemp("site")
    (d / "site.toml").write_text(SITE)
    out = d / "plan"
    assert main(["plan", "--site", str(d / "site.toml"), "--out", str(out), "--max-flight-time", "10"]) == 0
    return out, json.loads((out / "plan.json").read_text())


def test_one_mission_every_camera_reads_its_holds(site_plan):
    out, s = site_plan
    assert s["kind"] == "site" and [c["name"] for c in s["cameras"]] == ["east", "north-wide"]
    f = s["flight"]
    assert f["n_flights"] == 1 and f["flight_time_s"] <= 600.0 + 1e-6 and f["fits_one_flight"]
    o = s["enu_origin"]
    origin = EnuOrigin(o["lat_deg"], o["lon_deg"], o["h_m"])
    # the drone positions of plan.json, marker on the nose facing its camera's pole, projected through each camera's guess
    grid = s["grid"]
    drone = geodetic_to_enu(np.array([g["lat_deg"] for g in grid]), np.array([g["lon_deg"] for g in grid]),
                            np.array([g["h_m"] for g in grid]), origin)
    yaw = np.radians([g["yaw_deg"] for g in grid])
    fwd = np.stack([np.sin(yaw), np.cos(yaw), np.zeros_like(yaw)], 1)
    right = np.stack([np.cos(yaw), -np.sin(yaw), np.zeros_like(yaw)], 1)
    marker = drone + 0.15 * fwd + 0.0 * right - np.array([0.0, 0.0, 0.05])
    for entry in s["cameras"]:
        cam = _camera(entry)  # its pole is the site origin here
        uv = cam.project(marker)
        depth = cam.depth(marker)
        inside = (depth > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        own = np.array([g["camera"] == entry["name"] for g in grid])
        seen = np.array([entry["name"] in g["seen_by"] for g in grid])
        assert own.sum() == entry["holds_owned"] >= 10  # two depths over a lattice of at least 3x3 targets, less what the limits drop
        assert inside[own].all()  # every hold designed for a camera is in its image
        assert inside[seen].all() and seen.sum() == entry["holds_seen"] >= own.sum()
        # the holds face their camera: yaw is the bearing to the pole (both cameras on one pole)
        bearing = np.degrees(np.arctan2(-drone[:, 0], -drone[:, 1])) % 360
        assert np.allclose((np.asarray([g["yaw_deg"] for g in grid]) - bearing + 180) % 360 - 180, 0.0, atol=0.05)
        # the pixels plan.json gives are the camera's projection
        px = np.array([g["seen_by"][entry["name"]]["pixel"] for g in grid if entry["name"] in g["seen_by"]])
        assert np.allclose(px, uv[seen], atol=1.0)
        assert 40.0 <= entry["coverage"]["pct"] <= 100.0
        assert entry["predicted_ground_cm_rms"] is not None and entry["predicted_ground_cm_rms"] > 0
        assert entry["roi"]["kind"] == "range"
    assert (out / "camera_guess-east.yaml").is_file() and (out / "camera_guess-north-wide.yaml").is_file()


def test_mission_files_read_back(site_plan):
    from dronecal_field.mavlink.missionfile import read_mission

    out, s = site_plan
    plan = read_mission(out / "mission.plan")
    wpl = read_mission(out / "mission.waypoints")
    nav_p = [(i.lat_deg, i.lon_deg, i.z) for i in plan.nav_items if i.command == 16]
    nav_w = [(i.lat_deg, i.lon_deg, i.z) for i in wpl.nav_items if i.command == 16]
    assert np.allclose(nav_p, nav_w, atol=1e-6)
    holds = np.array([[g["lat_deg"], g["lon_deg"]] for g in s["grid"]])
    flown = np.array(nav_p)[:, :2]
    assert np.abs(holds[:, None] - flown[None]).max(axis=2).min(axis=1).max() < 2e-7  # every hold is a waypoint (1e-7 deg wire quantum)
    assert len(s["grid"]) == s["points"]
    # one DO_SET_ROI per camera group, at that camera (same pole: same lat/lon, its own height)
    rois = [i for i in plan.items if i.command == 201]
    assert len(rois) == 2
    for r in rois:
        assert r.lat_deg == pytest.approx(s["poles"][0]["lat_deg"], abs=1e-7) and r.lon_deg == pytest.approx(s["poles"][0]["lon_deg"], abs=1e-7)
    assert sorted(round(r.z - s["home"]["h_m"] + s["poles"][0]["h_m"], 1) for r in rois) == [3.0, 3.5]
    # the mission_seq of every hold is a NAV_WAYPOINT at that hold
    for g in s["grid"]:
        it = plan.items[g["mission_seq"]]
        assert it.command == 16 and it.lat_deg == pytest.approx(g["lat_deg"], abs=2e-7)
    px4 = json.loads((out / "mission-px4.plan").read_text())
    assert sum(1 for i in px4["mission"]["items"] if i["command"] == 195) == 2  # DO_SET_ROI_LOCATION for PX4


@pytest.mark.parametrize("body, needle", [
    (SITE.replace('name = "north-wide"', 'name = "east"'), "camera name 'east' is used twice"),
    (SITE.replace('name = "north-wide"', 'name = "North Wide"'), "camera name 'North Wide' is not [a-z0-9]"),
    (SITE.replace('pole = "p"\nmount_height = 3.5', 'pole = "q"\nmount_height = 3.5'), "pole 'q' is not one of the [[pole]] tables"),
    (SITE.replace("tilt = 25.0\nimage_size = \"1280x960\"", "image_size = \"1280x960\""), "camera 'east': missing tilt"),
    (SITE.replace("lon = 149.165230\n", ""), "pole 'p' has no lon"),
    (SITE.replace("distortion = [-0.28, 0.07]", "distortion = [-0.28, 0.07, 0.1]"), "distortion [-0.28, 0.07, 0.1] is not"),
    (SITE.replace("focal_px = 900", "focal_px = 900\nmarker_sizes = [0.3]"), "unknown key(s) marker_sizes"),
    (SITE.replace("mount_height = 3.5", "mount_height = -3.5"), "camera 'north-wide': --mount-height -3.5 is outside"),
])
def test_bad_site_files_give_one_line(tmp_path, capsys, body, needle):
    p = tmp_path / "site.toml"
    p.write_text(body)
    rc = main(["plan", "--site", str(p), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err.strip()
    assert rc != 0 and needle in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "out").exists()


def test_single_camera_site_file_still_plans_one_camera(tmp_path):
    from dronecal_field.plan.multisite import is_multi_site

    assert not is_multi_site("missions/security-4k.toml") and is_multi_site("missions/site-two-poles.toml")
    (tmp_path / "s.toml").write_text(SITE)
    assert is_multi_site(tmp_path / "s.toml")
    (tmp_path / "one.toml").write_text("[camera]\nlat = 1.0\n")
    assert not is_multi_site(tmp_path / "one.toml")


def test_marker_seen_needs_view_size_and_facing():
    from dronecal_field.core.camera import CameraPose, Distortion, Intrinsics, look_rotation
    from dronecal_field.plan.multiplan import MAX_FACING_DEG, marker_seen

    # 1280x960, f 1110 px, 3 m up, looking along +X (east in ENU terms here) 20 deg down
    fwd = np.array([math.cos(math.radians(20)), 0.0, -math.sin(math.radians(20))])
    cam = Camera(intrinsics=Intrinsics(fx=1110.0, fy=1110.0, cx=640.0, cy=480.0, width=1280, height=960), distortion=Distortion(),
                 pose=CameraPose.from_position(look_rotation(fwd), np.array([0.0, 0.0, 3.0])))
    marker = np.array([[6.0, 0.0, 1.0], [6.0, 0.0, 1.0], [6.0, 0.0, 1.0], [40.0, 0.0, 1.0], [6.0, 30.0, 1.0]])
    turn = math.radians(MAX_FACING_DEG + 5)
    facing = np.array([[-1.0, 0.0], [-math.cos(turn), math.sin(turn)], [-math.cos(math.radians(50)), math.sin(math.radians(50))],
                       [-1.0, 0.0], [-1.0, 0.0]])
    ok, uv, px = marker_seen(cam, marker, facing, 0.3, 20.0)
    assert ok.tolist() == [True, False, True, False, False]  # facing, turned 65 deg, turned 50 deg, 8 px at 40 m, outside the image
    assert px[0] == pytest.approx(1110 * 0.3 / math.hypot(6.0, 2.0), rel=1e-6)  # 52.7 px face-on
    assert px[2] == pytest.approx(px[0] * math.cos(math.radians(50)), rel=1e-6)
    assert uv[0, 0] == pytest.approx(640.0, abs=1e-6)


def test_the_goal_site_gives_every_camera_holds_at_two_depths():
    """missions/site-two-poles (the issue's one-battery goal, one flight <= 15 min): the holds each camera sees pass
    calibrate's own geometry check (not collinear, not coplanar, enough points off the main plane), so no camera of the
    site is refused as coplanar, and they reach at least two distances along the camera's rays."""
    from dronecal_field.core.calibrate import check_correspondences

    s = json.loads(open("missions/site-two-poles/plan.json").read())
    assert s["flight"]["n_flights"] == 1 and s["flight"]["flight_time_s"] <= 900.0
    R = np.asarray(s["site_frame"]["R_enu_from_site"], float)
    for entry in s["cameras"]:
        name = entry["name"]
        seen = [g for g in s["grid"] if name in g["seen_by"]]
        X = np.array([g["marker_site_m"] for g in seen]) @ R.T  # ENU at the site origin
        uv = np.array([g["seen_by"][name]["pixel"] for g in seen])
        check_correspondences(X, uv, 9, 0.05)  # raises DegenerateGeometryError as calibrate would
        centre = np.asarray(entry["position_site_enu_m"], float)
        depth = np.linalg.norm(X - centre, axis=1)
        assert depth.max() / depth.min() > 1.5, (name, depth.min(), depth.max())
