"""End-to-end runs of the offline stage on files written by the INDEPENDENT contract writer.

Each run is a flight over a truth camera, written from the contract text
(tests/contract_writer.py), with one kind of field mess at a time: a 0.5 s
camera latency, no hover events, a cut-off file, GNSS dropouts, degraded
fixes, frames without the marker, corrupt frames, no attitude.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from contract_writer import (
    ORIGIN,
    MarkerLook,
    RunSpec,
    grid_waypoints,
    make_flight,
    pole_camera,
    truncate,
    write_run,
)
from dronecal_field.camerafile import read_camera
from dronecal_field.errors import ContractError, DegenerateGeometryError, InputError
from dronecal_field.geodesy import enu_to_geodetic, geodetic_to_enu
from dronecal_field.pipeline.annotate import write_annotated_copy
from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run
from dronecal_field.runfile.reader import open_run

S = 1_000_000_000
WIDE_GRID = dict(east_m=(-3.0, 0.0, 3.0), north_m=(6.0, 8.5, 11.0), up_m=(1.0, 4.0))


def _position_error_and_bound(report, camera):
    """(error, 3-sigma bound) of the camera centre, the bound from the report's own linearised uncertainty."""
    err = report.camera.pose.position_world - _truth_in(report, camera)
    std = np.array([report.linearised.param_std[f"pos_{a}"] for a in "xyz"])
    return float(np.linalg.norm(err)), float(3 * np.linalg.norm(std))


def _truth_in(report, camera):
    """The truth camera centre in the report's ENU frame (its origin may be the first fix)."""
    geo = enu_to_geodetic(camera.pose.position_world[None], ORIGIN)[0]
    return geodetic_to_enu(geo[0], geo[1], geo[2], report.origin)[0]


@pytest.fixture(scope="module")
def main_run(tmp_path_factory):
    """Distorted camera, the simulator's renderer, 0.5 s latency, no events: windows from the track."""
    tmp = tmp_path_factory.mktemp("main")
    camera = pole_camera(distortion=(-0.15, 0.03, 0.0, 0.0, 0.0))
    flight = make_flight(camera, grid_waypoints(**WIDE_GRID), seed=11)
    spec = RunSpec(latency_s=0.5, declared_latency="unknown", with_events=False, site_origin=ORIGIN, renderer="sim")
    path = tmp / "main.mcap"
    truth = write_run(path, camera, flight, MarkerLook(marker_id=7), spec)
    report = calibrate_run(path, CalibrateOptions(out_dir=tmp / "out", annotate=True, trials=300))
    return camera, flight, truth, report, tmp


def test_main_run_meets_the_accuracy_targets(main_run):
    camera, flight, truth, report, _ = main_run
    cam = report.camera
    assert report.window_source == "gnss_track"
    assert len(report.used_points) >= len(flight.holds) - 1
    fx_err = abs(cam.intrinsics.fx / camera.intrinsics.fx - 1)
    fy_err = abs(cam.intrinsics.fy / camera.intrinsics.fy - 1)
    pp_err = np.hypot(cam.intrinsics.cx - camera.intrinsics.cx, cam.intrinsics.cy - camera.intrinsics.cy)
    pos_err = np.linalg.norm(cam.pose.position_world - _truth_in(report, camera))
    assert fx_err < 0.01 and fy_err < 0.01, (cam.intrinsics, camera.intrinsics)
    assert pp_err < 5.0, pp_err
    assert pos_err < 0.05, pos_err
    # Projection against the true camera over the flown volume.
    X = np.array([p.marker_enu_m for p in report.used_points])
    proj = np.sqrt(np.mean(np.sum((cam.project(X) - camera.project(X)) ** 2, 1)))
    assert proj < 1.0, proj
    assert report.result.rms_px < 1.0


