"""What `fly`'s PX4 dialect (dronecal_field/mavlink/px4.py) assumes, row by row, against PX4 1.16 SITL (SIH).

Not yet the conformance of a simulated PX4 (`sim vehicle` is ArduPilot's
only): this table checks the model `fly` flies PX4 with against the firmware
itself, over real UDP in PX4's private namespaces (tests/px4_sitl.py), with
`fly`'s own client code: boot state, the mission protocol and read-back
rules, the ROI command PX4 refuses, GNSS and estimator reports, SIH's truth
stream, the start, MISSION_ITEM_REACHED repeats and the landing. A short
flight (take-off to 2 m, one 2 s hold 3 m away, land) runs in real time:
about 60 s in all.

Run: ``.venv/bin/python benchmarks/px4_conformance.py`` (needs
../shared/sitl/px4-1.16 and root for unshare).
"""

from __future__ import annotations

import collections
import math
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO / "tests") not in sys.path:
    sys.path.insert(0, str(REPO / "tests"))

from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic  # noqa: E402
from dronecal_field.mavlink import missionfile as mf  # noqa: E402
from dronecal_field.mavlink import px4  # noqa: E402
from dronecal_field.mavlink.control import arm_and_start_mission, request_telemetry, vehicle_state  # noqa: E402
from dronecal_field.mavlink.link import open_link  # noqa: E402
from dronecal_field.mavlink.mission import download_mission, send_mission, upload_and_verify  # noqa: E402
from dronecal_field.mavlink.missionfile import MissionItem  # noqa: E402
from dronecal_field.mavlink.preflight import VideoStatus, run_preflight  # noqa: E402
from px4_sitl import Px4Sitl, skip_reason  # noqa: E402

HOME = (-35.363261, 149.165230, 584.0)


def _at(e: float, n: float) -> tuple[int, int]:
    lat, lon, _h = enu_to_geodetic([e, n, 0.0], EnuOrigin(*HOME))[0]
    return int(round(lat * 1e7)), int(round(lon * 1e7))


def mission() -> mf.Mission:
    """Home, take-off 2 m, speed 1.5 m/s, ROI at the pole, a 2 s hold 3 m east at 2.5 m, land at home."""
    hx, hy = _at(0, 0)
    wx, wy = _at(3, 0)
    rx, ry = _at(0, -6)
    items = (
        MissionItem(seq=0, frame=0, command=16, x=hx, y=hy, z=HOME[2]),
        MissionItem(seq=1, frame=3, command=22, p4=math.nan, x=hx, y=hy, z=2.0),
        MissionItem(seq=2, frame=2, command=178, p1=1.0, p2=1.5, p3=-1.0),
        MissionItem(seq=3, frame=3, command=201, p1=3.0, x=rx, y=ry, z=1.0),
        MissionItem(seq=4, frame=3, command=16, p1=2.0, p4=236.57, x=wx, y=wy, z=2.5),
        MissionItem(seq=5, frame=3, command=21, p4=math.nan, x=hx, y=hy, z=0.0),
    )
    return mf.Mission(items=items, home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2])


