"""The paper's experiment (section 6, Table 1, Fig. 7/8) re-run on our simulated office.

For each setup (1: exact metric map, scans every ~11 mm; 2: schematic floor plan, scans every
~104 mm) and each method (``shape``, ``icp``, ``lines``) a fresh localiser is created with the
true first pose as its initial pose (as in the paper) and fed every simulated scan in order.
The methods never see ground truth afterwards and get no odometry (the paper's baselines start
each scan from their previous estimate). Per scan the position error (metres) and the heading
error (radians) against the true pose are recorded; the summary is the mean errors and the
proximity test: setup 1 passes below 100 mm and 45 degrees, setup 2 below 500 mm and 45
degrees.

``shapeloc-sim experiment`` (or ``python -m sim_publisher.experiment``) runs it from the command
line; :func:`main` (prints the table) or :func:`run_experiment` (returns the numbers) from
Python. Outputs (``--out``, default ``docs/experiment``): ``results.csv``, ``table.md`` and
``setup1.png`` / ``setup2.png`` (one panel per method: map, true path, estimates).
"""

from __future__ import annotations

import argparse
import csv
import math
import multiprocessing as mp
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from service.core.types import METHODS, wrap_angle
from service.errors import LocalizationError, ShapelocError
from sim_publisher.plot import plot_map, plot_path
from sim_publisher.scenario import Setup, make_setup, run_stats

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
#: The service's methods plus ``shape-tracker``: the shape tracker alone (no global search
#: after a loss), closest to the paper's SBL; not part of the default run.
EXPERIMENT_METHODS: tuple[str, ...] = (*METHODS, "shape-tracker")
METHOD_NAMES = {
    "icp": "ICP",
    "lines": "line-based",
    "shape": "shape-based",
    "shape-tracker": "shape-based, tracker only",
}
#: Paper's row order in Table 1.
METHOD_ORDER = ("icp", "lines", "shape", "shape-tracker")
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
#: Relative cost per scan used only to start the slowest runs first.
_COST = {"shape": 6.0, "shape-tracker": 6.0, "icp": 1.0, "lines": 1.0}


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

    def markdown(self) -> str:
        """``table.md``: the table plus how it was produced."""
        lines = [
            "# Table 1 reproduced (generated by `shapeloc-sim experiment`)",
            "",
            f"Seed {self.seed}; "
            + ("full runs" if self.max_scans is None else f"first {self.max_scans} scans")
            + f"; wall time {self.wall_seconds:.0f} s (2-core machine shared with other jobs, "
            "so ms/scan is noisy). Every method starts at the true first pose and then sees only "
            "the scans (no odometry, no ground truth).",
            "",
        ]
        for s in sorted(self.setups):
            i = self.setups[s]
            lines.append(
                f"- setup {s} ({i.name}): path {i.path_length_m:.2f} m, {i.scans} scans, "
                f"mean step {i.mean_step_mm:.0f} mm, mean rotation {i.mean_rotation_deg:.1f} deg"
            )
        lines += ["", self.table_text(), *_NOTES]
        for (s, m), r in sorted(self.runs.items()):
            lines.append(
                f"- setup {s}, {METHOD_NAMES.get(m, m)}: reported itself lost on "
                f"{r.lost_pct:.1f}% of the scans; global searches: {r.global_searches}; "
                f"failed updates: {r.failures}."
            )
        lines.append("")
        return "\n".join(lines)


_NOTES = (
    "## How the methods were run",
    "",
    "- **shape-based**: what `service.core.factory.create_localizer('shape', ...)` returns "
    "(the shape tracker with its default configuration for the map kind, wrapped in the "
    "global search that takes over after the tracker declares itself lost).",
    "- **ICP** (`service.core.baselines.icp`, Besl & McKay on an occupancy grid as in the "
    "paper): 50 mm cells rasterised exactly from the map polylines, nearest occupied cell "
    "centres from a precomputed distance transform, a pair-distance gate shrinking from 1.0 m "
    "to 0.2 m, closed-form rigid least squares per iteration, at most 40 iterations.",
    "- **line-based** (`service.core.baselines.lines`, after Cox / Lu & Milios / Gutmann): "
    "split-and-merge scan lines (4 cm split threshold, >= 6 points, >= 0.3 m), map lines from "
    "merged collinear polyline edges, nearest-line association within orientation (15 -> 5 "
    "deg) and perpendicular-distance (0.5 -> 0.2 m) gates, damped point-to-line least squares.",
    "- Both baselines start every scan from their previous estimate, as in the paper; neither "
    "uses odometry (their `use_odometry` flag stays off).",
    "",
)


