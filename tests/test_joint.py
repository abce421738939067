"""``calibrate`` pools the flights of one split plan into one camera (issue 10: plans split into flights).

One distorted pole camera, its plan split into two flights: flight 1 holds on
the left half of the image, flight 2 on the right half. Each run file is
written by the independent contract writer and given what ``fly`` attaches:
the plan's plan.json (the same bytes for both) and that flight's mission.plan.
``calibrate a b`` must see they are flights of one plan and give ONE camera
whose error over the visible ground (3-30 m, against the truth) is below the
error of either half calibrated alone; ``--separate`` gives the two halves;
``--joint`` on runs of two different cameras is refused in one line.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from contract_writer import ORIGIN, MarkerLook, RunSpec, grid_waypoints, make_flight, pole_camera, write_run
from dronecal_field.camerafile import read_camera
from dronecal_field.demo import in_enu_frame_of
from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic
from dronecal_field.sim.compare import compare_cameras

TRUTH = pole_camera(f_px=520.0, distortion=(-0.22, 0.06, 0.0, 0.0, 0.0))
HALVES = {  # east of the antenna at each hold: the left and the right half of the image
    1: grid_waypoints(east_m=(-2.6, -1.2), north_m=(6.0, 8.5, 11.0), up_m=(0.8, 3.3)),
    2: grid_waypoints(east_m=(1.2, 2.6), north_m=(6.0, 8.5, 11.0), up_m=(0.8, 3.3)),
}


# Flight 2's run declares its ENU frame 32 m away and 1.5 m up (dronecal.site): the joint moves its points into flight 1's.
SHIFTED = EnuOrigin(*enu_to_geodetic(np.array([[20.0, -25.0, 1.5]]), ORIGIN)[0])


def _plan_json() -> bytes:
    """The plan.json of the split plan (what ``plan`` writes and ``fly`` attaches): origin, camera, ROI, the grid by flight."""
    grid = []
    for flight, wps in HALVES.items():
        geo = enu_to_geodetic(wps, ORIGIN)
        grid += [{"index": len(grid) + k, "flight": flight, "mission_seq": 4 + k, "lat_deg": g[0], "lon_deg": g[1], "h_m": g[2]}
                 for k, g in enumerate(geo)]
    plan = {
        "format": "dronecal-field plan, test",
        "enu_origin": {"lat_deg": ORIGIN.lat_deg, "lon_deg": ORIGIN.lon_deg, "h_m": ORIGIN.h_m},
        "camera_guess": {"width": TRUTH.width, "height": TRUTH.height, "position_enu_m": list(TRUTH.pose.position_world)},
        "roi": {"kind": "range", "range_m": [3.0, 30.0], "text": "the ground 3-30 m from the pole"},
        "grid": grid,
        "flight": {"n_flights": 2},
    }
    return json.dumps(plan, indent=1).encode()


def _mission_plan(flight: int) -> bytes:
    """That flight's QGroundControl mission: a NAV_WAYPOINT (hold 2.5 s) at each of its holds."""
    geo = enu_to_geodetic(HALVES[flight], ORIGIN)
    items = [{"type": "SimpleItem", "command": 16, "doJumpId": 4 + k, "params": [2.5, 0, 0, None, g[0], g[1], g[2] - ORIGIN.h_m]}
             for k, g in enumerate(geo)]
    return json.dumps({"fileType": "Plan", "mission": {"items": items}}).encode()


