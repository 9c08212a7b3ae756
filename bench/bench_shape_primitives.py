"""Timing of the shape primitives (grouping, DCE, S*, partial optimal similarity, complexity).

Usage: ``.venv/bin/python -m bench.bench_shape_primitives [--scans N] [--seed S]``

Inputs are realistic: simulated 361-beam scans of setup 1 (office tour, exact metric map,
furniture, 1 cm noise) spread evenly along the tour. S* is timed on every pair of DCE'd
polylines of two consecutive scans (what a matcher would compare), bucketed by the larger
vertex count. Prints microseconds per call, p50 / p99 / mean, and the machine load (the
numbers are wall-clock and noisy on a shared machine).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

import numpy as np

from service.core.shapes.dce import DCE_NOISE_THRESHOLD, dce, refine_vertices
from service.core.shapes.polylines import group_polylines
from service.core.shapes.similarity import (
    partial_optimal_similarity,
    prepare,
    shape_complexity,
    shape_distance,
)
from sim_publisher.scenario import make_setup


def timed(fn: Callable[[], object], repeat: int = 3) -> float:
    """Best of ``repeat`` wall-clock runs of ``fn()``, microseconds."""
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter_ns()
        fn()
        best = min(best, (time.perf_counter_ns() - t0) / 1e3)
    return best


def row(name: str, samples: list[float], note: str = "") -> str:
    a = np.asarray(samples)
    if a.size == 0:
        return f"{name:<34} {'-':>8} {'-':>8} {'-':>8} {0:>7}  {note}"
    return (
        f"{name:<34} {np.percentile(a, 50):8.1f} {np.percentile(a, 99):8.1f} "
        f"{a.mean():8.1f} {a.size:7d}  {note}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=40, help="number of scan pairs (default 40)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    setup = make_setup(1, seed=args.seed)
    idx = np.linspace(0, len(setup) - 2, args.scans).astype(int)

    t_group: list[float] = []
    t_dce: list[float] = []
    t_refine: list[float] = []
    t_bounded: list[float] = []
    t_extract: list[float] = []
    t_prep: list[float] = []
    t_cplx: list[float] = []
    t_po: list[float] = []
    t_pairs_scan: list[float] = []
    buckets: dict[str, list[float]] = {"2": [], "3-4": [], "5-8": [], "9+": []}
    raw_pairs: list[float] = []
    n_polys: list[int] = []
    n_verts: list[int] = []

    def bucket(k: int) -> str:
        return "2" if k <= 2 else "3-4" if k <= 4 else "5-8" if k <= 8 else "9+"

    for i in idx:
        scans = [setup.scan(int(i)), setup.scan(int(i) + 1)]
        simplified: list[list[np.ndarray]] = []
        raws: list[list[np.ndarray]] = []
        for r, a in scans:
            t_group.append(timed(lambda r=r, a=a: group_polylines(r, a)))
            pls = group_polylines(r, a)
            t_dce.append(timed(lambda pls=pls: [dce(p.points) for p in pls]))
            t_extract.append(timed(lambda r=r, a=a: [dce(p.points) for p in group_polylines(r, a)]))
            keeps = [dce(p.points) for p in pls]
            t_refine.append(
                timed(
                    lambda pls=pls, keeps=keeps: [
                        refine_vertices(p.points, k) for p, k in zip(pls, keeps, strict=True)
                    ]
                )
            )
            simplified.append([p.points[k] for p, k in zip(pls, keeps, strict=True)])
            raws.append([p.points for p in pls])
        n_polys.append(len(simplified[0]))
        n_verts.extend(len(v) for v in simplified[0])
        for v in simplified[0]:
            t_prep.append(timed(lambda v=v: prepare(v)))
            t_cplx.append(timed(lambda v=v: shape_complexity(v)))
        P = [prepare(v) for v in simplified[0]]
        Q = [prepare(v) for v in simplified[1]]
        t_pairs_scan.append(timed(lambda P=P, Q=Q: [shape_distance(p, q) for p in P for q in Q]))
        for p, pv in zip(P, simplified[0], strict=True):
            for q, qv in zip(Q, simplified[1], strict=True):
                buckets[bucket(max(p.k, q.k))].append(timed(lambda p=p, q=q: shape_distance(p, q)))
                t_bounded.append(timed(lambda p=p, q=q: shape_distance(p, q, upper_bound=0.5)))
                if len(raw_pairs) < 2000:
                    raw_pairs.append(timed(lambda pv=pv, qv=qv: shape_distance(pv, qv)))
        # partial optimal similarity: each raw scan polyline vs its most similar next-scan one
        for raw, p in zip(raws[0], P, strict=True):
            ds = [shape_distance(p, q) for q in Q]
            if not ds:
                continue
            qv = simplified[1][int(np.argmin(ds))]
            t_po.append(timed(lambda raw=raw, qv=qv: partial_optimal_similarity(raw, qv)))

    load = os.getloadavg()
    print(
        f"shape primitives, setup 1 scans (361 beams), {len(idx)} scan pairs, "
        f"DCE threshold {DCE_NOISE_THRESHOLD} m; load avg {load[0]:.2f} {load[1]:.2f} "
        f"{load[2]:.2f} on {os.cpu_count()} cpus"
    )
    print(
        f"polylines per scan: mean {np.mean(n_polys):.1f}; vertices per polyline after DCE: "
        f"mean {np.mean(n_verts):.1f}, p90 {np.percentile(n_verts, 90):.0f}, "
        f"max {max(n_verts)}"
    )
    print(f"{'operation [us]':<34} {'p50':>8} {'p99':>8} {'mean':>8} {'n':>7}")
    print(row("group_polylines (per scan)", t_group))
    print(row("dce, all polylines (per scan)", t_dce))
    print(row("group + dce (per scan)", t_extract))
    print(row("refine_vertices, all (per scan)", t_refine))
    print(row("prepare (per polyline)", t_prep))
    print(row("shape_complexity (per polyline)", t_cplx))
    for name, samples in buckets.items():
        print(row(f"shape_distance prepared, k<={name}", samples, "max vertices of the pair"))
    allp = [x for s in buckets.values() for x in s]
    print(row("shape_distance prepared, all", allp))
    print(row("shape_distance, upper_bound=0.5", t_bounded, "pruned search"))
    print(row("shape_distance from arrays", raw_pairs, "incl. prepare of both"))
    print(row("S* all pairs of 2 scans (per scan)", t_pairs_scan, "n_p x n_q calls"))
    print(row("partial_optimal_similarity", t_po, "raw grouped points vs DCE'd q"))


if __name__ == "__main__":
    main()
