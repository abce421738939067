"""The simulated copter keeps ArduCopter's time: the recorded 4.7 SITL grid flight, and the plan's flight-time model.

The recording (shared/replays/arducopter-sitl, calib-grid-rtk): 70 waypoints
1 m apart with 3 s holds, one MISSION_ITEM_REACHED every 6.9-7.2 s, 479.3 s
from seq 4 to seq 73; the 5 m first leg peaks at 1.36 m/s and 1 m legs at
0.57 m/s. A simulator that flies faster than the firmware makes every flight
time it reports too short (a 12.3 min plan flew in 10.6 min before this).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from dronecal_field.geodesy import EnuOrigin, enu_to_geodetic, geodetic_to_enu
from dronecal_field.mavlink import ardupilot as ap
from dronecal_field.mavlink import missionfile as mf
from dronecal_field.plan.route import FlightModel, path_time_s
from dronecal_field.sim.vehicle_flight import CopterModel, CopterParams

from conftest import REPLAYS, needs_replays


def _fly(items: list[mf.MissionItem], dt: float = 0.01) -> tuple[dict[int, float], dict[int, float], float]:
    """Fly the mission in the simulator's copter model: (reached time by seq, peak horizontal speed by seq, disarm time)."""
    home = items[0]
    h0 = float(home.z)
    origin = EnuOrigin(home.x * 1e-7, home.y * 1e-7, h0)

    def to_enu(item: mf.MissionItem) -> np.ndarray | None:
        if item.frame not in mf.GLOBAL_FRAMES or (item.x == 0 and item.y == 0):
            return None
        e, n, _ = geodetic_to_enu(item.x * 1e-7, item.y * 1e-7, h0, origin)[0]
        up = float(item.z) - h0 if item.frame in (mf.FRAME_GLOBAL, mf.FRAME_GLOBAL_INT) else float(item.z)
        return np.array([e, n, up])

    m = CopterModel(to_enu, CopterParams(hover_drift_m=0.0), np.random.default_rng(0))
    m.set_mission(items)
    m.ready = True
    assert m.set_mode(ap.MODE_GUIDED) == 0 and m.arm() == 0 and m.mission_start() == 0
    t, reached, peak = 0.0, {}, {}
    while t < 3600.0 and (m.armed or t < 1.0):
        m.step(dt)
        t += dt
        for s in m.reached:
            reached.setdefault(s, t)
        m.reached.clear()
        peak[m.current_seq] = max(peak.get(m.current_seq, 0.0), float(np.hypot(*m.vel[:2])))
    return reached, peak, t


@needs_replays
def test_sim_copter_flies_the_recorded_grid_in_arducopters_time():
    items = mf.read_mission(REPLAYS / "calib-grid.waypoints").items
    checks = json.loads((REPLAYS / "calib-grid-rtk.checks.json").read_text())
    recorded = {int(r[0]): float(r[1]) for r in checks["reached"]}
    reached, peak, _ = _fly(items)
    sim = reached[73] - reached[4]
    assert recorded[73] - recorded[4] == pytest.approx(479.3, abs=0.1)
    assert abs(sim - 479.3) / 479.3 < 0.02  # measured: 482.2 s (was 345 s: 28 % fast)
    assert 6.9 <= sim / 69 <= 7.2  # README: one seq every 6.9-7.2 s
    assert peak[10] == pytest.approx(0.57, abs=0.05)  # a 1 m grid leg
    assert peak[4] == pytest.approx(1.36, abs=0.12)  # the 5 m first leg under DO_CHANGE_SPEED 1.5


def test_sim_copter_and_plan_model_agree_on_fly_through_legs():
    """A hold, a run of pass-through points at 0.4 m/s, a hold: the plan's path_time_s and the simulated copter within 3 %."""
    fm = FlightModel()
    pts = np.array([[0.0, 0.0, 2.0], [0.0, 1.0, 2.0], [0.3, 2.0, 2.1], [0.6, 3.0, 2.2], [0.9, 4.0, 2.3], [1.2, 5.0, 2.4], [1.2, 8.0, 2.4]])
    lat0, lon0, h0 = -35.363261, 149.165230, 584.0
    ll = enu_to_geodetic(np.c_[pts[:, :2], np.zeros(len(pts))], EnuOrigin(lat0, lon0, h0))
    items = [mf.MissionItem(seq=0, frame=mf.FRAME_GLOBAL, command=mf.CMD_NAV_WAYPOINT, x=int(round(lat0 * 1e7)), y=int(round(lon0 * 1e7)), z=h0)]
    items.append(mf.MissionItem(seq=1, frame=mf.FRAME_GLOBAL_RELATIVE_ALT, command=mf.CMD_NAV_TAKEOFF, x=0, y=0, z=2.0))

    def wp(k: int, hold: float) -> mf.MissionItem:
        return mf.MissionItem(seq=len(items), frame=mf.FRAME_GLOBAL_RELATIVE_ALT, command=mf.CMD_NAV_WAYPOINT, p1=hold,
                              x=int(round(ll[k][0] * 1e7)), y=int(round(ll[k][1] * 1e7)), z=float(pts[k, 2]))

    items.append(mf.MissionItem(seq=2, frame=mf.FRAME_MISSION, command=mf.CMD_DO_CHANGE_SPEED, p1=1.0, p2=1.5, p3=-1.0))
    items.append(wp(1, 3.0))
    first = len(items) - 1
    items.append(mf.MissionItem(seq=len(items), frame=mf.FRAME_MISSION, command=mf.CMD_DO_CHANGE_SPEED, p1=1.0, p2=0.4, p3=-1.0))
    for k in range(2, 6):
        items.append(wp(k, 0.0))
    items.append(wp(6, 3.0))
    last = len(items) - 1
    items.append(mf.MissionItem(seq=len(items), frame=mf.FRAME_GLOBAL_RELATIVE_ALT, command=mf.CMD_NAV_LAND, x=0, y=0, z=0.0))
    reached, _, _ = _fly(items)
    sim = reached[last] - reached[first] - 3.0
    speeds = np.full(5, 0.4)  # ArduCopter runs DO_CHANGE_SPEED 0.4 when the NAV item before it starts: from there on
    model = path_time_s(pts[1:], np.array([True, False, False, False, False, True]), speeds, fm)
    assert abs(sim - model) / model < 0.03, (sim, model)
