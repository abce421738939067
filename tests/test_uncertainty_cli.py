"""`dronecal-field uncertainty` end to end through the real entry point, and its errors."""

import json

import cv2
import numpy as np
import pytest

from conftest import run_cli
from dronecal_field.camerafile import read_camera, write_camera
from dronecal_field.core.synthetic import paper_camera, paper_grid


@pytest.fixture()
def table1_files(tmp_path):
    cam = paper_camera(distorted=True)
    write_camera(tmp_path / "camera.yaml", cam)
    X = paper_grid(cam)
    np.savetxt(tmp_path / "points.csv", X, delimiter=",", header="x,y,z", comments="")
    return tmp_path


def test_camera_file_round_trip_and_opencv_readable(tmp_path):
    cam = paper_camera(distorted=True).with_(enu_origin=(-35.363261, 149.16523, 584.0), covariance=np.diag(np.arange(1.0, 16.0)))
    write_camera(tmp_path / "camera.yaml", cam)
    back = read_camera(tmp_path / "camera.yaml")
    assert np.allclose(back.intrinsics.matrix, cam.intrinsics.matrix)
    assert np.allclose(back.distortion.as_array(), cam.distortion.as_array())
    assert np.allclose(back.pose.R_cam_from_world, cam.pose.R_cam_from_world)
    assert np.allclose(back.pose.position_world, [0.5, 0.0, 2.0])
    assert back.enu_origin == pytest.approx(cam.enu_origin)
    assert np.allclose(back.covariance, cam.covariance)
    fs = cv2.FileStorage(str(tmp_path / "camera.yaml"), cv2.FILE_STORAGE_READ)
    assert fs.getNode("image_width").real() == 1280
    assert fs.getNode("distortion_coefficients").mat().shape == (1, 5)
    assert fs.getNode("camera_position_enu").mat().shape == (3, 1)


def test_json_output(table1_files):
    r = run_cli("uncertainty", "--camera", str(table1_files / "camera.yaml"), "--points", str(table1_files / "points.csv"),
                "--trials", "200", "--seed", "4", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["trials"] == 200
    assert 3.8 < out["rms_mean"] < 5.0
    assert out["rms_max"] > out["rms_mean"]
    assert 0.03 < out["rms_var"] < 0.3
    assert out["model"] == "k1k2p1p2"


def test_table_output_with_linearised_and_convergence_plot(table1_files):
    png = table1_files / "fig1.png"
    r = run_cli("uncertainty", "--camera", str(table1_files / "camera.yaml"), "--points", str(table1_files / "points.csv"),
                "--trials", "100", "--linearised", "--plot-convergence", str(png))
    assert r.returncode == 0, r.stderr
    assert "RMS reprojection mean (px)" in r.stdout and "linearised" in r.stdout
    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 200


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--points", "missing.csv"], "points file missing.csv does not exist"),
        (["--sigma-3d", "0.01,abc"], "--sigma-3d '0.01,abc' is not three numbers within 0-100 m"),
        (["--trials", "1"], "--trials 1 is outside 2..100000"),
        (["--model", "fisheye"], "unknown distortion model 'fisheye'"),
    ],
)
def test_bad_input_is_one_line_exit_2(table1_files, args, needle):
    base = {"--camera": str(table1_files / "camera.yaml"), "--points": str(table1_files / "points.csv")}
    argv = ["uncertainty"]
    given = dict(zip(args[::2], args[1::2]))
    for k, v in {**base, **given}.items():
        path = table1_files / v if k == "--points" and v == "missing.csv" else v
        argv += [k, str(path) if k != "--points" or v != "missing.csv" else "missing.csv"]
    r = run_cli(*argv, cwd=table1_files)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert needle in r.stderr


def test_coplanar_points_file_is_refused(table1_files):
    (table1_files / "flat.csv").write_text("x,y,z\n" + "\n".join(f"{x},{y},0.5" for x in range(4, 9) for y in range(-3, 4)))
    r = run_cli("uncertainty", "--camera", str(table1_files / "camera.yaml"), "--points", str(table1_files / "flat.csv"))
    assert r.returncode == 2 and "coplanar" in r.stderr and "Traceback" not in r.stderr


def test_missing_camera_key(table1_files):
    (table1_files / "bad.yaml").write_text("%YAML:1.0\n---\nimage_width: 1280\nimage_height: 960\n")
    r = run_cli("uncertainty", "--camera", str(table1_files / "bad.yaml"), "--points", str(table1_files / "points.csv"))
    assert r.returncode == 2 and "has no 'camera_matrix'" in r.stderr


