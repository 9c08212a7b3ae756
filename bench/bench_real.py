"""Real-data benchmark (issue 11, part 5): every method on whole recorded laser logs.

READS /work/shared (not in a user's clone): the raw logs ``intel.orig.bag``, ``fr079.orig.bag``,
``mit-csail.clf``, their ``*.relations`` and the per-scan references
``corrected/*.gfs_reference_per_scan.txt`` under ``--data`` (default /work/shared/data/real; see
its README.md). The maps are the committed ``docs/real/maps/{log}.geojson`` (metric, drawn from
the log at its reference poses) and ``{log}_schematic.geojson`` (schematised), see
docs/maps.md.

intel and fr079 are the TUNING logs; mit-csail is HELD-OUT (nothing is tuned on it) and is
marked so in every table.

One run = (log, method ``shape | icp | lines``, odometry on/off, map metric/schematic): the
localiser starts at the first scan's reference pose (a laser pose in GMapping's map frame) and
gets every scan of the log (or the first ``--limit``), with the scan's laser odometry
(``odom=on``) or ``None`` (``odom=off``, the seed paper's mode). When ``shape`` loses the
track it searches the whole map again: by default one whole search on the scan at hand (the
published table), with ``--search-budget-ms B`` spread over scans within B reference ms per
scan, as the service runs it (its default 50; write those rows to another ``--out``). Per run:

- ``scored``: scans with a flag-1 (GMapping-corrected) reference; the errors below are the
  Euclidean distance (m) of the estimated laser position from it on those scans only (flag-0
  references are carried by odometry and not scored); ``<0.1``, ``<0.3``, ``<0.5``: % of
  scored scans within that distance; mean / median error (m).
- ``lost``: % of the scans after the first whose status is not ``tracking``.
- relations: Kümmerle et al.'s relations error of the whole estimated track (every scan's
  published pose, whatever its status, scored by :func:`service.adapters.logs.relations_error` at
  the scans' own stamps): translation mean ± std (m), rotation mean (deg); relations whose stamps
  fall outside a ``--limit`` run are skipped. The reference track's own figure is printed per
  log for comparison (intel 0.057, fr079 0.058, mit-csail 0.077 m; published RBPF 0.070, 0.061,
  0.049 m).
- ``ms p50`` / ``ms p99``: wall time of the ``update`` call alone (perf_counter), per scan.
  Timings are only meaningful with the machine's load beside them: the 1-minute load average is
  recorded per run. ``--jobs`` defaults to 1 so that one run at a time owns a core; with
  ``--jobs 2`` on this 2-core machine runs share it with each other (and other users).

Outputs (``--out``, default docs/real): the printed table, ``table.md`` (the table, the command
lines, git commits and loads that produced its rows), ``results.csv`` (one row per run; a rerun
replaces the row with the same log/method/odom/map/scans), and ``{log}.png`` per log: the metric
map's polylines in grey, the flag-1 reference path, the ``shape`` + odometry estimate on the
metric map, its non-tracking scans and its scored scans more than 0.3 m off marked. Each run's
estimated track is cached in ``--cache`` (default build/bench_real, git-ignored) for the
figures; ``--resume`` skips runs already in results.csv with the same scan count.

    .venv/bin/python -m bench.bench_real [--logs intel,fr079,mit-csail] [--methods shape,icp,lines]
        [--odom on,off] [--maps metric,schematic] [--limit N] [--jobs 1] [--resume]
        [--out docs/real] [--no-plot]
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import math
import os
import shlex
import subprocess
import sys
import time
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.results import publish

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = Path("/work/shared/data/real")
LOG_FILES = {"intel": "intel.orig.bag", "fr079": "fr079.orig.bag", "mit-csail": "mit-csail.clf"}
HELD_OUT = frozenset({"mit-csail"})
METHODS = ("shape", "icp", "lines")
MAPS = ("metric", "schematic")
#: Published Rao-Blackwellised particle filter relations errors (Kümmerle et al. 2009), m.
RBPF = {"intel": 0.070, "fr079": 0.061, "mit-csail": 0.049}
THRESHOLDS = (0.1, 0.3, 0.5)

FIELDS = [
    "log",
    "split",
    "method",
    "odom",
    "map",
    "limit",
    "scans",
    "scored",
    "within_0.1",
    "within_0.3",
    "within_0.5",
    "mean_m",
    "median_m",
    "lost_pct",
    "rel_trans_mean_m",
    "rel_trans_std_m",
    "rel_rot_mean_deg",
    "rel_used",
    "rel_skipped",
    "ms_p50",
    "ms_p99",
    "wall_s",
    "load1",
    "jobs",
    "commit",
    "command",
]
KEY = ("log", "method", "odom", "map", "limit")


@dataclass(frozen=True)
class Run:
    log: str
    method: str
    odom: bool
    map: str
    limit: int | None
    budget: float | None = None  # the shape method's global search budget (None: whole)

    def tag(self) -> str:
        lim = "all" if self.limit is None else str(self.limit)
        budget = "" if self.budget is None else f"_b{self.budget:g}"
        return (
            f"{self.log}_{self.method}_{'odom' if self.odom else 'noodom'}_{self.map}_{lim}{budget}"
        )


@dataclass
class LogData:
    """A log's scans as arrays, in log order."""

    stamps: np.ndarray  # (n,) s
    ranges: list[np.ndarray]  # metres, NaN = no return
    angles: list[np.ndarray]  # rad, laser frame
    odom: list[np.ndarray | None]  # laser odometry pose or None
    reference: np.ndarray  # (n, 3) laser pose in GMapping's map frame, NaN where none
    ok: np.ndarray  # (n,) bool: flag-1 reference