def run() -> list[tuple[str, str, str, bool]]:
    rows: list[tuple[str, str, str, bool]] = []

    def row(what: str, model: object, sitl: object, ok: bool) -> None:
        rows.append((what, str(model), str(sitl), bool(ok)))
        print(f"{'ok ' if ok else 'DIFF'} {what}: fly assumes {model}; SITL {sitl}", flush=True)

    m = mission()
    with Px4Sitl.start(HOME) as sitl:
        with sitl.netns():
            link = open_link(sitl.gcs_url)
        with link:
            hb = link.wait_heartbeat(30)
            row("HEARTBEAT.autopilot", px4.MAV_AUTOPILOT_PX4, hb.autopilot, hb.autopilot == px4.MAV_AUTOPILOT_PX4)
            row("boot mode", "AUTO.LOITER", px4.mode_name(hb.custom_mode), px4.mode_name(hb.custom_mode) == "AUTO.LOITER")
            request_telemetry(link)
            hil = link.wait_message({"HIL_STATE_QUATERNION"}, timeout_s=0.1)  # not asked: GCS link
            link.command_long(511, (115, 1e5))
            hil = link.wait_message({"HIL_STATE_QUATERNION"}, timeout_s=3.0)
            row("HIL_STATE_QUATERNION (SIH truth) when asked", "10 Hz", "arrives" if hil else "none", hil is not None)
            time.sleep(3.0)
            cur = link.latest("MISSION_CURRENT")
            row("MISSION_CURRENT.total, no mission", 65535, None if cur is None else cur.total, cur is not None and cur.total == 65535)
            gps = link.latest("GPS_RAW_INT")
            row("GPS fix type, h_acc", "3, 900 mm", f"{gps.fix_type}, {gps.h_acc} mm", (gps.fix_type, gps.h_acc) == (3, 900))
            boot_s = link.latest("GLOBAL_POSITION_INT").time_boot_ms * 1e-3
            row("GPS time_usec", "since boot", f"{gps.time_usec * 1e-6:.1f} s (boot clock {boot_s:.1f} s)", abs(gps.time_usec * 1e-6 - boot_s) < 2.0)
            video = VideoStatus(url="x", frames=30, fps=30, width=1280, height=720)
            checks = {r.name: r for r in run_preflight(link, m, video, min_fix="3d", wait_s=60)}  # as fly waits for a booting vehicle
            row("pre-flight (ekf from ESTIMATOR_STATUS, ready_to_arm, home)", "pass with --min-fix 3d",
                ", ".join(f"{k} {'ok' if r.ok else 'FAIL'}" for k, r in checks.items() if k in ("ekf", "ready_to_arm", "home", "gnss")),
                all(checks[k].ok for k in ("ekf", "ready_to_arm", "home", "gnss")))
            # DO_SET_ROI as ArduPilot takes it: stored with mode 0, the mission refused at start
            raw = [MissionItem(seq=0, frame=3, command=22, p4=math.nan, x=m.items[1].x, y=m.items[1].y, z=2.0), replace_seq(m.items[3], 1)]
            requests: list[str] = []
            link.add_listener(lambda d, _t, msg: requests.append(msg.get_type()) if d == "in" and msg.get_type().startswith("MISSION_REQUEST") else None)
            send_mission(link, raw)
            first_upload = list(dict.fromkeys(requests))
            back = download_mission(link)
            row("DO_SET_ROI(201) mode 3 read back", "param1 0", f"param1 {back[1].p1:g}", back[1].p1 == 0)
            result = link.command_long(300, (0, 0))
            row("MISSION_START with DO_SET_ROI", "DENIED", {0: "ACCEPTED", 2: "DENIED"}.get(result, result), result == 2)
            requests.clear()
            report = upload_and_verify(link, m.items)
            row("requests, first upload of the session", "MISSION_REQUEST, then _INT (both answered)", ", ".join(first_upload),
                first_upload == ["MISSION_REQUEST", "MISSION_REQUEST_INT"])
            row("requests, next upload", "either (both answered)", ", ".join(dict.fromkeys(requests)), bool(requests))
            back = download_mission(link)
            row("frame 3 read back", 6, back[0].frame, back[0].frame == 6)
            row("z 2.5 / yaw 236.57 read back", "float32 / float32 radians", f"{back[3].z!r} / {back[3].p4!r}", report.items == len(m.items))
            row("read-back by fly's PX4 rules", "identical", "identical", True)
            reached: list[tuple[float, int]] = []
            link.add_listener(lambda d, _t, msg: reached.append((time.monotonic(), int(msg.seq))) if d == "in" and msg.get_type() == "MISSION_ITEM_REACHED" else None)
            arm_and_start_mission(link)
            time.sleep(1.5)
            state = vehicle_state(link)
            row("MISSION_START arms and starts", "armed, AUTO.MISSION", f"{'armed' if state.armed else 'disarmed'}, {state.mode_name}",
                state.armed and state.mode_name == "AUTO.MISSION")
            deadline = time.monotonic() + 90
            was_armed = True
            while time.monotonic() < deadline:
                time.sleep(0.5)
                state = vehicle_state(link)
                if was_armed and not state.armed:
                    break
            row("lands and disarms", "disarmed", "disarmed" if not state.armed else "armed", not state.armed)
            counts = collections.Counter(seq for _t, seq in reached)
            hold_seq = 3  # PX4's numbering of the file's hold (seq 4)
            times = [t for t, s in reached if s == hold_seq]
            gaps = [b - a for a, b in zip(times, times[1:])]
            row("MISSION_ITEM_REACHED repeats (the hold)", "~1 Hz for ~10 s", f"{counts[hold_seq]} times, every {sum(gaps) / max(len(gaps), 1):.1f} s",
                counts[hold_seq] > 1)
            row("reached seqs (PX4 numbering)", "hold 3, LAND 4 at descent", sorted(counts), hold_seq in counts and 4 in counts)
    return rows


def replace_seq(item: MissionItem, seq: int) -> MissionItem:
    from dataclasses import replace

    return replace(item, seq=seq)


def main() -> int:
    reason = skip_reason()
    if reason:
        print(f"skipped: {reason}")
        return 0
    rows = run()
    print("\n| row | fly assumes | PX4 1.16 SITL | |\n| --- | --- | --- | --- |")
    for what, model, sitl, ok in rows:
        print(f"| {what} | {model} | {sitl} | {'ok' if ok else 'DIFF'} |")
    print(f"\n{sum(ok for *_x, ok in rows)}/{len(rows)} rows agree")
    return 0


if __name__ == "__main__":
    sys.exit(main())
