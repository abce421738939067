"""The PX4 variant of a written mission: ``mission-px4.plan`` beside ``mission.plan``.

QGroundControl opens either file; the PX4 one says so (``firmwareType`` 12,
MAV_AUTOPILOT_PX4) and holds only items PX4 1.16 stores and flies as
planned (measured on its SITL, dronecal_field/mavlink/px4.py):

* the camera-facing yaw as DO_SET_ROI_LOCATION (195) at the pole: PX4
  stores DO_SET_ROI (201)'s ROI mode as 0 and then refuses MISSION_START;
* a hold waypoint with an acceptance radius (param 2) of 0.3 m: with PX4's
  default 2 m its hold starts 2 m early and its heading freezes there;
* fly-through legs (hold 0), DO_CHANGE_SPEED, TAKEOFF and LAND unchanged:
  PX4 keeps them (yaw as float32 radians, altitude as float32);
* no home item: QGC sends the items from seq 0 to PX4 itself, and
  ``plannedHomePosition`` stays where QGC expects it.

``fly`` makes the same changes on the wire when the vehicle is PX4, so
either file flies; this one is for a pilot uploading with QGroundControl.
"""

from __future__ import annotations

import copy

from dronecal_field.mavlink import px4 as px4_dialect
from dronecal_field.mavlink.missionfile import CMD_DO_SET_ROI, CMD_DO_SET_ROI_LOCATION, CMD_NAV_WAYPOINT

PX4_PLAN_SUFFIX = "-px4"


def px4_plan(plan: dict) -> dict:
    """A copy of the QGC plan dict ``plan`` (ArduPilot's, as plan writes it) for PX4."""
    out = copy.deepcopy(plan)
    mission = out["mission"]
    mission["firmwareType"] = px4_dialect.MAV_AUTOPILOT_PX4
    for item in mission["items"]:
        if item.get("type") == "SimpleItem" and item.get("command") == CMD_DO_SET_ROI:
            params = list(item["params"])
            item["command"] = CMD_DO_SET_ROI_LOCATION
            item["params"] = [0.0, 0.0, 0.0, 0.0, *params[4:7]]
        elif item.get("type") == "SimpleItem" and item.get("command") == CMD_NAV_WAYPOINT and (item["params"][0] or 0) > 0 and not (item["params"][1] or 0) > 0:
            item["params"] = [item["params"][0], px4_dialect.HOLD_ACCEPTANCE_M, *item["params"][2:]]
    return out


def px4_plan_name(name: str) -> str:
    """``mission`` -> ``mission-px4``, ``mission-2`` -> ``mission-2-px4``."""
    return f"{name}{PX4_PLAN_SUFFIX}"
