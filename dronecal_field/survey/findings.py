"""The paper's section IV.B findings, recomputed from survey rows (pure numpy on the result table).

Each finding compares strategies *camera by camera* on the cameras where all
of them calibrate ('ok' rows), as the paper does, by the paper's metric: the
mean over the Monte-Carlo trials of the RMS reprojection error
(``rms_mean``). The same comparison by ``projection_error_px`` (how far the
estimated camera projects points from the truth) is given beside it: the
RMS reprojection error is a residual, and residuals *shrink* when a model
fits fewer points more freely, so it favours sparse sampling for reasons
that have nothing to do with a better calibration (docs/survey.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dronecal_field.survey.catalogue import COMPARISONS

METRICS = ("rms_mean", "projection_error_px")


@dataclass(frozen=True)
class Finding:
    """One line of the findings table: the paper's number and ours by both metrics.

    ``unit`` is '%' for shares of cameras (0-100) and 'px' for errors. ``n``
    counts the cameras compared (all strategies 'ok').
    """

    key: str
    claim: str
    paper: float | None
    unit: str
    ours_rms: float | None
    ours_projection: float | None
    n: int
    strategies: tuple[str, ...]

    def to_dict(self) -> dict:
        return {
            "key": self.key,
            "claim": self.claim,
            "paper": self.paper,
            "unit": self.unit,
            "ours_rms": self.ours_rms,
            "ours_projection": self.ours_projection,
            "n": self.n,
            "strategies": list(self.strategies),
        }


def metric_by_strategy(table, metric: str = "rms_mean") -> dict[str, dict[int, float]]:
    """{strategy: {camera_id: metric}} over the 'ok' rows with a finite value."""
    t = table.to_pydict() if hasattr(table, "to_pydict") else table
    out: dict[str, dict[int, float]] = {}
    for cid, strat, status, value in zip(t["camera_id"], t["strategy"], t["status"], t[metric]):
        if status == "ok" and value is not None and np.isfinite(value):
            out.setdefault(strat, {})[int(cid)] = float(value)
    return out


def paired(values: dict[str, dict[int, float]], strategies: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Camera ids (n,) where every strategy is ok, and their values (n, len(strategies))."""
    if any(s not in values for s in strategies):
        return np.zeros(0, int), np.zeros((0, len(strategies)))
    common = set(values[strategies[0]])
    for s in strategies[1:]:
        common &= set(values[s])
    ids = np.array(sorted(common), dtype=int)
    return ids, np.array([[values[s][i] for s in strategies] for i in ids], float).reshape(len(ids), len(strategies))


def _share(mask: np.ndarray) -> float | None:
    return float(100.0 * mask.mean()) if mask.size else None


def _compute(table, metric: str) -> dict[str, tuple[float | None, int]]:
    """Every finding's value by one metric: {key: (value, n)}."""
    v = metric_by_strategy(table, metric)
    out: dict[str, tuple[float | None, int]] = {}
    z2, z3, z4 = COMPARISONS["heights"]
    _, m = paired(v, (z2, z3, z4))
    out["two_heights_enough"] = (_share(m[:, 0] <= np.minimum(m[:, 1], m[:, 2])), len(m))
    y1, y05 = COMPARISONS["y_step"]
    _, m = paired(v, (y1, y05))
    out["y_step_1m_better"] = (_share(m[:, 0] < m[:, 1]), len(m))
    far, near, full = COMPARISONS["x_range"]
    _, m = paired(v, (far, near))
    out["far_better_than_near"] = (_share(m[:, 0] < m[:, 1]), len(m))
    reduction = float(100.0 * (1.0 - m[:, 0].mean() / m[:, 1].mean())) if len(m) else None
    out["far_reduces_mean_vs_near"] = (reduction, len(m))
    out["far_mean"] = (float(m[:, 0].mean()) if len(m) else None, len(m))
    _, m3 = paired(v, (far, near, full))
    out["far_best_of_three"] = (_share(m3[:, 0] < np.minimum(m3[:, 1], m3[:, 2])), len(m3))
    reduction_full = float(100.0 * (1.0 - m3[:, 0].mean() / m3[:, 2].mean())) if len(m3) else None
    out["far_reduces_mean_vs_full"] = (reduction_full, len(m3))
    return out