_LOGS: dict[tuple[str, int | None], LogData] = {}


def load_log(data: Path, name: str, limit: int | None) -> LogData:
    """Read (once per process) the log ``name`` with its per-scan references."""
    from service.adapters.logs import attach_reference, load_reference, read_log

    key = (name, limit)
    if key not in _LOGS:
        info, it = read_log(data / LOG_FILES[name], limit=limit)
        ref = load_reference(data / "corrected" / f"{name}.gfs_reference_per_scan.txt")
        scans = list(attach_reference(it, ref, scan_count=info.scan_count))
        nan3 = np.full(3, np.nan)
        _LOGS[key] = LogData(
            stamps=np.array([s.stamp for s in scans]),
            ranges=[np.asarray(s.ranges) for s in scans],
            angles=[s.angles for s in scans],
            odom=[None if s.odom is None else np.asarray(s.odom) for s in scans],
            reference=np.array([nan3 if s.reference is None else s.reference for s in scans]),
            ok=np.array([bool(s.reference_ok and s.reference is not None) for s in scans]),
        )
    return _LOGS[key]


def map_path(name: str, kind: str) -> Path:
    suffix = "" if kind == "metric" else "_schematic"
    return REPO / "docs" / "real" / "maps" / f"{name}{suffix}.geojson"


def execute(run: Run, data: Path) -> tuple[Run, np.ndarray, np.ndarray, np.ndarray, float]:
    """Run one localiser over the log; return the run, the estimated poses ``(n, 3)``, the
    tracking flags ``(n,)``, the ``update`` times ``(n,)`` (s) and the wall time (s)."""
    from service.adapters.maps.files import load_map_file
    from service.core.factory import create_localizer

    log = load_log(data, run.log, run.limit)
    kind = run.map
    m = load_map_file(map_path(run.log, kind), kind=kind)
    first = int(np.flatnonzero(np.all(np.isfinite(log.reference), axis=1))[0])
    if first != 0:
        raise SystemExit(f"{run.log}: the first scan has no reference pose")
    loc = create_localizer(run.method, m, log.reference[0].copy(), search_budget_ms=run.budget)
    n = len(log.ranges)
    poses = np.full((n, 3), np.nan)
    tracking = np.zeros(n, dtype=bool)
    times = np.zeros(n)
    clock = time.perf_counter
    t_start = clock()
    for i in range(n):
        odom = log.odom[i] if run.odom else None
        t0 = clock()
        est = loc.update(log.ranges[i], log.angles[i], odom)
        times[i] = clock() - t0
        poses[i] = est.pose
        tracking[i] = est.status == "tracking"
    return run, poses, tracking, times, clock() - t_start


