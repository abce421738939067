"""The live check of a several-camera run (``fly --video NAME=URL`` repeated): one live calibration per camera.

Each camera gets its own :class:`~dronecal_field.live.worker.LiveCalibration`
(its frame ring, its detector, its running calibration, its verdict) fed by
its own recorder feed; the GNSS fixes, attitudes and hover/leg events are
shared, so each record is handed to every camera.

CPU, so that four streams fit a 2-core field laptop beside the recorder:

- no frame cache (the zone pass that detects every ring frame around holds
  and legs for ``calibrate`` after landing): ``calibrate`` reads the file;
- fewer frames a hold and a leg per camera (``LiveOptions.frames_per_hold``
  and ``frames_per_leg`` divided by the number of cameras, at least 4 and 6);
- a frame ring of ``RING_BYTES`` shared out between the cameras;
- one waypoint job at a time among the cameras (a shared lock), and after
  each a rest that keeps the jobs within ``SITE_CPU_SHARE`` of one core: the
  four workers of bench_site_fly --live, each on its own, dropped 35 % of the
  frames at load 40 (a niced worker preempted while holding the interpreter
  lock stalls the recorder's threads); a job that waits for its turn until
  its frames left the ring is checked after landing from the run file
  (the latest ``AFTER_LANDING_MAX`` per camera: four cameras with ~80 each
  kept fly concluding for over 6 minutes at load 30; the rest are
  ``calibrate``'s, said in the verdict);
- every worker at nice +10 as the single camera's, below the recorder.

A camera's verdict names re-fly waypoints only when the plan says which
waypoints it must see: a ``plan --site`` plan.json (``cameras``: each
camera's guess, ROI and ENU origin at its pole's foot; ``grid``: each point
with the cameras that see it, ``seen_by``) gives each camera its own plan
(:func:`camera_live_plan`) and its own ENU origin. Otherwise a camera that
does not see a waypoint meant for its neighbour is not "missed": its
verdict counts the waypoints where the marker was seen.
The Foxglove view (``--live-port``) shows the first camera.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from dronecal_field.live.progress import LiveOptions, constrained
from dronecal_field.live.worker import RING_BYTES, RING_FRAMES, LiveCalibration, LiveResult

MIN_RING_BYTES = 24 << 20  # per camera: a few seconds of 4K JPEG, more than a hold's frames
SITE_CPU_SHARE = 0.35  # of one core, the live jobs of every camera together
AFTER_LANDING_MAX = 8  # waypoints a camera checks after landing (the latest); the rest are calibrate's


@dataclass(frozen=True)
class SiteCamera:
    """One camera of the live check: its name, image size and its own plan (:func:`camera_live_plan`), if any."""

    name: str
    width: int
    height: int
    plan: dict | None = None


def camera_live_plan(plan_json: dict | None, name: str) -> dict | None:
    """Camera ``name``'s own plan out of a site plan.json: its entry in ``cameras`` (camera_guess, roi, site_frame,
    enu_origin) with the ``grid`` points it sees (``seen_by``, else ``camera``) and the shared ``marker``; None
    when plan.json does not name the camera."""
    from dronecal_field.recording.cameras import camera_plan

    entry = camera_plan(plan_json, name)
    if entry is None:
        return None
    sub = dict(entry)
    grid = plan_json.get("grid") if isinstance(plan_json, dict) else None
    if isinstance(grid, list) and "grid" not in sub:
        sub["grid"] = [g for g in grid if isinstance(g, dict)
                       and (name in (g.get("seen_by") or {}) or (not g.get("seen_by") and g.get("camera") == name))]
    if isinstance(plan_json, dict) and "marker" in plan_json and "marker" not in sub:
        sub["marker"] = plan_json["marker"]
    return sub


def site_options(min_fix: str, n_cameras: int) -> LiveOptions:
    """The live work per camera of ``n_cameras`` (see the module docstring)."""
    base = LiveOptions(min_fix=min_fix)
    n = max(1, int(n_cameras))
    return replace(base, frame_cache=False, frames_per_hold=max(4, base.frames_per_hold // n),
                   frames_per_leg=max(6, base.frames_per_leg // n))


class LiveSite:
    """The recorder's observer of records (``on_record``: to every camera) and a frame observer per camera (:meth:`camera`)."""

    def __init__(self, cameras: dict[str, LiveCalibration], planned: dict[str, bool], view: Any = None) -> None:
        self.cameras = cameras
        self.planned = planned  # the camera's plan names its waypoints: its verdict may ask for a re-fly
        self.view = view

    def camera(self, name: str) -> LiveCalibration:
        return self.cameras[name]

    def on_frame(self, frame: Any) -> None:  # frames go to each camera's own observer (CameraFeed), never here
        pass

    def on_record(self, record: Any) -> None:
        for live in self.cameras.values():
            live.on_record(record)

    def start(self) -> "LiveSite":
        for live in self.cameras.values():
            live.start()
        return self

    def status_text(self, name: str) -> str:
        return self.cameras[name].status_text()

    def new_summaries(self) -> list[str]:
        """Each camera's new summary lines, prefixed with its name."""
        return [f"[{name}] {line}" for name, live in self.cameras.items() for line in live.new_summaries()]

    def finish(self, timeout_s: float = 30.0, run_path: Any = None) -> dict[str, LiveResult]:
        """Every camera's result; waypoints its worker had not reached are checked from the ring, else from its own
        topic of the closed run file (``run_path``)."""
        return {name: live.finish(timeout_s, run_path=run_path) for name, live in self.cameras.items()}


