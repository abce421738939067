"""Benchmark: the batched Monte-Carlo against a loop of cv2.calibrateCamera, same perturbed data.

Run by hand:  .venv/bin/python benchmarks/bench_montecarlo.py [--trials 500] [--big 100000]

Prints both RMS statistics, the throughput ratio (baseline measured in the
same run), and with --big the peak memory of a large k (chunked).
"""

from __future__ import annotations

import argparse
import resource
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


def best_of(fn, repeats):
    best, out = np.inf, None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--trials", type=int, default=500)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--big", type=int, default=0, help="also run monte_carlo with this many trials and report peak memory")
    args = parser.parse_args()

    for distorted in (False, True):
        cam = paper_camera(distorted)
        X = paper_grid(cam)
        Q, q = perturbed(cam, X, args.trials, seed=1)
        engine(cam, Q[:10], q[:10])  # JIT warm-up (numba caches to disk after the first run)
        t_cv, rms_cv = best_of(lambda: opencv_loop(cam, Q, q), args.repeats)
        t_en, rms_en = best_of(lambda: engine(cam, Q, q), args.repeats)
        t_mc, mc = best_of(lambda: monte_carlo(cam, X, trials=args.trials, seed=1), args.repeats)
        name = "distorted" if distorted else "pinhole"
        print(f"Table 1 {name} camera, {len(X)} points, k = {args.trials}")
        print(f"  cv2.calibrateCamera loop : {t_cv * 1e3:8.1f} ms   mean RMS {rms_cv.mean():.5f}  var {rms_cv.var(ddof=1):.5f}  max {rms_cv.max():.4f}")
        print(f"  batched engine (solve)   : {t_en * 1e3:8.1f} ms   mean RMS {rms_en.mean():.5f}  var {rms_en.var(ddof=1):.5f}  max {rms_en.max():.4f}")
        print(f"  monte_carlo (+ projection errors, parameter spreads): {t_mc * 1e3:8.1f} ms")
        print(f"  ratio solve  : {t_cv / t_en:6.1f}x   mean RMS differs by {abs(rms_en.mean() / rms_cv.mean() - 1) * 100:.4f}%")
        print(f"  ratio full MC: {t_cv / t_mc:6.1f}x")

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
