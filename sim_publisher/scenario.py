"""The paper's two experimental setups on the office world (section 6).

Setup 1: exact metric map, a scan every ~11 mm of the tour (~3900 scans), proximity test
100 mm / 45 deg. Setup 2: schematic map, a scan every ~104 mm of the same tour (~410 scans),
proximity test 500 mm / 45 deg. In both, scans are simulated against the TRUE office world
(furniture included). Poses are map-frame ``[x, y, theta]`` (m, m, rad).

:func:`building_setup` builds the same two setups for a generated building
(:mod:`sim_publisher.generator`): its metric map for setup 1, its schematic map for setup 2,
its tour sampled every 11 / 104 mm, the same laser and odometry models, and, when the building
has moving people, scans that see them where they are at each scan's time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from service.adapters.maps.world import World
from service.core.types import MapData
from service.errors import InvalidMessage
from sim_publisher.laser import LaserConfig, LaserSimulator
from sim_publisher.office import office_metric_map, office_schematic_map, office_world
from sim_publisher.trajectory import (
    STEP_SETUP1,
    STEP_SETUP2,
    OdometryNoise,
    run_stats,
    simulate_odometry,
    tour_poses,
)

if TYPE_CHECKING:
    from sim_publisher.generator import Building, SchematicParams

__all__ = ["Setup", "building_setup", "make_setup", "run_stats"]


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
    #: Time (s) of every scan (None: no clock; only needed with ``dynamic``).
    times: np.ndarray | None = field(default=None, repr=False)
    #: Moving obstacles: time (s) -> circles ``(k, 3)`` ``[x, y, r]`` (m) seen by the laser.
    dynamic: Callable[[float], np.ndarray] | None = field(default=None, repr=False)
    #: The true poses in the map's own frame, when it differs from the world's: a schematic
    #: map drawn with a global scale error ``s`` about a centre ``c`` puts the robot at world
    #: point ``p`` on the map at ``c + (1 + s) (p - c)`` (heading unchanged). ``None``: the
    #: map frame is the world frame.
    map_truth: np.ndarray | None = field(default=None, repr=False)

    @property
    def reference(self) -> np.ndarray:
        """The true poses ``(n, 3)`` a localiser's map-frame estimates are judged against:
        ``map_truth`` when set, else ``truth``. The scans are simulated at ``truth``."""
        return self.truth if self.map_truth is None else self.map_truth

    def __len__(self) -> int:
        return int(self.truth.shape[0])

    def circles(self, i: int) -> np.ndarray | None:
        """The moving obstacles at scan ``i``'s time (None when there are none)."""
        if self.dynamic is None or self.times is None:
            return None
        return self.dynamic(float(self.times[i]))

    def scan(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan ``i`` at the true pose ``truth[i]``: ``(ranges m, NaN = no return; angles rad
        robot frame)``, with the moving obstacles at its time. Deterministic in (seed, i)."""
        if not 0 <= i < len(self):
            raise IndexError(f"scan index {i} out of range [0, {len(self)})")
        return self.laser.scan(self.truth[i], i, self.circles(i))

    def passed(self, i: int, pose: np.ndarray) -> bool:
        """The paper's proximity test for an estimate of pose ``i`` (against the map-frame
        :attr:`reference`)."""
        t = self.reference[i]
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


def building_setup(
    building: Building,
    setup: int,
    seed: int = 0,
    max_scans: int | None = None,
    laser: LaserConfig | None = None,
    schematic: SchematicParams | None = None,
    people: bool = True,
    odometry: OdometryNoise | None = None,
) -> Setup:
    """Setup 1 (exact metric map, a scan every 11 mm, proximity 100 mm / 45 deg) or 2
    (schematic map, every 104 mm, 500 mm / 45 deg) on a generated building, as
    :func:`make_setup` does for the office.

    ``seed`` drives the laser noise and the odometry (``odometry`` overrides its noise model);
    ``schematic`` the schematic map's parameters (setup 2); ``people=False`` hides the moving
    people. Setup 2's ``map_truth`` holds the true poses on the schematic map (its scale error
    applied): the proximity test and the benchmarks judge estimates against them. Scan ``i``
    is taken at time ``s_i / robot_speed`` (``s_i`` its arc length).
    """
    if setup not in (1, 2):
        raise InvalidMessage(f"setup must be 1 or 2, got {setup!r}")
    if max_scans is not None and max_scans < 1:
        raise InvalidMessage(f"max_scans must be >= 1, got {max_scans}")
    step = STEP_SETUP1 if setup == 1 else STEP_SETUP2
    s = building.tour.arc(step, max_scans)
    truth = building.tour.poses_at(s)
    world = building.world
    stream = seed * 10 + setup
    odom = simulate_odometry(truth, seed=stream, noise=odometry)
    sim = LaserSimulator(world.segments(), laser or LaserConfig(), seed=stream)
    map_truth = None
    if setup == 1:
        map_data = building.metric_map()
    else:
        plan = building.schematic(schematic)
        map_data = plan.map_data
        map_truth = truth.copy()
        map_truth[:, :2] = plan.center + plan.scale * (truth[:, :2] - plan.center)
    dynamic = building.people_at if people and building.people else None
    return Setup(
        name=f"{building.name}-setup{setup}-{'metric' if setup == 1 else 'schematic'}",
        map_data=map_data,
        truth=truth,
        odom=odom,
        laser=sim,
        proximity_mm=100.0 if setup == 1 else 500.0,
        step_m=step,
        world=world,
        times=building.times(s),
        dynamic=dynamic,
        map_truth=map_truth,
    )