def summarise(
    run: Run,
    log: LogData,
    relations: object,
    poses: np.ndarray,
    tracking: np.ndarray,
    times: np.ndarray,
) -> dict[str, object]:
    """The table row of one run (see the module docstring for every column)."""
    from service.adapters.logs import relations_error

    ok = log.ok & np.all(np.isfinite(poses), axis=1)
    err = np.hypot(*(poses[ok, :2] - log.reference[ok, :2]).T)
    rel = relations_error(log.stamps, poses, relations)  # type: ignore[arg-type]
    row: dict[str, object] = {
        "log": run.log,
        "split": "HELD-OUT" if run.log in HELD_OUT else "tuning",
        "method": run.method,
        "odom": "on" if run.odom else "off",
        "map": run.map,
        "limit": "all" if run.limit is None else run.limit,
        "scans": len(log.ranges),
        "scored": int(ok.sum()),
        "mean_m": float(err.mean()) if err.size else math.nan,
        "median_m": float(np.median(err)) if err.size else math.nan,
        "lost_pct": 100.0 * float(np.mean(~tracking[1:])) if tracking.size > 1 else math.nan,
        "rel_trans_mean_m": rel.translation_mean,
        "rel_trans_std_m": rel.translation_std,
        "rel_rot_mean_deg": rel.rotation_mean,
        "rel_used": rel.used,
        "rel_skipped": rel.skipped,
        "ms_p50": 1000.0 * float(np.percentile(times, 50)),
        "ms_p99": 1000.0 * float(np.percentile(times, 99)),
    }
    for t in THRESHOLDS:
        row[f"within_{t}"] = 100.0 * float(np.mean(err < t)) if err.size else math.nan
    return row


