"""Experiment runner (Table 1 of the paper): statistics, table layout, outputs, CLI
(``shapeloc-sim experiment``, ``python -m sim_publisher.experiment``), ranking."""

from __future__ import annotations

import argparse
import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from service.errors import LocalizationError
from sim_publisher.experiment import (
    BLOCK_TITLES,
    PAPER_TABLE,
    TABLE_COLUMNS,
    ExperimentResult,
    MethodRun,
    SetupInfo,
    add_arguments,
    run,
    run_experiment,
)

REPO = Path(__file__).resolve().parents[2]


def _parse_blocks(text: str) -> dict[str, list[list[str]]]:
    """Split ``table_text`` into {block title: rows of cells (header first)}."""
    blocks: dict[str, list[list[str]]] = {}
    current = None
    for line in text.splitlines():
        if not line.strip():
            continue
        if line.startswith("|"):
            if set(line) <= {"|", "-"}:
                continue
            assert current is not None, "table row before any block title"
            blocks[current].append([c.strip() for c in line.strip("|").split("|")])
        else:
            current = line.split(" (")[0]
            blocks[current] = []
    return blocks


def _run(setup: int, method: str, pos: list[float], head_deg: list[float]) -> MethodRun:
    n = len(pos)
    return MethodRun(
        setup=setup,
        method=method,
        estimates=np.zeros((n, 3)),
        position_error=np.array(pos),
        heading_error=np.radians(head_deg),
        statuses=("tracking",) * (n - 1) + ("lost",),
        seconds=0.004 * n,
    )


def test_statistics_and_table_layout_from_known_errors() -> None:
    info = {
        s: SetupInfo(s, f"setup{s}", f"map{s}", k, 4, 10.0, 11.0, 4.0)
        for s, k in ((1, "metric"), (2, "schematic"))
    }
    res = ExperimentResult(seed=0, max_scans=None, setups=info)
    res.runs[(2, "shape")] = _run(2, "shape", [0.1, 0.2, 0.6, 0.3], [1, 2, 3, 50])
    res.runs[(1, "icp")] = _run(1, "icp", [0.05, 0.2, 0.09, 0.01], [1, 1, 50, 2])
    res.runs[(1, "lines")] = _run(1, "lines", [1.0, 1.0, 1.0, 1.0], [90, 90, 90, 90])
    r = res.runs[(1, "icp")]
    assert math.isclose(r.mean_position_mm, 87.5)
    assert math.isclose(r.mean_heading_deg, 13.5)
    assert math.isclose(r.proximity_pct, 50.0)  # 0.2 m fails, 50 deg fails
    assert math.isclose(res.runs[(2, "shape")].proximity_pct, 50.0)  # 0.6 m and 50 deg fail
    assert math.isclose(r.lost_pct, 25.0)
    assert math.isclose(r.ms_per_scan, 4.0)
    blocks = _parse_blocks(res.table_text())
    assert list(blocks) == [BLOCK_TITLES[1], BLOCK_TITLES[2]]
    b1 = blocks[BLOCK_TITLES[1]]
    assert tuple(b1[0]) == TABLE_COLUMNS
    assert [row[0] for row in b1[1:]] == ["ICP", "line-based"]  # paper's row order
    assert b1[1][1:4] == ["88", "13.50", "50.0"]
    assert b1[1][4:7] == ["534", "1.5", "21"]  # the paper's numbers alongside
    assert blocks[BLOCK_TITLES[2]][1][:4] == ["shape-based", "300", "14.00", "50.0"]


