"""Issue 20: a plan flown other than planned either calibrates within 1.5x of the run flown as planned, or refuses
naming the cause. A fast subset of benchmarks/bench_perturbation.py, on runs written by the INDEPENDENT contract
writer (tests/contract_writer.py), scored against the truth over the visible ground 3-30 m (sim/compare.py).

The camera is the wide 1080p camera of the issue (f 900 px, k1 -0.28, k2 0.07, 3.5 m pole, tilt 25) rendered at
a third of its size (640x360, f 300: the same field of view), on a thinned paper's grid (30 holds 4-8 m out).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from contract_writer import ORIGIN, MarkerLook, RunSpec, grid_waypoints, make_flight, mission_plan, pole_camera, write_run
from dronecal_field.pipeline.run import CalibrateOptions, calibrate_run
from dronecal_field.sim.compare import compare_cameras

TRUTH = pole_camera(width=640, height=360, f_px=300.0, position_enu=(0.0, 0.0, 3.5), tilt_deg=25.0,
                    distortion=(-0.28, 0.07, 0.0, 0.0, 0.0), principal_offset_px=(4.0, -3.0))
LOOK = MarkerLook(marker_id=7, size_m=0.4)
PLANNED_HOLD_S = 8.0  # the mission.plan attached says 8 s holds; they were flown 3 s
WAYPOINTS = grid_waypoints(east_m=(-3.0, -1.5, 0.0, 1.5, 3.0), north_m=(4.0, 6.0, 8.0), up_m=(0.6, 1.6))


def _run(tmp: Path, name: str, transit: bool = False, plan: bool = True, false_fix_m: float = 0.0, **spec) -> Path:
    flight = make_flight(TRUTH, WAYPOINTS, hold_s=3.0, move_s=2.0, seed=5, transit_from_enu=(14.0, 2.0) if transit else None)
    if false_fix_m:  # the receiver holds a false RTK fix (still "rtk_fixed") over both transits
        spec["fix_bias"] = [(int(flight.t_ns[0]), flight.holds[0][0], (false_fix_m, 0.0, 0.0)),
                            (flight.holds[-1][1], int(flight.t_ns[-1]) + 1, (false_fix_m, 0.0, 0.0))]
    rs = RunSpec(fps=8.0, gnss_hz=10.0, latency_s=0.25, declared_latency="unknown", site_origin=ORIGIN, seed=11,
                 attachments={"mission.plan": mission_plan(flight, 1.5, TRUTH, hold_s=PLANNED_HOLD_S)} if plan else {}, **spec)
    path = tmp / f"{name}.mcap"
    write_run(path, TRUTH, flight, LOOK, rs)
    return path


def _ground(report) -> float:
    return compare_cameras(TRUTH, report.camera, ground_step_m=0.5).ground.rms_px


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("perturbation")
    return {"base": _run(tmp, "base"), "transit": _run(tmp, "transit", transit=True, plan=False, false_fix_m=0.15)}


@pytest.fixture(scope="module")
def base(runs):
    return calibrate_run(runs["base"], CalibrateOptions(trials=0))


def test_transit_legs_that_disagree_with_the_holds_are_left_out_in_one_line(runs, base):
    """No plan attached: the take-off 14 m to the side and the way home are two 3 m/s legs in the GNSS track, flown
    on a false RTK fix 15 cm east. Left out, the camera is the holds' again.

    The same transit on a true fix is kept (measured: pooled under k1 it pulled the holds to 0.65 px against 0.18 px
    alone; under k1k2 they fit together to 0.25 px, and the ground 3-30 m error fell from 25.5 to 11.5 px): the check
    leaves out only a set that no model fits with the rest."""
    report = calibrate_run(runs["transit"], CalibrateOptions(trials=0))
    g0, g = _ground(base), _ground(report)
    print(f"ground 3-30 m: base {g0:.2f} px, with transit legs {g:.2f} px; {report.result.model.name}, rms {report.result.rms_px:.2f}")
    assert g <= 1.1 * g0
    line = report.warnings[0]
    assert line.startswith("2 legs from the GNSS track (") and "disagree with the 30 holds by" in line
    assert line.endswith("left out; `--leg-source track` keeps them")
    assert report.agreement.left_out == {0, 1} and not report.leg_points


def test_the_leg_source_named_keeps_the_legs_and_says_they_disagree(runs, base):
    kept = calibrate_run(runs["transit"], CalibrateOptions(trials=0, leg_source="track"))
    print(f"ground 3-30 m: base {_ground(base):.2f} px, transit legs kept {_ground(kept):.2f} px")
    assert len(kept.leg_points) >= 20 and kept.warnings[0].endswith("kept, as `--leg-source track` asks")
    assert _ground(kept) > _ground(base)


def test_holds_shorter_than_planned_are_named_in_the_first_printed_line(base, tmp_path):
    """The base run's mission.plan says 8 s holds, flown 3 s: it calibrates, and says so first."""
    from dronecal_field.commands.calibrate import _summary_lines

    assert base.notices == ["the holds lasted 3.0 s where the plan said 8.0 s: the calibration used what that flight gave"]
    first = _summary_lines(base, "base.mcap", tmp_path)[0]
    assert first.startswith("calibrated base.mcap: 30 of 30 waypoints")
    assert first.endswith("; flown other than planned: the holds lasted 3.0 s where the plan said 8.0 s")