def _pipe_row(cells: Sequence[str], widths: Sequence[int]) -> str:
    first = f" {cells[0]:<{widths[0]}} "
    rest = [f" {c:>{w}} " for c, w in zip(cells[1:], widths[1:], strict=True)]
    return "|" + "|".join([first, *rest]) + "|"


def run_method(
    setup_obj: Any,
    setup_id: int,
    method: str,
    progress: Callable[[int], None] | None = None,
) -> MethodRun:
    """Run one method over all scans of one setup (``sim_publisher.scenario.Setup``)."""
    from service.core.factory import create_localizer

    truth = np.asarray(setup_obj.truth, dtype=np.float64)
    n = len(truth)
    if method == "shape-tracker":
        from service.core.localizer import ShapeLocalizer

        loc: Any = ShapeLocalizer(setup_obj.map_data, truth[0].copy(), None)
    else:
        loc = create_localizer(method, setup_obj.map_data, truth[0].copy(), None)
    est = np.empty((n, 3), dtype=np.float64)
    statuses: list[str] = []
    seconds = 0.0
    failures = 0
    last = truth[0].copy()
    for i in range(n):
        ranges, angles = setup_obj.scan(i)
        t0 = time.perf_counter()
        try:
            e = loc.update(ranges, angles)
        except LocalizationError:
            failures += 1
            seconds += time.perf_counter() - t0
            est[i] = last
            statuses.append("lost")
        else:
            seconds += time.perf_counter() - t0
            last = np.asarray(e.pose, dtype=np.float64)
            est[i] = last
            statuses.append(str(e.status))
        if progress is not None and (i % 20 == 19 or i == n - 1):
            progress(i % 20 + 1)
    pos_err = np.hypot(est[:, 0] - truth[:, 0], est[:, 1] - truth[:, 1])
    head_err = np.abs(np.asarray(wrap_angle(est[:, 2] - truth[:, 2]), dtype=np.float64))
    searches = int(getattr(loc, "searches", 0) or 0)
    return MethodRun(
        setup_id, method, est, pos_err, head_err, tuple(statuses), seconds, failures, searches
    )


def _make_setup(setup_id: int, seed: int, max_scans: int | None) -> Setup:
    return make_setup(setup_id, seed=seed, max_scans=max_scans)


_COUNTER: Any = None


def _init_worker(counter: Any) -> None:
    global _COUNTER  # set once per worker process by the pool initializer
    _COUNTER = counter


def _bump(k: int) -> None:
    if _COUNTER is not None:
        with _COUNTER.get_lock():
            _COUNTER.value += k


def _worker(setup_id: int, method: str, seed: int, max_scans: int | None) -> MethodRun:
    return run_method(_make_setup(setup_id, seed, max_scans), setup_id, method, _bump)


