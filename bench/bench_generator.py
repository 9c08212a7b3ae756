"""Building generator: time per building and the achieved tour statistics per setup.

    .venv/bin/python -m bench.bench_generator [--seeds 0-19,1000-1019] [--people N]
    .venv/bin/python -m bench.bench_generator --figure docs/generated_buildings.png

For every seed: the building drawn (type, layout, size, rooms, furniture items, clutter), the
time to generate it (shell, furniture, tour, people), the time to build both setups from it
(truth poses, odometry, laser, metric and schematic maps), the tour's minimum clearance
(exact, every 4 mm) and, per setup, the number of scans and the achieved mean step (mm) and
mean rotation per step (deg) against the seed paper's 11 mm / 4.0 deg and 104 mm / 30.6 deg.
One thread; wall-clock times on a shared machine: the load average is printed. Needs nothing
from /work/shared. ``--figure`` instead draws four buildings (one per layout; true world with
the tour above, schematic map below) with matplotlib.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from sim_publisher.generator import BuildingParams, generate_building  # noqa: E402
from sim_publisher.scenario import building_setup  # noqa: E402
from sim_publisher.trajectory import run_stats  # noqa: E402


def _seeds(spec: str) -> list[int]:
    out: list[int] = []
    for part in spec.split(","):
        a, _, b = part.partition("-")
        out.extend(range(int(a), int(b or a) + 1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-19,1000-1019", help="e.g. 0-19,1000-1019")
    ap.add_argument("--people", type=int, default=0, help="moving people per building")
    ap.add_argument("--figure", help="write the docs figure (PNG) instead of the table")
    args = ap.parse_args()
    if args.figure:
        figure(args.figure)
        return
    params = BuildingParams(people=args.people)
    generate_building(0, params)  # warm-up (imports, numba-free caches)
    head = (
        f"{'seed':>5} {'type':<8} {'layout':<8} {'size m':>11} {'rooms':>5} {'items':>5} "
        f"{'clutter':>7} {'gen s':>6} {'setups s':>8} {'clear m':>7} | "
        f"{'s1 scans':>8} {'step mm':>7} {'turn deg':>8} | {'s2 scans':>8} {'step mm':>7} "
        f"{'turn deg':>8}"
    )
    print(head)
    rows = []
    for seed in _seeds(args.seeds):
        t0 = time.perf_counter()
        b = generate_building(seed, params)
        t1 = time.perf_counter()
        s1, s2 = building_setup(b, 1), building_setup(b, 2)
        t2 = time.perf_counter()
        st1, st2 = run_stats(s1.truth), run_stats(s2.truth)
        clear = float(b.world.clearance(np.asarray(b.tour.xy[::2])).min())
        rows.append((t1 - t0, t2 - t1, st1, st2, len(s1), len(s2)))
        print(
            f"{seed:>5} {b.building_type:<8} {b.layout:<8} {b.width:>5.1f}x{b.height:<5.1f} "
            f"{len(b.rooms):>5} {len(b.items):>5} {b.clutter:>7.3f} {t1 - t0:>6.2f} "
            f"{t2 - t1:>8.3f} {clear:>7.3f} | {len(s1):>8} {st1['mean_step_mm']:>7.2f} "
            f"{st1['mean_rotation_deg']:>8.2f} | {len(s2):>8} {st2['mean_step_mm']:>7.2f} "
            f"{st2['mean_rotation_deg']:>8.2f}",
            flush=True,
        )
    gen = np.array([r[0] for r in rows])
    tot = gen + np.array([r[1] for r in rows])
    for k, name, paper in ((2, "setup 1", (11.0, 4.0)), (3, "setup 2", (104.0, 30.6))):
        step = np.array([r[k]["mean_step_mm"] for r in rows])
        turn = np.array([r[k]["mean_rotation_deg"] for r in rows])
        print(
            f"{name}: mean step {step.mean():.2f} mm (range {step.min():.2f}-{step.max():.2f}; "
            f"paper {paper[0]}), mean turn {turn.mean():.2f} deg (range {turn.min():.2f}-"
            f"{turn.max():.2f}; paper {paper[1]})"
        )
    print(
        f"scans per building: setup 1 max {max(r[4] for r in rows)}, setup 2 max "
        f"{max(r[5] for r in rows)}"
    )
    print(
        f"time per building (generate + both setups): mean {tot.mean():.2f} s, p50 "
        f"{np.median(tot):.2f} s, max {tot.max():.2f} s; generate alone max {gen.max():.2f} s"
    )
    print(f"load average: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


def figure(path: str, seeds: tuple[int, ...] = (11, 2, 1, 9)) -> None:
    """Four generated buildings: true world + tour (top), schematic map (bottom)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from shapely.plotting import plot_polygon

    from sim_publisher.generator import SchematicParams

    fig, axs = plt.subplots(2, len(seeds), figsize=(4.2 * len(seeds), 8.0))
    for k, seed in enumerate(seeds):
        b = generate_building(seed, BuildingParams(people=3))
        ax = axs[0, k]
        for o in b.world.obstacles:
            wall = o.kind == "wall"
            plot_polygon(
                o.geometry,
                ax=ax,
                add_points=False,
                linewidth=0.3,
                color="black" if wall else "tab:blue",
                facecolor="0.35" if wall else "lightsteelblue",
            )
        ax.plot(b.tour.xy[:, 0], b.tour.xy[:, 1], color="tab:red", lw=1.0)
        ax.plot(*b.tour.xy[0], "o", color="tab:green", ms=4)
        for p in b.people:
            ax.plot(p.path[:, 0], p.path[:, 1], ":", color="tab:purple", lw=0.7)
        ax.set_title(
            f"seed {seed}: {b.building_type}, {b.layout}, {b.width:.0f} x {b.height:.0f} m",
            fontsize=9,
        )
        sm = b.schematic(SchematicParams(closed_doors=0.25))
        ax2 = axs[1, k]
        for pl in sm.map_data.polylines:
            ax2.plot(pl[:, 0], pl[:, 1], color="black", lw=0.7)
        ax2.set_title(
            f"schematic: scale {100 * (sm.scale - 1):+.1f} %, {len(sm.closed_doors)} doors closed",
            fontsize=9,
        )
        for a in (ax, ax2):
            a.set_aspect("equal")
            a.set_xlim(-0.5, b.width + 0.5)
            a.set_ylim(-0.5, b.height + 0.5)
            a.tick_params(labelsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=72)
    print("wrote", path)


if __name__ == "__main__":
    main()
