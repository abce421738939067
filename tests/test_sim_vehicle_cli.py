"""``dronecal-field sim vehicle`` as a process: listen + out links, speed-up, clean stop."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink.link import mavutil_module, open_link

REPO = Path(__file__).resolve().parents[1]


def test_sim_vehicle_command_listens_sends_out_and_stops():
    out_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # plays the simulated camera
    out_sock.bind(("127.0.0.1", 0))
    out_sock.settimeout(5.0)
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "dronecal_field", "sim", "vehicle", "--listen", "udp:127.0.0.1:0", "--out", f"udp:127.0.0.1:{out_sock.getsockname()[1]}",
         "--home", "-35.363261,149.165230,584", "--speedup", "10", "--boot-s", "2", "--duration", "3",
         "--param", "MAV2_EXTRA1=10"],  # the --out link (link 2) streams ATTITUDE unasked, as a defaults file would set it
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )
    try:
        banner = proc.stdout.readline()
        listen = banner.split(": ", 1)[1].split(",")[0].strip()
        link = open_link(listen)
        try:
            hb = link.wait_heartbeat(5)
            # the listen link (link 1, no MAV1_* set) streams nothing until asked, as ArduPilot 4.7
            assert link.wait_message({"GLOBAL_POSITION_INT", "ATTITUDE"}, timeout_s=1.0) is None
            assert link.command_long(ap.CMD_SET_MESSAGE_INTERVAL, (link.dialect.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, 1e5)) == ap.MAV_RESULT_ACCEPTED
            assert link.set_mode("GUIDED") == ap.MAV_RESULT_ACCEPTED
            gpi = link.wait_message({"GLOBAL_POSITION_INT"}, lambda m: m.lat != 0, timeout_s=5)
        finally:
            link.close()
        mav = mavutil_module().mavlink.MAVLink(None)
        seen = set()
        while not {"HEARTBEAT", "ATTITUDE"} <= seen:
            for msg in mav.parse_buffer(out_sock.recvfrom(65535)[0]) or []:
                seen.add(msg.get_type())
        _out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
        out_sock.close()
    assert banner.startswith("sim vehicle: udp:127.0.0.1:") and "out udp:127.0.0.1:" in banner
    assert (hb.autopilot, hb.type) == (ap.MAV_AUTOPILOT_ARDUPILOTMEGA, ap.MAV_TYPE_QUADROTOR)
    assert gpi.lat == round(-35.363261 * 1e7) and abs(gpi.lon - round(149.165230 * 1e7)) <= 2
    assert {"HEARTBEAT", "ATTITUDE"} <= seen
    assert proc.returncode == 0 and "stopped at vehicle time" in err
    stopped_at_s = float(err.split("vehicle time ")[1].split(" s")[0])
    assert stopped_at_s > 6.0  # 3 wall seconds at 10x, less start-up and any slow-down on a busy machine


def test_sim_vehicle_refuses_the_old_stream_parameter_names_in_one_line():
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(
        [sys.executable, "-m", "dronecal_field", "sim", "vehicle", "--listen", "udp:127.0.0.1:0", "--home", "-35.363261,149.165230,584",
         "--duration-s", "1", "--param", "SR1_POSITION=10"],
        capture_output=True, text=True, env=env, timeout=60,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "SR1_POSITION" in lines[0] and "MAVn_" in lines[0] and "Traceback" not in proc.stderr
