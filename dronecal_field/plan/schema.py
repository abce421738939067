"""JSON schema of the QGroundControl ``.plan`` subset that ``plan`` writes (and ``fly`` may read).

Written from QGC's plan file format (fileType "Plan", version 1, mission
version 2, SimpleItem only, geoFence version 2 with polygons and circles,
rallyPoints version 2). Anything QGC itself requires is required here; the
items are restricted to SimpleItems with 7 numeric params.
"""

from __future__ import annotations

from typing import Any

_LATLON = {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 2}

QGC_PLAN_SCHEMA: dict[str, Any] = {
    "$schema": "https://json-schema.org/draft/2020-12/schema",
    "title": "QGroundControl plan (subset written by dronecal-field plan)",
    "type": "object",
    "required": ["fileType", "version", "groundStation", "mission", "geoFence", "rallyPoints"],
    "properties": {
        "fileType": {"const": "Plan"},
        "version": {"const": 1},
        "groundStation": {"type": "string"},
        "mission": {
            "type": "object",
            "required": ["version", "firmwareType", "vehicleType", "cruiseSpeed", "hoverSpeed", "items", "plannedHomePosition"],
            "properties": {
                "version": {"const": 2},
                "firmwareType": {"const": 3},  # MAV_AUTOPILOT_ARDUPILOTMEGA
                "vehicleType": {"type": "integer"},
                "cruiseSpeed": {"type": "number", "exclusiveMinimum": 0},
                "hoverSpeed": {"type": "number", "exclusiveMinimum": 0},
                "globalPlanAltitudeMode": {"enum": [0, 1, 2, 3, 4]},
                "plannedHomePosition": {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3},
                "items": {
                    "type": "array",
                    "minItems": 1,
                    "items": {
                        "type": "object",
                        "required": ["type", "command", "frame", "params", "autoContinue", "doJumpId"],
                        "properties": {
                            "type": {"const": "SimpleItem"},
                            "command": {"type": "integer", "minimum": 0},
                            "frame": {"enum": [0, 2, 3, 5, 6, 10]},
                            "params": {"type": "array", "items": {"type": ["number", "null"]}, "minItems": 7, "maxItems": 7},
                            "autoContinue": {"type": "boolean"},
                            "doJumpId": {"type": "integer", "minimum": 1},
                            "Altitude": {"type": "number"},
                            "AltitudeMode": {"enum": [0, 1, 2, 3, 4]},
                            "AMSLAltAboveTerrain": {"type": ["number", "null"]},
                        },
                        "additionalProperties": False,
                    },
                },
            },
        },
        "geoFence": {
            "type": "object",
            "required": ["version", "polygons", "circles"],
            "properties": {
                "version": {"const": 2},
                "polygons": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "required": ["inclusion", "polygon", "version"],
                        "properties": {
                            "inclusion": {"type": "boolean"},
                            "version": {"const": 1},
                            "polygon": {"type": "array", "items": _LATLON, "minItems": 3},
                        },
                        "additionalProperties": False,
                    },
                },
                "circles": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "required": ["circle", "inclusion", "version"],
                        "properties": {
                            "inclusion": {"type": "boolean"},
                            "version": {"const": 1},
                            "circle": {
                                "type": "object",
                                "required": ["center", "radius"],
                                "properties": {"center": _LATLON, "radius": {"type": "number", "exclusiveMinimum": 0}},
                                "additionalProperties": False,
                            },
                        },
                        "additionalProperties": False,
                    },
                },
            },
        },
        "rallyPoints": {
            "type": "object",
            "required": ["version", "points"],
            "properties": {"version": {"const": 2}, "points": {"type": "array"}},
        },
    },
}


def validate_plan(plan: dict) -> None:
    """Raise ``InputError`` naming the first violation when ``plan`` is outside the schema."""
    import jsonschema

    from dronecal_field.errors import InputError

    try:
        jsonschema.validate(plan, QGC_PLAN_SCHEMA)
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        raise InputError(f"mission plan is not a QGC plan at {where}: {exc.message}") from None
