"""Benchmark: the batched Monte-Carlo against a loop of cv2.calibrateCamera, same perturbed data.

Run by hand:  .venv/bin/python benchmarks/bench_montecarlo.py [--trials 500] [--repeats 5] [--threads 1] [--compile] [--big 100000]

For each Table 1 camera, every repeat times, one after the other, the
cv2.calibrateCamera loop (the baseline), the engine's solve alone and the
whole ``monte_carlo`` (noise, solves, projection errors, parameter spreads);
the script prints the medians over the repeats as ms per trial and as
ratios against the baseline of the same run, in wall time and in CPU time
(all threads of the process: what the work costs whatever the load). The machine's load average is
printed with them: on a busy 2-core machine the engine's two threads share
the cores with everyone else, so only ratios measured together mean anything.

``--compile`` also measures, in fresh processes, the first run's compile
cost (an empty numba cache) and the cost of loading the cached kernels;
``--big`` runs one large k (chunked) and reports peak memory.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np

from dronecal_field.core.calibrate import BatchState, CalibrationModel, levenberg_marquardt
from dronecal_field.core.synthetic import paper_camera, paper_grid
from dronecal_field.core.uncertainty import monte_carlo


def perturbed(cam, X, k, seed):
    rng = np.random.default_rng(seed)
    uv = cam.project(X)
    Q = X[None] + rng.standard_normal((k, len(X), 3)) * np.array([0.01, 0.01, 0.015])
    q = uv[None] + rng.standard_normal((k, len(X), 2)) * 2.0
    return Q, q


def opencv_loop(cam, Q, q):
    flags = cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_K3
    out = np.empty(len(Q))
    for i in range(len(Q)):
        out[i] = cv2.calibrateCamera(
            [Q[i].astype(np.float32)], [q[i].astype(np.float32)], (cam.width, cam.height),
            cam.intrinsics.matrix.copy(), np.zeros(5), flags=flags,
        )[0]
    return out


def engine(cam, Q, q):
    A = CalibrationModel().parameter_map()
    state = BatchState.from_camera(cam, len(Q))
    _, cost, _ = levenberg_marquardt(state, Q, q, A, max_iterations=30, tolerance=1e-6)
    return np.sqrt(cost / Q.shape[1])


def timed(fn):
    """(wall s, CPU s of the whole process, all threads, result) of one call."""
    t, c = time.perf_counter(), time.process_time()
    out = fn()
    return time.perf_counter() - t, time.process_time() - c, out


# Run in a fresh process: the first Monte-Carlo of a process, and a second one.
_FIRST_RUN = """
import time
t0 = time.perf_counter()
from dronecal_field.core.synthetic import paper_camera, paper_grid
from dronecal_field.core.uncertainty import monte_carlo
cam = paper_camera(True)
X = paper_grid(cam)
t1 = time.perf_counter()
monte_carlo(cam, X, trials=500, seed=1)
t2 = time.perf_counter()
monte_carlo(cam, X, trials=500, seed=1)
t3 = time.perf_counter()
print(t1 - t0, t2 - t1, t3 - t2)
"""


def first_run(cache_dir: str) -> tuple[float, float, float]:
    """(import s, first monte_carlo s, second monte_carlo s) in a new process using numba cache ``cache_dir``."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir)
    out = subprocess.run([sys.executable, "-c", _FIRST_RUN], env=env, capture_output=True, text=True, check=True)
    imp, first, second = (float(v) for v in out.stdout.split())
    return imp, first, second


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats per camera; medians are printed (default 5)")
    parser.add_argument("--compile", action="store_true", help="also measure the first run's compile cost and the cached load, in fresh processes")
    parser.add_argument("--big", type=int, default=0, help="also run monte_carlo with this many trials and report peak memory")
    parser.add_argument("--threads", type=int, default=0, help="numba threads for the engine (default: numba's, one per CPU)")
    args = parser.parse_args()

    import numba

    if args.threads:
        numba.set_num_threads(args.threads)

    print(f"numba {numba.__version__}, {numba.get_num_threads()} threads; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    for distorted in (False, True):
        cam = paper_camera(distorted)
        X = paper_grid(cam)
        Q, q = perturbed(cam, X, args.trials, seed=1)
        engine(cam, Q[:10], q[:10])  # JIT warm-up (numba caches to disk after the first run)
        monte_carlo(cam, X, trials=10, seed=1)
        t_cv, t_en, t_mc, c_cv, c_en, c_mc = [], [], [], [], [], []
        for _ in range(args.repeats):
            t, c, rms_cv = timed(lambda: opencv_loop(cam, Q, q))
            t_cv.append(t)
            c_cv.append(c)
            t, c, rms_en = timed(lambda: engine(cam, Q, q))
            t_en.append(t)
            c_en.append(c)
            t, c, mc = timed(lambda: monte_carlo(cam, X, trials=args.trials, seed=1))
            t_mc.append(t)
            c_mc.append(c)
        cv, en, full = (float(np.median(v)) / args.trials * 1e3 for v in (t_cv, t_en, t_mc))
        cpu_cv, cpu_en, cpu_full = (float(np.median(v)) / args.trials * 1e3 for v in (c_cv, c_en, c_mc))
        name = "distorted" if distorted else "pinhole"
        print(f"Table 1 {name} camera, {len(X)} points, k = {args.trials}, median of {args.repeats} (ms per trial); engine {monte_carlo.__module__} from {sys.modules[monte_carlo.__module__].__file__}")
        print(f"  cv2.calibrateCamera loop : {cv:8.4f}   mean RMS {rms_cv.mean():.5f}  var {rms_cv.var(ddof=1):.5f}  max {rms_cv.max():.4f}")
        print(f"  batched engine (solve)   : {en:8.4f}   mean RMS {rms_en.mean():.5f}  var {rms_en.var(ddof=1):.5f}  max {rms_en.max():.4f}")
        print(f"  monte_carlo (+ projection errors, parameter spreads): {full:8.4f}   mean RMS {mc.rms_mean:.5f}  "
              f"std fx {mc.param_std['fx']:.4f} px, k1 {mc.param_std['k1']:.5f}, ground 15 m {mc.ground_error_15m_cm:.3f} cm")
        print(f"  ratio solve  : {cv / en:6.1f}x   mean RMS differs by {abs(rms_en.mean() / rms_cv.mean() - 1) * 100:.4f}%")
        print(f"  ratio full MC: {cv / full:6.1f}x   (spread over repeats: {min(t_cv) / max(t_mc):.0f}x - {max(t_cv) / min(t_mc):.0f}x)")
        print(f"  CPU time, all threads (ms per trial): cv2 {cpu_cv:.4f}, solve {cpu_en:.4f}, full MC {cpu_full:.4f}: "
              f"ratios {cpu_cv / cpu_en:.1f}x and {cpu_cv / cpu_full:.1f}x")
    print(f"load average at the end {os.getloadavg()[0]:.1f}")

    if args.compile:
        with tempfile.TemporaryDirectory() as cold:
            imp, first, second = first_run(cold)
            print(f"first run, empty numba cache: import {imp:.1f} s, first monte_carlo (compiles) {first:.1f} s, second {second * 1e3:.0f} ms")
            imp, first, second = first_run(cold)
            print(f"next run, cached kernels: import {imp:.1f} s, first monte_carlo (loads them) {first:.2f} s, second {second * 1e3:.0f} ms")

    if args.big:
        cam = paper_camera(True)
        X = paper_grid(cam)
        before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        t = time.perf_counter()
        mc = monte_carlo(cam, X, trials=args.big, seed=2)
        dt = time.perf_counter() - t
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        print(f"k = {args.big}: {dt:.1f} s, mean RMS {mc.rms_mean:.4f}, peak RSS {peak / 1024:.0f} MiB (was {before / 1024:.0f} MiB before)")


if __name__ == "__main__":
    main()
