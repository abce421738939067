"""Point sets must agree before they are pooled (issue 20).

A run's points come in sets with different failure modes: the holds (hover
points), and each fly-through leg (pairs along a leg, either flown as planned
or found in the GNSS track, e.g. a transit to the first waypoint that passes
close under the camera). One set that does not fit the others (a transit
paired at the wrong instant, a leg whose marker was blurred, a lever arm that
does not hold at speed) pulls the pooled camera: on the paper's grid for a
wide 1080p camera, 38 pairs of 2 transit legs took a 70-hold calibration from
0.36 px to 82 px RMS and the automatic model to "none".

The check, pure functions on the points: the holds are calibrated alone (the
reference); when the pooled fit leaves the holds' residuals well above their
own fit's, the legs the reference camera predicts worst are left out, one
line says which and why, and the caller pairs and solves again without them.
A set that agrees stays, even when it reaches beyond the holds (a leg that
extends the coverage fits the pooled camera and leaves the holds' residuals
alone).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from dronecal_field.errors import DronecalError

# Fewer holds cannot judge the legs: their own camera is too loose between them. The 4K plan's 12 leg-end holds
# (contract writer, legs flown 8x faster) "disagreed" with 6 of its 11 planned legs by 1.9 px, the holds' own
# lens model interpolating poorly between them; leaving those legs out doubled the ground error.
MIN_REFERENCE_POINTS = 20
AGREE_FACTOR = 1.5  # the pooled fit may leave the holds' RMS this much above their own fit's (its dof counted) ...
AGREE_SLACK_PX = 0.1  # ... plus this
DISAGREE_FACTOR = 5.0  # a leg the holds' camera predicts worse than this times the holds' own RMS ...
DISAGREE_MIN_PX = 1.0  # ... and worse than this disagrees
AGREES = "pooled fit agrees with the holds' own"
PAIRS_PER_POINT = 10  # a leg's pairs share its timing error and correlated RTK noise: 10 (1 s at 10 Hz) are worth one hold


@dataclass(frozen=True)
class SetCheck:
    """One leg's agreement with the holds: its RMS through the holds' camera and through the pooled one."""

    leg: int
    source: str  # "event" or "gnss_track"
    n_points: int
    through_reference_px: float
    through_pooled_px: float
    left_out: bool

    def to_dict(self) -> dict:
        return {"leg": self.leg, "source": self.source, "points": self.n_points, "rms_through_holds_px": round(self.through_reference_px, 3),
                "rms_through_pooled_px": round(self.through_pooled_px, 3), "left_out": self.left_out}


@dataclass(frozen=True)
class Agreement:
    """The sets' agreement: the holds' own fit against the pooled fit, each leg, what was left out and the line saying so."""

    checked: bool
    reason: str
    holds: int = 0
    holds_alone_rms_px: float | None = None
    holds_pooled_rms_px: float | None = None
    legs: tuple[SetCheck, ...] = ()
    line: str | None = None
    verdict: str | None = None  # what was done with the legs that disagree

    @property
    def left_out(self) -> set[int]:
        return {s.leg for s in self.legs if s.left_out}

    def to_dict(self) -> dict:
        return {
            "checked": self.checked, "reason": self.reason, "holds": self.holds,
            "holds_alone_rms_px": self.holds_alone_rms_px, "holds_pooled_rms_px": self.holds_pooled_rms_px,
            "legs": [s.to_dict() for s in self.legs], "line": self.line,
        }


@dataclass(frozen=True)
class AgreementOptions:
    keep: bool = False  # the user named the leg source: report a disagreement, leave nothing out
    flag: str = "`--leg-source track`"  # the flag that keeps the legs, named in the line
    leg_source_name: str = "gnss_track"  # where the legs came from: "event" or "gnss_track"


def _rms(res: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(res, float) ** 2, axis=1)))) if len(res) else float("nan")


def _robust_rms(res: np.ndarray) -> float:
    """RMS of the residuals (N, 2) within 3x their median norm: a few late frames do not make a set disagree."""
    r = np.linalg.norm(np.asarray(res, float), axis=1)
    if not len(r):
        return float("nan")
    keep = r <= 3.0 * max(float(np.median(r)), 1e-9)
    return float(np.sqrt(np.mean(r[keep] ** 2)))


def check_sets(points: list, pooled, fit_reference, options: AgreementOptions = AgreementOptions()) -> Agreement:
    """Do the legs agree with the holds?

    Parameters
    ----------
    points : list of WaypointPoint, all (used and not); the used ones in order are the pooled fit's rows
    pooled : CalibrationResult of the used points
    fit_reference : callable (X (N, 3), uv (N, 2)) -> CalibrationResult, the holds' own calibration
    options : AgreementOptions

    Returns
    -------
    Agreement (``left_out``: the leg indices to pair no more)
    """
    used = [p for p in points if p.used]
    hold_rows = np.array([k for k, p in enumerate(used) if p.window.source != "leg"], int)
    legs: dict[int, list[int]] = {}
    for k, p in enumerate(used):
        if p.window.source == "leg":
            legs.setdefault(int(p.window.seq), []).append(k)
    if not legs:
        return Agreement(False, "no legs")
    if len(hold_rows) < MIN_REFERENCE_POINTS:
        return Agreement(False, f"{len(hold_rows)} holds: too few to judge the legs", holds=len(hold_rows))
    X = np.array([p.marker_enu_m for p in used])
    uv = np.array([p.uv_px for p in used])
    try:
        ref = fit_reference(X[hold_rows], uv[hold_rows])
    except DronecalError as exc:
        return Agreement(False, f"the holds alone do not calibrate ({str(exc).split(':')[0]})", holds=len(hold_rows))
    res = np.asarray(pooled.residuals_px, float)
    n_eq = 2 * len(hold_rows)
    alone = _robust_rms(ref.residuals_px) * float(np.sqrt(n_eq / max(n_eq - ref.model.n_free, 1)))  # what the noise is, not the overfit
    together = _robust_rms(res[hold_rows])
    predicted = {leg: _robust_rms(ref.camera.project(X[rows]) - uv[rows]) for leg, rows in legs.items()}
    limit = max(DISAGREE_FACTOR * alone, DISAGREE_MIN_PX)
    agree = together <= AGREE_FACTOR * alone + AGREE_SLACK_PX
    bad = set() if agree else {leg for leg, r in predicted.items() if r > limit}
    if not agree and not bad:  # the pooled fit is pulled, but by no single leg beyond the limit: the worst ones
        worst = max(predicted.values())
        bad = {leg for leg, r in predicted.items() if r >= 0.5 * worst and r > AGREE_FACTOR * alone + AGREE_SLACK_PX}
    # the odd set is the smaller one: legs worth more than the holds and the other legs are not left out (the holds may be odd)
    worth = {leg: max(min(len(rows), 2), len(rows) / PAIRS_PER_POINT) for leg, rows in legs.items()}
    minority = sum(worth[g] for g in bad) < len(hold_rows) + sum(w for g, w in worth.items() if g not in bad)
    source = options.leg_source_name
    checks = tuple(
        SetCheck(leg=leg, source=source, n_points=len(rows), through_reference_px=predicted[leg],
                 through_pooled_px=_robust_rms(res[rows]), left_out=leg in bad and minority and not options.keep)
        for leg, rows in sorted(legs.items())
    )
    out = Agreement(True, AGREES if agree else "pooled fit pulled away from the holds",
                    holds=len(hold_rows), holds_alone_rms_px=alone, holds_pooled_rms_px=together, legs=checks)
    if not bad:
        return out
    if not minority:
        verdict = ("kept: they outweigh the holds; check the lever arm (marker.offset_frd_m) and the holds' settle time "
                   "(--settle-s)")
    elif options.keep:
        verdict = f"kept, as {options.flag} asks"
    else:
        verdict = f"left out; {options.flag} keeps them"
    return replace(out, line=_line([c for c in checks if c.leg in bad], out, verdict), verdict=verdict)


def _line(bad: list[SetCheck], agreement: Agreement, verdict: str) -> str:
    """The one line: which legs, how many pairs, by how much they disagree, and what was done."""
    where = " from the GNSS track" if bad and bad[0].source == "gnss_track" else ""
    legs_text = f"{len(bad)} legs{where}" if len(bad) > 1 else f"1 leg{where}"
    by = float(np.median([c.through_reference_px for c in bad]))
    return (f"{legs_text} ({sum(c.n_points for c in bad)} pairs) disagree with the {agreement.holds} holds by {by:.1f} px "
            f"(the holds alone fit to {agreement.holds_alone_rms_px:.2f} px, with them {agreement.holds_pooled_rms_px:.2f} px): {verdict}")


def merged(first: Agreement, second: Agreement | None) -> Agreement:
    """The agreement of a run whose legs were checked again after ``first`` left some out: one line for all left out."""
    if second is None or not second.left_out:
        return first
    gone = [c for c in first.legs if c.left_out] + [c for c in second.legs if c.left_out]
    legs = tuple(sorted([*(c for c in first.legs if c.left_out), *second.legs], key=lambda c: c.leg))
    out = replace(first, legs=legs)
    return replace(out, line=_line(gone, first, first.verdict or ""))
