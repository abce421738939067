"""The region of validity in the offline stage's files: camera.yaml, report.json, ground_homography.yaml,
validity.geojson, report.html, on a real run file (contract writer) through the real pipeline.

The region is computed here the way the uncertainty stage does it
(``validity.assess_validity`` on the calibration, its measured-sigma
covariance and sigmas) and put into the report with ``dataclasses.replace``.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from contract_writer import ORIGIN, MarkerLook, RunSpec, grid_waypoints, make_flight, pole_camera, write_run
from dronecal_field.camerafile import read_validity_polygon
from dronecal_field.core.uncertainty import parameter_covariance
from dronecal_field.geodesy import geodetic_to_enu
from dronecal_field.pipeline import maps
from dronecal_field.pipeline import validity as V
from dronecal_field.pipeline.report import all_warnings, write_outputs
from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run


@pytest.fixture(scope="module")
def report_with_region(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("validity")
    # A wide lens seen only in a band of the image: the region is a small part of the view.
    camera = pole_camera(width=960, height=540, f_px=450.0, distortion=(-0.28, 0.07, 0.0, 0.0, 0.0))
    flight = make_flight(camera, grid_waypoints(east_m=(-2.5, 0.0, 2.5), north_m=(5.0, 6.5, 8.0), up_m=(0.6, 1.2)), hold_s=2.5, move_s=1.2, seed=5)
    path = tmp / "band.mcap"
    write_run(path, camera, flight, MarkerLook(size_m=0.5), RunSpec(fps=8.0, gnss_hz=10.0, site_origin=ORIGIN))
    report = calibrate_run(path, CalibrateOptions(trials=0))
    used = report.used_points
    s3 = np.array([p.sigma_enu_m for p in used])
    s2 = np.array([p.sigma_px for p in used])
    cov = parameter_covariance(report.camera, report.result.points_world, s3, s2, report.result.model)
    region = V.assess_validity(report.result, cov, s3, s2, origin=report.origin)
    umaps = maps.uncertainty_maps(report.camera, cov, nu=48, richer=region.richer_camera, richer_covariance=region.richer_covariance)
    report = replace(report, validity=region, maps=umaps)
    out = tmp / "out"
    write_outputs(report, out)
    return report, region, out


def test_camera_yaml_and_homography_carry_the_region(report_with_region):
    report, region, out = report_with_region
    assert np.allclose(read_validity_polygon(out / "camera.yaml"), region.polygon_px)
    import yaml

    doc = yaml.safe_load((out / "ground_homography.yaml").read_text())

    def matrix(key):
        m = doc[key]
        return np.array(m["data"], float).reshape(m["rows"], m["cols"])

    assert np.allclose(matrix("validity_polygon_px"), region.polygon_px)
    assert np.allclose(matrix("validity_ground_enu_m"), region.ground_polygon_enu_m)


def test_report_json_and_geojson_hold_the_region_and_its_warning(report_with_region):
    report, region, out = report_with_region
    data = json.loads((out / "report.json").read_text())
    v = data["validity"]
    assert v["chosen_model"] == report.result.model.name and v["richer_model"] is not None
    assert 0.0 < v["visible_ground_fraction"] < 0.6 and v["image_fraction"] >= v["hull_fraction"] > 0.0
    over = data["uncertainty"]["over_validity_region"]
    assert over["ground_position_error_cm_rms"] == pytest.approx(region.inside_cm_rms)
    assert over["ground_position_error_cm_max"] >= over["ground_position_error_cm_rms"] > 0.0
    assert data["uncertainty"]["image_map"]["with_model_extrapolation"]
    # The uncovered ground is a warning in report.json (and, through all_warnings, on the command line).
    assert any("of the visible ground 3-30 m" in w for w in data["warnings"])
    assert data["warnings"] == all_warnings(report)
    gj = json.loads((out / "validity.geojson").read_text())
    ring = np.array(gj["features"][0]["geometry"]["coordinates"][0])
    enu = geodetic_to_enu(ring[:, 1], ring[:, 0], np.full(len(ring), report.origin.h_m), report.origin)
    assert np.abs(enu[:-1, :2] - region.ground_polygon_enu_m[:, :2]).max() < 1e-3


def test_report_html_shows_the_region_and_readable_maps(report_with_region):
    report, region, out = report_with_region
    page = (out / "report.html").read_text()
    assert "Use this calibration only inside the region of validity" in page
    assert "ground position error over the region of validity" in page
    assert page.count("data:image/png;base64,") == 5 and "the region of validity on the ground" in page  # no Monte-Carlo figure with --trials 0
    # The maps: finite where a ray exists, infinite only beyond the distortion model's fold.
    m = report.maps
    assert np.isfinite(m.projection_px[~m.no_ray]).all()
    assert m.sky[0].any() and not m.sky[-1].any()
