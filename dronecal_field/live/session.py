"""What ``fly`` does with the live pipeline: start it beside the recorder, conclude it after landing.

The I/O shell of the live package: it opens the Foxglove server, writes
``live.json`` and ``refly.plan`` beside the run and, with ``fly
--calibrate``, runs the normal ``calibrate`` on the closed run.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

from dronecal_field.live.progress import LiveOptions
from dronecal_field.live.worker import LiveCalibration, LiveResult


def start_live(
    mission: Any, marker: Any, width: int, height: int, plan_json: dict | None, origin: Any, min_fix: str,
    camera_latency_s: float | None, live_host: str, live_port: int,
) -> LiveCalibration:
    """The live calibration, started; with ``live_port`` > 0 its Foxglove server too (:func:`open_view`)."""
    view = open_view(live_host, live_port)
    return LiveCalibration(
        mission, marker, width, height, plan=plan_json, origin=origin, options=LiveOptions(min_fix=min_fix), view=view,
        camera_latency_s=camera_latency_s,
    ).start()


def open_view(live_host: str, live_port: int) -> Any:
    """The Foxglove live view on ``live_port`` (None for 0).

    A port that cannot be bound is an InputError naming the flag: the pilot asked for the view.
    """
    from dronecal_field.errors import InputError

    if not 0 <= int(live_port) <= 65535:
        raise InputError(f"--live-port {live_port}: give a TCP port 1-65535 (8765 is Foxglove's usual one), or 0 for no live view")
    if live_port == 0:
        return None
    from dronecal_field.live.view import LiveView

    try:
        return LiveView(host=live_host, port=int(live_port))
    except Exception as exc:  # noqa: BLE001 - the SDK raises its own error types for a taken port
        raise InputError(f"--live-port {live_port}: cannot serve Foxglove on {live_host}:{live_port} ({exc}); choose a free port or 0 for none") from None


def refly_path(run_path: Path) -> Path:
    """``refly.plan`` beside ``run.mcap``; ``run-2.refly.plan`` beside ``run-2.mcap`` (a later flight keeps the first's)."""
    return run_path.with_name("refly.plan" if run_path.stem == "run" else f"{run_path.stem}.refly.plan")


def conclude(live: LiveCalibration, run_path: Path, mission: Any, timeout_s: float = 30.0) -> tuple[LiveResult, list[str]]:
    """Finish the live work; write ``<run>.live.json`` and, if waypoints were missed, the refly plan. (result, lines to print)."""
    from dronecal_field.live.refly import write_refly_plan

    result = live.finish(timeout_s, run_path=run_path if run_path.is_file() else None)
    lines = [s for s in live.new_summaries()]
    lines.append(f"verdict: {result.verdict.text}")
    doc = result.to_dict()
    doc["run"] = run_path.name
    if result.verdict.refly_seqs:
        path = refly_path(run_path)
        mapping = write_refly_plan(path, mission, result.verdict.refly_seqs, result.expected)
        doc["refly"] = {"file": path.name, "new_seq_to_flown_seq": {str(k): v for k, v in mapping.items()}}
        lines.append(f"refly: {path} holds just those {len(mapping)} waypoints (upload it to re-fly them; fly commands nothing by itself)")
    if result.checked_after_landing:
        lines.append(f"note: {len(result.checked_after_landing)} waypoints were checked after landing, from {run_path.name} "
                     "(the live worker was behind in flight; the verdict includes them)")
    if result.unchecked:
        lines.append(f"note: {len(result.unchecked)} waypoints could not be checked ({', '.join(map(str, result.unchecked[:10]))}"
                     f"{'...' if len(result.unchecked) > 10 else ''}): not in the verdict; calibrate checks them")
    live_json = run_path.with_name(run_path.stem + ".live.json")
    live_json.write_text(json.dumps(doc, indent=2, default=float), encoding="utf-8")
    if live.view is not None:
        live.view.close()
    return result, lines


def calibrate_after_landing(run_path: Path, min_fix: str, closed_mono: float, live: LiveCalibration | None = None) -> list[str]:
    """``calibrate RUN`` as the user would run it (its defaults, its output), into ``<run>-calibration/``; lines to print.

    ``live``: the concluded live pipeline of this flight: its frame cache (every ring frame around the holds
    and legs, detected in flight) stands in for the frames it covered, which are not decoded again.
    """
    import argparse
    import contextlib
    import io

    from dronecal_field.commands import calibrate as calibrate_cmd

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers()
    calibrate_cmd.register(sub)
    args = parser.parse_args(["calibrate", str(run_path), "--min-fix", min_fix])
    frames = live.frame_results() if live is not None else None
    t0, cpu0 = time.monotonic(), time.process_time()
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        if live is None:
            calibrate_cmd.run(args)  # exactly `calibrate RUN` (a several-camera run: every camera of it)
        else:
            calibrate_cmd.run_single(args, run_path, live=frames)
    lines = out.getvalue().rstrip().splitlines()
    ready = f"calibration ready {time.monotonic() - closed_mono:.1f} s after the run file was closed"
    # Where the time went, wall and this process's CPU (a loaded machine stretches the wall, not the CPU).
    parts = [f"calibrate {time.monotonic() - t0:.1f} s, {time.process_time() - cpu0:.1f} s CPU"]
    started = getattr(live, "finish_started", None)
    if started is not None:
        parts.insert(0, f"the live pass's last checks and verdict {t0 - started[0]:.1f} s, {cpu0 - started[1]:.1f} s CPU")
    lines.append(f"{ready} ({'; '.join(parts)})")
    return lines