def git_commit() -> str:
    try:
        out = subprocess.run(
            ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        )
        diff = subprocess.run(
            ["git", "-C", str(REPO), "diff", "HEAD", "--", "service"],
            capture_output=True,
            check=True,
        )
        if not diff.stdout:
            return out.stdout.strip()
        # uncommitted changes under service/: name them by a hash of the diff
        return f"{out.stdout.strip()}+service-diff-{hashlib.sha1(diff.stdout).hexdigest()[:8]}"
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def read_csv(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with open(path, newline="", encoding="utf-8") as fh:
        return list(csv.DictReader(fh))


def write_csv(path: Path, rows: Iterable[dict[str, object]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=FIELDS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: _fmt_csv(r.get(k, "")) for k in FIELDS})
    tmp.replace(path)


def _fmt_csv(v: object) -> object:
    if isinstance(v, float):
        return "nan" if not math.isfinite(v) else f"{v:.6g}"
    return v


def row_key(r: dict[str, object]) -> tuple[str, ...]:
    return tuple(str(r[k]) for k in KEY)


def order_key(r: dict[str, object]) -> tuple[int, int, int, int]:
    logs = list(LOG_FILES)
    return (  # log, map, method, odometry on first
        logs.index(str(r["log"])) if r["log"] in logs else 99,
        MAPS.index(str(r["map"])) if r["map"] in MAPS else 9,
        METHODS.index(str(r["method"])) if r["method"] in METHODS else 9,
        0 if r["odom"] == "on" else 1,
    )


def _num(v: object) -> float:
    try:
        return float(v)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan


def _f(v: object, spec: str) -> str:
    x = _num(v)
    return "–" if not math.isfinite(x) else format(x, spec)


COLUMNS = (
    "log",
    "method",
    "odom",
    "map",
    "scans",
    "scored",
    "<0.1 m %",
    "<0.3 m %",
    "<0.5 m %",
    "mean m",
    "median m",
    "lost %",
    "relations m (± std)",
    "rel deg",
    "ms p50",
    "ms p99",
)


def table_cells(r: dict[str, object]) -> list[str]:
    log = str(r["log"]) + (" (HELD-OUT)" if r["log"] in HELD_OUT else "")
    rel = f"{_f(r['rel_trans_mean_m'], '.3f')} ± {_f(r['rel_trans_std_m'], '.3f')}"
    return [
        log,
        str(r["method"]),
        str(r["odom"]),
        str(r["map"]),
        str(r["scans"]),
        str(r["scored"]),
        _f(r["within_0.1"], ".1f"),
        _f(r["within_0.3"], ".1f"),
        _f(r["within_0.5"], ".1f"),
        _f(r["mean_m"], ".3f"),
        _f(r["median_m"], ".3f"),
        _f(r["lost_pct"], ".1f"),
        rel,
        _f(r["rel_rot_mean_deg"], ".2f"),
        _f(r["ms_p50"], ".1f"),
        _f(r["ms_p99"], ".1f"),
    ]


def print_table(rows: list[dict[str, object]]) -> None:
    cells = [list(COLUMNS)] + [table_cells(r) for r in rows]
    widths = [max(len(c[i]) for c in cells) for i in range(len(COLUMNS))]
    for k, c in enumerate(cells):
        print(
            "  ".join(
                x.rjust(w) if i >= 4 else x.ljust(w)
                for i, (x, w) in enumerate(zip(c, widths, strict=True))
            )
        )
        if k == 0:
            print("  ".join("-" * w for w in widths))


def markdown(rows: list[dict[str, object]], reference: dict[str, str], scans_label: str) -> str:
    lines = [
        "# Real-data benchmark (issue 11)",
        "",
        "Written by `bench/bench_real.py` (reads /work/shared/data/real; see its docstring for"
        " every column). intel and fr079 are the tuning logs; **mit-csail is HELD-OUT**. Each run"
        " starts at the first scan's reference pose and localises every scan"
        f" ({scans_label}); errors are scored on flag-1 (GMapping-corrected) scans only; `lost` ="
        " % of scans after the first not `tracking`; relations = Kümmerle et al.'s metric over the"
        " whole estimated track (translation mean ± std, rotation mean); ms = the `update` call"
        " alone.",
        "",
        "| " + " | ".join(COLUMNS) + " |",
        "|" + "|".join("---" for _ in COLUMNS) + "|",
    ]
    lines += ["| " + " | ".join(table_cells(r)) + " |" for r in rows]
    lines += [
        "",
        "Reference tracks scored by the same relations metric (GMapping per-scan references,"
        " all rows): "
        + "; ".join(f"{k} {v}" for k, v in reference.items())
        + ". Published RBPF: "
        + ", ".join(f"{k} {v:.3f} m" for k, v in RBPF.items())
        + ".",
        "",
        "Produced by (command, git commit of HEAD — `+service-diff-HASH` when service/ had"
        " uncommitted changes, HASH naming that diff —, 1-minute load average at each run's"
        " start on this 2-core machine, parallel jobs):",
        "",
    ]
    prov: dict[tuple[str, str, str], list[str]] = {}
    for r in rows:
        prov.setdefault((str(r["command"]), str(r["commit"]), str(r["jobs"])), []).append(
            _f(r["load1"], ".2f")
        )
    for (cmd, commit, jobs), loads in prov.items():
        lo = min(_num(x) for x in loads)
        hi = max(_num(x) for x in loads)
        lines.append(
            f"- `{cmd}` — commit {commit}, --jobs {jobs}, {len(loads)} runs, load {lo:.2f}–{hi:.2f}"
        )
    return "\n".join(lines) + "\n"


def plot_log(name: str, out: Path, cache: Path, data: Path, limit: int | None) -> Path | None:
    """Figure of one log: map, reference path, the shape + odometry estimate on the metric map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from service.adapters.maps.files import load_map_file

    track = cache / (Run(name, "shape", True, "metric", limit).tag() + ".npz")
    if not track.exists():
        print(f"{name}: no cached shape+odom metric track ({track}); figure skipped")
        return None
    z = np.load(track)
    poses, tracking = z["poses"], z["tracking"]
    log = load_log(data, name, limit)
    m = load_map_file(map_path(name, "metric"), kind="metric")
    fig, ax = plt.subplots(figsize=(9, 9))
    for p in m.polylines:
        ax.plot(p[:, 0], p[:, 1], color="0.6", lw=0.5)
    ref = log.reference[log.ok]
    ax.plot(ref[:, 0], ref[:, 1], ".", color="tab:green", ms=1.5, label="reference (flag 1)")
    ax.plot(poses[:, 0], poses[:, 1], "-", color="tab:blue", lw=0.6, label="shape + odometry")
    lost = np.flatnonzero(~tracking[1:]) + 1
    err = np.hypot(*(poses[:, :2] - log.reference[:, :2]).T)
    bad = np.flatnonzero(log.ok & (err > 0.3))
    if bad.size:
        ax.plot(*poses[bad, :2].T, "o", mfc="none", color="tab:orange", ms=5, label="> 0.3 m off")
    if lost.size:
        ax.plot(*poses[lost, :2].T, "x", color="tab:red", ms=5, label="not tracking")
    split = " (HELD-OUT)" if name in HELD_OUT else ""
    ax.set_title(
        f"{name}{split}: shape + odometry on the metric map, {len(poses)} scans\n"
        f"{bad.size} scored scans > 0.3 m, {lost.size} not tracking",
        fontsize=10,
    )
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.legend(loc="best", fontsize=8)
    path = out / f"{name}.png"
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)
    return path


#: Rough ms per scan (measured on the first 300 scans), only to start the longest runs first.
_MS = {("shape", True): 5.0, ("shape", False): 40.0, ("icp", True): 2.0, ("icp", False): 3.0}
_SCANS = {"intel": 13631, "fr079": 4934, "mit-csail": 1988}


def expected_cost(run: Run) -> float:
    ms = _MS.get((run.method, run.odom), 15.0) * (3.0 if run.map == "schematic" else 1.0)
    return ms * min(_SCANS[run.log], run.limit or _SCANS[run.log])


def parse_list(text: str, allowed: Iterable[str], what: str) -> list[str]:
    items = [t.strip() for t in text.split(",") if t.strip()]
    bad = [t for t in items if t not in allowed]
    if bad or not items:
        raise SystemExit(f"--{what}: {bad or text!r} not in {', '.join(allowed)}")
    return items


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--logs", default=",".join(LOG_FILES))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--odom", default="on,off")
    ap.add_argument("--maps", default=",".join(MAPS))
    ap.add_argument("--limit", type=int, default=None, help="first N scans of each log")
    ap.add_argument("--jobs", type=int, default=1, help="process pool size (1: clean timing)")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "real")
    ap.add_argument(
        "--results", type=Path, default=None, help="also write the page real-logs.md there"
    )
    ap.add_argument("--cache", type=Path, default=REPO / "build" / "bench_real")
    ap.add_argument("--resume", action="store_true", help="skip runs already in results.csv")
    ap.add_argument("--no-plot", action="store_true")
    ap.add_argument(
        "--search-budget-ms",
        type=float,
        default=None,
        help="shape: spread a lost robot's global search over scans within this per-scan "
        "budget (reference ms) as the service does (its default 50); default: a whole search "
        "on the scan the track was lost on (the published tables); write to another --out",
    )
    args = ap.parse_args(argv)
    if not args.data.is_dir():
        raise SystemExit(f"{args.data}: no data directory (this benchmark reads /work/shared)")
    logs = parse_list(args.logs, LOG_FILES, "logs")
    methods = parse_list(args.methods, METHODS, "methods")
    odoms = [t == "on" for t in parse_list(args.odom, ("on", "off"), "odom")]
    maps = parse_list(args.maps, MAPS, "maps")
    limit: int | None = args.limit
    command = "python -m bench.bench_real " + shlex.join(sys.argv[1:] if argv is None else argv)
    commit = git_commit()
    out: Path = args.out
    cache: Path = args.cache
    cache.mkdir(parents=True, exist_ok=True)
    csv_path = out / "results.csv"
    rows = read_csv(csv_path)
    done = {row_key(r) for r in rows}

    from service.adapters.logs import load_relations, relations_error

    relations = {k: load_relations(args.data / f"{k}.relations") for k in LOG_FILES}
    lim_label = "all" if limit is None else str(limit)
    runs = []
    for k in logs:
        for mp in maps:
            for me in methods:
                for od in odoms:
                    run = Run(k, me, od, mp, limit, args.search_budget_ms)
                    key = (k, me, "on" if od else "off", mp, lim_label)
                    if args.resume and key in done:
                        print(f"{run.tag()}: in {csv_path}, skipped (--resume)")
                        continue
                    runs.append(run)
    runs.sort(key=expected_cost, reverse=True)  # longest first keeps both workers busy
    print(
        f"{len(runs)} runs, --jobs {args.jobs} (default 1 keeps timings clean; 2 shares this"
        f" machine's 2 cores), commit {commit}, load {os.getloadavg()}"
    )

    def finish(run: Run, poses, tracking, times, wall: float, load1: float) -> None:  # type: ignore[no-untyped-def]
        np.savez_compressed(cache / f"{run.tag()}.npz", poses=poses, tracking=tracking, times=times)
        row = summarise(
            run, load_log(args.data, run.log, limit), relations[run.log], poses, tracking, times
        )
        row.update(wall_s=wall, load1=load1, jobs=args.jobs, commit=commit, command=command)
        key = row_key(row)
        rows[:] = [r for r in rows if row_key(r) != key] + [row]
        write_csv(csv_path, sorted(rows, key=order_key))
        print(
            f"{run.tag()}: {row['within_0.3']:.1f} % < 0.3 m, lost {row['lost_pct']:.1f} %, "
            f"rel {row['rel_trans_mean_m']:.3f} m, p50 {row['ms_p50']:.1f} ms, wall {wall:.0f} s",
            flush=True,
        )

    t0 = time.time()
    if args.jobs <= 1:
        for run in runs:
            load1 = os.getloadavg()[0]
            _, poses, tracking, times, wall = execute(run, args.data)
            finish(run, poses, tracking, times, wall, load1)
    else:
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            futs = {pool.submit(execute, run, args.data): os.getloadavg()[0] for run in runs}
            for fut in as_completed(futs):
                run, poses, tracking, times, wall = fut.result()
                finish(run, poses, tracking, times, wall, futs[fut])
    print(f"{len(runs)} runs in {time.time() - t0:.0f} s wall; load {os.getloadavg()}")

    n_label = "all scans" if limit is None else f"first {limit} scans"
    shown = sorted((r for r in rows if str(r["limit"]) == lim_label), key=order_key)
    reference: dict[str, str] = {}
    for k in LOG_FILES:
        if any(r["log"] == k for r in shown):
            lg = load_log(args.data, k, limit)
            rr = relations_error(lg.stamps, lg.reference, relations[k])
            reference[k] = (
                f"{rr.translation_mean:.3f} ± {rr.translation_std:.3f} m ({rr.used} relations)"
            )
    print_table(shown)
    for k, v in reference.items():
        print(f"reference track {k}: relations {v}; published RBPF {RBPF[k]:.3f} m")
    (out / "table.md").write_text(markdown(shown, reference, n_label), encoding="utf-8")
    print(f"wrote {out / 'table.md'} and {csv_path}")
    publish(args.results, "real-logs", markdown(shown, reference, n_label))
    if not args.no_plot:
        for k in logs:
            p = plot_log(k, out, cache, args.data, limit)
            if p is not None:
                print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
