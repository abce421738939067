"""`sim vehicle --autopilot px4` against PX4 1.16 SITL (SIH): the same probe on both, side by side.

The probe (tests/px4_probe.py) talks to a vehicle with `fly`'s own client code
and returns what it saw: boot mode and identity, GPS (fix type, h_acc, the
time base, the fix rate), SYS_STATUS health, MISSION_CURRENT with no
mission, the upload's request types, the read-back (frame 3 -> 6, float32
altitude, yaw through float32 radians), DO_SET_ROI refused at start, the
start (MISSION_START arms and starts), then a short flight: take-off to
2.5 m, 2 m/s, a 3 s hold 4 m east facing the pole (DO_SET_ROI_LOCATION),
a fly-through 6 m north, 1 m/s, a 2 s hold, LAND at home. From the
flight's GLOBAL_POSITION_INT track (vehicle clock) it measures the climb
and descent rates, each hold's still time, the legs' top speeds and
acceleration, the speed at the fly-through point, the yaw error to the
pole at the holds, the MISSION_ITEM_REACHED messages (which seqs, how
often repeated, when against the hold), the modes, the landing and the
disarm. :func:`rows` puts two probes side by side with a tolerance each.

The SITL runs in real time (about 75 s in all); the simulator at
``--speedup`` 4 (about 25 s). A saved SITL probe (``--sitl-json``) lets the
simulator be compared again without the firmware.

Run: ``.venv/bin/python benchmarks/sim_px4_conformance.py [--sitl-json out.json] [--reuse]``
(the SITL part needs ../shared/sitl/px4-1.16 and root for unshare).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO / "tests") not in sys.path:
    sys.path.insert(0, str(REPO / "tests"))

from px4_probe import FULL, SHORT, probe_sim, probe_sitl, rows  # noqa: E402

def print_table(table: list[tuple[str, str, str, bool]]) -> None:
    print("\n| item | PX4 1.16 SITL (each run) | sim vehicle --autopilot px4 | agree |\n| --- | --- | --- | --- |")
    for what, a, b, ok in table:
        print(f"| {what} | {a} | {b} | {'yes' if ok else 'NO'} |")
    print(f"\n{sum(ok for *_x, ok in table)}/{len(table)} rows agree")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sitl-json", type=Path, action="append", default=[], help="save the SITL probe here (or read it with --reuse; repeatable: several runs)")
    parser.add_argument("--reuse", action="store_true", help="read the SITL probe from --sitl-json instead of running the SITL")
    parser.add_argument("--speedup", type=float, default=4.0)
    parser.add_argument("--sitl-only", action="store_true")
    parser.add_argument("--short", action="store_true", help="the CI's short flight (one hold) instead of the full one")
    args = parser.parse_args()
    if args.reuse and args.sitl_json:
        sitls = [json.loads(p.read_text()) for p in args.sitl_json]
    else:
        from px4_sitl import skip_reason

        reason = skip_reason()
        if reason:
            print(f"skipped: {reason}")
            return 0
        t0 = time.monotonic()
        sitl = probe_sitl(SHORT if args.short else FULL)
        print(f"SITL probe: {time.monotonic() - t0:.0f} s")
        if args.sitl_json:
            args.sitl_json[0].write_text(json.dumps(sitl, indent=1, default=str))
        sitls = [sitl]
    if args.sitl_only:
        print(json.dumps({k: v for k, v in sitls[0].items() if k != "track"}, indent=1, default=str))
        return 0
    t0 = time.monotonic()
    sim = probe_sim(args.speedup, scenario=SHORT if args.short else FULL)
    print(f"sim probe: {time.monotonic() - t0:.0f} s")
    print_table(rows(sitls, sim))
    return 0


if __name__ == "__main__":
    sys.exit(main())
