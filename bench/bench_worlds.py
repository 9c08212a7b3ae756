"""Generated buildings: every method on buildings it was not tuned on, writes
docs/results/worlds.md.

Seeds 0-19 are the **tuning** split, seeds >= 1000 the **held-out** split; the published page
is the held-out split. For each building (``sim_publisher.generator``) and each of the paper's
two setups -- 1: exact metric map, a scan every ~11 mm; 2: the building's schematic map
(furniture dropped, corners moved 2-10 cm, scale error up to +-2 %), every ~104 mm -- each
method tracks the whole tour from the true first pose, exactly as the paper's experiment does
on the office (no odometry), and with ``--odom`` also with the simulated odometry every scan
carries. Without odometry ``shape`` measures the motion between scans from the scans (its laser
odometry, :mod:`service.core.tracking.laser_odometry`); ``--methods shape-paper`` runs it as the
paper does, with no odometry of any kind (``bench/methods.py``).

Per setup, method and odometry mode, over the worlds of a split: the median, worst decile
(10th percentile) and worst world of the proximity test (the paper's: 100 mm / 45 deg on
setup 1, 500 mm / 45 deg on setup 2), the mean position error (median world), the share of
lost scans (median and worst world, and how many worlds lost any scan) and the share of
``tracking`` poses that fail the proximity test ("confident wrong", pooled over all worlds).
A figure of the worst world of each setup (shape method, no odometry) goes beside the table.

    python -m bench.bench_worlds                       # held-out seeds 1000-1023, 2 processes
    python -m bench.bench_worlds --split tuning        # seeds 0-19 (for tuning work)
    python -m bench.bench_worlds --odom --people 2     # also with odometry; moving people
    python -m bench.bench_worlds --methods icp,lines --odom-only --baseline-odom --update
                                                       # add the baselines' odometry rows
    python -m bench.bench_worlds --report-only --merge OTHER/results.csv
                                                       # the page again, with another run's rows

``--out DIR`` (default docs/results/worlds): the page ``DIR.md`` (overwritten; it names the
command, commit, machine and load of every row it shows), ``DIR/results.csv`` (one row per
tour, with its provenance) and ``DIR/worst_setup{1,2}.png``. ``--update`` keeps the earlier
rows of ``results.csv`` that this run does not repeat; ``--report-only`` runs nothing and
renders the page from ``results.csv`` (after merging the rows of ``--merge`` CSVs), drawing a
worst-world figure from the poses cached in ``--cache`` or, without them, by running that one
tour again. Uses no data outside the repository.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from bench.harness import REPO as ROOT
from sim_publisher import results_page as report
from sim_publisher.results_page import Provenance

SPLITS = {"tuning": list(range(0, 20)), "held-out": list(range(1000, 1024))}


@dataclass
class Run:
    """One tour of one method on one building."""

    seed: int
    setup: int
    method: str
    odom: bool
    scans: int
    proximity: float  # share of scans passing the proximity test
    mean_mm: float
    median_mm: float
    mean_deg: float
    lost: float  # share of scans with status "lost"
    tracking: int  # poses published as tracking
    wrong_tracking: int  # ... of which fail the proximity test
    ms_p50: float
    ms_p99: float
    building: str


@lru_cache(maxsize=4)
def generated_building(seed: int, people: int, clutter: float | None = None):
    """The generated building of ``seed`` (``clutter``: furniture density, default the
    generator's)."""
    from sim_publisher.generator import BuildingParams, generate_building

    extra = {} if clutter is None else {"clutter": clutter}
    return generate_building(seed, BuildingParams(people=people, **extra))


def run_one(
    seed: int, setup: int, method: str, odom: bool, people: int, max_scans: int | None
) -> tuple[Run, np.ndarray | None]:
    """Track one tour; returns the run's figures and (for ``shape``) the estimated poses."""
    from bench.methods import make_localizer
    from sim_publisher.scenario import building_setup

    b = generated_building(seed, people)
    s = building_setup(b, setup, seed=0, max_scans=max_scans)
    loc = make_localizer(method, s.map_data, s.reference[0])
    n = len(s)
    err = np.empty(n)
    deg = np.empty(n)
    ok = np.zeros(n, dtype=bool)
    lost = np.zeros(n, dtype=bool)
    trk = np.zeros(n, dtype=bool)
    ms = np.empty(n)
    poses = np.empty((n, 3))
    for i in range(n):
        r, a = s.scan(i)
        t0 = time.perf_counter()
        est = loc.update(r, a, s.odom[i] if odom else None)
        ms[i] = 1e3 * (time.perf_counter() - t0)
        t = s.reference[i]
        poses[i] = est.pose
        err[i] = 1e3 * math.hypot(est.pose[0] - t[0], est.pose[1] - t[1])
        deg[i] = math.degrees(abs((est.pose[2] - t[2] + math.pi) % (2 * math.pi) - math.pi))
        ok[i] = s.passed(i, est.pose)
        lost[i] = est.status == "lost"
        trk[i] = est.status == "tracking"
    run = Run(
        seed=seed,
        setup=setup,
        method=method,
        odom=odom,
        scans=n,
        proximity=float(ok.mean()),
        mean_mm=float(err.mean()),
        median_mm=float(np.median(err)),
        mean_deg=float(deg.mean()),
        lost=float(lost.mean()),
        tracking=int(trk.sum()),
        wrong_tracking=int((trk & ~ok).sum()),
        ms_p50=float(np.percentile(ms, 50)),
        ms_p99=float(np.percentile(ms, 99)),
        building=f"{b.name}",
    )
    return run, (poses if method == "shape" else None)


def _read_results(path: Path) -> list[Run]:
    """The runs of an earlier ``results.csv``."""
    out = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            kw = {}
            for name, field in Run.__dataclass_fields__.items():
                v = row[name]
                t = field.type
                if t in ("int", int):
                    kw[name] = int(v)
                elif t in ("float", float):
                    kw[name] = float(v)
                elif t in ("bool", bool):
                    kw[name] = v == "True"
                else:
                    kw[name] = v
            out.append(Run(**kw))
    return out


def _job(args: tuple) -> tuple[Run, np.ndarray | None]:
    return run_one(*args)


def summarise(runs: list[Run]) -> list[dict]:
    """One row per (setup, method, odom) over the worlds of ``runs``."""
    rows = []
    keys = sorted({(r.setup, r.method, r.odom) for r in runs}, key=lambda k: (k[0], k[2], k[1]))
    for setup, method, odom in keys:
        rs = [r for r in runs if (r.setup, r.method, r.odom) == (setup, method, odom)]
        prox = np.array([r.proximity for r in rs])
        worst = min(rs, key=lambda r: (r.proximity, -r.mean_mm))
        trk = sum(r.tracking for r in rs)
        wrong = sum(r.wrong_tracking for r in rs)
        rows.append(
            {
                "setup": setup,
                "method": method,
                "odometry": "yes" if odom else "no",
                "worlds": len(rs),
                "proximity_median": 100 * float(np.median(prox)),
                "proximity_worst_decile": 100 * float(np.percentile(prox, 10)),
                "proximity_worst": 100 * worst.proximity,
                "worst_world": worst.seed,
                "mean_mm_median_world": float(np.median([r.mean_mm for r in rs])),
                "lost_median": 100 * float(np.median([r.lost for r in rs])),
                "lost_worst": 100 * max(r.lost for r in rs),
                "worlds_with_lost": sum(r.lost > 0 for r in rs),
                "confident_wrong": 100 * wrong / trk if trk else 0.0,
                "ms_p50": float(np.median([r.ms_p50 for r in rs])),
                "ms_p99": float(np.median([r.ms_p99 for r in rs])),
            }
        )
    return rows


def table(rows: list[dict]) -> str:
    head = (
        "| setup | method | odometry | worlds | proximity median | worst decile | worst world "
        "| mean error, median world | lost: median / worst / worlds | confident wrong "
        "| ms p50 / p99 |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        lines.append(
            f"| {r['setup']} | {r['method']} | {r['odometry']} | {r['worlds']} "
            f"| {r['proximity_median']:.1f} % | {r['proximity_worst_decile']:.1f} % "
            f"| {r['proximity_worst']:.1f} % (seed {r['worst_world']}) "
            f"| {r['mean_mm_median_world']:.0f} mm "
            f"| {r['lost_median']:.2f} / {r['lost_worst']:.2f} % / {r['worlds_with_lost']} "
            f"| {r['confident_wrong']:.2f} % | {r['ms_p50']:.1f} / {r['ms_p99']:.1f} |"
        )
    return head + "\n".join(lines) + "\n"


def figure(run: Run, poses: np.ndarray, people: int, max_scans: int | None, path: Path) -> None:
    """Map, true path and the shape method's estimates of one world."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from sim_publisher.scenario import building_setup

    s = building_setup(generated_building(run.seed, people), run.setup, seed=0, max_scans=max_scans)
    fig, ax = plt.subplots(figsize=(8, 8))
    for p in s.map_data.polylines:
        ax.plot(p[:, 0], p[:, 1], "k-", lw=0.6)
    ax.plot(s.reference[:, 0], s.reference[:, 1], "g-", lw=1.0, label="true path")
    ax.plot(poses[:, 0], poses[:, 1], "r.", ms=1.5, label="shape estimates")
    ax.set_aspect("equal")
    ax.legend(loc="upper right", fontsize=8)
    ax.set_title(
        f"{run.building} setup {run.setup} ({'odometry' if run.odom else 'no odometry'}): "
        f"{100 * run.proximity:.1f} % proximity, {run.mean_mm:.0f} mm mean",
        fontsize=9,
    )
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


PARAGRAPH = (
    "Each method tracks the whole tour of every generated building of the {split} split"
    " ({n} worlds, seeds {first}-{last}{held}) from the true first pose, on the paper's two"
    " setups: 1, the exact metric map and a scan every ~11 mm; 2, the building's floor plan"
    " (furniture dropped, corners moved 2-10 cm, scale error up to ±2 %) and a scan every"
    " ~104 mm. Without odometry it is the paper's experiment; with odometry every scan carries"
    " the simulated wheel odometry. Per setup, method and odometry mode: the share of scans"
    " passing the paper's proximity test (100 mm / 45° on setup 1, 500 mm / 45° on setup 2) in"
    " the median world, the worst decile and the worst world; the mean position error of the"
    " median world; the share of `lost` scans (median world / worst world / worlds with any);"
    " the share of `tracking` poses failing the proximity test (confident wrong, over all"
    " worlds); the `update` call's time per scan (median over worlds). Moving people per"
    " building: {people}."
)
#: CSV columns beside the :class:`Run` fields.
EXTRA_FIELDS = ("people", *report.PROVENANCE_FIELDS)


def _poses_file(cache: Path, seed: int, setup: int, odom: bool) -> Path:
    return cache / f"shape_{seed}_s{setup}_{'odom' if odom else 'noodom'}.npy"


def write_results(path: Path, runs: list[tuple[Run, Provenance, int]]) -> None:
    """``results.csv``: one row per tour, with its provenance and moving people."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fields = [*Run.__dataclass_fields__, *EXTRA_FIELDS]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        for r, prov, people in sorted(runs, key=lambda x: _run_key(x[0])):
            w.writerow({**asdict(r), "people": people, **prov.as_row()})


def _run_key(r: Run) -> tuple[int, str, bool, int]:
    return (r.setup, r.method, r.odom, r.seed)


def read_results(path: Path, fallback: Provenance) -> list[tuple[Run, Provenance, int]]:
    """The runs of a ``results.csv`` with their provenance (``fallback`` for a CSV written
    before it kept one) and moving people."""
    runs = _read_results(path)
    with open(path, newline="") as f:
        extra = list(csv.DictReader(f))
    return [
        (r, Provenance.from_row(row, fallback), int(row.get("people") or 0))
        for r, row in zip(runs, extra, strict=True)
    ]


def split_of(seeds: list[int]) -> str:
    """The split the seeds belong to (:data:`SPLITS`: held-out seeds are >= 1000)."""
    if all(s >= 1000 for s in seeds):
        return "held-out"
    return "tuning" if all(s < 1000 for s in seeds) else "tuning and held-out"


def render(out: Path, runs: list[tuple[Run, Provenance, int]], cache: Path) -> Path:
    """The page ``out.md`` of ``runs`` with the worst worlds' figures (drawn from the poses in
    ``cache``, or by running those tours again); returns its path."""
    plain = [r for r, _, _ in runs]
    people = sorted({p for _, _, p in runs})
    rows = summarise(plain)
    text = table(rows)
    print(text)
    figs = []
    for setup in (1, 2):
        rs = [r for r in plain if r.method == "shape" and r.setup == setup and not r.odom]
        if not rs:
            continue
        worst = min(rs, key=lambda r: (r.proximity, -r.mean_mm))
        ppl = next(p for r, _, p in runs if r is worst)
        cached = _poses_file(cache, worst.seed, setup, False)
        if cached.exists():
            poses = np.load(cached)
        else:
            print(f"no cached poses of seed {worst.seed} setup {setup}: running that tour again")
            poses = run_one(worst.seed, setup, "shape", False, ppl, worst.scans)[1]
        name = f"worst_setup{setup}.png"
        figure(worst, poses, ppl, worst.scans, out / name)
        figs.append(f"{out.name}/{name}")
    seeds = sorted({r.seed for r in plain})
    split = split_of(seeds)
    held = ", not tuned on" if split == "held-out" else ""
    paragraph = PARAGRAPH.format(
        split=split,
        n=len(seeds),
        first=seeds[0],
        last=seeds[-1],
        held=held,
        people=", ".join(str(p) for p in people),
    )
    provs = [(prov, f"{r.method}{' + odometry' if r.odom else ''}") for r, prov, _ in runs]
    body = [text, *(f"![worst world of setup {f[-5]}]({f})" for f in figs)]
    title = f"Generated buildings, {split} split"
    return report.write_page(out.with_suffix(".md"), report.page(title, paragraph, provs, body))


def main(
    split: str,
    methods: list[str],
    odom: bool,
    people: int,
    jobs: int,
    out: Path,
    seeds: list[int] | None = None,
    max_scans: int | None = None,
    setups: tuple[int, ...] = (1, 2),
    odom_only: bool = False,
    update: bool = False,
    baseline_odom: bool = False,
    command: str = "",
    cache: Path | None = None,
) -> list[Run]:
    here = Provenance.capture(command or report.command_line("bench.bench_worlds", sys.argv[1:]))
    cache = cache if cache is not None else ROOT / "build" / "bench_worlds"
    cache.mkdir(parents=True, exist_ok=True)
    seeds = seeds if seeds is not None else SPLITS[split]
    modes = [True] if odom_only else ([False, True] if odom else [False])
    work = [
        (seed, setup, m, o, people, max_scans)
        for seed in seeds
        for setup in setups
        for m in methods
        for o in modes
        # odometry rows: the shape method only unless asked (time budget)
        if not (o and m != "shape" and not baseline_odom)
    ]
    # slow units first so the two processes finish together
    work.sort(key=lambda w: (w[2] != "shape", w[1] != 1))
    t0 = time.perf_counter()
    runs: list[Run] = []
    with ProcessPoolExecutor(max_workers=jobs) as ex:
        for k, (run, p) in enumerate(ex.map(_job, work, chunksize=1)):
            runs.append(run)
            if p is not None:
                np.save(_poses_file(cache, run.seed, run.setup, run.odom), p)
            print(
                f"[{k + 1}/{len(work)}] seed {run.seed} setup {run.setup} {run.method:5s} "
                f"odom={int(run.odom)}: {100 * run.proximity:5.1f} % "
                f"{run.mean_mm:7.1f} mm lost {100 * run.lost:.2f} % "
                f"wrong {run.wrong_tracking} ({time.perf_counter() - t0:.0f} s)",
                flush=True,
            )
    wall = time.perf_counter() - t0
    print(f"{len(runs)} runs in {wall:.0f} s wall with {jobs} processes (load {os.getloadavg()})")
    here = here.ended()
    done = [(r, here, people) for r in runs]
    csv_path = out / "results.csv"
    if update and csv_path.exists():
        # keep the earlier runs this invocation did not repeat (same seed/setup/method/odom)
        fresh = {(r.seed, r.setup, r.method, r.odom) for r in runs}
        kept = [
            x
            for x in read_results(csv_path, here)
            if (x[0].seed, x[0].setup, x[0].method, x[0].odom) not in fresh
        ]
        print(f"--update: {len(kept)} earlier runs kept from {csv_path}")
        done += kept
    write_results(csv_path, done)
    page = render(out, done, cache)
    print(f"wrote {page} and {csv_path}")
    return runs


def report_only(out: Path, merge: list[Path], cache: Path, command: str) -> Path:
    """Render the page from ``out/results.csv`` after merging the runs of the ``merge`` CSVs
    into it (a run replaces the one of the same seed, setup, method and odometry)."""
    here = Provenance.capture(command)
    csv_path = out / "results.csv"
    runs = read_results(csv_path, here) if csv_path.exists() else []
    for extra in merge:
        # a CSV written before the rows kept their machine and date: the same machine renders
        # it, on the day the file was last written
        written = time.strftime("%Y-%m-%d", time.gmtime(extra.stat().st_mtime))
        fill = Provenance("", "", here.machine, math.nan, written)
        more = read_results(extra, fill)
        fresh = {_run_key(r) for r, _, _ in more}
        runs = [x for x in runs if _run_key(x[0]) not in fresh] + more
        print(f"merged {len(more)} runs of {extra}")
    if not runs:
        raise SystemExit(f"{csv_path}: no runs to render")
    if merge:
        write_results(csv_path, runs)
    return render(out, runs, cache)


def cli(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--split", choices=sorted(SPLITS), default="held-out")
    p.add_argument("--seeds", type=str, default=None, help="comma list, overrides --split")
    p.add_argument("--methods", default="shape,icp,lines")
    p.add_argument("--odom", action="store_true", help="also run shape with odometry")
    p.add_argument("--people", type=int, default=0, help="moving people per building")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--max-scans", type=int, default=None, help="truncate tours (quick runs)")
    p.add_argument(
        "--out",
        type=Path,
        default=ROOT / "docs" / "results" / "worlds",
        help="results.csv and figures go in OUT, the page is OUT.md",
    )
    p.add_argument("--cache", type=Path, default=ROOT / "build" / "bench_worlds")
    p.add_argument("--setups", default="1,2", help="comma list of setups to run")
    p.add_argument("--odom-only", action="store_true", help="only the odometry rows")
    p.add_argument(
        "--update",
        action="store_true",
        help="merge into the existing results.csv: rows not rerun are kept in the table",
    )
    p.add_argument(
        "--baseline-odom", action="store_true", help="odometry rows for icp and lines too"
    )
    p.add_argument(
        "--report-only",
        action="store_true",
        help="run nothing: render the page from OUT/results.csv",
    )
    p.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        default=[],
        metavar="CSV",
        help="with --report-only: first merge these results.csv into OUT/results.csv",
    )
    raw = sys.argv[1:] if argv is None else argv
    a = p.parse_args(argv)
    command = report.command_line("bench.bench_worlds", raw)
    if a.merge and not a.report_only:
        raise SystemExit("--merge goes with --report-only")
    if a.report_only:
        page = report_only(a.out, a.merge, a.cache, command)
        print(f"wrote {page}")
        return
    seeds = [int(x) for x in a.seeds.split(",")] if a.seeds else None
    setups = tuple(int(x) for x in a.setups.split(","))
    main(
        a.split,
        a.methods.split(","),
        a.odom,
        a.people,
        a.jobs,
        a.out,
        seeds,
        a.max_scans,
        setups,
        a.odom_only,
        a.update,
        a.baseline_odom,
        command,
        a.cache,
    )


if __name__ == "__main__":
    cli()
