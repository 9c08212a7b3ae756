"""Kidnapped robot with odometry on the real logs, writes docs/results/kidnap.md.

READS ../shared (the real logs, /work/shared/data/real, as ``bench_real.py``). Each trial
tracks a log from a random scan's reference pose for ``--pre`` scans, then carries the robot to
a random stretch of the same log at least 3 m away: the scans come from there while the
odometry runs on from the old place with that stretch's own increments (the wheels report the
drive, not the jump). ``--post`` scans follow. Two rules run on the same trials: the default
(``GlobalConfig.contradiction``: a scan the tracker rejects ends the track, after
``lost_after`` in a row, only if it contradicts the pose, i.e. more than that share of its
beams return from beyond a drawn wall, or after a break in the scan-to-scan fit) and ``-1``
(every rejected, low-scoring scan counts), which shows what the default rule buys.

Columns, per log, map and rule:

- ``lost <= 3``: % of trials whose status is not ``tracking`` on one of the first 3 scans after
  the jump (the tracker's contract: a rejected scan keeps its prior, ``tracking``, until
  ``lost_after`` of them);
- ``never lost``: trials still ``tracking`` on every scan after the jump;
- ``lost at p50 / max``: scans after the jump until the first non-``tracking`` status;
- ``wrong scans``: ``tracking`` estimates after the jump more than 0.5 m or 10 deg from the
  reference (scored on flag-1 scans), summed over the trials, and the trials with any;
- ``re-fixed``: trials published ``tracking`` within 0.5 m / 10 deg again after a loss.

Deterministic (``--seed``); ``--jobs`` processes. ``--out DIR`` (default docs/results/kidnap):
the page ``DIR.md`` (overwritten) and ``DIR/results.csv`` (one row per trial, with the run's
provenance); ``--report-only`` renders the page again from that CSV without running.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from bench import bench_real as br
from bench.harness import REPO
from sim_publisher import results_page as report
from sim_publisher.results_page import Provenance

#: The collapse rules compared, by their label in the table.
RULES = {"default": None, "every unexplained scan (-1)": -1.0}


def pick_trials(log: br.LogData, n: int, pre: int, post: int, seed: int) -> list[tuple[int, int]]:
    """``n`` (start, jump target) pairs: both stretches have odometry throughout, the start a
    reference pose, and the target lies at least 3 m from where the robot is carried from."""
    rng = np.random.default_rng(seed)
    ref, total = log.reference, len(log.ranges)
    out: list[tuple[int, int]] = []
    while len(out) < n:
        k0 = int(rng.integers(0, total - pre - 1))
        j = int(rng.integers(0, total - post - 2))
        if not np.all(np.isfinite(ref[k0])) or not np.all(np.isfinite(ref[k0 + pre])):
            continue
        if any(log.odom[i] is None for i in range(k0, k0 + pre)):
            continue
        if any(log.odom[i] is None for i in range(j, j + post + 1)):
            continue
        if not np.all(np.isfinite(ref[j])):
            continue
        if math.dist(ref[j][:2], ref[k0 + pre][:2]) < 3.0:
            continue
        out.append((k0, j))
    return out


def run_trial(
    name: str, kind: str, rule: float | None, k0: int, j: int, pre: int, post: int
) -> dict[str, object]:
    from service.adapters.maps.files import load_map_file
    from service.core.factory import create_localizer
    from service.core.pose import compose, relative
    from service.core.types import wrap_angle

    log = br.load_log(br.DEFAULT_DATA, name, None)
    md = load_map_file(br.map_path(name, kind), kind=kind)
    loc = create_localizer("shape", md, log.reference[k0].copy())
    if rule is not None:
        # -1 lies outside the field's range on purpose (every share exceeds it): unvalidated
        loc.gconfig = loc.gconfig.model_copy(update={"contradiction": rule})  # type: ignore[attr-defined]
    for i in range(k0, k0 + pre):
        loc.update(log.ranges[i], log.angles[i], log.odom[i])
    base = np.asarray(log.odom[k0 + pre - 1], dtype=float)
    o0 = np.asarray(log.odom[j], dtype=float)
    lost_at = None
    wrong = 0
    refixed = False
    for s in range(post):
        i = j + 1 + s
        odom = compose(base, relative(o0, np.asarray(log.odom[i], dtype=float)))
        est = loc.update(log.ranges[i], log.angles[i], odom)
        if est.status != "tracking":
            lost_at = s if lost_at is None else lost_at
            continue
        if not log.ok[i]:
            continue
        ref = log.reference[i]
        ok = math.dist(est.pose[:2], ref[:2]) < 0.5 and abs(
            wrap_angle(float(est.pose[2] - ref[2]))
        ) < math.radians(10)
        wrong += not ok
        refixed |= ok and lost_at is not None
    return {"log": name, "map": kind, "rule": rule, "start": k0, "target": j,
            "lost_at": lost_at, "wrong": wrong, "refixed": refixed}  # fmt: skip


def summarise(rows: list[dict[str, object]]) -> dict[str, str]:
    lost = [r["lost_at"] for r in rows if r["lost_at"] is not None]
    n = len(rows)
    return {
        "trials": str(n),
        "lost <= 3": f"{100.0 * sum(int(x) < 3 for x in lost) / n:.1f} %",  # type: ignore[call-overload]
        "never lost": str(n - len(lost)),
        "lost at p50 / max": (
            f"{np.median(lost):.0f} / {max(lost)}" if lost else "-"  # type: ignore[type-var]
        ),
        "wrong scans (trials)": (
            f"{sum(int(r['wrong']) for r in rows)} ({sum(int(r['wrong']) > 0 for r in rows)})"  # type: ignore[call-overload]
        ),
        "re-fixed": str(sum(bool(r["refixed"]) for r in rows)),
    }


PARAGRAPH = (
    "How a tracked robot notices that it was carried elsewhere, and how often it publishes a"
    " wrong pose as `tracking` meanwhile. Each trial tracks a real log (the Freiburg SLAM"
    " benchmark's intel and fr079, the tuning logs, and mit-csail, held out) from a random"
    " scan's reference pose for {pre} scans, then the scans come from a random stretch of the"
    " same log at least 3 m away while the odometry runs on from the old place with that"
    " stretch's own increments; {post} scans follow. Two rules run on the same trials: the"
    " default (a rejected scan ends the track only if it contradicts the pose, beams through"
    " drawn walls, or after a break in the scan-to-scan fit) and -1 (every rejected,"
    " low-scoring scan counts). `lost <= 3`:"
    " trials no longer `tracking` within 3 scans of the jump; `lost at`: scans until then;"
    " `wrong scans`: `tracking` poses after the jump more than 0.5 m or 10° from the reference"
    " (trials with any); `re-fixed`: trials `tracking` at the right place again after a loss."
    " Definitions: the docstring of `bench/bench_kidnap.py`."
)
HEAD = ["log", "map", "rule", "trials", "lost <= 3", "never lost", "lost at p50 / max",
        "wrong scans (trials)", "re-fixed"]  # fmt: skip


def _rule(v: object) -> float | None:
    return None if v in (None, "", "None") else float(v)  # type: ignore[arg-type]


def render(path: Path, rows: list[dict[str, object]]) -> Path:
    """The page ``path`` of the trial ``rows`` (read back from the CSV or fresh)."""
    logs = list(dict.fromkeys(str(r["log"]) for r in rows))
    maps = list(dict.fromkeys(str(r["map"]) for r in rows))
    cells = []
    for name in logs:
        for kind in maps:
            for label, rule in RULES.items():
                sel = [
                    r for r in rows if (r["log"], r["map"], _rule(r["rule"])) == (name, kind, rule)
                ]
                if not sel:
                    continue
                held = " (HELD-OUT)" if name in br.HELD_OUT else ""
                cells.append([name + held, kind, label, *summarise(sel).values()])
    table = report.md_table(HEAD, cells)
    print(table)
    first = rows[0]
    paragraph = PARAGRAPH.format(pre=first["pre"], post=first["post"])
    runs = [(Provenance.from_row(r), "") for r in rows]
    return report.write_page(path, report.page("Kidnapped robot", paragraph, runs, [table]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", default="intel,fr079,mit-csail")
    ap.add_argument("--maps", default="schematic,metric")
    ap.add_argument("--trials", type=int, default=30)
    ap.add_argument("--pre", type=int, default=30)
    ap.add_argument("--post", type=int, default=60)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument(
        "--out",
        type=Path,
        default=REPO / "docs" / "results" / "kidnap",
        help="results.csv goes in OUT, the page is OUT.md",
    )
    ap.add_argument(
        "--report-only", action="store_true", help="render the page from OUT/results.csv"
    )
    args = ap.parse_args(argv)
    csv_path = args.out / "results.csv"
    page = args.out.with_suffix(".md")
    if args.report_only:
        with open(csv_path, newline="", encoding="utf-8") as fh:
            rows: list[dict[str, object]] = [
                {
                    **r,
                    "lost_at": int(r["lost_at"]) if r["lost_at"] else None,
                    "wrong": int(r["wrong"]),
                    "refixed": r["refixed"] == "True",
                }
                for r in csv.DictReader(fh)
            ]
        print(f"wrote {render(page, rows)} from {csv_path}")
        return 0
    here = Provenance.capture(
        report.command_line("bench.bench_kidnap", sys.argv[1:] if argv is None else argv)
    )
    t0 = time.time()
    jobs = []
    for name in args.logs.split(","):
        log = br.load_log(br.DEFAULT_DATA, name, None)
        pairs = pick_trials(log, args.trials, args.pre, args.post, args.seed)
        for kind in args.maps.split(","):
            for rule in RULES.values():
                jobs += [(name, kind, rule, k0, j, args.pre, args.post) for k0, j in pairs]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        rows = list(pool.map(run_trial, *zip(*jobs, strict=True)))
    print(f"{len(jobs)} trials in {time.time() - t0:.0f} s, load {os.getloadavg()[0]:.2f}")
    extra = {"pre": args.pre, "post": args.post, "seed": args.seed, **here.ended().as_row()}
    rows = [{**r, **extra} for r in rows]
    args.out.mkdir(parents=True, exist_ok=True)
    with open(csv_path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"wrote {render(page, rows)} and {csv_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
