"""`sim vehicle --autopilot px4` on its own: PX4's storage rules, and the short probe flight against the SITL's measured values.

The numbers asserted are those PX4 1.16 SITL gave the same probe
(tests/px4_probe.py; benchmarks/sim_px4_conformance.py keeps the table):
tests/test_px4_sim_conformance.py compares with the firmware itself when it
is installed; this test runs everywhere (about 10 s at 8x).
"""

from __future__ import annotations

import math

import pytest

from dronecal_field.mavlink import missionfile as mf
from dronecal_field.pipeline.gnss_quality import gnss_quality
from dronecal_field.sim.vehicle import SimVehicle, VehicleConfig
from dronecal_field.sim.vehicle_px4 import Px4Vehicle, mission_valid, px4_stored
from px4_probe import HOME, SHORT, probe_sim


@pytest.mark.parametrize("item, frame, p, z", [
    (mf.MissionItem(seq=0, frame=3, command=16, p1=3.0, p2=0.3, p3=1.0, p4=236.57, x=1, y=2, z=3.147), 6, (3.0, 0.30000001192092896, 0.0, 236.56997680664062), 3.1470000743865967),
    (mf.MissionItem(seq=0, frame=3, command=22, p1=5.0, p4=math.nan, x=1, y=2, z=2.0), 6, (0.0, 0.0, 0.0, math.nan), 2.0),
    (mf.MissionItem(seq=0, frame=0, command=21, p2=1.0, p4=-90.0, x=1, y=2, z=584.1), 5, (0.0, 1.0, 0.0, 270.0), 584.0999755859375),
    (mf.MissionItem(seq=0, frame=3, command=195, p1=3.0, x=1, y=2, z=1.0), 6, (0.0, 0.0, 0.0, 0.0), 1.0),
    (mf.MissionItem(seq=0, frame=3, command=201, p1=3.0, x=1, y=2, z=1.0), 6, (0.0, 0.0, 0.0, 0.0), 1.0),
    (mf.MissionItem(seq=0, frame=2, command=178, p1=1.0, p2=1.1, p3=-1.0), 2, (1.0, 1.100000023841858, -1.0, 0.0), 0.0),
])  # fmt: skip
def test_px4_storage_as_the_sitl_reads_it_back(item, frame, p, z):
    """Frame 3 -> 6 (0 -> 5), float32 params and altitude, yaw through float32 radians wrapped to [0, 360), 201's mode lost."""
    back = px4_stored(item)
    assert back.frame == frame and back.z == z and (back.x, back.y) == (item.x, item.y)
    for got, want in zip((back.p1, back.p2, back.p3, back.p4), p):
        assert (math.isnan(got) and math.isnan(want)) or got == pytest.approx(want, abs=1e-4 if want == 270.0 else 0)
    assert mission_valid([back])  # 201 stored with mode 0 still starts (SITL: ACCEPTED 1.5 s after the upload)
    assert px4_stored(mf.MissionItem(seq=0, frame=2, command=16, x=1, y=2, z=1.0)) is None  # a position command needs a global frame


def test_the_config_builds_a_px4_vehicle():
    sim = SimVehicle(VehicleConfig(home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2], autopilot="px4"), listen=["udp:127.0.0.1:0"])
    try:
        assert isinstance(sim, Px4Vehicle) and sim.config.boot_s == 12.0 and sim.config.gnss_sigma_h_m == 0.2 and sim.acc_mm == (900, 1780)
    finally:
        sim.stop()
    rtk = SimVehicle(VehicleConfig(home_lat_deg=HOME[0], home_lon_deg=HOME[1], home_alt_m=HOME[2], autopilot="px4", gnss="rtk"), listen=["udp:127.0.0.1:0"])
    try:
        assert rtk.config.gnss_sigma_h_m == 0.007 and rtk.acc_mm == (14, 10)
    finally:
        rtk.stop()


@pytest.mark.timeout(180)
def test_short_probe_flight_matches_the_sitl_measurements():
    obs = probe_sim(8.0, scenario=SHORT, log=lambda *_a: None)
    # protocol: exactly what PX4 1.16 SITL did
    assert (obs["autopilot"], obs["type"], obs["boot_base_mode"], obs["boot_mode"]) == (12, 2, 29, "AUTO.LOITER")
    assert obs["mission_total_empty"] == 65535 and obs["mission_total"] == 5
    assert (obs["gps_fix_type"], obs["gps_h_acc_mm"], obs["gps_v_acc_mm"]) == (3, 900, 1780)
    assert abs(obs["gps_time_minus_boot_s"]) < 0.3  # time_usec since boot, not UTC
    assert obs["requests_first_upload"] == ["MISSION_REQUEST", "MISSION_REQUEST_INT"] and obs["requests_next_upload"] == ["MISSION_REQUEST_INT"]
    assert (obs["roi201_p1_back"], obs["start_with_roi201"]) == (0.0, 0)  # mode lost, yet started 1.5 s after the upload
    assert (obs["frame3_back"], obs["do_frame_back"], obs["yaw_back"], obs["roi_command_back"]) == (6, 2, 236.56997680664062, 195)
    assert obs["modes"] == ["AUTO.LOITER", "AUTO.MISSION*", "AUTO.MISSION", "AUTO.MISSION*", "AUTO.MISSION"]  # the 201 start, disarmed
    assert obs["reached_seqs"] == [2, 3, 4]  # takeoff and speed overwritten by the ROI (2), the hold (3), LAND at descent (4)
    assert obs["reached_repeat_period_s"] == pytest.approx(1.0, abs=0.1) and obs["reached_counts"]["4"] >= 9
    # flight: within the SITL's runs (still 2.8-4.0 s for 3 s planned, yaw error 0.9-1.6 deg, descent 0.64-0.69 m/s)
    hold = obs["holds"]["A"]
    assert 2.5 <= hold["still_s"] <= 4.5 and hold["yaw_err_deg"] < 3.0
    assert 0.55 <= obs["descent_rate_mps"] <= 0.8 and obs["land_miss_m"] < 0.5
    assert 3.5 <= obs["airborne_after_start_s"] <= 6.0


def test_what_the_reported_gnss_accuracy_means():
    sitl = gnss_quality(["3d"] * 50, 0.9, 1.78, holds_used=16, median_range_m=10.0)
    assert sitl.headline.startswith("GNSS reported 0.9 m / 1.8 m vertical (3D fix, no RTK): from the GNSS alone the camera position is known to ~0.9 m")
    assert "fly with RTK" in sitl.headline and sitl.limits_calibration and sitl.focal_pct == pytest.approx(2.25)
    rtk = gnss_quality(["rtk_fixed"] * 50, 0.014, 0.01, holds_used=16, median_range_m=10.0)
    assert not rtk.limits_calibration and "fly with RTK" not in rtk.headline and rtk.camera_position_m == pytest.approx(0.0035)
    assert gnss_quality(["3d"], None, holds_used=8, median_range_m=10.0).camera_position_m is None
