"""Odometry checked against the scans (``service.core.tracking.scan_odometry``): how far each
odometry increment is from the reference's, as received and as corrected.

For every pair of scans ``(j, i)`` that both have a reference pose -- consecutive scans
(``gap 1``), scans 10 apart (``gap 10``), or on intel, whose flag-1 references are sparse,
each flag-1 scan and the previous flag-1 scan at most 30 scans before it (``gap ref``); and
the tours fed every k-th scan only (``--strides``; ``1 of 3``: consecutive fed scans, 3 scans
apart in the log, the odometry's increment 3 times as long) --
the increment ``odom_j^-1 (+) odom_i`` is compared with the reference's ``ref_j^-1 (+) ref_i``:
translation error (m) and heading error (deg), percentiles over all pairs, and how many pairs
the correction made worse / better by more than 5 cm. Also the share of scans whose
increment was replaced by the fit and the time per scan (``ScanOdometry.correct``, after 10
warm-up scans).

Real logs: the GMapping-corrected references of ``../shared/data/real`` (``--data``; not part
of a clone). mit-csail is the held-out log. Generated buildings (``--worlds``, default the
tuning seeds 0-19 and held-out 1000-1007; setup 2: schematic tour, a scan every 104 mm, the
simulated odometry; moving people on) need no data.

    python -m bench.bench_odometry                # all, writes docs/results/odometry.md
    python -m bench.bench_odometry --logs fr079 --worlds 12 --out /tmp/odometry.md
"""

from __future__ import annotations

import argparse
import itertools
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np

from bench.harness import REPO as ROOT
from service.core.pose import compose, invert
from service.core.tracking.motion import MotionConfig
from service.core.tracking.scan_odometry import ScanOdometry
from sim_publisher import results_page as report
from sim_publisher.results_page import Provenance

HELD_OUT_LOGS = ("mit-csail",)


def _pairs(flags: np.ndarray, gap: int | None) -> list[tuple[int, int]]:
    idx = np.flatnonzero(flags)
    if gap is not None:
        return [(int(i) - gap, int(i)) for i in idx if i - gap >= 0 and flags[i - gap]]
    return [(int(a), int(b)) for a, b in itertools.pairwise(idx) if 0 < b - a <= 30]


def _errors(poses: np.ndarray, ref: np.ndarray, pairs: list[tuple[int, int]]) -> np.ndarray:
    out = np.empty((len(pairs), 2))
    for k, (j, i) in enumerate(pairs):
        d = compose(invert(poses[j]), poses[i])
        t = compose(invert(ref[j]), ref[i])
        out[k] = math.hypot(d[0] - t[0], d[1] - t[1]), abs(math.remainder(d[2] - t[2], 2 * math.pi))
    return out


#: turn bins (rad) of the heading-error-by-turn table
TURN_BINS = ((0.0, 0.05), (0.05, 0.15), (0.15, 0.3), (0.3, 0.6), (0.6, 4.0))


def _turn_rows(
    name: str, ref: np.ndarray, pairs: list[tuple[int, int]], raw: np.ndarray, fix: np.ndarray
) -> list[str]:
    """Heading error (deg) p50 / p90 / p99 of the raw and the checked increments by the
    reference's turn between the two scans (:data:`TURN_BINS`); bins with < 5 pairs left out.
    Why: ``MotionConfig.matched_turn_noise`` (a checked increment's error does not grow with
    the turn the way the raw odometry's does)."""
    turn = np.array(
        [abs(math.remainder(compose(invert(ref[j]), ref[i])[2], 2 * math.pi)) for j, i in pairs]
    )
    rows = []
    for lo, hi in TURN_BINS:
        sel = (turn >= lo) & (turn < hi)
        if sel.sum() < 5:
            continue
        r = np.degrees(np.percentile(raw[sel, 1], [50, 90, 99]))
        f = np.degrees(np.percentile(fix[sel, 1], [50, 90, 99]))
        rows.append(
            f"| {name} | {lo:.2f}-{hi:.2f} | {int(sel.sum())} | {r[0]:.2f} / {r[1]:.2f} / "
            f"{r[2]:.2f} | {f[0]:.2f} / {f[1]:.2f} / {f[2]:.2f} |"
        )
    return rows


