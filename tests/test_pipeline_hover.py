"""Hover windows from the GNSS track, from MISSION_ITEM_REACHED and from event intervals."""

from __future__ import annotations

import numpy as np
import pytest

from contract_writer import grid_waypoints, make_flight, pole_camera
from dronecal_field.pipeline.hover import (
    HoverWindow,
    windows_from_intervals,
    windows_from_reached,
    windows_from_track,
    track_speed,
)


@pytest.fixture(scope="module")
def flight():
    return make_flight(pole_camera(), grid_waypoints(), seed=2)


def _fixes(flight, hz=5.0, sigma=0.008, seed=0, drop=None):
    t = np.arange(flight.t_ns[0], flight.t_ns[-1], int(1e9 / hz))
    if drop is not None:
        t = t[(t < drop[0]) | (t >= drop[1])]
    pos, _ = flight.at(t)
    return t, pos + np.random.default_rng(seed).normal(0, sigma, pos.shape)


def _match(windows, holds):
    """For each true hold, the window overlapping it most: (start error s, end error s)."""
    out = []
    for a, b, _ in holds:
        overlaps = [min(b, w.end_ns) - max(a, w.start_ns) for w in windows]
        w = windows[int(np.argmax(overlaps))]
        out.append(((w.start_ns - a) * 1e-9, (w.end_ns - b) * 1e-9))
    return np.array(out)


def test_speed_of_a_still_noisy_track_is_small_and_a_moving_one_exact():
    t = np.arange(0, 10_000_000_000, 200_000_000)
    still = np.random.default_rng(0).normal(0, 0.01, (len(t), 3))
    assert np.nanmax(track_speed(t, still)) < 0.06
    moving = np.c_[0.5 * t * 1e-9, np.zeros(len(t)), np.zeros(len(t))]
    assert np.allclose(track_speed(t, moving)[2:-2], 0.5)


def test_track_windows_match_the_true_holds(flight):
    t, pos = _fixes(flight)
    windows = windows_from_track(t, pos)
    assert all(w.source == "gnss_track" for w in windows)
    err = _match(windows, flight.holds)
    # Every hold found, each within half a second at both ends (the speed baseline is 1 s).
    assert len(windows) == len(flight.holds) + 1  # plus the wait on the ground before take-off
    assert np.abs(err).max() < 0.5, err


def test_a_gnss_dropout_inside_a_hold_splits_or_shortens_it_but_never_bridges(flight):
    a, b, _ = flight.holds[4]
    gap = (a + 1_000_000_000, a + 2_600_000_000)
    t, pos = _fixes(flight, drop=gap)
    windows = windows_from_track(t, pos)
    for w in windows:
        assert not (w.start_ns < gap[0] and w.end_ns > gap[1])
    # The rest of the holds are still found.
    assert len(windows) >= len(flight.holds) - 1


def test_reached_gives_windows_ending_at_the_message_and_skips_do_items(flight):
    t, pos = _fixes(flight)
    reached = [(b, seq) for a, b, seq in flight.holds]
    # DO items (seq 2, 3) are "reached" while the drone climbs: not hovers.
    climb_t = int(flight.holds[0][0] - 2_000_000_000)
    reached += [(climb_t, 2), (climb_t, 3)]
    holds = {seq: 3.0 for _, _, seq in flight.holds}
    windows = windows_from_reached(reached, t, pos, holds)
    assert [w.seq for w in windows] == [seq for _, _, seq in flight.holds]
    assert all(w.source == "mission_item_reached" for w in windows)
    for w, (a, b, _) in zip(windows, flight.holds):
        assert w.end_ns == b
        assert abs(w.start_ns - a) < 10_000_000  # the plan's 3 s hold

    # Without the plan the start comes from the track.
    windows = windows_from_reached(reached, t, pos, None)
    err = _match(windows, flight.holds)
    assert len(windows) == len(flight.holds)
    assert np.abs(err[:, 0]).max() < 0.5


def test_intervals_are_sorted_numbered_and_duplicates_merged():
    windows = windows_from_intervals([(50, 80, 5), (10, 40, 4), (12, 38, 4), (90, 90, 6)], "event")
    assert [(w.index, w.start_ns, w.end_ns, w.seq) for w in windows] == [(0, 10, 40, 4), (1, 50, 80, 5)]


def test_stable_part_trims_settling_and_keeps_a_middle_third_of_short_holds():
    w = HoverWindow(index=0, start_ns=0, end_ns=3_000_000_000, source="event")
    assert w.stable(1.0, 0.2) == (1_000_000_000, 2_800_000_000)
    short = HoverWindow(index=0, start_ns=0, end_ns=900_000_000, source="event")
    a, b = short.stable(1.0, 0.2)
    assert (a, b) == (300_000_000, 600_000_000)
