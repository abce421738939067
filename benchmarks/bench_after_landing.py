"""What ``fly --calibrate`` does after landing, on a recorded run, worst case: the live worker reached nothing in flight.

Run by hand::

    .venv/bin/python benchmarks/bench_after_landing.py RUN.mcap --plan-dir PLAN [--repeat 1]

A ``LiveCalibration`` is built as ``fly`` builds it (the plan's mission,
marker, ROI and site origin) and handed the run's GNSS fixes, attitudes and
hover/leg events through its observer, with no worker thread: every waypoint
is then one ``fly`` could not check in flight (the job queue full, its frames
gone from the ring), as on a starved machine. Then, in this one process,
``session.conclude`` (the after-landing checks from the run file, the
verdict) and ``session.calibrate_after_landing`` (``calibrate`` taking the
frame cache). Printed: the CPU seconds (this process, all threads) and wall
of each, the load, and calibrate's own line of frames taken from the cache.
Speed claims use the CPU seconds: the machine is shared.

Measured 2026-11-27 on /tmp/h22/b7/run.mcap (bench_rtsp_chain's 720p10 H.265
run of 13:03, 1621 frames, 77 hover/leg events; load 10-15), each line one
step of this round's change to the live worker:

- before: conclude 25.9 s CPU (every waypoint's frames decoded from its
  keyframe, the fix track made per waypoint: 6.7 s of it) + calibrate 24.0 s
  CPU taking no frame from the cache = 49.9 s;
- decoded outcomes kept in the frame cache, holds on calibrate's keyframe
  bursts, the track made once: 24.2 + 16.1 = 40.3 s; calibrate takes 342 of
  its 681 frames from the cache;
- legs on calibrate's leg_period grid: 23.0 + 11.9 = 34.8 s; 506 of 681 from
  the cache. The same calibration (fx 1000.08 px) and verdict throughout.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def main() -> int:
    from dronecal_field.live.progress import LiveOptions
    from dronecal_field.live.session import calibrate_after_landing, conclude
    from dronecal_field.live.worker import LiveCalibration
    from dronecal_field.mavlink.missionfile import read_mission
    from dronecal_field.runfile.reader import open_run
    from dronecal_field.runfile.records import site_origin_from_plan_json

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path)
    p.add_argument("--plan-dir", type=Path, required=True, help="the plan folder flown (plan.json, mission.plan)")
    p.add_argument("--mission", default=None, help="the mission file flown (default: PLAN/mission.plan, else mission-1.plan)")
    p.add_argument("--min-fix", default="rtk_fixed")
    p.add_argument("--profile", type=Path, default=None, help="write a CPU-time cProfile of the whole after-landing part here")
    args = p.parse_args()
    plan_json = json.loads((args.plan_dir / "plan.json").read_text())
    mission_path = Path(args.mission) if args.mission else args.plan_dir / "mission.plan"
    if not mission_path.exists():
        mission_path = args.plan_dir / "mission-1.plan"
    mission = read_mission(mission_path)
    work = Path(tempfile.mkdtemp(prefix="bench-after-landing-"))
    run_path = work / "run.mcap"
    os.symlink(args.run.resolve(), run_path)  # calibrate writes RUN-calibration/ beside it: not beside the original
    with open_run(run_path) as run:
        md = run.metadata
        records = sorted(list(run.iter_fixes()) + list(run.iter_attitude()) + [e for e in run.iter_events() if e.type in ("hover", "leg")],
                         key=lambda r: r.timestamp_ns)
    live = LiveCalibration(mission, md.marker, md.width, md.height, plan=plan_json, origin=site_origin_from_plan_json(plan_json),
                           options=LiveOptions(min_fix=args.min_fix), camera_latency_s=md.camera_latency_s)
    for r in records:
        live.on_record(r)
    print(f"{sum(1 for r in records if getattr(r, 'type', None) in ('hover', 'leg'))} hover/leg events, "
          f"{len(live._deferred)} deferred + {live._jobs.qsize()} queued (no worker ran); load {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores", flush=True)
    prof = None
    if args.profile:
        import cProfile

        prof = cProfile.Profile(time.process_time)
        prof.enable()
    c0, t0 = cpu_s(), time.monotonic()
    result, lines = conclude(live, run_path, mission, timeout_s=1.0)
    c1, t1 = cpu_s(), time.monotonic()
    print(f"conclude: {c1 - c0:.1f} s CPU, {t1 - t0:.1f} s wall; {len(result.checked_after_landing)} waypoints checked after landing")
    for line in lines[-3:]:
        print("  " + line[:160])
    out = calibrate_after_landing(run_path, args.min_fix, t0, live)
    c2, t2 = cpu_s(), time.monotonic()
    if prof is not None:
        prof.disable()
        prof.dump_stats(args.profile)
    print(f"calibrate_after_landing: {c2 - c1:.1f} s CPU, {t2 - t1:.1f} s wall")
    for line in out:
        if any(k in line for k in ("fx ", "detections:", "corrupt", "calibration ready")):
            print("  " + line[:160])
    print(f"after landing in all: {c2 - c0:.1f} s CPU, {t2 - t0:.1f} s wall (load {os.getloadavg()[0]:.1f}); work folder {work}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
