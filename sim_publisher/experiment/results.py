"""Result types and formatting of the Table-1 experiment.

The paper's numbers (:data:`PAPER_TABLE`), the proximity test per setup (:data:`PROXIMITY`),
the methods and their display names and order; :class:`MethodRun` (one method on one setup,
with its summary statistics), :class:`SetupInfo` and :class:`ExperimentResult` (all runs, with
the pipe table, the CSV rows and ``table.md``).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service.core.types import METHODS
from sim_publisher import results_page
from sim_publisher.results_page import Provenance

#: Table 1 of the paper: (position error mm, heading error deg, proximity test %).
PAPER_TABLE: dict[int, dict[str, tuple[float, float, float]]] = {
    1: {"icp": (534.0, 1.5, 21.0), "lines": (5167.0, 65.0, 0.4), "shape": (144.0, 1.21, 78.0)},
    2: {"icp": (2234.0, 25.9, 50.0), "lines": (1836.0, 16.6, 30.0), "shape": (553.0, 3.3, 86.0)},
}
#: Proximity test per setup: (max position error m, max heading error rad).
PROXIMITY: dict[int, tuple[float, float]] = {
    1: (0.100, math.radians(45.0)),
    2: (0.500, math.radians(45.0)),
}
BLOCK_TITLES = {1: "map-based SL", 2: "SL using schematized map"}
#: The service's methods plus ``shape-paper``: ``shape`` without its laser odometry (the
#: motion between scans measured from the scans, service.core.tracking.laser_odometry), the seed
#: paper's own mode; and ``shape-tracker``: the shape tracker alone (no global search after a
#: loss, no laser odometry), closest to the paper's SBL. Neither is part of the default run.
EXPERIMENT_METHODS: tuple[str, ...] = (*METHODS, "shape-paper", "shape-tracker")
METHOD_NAMES = {
    "icp": "ICP",
    "lines": "line-based",
    "shape": "shape-based",
    "shape-paper": "shape-based, paper's mode",
    "shape-tracker": "shape-based, tracker only",
}
#: Paper's row order in Table 1.
METHOD_ORDER = ("icp", "lines", "shape", "shape-paper", "shape-tracker")
TABLE_COLUMNS = (
    "method",
    "position [mm]",
    "heading [deg]",
    "proximity test [%]",
    "paper position [mm]",
    "paper heading [deg]",
    "paper proximity [%]",
    "ms/scan",
)


@dataclass
class MethodRun:
    """One method on one setup.

    ``estimates`` ``(n, 3)`` map-frame poses, ``position_error`` ``(n,)`` metres,
    ``heading_error`` ``(n,)`` radians (absolute), ``statuses`` the reported status per scan,
    ``seconds`` the summed wall time of the ``update`` calls, ``failures`` the number of scans
    whose update raised :class:`LocalizationError` (the previous estimate is kept for them),
    ``global_searches`` the scans on which the localiser ran a global search (only ``shape``
    has one: it re-localises without a prior after declaring itself lost).
    """

    setup: int
    method: str
    estimates: np.ndarray
    position_error: np.ndarray
    heading_error: np.ndarray
    statuses: tuple[str, ...]
    seconds: float
    failures: int = 0
    global_searches: int = 0

    @property
    def scans(self) -> int:
        """Number of scans processed."""
        return len(self.position_error)

    @property
    def mean_position_mm(self) -> float:
        """Mean position error in millimetres."""
        return float(np.mean(self.position_error) * 1000.0)

    @property
    def mean_heading_deg(self) -> float:
        """Mean absolute heading error in degrees."""
        return float(np.degrees(np.mean(self.heading_error)))

    @property
    def proximity_pct(self) -> float:
        """Share of scans passing the setup's proximity test, in percent."""
        max_pos, max_head = PROXIMITY[self.setup]
        ok = (self.position_error < max_pos) & (self.heading_error < max_head)
        return float(100.0 * np.mean(ok))

    @property
    def ms_per_scan(self) -> float:
        """Mean wall time of one ``update`` in milliseconds (noisy: shared machine)."""
        return 1000.0 * self.seconds / max(self.scans, 1)

    @property
    def lost_pct(self) -> float:
        """Share of scans the method itself reported as ``lost``, in percent."""
        return float(100.0 * np.mean([s == "lost" for s in self.statuses]))


@dataclass
class SetupInfo:
    """What the table needs to know about a setup (from ``sim_publisher.scenario``)."""

    setup: int
    name: str
    map_id: str
    map_kind: str
    scans: int
    path_length_m: float
    mean_step_mm: float
    mean_rotation_deg: float


