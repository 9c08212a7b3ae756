"""The paper's experiment (section 6, Table 1, Fig. 7/8) re-run on our simulated office.

For each setup (1: exact metric map, scans every ~11 mm; 2: schematic floor plan, scans every
~104 mm) and each method (``shape``, ``icp``, ``lines``) a fresh localiser is created with the
true first pose as its initial pose (as in the paper) and fed every simulated scan in order.
The methods never see ground truth afterwards and get no odometry (the paper's baselines start
each scan from their previous estimate; ``shape`` measures the motion between scans from the
scans themselves, its laser odometry, as the service does for a robot without odometry;
``shape-paper`` is ``shape`` without it, the paper's own mode). Per scan the position error
(metres) and the heading error (radians) against the true pose are recorded; the summary is the
mean errors and the proximity test: setup 1 passes below 100 mm and 45 degrees, setup 2 below
500 mm and 45 degrees.

``shapeloc-sim experiment`` (or ``python -m sim_publisher.experiment``) runs it from the command
line; :func:`main` (prints the table) or :func:`run_experiment` (returns the numbers) from
Python. Outputs (``--out DIR``, default ``docs/results/experiment``): the results page
``DIR.md`` (overwritten on each run), ``DIR/results.csv`` and ``DIR/setup1.png`` /
``DIR/setup2.png`` (one panel per method: map, true path, estimates).

The package: :mod:`.results` (the paper's numbers, :class:`MethodRun`,
:class:`ExperimentResult` and its table, CSV and Markdown), :mod:`.runner` (:func:`run_method`,
:func:`run_experiment`, the process pool), :mod:`.output` (:func:`write_outputs`,
:func:`plot_setup`); this module holds the command line and re-exports the public names.
"""

from __future__ import annotations

import argparse
import shlex
import sys
from collections.abc import Sequence
from pathlib import Path

from service.errors import ShapelocError
from sim_publisher.experiment.output import plot_setup, write_outputs
from sim_publisher.experiment.results import (
    BLOCK_TITLES,
    EXPERIMENT_METHODS,
    METHOD_NAMES,
    METHOD_ORDER,
    PAPER_TABLE,
    PROXIMITY,
    TABLE_COLUMNS,
    ExperimentResult,
    MethodRun,
    SetupInfo,
)
from sim_publisher.experiment.runner import run_experiment, run_method

__all__ = [
    "BLOCK_TITLES",
    "EXPERIMENT_METHODS",
    "METHOD_NAMES",
    "METHOD_ORDER",
    "PAPER_TABLE",
    "PROXIMITY",
    "TABLE_COLUMNS",
    "ExperimentResult",
    "MethodRun",
    "SetupInfo",
    "add_arguments",
    "cli",
    "main",
    "plot_setup",
    "run",
    "run_experiment",
    "run_method",
    "write_outputs",
]


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
        help="method to run (repeatable; default shape, icp, lines; shape-paper = shape "
        "without its laser odometry, the paper's mode; shape-tracker = the shape "
        "tracker without global search)",
    )
    parser.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    parser.add_argument(
        "--max-scans", type=int, default=None, metavar="N", help="only the first N scans"
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("docs/results/experiment"),
        help="CSV and figures go in OUT, the results page is OUT.md",
    )
    parser.add_argument("--jobs", type=int, default=2, help="worker processes (default 2)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    parser.add_argument("--no-plots", action="store_true", help="skip the PNG figures")


def main(
    setups: Sequence[int] = (1, 2),
    methods: Sequence[str] = ("shape", "icp", "lines"),
    seed: int = 0,
    max_scans: int | None = None,
    out: Path = Path("docs/results/experiment"),
    progress: bool = True,
    jobs: int = 2,
    plots: bool = True,
    command: str | None = None,
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
            command=command,
        )
    except ShapelocError as exc:
        print(f"experiment failed: {exc}", file=sys.stderr)
        return 1
    print(result.table_text(), end="")
    print(f"wall time {result.wall_seconds:.1f} s; outputs in {out} and {out.with_suffix('.md')}")
    return 0


def run(args: argparse.Namespace, prog: str = "shapeloc-sim experiment") -> int:
    """:func:`main` with arguments parsed by a parser that :func:`add_arguments` filled;
    ``prog`` starts the command line the results page names."""
    return main(
        setups=tuple(args.setup or (1, 2)),
        methods=tuple(args.method or ("shape", "icp", "lines")),
        seed=args.seed,
        max_scans=args.max_scans,
        out=args.out,
        progress=not args.no_progress,
        jobs=args.jobs,
        plots=not args.no_plots,
        command=command_line(args, prog),
    )


def command_line(args: argparse.Namespace, prog: str) -> str:
    """The command line that repeats a run of ``args``: ``prog`` and every option that is
    not at its default (progress display left out), in a fixed order."""
    parts = [prog]
    for s in args.setup or ():
        parts += ["--setup", str(s)]
    for m in args.method or ():
        parts += ["--method", m]
    if args.seed != 0:
        parts += ["--seed", str(args.seed)]
    if args.max_scans is not None:
        parts += ["--max-scans", str(args.max_scans)]
    if args.out != Path("docs/results/experiment"):
        parts += ["--out", str(args.out)]
    if args.jobs != 2:
        parts += ["--jobs", str(args.jobs)]
    if args.no_plots:
        parts.append("--no-plots")
    return " ".join([prog, shlex.join(parts[1:])]) if parts[1:] else prog


def cli(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``python -m sim_publisher.experiment`` (same options as
    ``shapeloc-sim experiment``)."""
    parser = argparse.ArgumentParser(
        prog="python -m sim_publisher.experiment", description=__doc__.splitlines()[0]
    )
    add_arguments(parser)
    return run(parser.parse_args(argv), "python -m sim_publisher.experiment")
