"""Issue 23: pooling a scout with its main flight, weighted by each run's noise against weighted alike.

    .venv/bin/python benchmarks/bench_scout_pool.py DIR [DIR ...]

DIR is a camera's folder of bench_scout.py (truth.yaml beside scout.mcap, main.mcap) or of bench_scout_writer.py
(its truth is bench_scout_writer's for the folder's name: wide, 4k, table1). Printed per folder: the ground 3-30 m
error against the truth of the main run alone (calibration-main/, as the bench wrote it), the scout + main pooled
with each run weighted by its own noise (calibration-pooled/, today's ``calibrate --joint``), and the same points
pooled with every point weighted alike (joint.EQUAL_NOISE_RATIO set to infinity, in this process only: the pooling
before noise weighting), plus the noise each run's points were weighted by.
"""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _truth(folder: Path):
    from dronecal_field.camerafile import read_camera

    if (folder / "truth.yaml").exists():
        return read_camera(folder / "truth.yaml")
    from bench_scout_writer import _truth as writer_truth

    return writer_truth(folder.name)


def _ground(truth, cal: Path):
    from dronecal_field.camerafile import read_camera
    from dronecal_field.demo import in_enu_frame_of
    from dronecal_field.sim.compare import compare_cameras

    return compare_cameras(truth, in_enu_frame_of(read_camera(cal / "camera.yaml"), truth.enu_origin), ground_step_m=0.5).ground


def main() -> None:
    from dronecal_field.pipeline import joint
    from dronecal_field.pipeline.run import CalibrateOptions, calibrate_runs

    for folder in map(Path, sys.argv[1:]):
        truth = _truth(folder)
        runs = [folder / "scout.mcap", folder / "main.mcap"]
        alike = folder / "calibration-pooled-alike"
        rep = json.loads((folder / "calibration-pooled" / "report.json").read_text())
        if not (alike / "camera.yaml").exists():
            ratio = joint.EQUAL_NOISE_RATIO
            joint.EQUAL_NOISE_RATIO = float("inf")
            try:
                # the pooled calibration's settle (bench_scout gives 1 vehicle second on the run's wall clock, slowed vehicles)
                base = CalibrateOptions(trials=0, out_dir=alike)
                settle = rep.get("options", {}).get("settle_s", base.points.settle_s)
                calibrate_runs(runs, replace(base, points=replace(base.points, settle_s=settle)))
            finally:
                joint.EQUAL_NOISE_RATIO = ratio
        noise = {Path(r["path"]).name: r["noise_px_weighted_by"] for r in rep["joint"]["runs"]}
        row = {tag: _ground(truth, folder / f"calibration-{tag}") for tag in ("main", "pooled", "pooled-alike")}
        print(f"{folder}: ground 3-30 m RMS / max px: main alone {row['main'].rms_px:.3f} / {row['main'].max_px:.2f}, "
              f"pooled by noise {row['pooled'].rms_px:.3f} / {row['pooled'].max_px:.2f}, pooled alike "
              f"{row['pooled-alike'].rms_px:.3f} / {row['pooled-alike'].max_px:.2f}; noise px {noise}", flush=True)


if __name__ == "__main__":
    main()
