"""The results pages' writer: provenance kept in a CSV row and read back, the header a page
carries (one run, several runs), commands without their output locations, Markdown tables."""

from __future__ import annotations

import math
import re
from pathlib import Path

from sim_publisher import results_page as rp
from sim_publisher.results_page import Provenance

MACHINE = "Test CPU, 2 cores; Python 3.11.7, numpy 2.4.6"


def _prov(command: str = "python -m bench.x --a 1", load: float = 1.5, **kw: object) -> Provenance:
    base = {"commit": "abc1234", "machine": MACHINE, "date": "2026-11-28"}
    base.update(kw)  # type: ignore[arg-type]
    return Provenance(command, load1=load, **base)  # type: ignore[arg-type]


def test_a_row_keeps_the_provenance_and_gives_it_back() -> None:
    prov = _prov(load=1.234).ended(3.5)
    row = prov.as_row()
    assert set(row) == set(rp.PROVENANCE_FIELDS)
    back = Provenance.from_row({"other": "x", **row})
    assert back == Provenance(prov.command, "abc1234", MACHINE, 1.23, "2026-11-28", 3.5)
    # a run that did not record its end
    assert math.isnan(Provenance.from_row(_prov().as_row()).load_end)


def test_a_row_without_provenance_takes_the_fallback_and_needs_one() -> None:
    old = {"command": "python -m bench.x", "commit": "0b1a718", "load1": "2.00"}
    fill = Provenance("", "", MACHINE, math.nan, "2026-11-27")
    got = Provenance.from_row(old, fill)
    assert (got.command, got.commit, got.machine, got.load1, got.date) == (
        "python -m bench.x",
        "0b1a718",
        MACHINE,
        2.0,
        "2026-11-27",
    )
    try:
        Provenance.from_row(old)
    except KeyError as e:
        assert "machine" in str(e)
    else:
        raise AssertionError("a row without a machine and no fallback was accepted")


def test_capture_describes_this_machine_and_commit() -> None:
    prov = Provenance.capture("python -m bench.x")
    assert re.fullmatch(r".+, \d+ cores?; Python \d+\.\d+\.\d+, numpy \S+", prov.machine)
    assert re.fullmatch(r"\d{4}-\d\d-\d\d", prov.date)
    assert prov.commit == "unknown" or re.fullmatch(
        r"[0-9a-f]{4,40}(\+diff-[0-9a-f]{8})?", prov.commit
    )
    assert math.isnan(prov.load_end) and math.isfinite(prov.ended().load_end)


def test_the_shown_command_leaves_out_where_the_output_goes() -> None:
    cmd = (
        "python -m bench.bench_real --methods shape --out /tmp/a --jobs 2 --cache=/tmp/c --no-plot"
    )
    assert rp.shown_command(cmd) == "python -m bench.bench_real --methods shape --jobs 2 --no-plot"
    assert (
        rp.shown_command("python -m bench.x --seeds '1, 2'") == "python -m bench.x --seeds '1, 2'"
    )
    call = "f(setups=(2,), methods=('shape', 'icp'))"  # not a shell command: kept as written
    assert rp.shown_command(call) == call


def test_one_run_gives_command_commit_machine_load_and_date() -> None:
    text = rp.page(
        "Title",
        "What is measured.",
        [(_prov(load=1.5).ended(4.25), "a"), (_prov(load=1.5).ended(4.25), "b")],
        ["| t |\n|---|\n| 1 |\n"],
    )
    assert text.splitlines()[:2] == ["# Title", ""]
    assert "- Command: `python -m bench.x --a 1`" in text
    assert "- Commit: abc1234" in text
    assert f"- Machine: {MACHINE}; load average 1.50 at start, 4.25 at the end" in text
    assert "- Date: 2026-11-28" in text
    assert text.endswith("| 1 |\n") and "\n\n\n" not in text


def test_several_runs_give_one_line_each_with_their_rows() -> None:
    runs = [
        (_prov("python -m bench.x --m shape --out /tmp/s", load=1.0), "shape"),
        (_prov("python -m bench.x --m shape --out /tmp/s", load=2.0), "shape"),
        (_prov("python -m bench.x --m icp", load=3.0, commit="def5678"), "icp"),
    ]
    block = rp.provenance_block(runs)
    assert block.splitlines() == [
        "- `python -m bench.x --m shape` (shape): commit abc1234, 2026-11-28, "
        "load average 1.00–2.00 at the runs' starts",
        "- `python -m bench.x --m icp` (icp): commit def5678, 2026-11-28, "
        "load average 3.00 at start",
        f"- Machine: {MACHINE}",
    ]


def test_a_table_escapes_pipes_and_a_page_is_written_whole(tmp_path: Path) -> None:
    table = rp.md_table(("a", "b|c"), [(1, "x|y"), (2.5, "z")])
    assert table.splitlines() == ["| a | b\\|c |", "|---|---|", "| 1 | x\\|y |", "| 2.5 | z |"]
    assert rp.fmt(float("nan"), ".1f") == "–" and rp.fmt("1.25", ".1f") == "1.2"
    path = rp.write_page(tmp_path / "sub" / "page.md", "# x\n")
    assert path.read_text() == "# x\n" and not list(path.parent.glob("*.tmp"))
