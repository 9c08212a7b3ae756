"""The search's work model against this machine's CPU
(``service.core.reloc.global_search.WORK_MS``).

A budgeted search (``GlobalConfig.search_budget_ms``) counts its work in reference ms from a
deterministic model, so the same scans give the same poses on any machine. This bench times
the model's items one by one on the tuning maps and prints, per map and item, the measured
CPU ms per pose next to the model's figure and their ratio. A ratio above 1 means a budget
buys more CPU than it names on that map; well below 1, a search takes more scans (and so
more travel) than the budget would allow.

Items (per pose, on scans of the map's tour at their reference poses, perturbed by
0.2 m / 0.05 rad; the scans' points subsampled as the search does):

- ``polish``: a distance-field polish of 12 poses in one call; ``polish1``: of one pose
  (a keyframe's score);
- ``support``: the point support of 800 poses;
- ``field40``: the shortlist's violation ranking of 800 poses, 40 beams marched on the
  distance field (``GlobalConfig.shortlist_violation_beams``; on every map, though only the
  floor plans run it);
- ``beams90``: the shortlist's 90-beam check;
- ``refine``: the four-stage refinement;
- ``verify``: a verification over ``verify_beams`` beams;
- ``frame``: a keyframe's one-pose polish and beam score (``drive.pair_ms``).

The S* comparisons and induced alignments are not timed here (their cost depends on the
scan's shape, not the map; a drive trial's per-step timing showed them within 0.4-1.5x of
the model).

Maps: office and building 3 (simulated, metric and floor plan), intel and fr079 (real logs,
metric and schematised). The real logs are read from ``--data`` (``../shared/data/real``);
without it only the simulated maps run. mit-csail (held out) is not measured.

Run: ``python -m bench.bench_work_model [--scans 12] [--data ../shared/data/real]``
(~1 min; alone on the machine, as CPU time is measured).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench import bench_global as bg
from service.core.reloc import drive as ev
from service.core.reloc.global_search import (
    FINE_SCALE,
    SUPPORT_POINTS,
    WORK_MS,
    beam_costs,
    cast_ms,
    polish_ms,
    refine,
    refine_ms,
    verify,
    verify_ms,
)
from service.core.sensor.scoring import subsample
from service.core.shapes.configuration import scan_configuration

MAPS = [
    ("office", "office", "metric"),
    ("office", "office", "schematic"),
    ("worlds", "3", "metric"),
    ("worlds", "3", "schematic"),
    ("real", "intel", "metric"),
    ("real", "intel", "schematic"),
    ("real", "fr079", "metric"),
    ("real", "fr079", "schematic"),
]


def model(loc: Any, points: int) -> dict[str, float]:
    """The work model's figure (reference ms per pose) of each timed item on ``loc``'s map."""
    idx, g = loc.index, loc.gconfig
    return {
        "polish": polish_ms(points),
        "polish1": WORK_MS["polish_call"] + polish_ms(points),
        "support": points * WORK_MS["support"],
        "field40": 40 * WORK_MS["field_beam"],
        "beams90": 90 * WORK_MS["beam"] + cast_ms(idx),
        "refine": refine_ms(idx),
        "verify": verify_ms(idx, g),
        "frame": ev.pair_ms(idx, g),
    }


def measure(m: bg.DriveMap, data: Path, scans: int, seed: int) -> tuple[dict[str, float], Any]:
    """CPU ms per pose of each item on ``scans`` scans of ``m``'s tour (a first pass over
    them warms the caches and is not counted)."""
    src = bg.drive_source(m, data, 1)
    loc = bg.drive_localizer(src.map_data, None, 50.0)
    idx, cfg, g = loc.index, loc.config, loc.gconfig
    rng = np.random.default_rng(seed)
    scored = np.flatnonzero(src.scored)
    picks = scored[np.linspace(0, len(scored) - 1, scans).astype(int)]
    clock = time.process_time
    acc: dict[str, list[float]] = {}
    for rep in range(2):
        for i in picks.tolist():
            r, a = src.scan(i)
            P = scan_configuration(r, a, cfg.extraction())
            if not P.features:
                continue
            sp = subsample(np.vstack([f.points for f in P.features]), SUPPORT_POINTS)
            truth = src.truth[i]
            poses = truth + rng.normal(0.0, [0.2, 0.2, 0.05], size=(12, 3))
            many = truth + rng.normal(0.0, [2.0, 2.0, 1.0], size=(800, 3))
            kf = ev.make_frame(0, r, a, np.zeros(3), 0.0, g)
            one = poses[:1]
            laps: list[tuple[str, int, float]] = []
            t0 = clock()
            idx.sensor.polish(poses, sp, FINE_SCALE)
            laps.append(("polish", len(poses), clock() - t0))
            t0 = clock()
            idx.sensor.polish(one, sp, FINE_SCALE, prior=ev.RESCORE_PRIOR)
            laps.append(("polish1", 1, clock() - t0))
            t0 = clock()
            idx.sensor.support(many, sp, cfg.support_tolerance)
            laps.append(("support", len(many), clock() - t0))
            beams = subsample(np.flatnonzero(np.isfinite(r)), 40)
            margin = max(cfg.support_tolerance, g.violation_margin)
            t0 = clock()
            idx.sensor.crossings(many, r[beams], a[beams], margin)
            laps.append(("field40", len(many), clock() - t0))
            t0 = clock()
            beam_costs(idx.sensor, poses, r, a, 90, cfg, g)
            laps.append(("beams90", len(poses), clock() - t0))
            t0 = clock()
            refine(idx, poses, sp, cfg)
            laps.append(("refine", len(poses), clock() - t0))
            t0 = clock()
            for p in poses:
                verify(idx, p, r, a, P, cfg, g)
            laps.append(("verify", len(poses), clock() - t0))
            t0 = clock()
            idx.sensor.polish(one, kf.points, FINE_SCALE, prior=ev.RESCORE_PRIOR)
            ev.frame_cost(idx, one[0], kf, cfg, g)
            laps.append(("frame", 1, clock() - t0))
            if rep:
                for name, n, dt in laps:
                    a_ = acc.setdefault(name, [0.0, 0.0])
                    a_[0] += dt * 1e3
                    a_[1] += n
    return {k: v[0] / v[1] for k, v in acc.items()}, loc


def main(scans: int, data: Path, seed: int) -> int:
    """Print the table (see the module docstring)."""
    rows = []
    for group, world, kind in MAPS:
        if group == "real" and not any(data.glob(f"{world}.*")):
            # the logs are files named after them (intel.orig.bag, mit-csail.clf, ...)
            print(f"skipped {world}: no {data}/{world}.*")
            continue
        m = bg.DriveMap(group, world, kind)
        got, loc = measure(m, data, scans, seed)
        ref = model(loc, SUPPORT_POINTS)
        segs = len(loc.index.sensor.segments)
        for item, ms in got.items():
            rows.append((m.label(), segs, item, ms, ref[item]))
    print("\n| map | segments | item | CPU ms / pose | model ms / pose | ratio |")
    print("|---|---|---|---|---|---|")
    for label, segs, item, ms, ref in rows:
        print(f"| {label} | {segs} | {item} | {ms:.4f} | {ref:.4f} | {ms / ref:.2f} |")
    worst = max((ms / ref, label, item) for label, _s, item, ms, ref in rows) if rows else None
    if worst is not None:
        print(f"\nhighest ratio {worst[0]:.2f} ({worst[2]} on {worst[1]})")
    return 0


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scans", type=int, default=12, help="scans per map")
    ap.add_argument("--data", type=Path, default=Path("/work/shared/data/real"))
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    sys.exit(main(a.scans, a.data, a.seed))
