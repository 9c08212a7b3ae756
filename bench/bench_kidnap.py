"""Kidnapped robot with odometry on the real logs (reads /work/shared/data/real; stop 42).

Each trial tracks a log from a random scan's reference pose for ``--pre`` scans, then carries
the robot to a random stretch of the same log at least 3 m away: the scans come from there
while the odometry runs on from the old place with that stretch's own increments (the wheels
report the drive, not the jump). ``--post`` scans follow. Both collapse rules run on the same
trials: the default (``GlobalConfig.collapse_violation``: an unexplained scan ends the track
only if it contradicts the pose, or after a break in the scan-to-scan fit) and ``-1`` (every
unexplained scan counts, the rule before stop 42).

Columns, per log, map and rule:

- ``lost <= 3``: % of trials whose status is not ``tracking`` on one of the first 3 scans after
  the jump (the tracker's contract: a rejected scan keeps its prior, ``tracking``, until
  ``lost_after`` of them);
- ``never lost``: trials still ``tracking`` on every scan after the jump;
- ``lost at p50 / max``: scans after the jump until the first non-``tracking`` status;
- ``wrong scans``: ``tracking`` estimates after the jump more than 0.5 m or 10 deg from the
  reference (scored on flag-1 scans), summed over the trials, and the trials with any;
- ``re-fixed``: trials published ``tracking`` within 0.5 m / 10 deg again after a loss.

Deterministic (``--seed``); ``--jobs`` processes. Writes ``table.md`` and ``results.csv`` to
``--out`` (default docs/kidnap).
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

RULES = {"default": None, "before stop 42 (-1)": -1.0}


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
        loc.gconfig = loc.gconfig.model_copy(update={"collapse_violation": rule})  # type: ignore[attr-defined]
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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--logs", default="intel,fr079,mit-csail")
    ap.add_argument("--maps", default="schematic,metric")
    ap.add_argument("--trials", type=int, default=30)
    ap.add_argument("--pre", type=int, default=30)
    ap.add_argument("--post", type=int, default=60)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "kidnap")
    args = ap.parse_args(argv)
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
    args.out.mkdir(parents=True, exist_ok=True)
    with open(args.out / "results.csv", "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    head = ["log", "map", "rule", "trials", "lost <= 3", "never lost", "lost at p50 / max",
            "wrong scans (trials)", "re-fixed"]  # fmt: skip
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for name in args.logs.split(","):
        for kind in args.maps.split(","):
            for label, rule in RULES.items():
                sel = [r for r in rows if (r["log"], r["map"], r["rule"]) == (name, kind, rule)]
                held = " (HELD-OUT)" if name == "mit-csail" else ""
                s = summarise(sel)
                lines.append("| " + " | ".join([name + held, kind, label, *s.values()]) + " |")
    command = "python -m bench.bench_kidnap " + " ".join(sys.argv[1:] if argv is None else argv)
    text = (
        "# Kidnapped robot with odometry on the real logs (stop 42)\n\n"
        f"Written by `{command}` ({len(jobs)} trials in {time.time() - t0:.0f} s, "
        f"--jobs {args.jobs}, load at end {os.getloadavg()[0]:.2f}); see the script's "
        "docstring for the columns. intel and fr079 are the tuning logs, mit-csail is held "
        "out.\n\n" + "\n".join(lines) + "\n"
    )
    (args.out / "table.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