def test_main_run_finds_the_latency_and_decodes_few_frames(main_run):
    _, _, truth, report, _ = main_run
    off = report.offset
    assert off.method == "image-vs-gnss"
    assert abs(off.offset_s - 0.5) < 0.03 and off.std_s < 0.03, off
    assert report.frames.frames_corrupt == 0
    # Decoding is spent in the windows: well under every frame of the run.
    assert report.frames.frames_decoded < 0.75 * truth["n_frames"]
    assert report.monte_carlo.trials == 300 and report.monte_carlo.failed_trials == 0
    assert report.monte_carlo.ground_error_15m_cm > 0


def test_main_run_writes_every_output(main_run):
    camera, _, _, report, tmp = main_run
    out = tmp / "out"
    for name in ("camera.yaml", "camera_info.yaml", "report.json", "report.html", "ground_homography.yaml", "detections.csv"):
        assert (out / name).stat().st_size > 100, name
    back = read_camera(out / "camera.yaml")
    assert abs(back.intrinsics.fx - report.camera.intrinsics.fx) < 1e-6
    assert np.allclose(back.enu_origin, ORIGIN.as_list())
    assert np.allclose(back.pose.position_world, report.camera.pose.position_world, atol=1e-9)
    assert back.covariance is not None and back.covariance[0, 0] > 0

    data = json.loads((out / "report.json").read_text())
    assert data["frame"]["altitude_datum"] == "ellipsoid"
    assert data["hover_windows"]["count"] == len(report.windows)
    assert len(data["hover_windows"]["windows"]) == len(report.windows)
    assert data["calibration"]["rms_px"] == pytest.approx(report.result.rms_px)
    assert data["uncertainty"]["monte_carlo"]["trials"] == 300
    assert data["uncertainty"]["at_15m"]["speed_error_kmh_at_50kmh"] > 0
    assert data["time_offset"]["offset_s"] == pytest.approx(report.offset.offset_s)
    dropped = data["hover_windows"]["dropped"]
    assert all(d["reason"] for d in dropped)
    assert data["gnss"]["fix_rate_hz"] == pytest.approx(5.0, abs=0.3) and data["gnss"]["repeated_fixes_left_out"] == 0
    assert data["points"]["pairing"].startswith("at each fix")
    consistency = data["uncertainty"]["consistency"]
    assert consistency["ratio"] == pytest.approx(report.result.rms_px / (report.monte_carlo.rms_mean / report.sigma_scale))
    assert report.sigma_scale >= 1.0 and data["uncertainty"]["sigmas"]["scale"] == report.sigma_scale
    assert consistency["note"].startswith(f"fit RMS {report.result.rms_px:.2f} px")
    assert "under the first calibration's distortion" in data["points"]["marker_centre"]  # the camera is distorted

    html = (out / "report.html").read_text()
    # residuals, coverage, Monte-Carlo, the two uncertainty maps, the ground plan of the region of validity
    assert html.count("data:image/png;base64,") == 6 and "<script" not in html
    assert "region of validity" in html and (out / "validity.geojson").is_file()
    assert data["validity"]["polygon_px"] and 0 < data["validity"]["image_fraction"] <= 1
    assert "fit vs measured sigmas" in html and "from the fit's residuals" in html

    info = (out / "camera_info.yaml").read_text()
    assert "distortion_model: plumb_bob" in info and f"image_width: {camera.width}" in info

    rows = list(csv.DictReader((out / "detections.csv").open()))
    assert len(rows) == len(report.detections)
    assert sum(int(r["in_settled_part"]) for r in rows) >= 3 * len(report.used_points)

    # The homography takes a ground point to its (undistorted) pixel.
    H = np.array(report.homography)
    g = np.array([1.0, 12.0, 0.0])
    q = H @ np.array([g[0], g[1], 1.0])
    pin = report.camera.with_(distortion=type(report.camera.distortion)())
    assert np.allclose(q[:2] / q[2], pin.project(g[None])[0], atol=1e-6)


