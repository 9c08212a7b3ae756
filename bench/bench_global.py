"""Global localisation acceptance measurement (prints tables).

``python -m bench.bench_global [--poses 200] [--seed 1] [--maps metric,schematic]
[--motions creep,look-around] [--setup-scans N] [--no-setups]``

1. Precompute per map: the view index built cold (into an empty cache dir) and loaded from
   that cache (a fresh process' view: the in-memory copy is dropped first).
2. Random free-space poses (``sim_publisher.publisher.random_free_poses``, >= 0.3 m from any
   obstacle, heading uniform; seeded) per map, no initial pose, up to 3 scans each. The robot
   MOVES 3 cm along its heading between the scans (``creep``: it stays put if that would leave
   free space; no odometry), or TURNS 90 deg in place (``look-around``: odometry sent, the
   localiser fuses the scans). Found = the first ``tracking`` estimate is within 0.5 m and
   10 deg of the truth; a ``tracking`` estimate outside that is a confident wrong pose. Time
   to first fix = wall time of the ``update`` calls up to the fix (one process, one core; the
   machine's load is printed).
3. No confident wrong poses: both full setups (``sim_publisher.scenario.make_setup``) run with
   ``initial_pose`` null; of all estimates with status ``tracking``, the fraction passing the
   setup's proximity test (setup 1: 100 mm / 45 deg, setup 2: 500 mm / 45 deg).

Drive trials (``--drive``): global localisation WHILE THE ROBOT DRIVES
-------------------------------------------------------------------------------
``python -m bench.bench_global --drive [--groups office,worlds,real] [--starts 200]
[--worlds 8] [--real-starts 40] [--logs intel,fr079,mit-csail] [--data DIR] [--jobs 2]
[--quick N] [--stride1 1] [--seed 1] [--cache build/bench_global/index] [--out build/bench_global]
[--results docs/results]``

A trial picks a random start scan on a tour, creates ``create_localizer("shape", map, None,
search_budget_ms=--budget-ms)`` (no initial pose; the service's default budget of 50 reference
ms per scan, 0 = a whole search per scan as offline) and feeds that scan and every
following one WITH its odometry
(``update(ranges, angles, odom)``) until the travel since the start exceeds the map's travel
limit + 5 m (the margin; the first scan beyond it is the trial's last) or the tour ends.

Maps (one table row each):

- ``office``: ``make_setup(1)`` (the office's metric map, a scan every 11 mm) and
  ``make_setup(2)`` (its schematic floor plan, a scan every 104 mm), ``--starts`` starts each.
- ``worlds``: held-out generated buildings (``bench_worlds.generated_building(seed, 0)``:
  seeds 1000 .. 999 + ``--worlds``, no moving people) with ``building_setup(b, 1 | 2,
  seed=0)``. Per setup the ``--starts`` starts are spread evenly over the worlds (``starts //
  worlds`` each, the first ``starts % worlds`` worlds one more), so each setup's row has
  ``--starts`` trials in all. Their tours are 25 m long: a setup-2 trial needs 20 m, so its
  starts lie in the first 5 m of the tour.
- ``real``: the logs intel, fr079 (tuning) and mit-csail (HELD OUT) on the committed metric
  and schematised maps (``docs/real/maps/{log}.geojson``, ``{log}_schematic.geojson``), the
  log's laser odometry on, ``--real-starts`` starts per log and map, the scans read from
  ``--data`` with ``bench_real.load_log``.

Definitions:

- travel: in simulation the sum of the TRUE step lengths (translation only) since the start
  scan; on the real logs the sum of the (laser) odometry step lengths, since the per-scan
  references jump at GMapping's corrections (their sum on intel is 790 m against 593 m).
- travel limit: 5 m on metric maps (office and worlds, setup 1); 15 m on floor plans
  (setup 2) and on both maps of the real logs (the issue: "fixed correctly within 15 m of
  travel on every log").
- start scans: distinct scans drawn uniformly (``numpy.random.default_rng([--seed, group,
  world, map])``) among those after which at least limit + 5 m of travel remain; on real logs
  only scans with a reference. A tour without such a scan is skipped, and the output says so.
  ``--stride1 K`` feeds only every K-th scan on setup-1 tours (default 1: the 11 mm spacing
  of the paper; each fed scan carries its own odometry pose, so the increments stay
  consistent); the table states the stride. ``--real-stride K`` does the same on the real logs,
  each block of K scans feeding its first referenced scan (:func:`fed_scans`). It asks a tuning
  log what a faster robot would see: a search's work is spread over scans, so it costs travel
  in proportion to the distance between scans. Median step while moving: intel 0.06 m (every
  0.09 s, 0.65 m/s), fr079 0.10 m (0.21 s, 0.45 m/s), mit-csail 0.21 m (0.21 s, 1.0 m/s);
  fr079 with K = 2 steps as far as mit-csail, intel with K = 4.
- scored scan: in simulation every scan; on a real log a scan with a flag-1 (GMapping-
  corrected) reference, as in ``bench_real.py`` (a scan without one is not scored). intel has
  one every ~17 scans (~0.8 m), mit-csail every ~4 scans (~1 m), fr079 nearly every scan, so
  on intel and mit-csail the travel to a fix is rounded up to the next scored scan.
- found (correctly fixed): the first scored estimate with status ``tracking`` that is within
  0.5 m and 10 deg of the truth (the real logs' truth: the scan's reference laser pose).
  Travel to fix: the travel at that scan. "found <= limit": that travel is at most the travel
  limit; "found at all": anywhere in the trial (up to limit + 5 m).
- confident wrong, first fix: the trial published a scored ``tracking`` estimate that failed
  the 0.5 m / 10 deg test before its correct fix (or had no correct fix): the robot was
  declared found at a wrong place.
- confident wrong after the fix: scored ``tracking`` estimates after the first correct fix
  that fail the tour's own test: ``Setup.passed`` (setup 1: 100 mm / 45 deg, setup 2:
  500 mm / 45 deg) in simulation, 0.5 m on the real logs. Reported as trials with any, and as
  % of the scored tracking estimates after the fix.
- searching again after fix: trials in which the localiser, after the correct fix, lost
  the track and fed scans to the global search again (``search_after_fix`` in the CSV: how
  many scans).
- CPU to fix: ``time.process_time`` summed over the ``update`` calls from the start scan up
  to and including the fix (the worker process' CPU time, unaffected by the other process).
- search-scan ms: wall time (``perf_counter``) of single ``update`` calls made while the
  localiser was searching (``GlobalShapeLocalizer.searching`` before the call; for a
  localiser without that flag: the previous status was not ``tracking``), i.e. how long one
  scan's search blocks a worker. Max and p99 pooled over all trials of the row.
- search work max: the largest deterministic work (``GlobalShapeLocalizer.work_ms``,
  reference ms of ``global_search.WORK_MS``) one searching scan spent: what the budget bounds,
  independent of the machine's load.
- hypotheses: the live hypotheses the estimate reports, read as ``est.hypotheses`` when the
  core has that field, else ``est.extras["hypotheses"]`` (a count, or the length of a list);
  mean over the search scans that report it; "–" when none does.
- percentiles of travel and CPU to fix are over ALL trials of a row, a trial without a correct
  fix counting as infinite ("n/f": the percentile falls on such trials).
- s / trial: mean wall time of a trial in its worker (the machine's load is in the output).
- plan share (a second table): found within the limit / trials split by the trial's mean plan
  share (``bench/plan_share.py``), and each trial not fixed within the limit with the travel
  from which the map holds (``global_drive.holds_from``) and the travel to its fix: a trial
  that starts where the map does not show what the robot sees is limited by the map.

Cost (measured at commit 312191d, CPU s per trial): setup 1 ~3 (911 scans tracked at ~3 ms;
the fix itself ~0.3), setup 2 ~2-4, real logs ~25 on average (a trial that never fixes
searches every scan: ~95 on fr079's metric map); a new world's two view indexes ~40 once
(then cached). The defaults (800 simulated + 60 real trials) are ~4200 CPU s, ~35 min on two
free cores; ``--starts 100`` ~2700 CPU s; ``--stride1 4`` saves ~3/4 of setup 1's cost.

Work is spread over ``--jobs`` processes (spawned; one trial per task). Each map's view index
is first made ready once (built, or loaded from ``--cache``, git-ignored ``build/``) by one task
per map, then every process loads it from that cache once and keeps it in memory for all its
trials. Writes ``drive.md`` (tables, command, commit, date, load) and ``drive.csv`` (one row
per trial) under ``--out`` (git-ignored ``build/bench_global`` unless given), and with
``--results`` the results page ``drive.md`` there.

Code: this file holds the command line (:func:`main`) and the single-scan benchmark above;
the drive trials live in ``global_drive.py`` (maps, tours, start choice, scoring),
``global_drive_run.py`` (the trial loop, the process pool, :func:`drive_main`) and
``global_drive_tables.py`` (the tables and the CSV).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

from bench.global_drive import (
    REAL_LOGS,
    DriveMap,
    DriveTrial,
    choose_starts,
    classify,
    cumulative_travel,
    drive_localizer,
    drive_maps,
    drive_source,
    fed_scans,
    fix_ok,
    hypotheses_of,
    load_average,
    office_room,
    spread,
    trial_end,
)
from bench.global_drive_run import drive_main
from bench.global_drive_tables import pct_inf, share_table
from service.adapters.maps.index_files import IndexFiles
from service.core.factory import create_localizer
from service.core.reloc import view_index as vi
from service.core.types import wrap_angle
from sim_publisher.office import office_metric_map, office_schematic_map, office_world
from sim_publisher.publisher import random_free_poses
from sim_publisher.scenario import make_setup
from sim_publisher.trajectory import simulate_odometry

#: The single-scan benchmark and ``main`` are this module's own; the drive benchmark's names
#: that ``tests/bench/test_bench_global_drive.py`` and ``bench_work_model.py`` read as
#: ``bench_global.X`` are re-exported from ``global_drive`` / ``global_drive_tables``.
__all__ = [
    "MAPS",
    "REAL_LOGS",
    "DriveMap",
    "DriveTrial",
    "choose_starts",
    "classify",
    "cumulative_travel",
    "drive_localizer",
    "drive_main",
    "drive_maps",
    "drive_source",
    "fed_scans",
    "fix_ok",
    "hypotheses_of",
    "load_average",
    "main",
    "office_room",
    "pct_inf",
    "precompute",
    "random_trials",
    "setup_run",
    "share_table",
    "spread",
    "trial_end",
    "trial_poses",
]

MAPS = {"metric": (office_metric_map, 1), "schematic": (office_schematic_map, 2)}


def precompute(name: str, cache: Path) -> tuple[float, float, int, int]:
    """(cold build s, cached load s, viewpoints, units) of one map."""
    md = MAPS[name][0]()
    vi.clear_memory_cache()
    t0 = time.perf_counter()
    idx = vi.load_or_build_index(md, store=IndexFiles(cache))
    cold = time.perf_counter() - t0
    vi.clear_memory_cache()
    t0 = time.perf_counter()
    vi.load_or_build_index(md, store=IndexFiles(cache))
    warm = time.perf_counter() - t0
    return cold, warm, len(idx.viewpoints), len(idx)


def trial_poses(start: np.ndarray, motion: str, world, turn: float = np.pi / 2) -> np.ndarray:
    """The up to 3 true poses of one trial (map frame). ``creep``: 3 cm forward per scan (stays
    put if that would leave free space). ``look-around``: turns in place by ``turn`` per scan."""
    if motion == "look-around":
        return np.array([[start[0], start[1], wrap_angle(start[2] + s * turn)] for s in range(3)])
    out = []
    for s in range(3):
        p = start + np.array([0.03 * s * np.cos(start[2]), 0.03 * s * np.sin(start[2]), 0.0])
        out.append(p if world.is_free(p[:2], 0.25)[0] else start.copy())
    return np.array(out)


def random_trials(name: str, n: int, seed: int, motion: str = "creep") -> dict[str, float]:
    """Found / wrong / unresolved fractions and time-to-first-fix percentiles. ``motion`` as in
    :func:`trial_poses`; look-around trials send odometry (``simulate_odometry``: about 1-3 %
    rotation error), creep trials send none."""
    md = MAPS[name][0]()
    su = make_setup(MAPS[name][1], max_scans=2)
    world = office_world()
    found = wrong = 0
    ttf: list[float] = []
    scans_needed: list[int] = []
    rooms: dict[str, list[int]] = {}  # room -> [trials, found, wrong]
    for k, start in enumerate(random_free_poses(world, n, seed)):
        room = rooms.setdefault(office_room(start[0], start[1]), [0, 0, 0])
        room[0] += 1
        truth = trial_poses(start, motion, world)
        odom = simulate_odometry(truth, seed=1000 + k) if motion == "look-around" else None
        loc = create_localizer("shape", md, None)
        spent = 0.0
        for s in range(3):
            p = truth[s]
            r, a = su.laser.scan(p, 1000 * k + s)
            t0 = time.perf_counter()
            est = loc.update(r, a, None if odom is None else odom[s])
            spent += time.perf_counter() - t0
            if est.status == "tracking":
                ok = np.hypot(*(est.pose[:2] - p[:2])) < 0.5 and abs(
                    wrap_angle(float(est.pose[2] - p[2]))
                ) < np.deg2rad(10.0)
                found += bool(ok)
                wrong += not ok
                room[1 if ok else 2] += 1
                if ok:
                    ttf.append(spent)
                    scans_needed.append(s + 1)
                break
    t = np.asarray(ttf) if ttf else np.full(1, np.nan)
    return {
        "n": n,
        "found": found / n,
        "wrong": wrong / n,
        "none": (n - found - wrong) / n,
        "ttf50": float(np.percentile(t, 50)),
        "ttf95": float(np.percentile(t, 95)),
        "scans_mean": float(np.mean(scans_needed)) if scans_needed else float("nan"),
        "rooms": rooms,
    }


def setup_run(setup: int, max_scans: int | None) -> dict[str, float]:
    """Full setup with initial_pose null: tracking poses passing the proximity test."""
    su = make_setup(setup, max_scans=max_scans)
    loc = create_localizer("shape", su.map_data, None)
    tracking = passed = first_fix = lost = 0
    first = None
    t0 = time.perf_counter()
    for i in range(len(su)):
        est = loc.update(*su.scan(i))
        if est.status == "tracking":
            tracking += 1
            passed += su.passed(i, est.pose)
            if first is None:
                first = i
        elif est.status == "lost":
            lost += 1
    first_fix = -1 if first is None else first
    return {
        "scans": len(su),
        "tracking": tracking,
        "passed": passed / tracking if tracking else float("nan"),
        "first_fix_scan": first_fix,
        "lost": lost,
        "seconds": time.perf_counter() - t0,
    }


def main(argv: list[str] | None = None) -> int:
    """Run the measurements and print the tables."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=200, help="random poses per map")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--maps", default="metric,schematic")
    ap.add_argument("--setup-scans", type=int, default=None, help="truncate the setups")
    ap.add_argument("--no-setups", action="store_true", help="skip the full-setup runs")
    ap.add_argument(
        "--motions", default="creep,look-around", help="trial motions (creep, look-around)"
    )
    drive = ap.add_argument_group("drive trials (--drive; see the module docstring)")
    drive.add_argument("--drive", action="store_true", help="run the drive trials instead")
    drive.add_argument("--groups", default="office,worlds,real", help="office,worlds,real")
    drive.add_argument(
        "--starts", type=int, default=200, help="starts per office setup and per worlds setup"
    )
    drive.add_argument(
        "--worlds", default="8", help="held-out worlds: a count N (seeds 1000..999+N), a-b or a,b"
    )
    drive.add_argument(
        "--kinds", default="metric,schematic", help="map kinds: metric and/or schematic"
    )
    drive.add_argument(
        "--clutter",
        type=float,
        default=None,
        help="the buildings' furniture density (generator's BuildingParams.clutter, at most "
        "0.25; default the office's 0.089): the floor plan is the same, the scans see more "
        "furniture (a plan share below 0.5 on some tours, as in real furnished halls)",
    )
    drive.add_argument("--real-starts", type=int, default=40, help="starts per real log and map")
    drive.add_argument("--logs", default=",".join(REAL_LOGS), help="real logs")
    drive.add_argument("--data", type=Path, default=Path("/work/shared/data/real"))
    drive.add_argument("--jobs", type=int, default=2, help="processes (1: in this process)")
    drive.add_argument(
        "--quick", type=int, default=None, help="smoke run: at most N starts per map and world"
    )
    drive.add_argument("--stride1", type=int, default=1, help="feed every k-th setup-1 scan")
    drive.add_argument("--real-stride", type=int, default=1, help="feed every k-th real scan")
    drive.add_argument(
        "--budget-ms",
        type=float,
        default=50.0,
        help="per-scan search budget, reference ms (the service's default 50; 0: whole search)",
    )
    drive.add_argument(
        "--results",
        type=Path,
        default=None,
        help="also write the results page drive.md there (docs/results)",
    )
    drive.add_argument(
        "--calibrate",
        default=None,
        help="calibration: no fix is ever made; each searching scan's decision LLR, its "
        "leader's error and whether its twin check ran are saved per trial into this dir "
        "(bench/calibrate_llr.py reads them)",
    )
    drive.add_argument(
        "--calibrate-pass",
        default=None,
        help="the probation's calibration (floor plans): no probation ever passes; on each "
        "scan a probation is judged, the decision's LLR, the winner's error and whether it led "
        "are saved per trial into this dir (bench/calibrate_llr.py --pass reads them)",
    )
    drive.add_argument(
        "--cache",
        type=Path,
        default=Path(__file__).resolve().parents[1] / "build" / "bench_global" / "index",
    )
    drive.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parents[1] / "build" / "bench_global"
    )
    args = ap.parse_args(argv)
    if args.drive:
        if args.stride1 < 1 or args.real_stride < 1:
            ap.error("--stride1 and --real-stride must be >= 1")
        return drive_main(args, sys.argv[1:] if argv is None else argv)
    maps = [m.strip() for m in args.maps.split(",") if m.strip()]
    print(f"load average at start: {load_average()}")
    with tempfile.TemporaryDirectory() as tmp:
        print("\n| map | viewpoints | units | precompute cold s | cached load s |")
        print("|---|---|---|---|---|")
        for m in maps:
            cold, warm, v, u = precompute(m, Path(tmp))
            print(f"| {m} | {v} | {u} | {cold:.1f} | {warm:.2f} |")
    motions = [m.strip() for m in args.motions.split(",") if m.strip()]
    print(
        f"\n{args.poses} random free-space poses per map (seed {args.seed}), no initial pose, "
        "<= 3 scans; creep: 3 cm forward between scans, no odometry; look-around: turning "
        "90 deg in place between scans, odometry sent"
    )
    print(
        "| map | motion | found < 0.5 m, < 10 deg | confident wrong | no fix in 3 scans "
        "| scans to fix (mean) | first fix p50 s | p95 s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    by_room = {}
    for m in maps:
        for motion in motions:
            r = random_trials(m, args.poses, args.seed, motion)
            by_room[(m, motion)] = r["rooms"]
            print(
                f"| {m} | {motion} | {100 * r['found']:.1f} % | {100 * r['wrong']:.1f} % | "
                f"{100 * r['none']:.1f} % | {r['scans_mean']:.2f} | {r['ttf50']:.2f} | "
                f"{r['ttf95']:.2f} |",
                flush=True,
            )
    names = sorted({k for rooms in by_room.values() for k in rooms})
    print("\nBy room of the start pose: found / trials (confident wrong, if any)")
    print("| map | motion | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for (m, motion), rooms in by_room.items():
        cells = []
        for k in names:
            t, f, w = rooms.get(k, [0, 0, 0])
            cells.append(f"{f}/{t}" + (f" ({w})" if w else ""))
        print(f"| {m} | {motion} | " + " | ".join(cells) + " |")
    print(f"load average: {load_average()}")
    if not args.no_setups:
        print("\nFull setups with initial_pose null (no confident wrong poses)")
        print(
            "| setup | scans | tracking | tracking poses passing | first fix at scan | lost | s |"
        )
        print("|---|---|---|---|---|---|---|")
        for st in (1, 2):
            r = setup_run(st, args.setup_scans)
            print(
                f"| {st} | {r['scans']} | {r['tracking']} | {100 * r['passed']:.2f} % | "
                f"{r['first_fix_scan']} | {r['lost']} | {r['seconds']:.0f} |"
            )
        print(f"load average: {load_average()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
