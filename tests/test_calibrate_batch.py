"""``dronecal-field calibrate`` on many runs: a real 2-worker local Dask cluster, one folder per run, the summary.

Two pole cameras with different lenses and headings, each flown once
(written by the independent contract writer), plus one file that is not a
run at all: the good cameras come back within 1 % of their true focal
length, the broken one is listed with its error and stops nothing.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from conftest import run_cli
from contract_writer import ORIGIN, MarkerLook, RunSpec, grid_waypoints, make_flight, pole_camera, write_run
from dronecal_field.camerafile import read_camera
from dronecal_field.errors import InputError
from dronecal_field.pipeline.batch import COLUMNS, plan_tasks
from dronecal_field.pipeline.run import CalibrateOptions


def _east_facing(waypoints: np.ndarray, pole_enu: tuple[float, float]) -> np.ndarray:
    """The north-facing grid turned 90 deg clockwise and moved to a pole at ``pole_enu``, for a camera looking east."""
    return np.column_stack([waypoints[:, 1] + pole_enu[0], -waypoints[:, 0] + pole_enu[1], waypoints[:, 2]])


@pytest.fixture(scope="module")
def campus(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("campus")
    grid = grid_waypoints(east_m=(-3.0, 0.0, 3.0), up_m=(1.0, 4.0))
    cameras = {
        "pole-north": (pole_camera(f_px=520.0), grid, 22),
        "pole-east": (pole_camera(f_px=700.0, azimuth_deg=90.0, position_enu=(1.0, -2.0, 4.5)), _east_facing(grid, (1.0, -2.0)), 24),
    }
    paths = []
    for name, (camera, waypoints, seed) in cameras.items():
        flight = make_flight(camera, waypoints, hold_s=2.5, move_s=1.5, seed=seed)
        path = tmp / f"{name}.mcap"
        write_run(path, camera, flight, MarkerLook(), RunSpec(fps=8.0, latency_s=0.25, site_origin=ORIGIN))
        paths.append(path)
    broken = tmp / "pole-broken.mcap"
    broken.write_bytes(b"not an mcap file at all")
    paths.insert(1, broken)
    out = tmp / "campus-calibration"
    proc = run_cli("calibrate", *map(str, paths), "--out", str(out), "--workers", "2", "--trials", "60", timeout=180)
    return {name: cam for name, (cam, _, _) in cameras.items()}, paths, out, proc


@pytest.mark.slow  # ~15-20 s: a 2-worker cluster starts and each worker loads cv2 and the kernels
def test_each_good_camera_is_calibrated_within_one_percent(campus):
    truth, _, out, proc = campus
    assert proc.returncode == 1, proc.stderr  # one run failed
    for name, camera in truth.items():
        cam = read_camera(out / name / "camera.yaml")
        assert abs(cam.intrinsics.fx / camera.intrinsics.fx - 1) < 0.01, (name, cam.intrinsics.fx)
        assert abs(cam.intrinsics.fy / camera.intrinsics.fy - 1) < 0.01, (name, cam.intrinsics.fy)
        assert np.linalg.norm(cam.pose.position_world - camera.pose.position_world) < 0.1
        report = json.loads((out / name / "report.json").read_text())
        assert report["uncertainty"]["monte_carlo"]["trials"] == 60
    assert not (out / "pole-broken").exists()  # refused before anything is written


@pytest.mark.slow
def test_summary_lists_every_run_in_order_with_the_broken_one_and_its_error(campus):
    truth, paths, out, proc = campus
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [r["run"] for r in rows] == [p.stem for p in paths]
    assert list(rows[0].keys()) == list(COLUMNS)
    by_run = {r["run"]: r for r in rows}
    bad = by_run["pole-broken"]
    assert bad["status"] == "failed" and "not an MCAP file" in bad["message"] and bad["fx_px"] == ""
    for name, camera in truth.items():
        r = by_run[name]
        assert r["status"] == "ok" and r["message"] == ""
        assert abs(float(r["fx_px"]) / camera.intrinsics.fx - 1) < 0.01
        used, total = int(r["waypoints_used"]), int(r["waypoints"])
        assert 12 <= used <= total == 18
        assert 0.0 < float(r["rms_px"]) < 1.5 and float(r["ground_error_15m_cm"]) > 0
        assert float(r["position_u_m"]) == pytest.approx(camera.pose.position_world[2], abs=0.1)
        assert float(r["lat_deg"]) == pytest.approx(ORIGIN.lat_deg, abs=1e-4)

    doc = json.loads((out / "summary.json").read_text())
    assert doc["counts"] == {"ok": 2, "failed": 1} and doc["runs"] == 3
    assert doc["workers"] == 2 and doc["options"]["trials"] == 60
    assert [r["run"] for r in doc["rows"]] == [p.stem for p in paths]
    assert doc["rows"][0]["fx_px"] == pytest.approx(float(rows[0]["fx_px"]), rel=1e-9)

    # the printed table: one line per run, the failure with its message; the failure count on stderr
    lines = proc.stdout.splitlines()
    assert sum(line.startswith("pole-") for line in lines) == 3
    assert any(line.startswith("pole-broken") and "failed" in line and "not an MCAP file" in line for line in lines)
    assert "2 of 3 runs calibrated on 2 worker(s)" in proc.stdout
    assert "1 of 3 runs failed" in proc.stderr


def test_batch_input_errors(tmp_path):
    a, b = tmp_path / "x" / "flight.mcap", tmp_path / "y" / "flight.mcap"
    with pytest.raises(InputError, match="stem 'flight'"):
        plan_tasks([a, b], tmp_path / "out", CalibrateOptions())
    tasks = plan_tasks([a, tmp_path / "other.mcap"], tmp_path / "out", CalibrateOptions(trials=7))
    assert [t.options.out_dir.name for t in tasks] == ["flight", "other"] and tasks[1].options.trials == 7
    proc = run_cli("calibrate", str(a), str(b))
    assert proc.returncode == 2 and "need --out DIR" in proc.stderr and proc.stderr.count("\n") == 1


def test_a_several_camera_run_in_a_batch_calibrates_every_camera(tmp_path):
    """Batch mode (issue 24): a two-camera run beside a one-camera run gives a row per camera of the site run, each
    camera in its own folder with the run's site.json beside them, not only the first camera."""
    from contract_writer import SiteCamera, facing_point, site_waypoints, write_site_run
    from dronecal_field.pipeline.batch import calibrate_many
    from dronecal_field.sim.compare import compare_cameras

    a = pole_camera(azimuth_deg=-20, position_enu=(0.0, 0.0, 5.0), tilt_deg=18)
    b = pole_camera(azimuth_deg=20, position_enu=(0.0, 0.0, 5.0), tilt_deg=14, f_px=600, principal_offset_px=(-5.0, 3.0))
    flight = make_flight(facing_point([a, b]), site_waypoints([a, b], lateral_m=(-2.5, 0.0, 2.5), ahead_m=(5.5, 8.5), up_m=(1.5, 3.5)),
                         hold_s=2.2, move_s=1.3, seed=0)
    site = tmp_path / "site.mcap"
    write_site_run(site, [SiteCamera("west", a, latency_s=0.12), SiteCamera("east", b, latency_s=-0.08)], flight, MarkerLook(),
                   RunSpec(fps=6.0, seed=5, site_origin=ORIGIN))
    one = tmp_path / "one.mcap"
    write_run(one, a, flight, MarkerLook(), RunSpec(fps=6.0, seed=5, site_origin=ORIGIN, latency_s=0.12))
    out = tmp_path / "out"
    report = calibrate_many([site, one], out, CalibrateOptions(trials=0))
    assert [(r.run, r.camera, r.status) for r in report.rows] == [("site", "west", "ok"), ("site", "east", "ok"), ("one", None, "ok")], \
        [(r.run, r.camera, r.status, r.message) for r in report.rows]
    for row, truth in zip(report.rows, (a, b, a)):
        c = compare_cameras(truth, read_camera(f"{row.out_dir}/camera.yaml"))
        assert c.focal_error_pct < 1.5 and c.position_error_cm < 5.0, (row.run, row.camera, c)
        assert abs(row.fx_px / truth.intrinsics.fx - 1) < 0.015 and row.waypoints_used >= 8
    assert abs(report.rows[0].time_offset_s - 0.12) < 0.02 and abs(report.rows[1].time_offset_s + 0.08) < 0.02
    assert (out / "site" / "site.json").is_file() and (out / "site" / "east" / "camera.yaml").is_file()
    rows = list(csv.DictReader((out / "summary.csv").open()))
    assert [(r["run"], r["camera"]) for r in rows] == [("site", "west"), ("site", "east"), ("one", "")]
    doc = json.loads((out / "summary.json").read_text())
    assert doc["counts"] == {"ok": 3} and [r["camera"] for r in doc["rows"]] == ["west", "east", None]
