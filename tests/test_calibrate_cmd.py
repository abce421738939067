"""``dronecal-field calibrate`` through the real console entry point: exit codes, summary, files."""

from __future__ import annotations

import json

import pytest

from conftest import run_cli
from contract_writer import ORIGIN, MarkerLook, RunSpec, grid_waypoints, make_flight, pole_camera, write_run
from dronecal_field.runfile.reader import open_run


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("cmd")
    camera = pole_camera()
    flight = make_flight(camera, grid_waypoints(east_m=(-3.0, 0.0, 3.0), up_m=(1.0, 4.0)), hold_s=2.5, move_s=1.5, seed=21)
    path = tmp / "flight.mcap"
    write_run(path, camera, flight, MarkerLook(), RunSpec(fps=8.0, latency_s=0.25, site_origin=ORIGIN))
    return camera, flight, path, tmp


def test_calibrate_prints_a_summary_and_writes_the_report_beside_the_run(small_run):
    camera, flight, path, tmp = small_run
    out = tmp / "flight-calibration"  # the default --out
    proc = run_cli("calibrate", str(path), "--trials", "60", "--model", "k1", "--annotate")
    assert proc.returncode == 0, proc.stderr
    assert f"of {len(flight.holds)} waypoints" in proc.stdout and "model k1" in proc.stdout
    assert "camera time offset +0.2" in proc.stdout
    assert f"report: {out / 'report.html'}" in proc.stdout
    data = json.loads((out / "report.json").read_text())
    fx = data["calibration"]["camera"]["fx"]
    assert abs(fx / camera.intrinsics.fx - 1) < 0.02
    assert data["calibration"]["model"] == "k1" and data["calibration"]["model_reason"] == "--model given"
    assert data["uncertainty"]["monte_carlo"]["trials"] == 60
    assert data["options"]["trials"] == 60
    with open_run(out / "flight.annotated.mcap") as annotated, open_run(path) as original:
        assert sum(1 for _ in annotated.iter_frames()) == sum(1 for _ in original.iter_frames())
        assert annotated.topics["/camera/annotations"] == "foxglove.ImageAnnotations"


def test_calibrate_errors_exit_2_with_one_line(small_run, tmp_path):
    _, _, path, _ = small_run
    proc = run_cli("calibrate", str(tmp_path / "missing.mcap"))
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "dronecal-field calibrate: error:" in proc.stderr
    broken = tmp_path / "broken.mcap"
    broken.write_bytes(b"not an mcap file at all")
    proc = run_cli("calibrate", str(broken))
    assert proc.returncode == 2 and "not an MCAP file" in proc.stderr
    proc = run_cli("calibrate", str(path), "--min-fix", "bogus")
    assert proc.returncode == 2 and "invalid choice" in proc.stderr  # argparse's own usage error
    proc = run_cli("calibrate", str(path), "--trials", "1")
    assert proc.returncode == 2 and "--trials 1: use 0" in proc.stderr


def test_calibrate_help_is_fast_and_documents_the_outputs():
    proc = run_cli("calibrate", "--help")
    assert proc.returncode == 0
    for word in ("camera.yaml", "--min-fix", "--model", "--annotate", "--trials"):
        assert word in proc.stdout


@pytest.mark.parametrize("flag, value, names", [
    ("--loss-scale-px", "0", "--loss-scale-px 0"),
    ("--loss-scale-px", "nan", "--loss-scale-px nan"),
    ("--settle-s", "-1", "--settle-s -1"),
    ("--max-readout-s", "5", "--max-readout-s 5"),
    ("--max-frames-per-window", "0", "--max-frames-per-window 0"),
])
def test_nonsense_options_are_refused_in_one_line(small_run, tmp_path, flag, value, names):
    _, _, path, _ = small_run
    proc = run_cli("calibrate", str(path), "--out", str(tmp_path / "out"), flag, value)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.count("\n") == 1 and names in proc.stderr
    assert not (tmp_path / "out").exists()


def test_calibrate_refuses_an_absurd_number_of_trials_before_reading_the_run(tmp_path):
    """Issue 21: `calibrate --trials 100000000` ran on; it is refused in one line before any run is opened."""
    proc = run_cli("calibrate", str(tmp_path / "absent.mcap"), "--trials", "100000000")
    assert proc.returncode == 2 and "--trials" in proc.stderr and "outside [0, 100000]" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "Traceback" not in proc.stderr
