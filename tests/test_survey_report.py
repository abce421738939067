"""Findings and the report on a stored small survey.

tests/data/survey_small.parquet was made with
    dronecal-field survey --cameras 80 --trials 100 --strategies paper --out /tmp/s --workers 2
    dronecal-field survey export /tmp/s --to tests/data/survey_small.parquet
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import run_cli
from dronecal_field.errors import InputError
from dronecal_field.survey.findings import paper_findings
from dronecal_field.survey.store import COLUMNS, load_results, read_config, rows_to_table

DATA = Path(__file__).parent / "data" / "survey_small.parquet"


def _table(values: dict[str, list[float | None]]):
    """A result table of len(values[...]) cameras; None marks a degenerate row."""
    rows = []
    for strategy, vals in values.items():
        for cid, v in enumerate(vals):
            rows.append({"camera_id": cid, "strategy": strategy, "status": "ok" if v is not None else "degenerate",
                         "rms_mean": v, "projection_error_px": None if v is None else 10.0 - v, "hfov_deg": 40.0 + 10 * cid})
    return rows_to_table(rows)


def test_findings_count_cameras_pair_by_pair():
    t = _table({
        "full-y1-z2": [3.0, 3.0, 3.0, 3.0],
        "full-y1-z3": [3.5, 2.0, 3.1, 3.2],
        "full-y1-z4": [3.6, 3.5, 3.0, None],
        "full-y0.5-z2": [3.2, 2.9, 3.3, 3.4],
        "far-y1-z2": [2.0, 2.0, 5.0, None],
        "near-y1-z2": [4.0, 3.0, 4.0, 4.0],
    })
    f = {x.key: x for x in paper_findings(t)}
    # camera 3 has no z4 row: 3 cameras compared; camera 1 improves with 3 heights, camera 2 ties with 4 (not an improvement)
    assert f["two_heights_enough"].n == 3
    assert f["two_heights_enough"].ours_rms == pytest.approx(200 / 3)
    assert f["y_step_1m_better"].ours_rms == pytest.approx(75.0)  # camera 1: 0.5 m is better
    assert f["far_better_than_near"].n == 3 and f["far_better_than_near"].ours_rms == pytest.approx(200 / 3)
    assert f["far_reduces_mean_vs_near"].ours_rms == pytest.approx(100 * (1 - 3.0 / (11 / 3)))
    assert f["far_mean"].ours_rms == pytest.approx(3.0)
    # the projection metric (10 - v here) reverses every comparison
    assert f["y_step_1m_better"].ours_projection == pytest.approx(25.0)
    assert f["far_better_than_near"].paper == 79.0
    assert f["far_best_of_three"].n == 3 and f["far_best_of_three"].ours_rms == pytest.approx(200 / 3)


def test_stored_results_load_and_hold_the_papers_strategies():
    t = load_results(DATA)
    assert t.column_names == [name for name, _ in COLUMNS]
    assert t.num_rows == 80 * 6
    keys = list(zip(t.column("camera_id").to_pylist(), t.column("strategy").to_pylist()))
    assert len(set(keys)) == len(keys)
    cfg = read_config(DATA)
    assert cfg["n_cameras"] == 80 and cfg["monte_carlo"]["trials"] == 100
    ok = np.array(t.column("status").to_pylist()) == "ok"
    rms = np.array(t.column("rms_mean").to_pylist(), dtype=float)[ok]
    # 2 px detection noise alone gives at least ~2 * sqrt(2 - 14/n) px; GNSS noise only adds
    assert rms.min() > 2.0 and np.median(rms) < 12.0


def test_report_on_stored_results_reproduces_the_papers_table_and_figures(tmp_path):
    out = tmp_path / "report"
    proc = run_cli("survey", "report", str(DATA), "--report-dir", str(out), "--fig10-trials", "60", timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "cameras better sampled far (X 4-8 m) than near (0-4 m)" in proc.stdout
    html = (out / "index.html").read_text()
    for name in ("figure8.png", "figure9.png", "figure10.png"):
        assert f'src="{name}"' in html
        import matplotlib.image as mpimg

        img = mpimg.imread(out / name)
        assert img.shape[0] > 300 and img.shape[1] > 500
        assert float(np.std(img[..., :3])) > 0.05  # not a blank canvas
    import json

    summary = json.loads((out / "findings.json").read_text())
    found = {f["key"]: f for f in summary["findings"]}
    # recompute one finding independently from the table: far vs near, camera by camera
    t = load_results(DATA).to_pydict()
    by = {}
    for cid, s, st, v in zip(t["camera_id"], t["strategy"], t["status"], t["rms_mean"]):
        if st == "ok":
            by.setdefault(s, {})[cid] = v
    common = sorted(set(by["far-y1-z2"]) & set(by["near-y1-z2"]))
    share = 100.0 * np.mean([by["far-y1-z2"][c] < by["near-y1-z2"][c] for c in common])
    assert found["far_better_than_near"]["n"] == len(common) > 20
    assert found["far_better_than_near"]["ours_rms"] == pytest.approx(share)
    assert found["far_better_than_near"]["paper"] == 79.0
    # the far sampling's mean error lands near the paper's 4 px
    assert 2.8 < found["far_mean"]["ours_rms"] < 6.0
    # Figure 10: the GNSS share of the error shrinks with the sampling distance
    fig10 = summary["figure10"]
    gap = np.array(fig10["with_gnss_px"], float) - np.array(fig10["image_only_px"], float)
    assert np.all(gap[np.isfinite(gap)] > 0)
    assert gap[np.isfinite(gap)][-1] < gap[np.isfinite(gap)][0]


def test_report_refuses_what_is_not_a_survey(tmp_path):
    bad = tmp_path / "x.parquet"
    bad.write_text("not parquet")
    with pytest.raises(InputError):
        load_results(bad)
    proc = run_cli("survey", "report", str(tmp_path / "missing.parquet"))
    assert proc.returncode == 2 and "do not exist" in proc.stderr


@pytest.mark.parametrize("action, own, foreign", [("report", "--report-dir", "--cameras"), ("export", "--to", "--cameras"), ("run", "--cameras", "--report-dir DIR")])
def test_each_survey_action_prints_its_own_help(capsys, action, own, foreign) -> None:
    from dronecal_field.cli import main

    argv = ["survey", "--help"] if action == "run" else ["survey", action, "--help"]
    with pytest.raises(SystemExit) as exit_:
        main(argv)
    text = capsys.readouterr().out
    assert exit_.value.code == 0
    assert own in text and foreign not in text
    assert text.startswith("usage: dronecal-field survey" + ("" if action == "run" else f" {action}"))
    assert "``" not in text


def test_report_folder_is_replaced_as_a_set_keeping_other_files(tmp_path) -> None:
    """A re-run replaces the report's own files at once (no half-new folder) and keeps what the user put there."""
    from dronecal_field.survey.report import REPORT_FILES, write_report

    out = tmp_path / "report"
    out.mkdir()
    (out / "notes.txt").write_text("reviewed with the team\n")
    (out / "figure8.png").write_bytes(b"stale")
    files = write_report(DATA, out, fig10_trials=20)
    assert files.html == out / "index.html" and files.html.is_file()
    assert sorted(p.name for p in out.iterdir()) == sorted([*REPORT_FILES, "notes.txt"])
    assert (out / "notes.txt").read_text() == "reviewed with the team\n"
    assert (out / "figure8.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".report.")]  # no temporary sibling left
