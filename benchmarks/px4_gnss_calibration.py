"""The PX4 flight calibrated with the SITL's GNSS (3D fix, 0.2 m / 0.5 m) and with RTK: truth, confidence, what the report says.

One plan (the demo camera's; by default the PX4 SITL CI flight's,
tests/data/px4_sitl_mission.plan: 8 holds of 8 s spread over the image), flown by
`fly --start` on `sim vehicle --autopilot px4` with `sim camera`, once per
receiver and seed: ``--gnss auto`` (PX4 SITL's SensorGpsSim: white noise
0.2 m per horizontal axis and 0.5 m vertical, fix type 3, h_acc 900 mm) and
``--gnss rtk`` (RTK fixed, 7 mm / 15 mm). Each run is calibrated from its holds
(``--leg-source none``, as tests/test_px4_sitl.py calibrates) and scored
against the simulator's truth camera: focal error (%), camera position
(cm), ground 3-30 m (px), and the report's own confidence (Monte-Carlo
focal std, ground error at 15 m) against the true error, with the sentence
the report prints about the GNSS (pipeline/gnss_quality.py).

Run: ``.venv/bin/python benchmarks/px4_gnss_calibration.py [--seeds 2] [--speedup 2] [--mission PLAN | --replan]``
(about 2-4 min a flight on a busy 2-core machine).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO / "tests") not in sys.path:
    sys.path.insert(0, str(REPO / "tests"))

from dronecal_field.demo import cli_argv  # noqa: E402
from test_px4_sim_flight import fly_px4_sim, plan_for_px4, score  # noqa: E402

SITL_MISSION = REPO / "tests" / "data" / "px4_sitl_mission.plan"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("/tmp/px4-gnss-calibration"))
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--speedup", type=float, default=2.0)
    parser.add_argument("--mission", type=Path, default=SITL_MISSION, help="the plan flown (default: the PX4 SITL CI flight's)")
    parser.add_argument("--replan", action="store_true", help="plan again (the demo camera, 3 min) instead of flying --mission")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.replan and not args.mission.is_file():
        parser.error(f"--mission {args.mission}: no such plan; give a .plan file or --replan")
    mission = plan_for_px4(args.out, saved=False) if args.replan else args.mission
    plan_for_px4(args.out)  # the truth camera goes to out/truth.yaml
    truth = args.out / "truth.yaml"
    rows = []
    for seed in range(args.seeds):
        for gnss in ("auto", "rtk"):
            out = args.out / f"{gnss}-{seed}"
            if out.exists():
                shutil.rmtree(out)
            out.mkdir()
            shutil.copy(truth, out / "truth.yaml")
            t0 = time.monotonic()
            try:
                fly_px4_sim(out, mission, gnss=gnss, speedup=args.speedup, seed=seed, trials=10)
            except AssertionError:  # calibrate (with legs) refused: the holds-only calibration below is the one scored
                pass
            if not (out / "run.mcap").is_file():
                rows.append(dict(gnss=gnss, seed=seed, refused="the flight failed: see " + str(out / "logs" / "fly.log")))
                continue
            # as tests/test_px4_sitl.py calibrates: holds only (a leg's pairs carry each 3D fix's 0.5 m unaveraged)
            shutil.rmtree(out / "calibration", ignore_errors=True)
            min_fix = "rtk_fixed" if gnss == "rtk" else "3d"
            proc = subprocess.run(cli_argv("calibrate", out / "run.mcap", "--out", out / "calibration", "--trials", 100, "--min-fix", min_fix,
                                           "--leg-source", "none", "--settle-s", f"{1.0 / args.speedup:.3f}"),
                                  capture_output=True, text=True, timeout=900)  # fmt: skip
            (out / "logs" / "calibrate-holds.log").write_text(proc.stdout + proc.stderr)
            if proc.returncode != 0:
                refused = (proc.stdout + proc.stderr).strip().splitlines()[-1][:300]
                rows.append(dict(gnss=gnss, seed=seed, refused=refused))
                print(json.dumps(rows[-1]), flush=True)
                continue
            s = score(out)
            report = s["report"]
            row = dict(gnss=gnss, seed=seed, wall_s=round(time.monotonic() - t0), focal_pct=s["focal_pct"], focal_px=s["focal_px"],
                       focal_std_px=s["focal_std_px"], position_cm=s["position_cm"], ground_px=s["ground_px"], ground_15m_cm=s["ground_15m_cm"],
                       ground_15m_std_cm=s["ground_15m_std_cm"], ground_15m_p95_cm=s["ground_15m_p95_cm"], holds_used=s["holds_used"],
                       quality=report["gnss"].get("quality"))  # fmt: skip
            rows.append(row)
            print(json.dumps(row, default=str), flush=True)
    print("\n| GNSS | seed | focal error | focal std (report) | camera position | ground 3-30 m | ground at 15 m: true / report (p95) | holds |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for r in rows:
        if "refused" in r:
            print(f"| {'SITL 3D fix (0.2/0.5 m)' if r['gnss'] == 'auto' else 'RTK (7/15 mm)'} | {r['seed']} | {r['refused']} | | | | | |")
            continue
        g15 = "n/a" if r["ground_15m_cm"] is None else f"{r['ground_15m_cm']:.1f}"
        print(f"| {'SITL 3D fix (0.2/0.5 m)' if r['gnss'] == 'auto' else 'RTK (7/15 mm)'} | {r['seed']} | {r['focal_pct']:+.2f} % ({r['focal_px']:.1f} px) "
              f"| {r['focal_std_px']:.1f} px | {r['position_cm']:.1f} cm | {r['ground_px']:.2f} px | {g15} / {r['ground_15m_std_cm']:.1f} "
              f"({r['ground_15m_p95_cm']:.1f}) cm | {r['holds_used']} |")  # fmt: skip
    for r in rows:
        if "quality" in r:
            print(f"{r['gnss']}-{r['seed']}: {' '.join(r['quality'] or [])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