# key -> (claim, paper value, unit, strategies compared)
CLAIMS: dict[str, tuple[str, float | None, str, tuple[str, ...]]] = {
    "two_heights_enough": ("cameras for which 3 or 4 heights do not improve on 2", 98.0, "%", COMPARISONS["heights"]),
    "y_step_1m_better": ("cameras better with a 1 m step along Y than 0.5 m", 97.0, "%", COMPARISONS["y_step"]),
    "far_better_than_near": ("cameras better sampled far (X 4-8 m) than near (0-4 m)", 79.0, "%", COMPARISONS["x_range"][:2]),
    "far_reduces_mean_vs_near": ("reduction of the mean error, far vs near", 38.0, "%", COMPARISONS["x_range"][:2]),
    "far_mean": ("mean error with the far sampling", 4.0, "px", COMPARISONS["x_range"][:2]),
    "far_best_of_three": ("cameras better far than both near and full (0-8 m)", None, "%", COMPARISONS["x_range"]),
    "far_reduces_mean_vs_full": ("reduction of the mean error, far vs full", None, "%", COMPARISONS["x_range"]),
}


def paper_findings(table) -> list[Finding]:
    """The findings table: the paper's numbers next to ours (RMS reprojection and projection error).

    Parameters
    ----------
    table : survey rows (pyarrow Table or dict of columns) holding at least
        the strategies of :data:`COMPARISONS`; findings whose strategies are
        missing get None and n = 0.
    """
    by_rms = _compute(table, "rms_mean")
    by_proj = _compute(table, "projection_error_px")
    return [
        Finding(
            key=key,
            claim=claim,
            paper=paper,
            unit=unit,
            ours_rms=by_rms[key][0],
            ours_projection=by_proj[key][0],
            n=by_rms[key][1],
            strategies=strategies,
        )
        for key, (claim, paper, unit, strategies) in CLAIMS.items()
    ]


def near_winners_fov(table) -> dict[str, float | int | None]:
    """Do the cameras that prefer near sampling have extreme fields of view (the paper's 21 %)?

    Returns the number of near-winners and the share of them (%) whose
    horizontal FOV lies outside the middle half (25th-75th percentile) of all
    compared cameras: 50 % if the FOV did not matter, more if the paper is right.
    """
    v = metric_by_strategy(table, "rms_mean")
    far, near = COMPARISONS["x_range"][:2]
    ids, m = paired(v, (far, near))
    if not len(ids):
        return {"near_winners": 0, "extreme_fov_share": None, "fov_q25": None, "fov_q75": None}
    t = table.to_pydict() if hasattr(table, "to_pydict") else table
    fov = {int(c): float(h) for c, h in zip(t["camera_id"], t["hfov_deg"])}
    h = np.array([fov[i] for i in ids])
    q25, q75 = np.percentile(h, [25, 75])
    winners = m[:, 1] < m[:, 0]
    extreme = (h < q25) | (h > q75)
    return {
        "near_winners": int(winners.sum()),
        "extreme_fov_share": _share(extreme[winners]),
        "fov_q25": float(q25),
        "fov_q75": float(q75),
    }


def status_counts(table) -> dict[str, dict[str, int]]:
    """{strategy: {status: rows}}."""
    t = table.to_pydict() if hasattr(table, "to_pydict") else table
    out: dict[str, dict[str, int]] = {}
    for strat, status in zip(t["strategy"], t["status"]):
        d = out.setdefault(strat, {})
        d[status] = d.get(status, 0) + 1
    return out


def format_findings(findings: list[Finding]) -> str:
    """A plain-text table of the findings (for the terminal)."""

    def fmt(v: float | None, unit: str) -> str:
        if v is None:
            return "-"
        return f"{v:.0f} %" if unit == "%" else f"{v:.2f} {unit}"

    lines = [f"{'finding':58} {'paper':>8} {'ours RMS':>10} {'ours proj':>10} {'cameras':>8}"]
    for f in findings:
        lines.append(f"{f.claim:58} {fmt(f.paper, f.unit):>8} {fmt(f.ours_rms, f.unit):>10} {fmt(f.ours_projection, f.unit):>10} {f.n:>8}")
    return "\n".join(lines)
