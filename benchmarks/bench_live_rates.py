"""The live view's topic rates while `fly` records, on a busy machine (issue 19), against docs/live.md's rates.

    .venv/bin/python benchmarks/bench_live_rates.py --plan demo-output/plan --hogs 2

Starts the demo's simulators (`sim vehicle` at ``--speedup``, `sim camera` through the demo's truth camera),
flies ``--plan`` (a demo's plan folder: `make demo` leaves one) with `fly --start --live-port`, while ``--hogs``
CPU-bound processes compete, and reads the live view with a Foxglove WebSocket client offering only the
published subprotocol ``foxglove.websocket.v1`` (tests/test_live_foxglove.py's RFC 6455 client). Per topic: messages,
mean rate over the flight, the longest gap. Documented: /live/status and /live/camera/image twice a second,
/live/gnss with every fix batch (twice a second), /live/camera/calibration once the running calibration exists.
No timing assertion: run by hand, numbers go in the notes.
"""

from __future__ import annotations

import argparse
import json
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

DOCUMENTED_HZ = {"/live/status": 2.0, "/live/camera/image": 2.0, "/live/gnss": 2.0}


def _read_view(port: int, counts: dict, stop: threading.Event) -> None:
    from test_live_foxglove import ws_connect, ws_recv, ws_send_text

    sock = None
    while sock is None and not stop.is_set():
        try:
            sock = ws_connect(port, subprotocol="foxglove.websocket.v1")
        except (OSError, AssertionError):
            time.sleep(0.5)
    if sock is None:
        return
    sock.settimeout(1.0)
    channels: dict[int, str] = {}  # our subscription id -> topic
    seen: set[int] = set()  # channel ids subscribed
    while not stop.is_set():
        try:
            op, payload = ws_recv(sock)
        except socket.timeout:
            continue
        except (OSError, AssertionError):
            return
        if op == 1:
            msg = json.loads(payload)
            if msg.get("op") == "advertise":
                for c in msg["channels"]:
                    if c["id"] in seen:
                        continue
                    seen.add(c["id"])
                    sub = len(channels) + 1
                    channels[sub] = c["topic"]
                    ws_send_text(sock, json.dumps({"op": "subscribe", "subscriptions": [{"id": sub, "channelId": c["id"]}]}))
        elif op == 2 and payload and payload[0] == 0x01:
            sub = struct.unpack_from("<I", payload, 1)[0]
            counts.setdefault(channels.get(sub, "?"), []).append(time.monotonic())
    sock.close()


def main() -> int:
    from dronecal_field.demo import MARKER, _free_port, cli_argv, start_simulators

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--plan", type=Path, required=True, help="a plan folder from `dronecal-field demo` (DIR/plan)")
    parser.add_argument("--hogs", type=int, default=2)
    parser.add_argument("--speedup", type=float, default=3.0)
    parser.add_argument("--out", type=Path, default=Path("/tmp/live-rates"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    truth = args.plan.parent / "truth.yaml"
    home = json.loads((args.plan / "mission.plan").read_text())["mission"]["plannedHomePosition"]
    run = args.out / f"run-{int(time.time())}.mcap"
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.hogs)]
    sims = start_simulators(truth, tuple(home), args.out, args.speedup, 15.0, MARKER)
    port = _free_port(socket.SOCK_STREAM)
    counts: dict[str, list[float]] = {}
    stop = threading.Event()
    reader = threading.Thread(target=_read_view, args=(port, counts, stop), daemon=True)
    try:
        sims.wait_ready()
        reader.start()
        t0 = time.monotonic()
        with (args.out / f"{run.stem}.fly.log").open("w") as log:
            proc = subprocess.run(cli_argv("fly", "--connect", sims.vehicle_url, "--mission", args.plan / "mission.plan", "--video",
                                           sims.video_url, "--out", run, "--start", "--timeout-s", "900", "--live-port", port),
                                  stdout=log, stderr=subprocess.STDOUT, text=True)
        flight_s = time.monotonic() - t0
    finally:
        stop.set()
        sims.stop()
        for h in hogs:
            h.kill()
    load = __import__("os").getloadavg()[0]
    tail = (args.out / f"{run.stem}.fly.log").read_text(errors="replace").strip().splitlines()[-3:]
    print(f"fly exit {proc.returncode}, {flight_s:.0f} s, load {load:.1f}; " + " / ".join(tail)[:300])
    live = json.loads(run.with_name(run.stem + ".live.json").read_text()) if run.with_name(run.stem + ".live.json").is_file() else {}
    print(f"view publish errors: {live.get('view_errors')}")
    print(f"{'topic':28} {'msgs':>6} {'mean Hz':>8} {'documented':>10} {'longest gap s':>13}")
    for topic, times in sorted(counts.items()):
        span = max(times[-1] - times[0], 1e-9)
        gaps = [b - a for a, b in zip(times, times[1:])] or [0.0]
        doc = DOCUMENTED_HZ.get(topic)
        print(f"{topic:28} {len(times):>6} {(len(times) - 1) / span:>8.2f} {('%.1f' % doc) if doc else '-':>10} {max(gaps):>13.2f}")
    (args.out / "rates.json").write_text(json.dumps({t: len(v) for t, v in counts.items()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