def test_short_schematic_run_shape_beats_both_baselines(tmp_path: Path) -> None:
    """Setup 2, first 80 scans, all three methods, figures into tmp_path (~10-20 s)."""
    out = tmp_path / "experiment"
    res = run_experiment(setups=(2,), max_scans=80, out_dir=out, progress=False, jobs=1, plots=True)
    blocks = _parse_blocks(res.table_text())
    assert list(blocks) == [BLOCK_TITLES[2]]
    rows = blocks[BLOCK_TITLES[2]]
    assert tuple(rows[0]) == TABLE_COLUMNS
    assert [row[0] for row in rows[1:]] == ["ICP", "line-based", "shape-based"]
    for row in rows[1:]:
        assert len(row) == len(TABLE_COLUMNS)
        values = [float(c) for c in row[1:]]
        assert all(math.isfinite(v) and v >= 0.0 for v in values)
        assert values[2] <= 100.0
    for m in ("icp", "lines", "shape"):
        run_ = res.runs[(2, m)]
        assert run_.scans == 80
        assert run_.estimates.shape == (80, 3)
        # Every method starts at the true first pose.
        assert run_.position_error[0] < 0.5
    shape, icp, lines = (res.runs[(2, m)] for m in ("shape", "icp", "lines"))
    assert shape.proximity_pct > icp.proximity_pct
    assert shape.proximity_pct > lines.proximity_pct
    assert shape.mean_position_mm < icp.mean_position_mm
    assert shape.mean_position_mm < lines.mean_position_mm
    # Outputs: CSV with one row per method, the page beside the directory with the table,
    # how it was produced and the figure, a PNG.
    with (out / "results.csv").open(encoding="utf-8") as fh:
        table = list(csv.DictReader(fh))
    assert [r["method"] for r in table] == ["icp", "lines", "shape"]
    assert float(table[2]["proximity_pct"]) == pytest.approx(shape.proximity_pct, abs=0.01)
    assert float(table[0]["paper_proximity_pct"]) == PAPER_TABLE[2]["icp"][2]
    page = (tmp_path / "experiment.md").read_text(encoding="utf-8")
    assert res.table_text() in page
    assert "- Command: `sim_publisher.experiment.run_experiment(" in page
    assert "- Machine: " in page and " cores; Python " in page
    assert "![setup 2](experiment/setup2.png)" in page
    png = (out / "setup2.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_results_do_not_depend_on_jobs() -> None:
    """Baselines on both setups, 12 scans, in-process vs a 2-process pool (~5 s)."""
    kw = {"methods": ("icp", "lines"), "max_scans": 12, "out_dir": None, "progress": False}
    one = run_experiment(jobs=1, **kw)
    two = run_experiment(jobs=2, **kw)
    assert set(one.runs) == set(two.runs) == {(s, m) for s in (1, 2) for m in ("icp", "lines")}
    for key, a in one.runs.items():
        assert np.array_equal(a.estimates, two.runs[key].estimates), key
        assert a.statuses == two.runs[key].statuses


def test_cli_arguments_and_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    argv = ["--setup", "1", "--method", "icp", "--method", "lines", "--max-scans", "5"]
    argv += ["--out", str(tmp_path), "--no-plots", "--no-progress", "--jobs", "1"]
    args = parser.parse_args(argv)
    assert args.setup == [1] and args.method == ["icp", "lines"] and args.max_scans == 5
    assert run(args) == 0
    out = capsys.readouterr().out
    assert BLOCK_TITLES[1] in out and "line-based" in out
    assert (tmp_path / "results.csv").exists() and not (tmp_path / "setup1.png").exists()
    with pytest.raises(SystemExit):
        parser.parse_args(["--setup", "3"])
    tracker = run_experiment(
        setups=(2,), methods=("shape-tracker",), max_scans=4, out_dir=None, progress=False
    )
    assert "shape-based, tracker only" in tracker.table_text()
    assert tracker.runs[(2, "shape-tracker")].global_searches == 0
    with pytest.raises(LocalizationError, match="unknown method"):
        run_experiment(methods=("magic",), out_dir=None, progress=False)
    with pytest.raises(LocalizationError, match="max_scans"):
        run_experiment(max_scans=0, out_dir=None, progress=False)


def test_module_entry_point_parses_arguments() -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "sim_publisher.experiment", "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    for opt in ("--setup", "--method", "--seed", "--max-scans", "--out", "--jobs", "--no-plots"):
        assert opt in proc.stdout


def test_shapeloc_sim_experiment_delegates_its_arguments(monkeypatch) -> None:
    """``shapeloc-sim experiment ...`` parses the experiment's options and runs
    :func:`sim_publisher.experiment.main` with them (no Zenoh involved)."""
    from sim_publisher import experiment
    from sim_publisher.__main__ import cli as sim_cli

    seen = {}

    def fake_main(**kwargs) -> int:
        seen.update(kwargs)
        return 3

    monkeypatch.setattr(experiment, "main", fake_main)
    argv = ["experiment", "--setup", "2", "--method", "icp", "--max-scans", "7", "--no-plots"]
    assert sim_cli([*argv, "--out", "x/y"]) == 3
    assert seen == {
        "setups": (2,),
        "methods": ("icp",),
        "seed": 0,
        "max_scans": 7,
        "out": Path("x/y"),
        "progress": True,
        "jobs": 2,
        "plots": False,
        # the command the results page names repeats the run
        "command": "shapeloc-sim experiment --setup 2 --method icp --max-scans 7 --out x/y "
        "--no-plots",
    }
    with pytest.raises(SystemExit):
        sim_cli(["experiment", "--setup", "3"])
