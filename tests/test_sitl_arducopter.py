"""Mission upload and read-back against ArduPilot's own firmware (ArduCopter 4.7 SITL).

Every item type `plan` writes (take-off, DO_CHANGE_SPEED, DO_SET_ROI, holds,
fly-through waypoints, CONDITION_YAW, RTL, NAV_LAND; relative and AMSL
altitudes) goes through our mission client (`mavlink.mission.upload_and_verify`)
to the real firmware, which must accept it and read it back exactly as
`missionfile.ardupilot_readback` models it: float for float, not only to the
storage resolution. The plan's geofence is not part of this: `fly` uploads
the mission only.

One SITL for the module (tests/sitl.py: private network namespace, -w, a fresh
working directory); skipped with the reason when the binary is absent.
"""

from __future__ import annotations

import collections
from pathlib import Path

import pytest

from dronecal_field.cli import main
from dronecal_field.mavlink import missionfile as mf
from dronecal_field.mavlink.link import open_link
from dronecal_field.mavlink.mission import download_mission, upload_and_verify
from dronecal_field.mavlink.missionfile import MissionItem, read_mission
from sitl import ArduCopterSitl, needs_sitl
from test_mavlink_support import HOME, ask_telemetry

pytestmark = [needs_sitl, pytest.mark.timeout(240)]

# The demo's camera (dronecal_field/demo.py) at SITL's CMAC site; small, fast plans.
PLAN_CAMERA = [
    f"--lat={HOME[0]}", f"--lon={HOME[1]}", "--ground-alt", str(HOME[2]), "--mount-height", "4", "--azimuth", "30",
    "--tilt", "25", "--image-size", "1280x720", "--focal-px", "950", "--distortion", "medium", "--marker-size", "0.4",
    "--marker-offset", "0.1,0,0.05", "--trials", "20", "--roi-range", "3,10",
]  # fmt: skip


@pytest.fixture(scope="module")
def sitl():
    with ArduCopterSitl.start(HOME, speedup=10) as s:
        yield s


@pytest.fixture(scope="module")
def gcs(sitl):
    with sitl.netns():
        link = open_link(sitl.gcs_url)
    try:
        assert link.wait_heartbeat(30) is not None, f"no HEARTBEAT from SITL: {sitl.log_tail()}"
        ask_telemetry(link)  # 4.7 streams nothing unasked; the upload waits for SYS_STATUS's ready-to-arm
        yield link
    finally:
        link.close()


@pytest.fixture(scope="module")
def plans(tmp_path_factory) -> dict[str, list[Path]]:
    """Missions made by `dronecal-field plan`: mixed holds + fly-through ending in RTL; holds with CONDITION_YAW, AMSL, ending in a landing."""
    out = {}
    for name, extra in {
        "mixed-rtl": ["--sampling", "mixed", "--hover", "2", "--end", "rtl", "--max-flight-time", "3"],
        "yaw-amsl-land": ["--sampling", "hover", "--hover", "1", "--end", "land", "--yaw-mode", "condition-yaw", "--alt-frame", "amsl",
                          "--geoid-separation", "0", "--max-flight-time", "3"],
    }.items():  # fmt: skip
        folder = tmp_path_factory.mktemp("plan") / name
        assert main(["plan", *PLAN_CAMERA, *extra, "--out", str(folder)]) == 0
        out[name] = sorted(f for f in folder.glob("mission*.plan") if not f.name.endswith("-px4.plan"))  # PX4's own variant: test_px4_*
        assert out[name], name
    return out


def _kinds(items: list[MissionItem] | tuple[MissionItem, ...]) -> collections.Counter:
    def kind(item: MissionItem) -> str:
        if item.command == mf.CMD_NAV_WAYPOINT:
            return "hold" if item.p1 > 0 else "fly-through"
        return mf.COMMAND_NAMES.get(item.command, str(item.command))

    return collections.Counter(kind(item) for item in items[1:])


def _upload_and_check_exact(gcs, items) -> list[MissionItem]:
    report = upload_and_verify(gcs, items, ready_timeout_s=120.0)
    back = list(report.readback)
    assert len(back) == len(items)
    for sent, got in zip(items[1:], back[1:]):
        # the model is the firmware: every field, z and params float for float
        assert got == mf.ardupilot_readback(sent), (sent, got)
    return back


def test_every_item_type_plan_writes_uploads_and_reads_back_as_the_model_says(gcs, plans):
    seen = collections.Counter()
    for name, files in plans.items():
        for path in files:
            mission = read_mission(path)
            back = _upload_and_check_exact(gcs, list(mission.items))
            seen.update(_kinds(mission.items))
            # home (seq 0) is the vehicle's own, as recorded
            assert back[0].command == mf.CMD_NAV_WAYPOINT and abs(back[0].x - round(HOME[0] * 1e7)) <= 1
    for kind in ("Takeoff", "ChangeSpeed", "SetROI", "hold", "fly-through", "CondYaw", "RTL", "Land"):
        assert seen[kind] > 0, (kind, seen)


def test_altitudes_come_back_in_float32_centimetres_as_issue_19_saw(gcs):
    lat, lon = round(HOME[0] * 1e7) + 400, round(HOME[1] * 1e7) + 300
    home = MissionItem(seq=0, frame=mf.FRAME_GLOBAL, command=mf.CMD_NAV_WAYPOINT, x=round(HOME[0] * 1e7), y=round(HOME[1] * 1e7), z=HOME[2])
    sent = [
        home,
        MissionItem(seq=1, frame=6, command=mf.CMD_NAV_TAKEOFF, z=1.47),
        MissionItem(seq=2, frame=6, command=mf.CMD_NAV_WAYPOINT, p1=1.5, p4=144.37, x=lat, y=lon, z=3.633),  # hold 1 s, yaw dropped
        MissionItem(seq=3, frame=6, command=mf.CMD_NAV_WAYPOINT, p1=0.0, p2=0.5, x=lat + 100, y=lon, z=2.999),
        MissionItem(seq=4, frame=2, command=mf.CMD_DO_CHANGE_SPEED, p1=1.0, p2=1.3, p3=-1.0),
        MissionItem(seq=5, frame=5, command=mf.CMD_NAV_WAYPOINT, p1=2.0, x=lat, y=lon + 100, z=HOME[2] + 2.345),
        MissionItem(seq=6, frame=6, command=mf.CMD_NAV_LAND, x=lat, y=lon, z=0.0),
    ]
    back = _upload_and_check_exact(gcs, sent)
    assert back[1].z == 1.46999990940094  # issue 19's read-back, now the model's
    assert back[2].z == pytest.approx(3.63, abs=1e-6) and (back[2].p1, back[2].p4) == (1.0, 0.0)
    assert back[3].z == pytest.approx(2.99, abs=1e-6) and back[3].p2 == 0.0
    assert back[4].frame == 0 and back[4].p2 == pytest.approx(1.3, abs=1e-6)
    assert back[5].frame == 0 and back[5].z == pytest.approx(HOME[2] + 2.34, abs=1e-4)
    assert back[6].p4 == 1.0  # NAV_LAND's yaw-direction flag
    # and a second read-back (no upload in between) gives the same items
    assert download_mission(gcs) == back
