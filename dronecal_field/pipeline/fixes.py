"""Which GNSS messages are distinct fixes: a fix is told apart by its time, not its position.

The contract (shared/contracts/run-format.md) stamps each ``/gnss/fix`` at the
fix's own measurement time and writes one message per fix. A steady hover can
repeat a position exactly at MAVLink's 1e-7 deg quantisation (real ArduCopter
4.7: 588 of 1537 new fixes of ``fly-calib-t1.tlog``), and those are still new
fixes. Writers that stamp arrival and pass on a telemetry stream faster than
the receiver repeat each fix under a later stamp; for them the rule falls back
(best first):

``fix time``
    The contract's rule: only a message with the same timestamp as the one
    before is a repeat.
``position and GPS_RAW_INT.time_usec``
    Fixes stamped at the arrival of their ``/mavlink/GPS_RAW_INT`` message: a
    repeat has the same position AND the same ``time_usec`` as the fix before.
``position``
    Arrival-stamped fixes without raw telemetry (``gnss.latency_s`` declared,
    or fixes repeated bit for bit while the track moves, which no real new fix
    does): a repeat is a fix at exactly the position before it. Equal-position
    fixes of a still hover are then lost, and the report says so.

Pure numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RULES = ("fix time", "position and GPS_RAW_INT.time_usec", "position")


@dataclass(frozen=True, eq=False)
class DistinctFixes:
    """The outcome of :func:`distinct_fixes`.

    Attributes
    ----------
    keep : (N,) bool
        True for the first message of each fix.
    rule : str
        One of RULES: how repeats were told apart.
    n_repeats : int
        Messages left out as repeats of the fix before.
    n_equal_position_kept : int
        Kept fixes with exactly the position of the fix before (still hovers).
    """

    keep: np.ndarray
    rule: str
    n_repeats: int
    n_equal_position_kept: int

    def to_dict(self) -> dict:
        return {"rule": self.rule, "repeats_left_out": self.n_repeats, "equal_position_fixes_kept": self.n_equal_position_kept}


def distinct_fixes(
    t_ns: np.ndarray,
    lla: np.ndarray,
    raw_time_usec: np.ndarray | None = None,
    arrival_stamped: bool = False,
    moving_m: float = 0.1,
    min_moving_repeats: int = 3,
) -> DistinctFixes:
    """Mark the distinct fixes of a time-sorted GNSS message sequence.

    Parameters
    ----------
    t_ns : (N,) int64
        Message timestamps, increasing (ties allowed).
    lla : (N, 3)
        Latitude, longitude (deg), height (m), as recorded.
    raw_time_usec : (N,) int64, optional
        ``GPS_RAW_INT.time_usec`` of the raw message each fix was stamped with
        (0 where unknown); given only when the fixes are stamped at those
        messages' arrival.
    arrival_stamped : bool
        The writer declared ``gnss.latency_s``: stamps are arrival, not fix time.
    moving_m : float
        An equal-position message counts as "while moving" when the fixes on
        either side of it are more than this far apart.
    min_moving_repeats : int
        This many equal-position messages while moving reveal a stream that
        repeats fixes (rule ``position``).

    Returns
    -------
    DistinctFixes
    """
    t = np.asarray(t_ns, np.int64)
    p = np.asarray(lla, float).reshape(-1, 3)
    n = len(t)
    if n == 0:
        return DistinctFixes(keep=np.zeros(0, bool), rule=RULES[0], n_repeats=0, n_equal_position_kept=0)
    same_time = np.r_[False, np.diff(t) == 0]
    same_pos = np.r_[False, np.all(np.diff(p, axis=0) == 0.0, axis=1)]
    if raw_time_usec is not None:
        raw = np.asarray(raw_time_usec, np.int64)
        same_raw = np.r_[False, (np.diff(raw) == 0) & (raw[1:] > 0)]
        repeat = same_time | (same_pos & same_raw)
        rule = RULES[1]
    else:
        moving_repeats = 0
        q = p[~same_time]  # one message per timestamp
        if len(q) >= 3:
            # Neighbours far apart around an equal pair: the track moves there.
            q_same = np.all(np.diff(q, axis=0) == 0.0, axis=1)
            k = np.flatnonzero(q_same[:-1]) + 1
            lat_m = 111_320.0
            scale = np.c_[np.full(len(k), lat_m), lat_m * np.cos(np.radians(q[k, 0])), np.ones(len(k))]
            d = (q[k + 1] - q[k - 1]) * scale
            moving_repeats = int(np.sum(np.linalg.norm(d, axis=1) > moving_m))
        if arrival_stamped or moving_repeats >= min_moving_repeats:
            repeat = same_time | same_pos
            rule = RULES[2]
        else:
            repeat = same_time
            rule = RULES[0]
    keep = ~repeat
    return DistinctFixes(
        keep=keep,
        rule=rule,
        n_repeats=int(repeat.sum()),
        n_equal_position_kept=int(np.sum(same_pos & keep)),
    )