def test_a_sped_up_simulators_holds_and_legs_are_measured_on_the_vehicle_clock():
    """The demo's simulator runs 3x: its 1 s leg-end holds last 0.33 s and its 0.53 m/s legs 1.6 m/s of run time.
    calibrate said 'the holds lasted 0.3 s where the plan said 1.0 s' and 'legs flown at 1.5 m/s' on the demo's own
    flight; the recorder's events carry the vehicle clock rate, and the comparison is made on that clock."""
    from types import SimpleNamespace

    import numpy as np

    from dronecal_field.pipeline.asflown import flight_against_plan
    from dronecal_field.pipeline.hover import HoverWindow
    from dronecal_field.pipeline.legs import Leg

    t = np.arange(0, 10_000_000_000, 100_000_000, dtype=np.int64)
    track = SimpleNamespace(t_ns=t, velocity_enu_mps=np.tile([1.59, 0.0, 0.0], (len(t), 1)),  # 0.53 m/s at 3x
                            marker_enu_m=np.outer(t * 1e-9, [1.59, 0.0, 0.0]))
    windows = [HoverWindow(index=k, start_ns=0, end_ns=333_333_333, source="event", seq=4 + k) for k in range(3)]  # 1 s at 3x
    legs = [Leg(index=0, start_ns=0, end_ns=9_000_000_000, source="event")]

    def read(rate):
        return SimpleNamespace(track=track, planned_speed_mps=0.53, holds={4: 1.0, 5: 1.0, 6: 1.0}, vehicle_clock_rate=rate,
                               hold_sites_enu_m={})

    assert flight_against_plan(read(3.0), windows, legs) == []
    causes = flight_against_plan(read(1.0), windows, legs)  # the same numbers from a real vehicle: both said
    assert any("legs were flown at 1.6 m/s" in c for c in causes) and any("holds lasted 0.3 s" in c for c in causes)


def test_a_run_that_missed_a_quarter_of_the_plan_says_so_first(tmp_path):
    """The run starts a quarter into the flight (the first holds never reached): the plan's holds it lacks are named
    first, as a slower or shorter flight is; the camera is still written."""
    from dronecal_field.pipeline.asflown import unflown_holds
    from dronecal_field.pipeline.hover import HoverWindow

    report = calibrate_run(_run(tmp_path, "late", keep_span=(0.25, 1.0)), CalibrateOptions(trials=0))
    missing = [n for n in report.notices if "missing from the run" in n]
    print(missing, f"ground 3-30 m {_ground(report):.2f} px")
    assert len(missing) == 1 and missing[0].startswith("7 of the plan's 30 holds are missing from the run (seq 4-10)")
    # the rule on its own: at least 2 and a tenth of the holds; windows without a seq (from the track) say nothing
    holds = {s: 3.0 for s in range(4, 24)}
    wins = [HoverWindow(index=k, start_ns=0, end_ns=1, source="event", seq=s) for k, s in enumerate(range(6, 24))]
    assert unflown_holds(holds, wins) == "2 of the plan's 20 holds are missing from the run (seq 4-5)"
    assert unflown_holds(holds, [HoverWindow(0, 0, 1, "event", 4), *wins]) is None
    assert unflown_holds(holds, [HoverWindow(0, 0, 1, "track", None)]) is None
    assert unflown_holds(holds, wins[:5] + wins[7:]) == "4 of the plan's 20 holds are missing from the run (seq 4-5, 11-12)"
