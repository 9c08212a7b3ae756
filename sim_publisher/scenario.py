"""The paper's two experimental setups on the office world (section 6).

Setup 1: exact metric map, a scan every ~11 mm of the tour (~3900 scans), proximity test
100 mm / 45 deg. Setup 2: schematic map, a scan every ~104 mm of the same tour (~410 scans),
proximity test 500 mm / 45 deg. In both, scans are simulated against the TRUE office world
(furniture included). Poses are map-frame ``[x, y, theta]`` (m, m, rad).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from service.core.types import MapData
from service.errors import InvalidMessage
from service.maps.world import World
from sim_publisher.laser import LaserConfig, LaserSimulator
from sim_publisher.office import office_metric_map, office_schematic_map, office_world
from sim_publisher.trajectory import (
    STEP_SETUP1,
    STEP_SETUP2,
    run_stats,
    simulate_odometry,
    tour_poses,
)

__all__ = ["Setup", "make_setup", "run_stats"]


@dataclass
class Setup:
    """One experiment: the map given to the localiser, true poses, drifting odometry and a
    laser simulator bound to the true world.

    ``truth`` and ``odom`` are ``(n, 3)``; ``odom`` starts at ``truth[0]`` and is meant for the
    baselines only. ``proximity_mm``/``proximity_deg`` are the paper's pass thresholds.
    """

    name: str
    map_data: MapData
    truth: np.ndarray
    odom: np.ndarray
    laser: LaserSimulator
    proximity_mm: float
    proximity_deg: float = 45.0
    step_m: float = STEP_SETUP1
    world: World = field(default_factory=office_world, repr=False)

    def __len__(self) -> int:
        return int(self.truth.shape[0])

    def scan(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan ``i`` at the true pose ``truth[i]``: ``(ranges m, NaN = no return; angles rad
        robot frame)``. Deterministic in (seed, i)."""
        if not 0 <= i < len(self):
            raise IndexError(f"scan index {i} out of range [0, {len(self)})")
        return self.laser.scan(self.truth[i], i)

    def passed(self, i: int, pose: np.ndarray) -> bool:
        """The paper's proximity test for an estimate of pose ``i``."""
        t = self.truth[i]
        d = float(np.hypot(pose[0] - t[0], pose[1] - t[1]))
        dth = abs((pose[2] - t[2] + np.pi) % (2 * np.pi) - np.pi)
        return d * 1000.0 < self.proximity_mm and np.rad2deg(dth) < self.proximity_deg


def make_setup(
    setup: int, seed: int = 0, max_scans: int | None = None, laser: LaserConfig | None = None
) -> Setup:
    """Build setup 1 (metric map) or 2 (schematic map). ``seed`` drives laser noise and
    odometry; the route is fixed. ``max_scans`` truncates to the first scans."""
    if setup not in (1, 2):
        raise InvalidMessage(f"setup must be 1 or 2, got {setup!r}")
    if max_scans is not None and max_scans < 1:
        raise InvalidMessage(f"max_scans must be >= 1, got {max_scans}")
    world = office_world()
    step = STEP_SETUP1 if setup == 1 else STEP_SETUP2
    truth = tour_poses(step, max_scans)
    odom = simulate_odometry(truth, seed=seed * 10 + setup)
    sim = LaserSimulator(world.segments(), laser or LaserConfig(), seed=seed * 10 + setup)
    if setup == 1:
        return Setup(
            name="setup1-metric",
            map_data=office_metric_map(),
            truth=truth,
            odom=odom,
            laser=sim,
            proximity_mm=100.0,
            step_m=step,
            world=world,
        )
    return Setup(
        name="setup2-schematic",
        map_data=office_schematic_map(),
        truth=truth,
        odom=odom,
        laser=sim,
        proximity_mm=500.0,
        step_m=step,
        world=world,
    )