class _Bar:
    """A one-line text progress bar on stderr."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.total = max(total, 1)
        self.enabled = enabled
        self.t0 = time.perf_counter()

    def show(self, done: int, note: str = "") -> None:
        if not self.enabled:
            return
        frac = min(done / self.total, 1.0)
        filled = round(30 * frac)
        el = time.perf_counter() - self.t0
        sys.stderr.write(
            f"\r[{'#' * filled}{'.' * (30 - filled)}] {done}/{self.total} scans {el:5.0f} s {note}"[
                :110
            ].ljust(110)
        )
        sys.stderr.flush()

    def close(self) -> None:
        if self.enabled:
            sys.stderr.write("\n")
            sys.stderr.flush()


def run_experiment(
    setups: Sequence[int] = (1, 2),
    methods: Sequence[str] = ("shape", "icp", "lines"),
    seed: int = 0,
    max_scans: int | None = None,
    out_dir: Path | None = Path("docs/experiment"),
    progress: bool = True,
    jobs: int = 2,
    plots: bool = True,
) -> ExperimentResult:
    """Run every ``method`` on every ``setup`` and write the results to ``out_dir``.

    ``max_scans`` shortens each run to its first scans. ``jobs`` > 1 runs the
    (setup, method) pairs in a process pool; results do not depend on it. ``out_dir`` ``None``
    writes nothing. Raises :class:`LocalizationError` for an unknown setup or method.
    """
    setups = tuple(dict.fromkeys(int(s) for s in setups))
    methods = tuple(dict.fromkeys(methods))
    for s in setups:
        if s not in PROXIMITY:
            raise LocalizationError(f"unknown setup {s}; expected 1 or 2")
    for m in methods:
        if m not in EXPERIMENT_METHODS:
            raise LocalizationError(
                f"unknown method {m!r}; expected one of {', '.join(EXPERIMENT_METHODS)}"
            )
    if not setups or not methods:
        raise LocalizationError("nothing to run: no setup or no method selected")
    if max_scans is not None and max_scans < 1:
        raise LocalizationError(f"max_scans must be >= 1, got {max_scans}")
    t_start = time.perf_counter()
    setup_objs = {s: _make_setup(s, seed, max_scans) for s in setups}
    infos = {s: _setup_info(s, o) for s, o in setup_objs.items()}
    result = ExperimentResult(seed=seed, max_scans=max_scans, setups=infos)
    tasks = [(s, m) for s in setups for m in methods]
    tasks.sort(key=lambda t: -infos[t[0]].scans * _COST.get(t[1], 1.0))
    total = sum(infos[s].scans for s, _ in tasks)
    bar = _Bar(total, progress)
    if jobs <= 1 or len(tasks) == 1:
        done = 0

        def tick(k: int) -> None:
            nonlocal done
            done += k
            bar.show(done)

        for s, m in tasks:
            result.runs[(s, m)] = run_method(setup_objs[s], s, m, tick)
    else:
        # fork where the platform has it (workers only run numpy code, and a script calling
        # run_experiment needs no __main__ guard); spawn elsewhere.
        method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
        ctx = mp.get_context(method)
        counter = ctx.Value("q", 0)
        with ProcessPoolExecutor(
            max_workers=min(jobs, len(tasks)),
            mp_context=ctx,
            initializer=_init_worker,
            initargs=(counter,),
        ) as pool:
            futs: dict[Future, tuple[int, str]] = {
                pool.submit(_worker, s, m, seed, max_scans): (s, m) for s, m in tasks
            }
            pending = set(futs)
            while pending:
                finished, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                for f in finished:
                    result.runs[futs[f]] = f.result()
                bar.show(int(counter.value), f"{len(result.runs)}/{len(tasks)} runs done")
    bar.close()
    result.wall_seconds = time.perf_counter() - t_start
    if out_dir is not None:
        write_outputs(result, Path(out_dir), setup_objs if plots else None)
    return result


def _setup_info(setup_id: int, obj: Setup) -> SetupInfo:
    st = run_stats(obj.truth)
    return SetupInfo(
        setup=setup_id,
        name=str(getattr(obj, "name", f"setup {setup_id}")),
        map_id=obj.map_data.map_id,
        map_kind=obj.map_data.kind,
        scans=len(obj.truth),
        path_length_m=float(st["path_length_m"]),
        mean_step_mm=float(st["mean_step_mm"]),
        mean_rotation_deg=float(st["mean_rotation_deg"]),
    )


def write_outputs(result: ExperimentResult, out_dir: Path, setup_objs: dict | None) -> list[Path]:
    """Write ``results.csv``, ``table.md`` and (if ``setup_objs`` is given) one PNG per setup
    into ``out_dir``; returns the written paths."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / "results.csv", out_dir / "table.md"]
    result.write_csv(paths[0])
    paths[1].write_text(result.markdown(), encoding="utf-8")
    if setup_objs is not None:
        for s, obj in setup_objs.items():
            paths.append(plot_setup(result, s, obj, out_dir / f"setup{s}.png"))
    return paths