def start_live_site(mission: Any, marker: Any, cameras: list[SiteCamera], origin: Any, min_fix: str,
                    camera_latency_s: float | None, live_host: str, live_port: int) -> LiveSite:
    """A live calibration per camera, started; with ``live_port`` > 0 the Foxglove view of the first camera."""
    from dronecal_field.live.session import open_view

    from dronecal_field.runfile.records import site_origin_from_plan_json

    view = open_view(live_host, live_port)
    options = site_options(min_fix, len(cameras))
    ring_bytes = max(MIN_RING_BYTES, RING_BYTES // max(1, len(cameras)))
    job_lock = threading.Lock()
    # a camera's guess and ROI are in the ENU frame at its own pole's foot: its live frame is that one
    origins = {cam.name: (site_origin_from_plan_json(cam.plan, f"plan.json camera {cam.name}") if cam.plan else None) or origin
               for cam in cameras}
    lives = {
        cam.name: LiveCalibration(mission, marker, cam.width, cam.height, plan=cam.plan, origin=origins[cam.name], options=options,
                                  view=view if i == 0 else None, camera_latency_s=camera_latency_s,
                                  ring_frames=RING_FRAMES, ring_bytes=ring_bytes, camera=cam.name, job_lock=job_lock,
                                  cpu_share=SITE_CPU_SHARE, after_landing_max=AFTER_LANDING_MAX)
        for i, cam in enumerate(cameras)
    }
    planned = {cam.name: bool(cam.plan and isinstance(cam.plan.get("grid"), list) and cam.plan["grid"]) for cam in cameras}
    return LiveSite(lives, planned, view).start()


def camera_verdict(name: str, result: LiveResult, planned: bool) -> tuple[str, tuple[int, ...]]:
    """(the camera's verdict line, its re-fly seqs): the plan's verdict when it names the camera's waypoints, else a count."""
    if planned:
        return f"camera {name}: {result.verdict.text}", tuple(result.verdict.refly_seqs)
    checked = {o.seq for o in result.outcomes}
    seen = sorted({o.seq for o in result.outcomes if o.good})
    text = f"camera {name}: marker seen at {len(seen)} of {len(checked)} waypoints checked"
    if not seen and checked:
        text += " (NEVER SEEN: check the camera's stream, position and azimuth)"
    est = result.estimate
    if constrained(est):
        text += f"; predicted ground error {est.ground_error_15m_cm:.1f} cm at 15 m ({est.n_points} points)"
    elif est is None:
        text += "; no live calibration yet (calibrate needs 6 points)"
    if result.checked_after_landing:
        text += f"; {len(result.checked_after_landing)} checked after landing from the run file (the live worker was behind)"
    if result.unchecked:
        text += f"; {len(result.unchecked)} waypoints left to calibrate (not checked live)"
    return text, ()


def conclude_site(site: LiveSite, run_path: Path, mission: Any, timeout_s: float = 30.0) -> tuple[dict[str, LiveResult], list[str]]:
    """Finish every camera's live work; write ``<run>.live.json`` (``cameras``: one entry per camera) and, when a
    camera's plan names waypoints it missed, one ``refly.plan`` with them all. (results, lines to print)."""
    from dronecal_field.live.refly import write_refly_plan
    from dronecal_field.live.session import refly_path

    results = site.finish(timeout_s, run_path=run_path if run_path.is_file() else None)
    lines = site.new_summaries()
    doc: dict[str, Any] = {"run": run_path.name, "cameras": {}}
    refly: set[int] = set()
    expected: set[int] = set()
    for name, result in results.items():
        text, seqs = camera_verdict(name, result, site.planned[name])
        lines.append(f"verdict {text}")
        refly.update(seqs)
        if site.planned[name]:
            expected.update(result.expected)
        entry = result.to_dict()
        entry["verdict_line"] = text
        doc["cameras"][name] = entry
    if refly:
        path = refly_path(run_path)
        mapping = write_refly_plan(path, mission, sorted(refly), sorted(expected))
        doc["refly"] = {"file": path.name, "new_seq_to_flown_seq": {str(k): v for k, v in mapping.items()}}
        lines.append(f"refly: {path} holds the {len(mapping)} waypoints some camera missed (upload it to re-fly them; fly commands nothing by itself)")
    live_json = run_path.with_name(run_path.stem + ".live.json")
    live_json.write_text(json.dumps(doc, indent=2, default=float), encoding="utf-8")
    if site.view is not None:
        site.view.close()
    return results, lines
