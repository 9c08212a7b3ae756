"""Global localisation while driving WITHOUT odometry: the drive trials of
``bench_global.py --drive`` with every scan's odometry withheld, writes
docs/results/global_no_odometry.md.

Why a separate command: the drive benchmark feeds each scan with the tour's odometry (the
simulated one, or the real log's); a robot that sends none is localised by the same
``create_localizer("shape", map, None)``, whose laser odometry
(:mod:`service.core.tracking.laser_odometry`) then measures the motion between scans from the scans
themselves. Everything else -- maps, start scans, travel (true steps in simulation, the log's
odometry steps on real logs: a measure of the drive, never given to the localiser), scoring,
tables -- is the drive benchmark's own (see the docstring of ``bench_global.py``): the trials
run through ``global_drive_run.run_drive_trial`` with the tour's odometry replaced by ``None``.

    python -m bench.bench_global_laser [any option of bench_global --drive]
        [--out docs/results/global_no_odometry]

``--out DIR`` (default ``docs/results/global_no_odometry``): the page ``DIR.md`` (overwritten)
and one row per trial in ``DIR/results.csv``.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from bench import bench_global, global_drive_run
from bench.global_drive import DriveMap, DriveSource, DriveTask, DriveTrial, drive_source

__all__ = ["main", "run_trial_without_odometry", "source_without_odometry"]

REPO = Path(__file__).resolve().parents[1]
DEFAULT_OUT = REPO / "docs" / "results" / "global_no_odometry"


def source_without_odometry(m: DriveMap, data: Path, stride: int = 1) -> DriveSource:
    """The drive benchmark's tour of ``m`` with no odometry on any scan."""
    src = drive_source(m, data, stride)
    return dataclasses.replace(src, odom=lambda i: None)


def run_trial_without_odometry(task: DriveTask) -> DriveTrial:
    """One drive trial (``global_drive_run.run_drive_trial``) fed no odometry. Runs in the
    pool's processes: the tour source is replaced in the process that runs the trial."""
    global_drive_run.drive_source = source_without_odometry  # type: ignore[assignment]
    return _RUN(task)


_RUN = global_drive_run.run_drive_trial


def _page(out: Path) -> None:
    """The drive benchmark's ``drive.md`` / ``drive.csv`` under ``out`` as this benchmark's
    page ``out.md`` and ``out/results.csv``, saying that no odometry was fed."""
    md, csv_ = out / "drive.md", out / "drive.csv"
    text = md.read_text(encoding="utf-8")
    title, _, rest = text.partition("\n")
    text = f"{title}, without odometry\n{rest}"
    text = text.replace(
        "feeds every following scan with its odometry",
        "feeds every following scan WITHOUT odometry (`odom=None`: the localiser's laser "
        "odometry measures the motion between scans; `bench/bench_global_laser.py`)",
    )
    text = text.replace("python -m bench.bench_global ", "python -m bench.bench_global_laser ")
    out.with_suffix(".md").write_text(text, encoding="utf-8")
    csv_.replace(out / "results.csv")
    md.unlink()


def main(argv: list[str] | None = None) -> int:
    """Run the drive trials without odometry (options as ``bench_global --drive``)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if "--out" not in args:
        args += ["--out", str(DEFAULT_OUT)]
    out = Path(args[args.index("--out") + 1])
    global_drive_run.run_drive_trial = run_trial_without_odometry  # type: ignore[assignment]
    try:
        code = bench_global.main(["--drive", *args])
    finally:
        global_drive_run.run_drive_trial = _RUN  # type: ignore[assignment]
    if code == 0:
        _page(out)
        print(f"wrote {out.with_suffix('.md')} and {out / 'results.csv'}")
    return code


if __name__ == "__main__":
    sys.exit(main())
