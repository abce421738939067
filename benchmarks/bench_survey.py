"""Survey speed: the batched engine on Dask against a plain cv2.calibrateCamera loop, and 1 -> 2 worker scaling.

    .venv/bin/python benchmarks/bench_survey.py                  # scaling (200 cameras) + cv2 comparison
    .venv/bin/python benchmarks/bench_survey.py --full           # + the paper's full study: 5000 cameras x 500 trials, one strategy
    .venv/bin/python benchmarks/bench_survey.py --full-cameras 500   # a smaller "full" run to extrapolate from

Every timed run starts after the workers have compiled (or loaded) the numba
kernels (``cluster.run_on_every_worker(warm_up)``), so rates exclude JIT.
The cv2 loop is the paper's algorithm literally: per trial, perturb, then
``cv2.calibrateCamera`` (intrinsic guess = the true camera, k3 fixed: the
engine's 'default' model) on one process; its time per trial, times 500, is
compared with the engine's time per camera at 500 trials on one process.
Prints a readable summary and one JSON line.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dronecal_field.cluster import dask_client  # noqa: E402
from dronecal_field.survey.catalogue import PaperLattice, catalogue  # noqa: E402
from dronecal_field.survey.design import latin_hypercube  # noqa: E402
from dronecal_field.survey.evaluate import MonteCarloSettings, evaluate_camera, warm_up  # noqa: E402
from dronecal_field.survey.runner import SurveyConfig, run_survey  # noqa: E402
from dronecal_field.survey.store import load_results  # noqa: E402

STRATEGY = "far-y1-z2"


BUSY = "s = 0\nfor i in range(15_000_000): s += i"


def machine_baseline() -> dict:
    """How well this machine runs two CPU-bound processes at once right now (shared machines vary).

    Pure-Python loops share nothing, so 2 processes / 1 process throughput
    is the ceiling any 1 -> 2 worker scaling can reach at this moment.
    """
    import os
    import subprocess

    def wall(n: int) -> float:
        t0 = time.perf_counter()
        procs = [subprocess.Popen([sys.executable, "-c", BUSY]) for _ in range(n)]
        for p in procs:
            p.wait()
        return time.perf_counter() - t0

    one, two = wall(1), wall(2)
    return {"busy_loop_scaling": 2.0 * one / two, "loadavg_1min": os.getloadavg()[0]}


def survey_rate(n_cameras: int, trials: int, workers: int, seed: int = 0, progress: bool = False) -> dict:
    """Run a fresh one-strategy survey on a local cluster; rows/s after warm-up."""
    config = SurveyConfig(n_cameras=n_cameras, design_seed=seed, settings=MonteCarloSettings(trials=trials, seed=seed))
    with tempfile.TemporaryDirectory(prefix="bench-survey-") as d, dask_client(None, workers) as client:
        t0 = time.perf_counter()
        report = run_survey(config, catalogue(STRATEGY), Path(d) / "r", client=client, batch_size=10, progress=progress)
        wall = time.perf_counter() - t0
        table = load_results(Path(d) / "r")
    ok = sum(s == "ok" for s in table.column("status").to_pylist())
    return {
        "cameras": n_cameras,
        "trials": trials,
        "workers": workers,
        "rows": report.computed,
        "ok_rows": ok,
        "wall_s_with_warmup": wall,
        "rows_per_s": report.rows_per_s,
        "compute_s": report.compute_s,
        "run_s": report.computed / report.rows_per_s if report.rows_per_s else float("nan"),
    }


def cv2_loop(n_cameras: int, trials: int, seed: int = 0) -> dict:
    """Seconds per Monte-Carlo trial with cv2.calibrateCamera, and per camera (500 trials) with the engine, on one process."""
    import cv2
    import numba

    # one core each: cv2 and the engine both get a single thread, as a survey worker does
    cv2.setNumThreads(1)
    numba.set_num_threads(1)
    warm_up()
    settings = MonteCarloSettings(trials=500, seed=seed)
    lattice = PaperLattice()
    strat = catalogue(STRATEGY)[0]
    cams = []
    for sc in latin_hypercube(400, seed):
        cam = sc.camera()
        pts = lattice.points(strat, cam)
        if len(pts) >= 30:
            cams.append((sc, cam, pts))
        if len(cams) == n_cameras:
            break
    rng = np.random.default_rng(seed)
    cv2_s, engine_s, cv2_rms, engine_rms = [], [], [], []
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 30, 1e-9)
    for sc, cam, pts in cams:
        uv = cam.project(pts)
        K0 = cam.intrinsics.matrix
        d0 = cam.distortion.as_array()
        rms = []
        t0 = time.perf_counter()
        for _ in range(trials):
            Q = (pts + rng.standard_normal(pts.shape) * np.array(settings.sigma_3d)).astype(np.float32)
            q = (uv + rng.standard_normal(uv.shape) * settings.sigma_2d).astype(np.float32)
            err, *_ = cv2.calibrateCamera([Q], [q], (cam.width, cam.height), K0.copy(), d0.copy(), flags=flags, criteria=crit)
            rms.append(err)
        cv2_s.append((time.perf_counter() - t0) / trials)
        cv2_rms.append(float(np.mean(rms)))
        t0 = time.perf_counter()
        row = evaluate_camera(cam, pts, settings, seed)
        engine_s.append(time.perf_counter() - t0)
        engine_rms.append(row["rms_mean"])
    per_camera_cv2 = float(np.mean(cv2_s)) * 500
    per_camera_engine = float(np.mean(engine_s))
    return {
        "cameras": len(cams),
        "cv2_trials_per_camera": trials,
        "points_mean": float(np.mean([len(p) for *_, p in cams])),
        "cv2_s_per_trial": float(np.mean(cv2_s)),
        "cv2_s_per_camera_500": per_camera_cv2,
        "engine_s_per_camera_500": per_camera_engine,
        "speedup_one_process": per_camera_cv2 / per_camera_engine,
        "cv2_rms_mean": cv2_rms,
        "engine_rms_mean": engine_rms,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--full", action="store_true", help="run the paper's full study: 5000 cameras x 500 trials, 2 workers")
    ap.add_argument("--full-cameras", type=int, default=None, help="cameras of the full run (default 5000 with --full)")
    ap.add_argument("--scaling-cameras", type=int, default=200, help="cameras for the 1 vs 2 worker measurement (0 skips)")
    ap.add_argument("--cv2-cameras", type=int, default=5, help="cameras for the cv2 loop (0 skips)")
    ap.add_argument("--cv2-trials", type=int, default=60, help="cv2 trials per camera (extrapolated to 500)")
    ap.add_argument("--trials", type=int, default=500)
    args = ap.parse_args()
    out: dict = {}
    if args.cv2_cameras:
        c = cv2_loop(args.cv2_cameras, args.cv2_trials)
        out["cv2"] = c
        print(f"cv2.calibrateCamera loop: {c['cv2_s_per_trial'] * 1e3:.2f} ms/trial -> {c['cv2_s_per_camera_500']:.2f} s per camera at 500 trials "
              f"({c['points_mean']:.0f} points); engine {c['engine_s_per_camera_500']:.3f} s per camera: {c['speedup_one_process']:.1f}x on one process")
        print("  mean RMS cv2 vs engine (px): " + ", ".join(f"{a:.2f}/{b:.2f}" for a, b in zip(c["cv2_rms_mean"], c["engine_rms_mean"])))
    if args.scaling_cameras:
        before = machine_baseline()
        one = survey_rate(args.scaling_cameras, args.trials, 1)
        two = survey_rate(args.scaling_cameras, args.trials, 2)
        after = machine_baseline()
        out["scaling"] = {"one": one, "two": two, "speedup": two["rows_per_s"] / one["rows_per_s"], "machine_before": before, "machine_after": after}
        print(f"scaling, {args.scaling_cameras} cameras x {args.trials} trials: 1 worker {one['rows_per_s']:.2f} rows/s, "
              f"2 workers {two['rows_per_s']:.2f} rows/s: {out['scaling']['speedup']:.2f}x "
              f"(machine ceiling for 2 CPU-bound processes now: {before['busy_loop_scaling']:.2f}x before, "
              f"{after['busy_loop_scaling']:.2f}x after; load {before['loadavg_1min']:.1f})")
    n_full = args.full_cameras or (5000 if args.full else None)
    if n_full:
        full = survey_rate(n_full, args.trials, 2, progress=True)
        out["full"] = full
        extrap = 5000 / full["rows_per_s"] if full["rows_per_s"] else float("nan")
        full["extrapolated_5000_s"] = extrap
        print(f"full study, {n_full} cameras x {args.trials} trials, 2 workers: {full['run_s']:.0f} s "
              f"({full['wall_s_with_warmup']:.0f} s with cluster start and warm-up), {full['rows_per_s']:.2f} rows/s, "
              f"{full['ok_rows']} ok rows; 5000 cameras: {extrap / 60:.1f} min")
        if "cv2" in out:
            cv2_total = out["cv2"]["cv2_s_per_camera_500"] * full["ok_rows"] * 5000 / n_full / 2
            print(f"  the cv2 loop on the same 2 cores would take ~{cv2_total / 3600:.1f} h: {cv2_total / extrap:.0f}x")
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