def test_annotated_copy_opens_as_a_run_with_the_calibration(main_run):
    _, _, truth, report, tmp = main_run
    annotated = Path(report.outputs["annotated_run"])
    with open_run(annotated) as run:
        assert not run.truncated
        topics = run.topics
        assert topics["/camera/calibration"] == "foxglove.CameraCalibration"
        assert topics["/camera/annotations"] == "foxglove.ImageAnnotations"
        n_frames = sum(1 for _ in run.iter_frames())
        n_fixes = sum(1 for _ in run.iter_fixes())
    assert n_frames == truth["n_frames"] and n_fixes == truth["n_fixes"]
    # the added messages go in among the run's own by time: every chunk starts after the one before it ends
    from mcap.reader import make_reader

    with open(annotated, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 2
    assert all(b.message_start_time >= a.message_end_time for a, b in zip(chunks, chunks[1:]))


@pytest.fixture(scope="module")
def messy_run(tmp_path_factory):
    """Events, GNSS dropout in one hold, degraded fixes in two, marker hidden in one, corrupt frames."""
    tmp = tmp_path_factory.mktemp("messy")
    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints(), seed=12)
    h = flight.holds
    spec = RunSpec(
        latency_s=-0.3,
        dropouts=[(h[3][0] - S // 2, h[3][1] + S // 2)],
        degraded_holds={6: "rtk_float", 10: "dgps"},
        hidden=[(h[8][0] - S // 2, h[8][1] + S // 2)],
        corrupt_every=7,
        site_origin=ORIGIN,
    )
    path = tmp / "messy.mcap"
    truth = write_run(path, camera, flight, MarkerLook(), spec)
    report = calibrate_run(path, CalibrateOptions(trials=50))
    return camera, flight, truth, report, path


def test_messy_run_drops_exactly_the_bad_windows_with_reasons(messy_run):
    camera, flight, truth, report, _ = messy_run
    assert report.window_source == "event"
    assert [w.seq for w in report.windows] == [seq for _, _, seq in flight.holds]
    reasons = {p.window.index: p.dropped for p in report.points if not p.used}
    assert set(reasons) == {3, 6, 8, 10}, reasons
    assert "dropout" in reasons[3]
    assert "rtk_float" in reasons[6] and "dgps" in reasons[10]
    assert "detections" in reasons[8]
    assert report.frames.frames_corrupt > 0
    assert any("corrupt" in w for w in report.warnings)


def test_messy_run_still_calibrates(messy_run):
    camera, _, _, report, _ = messy_run
    cam = report.camera
    assert abs(cam.intrinsics.fx / camera.intrinsics.fx - 1) < 0.02
    err, bound = _position_error_and_bound(report, camera)
    assert err < bound and bound < 0.5, (err, bound)
    assert abs(report.offset.offset_s + 0.3) < 0.04


def test_cut_off_run_calibrates_from_its_complete_part(messy_run, tmp_path):
    camera, flight, _, full, path = messy_run
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes())
    truncate(cut, 0.8)
    report = calibrate_run(cut, CalibrateOptions(trials=0))
    assert report.truncated and any("cut off" in w for w in report.warnings)
    assert len(report.windows) < len(full.windows)
    assert len(report.used_points) >= 6
    assert report.monte_carlo is None and report.linearised is not None
    assert abs(report.camera.intrinsics.fx / camera.intrinsics.fx - 1) < 0.03
    # The annotated copy of a cut-off run keeps its complete part and is itself complete.
    added = write_annotated_copy(cut, tmp_path / "cut.annotated.mcap", report)
    assert added == len(report.detections) + 1
    with open_run(cut) as original, open_run(tmp_path / "cut.annotated.mcap") as annotated:
        assert not annotated.truncated
        assert sum(1 for _ in annotated.iter_frames()) == sum(1 for _ in original.iter_frames())


def test_reached_without_attitude_uses_the_level_nose_to_camera_lever_arm(tmp_path):
    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints(), seed=13, offset_frd_m=(0.3, 0.0, 0.15), tilt_rad=0.0)
    spec = RunSpec(with_events=False, with_reached=True, with_attitude=False, site_origin=ORIGIN)
    path = tmp_path / "reached.mcap"
    write_run(path, camera, flight, MarkerLook(), spec)
    report = calibrate_run(path, CalibrateOptions(trials=0))
    assert report.window_source == "mission_item_reached"
    assert [w.seq for w in report.windows] == [seq for _, _, seq in flight.holds]
    assert "assumed level" in report.attitude_source
    # The 30 cm lever arm is applied: points land on the true marker centres.
    centres = {seq: flight.marker_centre(np.array([(a + b) // 2]))[0] for a, b, seq in flight.holds}
    errors = [np.linalg.norm(p.marker_enu_m - centres[p.window.seq]) for p in report.used_points]
    assert np.median(errors) < 0.03, errors
    err, bound = _position_error_and_bound(report, camera)
    assert err < bound and bound < 0.5, (err, bound)


def test_led_run_calibrates(tmp_path):
    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints(**WIDE_GRID), seed=14)
    path = tmp_path / "led.mcap"
    write_run(path, camera, flight, MarkerLook(kind="led"), RunSpec(site_origin=ORIGIN))
    report = calibrate_run(path, CalibrateOptions(trials=0))
    assert report.detections[0].kind == "led"
    assert len(report.used_points) >= len(flight.holds) - 1
    assert abs(report.camera.intrinsics.fx / camera.intrinsics.fx - 1) < 0.02


def test_repeated_fixes_are_left_out_with_a_warning(tmp_path):
    # 5 Hz fixes sent twice each under arrival stamps (ArduPilot streaming GPS_RAW_INT at 10 Hz with
    # GPS_RATE_MS = 200, a writer that breaks the one-message-per-fix rule): repeats while the drone
    # moves give the writer away, the fallback rule "position" leaves the stale repeats out, so the
    # points are those of the plain 5 Hz run.
    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints(**WIDE_GRID), seed=16)
    reports = []
    for repeat in (1, 2):
        path = tmp_path / f"repeat{repeat}.mcap"
        write_run(path, camera, flight, MarkerLook(), RunSpec(site_origin=ORIGIN, repeat_fixes=repeat))
        reports.append(calibrate_run(path, CalibrateOptions(trials=0)))
    plain, repeated = reports
    assert [p.n_fixes for p in repeated.points] == [p.n_fixes for p in plain.points]
    np.testing.assert_allclose([p.marker_enu_m for p in repeated.used_points], [p.marker_enu_m for p in plain.used_points], atol=1e-9)
    assert repeated.fixes_repeated == repeated.track.t_ns.size == plain.track.t_ns.size
    warning = [w for w in repeated.warnings if "repeat the fix before" in w]
    assert warning and "GPS_RATE_MS" in warning[0] and "rule: position" in warning[0]
    assert not [w for w in plain.warnings if "repeat the fix before" in w]
    assert (plain.fix_identity.rule, repeated.fix_identity.rule) == ("fix time", "position")
    assert plain.offset.to_dict()["gnss_fix_times"]["rule"] == "fix time"


# --------------------------------------------------------------------------
# Failures: one clear error each


def _small(tmp_path, name, look=MarkerLook(), waypoints=None, **spec):
    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints() if waypoints is None else waypoints, hold_s=2.0, move_s=1.5, seed=15)
    path = tmp_path / f"{name}.mcap"
    write_run(path, camera, flight, look, RunSpec(fps=6.0, **spec))
    return path, flight


def test_no_marker_names_the_frames_and_the_hint(tmp_path):
    path, _ = _small(tmp_path, "hidden", hidden=[(0, 2**62)])
    with pytest.raises(InputError, match=r"no marker found: looked for ArUco id 7 of DICT_4X4_50 \(0.4 m\) in \d+ frames"):
        calibrate_run(path, CalibrateOptions(trials=0))


def test_missing_metadata_key_is_a_contract_error_naming_it(tmp_path):
    path, _ = _small(tmp_path, "nokey", omit_metadata_keys=("marker.offset_frd_m",))
    with pytest.raises(ContractError, match="marker.offset_frd_m"):
        calibrate_run(path, CalibrateOptions(trials=0))


def test_coplanar_waypoints_are_refused(tmp_path):
    path, _ = _small(tmp_path, "flat", waypoints=grid_waypoints(up_m=(2.5,)))
    with pytest.raises(DegenerateGeometryError, match="coplanar"):
        calibrate_run(path, CalibrateOptions(trials=0))


def test_too_few_good_waypoints_lists_why(tmp_path):
    path, flight = _small(tmp_path, "float", fix_type="rtk_float", degraded_holds={})
    with pytest.raises(DegenerateGeometryError, match=r"too few good waypoints: 0 of \d+ .*rtk_float is worse than --min-fix rtk_fixed"):
        calibrate_run(path, CalibrateOptions(trials=0))
    report = calibrate_run(path, CalibrateOptions(trials=0, min_fix="rtk_float"))
    assert len(report.used_points) == len(flight.holds)


def test_no_usable_fix(tmp_path):
    path, _ = _small(tmp_path, "nofix", fix_type="no_fix")
    with pytest.raises(InputError, match="no usable GNSS fix"):
        calibrate_run(path, CalibrateOptions(trials=0))


def test_outputs_replace_an_earlier_calibration_as_a_set_and_keep_the_users_files(tmp_path):
    """calibrate --out into an earlier calibration folder: every output is new, a user's notes stay, no temporary folder is left."""
    from dronecal_field.pipeline.report import write_outputs

    out = tmp_path / "calibration"
    out.mkdir()
    (out / "notes.txt").write_text("camera 7, north gate\n")
    (out / "report.html").write_text("an earlier run's report")
    (out / "camera.yaml").write_text("an earlier run's camera")
    report = calibrate_run(Path(__file__).resolve().parents[1] / "replays" / "nominal.mcap", CalibrateOptions(trials=0))
    outputs = write_outputs(report, out)
    assert (out / "notes.txt").read_text() == "camera 7, north gate\n"
    assert (out / "report.html").read_text().startswith("<!DOCTYPE html>")
    assert read_camera(out / "camera.yaml").width == report.metadata.width
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calibration"]  # no .calibration.tmp-/old- left behind
    assert all(Path(v).parent == out for v in outputs.values())


def test_a_run_cut_during_the_climb_between_layers_says_why_it_cannot_calibrate(tmp_path):
    """Issue 11, item 3: the replay cut in the climb to its second layer (one plane of holds, few frames a hold).

    The offset from the marker's motion is uncertain there (+0.20 +- 0.06 s; the whole run gives +0.027 s) and
    leaves no hold with its 3 detections; the candidates around it calibrate the holds, whose one plane is the
    real reason: that is what the user reads, not "relax --min-fix".
    """
    full = Path(__file__).resolve().parents[1] / "replays" / "nominal.mcap"
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full.read_bytes()[:2881961])
    with pytest.raises(DegenerateGeometryError) as err:
        calibrate_run(cut, CalibrateOptions(trials=0))
    text = str(err.value)
    assert "lie in one plane" in text and "fly a second height" in text and "cut off at byte" in text
    assert "--min-fix" not in text


def test_a_clock_jump_the_recorder_saw_is_said_with_the_holds_near_it(main_run):
    from dronecal_field.pipeline.run import _clock_jump_cost
    from dronecal_field.runfile.records import RunEvent

    _, _, _, report, _ = main_run
    hold = next(p for p in report.points if p.used and p.window.source != "leg")
    text = _clock_jump_cost(RunEvent(hold.window.start_ns, 0, "clock_jump", {"jump_s": "+2.000"}), report.points, report.track.t_ns)
    assert text.startswith("the recorder's clock jumped +2.000 s against the vehicle's at +")
    n = int(text.split("may not line up; ")[1].split(" hover windows")[0])
    assert n >= 1 and "NTP" in text