@dataclass
class ExperimentResult:
    """All runs of one experiment, keyed by ``(setup, method)``."""

    seed: int
    max_scans: int | None
    setups: dict[int, SetupInfo]
    runs: dict[tuple[int, str], MethodRun] = field(default_factory=dict)
    wall_seconds: float = 0.0
    #: How the run was started (command, commit, machine, load, date), for the page.
    provenance: Provenance | None = None

    def ordered_methods(self, setup: int) -> list[str]:
        """Methods run on ``setup`` in the paper's row order."""
        have = {m for (s, m) in self.runs if s == setup}
        return [m for m in METHOD_ORDER if m in have] + sorted(have - set(METHOD_ORDER))

    def rows(self, setup: int) -> list[list[str]]:
        """Table rows (strings) of one setup, columns as :data:`TABLE_COLUMNS`."""
        out = []
        for m in self.ordered_methods(setup):
            r = self.runs[(setup, m)]
            paper = PAPER_TABLE.get(setup, {}).get(m.split("-")[0])
            out.append(
                [
                    METHOD_NAMES.get(m, m),
                    f"{r.mean_position_mm:.0f}",
                    f"{r.mean_heading_deg:.2f}",
                    f"{r.proximity_pct:.1f}",
                    f"{paper[0]:.0f}" if paper else "-",
                    f"{paper[1]:g}" if paper else "-",
                    f"{paper[2]:g}" if paper else "-",
                    f"{r.ms_per_scan:.2f}",
                ]
            )
        return out

    def table_text(self) -> str:
        """Table 1 of the paper with our numbers (and the paper's alongside), one block per
        setup, as pipe tables (valid Markdown)."""
        parts = []
        for s in sorted(self.setups):
            info = self.setups[s]
            max_pos, max_head = PROXIMITY[s]
            parts.append(
                f"{BLOCK_TITLES.get(s, f'setup {s}')} (setup {s}: {info.map_kind} map "
                f"{info.map_id!r}, {info.scans} scans, proximity test < {max_pos * 1000:.0f} mm "
                f"and < {math.degrees(max_head):.0f} deg):"
            )
            parts.append("")
            widths = [max(len(c), 11) for c in TABLE_COLUMNS]
            rows = self.rows(s)
            for row in rows:
                widths = [max(w, len(c)) for w, c in zip(widths, row, strict=True)]
            parts.append(_pipe_row(TABLE_COLUMNS, widths))
            parts.append("|" + "|".join("-" * (w + 2) for w in widths) + "|")
            parts.extend(_pipe_row(row, widths) for row in rows)
            parts.append("")
        return "\n".join(parts).rstrip() + "\n"

    def write_csv(self, path: Path) -> None:
        """One row per (setup, method) with our numbers and the paper's."""
        with Path(path).open("w", newline="", encoding="utf-8") as fh:
            w = csv.writer(fh)
            w.writerow(
                [
                    "setup",
                    "map_kind",
                    "method",
                    "scans",
                    "position_mm",
                    "heading_deg",
                    "proximity_pct",
                    "lost_pct",
                    "failures",
                    "global_searches",
                    "ms_per_scan",
                    "paper_position_mm",
                    "paper_heading_deg",
                    "paper_proximity_pct",
                ]
            )
            for s in sorted(self.setups):
                for m in self.ordered_methods(s):
                    r = self.runs[(s, m)]
                    paper = PAPER_TABLE.get(s, {}).get(m.split("-")[0], (math.nan,) * 3)
                    w.writerow(
                        [
                            s,
                            self.setups[s].map_kind,
                            m,
                            r.scans,
                            f"{r.mean_position_mm:.1f}",
                            f"{r.mean_heading_deg:.3f}",
                            f"{r.proximity_pct:.2f}",
                            f"{r.lost_pct:.2f}",
                            r.failures,
                            r.global_searches,
                            f"{r.ms_per_scan:.3f}",
                            *paper,
                        ]
                    )

    def markdown(self, figures: Sequence[str] = ()) -> str:
        """The results page: what is measured, how it was produced, the table, the setups,
        what each method reported about itself, and the ``figures`` (relative paths)."""
        prov = self.provenance or Provenance.capture("sim_publisher.experiment.run_experiment")
        scans = "every scan" if self.max_scans is None else f"the first {self.max_scans} scans"
        paragraph = PARAGRAPH.format(seed=self.seed, scans=scans)
        setups = results_page.md_table(
            ("setup", "map", "scans", "path m", "mean step mm", "mean rotation deg"),
            (
                (
                    f"{s} ({i.name})",
                    f"{i.map_kind} {i.map_id!r}",
                    i.scans,
                    f"{i.path_length_m:.2f}",
                    f"{i.mean_step_mm:.0f}",
                    f"{i.mean_rotation_deg:.1f}",
                )
                for s, i in sorted(self.setups.items())
            ),
        )
        selves = results_page.md_table(
            ("setup", "method", "reported lost %", "global searches", "failed updates"),
            (
                (s, METHOD_NAMES.get(m, m), f"{r.lost_pct:.1f}", r.global_searches, r.failures)
                for (s, m), r in sorted(self.runs.items())
            ),
        )
        figs = [f"![setup {f[-5]}]({f})" for f in figures]
        title = "The paper's experiment (Table 1)"
        body = [self.table_text(), setups, selves, *figs]
        return results_page.page(title, paragraph, [(prov, "")], body)


PARAGRAPH = (
    "The seed paper's experiment (section 6, Table 1) on the simulated office, the world the"
    " methods were developed on (held-out worlds: [worlds.md](worlds.md)): setup 1 localises"
    " on the exact metric map with a scan every ~11 mm, setup 2 on the office's schematic floor"
    " plan with a scan every ~104 mm. Every method starts at the true first pose and then sees"
    " only the scans ({scans}; no odometry, no ground truth; simulation seed {seed}); the"
    " baselines, ICP on an occupancy grid (`service.core.baselines.icp`) and line-based"
    " matching (`service.core.baselines.lines`), start every scan from their previous estimate,"
    " as in the paper. Per method: the mean position and heading errors, the share of scans"
    " passing the paper's proximity test, the paper's figures beside ours, and the mean time of"
    " one `update` call."
)


def _pipe_row(cells: Sequence[str], widths: Sequence[int]) -> str:
    first = f" {cells[0]:<{widths[0]}} "
    rest = [f" {c:>{w}} " for c, w in zip(cells[1:], widths[1:], strict=True)]
    return "|" + "|".join([first, *rest]) + "|"