def _with_attachments(src: Path, dst: Path, attachments: dict[str, bytes]) -> None:
    """A copy of an MCAP run with these attachments added (as ``fly`` attaches plan.json and mission.plan)."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    with open(src, "rb") as f_in, open(dst, "wb") as f_out:
        reader = make_reader(f_in)
        writer = Writer(f_out, compression=CompressionType.NONE)
        writer.start(profile="", library="dronecal-tests")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, dict(record.metadata))
        for name, data in attachments.items():
            writer.add_attachment(create_time=0, log_time=0, name=name, media_type="application/json", data=data)
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding, schemas[schema.id])
            writer.add_message(channel_id=channels[channel.id], log_time=message.log_time, data=message.data,
                               publish_time=message.publish_time, sequence=message.sequence)
        writer.finish()


def _ground_error(camera_yaml: Path):
    return compare_cameras(TRUTH, in_enu_frame_of(read_camera(camera_yaml), TRUTH.enu_origin), ground_step_m=0.5).ground


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("split-plan")
    plan = _plan_json()
    paths = []
    for flight, wps in HALVES.items():
        raw = tmp / f"raw-{flight}.mcap"
        write_run(raw, TRUTH, make_flight(TRUTH, wps, hold_s=2.5, move_s=1.5, seed=30 + flight), MarkerLook(),
                  RunSpec(fps=8.0, latency_s=0.15 * flight, site_origin=ORIGIN if flight == 1 else SHIFTED, seed=40 + flight))
        path = tmp / f"run-{flight}.mcap"
        _with_attachments(raw, path, {"plan.json": plan, "mission.plan": _mission_plan(flight)})
        raw.unlink()
        paths.append(path)
    return tmp, paths


@pytest.fixture(scope="module")
def joint(flights):
    tmp, paths = flights
    out = tmp / "joint"
    proc = run_cli("calibrate", *map(str, paths), "--out", str(out), "--trials", "40", timeout=300)
    return out, proc


@pytest.fixture(scope="module")
def separate(flights):
    tmp, paths = flights
    out = tmp / "separate"
    proc = run_cli("calibrate", *map(str, paths), "--separate", "--out", str(out), "--workers", "0", "--trials", "0", timeout=300)
    return out, proc


@pytest.mark.slow  # ~25 s: two runs written, calibrated alone and together
def test_flights_of_one_plan_are_pooled_into_one_better_camera(flights, joint, separate):
    _, paths = flights
    out, proc = joint
    assert proc.returncode == 0, proc.stderr
    assert "runs run-1.mcap, run-2.mcap are flights 1 and 2 of one plan: calibrated together; --separate" in proc.stdout
    # one camera, one report, naming both runs and what each gave
    assert sorted(p.name for p in out.glob("camera.yaml")) == ["camera.yaml"]
    report = json.loads((out / "report.json").read_text())
    runs = report["joint"]["runs"]
    assert [Path(r["path"]).name for r in runs] == ["run-1.mcap", "run-2.mcap"]
    assert [r["flight"] for r in runs] == [1, 2]
    assert all(r["calibrated_alone_first"] for r in runs)
    assert all(r["points_used"] >= 10 for r in runs), [r["points_used"] for r in runs]
    assert report["calibration"]["n_points"] == sum(r["points_used"] for r in runs)
    moved = [r["enu_origin_from_joint_m"] for r in runs]
    assert moved[0] == 0.0 and abs(moved[1] - np.linalg.norm([20.0, -25.0, 1.5])) < 0.01, moved
    # each flight keeps its own camera clock: the frames of run 2 are stamped 0.15 s later than those of run 1
    offsets = [r["time_offset"]["offset_s"] for r in runs]
    assert abs(offsets[0] - 0.15) < 0.05 and abs(offsets[1] - 0.30) < 0.05, offsets
    html = (out / "report.html").read_text()
    assert "Joint calibration of run-1.mcap, run-2.mcap" in html and "Runs calibrated together" in html

    sep_out, sep = separate
    assert sep.returncode == 0, sep.stderr
    assert "calibrated together" not in sep.stdout
    halves = [_ground_error(sep_out / f"run-{k}" / "camera.yaml") for k in (1, 2)]
    pooled = _ground_error(out / "camera.yaml")
    print(f"ground 3-30 m against the truth: joint {pooled.rms_px:.3f} px RMS (max {pooled.max_px:.2f}); "
          + "; ".join(f"run-{k} alone {h.rms_px:.3f} px RMS (max {h.max_px:.2f})" for k, h in zip((1, 2), halves)))
    # measured: joint 1.00 px RMS (p95 2.27), the halves 1.55 (p95 3.32) and 1.80 px RMS; each half extrapolates over
    # the other half of the image, the joint camera over the rows below the lowest holds only
    for h in halves:
        assert pooled.rms_px < 0.75 * h.rms_px, (pooled.rms_px, [x.rms_px for x in halves])
        assert pooled.p95_px < h.p95_px, (pooled.p95_px, [x.p95_px for x in halves])
    assert pooled.rms_px < 1.3


def test_joint_refuses_runs_of_two_different_cameras(flights, tmp_path):
    _, paths = flights
    other = pole_camera(width=800, height=600, f_px=600.0)
    path = tmp_path / "other.mcap"
    wps = grid_waypoints(east_m=(-1.0, 1.0), north_m=(6.0, 8.0), up_m=(1.5,))
    write_run(path, other, make_flight(other, wps, hold_s=1.0, move_s=1.0, seed=5), MarkerLook(), RunSpec(fps=4.0, site_origin=ORIGIN))
    proc = run_cli("calibrate", str(paths[0]), str(path), "--joint", "--out", str(tmp_path / "out"), timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert "run-1.mcap is 640x480 and other.mcap is 800x600" in lines[0] and "drop --joint" in lines[0]
    assert not (tmp_path / "out").exists()
    # without --joint the three runs are a batch, and the two flights of one plan are named with how to pool them
    from dronecal_field.commands.calibrate import _flights_of_one_plan

    pooled, notes = _flights_of_one_plan([paths[0], path, paths[1]])
    assert not pooled and len(notes) == 1
    assert notes[0].startswith("runs run-1.mcap, run-2.mcap are flights 1 and 2 of one plan, calibrated here each alone")


def test_a_flight_too_small_to_calibrate_alone_still_contributes(flights, tmp_path):
    """A flight cut short after 3 holds (6 needed alone) is paired at its motion-based offset and pooled."""
    from dronecal_field.pipeline.run import CalibrateOptions, calibrate_runs

    _, paths = flights
    short = HALVES[2][[0, 3, 8]]
    raw, path = tmp_path / "raw.mcap", tmp_path / "run-2-short.mcap"
    write_run(raw, TRUTH, make_flight(TRUTH, short, hold_s=2.5, move_s=1.5, seed=32), MarkerLook(),
              RunSpec(fps=8.0, latency_s=0.30, site_origin=ORIGIN, seed=42))
    _with_attachments(raw, path, {"plan.json": _plan_json(), "mission.plan": _mission_plan(2)})
    report = calibrate_runs([paths[0], path], CalibrateOptions(trials=0)).cameras[None]
    alone, small = report.runs
    assert alone.alone and alone.used == 12
    assert not small.alone and small.used == 3 and "too few good waypoints" in small.alone_reason
    assert abs(small.offset.offset_s - 0.30) < 0.05, small.offset.offset_s
    assert len(report.used_points) == 15
    # its points are paired right: through the TRUE camera they reproject within a pixel (joint frame = the truth's)
    X = np.array([p.marker_enu_m for p in small.points if p.used])
    uv = np.array([p.uv_px for p in small.points if p.used])
    assert np.max(np.linalg.norm(TRUTH.project(X) - uv, axis=1)) < 1.0
    assert report.result.rms_px < 1.0
    assert any("run-2-short.mcap does not calibrate alone" in w for w in report.warnings)


@pytest.mark.parametrize("case", ["one run", "the same run twice"])
def test_joint_needs_two_different_runs(flights, tmp_path, case):
    _, paths = flights
    runs = [paths[0]] if case == "one run" else [paths[0], paths[0]]
    proc = run_cli("calibrate", *map(str, runs), "--joint", "--out", str(tmp_path / "out"), timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert ("two or more run files" if case == "one run" else "are the same run file") in lines[0]


@pytest.mark.slow  # ~25 s: two runs written, calibrated alone and pooled
def test_a_noisy_run_pooled_with_a_quiet_one_is_weighted_by_its_own_noise(tmp_path):
    """Issue 23: a scout-like run whose GNSS wanders by decimetres pooled with a quiet RTK run.

    Weighted alike, the noisy run's points pull the camera off; weighted by each run's own
    measured noise, the pooled camera is as good as the quiet run alone (or better).
    """
    from dronecal_field.core.calibrate import calibrate
    from dronecal_field.pipeline.run import CalibrateOptions, calibrate_runs

    quiet_wps = grid_waypoints(east_m=(-2.4, -0.8, 0.8, 2.4), north_m=(6.0, 10.0), up_m=(0.8, 3.3))
    noisy_wps = grid_waypoints(east_m=(-2.0, 0.0, 2.0), north_m=(5.5, 9.0), up_m=(1.2, 2.8))
    paths = []
    for name, wps, spec, seed in (
        ("quiet", quiet_wps, RunSpec(fps=6.0, site_origin=ORIGIN, seed=51), 61),
        ("noisy", noisy_wps, RunSpec(fps=6.0, site_origin=ORIGIN, seed=52, gnss_sigma_m=(0.12, 0.12, 0.15), gnss_noise_tau_s=3.0), 62),
    ):
        path = tmp_path / f"{name}.mcap"
        write_run(path, TRUTH, make_flight(TRUTH, wps, hold_s=2.0, move_s=1.2, seed=seed), MarkerLook(), spec)
        paths.append(path)
    alone = calibrate_runs(paths[:1], CalibrateOptions(trials=0)).cameras[None]
    report = calibrate_runs(paths, CalibrateOptions(trials=0)).cameras[None]

    def ground(camera):
        return compare_cameras(TRUTH, in_enu_frame_of(camera, TRUTH.enu_origin), ground_step_m=0.5).ground.rms_px

    quiet, noisy = report.runs
    assert set(quiet.noise_px) == {"holds"} and set(noisy.noise_px) == {"holds"}, (quiet.noise_px, noisy.noise_px)
    # each run's noise as measured about the pooled camera: the noisy run's several times the quiet one's
    assert noisy.noise_px["holds"] > 4.0 * quiet.noise_px["holds"], (quiet.noise_px, noisy.noise_px)
    used = report.used_points
    X = np.array([p.marker_enu_m for p in used])
    uv = np.array([p.uv_px for p in used])
    alike = calibrate(X, uv, TRUTH.width, TRUTH.height, model=report.result.model).camera.with_(enu_origin=report.result.camera.enu_origin)
    g_alone, g_pooled, g_alike = ground(alone.result.camera), ground(report.result.camera), ground(alike)
    print(f"ground 3-30 m RMS: quiet run alone {g_alone:.3f} px ({alone.result.model.name}), pooled weighted {g_pooled:.3f} ({report.result.model.name}), pooled alike {g_alike:.3f}; "
          f"noise {quiet.noise_px} / {noisy.noise_px}")
    # measured (load 10): quiet alone 1.50 px, pooled weighted 1.51, pooled alike 10.9; noise 0.28 / 8.7 px
    assert g_pooled < 1.1 * g_alone, (g_pooled, g_alone)
    assert g_pooled < 0.8 * g_alike, (g_pooled, g_alike)
    assert "weighted by their own noise" in report.model_reason
