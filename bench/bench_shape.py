"""Per-scan time of the shape-based localiser, broken down by stage.

Runs a stretch of setup 1 (metric map) and setup 2 (schematic map) on one core (BLAS threads
pinned to 1), without and with odometry, and prints, per setup and mode, p50 / p99 / mean
milliseconds per scan of every stage:

* extraction  — grouping + first-stage DCE of the scan (``scan_configuration``)
* map view    — abstract sensor reading (ray cast + grouping + DCE; cached, so mostly 0)
* heading     — heading (cut-point) hypotheses and support scoring (KD-tree queries)
* S*          — shape distances (step 1 and step 2, including S* preparation)
* ΔA fits     — induced alignments of candidate pairs (vectorised point-to-line fits)
* DP          — the eq. 5 dynamic programme itself
* pose        — least squares over matched pairs (``pose_from_matches``)
* fit         — the precise point-to-line fit (``refine_pose``), every candidate
* walls       — beams through map walls per candidate (``ShapeLocalizer.violations``)
* total       — the whole ``ShapeLocalizer.update``; "other" = total minus the stages

The first updates of the process (loading or compiling the numba kernels) run before the
measurement and their time is printed separately.

Usage: ``python -m bench.bench_shape [--scans1 600] [--scans2 150]``. The stages are timed by
wrapping the core's functions in this script only; numbers are wall-clock and noisy on a
shared machine (the header prints the load average).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")

import argparse
import itertools
import time
from collections import defaultdict
from collections.abc import Callable
from typing import Any

import numpy as np

import service.core.shapes.configuration as conf_mod
import service.core.shapes.matching as match_mod
import service.core.shapes.shape_cost as cost_mod
import service.core.shapes.two_step as step_mod
import service.core.tracking.localizer as loc_mod
from service.core import kernels
from sim_publisher.scenario import make_setup

STAGES = ("extraction", "map view", "heading", "S*", "ΔA fits", "DP", "pose", "fit", "walls")
_acc: dict[str, float] = defaultdict(float)


def _timed(stage: str, fn: Callable[..., Any]) -> Callable[..., Any]:
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            _acc[stage] += time.perf_counter() - t0

    return wrapper


def _install() -> None:
    """Wrap each stage's function where the localiser looks it up (the module that calls it)."""
    loc_mod.scan_configuration = _timed("extraction", loc_mod.scan_configuration)
    conf_mod.MapViewCache.view = _timed("map view", conf_mod.MapViewCache.view)
    step_mod.heading_hypotheses = _timed("heading", step_mod.heading_hypotheses)
    step_mod.support = _timed("heading", step_mod.support)
    cost_mod.shape_distance = _timed("S*", cost_mod.shape_distance)
    cost_mod.shape_distances = _timed("S*", cost_mod.shape_distances)  # the batched S*
    cost_mod.prepare = _timed("S*", cost_mod.prepare)
    step_mod.fit_pairs = _timed("ΔA fits", step_mod.fit_pairs)
    match_mod.fit_pairs_ranges = _timed("ΔA fits", match_mod.fit_pairs_ranges)
    match_mod.order_preserving_dp = _timed("DP", match_mod.order_preserving_dp)
    step_mod.pose_from_matches = _timed("pose", step_mod.pose_from_matches)
    loc_mod.refine_pose = _timed("fit", loc_mod.refine_pose)
    loc_mod.ShapeLocalizer.violations = _timed("walls", loc_mod.ShapeLocalizer.violations)


def bench(setup_id: int, scans: int, odom: bool) -> dict[str, np.ndarray]:
    """Per-scan seconds of every stage over the first ``scans`` scans of a setup, with the
    simulated odometry as motion prior or without (the paper's mode)."""
    s = make_setup(setup_id, seed=0, max_scans=scans)
    loc = loc_mod.ShapeLocalizer(s.map_data, s.truth[0])
    rows: dict[str, list[float]] = defaultdict(list)
    data = [(*s.scan(i), s.odom[i] if odom else None) for i in range(len(s))]
    for ranges, angles, o in data:
        _acc.clear()
        t0 = time.perf_counter()
        loc.update(ranges, angles, o)
        total = time.perf_counter() - t0
        for st in STAGES:
            rows[st].append(_acc.get(st, 0.0))
        rows["other"].append(total - sum(_acc.get(st, 0.0) for st in STAGES))
        rows["total"].append(total)
    return {k: np.asarray(v) for k, v in rows.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans1", type=int, default=600, help="scans of setup 1 (default 600)")
    ap.add_argument("--scans2", type=int, default=150, help="scans of setup 2 (default 150)")
    args = ap.parse_args()
    _install()
    load = os.getloadavg()
    print(f"shape localiser, 361 beams, 1 BLAS thread; load average {load[0]:.2f} {load[1]:.2f}")
    # The first update of a process loads the compiled kernels (numba's on-disk cache) or
    # compiles them; reported here once and kept out of the per-scan statistics.
    warm = make_setup(2, seed=0, max_scans=3)
    t0 = time.perf_counter()
    wl = loc_mod.ShapeLocalizer(warm.map_data, warm.truth[0])
    for i in range(len(warm)):
        wl.update(*warm.scan(i))
    kind = "numba" if kernels.HAVE_NUMBA else "numpy/Python reference (numba not installed)"
    print(
        f"kernels {kind}; "
        f"first updates of this process (kernel load or compile): {time.perf_counter() - t0:.2f} s"
    )
    for (setup_id, n), odom in itertools.product(((1, args.scans1), (2, args.scans2)), (0, 1)):
        if n <= 0:
            continue
        res = bench(setup_id, n, bool(odom))
        mode = "with odometry" if odom else "no odometry (paper)"
        print(f"\nsetup {setup_id}, {mode}: {n} scans   (ms per scan)")
        print(f"{'stage':<12} {'p50':>8} {'p99':>8} {'mean':>8}")
        for st in (*STAGES, "other", "total"):
            v = 1000.0 * res[st]
            print(
                f"{st:<12} {np.percentile(v, 50):8.2f} {np.percentile(v, 99):8.2f} {v.mean():8.2f}"
            )


if __name__ == "__main__":
    main()
