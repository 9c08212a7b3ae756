"""Ray casting / laser simulation speed on the office world (single thread).

    .venv/bin/python -m bench.bench_laser [--repeat N]

Prints ms per scan (p50, p95, p99, mean) for 361 and 720 beams, casting from the poses of the
setup-2 tour (~410 poses) against the TRUE office world (all obstacle segments). ``cast`` is
the bare RayCaster; ``scan`` adds noise and dropouts (LaserSimulator). Numbers are wall-clock
and noisy on a shared machine: report them with the `uptime` load.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from service.core.sensor.raycast import RayCaster  # noqa: E402
from sim_publisher.laser import LaserConfig, LaserSimulator  # noqa: E402
from sim_publisher.office import office_world  # noqa: E402
from sim_publisher.trajectory import STEP_SETUP2, tour_poses  # noqa: E402


def _stats(ms: np.ndarray) -> str:
    p50, p95, p99 = np.percentile(ms, [50, 95, 99])
    return f"{p50:8.3f} {p95:8.3f} {p99:8.3f} {ms.mean():8.3f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2, help="passes over the tour poses")
    args = ap.parse_args()
    world = office_world()
    segs = world.segments()
    poses = tour_poses(STEP_SETUP2)
    print(f"office world: {segs.shape[0]} segments, {len(poses)} poses x {args.repeat} passes")
    print(f"{'what':<8}{'beams':>6} {'p50 ms':>8} {'p95 ms':>8} {'p99 ms':>8} {'mean ms':>8}")
    caster = RayCaster(segs)
    for beams in (361, 720):
        cfg = LaserConfig(beams=beams, fov=math.pi if beams == 361 else 2 * math.pi)
        sim = LaserSimulator(segs, cfg, seed=0)
        for what in ("cast", "scan"):
            ms = []
            for _ in range(args.repeat):
                for i, pose in enumerate(poses):
                    t0 = time.perf_counter()
                    if what == "cast":
                        caster.cast(pose, sim.angles, cfg.max_range)
                    else:
                        sim.scan(pose, i)
                    ms.append((time.perf_counter() - t0) * 1e3)
            print(f"{what:<8}{beams:>6} {_stats(np.asarray(ms))}")
    print(f"load average: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
