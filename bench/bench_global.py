"""Global localisation acceptance measurement (prints tables).

``python bench/bench_global.py [--poses 200] [--seed 1] [--maps metric,schematic]
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
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.core import global_localization as gl
from service.core.factory import create_localizer
from service.core.types import wrap_angle
from sim_publisher.office import office_metric_map, office_schematic_map, office_world
from sim_publisher.publisher import random_free_poses
from sim_publisher.scenario import make_setup
from sim_publisher.trajectory import simulate_odometry

MAPS = {"metric": (office_metric_map, 1), "schematic": (office_schematic_map, 2)}


def _load() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def precompute(name: str, cache: Path) -> tuple[float, float, int, int]:
    """(cold build s, cached load s, viewpoints, units) of one map."""
    md = MAPS[name][0]()
    gl.clear_memory_cache()
    t0 = time.perf_counter()
    idx = gl.load_or_build_index(md, cache_dir=cache)
    cold = time.perf_counter() - t0
    gl.clear_memory_cache()
    t0 = time.perf_counter()
    gl.load_or_build_index(md, cache_dir=cache)
    warm = time.perf_counter() - t0
    return cold, warm, len(idx.viewpoints), len(idx)


def office_room(x: float, y: float) -> str:
    """Room of a point of the office world (``sim_publisher/worlds/make_office.py``): west rooms
    W1-W4 (walls at y = 6, 12, 17), the corridor C (5.6 < x < 7.6), east rooms E1-E3 (walls at
    y = 8, 15). W1 and W4 are congruent within 0.2 m (their doors sit 3.0 m and 2.8 m above
    their south walls)."""
    if x < 5.6:
        return "W" + str(1 + int(y > 6.0) + int(y > 12.0) + int(y > 17.0))
    if x > 7.6:
        return "E" + str(1 + int(y > 8.0) + int(y > 15.0))
    return "C"


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
    args = ap.parse_args(argv)
    maps = [m.strip() for m in args.maps.split(",") if m.strip()]
    print(f"load average at start: {_load()}")
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
    print(f"load average: {_load()}")
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
        print(f"load average: {_load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