def run_tour(
    scans: list[tuple[np.ndarray, np.ndarray]], odom: np.ndarray, motion: MotionConfig
) -> tuple[np.ndarray, float, np.ndarray]:
    """Corrected odometry poses ``(n, 3)``, the share of scans corrected, times (ms)."""
    so = ScanOdometry(motion.scan_odometry, motion)
    out = np.empty_like(odom)
    corrected = 0
    ms = []
    for i, (r, a) in enumerate(scans):
        t0 = time.perf_counter()
        out[i] = so.correct(r, a, odom[i])
        ms.append(1e3 * (time.perf_counter() - t0))
        corrected += so.corrected
    return out, corrected / len(scans), np.asarray(ms[10:])


def _row(
    name: str, split: str, gap: str, raw: np.ndarray, fix: np.ndarray, share: float, ms: np.ndarray
) -> str:
    def cell(e: np.ndarray) -> str:
        t = np.percentile(e[:, 0], [50, 90, 99])
        r = np.degrees(np.percentile(e[:, 1], [50, 90, 99]))
        return f"{t[0]:.3f} / {t[1]:.3f} / {t[2]:.3f} | {r[0]:.2f} / {r[1]:.2f} / {r[2]:.2f}"

    worse = int(np.sum(fix[:, 0] > raw[:, 0] + 0.05))
    better = int(np.sum(fix[:, 0] < raw[:, 0] - 0.05))
    return (
        f"| {name} | {split} | {gap} | {len(raw)} | {cell(raw)} | {cell(fix)} | {worse} / "
        f"{better} | {100 * share:.1f} % | {np.median(ms):.2f} / {np.percentile(ms, 99):.2f} |"
    )


def real_rows(
    data: Path, logs: list[str], motion: MotionConfig, strides: tuple[int, ...] = (1,)
) -> tuple[list[str], list[str]]:
    """Rows of the real logs, and of their heading error by turn (:func:`_turn_rows`, the
    first gap of each tour); for each ``stride`` k > 1 the tour fed every k-th scan
    (a robot whose scans come farther apart: the increments are k times longer), its
    consecutive fed scans compared (label ``1 of k``, or ``ref of k`` on intel)."""
    from bench.bench_real import load_log

    rows, turns = [], []
    for name in logs:
        log = load_log(data, name, None)
        valid = [i for i, o in enumerate(log.odom) if o is not None]
        split = "held-out" if name in HELD_OUT_LOGS else "tuning"
        for k in strides:
            keep = valid[::k]
            scans = [(log.ranges[i], log.angles[i]) for i in keep]
            odom = np.array([log.odom[i] for i in keep])
            ref = log.reference[keep]
            flags = log.ok[keep]
            fixed, share, ms = run_tour(scans, odom, motion)
            gaps: list[tuple[str, int | None]] = [("1", 1), ("10", 10)] if k == 1 else [("1", 1)]
            if len(_pairs(flags, 1)) < 100:
                gaps = [("ref", None)]
            for n_gap, (label, gap) in enumerate(gaps):
                label = label if k == 1 else f"{label} of {k}"
                pairs = _pairs(flags, gap)
                raw, fix = _errors(odom, ref, pairs), _errors(fixed, ref, pairs)
                if n_gap == 0:
                    turns += _turn_rows(f"{name} ({split}), gap {label}", ref, pairs, raw, fix)
                rows.append(_row(name, split, label, raw, fix, share, ms))
                print(rows[-1], flush=True)
    return rows, turns


def world_rows(seeds: list[int], motion: MotionConfig) -> tuple[list[str], list[str]]:
    """Rows of the generated buildings (one per split), and of their heading error by turn
    (:func:`_turn_rows`)."""
    from bench.bench_worlds import generated_building
    from sim_publisher.scenario import building_setup

    groups: dict[str, list[int]] = {
        "tuning": [s for s in seeds if s < 1000],
        "held-out": [s for s in seeds if s >= 1000],
    }
    rows, turns = [], []
    for split, group in groups.items():
        if not group:
            continue
        raws, fixes, shares, times, refs, idx = [], [], [], [], [], []
        for seed in group:
            su = building_setup(generated_building(seed, 2), 2, seed=0)
            scans = [su.scan(i) for i in range(len(su.truth))]
            fixed, share, ms = run_tour(scans, su.odom, motion)
            pairs = _pairs(np.ones(len(su.truth), dtype=bool), 1)
            raws.append(_errors(su.odom, su.truth, pairs))
            fixes.append(_errors(fixed, su.truth, pairs))
            base = sum(len(t) for t in refs)
            refs.append(su.truth)
            idx += [(base + j, base + i) for j, i in pairs]
            shares.append(share)
            times.append(ms)
        name = f"buildings {group[0]}-{group[-1]} ({len(group)}), setup 2, 2 people"
        raw, fix = np.vstack(raws), np.vstack(fixes)
        turns += _turn_rows(f"{name} ({split})", np.vstack(refs), idx, raw, fix)
        rows.append(_row(name, split, "1", raw, fix, float(np.mean(shares)), np.concatenate(times)))
        print(rows[-1], flush=True)
    return rows, turns


