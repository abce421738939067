"""A small survey in-process and on a real Dask cluster (``dask scheduler`` + two ``dask worker`` processes), and resume after SIGKILL."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from dronecal_field.cluster import SINGLE_THREAD_ENV, dask_client
from dronecal_field.errors import InputError
from dronecal_field.survey.catalogue import catalogue
from dronecal_field.survey.evaluate import MonteCarloSettings
from dronecal_field.survey.runner import SurveyConfig, run_survey
from dronecal_field.survey.store import ResultStore, load_results

DASK = Path(sys.executable).parent / "dask"


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """Address of a scheduler with two single-thread workers, all on 127.0.0.1 with free ports."""
    d = tmp_path_factory.mktemp("dask")
    sched_file = d / "scheduler.json"
    env = {**os.environ, **SINGLE_THREAD_ENV}
    log = open(d / "dask.log", "wb")
    procs = [subprocess.Popen([str(DASK), "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
                               "--scheduler-file", str(sched_file)], stdout=log, stderr=log, env=env)]
    try:
        deadline = time.monotonic() + 60
        while not sched_file.is_file() and time.monotonic() < deadline:
            time.sleep(0.1)
        address = json.loads(sched_file.read_text())["address"]
        for _ in range(2):
            procs.append(subprocess.Popen([str(DASK), "worker", address, "--nthreads", "1", "--no-nanny", "--no-dashboard",
                                           "--host", "127.0.0.1"], stdout=log, stderr=log, env=env, cwd=str(d)))
        from distributed import Client

        with Client(address, timeout=30) as c:
            c.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            try:
                p.wait(timeout=15)
            except subprocess.TimeoutExpired:
                p.kill()
        log.close()


def _rows(path) -> dict[tuple[int, str], dict]:
    return {(r["camera_id"], r["strategy"]): r for r in load_results(path).to_pylist()}


def test_survey_in_process_and_on_a_cluster_gives_the_same_rows(scheduler, tmp_path):
    config = SurveyConfig(n_cameras=8, design_seed=4, settings=MonteCarloSettings(trials=40, seed=4))
    strategies = catalogue("paper")
    local = run_survey(config, strategies, tmp_path / "local", client=None, batch_size=5)
    with dask_client(scheduler) as client:
        remote = run_survey(config, strategies, tmp_path / "remote", client=client, batch_size=4)
    assert local.computed == remote.computed == 48 and remote.workers == 2
    a, b = _rows(tmp_path / "local"), _rows(tmp_path / "remote")
    assert a.keys() == b.keys() and len(a) == 48
    ok = [k for k in a if a[k]["status"] == "ok"]
    assert len(ok) >= 30
    for k in a:
        assert a[k]["status"] == b[k]["status"] and a[k]["n_points"] == b[k]["n_points"]
    # seeds depend on (seed, camera), not on the worker or the order: identical statistics
    np.testing.assert_allclose([a[k]["rms_mean"] for k in ok], [b[k]["rms_mean"] for k in ok], rtol=1e-9)
    np.testing.assert_allclose([a[k]["projection_error_px"] for k in ok], [b[k]["projection_error_px"] for k in ok], rtol=1e-9)
    # a finished survey run again computes nothing
    again = run_survey(config, strategies, tmp_path / "local", client=None)
    assert (again.already_done, again.computed) == (48, 0)
    # other settings into the same directory are refused, more strategies are welcome
    with pytest.raises(InputError, match="other settings"):
        run_survey(SurveyConfig(n_cameras=9, design_seed=4), strategies, tmp_path / "local")
    more = run_survey(config, catalogue("full-y0.5-z3"), tmp_path / "local", client=None)
    assert (more.already_done, more.computed) == (0, 8)
    assert len(_rows(tmp_path / "local")) == 56


def test_killed_survey_resumes_without_computing_a_row_twice(scheduler, tmp_path):
    out = tmp_path / "results.parquet"
    n_cameras, trials, batch = 40, 150, 3
    total = n_cameras * 2
    args = ["survey", "--cameras", str(n_cameras), "--trials", str(trials), "--strategies", "far-y1-z2,near-y1-z2",
            "--out", str(out), "--batch-size", str(batch), "--scheduler", scheduler, "--no-progress"]
    proc = subprocess.Popen([sys.executable, "-m", "dronecal_field", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    store = ResultStore(out)
    deadline = time.monotonic() + 120
    while len(store.parts()) < 2 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    proc.stdout.close()
    proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    stored = len(store.done_keys())
    assert 0 < stored < total, f"the survey was not killed mid-way ({stored} of {total} rows stored)"

    done = run_cli(*args, "--json", timeout=180)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["already_done"] == stored
    assert report["computed"] == total - stored
    table = load_results(out)
    keys = list(zip(table.column("camera_id").to_pylist(), table.column("strategy").to_pylist()))
    assert len(keys) == len(set(keys)) == total
    assert not list(out.glob(".*.tmp"))
    statuses = set(table.column("status").to_pylist())
    assert statuses <= {"ok", "degenerate", "failed"} and "ok" in statuses
