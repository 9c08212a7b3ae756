"""The decision threshold's calibration page (bench/calibrate_llr.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.calibrate_llr import cause, main, outcome, pass_outcome
from bench.global_drive_run import COMMAND_FILE


def _rows(*rows: tuple[float, float, float, float, float, float]) -> np.ndarray:
    return np.asarray(rows, dtype=np.float64)


def _rows5(*rows: tuple[float, float, float, float, float]) -> np.ndarray:
    return np.asarray(rows, dtype=np.float64)


def test_a_checked_wrong_leader_at_the_threshold_is_a_false_fix() -> None:
    # travel, llr, error m, heading error rad, checked, found
    rows = _rows((1.0, 12.0, 9.0, 1.5, 1.0, 1.0), (2.0, 30.0, 0.1, 0.0, 1.0, 1.0))
    assert outcome(rows, 10.0) == ("wrong", 1.0)
    assert outcome(rows, 20.0) == ("right", 2.0)
    assert outcome(rows, 40.0)[0] == "none"
    unchecked = _rows((1.0, 12.0, 9.0, 1.5, 0.0, 1.0), (2.0, 30.0, 0.1, 0.0, 1.0, 1.0))
    assert outcome(unchecked, 10.0) == ("right", 2.0)


def test_the_page_names_the_run_and_the_presets(tmp_path: Path) -> None:
    tables = tmp_path / "tables"
    tables.mkdir()
    (tables / COMMAND_FILE).write_text("python -m bench.bench_global --drive\nabc1234\n")
    # one tuning floor-plan drive that leads a wrong place at 12 nats and never the true one;
    # a held-out world's table is never read
    np.save(tables / "real_intel_schematic_7.npy", _rows((1.0, 12.0, 9.0, 1.5, 1.0, 1.0)))
    np.save(tables / "worlds_1003_schematic_1.npy", _rows((1.0, 99.0, 9.0, 1.5, 1.0, 1.0)))
    results = tmp_path / "results"
    assert main([str(tables), "--results", str(results)]) == 0
    page = (results / "llr-threshold.md").read_text()
    assert "`python -m bench.bench_global --drive` at commit abc1234" in page
    assert "## schematic (1 tuning trials)" in page
    assert "| 10 | 1 | 0/1 |" in page and "| 15 | 0 | 0/1 |" in page
    assert "Smallest threshold without a false fix: 15 x 1.25 = 18.75." in page
    assert "The preset's `fix_llr`: 25, probation 2 m." in page
    assert "## metric" not in page


def test_a_probation_whose_wrong_winner_leads_at_the_pass_is_a_false_pass() -> None:
    # travel, llr on a judged probation scan, winner's error m, heading error rad, winner led
    rows = _rows5(
        (2.0, 30.0, 9.0, 0.1, 1.0), (4.0, 99.0, 0.1, 0.0, 0.0), (6.0, 50.0, 0.2, 0.0, 1.0)
    )
    assert pass_outcome(rows, 25.0) == ("wrong", 2.0)
    assert pass_outcome(rows, 40.0) == ("right", 6.0)  # the 99 at 4 m was another place's lead
    assert pass_outcome(rows, 60.0)[0] == "none"


def test_the_pass_page_counts_judged_probation_scans_of_floor_plans_only(tmp_path: Path) -> None:
    tables = tmp_path / "tables"
    tables.mkdir()
    (tables / COMMAND_FILE).write_text("python -m bench.bench_global --drive\nabc1234\n")
    np.save(tables / "real_fr079_schematic_3.npy", _rows5((2.0, 33.0, 15.0, 3.1, 1.0)))
    np.save(tables / "real_fr079_metric_3.npy", _rows5((2.0, 33.0, 15.0, 3.1, 1.0)))
    results = tmp_path / "results"
    assert main(["--pass", str(tables), "--results", str(results)]) == 0
    page = (results / "llr-probation.md").read_text()
    assert "# The probation's pass from the tuning split" in page
    assert "| 30 | 1 | 0/1 | nan | 0 |" in page and "| 35 | 0 | 0/1 | nan | 0 |" in page
    assert "| 20 |" not in page  # a probation passes at fix_llr (25) or more
    assert "Smallest threshold without a false pass: 35 x 1.25 = 43.75." in page
    assert "## metric" not in page  # no probation on metric maps


def test_where_every_threshold_leaves_a_false_pass_the_rule_takes_the_fewest(
    tmp_path: Path,
) -> None:
    tables = tmp_path / "tables"
    tables.mkdir()
    # a wrong winner leading at 40 nats; another drive's winner right at 50, 0.6 m off at 99
    np.save(tables / "real_intel_schematic_1.npy", _rows5((2.0, 40.0, 9.0, 1.5, 1.0)))
    np.save(
        tables / "real_intel_schematic_2.npy",
        _rows5((2.0, 50.0, 0.3, 0.0, 1.0), (3.0, 99.0, 0.6, 0.0, 1.0)),
    )
    results = tmp_path / "results"
    assert main(["--pass", str(tables), "--results", str(results)]) == 0
    page = (results / "llr-probation.md").read_text()
    assert "| 40 | 1 | 1/2 |" in page and "| 45 | 0 | 1/2 |" in page
    assert "| 55 | 1 | 0/2 |" in page
    assert "Smallest threshold without a false pass: 45 x 1.25 = 56.25." in page
    np.save(tables / "real_intel_schematic_3.npy", _rows5((2.0, 80.0, 5.0, 0.0, 1.0)))
    assert main(["--pass", str(tables), "--results", str(results)]) == 0
    page = (results / "llr-probation.md").read_text()
    assert "No threshold up to 80 is without a false pass; the smallest at the fewest (1): " in page
    assert "45 x 1.25 = 56.25" in page


def _drive(*scans: tuple[float, float, bool, float, bool]) -> np.ndarray:
    """Rows of a --calibrate table from (travel, llr, leader right, LLR against the unseen
    place alone, a place kept holds the truth)."""
    rows = [
        (tr, llr, 0.1 if ok else 9.0, 0.0, 1.0, 1.0, unseen, float(held))
        for tr, llr, ok, unseen, held in scans
    ]
    return np.asarray(rows, dtype=np.float64)


def test_a_slow_fix_is_put_down_to_what_held_most_of_its_scans() -> None:
    # true place fixed at 62.5 nats at 3 m: not slow
    assert (
        cause(_drive((1.0, 10.0, True, 10.0, True), (3.0, 70.0, True, 70.0, True)), 62.5, 15)
        is None
    )
    # a wrong place leads to 9 m, the truth held by a kept place on most of those scans
    rows = _drive(
        *[(2.0 + 0.5 * k, 20.0, False, 20.0, k > 2) for k in range(14)],
        (9.5, 70.0, True, 70.0, True),
    )
    assert cause(rows, 62.5, 15.0) == "not leading"
    # the true place leads from 2 m, short of 62.5 against the unseen place alone
    rows = _drive(*[(2.0 + 0.5 * k, 40.0, True, 45.0, True) for k in range(20)])
    assert cause(rows, 62.5, 15.0) == "unseen"
    # ... or against the places found, the unseen place far behind
    rows = _drive(*[(2.0 + 0.5 * k, 40.0, True, 90.0, True) for k in range(20)])
    assert cause(rows, 62.5, 15.0) == "places"
    # tables written before the LLR's split give no cause
    assert cause(rows[:, :6], 62.5, 15.0) is None


def test_the_page_counts_the_slow_first_fixes_by_cause(tmp_path: Path) -> None:
    tables = tmp_path / "tables"
    tables.mkdir()
    np.save(
        tables / "real_fr079_schematic_3.npy",
        _drive(*[(2.0 + 0.5 * k, 40.0, True, 45.0, True) for k in range(30)]),
    )
    np.save(tables / "real_fr079_schematic_4.npy", _drive((3.0, 70.0, True, 70.0, True)))
    results = tmp_path / "results"
    assert main([str(tables), "--results", str(results)]) == 0
    page = (results / "llr-threshold.md").read_text()
    assert "Slow first fixes (the true place fixed at 62.5 nats only after 8 m" in page
    assert ": 1 of 2." in page
    assert "the unseen place alone holds its LLR short: 1" in page
    assert "the other places found hold its LLR short: 0" in page