PARAGRAPH = (
    "How far each odometry increment between two scans is from the reference's, as the robot "
    "reported it and as checked against the scans (`service.core.tracking.scan_odometry`): "
    "translation and heading error percentiles over all pairs of scans, the pairs the check made "
    "worse / better by more than 5 cm, the share of scans whose increment the scan fit replaced, "
    "and the check's time per scan. Pairs: consecutive scans (gap 1), scans 10 apart (gap 10), or "
    "on intel, whose corrected references are sparse, consecutive corrected scans (gap ref); `of "
    "3`: the tour fed every third scan (increments three times as long). Real logs: the Freiburg "
    "SLAM benchmark against its GMapping-corrected references (intel and fr079 tuning, mit-csail "
    "held out); generated buildings: setup 2 tours with two moving people against the simulator's "
    "truth (seeds 0-19 tuning, >= 1000 held out). The second table splits the heading error by the "
    "reference's turn between the two scans (`MotionConfig.matched_turn_noise`). Definitions: the "
    "docstring of `bench/bench_odometry.py`."
)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=Path("/work/shared/data/real"))
    ap.add_argument("--logs", default="intel,fr079,mit-csail", help="'' for none")
    ap.add_argument("--worlds", default="0-19,1000-1007", help="seeds, e.g. 0-19,1000-1007")
    ap.add_argument(
        "--out", type=Path, default=ROOT / "docs" / "results" / "odometry.md", help="the page"
    )
    ap.add_argument(
        "--strides", default="1,3", help="real logs also fed every k-th scan, e.g. 1,2,3"
    )
    ap.add_argument(
        "--fallback-sigma",
        type=float,
        default=None,
        help="ScanOdometryConfig.fallback_sigma (default: the config's, off)",
    )
    args = ap.parse_args(argv)
    here = Provenance.capture(
        report.command_line("bench.bench_odometry", sys.argv[1:] if argv is None else argv)
    )
    seeds: list[int] = []
    for part in filter(None, args.worlds.split(",")):
        lo, _, hi = part.partition("-")
        seeds += list(range(int(lo), int(hi or lo) + 1))
    motion = MotionConfig()
    if args.fallback_sigma is not None:
        check = motion.scan_odometry.model_copy(update={"fallback_sigma": args.fallback_sigma})
        motion = motion.model_copy(update={"scan_odometry": check})
    t0 = time.perf_counter()
    rows: list[str] = []
    turns: list[str] = []
    logs = [s for s in args.logs.split(",") if s]
    if logs and not args.data.is_dir():
        print(f"{args.data} not found (not part of a clone): the real logs are left out")
        logs = []
    if logs:
        strides = [int(v) for v in args.strides.split(",") if v]
        more, turned = real_rows(args.data, logs, motion, tuple(strides))
        rows += more
        turns += turned
    if seeds:
        more, turned = world_rows(seeds, motion)
        rows += more
        turns += turned
    head = (
        "| tour | split | gap | pairs | odometry: translation p50 / p90 / p99 m | heading p50 / "
        "p90 / p99 deg | checked: translation p50 / p90 / p99 m | heading p50 / p90 / p99 deg "
        "| worse / better by > 5 cm | corrected | ms p50 / p99 |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    turn_head = (
        "| tour | turn rad | pairs | odometry heading p50 / p90 / p99 deg | checked heading "
        "p50 / p90 / p99 deg |\n|---|---|---|---|---|\n"
    )
    body = [head + "\n".join(rows), turn_head + "\n".join(turns)]
    runs = [(here.ended(), "")]
    text = report.page("Odometry checked against the scans", PARAGRAPH, runs, body)
    report.write_page(args.out, text)
    print(f"wrote {args.out} in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