def plot_setup(result: ExperimentResult, setup_id: int, setup_obj: Any, path: Path) -> Path:
    """One panel per method: the map, the true path and that method's estimates (like the
    paper's Fig. 7 and 8). Needs matplotlib (imported here, Agg backend)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    methods = result.ordered_methods(setup_id)
    fig, axes = plt.subplots(1, len(methods), figsize=(4.2 * len(methods), 6.5), squeeze=False)
    truth = np.asarray(setup_obj.truth)
    for ax, m in zip(axes[0], methods, strict=True):
        r = result.runs[(setup_id, m)]
        plot_map(ax, setup_obj.map_data, color="0.3", linewidth=0.7)
        plot_path(ax, truth, color="k", linewidth=1.0, label="true path")
        ax.plot(
            r.estimates[:, 0], r.estimates[:, 1], ".", color="tab:red", markersize=1.5,
            label="estimates",
        )  # fmt: skip
        ax.set_title(
            f"{METHOD_NAMES.get(m, m)}: {r.mean_position_mm:.0f} mm, "
            f"{r.proximity_pct:.0f}% proximity",
            fontsize=9,
        )
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend(loc="upper right", fontsize=7, markerscale=4)
    fig.suptitle(f"setup {setup_id}: {BLOCK_TITLES.get(setup_id, '')}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the experiment's options to ``parser`` (``shapeloc-sim experiment`` and
    ``python -m sim_publisher.experiment``)."""
    parser.add_argument(
        "--setup", type=int, choices=(1, 2), action="append", help="setup to run (repeatable)"
    )
    parser.add_argument(
        "--method",
        choices=EXPERIMENT_METHODS,
        action="append",
        help="method to run (repeatable; default shape, icp, lines; shape-tracker = the shape "
        "tracker without global search)",
    )
    parser.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    parser.add_argument(
        "--max-scans", type=int, default=None, metavar="N", help="only the first N scans"
    )
    parser.add_argument(
        "--out", type=Path, default=Path("docs/experiment"), help="output directory"
    )
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG figures")


def main(
    setups: Sequence[int] = (1, 2),
    methods: Sequence[str] = ("shape", "icp", "lines"),
    seed: int = 0,
    max_scans: int | None = None,
    out: Path = Path("docs/experiment"),
    progress: bool = True,
    jobs: int = 2,
    plots: bool = True,
) -> int:
    """Run the experiment (see :func:`run_experiment`), print the table; returns the exit
    code (1 with a one-line message on stderr if the run fails)."""
    try:
        result = run_experiment(
            setups=setups,
            methods=methods,
            seed=seed,
            max_scans=max_scans,
            out_dir=out,
            progress=progress,
            jobs=jobs,
            plots=plots,
        )
    except ShapelocError as exc:
        print(f"experiment failed: {exc}", file=sys.stderr)
        return 1
    print(result.table_text(), end="")
    print(f"wall time {result.wall_seconds:.1f} s; outputs in {out}")
    return 0


def run(args: argparse.Namespace) -> int:
    """:func:`main` with arguments parsed by a parser that :func:`add_arguments` filled."""
    return main(
        setups=tuple(args.setup or (1, 2)),
        methods=tuple(args.method or ("shape", "icp", "lines")),
        seed=args.seed,
        max_scans=args.max_scans,
        out=args.out,
        progress=not args.no_progress,
        jobs=args.jobs,
        plots=not args.no_plots,
    )


def cli(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m sim_publisher.experiment`` (same options as
    ``shapeloc-sim experiment``)."""
    parser = argparse.ArgumentParser(
        prog="python -m sim_publisher.experiment", description=__doc__.splitlines()[0]
    )
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(cli())