def test_coplanarity_check_memory_is_linear_in_points() -> None:
    """200,000 points: the plane fit must not build an N x N matrix (a full SVD needed 6.3 GB for 20,000)."""
    import resource

    import numpy as np

    from dronecal_field.core.calibrate import _points_off_main_plane

    X = np.random.default_rng(0).normal(size=(200_000, 3))
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    n_off = _points_off_main_plane(X, 0.1)
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert 150_000 < n_off < 200_000
    assert grown_mb < 500


@pytest.mark.parametrize("case", ["non_utf8_points", "plot_into_missing_folder", "points_is_a_folder"])
def test_environment_errors_are_one_line(table1_files, case):
    cam, pts = table1_files / "camera.yaml", table1_files / "points.csv"
    extra: list[str] = []
    if case == "non_utf8_points":
        pts = table1_files / "latin1.csv"
        pts.write_bytes(b"x,y,z\n\xe9,1,2\n")
    elif case == "plot_into_missing_folder":
        extra = ["--trials", "20", "--plot-convergence", str(table1_files / "missing" / "fig.png")]
    else:
        pts = table1_files
    r = run_cli("uncertainty", "--camera", str(cam), "--points", str(pts), *extra)
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dronecal-field uncertainty: error:")


def test_a_cold_numba_cache_is_announced_in_one_line(tmp_path) -> None:
    """An empty numba cache (the first run after install) is seen without compiling, and said on stderr once,
    when the first solve is about to compile (a command refused on its input before that says nothing more)."""
    import os
    import subprocess
    import sys

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "empty-cache"))
    head = "from dronecal_field.cli import announce_first_compile; from dronecal_field.core.kernels import announce_compile_once; "
    quiet = subprocess.run([sys.executable, "-c", head + "announce_first_compile()"], capture_output=True, text=True, env=env, timeout=120)
    assert quiet.returncode == 0 and quiet.stderr.strip() == ""
    code = head + "announce_first_compile(); announce_compile_once(); announce_compile_once()"  # the solves
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert r.returncode == 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and "compiling the numerical kernels once" in lines[0] and "45 s" in lines[0]
    assert not (tmp_path / "empty-cache").exists() or not any((tmp_path / "empty-cache").rglob("*.nbc"))  # nothing compiled


def test_monte_carlo_memory_is_bounded_for_many_points() -> None:
    """The trials solved together shrink with the point count: ~300 bytes per (trial, point) stay under ~300 MB."""
    import resource

    import numpy as np

    from dronecal_field.core.synthetic import paper_camera
    from dronecal_field.core.uncertainty import MAX_TRIAL_POINTS_PER_CHUNK, monte_carlo, trials_per_chunk

    assert trials_per_chunk(2000, 60) == 2000  # the paper's grids: all 500 trials in one go, as before
    assert trials_per_chunk(2000, 20_000) == 50 and trials_per_chunk(2000, 100_000) == 10
    assert trials_per_chunk(2000, 5_000_000) == 1
    assert all(trials_per_chunk(2000, n) * n <= max(MAX_TRIAL_POINTS_PER_CHUNK, n) for n in (1, 7, 999, 12_345, 10**6, 10**7))
    # 20,000 points x 100 trials in chunks of 50: the peak is one chunk (~300 MB), not 100 x 20,000 x 300 B (600 MB)
    cam = paper_camera(distorted=True)
    rng = np.random.default_rng(1)
    i = cam.intrinsics
    uv = rng.uniform([20, 20], [i.width - 20, i.height - 20], (20_000, 2))
    depth = rng.uniform(4.0, 12.0, 20_000)
    rays = np.column_stack([(uv[:, 0] - i.cx) / i.fx, (uv[:, 1] - i.cy) / i.fy, np.ones(len(uv))])
    X = cam.pose.position_world + (depth[:, None] * rays) @ cam.pose.R_cam_from_world
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    mc = monte_carlo(cam, X, trials=100, seed=3)
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before) / 1024
    assert mc.trials == 100 and mc.failed_trials == 0
    assert 2.0 < mc.rms_mean < 6.0  # 2 px per axis plus 1-1.5 cm of 3D noise, on 20,000 points
    assert grown_mb < 450
