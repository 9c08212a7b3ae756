"""Real robot logs: every method on whole recorded laser logs, writes docs/results/real.md.

READS ../shared (not in a user's clone): the raw logs ``intel.orig.bag``, ``fr079.orig.bag``,
``mit-csail.clf``, their ``*.relations`` and the per-scan references
``corrected/*.gfs_reference_per_scan.txt`` under ``--data`` (default /work/shared/data/real; see
its README.md). The maps are the committed ``bench/data/maps/{log}.geojson`` (metric, drawn from
the log at its reference poses by ``bench/bench_maps.py``) and ``{log}_schematic.geojson``
(schematised), see docs/maps.md.

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
  fall outside a ``--limit`` run are skipped. The reference track's own figure is given per
  log for comparison, beside the published Rao-Blackwellised particle filter's.
- ``ms p50`` / ``ms p99``: wall time of the ``update`` call alone (perf_counter), per scan.
  Timings are only meaningful with the machine's load beside them: the 1-minute load average is
  recorded per run. ``--jobs`` defaults to 1 so that one run at a time owns a core; with
  ``--jobs 2`` on a 2-core machine runs share it with each other (and other users).

Outputs (``--out DIR``, default docs/results/real): ``DIR.md`` (the results page: the table,
the commands, commits, machine and loads that produced its rows; overwritten), ``DIR/results.csv``
(one row per run with its provenance; a rerun replaces the row with the same
log/method/odom/map/scans) and ``DIR/{log}.png`` per log: the metric map's polylines in grey, the
flag-1 reference path, the ``shape`` + odometry estimate on the metric map, its non-tracking
scans and its scored scans more than 0.3 m off marked. Each run's estimated track is cached in
``--cache`` (default build/bench_real, git-ignored) for the figures; ``--resume`` skips runs
already in results.csv with the same scan count. ``--report-only`` runs nothing: it renders the
page (and, from ``--cache``, the figures) again from ``DIR/results.csv``, after merging into it
the rows of the CSVs given with ``--merge`` (the ``results.csv`` of runs written elsewhere).

    .venv/bin/python -m bench.bench_real [--logs intel,fr079,mit-csail] [--methods shape,icp,lines]
        [--odom on,off] [--maps metric,schematic] [--limit N] [--jobs 1] [--resume]
        [--out docs/results/real] [--no-plot] [--report-only [--merge CSV ...]]
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time
from collections.abc import Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from sim_publisher import results_page as report
from sim_publisher.results_page import Provenance, git_commit

__all__ = ["git_commit", "load_log", "map_path"]

REPO = Path(__file__).resolve().parents[1]
#: The maps of the logs (written by bench/bench_maps.py).
MAPS_DIR = REPO / "bench" / "data" / "maps"
DEFAULT_DATA = Path("/work/shared/data/real")
LOG_FILES = {"intel": "intel.orig.bag", "fr079": "fr079.orig.bag", "mit-csail": "mit-csail.clf"}
HELD_OUT = frozenset({"mit-csail"})
METHODS = ("shape", "icp", "lines")
#: What --methods accepts: also ``shape-paper``, shape without the laser odometry on scans
#: without odometry (the seed paper's mode; bench/methods.py).
ALL_METHODS = ("shape", "shape-paper", "icp", "lines")
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
    "jobs",
    *report.PROVENANCE_FIELDS,
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
    return MAPS_DIR / f"{name}{suffix}.geojson"


def execute(run: Run, data: Path) -> tuple[Run, np.ndarray, np.ndarray, np.ndarray, float]:
    """Run one localiser over the log; return the run, the estimated poses ``(n, 3)``, the
    tracking flags ``(n,)``, the ``update`` times ``(n,)`` (s) and the wall time (s)."""
    from bench.methods import make_localizer
    from service.adapters.maps.files import load_map_file

    log = load_log(data, run.log, run.limit)
    kind = run.map
    m = load_map_file(map_path(run.log, kind), kind=kind)
    first = int(np.flatnonzero(np.all(np.isfinite(log.reference), axis=1))[0])
    if first != 0:
        raise SystemExit(f"{run.log}: the first scan has no reference pose")
    loc = make_localizer(run.method, m, log.reference[0].copy(), search_budget_ms=run.budget)
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
        ALL_METHODS.index(str(r["method"])) if r["method"] in ALL_METHODS else 9,
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


PARAGRAPH = (
    "Each method localises {scans} of three whole logs of the Freiburg SLAM benchmark"
    " (Kümmerle et al. 2009), starting at the first scan's reference pose, with the robot's"
    " odometry (`odom on`) or without it (`off`: `shape` then measures the motion between scans"
    " from the scans, its laser odometry; `shape-paper` is the seed paper's mode, no odometry of"
    " any kind), on the metric map drawn"
    " from the log and on that map schematised to a floor plan. intel and fr079 are the tuning"
    " logs; **mit-csail is held out** (nothing was tuned on it). Errors are the distance of the"
    " estimated laser position from the GMapping-corrected (flag-1) reference, on those scans"
    " only; `lost` is the share of scans after the first not `tracking`; relations is"
    " Kümmerle et al.'s metric over the whole estimated track (translation mean ± std, rotation"
    " mean), beside the reference track's own figure and the published Rao-Blackwellised"
    " particle filter's; ms is the `update` call alone, per scan. Definitions: the docstring of"
    " `bench/bench_real.py`."
)


def reference_relations(
    data: Path, logs: Iterable[str], limit: int | None
) -> dict[str, tuple[float, float, int]]:
    """Kümmerle et al.'s relations error of each log's own reference track: translation mean,
    std (m) and the relations used."""
    from service.adapters.logs import load_relations, relations_error

    out = {}
    for k in logs:
        lg = load_log(data, k, limit)
        rr = relations_error(lg.stamps, lg.reference, load_relations(data / f"{k}.relations"))
        out[k] = (rr.translation_mean, rr.translation_std, rr.used)
    return out


def markdown(
    rows: list[dict[str, object]],
    reference: dict[str, tuple[float, float, int]],
    scans_label: str,
    figures: list[str],
    fallback: Provenance,
) -> str:
    """The results page of ``rows`` (each carrying its provenance; ``fallback`` for rows
    written before the CSV kept it)."""
    runs = [(Provenance.from_row(r, fallback), str(r["method"])) for r in rows]
    body = [report.md_table(COLUMNS, (table_cells(r) for r in rows))]
    if reference:
        body.append(
            report.md_table(
                ("log", "reference track: relations m (± std)", "relations", "published RBPF m"),
                (
                    (
                        k + (" (HELD-OUT)" if k in HELD_OUT else ""),
                        f"{report.fmt(m, '.3f')} ± {report.fmt(sd, '.3f')}",
                        n,
                        f"{RBPF[k]:.3f}",
                    )
                    for k, (m, sd, n) in reference.items()
                ),
            )
        )
    body += [f"![{Path(f).stem}: shape + odometry on the metric map]({f})" for f in figures]
    return report.page("Real robot logs", PARAGRAPH.format(scans=scans_label), runs, body)


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


def merge_rows(
    rows: list[dict[str, object]], more: Iterable[dict[str, object]]
) -> list[dict[str, object]]:
    """``rows`` with ``more`` added; a row of ``more`` replaces the one with its key."""
    merged = {row_key(r): r for r in rows}
    for r in more:
        merged[row_key(r)] = r
    return sorted(merged.values(), key=order_key)


def read_reference(path: Path) -> dict[str, tuple[float, float, int]]:
    return {
        r["log"]: (float(r["mean_m"]), float(r["std_m"]), int(r["used"])) for r in read_csv(path)
    }


def write_reference(path: Path, reference: dict[str, tuple[float, float, int]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["log", "mean_m", "std_m", "used"])
        for k, (m, sd, n) in reference.items():
            w.writerow([k, f"{m:.6g}", f"{sd:.6g}", n])


def render(
    out: Path,
    rows: list[dict[str, object]],
    data: Path,
    cache: Path,
    limit: int | None,
    plot: bool,
    fallback: Provenance,
) -> Path:
    """Print the table of ``rows`` of this ``limit``, draw the figures (``plot``, from the
    tracks in ``cache``) and write the page ``out.md``; returns the page's path."""
    lim_label = "all" if limit is None else str(limit)
    shown = sorted((r for r in rows if str(r["limit"]) == lim_label), key=order_key)
    logs = [k for k in LOG_FILES if any(r["log"] == k for r in shown)]
    ref_csv = out / ("reference.csv" if limit is None else f"reference_{limit}.csv")
    reference = {k: v for k, v in read_reference(ref_csv).items() if k in logs}
    if set(reference) != set(logs) and data.is_dir():
        reference = reference_relations(data, logs, limit)
        write_reference(ref_csv, reference)
    print_table(shown)
    for k, (m, sd, n) in reference.items():
        print(f"reference track {k}: relations {m:.3f} ± {sd:.3f} m ({n}); RBPF {RBPF[k]:.3f} m")
    if plot and data.is_dir():
        for k in logs:
            fig = plot_log(k, out, cache, data, limit)
            if fig is not None:
                print(f"wrote {fig}")
    figures = [f"{out.name}/{k}.png" for k in logs if (out / f"{k}.png").exists()]
    n_label = "every scan" if limit is None else f"the first {limit} scans"
    text = markdown(shown, reference, n_label, figures, fallback)
    return report.write_page(out.with_suffix(".md"), text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--logs", default=",".join(LOG_FILES))
    ap.add_argument("--methods", default=",".join(METHODS))
    ap.add_argument("--odom", default="on,off")
    ap.add_argument("--maps", default=",".join(MAPS))
    ap.add_argument("--limit", type=int, default=None, help="first N scans of each log")
    ap.add_argument("--jobs", type=int, default=1, help="process pool size (1: clean timing)")
    ap.add_argument(
        "--out",
        type=Path,
        default=REPO / "docs" / "results" / "real",
        help="results.csv and figures go in OUT, the page is OUT.md",
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
    ap.add_argument(
        "--report-only",
        action="store_true",
        help="run nothing: render the page (and the figures, from --cache) from OUT/results.csv",
    )
    ap.add_argument(
        "--merge",
        type=Path,
        nargs="+",
        default=[],
        metavar="CSV",
        help="with --report-only: first merge these results.csv into OUT/results.csv (a row "
        "replaces the one of the same log, method, odometry, map and scans)",
    )
    args = ap.parse_args(argv)
    out: Path = args.out
    cache: Path = args.cache
    csv_path = out / "results.csv"
    limit: int | None = args.limit
    raw_argv = sys.argv[1:] if argv is None else argv
    here = Provenance.capture(report.command_line("bench.bench_real", raw_argv))
    if args.merge and not args.report_only:
        raise SystemExit("--merge goes with --report-only")
    if args.report_only:
        rows: list[dict[str, object]] = list(read_csv(csv_path))
        for extra in args.merge:
            if not extra.exists():
                raise SystemExit(f"{extra}: no such CSV")
            # a CSV written before the rows kept their machine and date: the same machine
            # renders it, on the day the file was last written
            written = time.strftime("%Y-%m-%d", time.gmtime(extra.stat().st_mtime))
            fill = Provenance("", "", here.machine, math.nan, written)
            more = []
            for r in read_csv(extra):
                prov = Provenance.from_row(r, fill)
                more.append({**r, **prov.as_row()})
            rows = merge_rows(rows, more)
            print(f"merged {len(more)} rows of {extra}")
        if not rows:
            raise SystemExit(f"{csv_path}: no rows to render")
        if args.merge:
            write_csv(csv_path, rows)
        page = render(out, rows, args.data, cache, limit, not args.no_plot, here)
        print(f"wrote {page} from {csv_path}")
        return 0

    if not args.data.is_dir():
        raise SystemExit(f"{args.data}: no data directory (this benchmark reads ../shared/data)")
    logs = parse_list(args.logs, LOG_FILES, "logs")
    methods = parse_list(args.methods, ALL_METHODS, "methods")
    odoms = [t == "on" for t in parse_list(args.odom, ("on", "off"), "odom")]
    maps = parse_list(args.maps, MAPS, "maps")
    cache.mkdir(parents=True, exist_ok=True)
    rows = list(read_csv(csv_path))
    done = {row_key(r) for r in rows}

    from service.adapters.logs import load_relations

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
        f"{len(runs)} runs, --jobs {args.jobs} (1 keeps timings clean), commit {here.commit}, "
        f"{here.machine}, load {here.load1:.2f}"
    )

    def finish(run: Run, poses, tracking, times, wall: float, load1: float) -> None:  # type: ignore[no-untyped-def]
        np.savez_compressed(cache / f"{run.tag()}.npz", poses=poses, tracking=tracking, times=times)
        row = summarise(
            run, load_log(args.data, run.log, limit), relations[run.log], poses, tracking, times
        )
        prov = Provenance(here.command, here.commit, here.machine, load1, here.date).ended()
        row.update(wall_s=wall, jobs=args.jobs, **prov.as_row())
        rows[:] = merge_rows(rows, [row])
        write_csv(csv_path, rows)
        print(
            f"{run.tag()}: {row['within_0.3']:.1f} % < 0.3 m, lost {row['lost_pct']:.1f} %, "
            f"rel {row['rel_trans_mean_m']:.3f} m, p50 {row['ms_p50']:.1f} ms, wall {wall:.0f} s",
            flush=True,
        )

    t0 = time.time()
    if args.jobs <= 1:
        for run in runs:
            load1 = report.load_average()
            _, poses, tracking, times, wall = execute(run, args.data)
            finish(run, poses, tracking, times, wall, load1)
    else:
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            futs = {pool.submit(execute, run, args.data): report.load_average() for run in runs}
            for fut in as_completed(futs):
                run, poses, tracking, times, wall = fut.result()
                finish(run, poses, tracking, times, wall, futs[fut])
    print(f"{len(runs)} runs in {time.time() - t0:.0f} s wall; load {os.getloadavg()}")
    page = render(out, rows, args.data, cache, limit, not args.no_plot, here)
    print(f"wrote {page} and {csv_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
