"""Worlds, scans and walks of the service scale benchmark (``bench/bench_service.py``).

A :class:`Pool` holds the setup-1 scans of one (world, map) along the world's tour, their
mirror images and the map the service gets (:func:`make_pool`). Each robot walks back and forth
along the tour from its own start (:func:`ping_pong`) with drifting odometry in its own frame
(:func:`walk_odometry`); :func:`plan_robots` lays out a row's tracked and searching robots.
:func:`pose_correct` is the correctness test the rows judge the answered poses with.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# --------------------------------------------------------------------------- worlds and walks


@dataclass
class Pool:
    """The scans of one (world, map): true poses ``(m, 3)`` along the tour, their ranges as
    little-endian float32 bytes (and the mirror images), the laser's geometry and the map the
    service gets."""

    world: str
    map_kind: str
    map_id: str
    map_msg: Any
    truth: np.ndarray
    ranges: list[bytes]
    mirrored: list[bytes]
    info: dict[str, float]
    beams: int
    #: step (m) and turn (deg) statistics between consecutive scans of a walk
    motion: dict[str, float] = field(default_factory=dict)

    @property
    def key(self) -> tuple[str, str]:
        return (self.world, self.map_kind)


def world_name(world: str) -> str:
    """``office`` or ``building-<seed>``."""
    return "office" if world == "office" else f"building-{int(world)}"


def make_pool(world: str, map_kind: str, stride: int, seed: int = 7) -> Pool:
    """Setup-1 scans of ``world`` (``office`` or a generated building's seed) every ``stride``
    samples (11 mm each) of the whole tour; the map of ``map_kind`` for the service."""
    from service.adapters.convert import map_message_of
    from sim_publisher.scenario import building_setup, make_setup

    if map_kind not in ("metric", "schematic"):
        raise ValueError(f"--map must be metric or schematic, got {map_kind!r}")
    if world == "office":
        setup = make_setup(1, seed=seed)
        if map_kind == "metric":
            map_data = setup.map_data
        else:
            from sim_publisher.office import office_schematic_map

            map_data = office_schematic_map()
    else:
        from sim_publisher.generator import BuildingParams, generate_building

        b = generate_building(int(world), BuildingParams())
        setup = building_setup(b, 1, seed=seed, people=False)
        map_data = setup.map_data if map_kind == "metric" else building_setup(b, 2).map_data
    idx = np.arange(0, len(setup), stride)
    ranges, mirrored = [], []
    for i in idx:
        r = np.asarray(setup.scan(int(i))[0], dtype="<f4")
        ranges.append(r.tobytes())
        mirrored.append(r[::-1].tobytes())
    lz = setup.laser
    info = {
        "angle_min": float(lz.angle_min),
        "angle_increment": float(lz.angle_increment),
        "range_min": float(lz.config.range_min),
        "range_max": float(lz.config.max_range),
    }
    # The mirror image needs a field of view symmetric about the robot's x axis.
    fov_end = info["angle_min"] + (lz.config.beams - 1) * info["angle_increment"]
    assert math.isclose(fov_end, -info["angle_min"], abs_tol=1e-9), "asymmetric laser"
    # the poses on the map's own frame (a generated plan's scale error applied; docs/worlds.md):
    # the robots start there, their odometry walks along them and the answers are judged on them
    truth = setup.reference[idx]
    m = len(idx)
    return Pool(
        world=world,
        map_kind=map_kind,
        map_id=map_data.map_id,
        map_msg=map_message_of(map_data),
        truth=truth,
        ranges=ranges,
        mirrored=mirrored,
        info=info,
        beams=int(lz.config.beams),
        # a walk there and back: every step a robot's consecutive scans can make, turnarounds too
        motion=motion_stats([truth[ping_pong(0, m, 2 * m - 1)]]),
    )


def ping_pong(start: int, m: int, count: int) -> np.ndarray:
    """Pool indices of ``count`` consecutive scans of a robot walking from ``start`` forward
    along a tour of ``m`` scans, reversing at either end (no scan repeated at a turnaround)."""
    if m < 2:
        raise ValueError("a walk needs at least 2 scans")
    period = 2 * (m - 1)
    k = (start + np.arange(count)) % period
    return np.where(k < m, k, period - k).astype(np.int64)


def odometry_frame(poses: np.ndarray) -> np.ndarray:
    """``poses`` ``(n, 3)`` expressed in the frame of the first one (which becomes 0, 0, 0)."""
    p = np.asarray(poses, dtype=np.float64)
    o = p[0]
    c, s = math.cos(o[2]), math.sin(o[2])
    d = p[:, :2] - o[:2]
    th = (p[:, 2] - o[2] + np.pi) % (2 * np.pi) - np.pi
    return np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], th]


def walk_odometry(truth_walk: np.ndarray, seed: int) -> np.ndarray:
    """Drifting odometry of one robot's walk (its own frame, starting at 0, 0, 0)."""
    from sim_publisher.trajectory import simulate_odometry

    return odometry_frame(simulate_odometry(truth_walk, seed=seed))


def mirror_poses(poses: np.ndarray) -> np.ndarray:
    """Mirror image (about the x axis) of poses ``(n, 3)``: ``(x, -y, -theta)``."""
    p = np.asarray(poses, dtype=np.float64)
    return np.c_[p[:, 0], -p[:, 1], -p[:, 2]]


def motion_stats(walks: list[np.ndarray]) -> dict[str, float]:
    """Mean and p95 step (m) and absolute turn (deg) between consecutive poses of the walks
    (true poses ``(n, 3)`` each)."""
    steps, turns = [], []
    for w in walks:
        if len(w) < 2:
            continue
        steps.append(np.hypot(*np.diff(w[:, :2], axis=0).T))
        turns.append(np.rad2deg(np.abs((np.diff(w[:, 2]) + np.pi) % (2 * np.pi) - np.pi)))
    if not steps:
        return dict.fromkeys(("step_mean", "step_p95", "turn_mean", "turn_p95"), math.nan)
    st, tu = np.concatenate(steps), np.concatenate(turns)
    return {
        "step_mean": float(st.mean()),
        "step_p95": float(np.percentile(st, 95)),
        "turn_mean": float(tu.mean()),
        "turn_p95": float(np.percentile(tu, 95)),
    }


def pose_correct(est: np.ndarray, truth: np.ndarray, max_m: float, max_deg: float) -> np.ndarray:
    """Per row: estimate within ``max_m`` and ``max_deg`` of the true pose (``(n, 3)`` each)."""
    e, t = np.asarray(est, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    d = np.hypot(e[:, 0] - t[:, 0], e[:, 1] - t[:, 1])
    dth = np.abs((e[:, 2] - t[:, 2] + np.pi) % (2 * np.pi) - np.pi)
    return (d < max_m) & (np.rad2deg(dth) < max_deg)


# --------------------------------------------------------------------------- robots


@dataclass
class RobotPlan:
    """One robot of a row: its id, pool indices and odometry per seq (seq 0 is the priming
    scan), true poses, and whether it searches (null initial pose) on mirrored scans."""

    robot_id: str
    searching: bool
    mirrored: bool
    walk: np.ndarray
    truth: np.ndarray
    odom: np.ndarray | None


def plan_robots(
    pool: Pool,
    row: int,
    n: int,
    k: int,
    count: int,
    odom: bool,
    search_mode: str,
) -> list[RobotPlan]:
    """N tracked robots spread evenly along the tour, then K searching ones between them;
    ``count`` scans each (seq 0 .. count-1)."""
    m = len(pool.ranges)
    plans = []
    total = n + k
    for j in range(total):
        searching = j >= n
        start = int((j * m) // max(total, 1) + (m // (2 * total) if searching else 0)) % m
        walk = ping_pong(start, m, count)
        truth = pool.truth[walk]
        mirrored = searching and search_mode == "foreign"
        if mirrored:
            truth = mirror_poses(truth)
        o = walk_odometry(truth, seed=1000 * row + j) if odom else None
        rid = f"{'s' if searching else 'r'}{row}-{j}"
        plans.append(RobotPlan(rid, searching, mirrored, walk, truth, o))
    return plans
