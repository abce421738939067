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


def fly_on_sitl(plan: Path, speedup: float) -> tuple[float, dict[int, float], float]:
    """Fly ``plan`` on ArduCopter 4.7 SITL from its home: (MISSION_START vehicle s, seq -> reached s, "Disarming motors" s)."""
    import contextlib
    import time

    import sitl_conformance as conf
    from sitl import ArduCopterSitl

    from dronecal_field.mavlink.control import arm_and_start_mission, request_telemetry
    from dronecal_field.mavlink.link import open_link
    from dronecal_field.mavlink.mission import upload_and_verify

    items = mf.read_mission(plan).items
    home = (items[0].x * 1e-7, items[0].y * 1e-7, float(items[0].z))
    with ArduCopterSitl.start(home, heading_deg=0.0, speedup=speedup) as sitl:
        with sitl.netns():
            gcs = open_link(sitl.gcs_url)
        with contextlib.closing(gcs):
            rec = conf._Recorder(gcs)
            gcs.wait_heartbeat(30)
            request_telemetry(gcs)
            deadline = time.monotonic() + 300
            while time.monotonic() < deadline:
                ekf, gps, st = gcs.latest("EKF_STATUS_REPORT"), gcs.latest("GPS_RAW_INT"), gcs.latest("SYS_STATUS")
                if ekf is not None and conf._ekf_healthy(ekf.flags) and gps is not None and gps.fix_type >= 3 and st is not None \
                        and st.onboard_control_sensors_health & conf.ap.MAV_SYS_STATUS_PREARM_CHECK:  # fmt: skip
                    break
                time.sleep(0.2)
            upload_and_verify(gcs, items, ready_timeout_s=120)
            arm_and_start_mission(gcs, timeout_s=2.0)
            start = rec.now()
            deadline = time.monotonic() + 3600
            while time.monotonic() < deadline and not any(str(m.text).startswith("Disarming") for _t, _w, m in rec.messages("STATUSTEXT", start + 5)):
                time.sleep(0.5)
            reached = {}
            for t, _w, m in rec.messages("MISSION_ITEM_REACHED"):
                reached.setdefault(int(m.seq), t)
            disarm = next(t for t, _w, m in rec.messages("STATUSTEXT", start + 5) if str(m.text).startswith("Disarming"))
            return start, reached, disarm


def planned_flight_s(plan: Path, flight: FlightModel) -> float:
    """The plan's whole flight, arming to disarm, as `plan.route` times it (take-off, legs, holds, NAV_LAND at home)."""
    from dronecal_field.plan.route import descent_time_s, takeoff_time_s

    items = mf.read_mission(plan).items
    home = items[0]
    origin = EnuOrigin(home.x * 1e-7, home.y * 1e-7, float(home.z))
    takeoff = next(it for it in items if it.command == mf.CMD_NAV_TAKEOFF)
    pts, holds, speeds = [np.array([0.0, 0.0, float(takeoff.z)])], [0.0], []
    speed = flight.speed_m_s
    for it in items[1:]:
        if it.command == mf.CMD_DO_CHANGE_SPEED and it.p2 > 0:
            speed = float(it.p2)
        if it.command == mf.CMD_NAV_WAYPOINT:
            e, n, _ = geodetic_to_enu(it.x * 1e-7, it.y * 1e-7, float(home.z), origin)[0]
            pts.append(np.array([e, n, float(it.z)]))
            holds.append(float(round(it.p1)))
            speeds.append(speed)
    P, H = np.asarray(pts), np.asarray(holds)
    legs = np.append(np.linalg.norm(np.diff(P, axis=0), axis=1), 0.0)  # the leg leaving each point
    stop = ~((H <= 0) & (legs > 0.01))
    stop[0] = stop[-1] = True
    reached = path_reached_s(P, stop, np.asarray(speeds), flight, H)
    return takeoff_time_s(float(takeoff.z), flight) + float(reached[-1] + H[-1]) + descent_time_s(float(P[-1, 2]), flight)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sitl", type=Path, default=None, help="also fly this .plan on ArduCopter 4.7 SITL and compare the whole flight")
    parser.add_argument("--speedup", type=float, default=5.0, help="SITL clock, x wall time (default 5)")
    args = parser.parse_args(argv)
    flight = FlightModel()
    if args.sitl is not None:
        planned = planned_flight_s(args.sitl, flight)
        start, reached, disarm = fly_on_sitl(args.sitl, args.speedup)
        print(f"{args.sitl}: planned {planned:.1f} s, flown on ArduCopter 4.7 SITL {disarm - start:.1f} s (MISSION_START to disarm), "
              f"planned / flown {planned / (disarm - start):.3f}; {len(reached)} MISSION_ITEM_REACHED")
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
