"""The mission of just the waypoints to fly again, as a ready-to-upload QGroundControl plan.

The flown mission is cut, not re-planned: its opening items (take-off, speed,
DO_SET_ROI at the camera), the chosen measurement waypoints in their flown
order with the DO items between them, and its closing items (the waypoint
above the take-off point, land or RTL). Each kept item is copied as it was
uploaded, so a re-flown waypoint is the same point with the same hold; only
the seqs are renumbered. ``fly`` never uploads it by itself: re-flying is the
pilot's decision.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from dronecal_field.mavlink.missionfile import CMD_NAV_WAYPOINT, Mission, to_qgc_plan


def refly_mission(mission: Mission, seqs: list[int] | tuple[int, ...], measurement_seqs: list[int] | tuple[int, ...]) -> tuple[Mission, dict[int, int]]:
    """(the cut mission, {new seq: flown seq}) keeping of ``measurement_seqs`` only ``seqs``.

    Parameters
    ----------
    mission : the flown mission (item 0 home).
    seqs : flown mission seqs to fly again.
    measurement_seqs : the flown mission's measurement waypoints (``progress.expected_seqs``); the
        NAV_WAYPOINTs before the first and after the last of them are the opening and closing items.
    """
    wanted = set(int(s) for s in seqs)
    measure = set(int(s) for s in measurement_seqs) | wanted
    unknown = wanted - {item.seq for item in mission.items if item.command == CMD_NAV_WAYPOINT}
    if unknown:
        raise ValueError(f"seqs {sorted(unknown)} are not NAV_WAYPOINTs of the mission")
    first = min(measure)
    last = max(measure)
    kept = [mission.items[0]]
    for item in mission.items[1:]:
        inside = first <= item.seq <= last
        if not inside or item.command != CMD_NAV_WAYPOINT:
            kept.append(item)  # opening, closing, and the DO items in between (speed changes)
        elif item.seq in wanted or item.seq not in measure:
            kept.append(item)  # a chosen point, or a transit waypoint between points
    renumbered = tuple(replace(item, seq=k) for k, item in enumerate(kept))
    mapping = {k: item.seq for k, item in enumerate(kept) if item.seq in wanted}
    return replace(mission, items=renumbered, source_format="plan"), mapping


def write_refly_plan(path: str | Path, mission: Mission, seqs: list[int] | tuple[int, ...], measurement_seqs: list[int] | tuple[int, ...]) -> dict[int, int]:
    """Write the cut mission to ``path`` (QGroundControl .plan); returns {new seq: flown seq}."""
    cut, mapping = refly_mission(mission, seqs, measurement_seqs)
    Path(path).write_text(to_qgc_plan(cut), encoding="utf-8")
    return mapping
