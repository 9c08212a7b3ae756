"""Simulated robots that produce wire messages (scan, ground truth, configuration).

Network-free: :class:`SimRobot` walks one robot along the office tour of a
:func:`sim_publisher.scenario.make_setup` setup and returns :class:`~schemas.messages.Scan` and
:class:`~schemas.messages.Truth` messages; :class:`SimFleet` holds several robots and the maps
they use. ``sim_publisher.__main__`` puts these on Zenoh. Poses are map-frame ``[x, y, theta]``
(metres, radians); scans are in the robot frame (REP 103) with the laser's angle and range
limits; "no return" beams are NaN.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.messages import Map, RobotConfig, Scan, Truth
from service.adapters.convert import map_message_of
from service.adapters.maps.files import load_map_file
from service.adapters.maps.world import World
from service.core.pose import compose, invert
from service.core.types import METHODS, MapData, wrap_angle
from sim_publisher.scenario import Setup, make_setup

MAP_CHOICES = ("metric", "schematic")
#: Setup whose sampling a robot uses by default, per map kind (paper sec. 6).
DEFAULT_SETUP = {"metric": 1, "schematic": 2}


def map_for(spec: str) -> MapData:
    """The map named by ``spec``: ``metric`` / ``schematic`` (the office) or a map/world file.

    Files are read by :func:`service.adapters.maps.files.load_map_file` (wire JSON/msgpack map,
    GeoJSON world or outlines, WKT world).
    """
    if spec == "metric":
        from sim_publisher.office import office_metric_map

        return office_metric_map()
    if spec == "schematic":
        from sim_publisher.office import office_schematic_map

        return office_schematic_map()
    return load_map_file(Path(spec))


class SimRobot:
    """One simulated robot driving along a setup's tour (back and forth at the ends).

    ``start`` is the first trajectory index, ``stride`` how many setup samples one step
    advances (to coarsen the sampling, e.g. for ``--step-mm``). Every :meth:`step` returns the
    next scan and its ground truth with the same ``seq`` and ``stamp``; seq starts at 0.

    Kidnapping: with ``kidnap_at`` set, the scan with that ``seq`` (and the ones after it) is
    taken at the tour position ``kidnap_to`` (trajectory index) instead of where the robot
    was: the robot is carried away without the localiser being told (its odometry stands still
    across the jump, as wheels would). The truth topic follows.

    Look-around start: with ``look_around = N > 0`` the first ``N`` scans (seq ``0..N-1``) are
    taken at the tour's start position with headings ``theta0 - (N - 1 - k) * look_turn``
    (``k`` the seq, ``theta0`` the heading of the start pose, ``look_turn`` radians CCW): the
    robot turns in place by ``look_turn`` between scans and ends the spin facing the tour (scan
    ``N - 1`` is taken at the start pose), so no turn separates the spin from the tour; scan
    ``N`` is the tour's start pose again, after which it drives the tour as without
    look-around. During the spin the odometry turns by
    ``look_turn * (1 + look_turn_error)`` per scan, position unchanged; ``look_turn_error`` is
    a seeded ~2 % rotation error (from ``look_seed`` and the robot id). The spin's odometry
    ends at the setup odometry of the start pose, so odometry stays one continuous frame and
    from seq ``N`` on every message equals the one the robot without look-around sends ``N``
    scans earlier (same stamp). A kidnap during the spin ends the spin (the robot is carried
    to the kidnap position and drives on from there).

    Laser mounting: with ``laser_offset`` ``[x, y, theta]`` (the laser's pose on the base,
    m / rad, x forward, y left) the scans are taken from the laser's pose ``truth ⊕ offset``
    while the truth, the odometry and the configuration's initial pose stay the base's, and
    the configuration carries the offset (as a nav2 robot's front would send it). ``None``:
    the laser at the base's origin (the scans are the setup's own).
    """

    def __init__(
        self,
        robot_id: str,
        setup: Setup,
        map_id: str,
        method: str = "shape",
        *,
        start: int = 0,
        stride: int = 1,
        global_localization: bool = False,
        send_odom: bool = True,
        kidnap_at: int | None = None,
        kidnap_to: int | None = None,
        look_around: int = 0,
        look_turn: float = math.pi / 2,
        look_seed: int = 0,
        laser_offset: Sequence[float] | None = None,
    ) -> None:
        if method not in METHODS:
            raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        n = len(setup.truth)
        if n < 2:
            raise ValueError("the setup's trajectory has fewer than 2 poses")
        self.robot_id = robot_id
        self.setup = setup
        self.map_id = map_id
        self.method = method
        self.global_localization = global_localization
        self.send_odom = send_odom
        if (kidnap_at is None) != (kidnap_to is None):
            raise ValueError("kidnap_at and kidnap_to go together")
        if kidnap_at is not None and kidnap_at < 0:
            raise ValueError(f"kidnap_at must be >= 0, got {kidnap_at}")
        self.indices = np.arange(0, n, stride)
        self._pos = int(np.clip(start // stride, 0, len(self.indices) - 1))
        self.kidnap_at = kidnap_at
        self._kidnap_pos = (
            None
            if kidnap_to is None
            else int(np.clip(kidnap_to // stride, 0, len(self.indices) - 1))
        )
        if isinstance(look_around, bool) or not isinstance(look_around, (int, np.integer)):
            raise ValueError(f"look_around must be an integer, got {look_around!r}")
        if look_around < 0:
            raise ValueError(f"look_around must be >= 0, got {look_around}")
        if isinstance(look_turn, bool) or not math.isfinite(look_turn):
            raise ValueError(f"look_turn must be a finite angle in radians, got {look_turn!r}")
        self.look_around = int(look_around)
        self.look_turn = float(look_turn)
        self.laser_offset: np.ndarray | None = None
        if laser_offset is not None:
            m = np.asarray(laser_offset, dtype=np.float64).reshape(-1)
            if m.shape != (3,) or not np.all(np.isfinite(m)):
                raise ValueError(f"laser_offset must be 3 finite numbers, got {laser_offset!r}")
            self.laser_offset = m if np.any(m) else None
        rng = np.random.default_rng((int(look_seed), zlib.crc32(robot_id.encode("utf-8"))))
        sign = 1.0 if rng.random() < 0.5 else -1.0
        #: Relative rotation error of the odometry while turning in place (about 2 %).
        self.look_turn_error = float(sign * rng.uniform(0.01, 0.03))
        self._spin_left = self.look_around
        self._dir = 1
        self.seq = 0
        #: Map from the setup's odometry frame to the reported one: a kidnapped robot's wheels
        #: do not see it carried, so at the kidnap the reported odometry stands still and
        #: then continues from there (identity until then).
        self._odom_frame = np.zeros(3)
        self._last_odom: np.ndarray | None = None
        laser = setup.laser
        self.angle_min = float(laser.angle_min)
        self.angle_increment = float(laser.angle_increment)
        self.range_max = float(laser.config.max_range)
        self.range_min = float(laser.config.range_min)

    @property
    def index(self) -> int:
        """Setup sample index of the next scan."""
        return int(self.indices[self._pos])

    @property
    def start_pose(self) -> np.ndarray:
        """True pose at the next scan, ``(3,)`` map frame (turned while looking around)."""
        pose = np.asarray(self.setup.truth[self.index], dtype=np.float64).copy()
        if self._spin_left > 0:
            pose[2] = wrap_angle(pose[2] - (self._spin_left - 1) * self.look_turn)
        return pose

    def _kidnap_next(self) -> bool:
        return self.kidnap_at is not None and self.seq == self.kidnap_at

    def config(self) -> RobotConfig:
        """Configuration message: the map, the method, and the true pose at the next scan as
        initial pose (``None`` with global localisation)."""
        pose = None if self.global_localization else [float(v) for v in self.start_pose]
        extra = {}
        if self.laser_offset is not None:
            extra["laser_offset"] = [float(v) for v in self.laser_offset]
        return RobotConfig(map_id=self.map_id, method=self.method, initial_pose=pose, **extra)

    def _laser_pose(self, pose: np.ndarray) -> np.ndarray:
        """Where the laser is when the base is at ``pose``."""
        if self.laser_offset is None:
            return pose
        return compose(np.asarray(pose, dtype=np.float64), self.laser_offset)

    def step(self, stamp: float) -> tuple[Scan, Truth]:
        """Scan and ground truth at the current tour position, then advance one step (at
        ``seq == kidnap_at`` the robot first jumps to the kidnap position; while looking
        around it turns in place instead of advancing)."""
        if self._kidnap_next():
            assert self._kidnap_pos is not None
            self._pos = self._kidnap_pos
            self._dir = 1
            self._spin_left = 0
            if self._last_odom is not None:
                carried = np.asarray(self.setup.odom[self.index], dtype=np.float64)
                self._odom_frame = compose(self._last_odom, invert(carried))
        i = self.index
        spinning = self._spin_left > 0
        if spinning:
            pose = self.start_pose
            # noise index past the tour's samples: a spun scan never reuses a tour scan's noise
            ranges, angles = self.setup.laser.scan(
                self._laser_pose(pose), len(self.setup) + self.seq
            )
            o = np.asarray(self.setup.odom[i], dtype=np.float64).copy()
            o[2] = wrap_angle(
                o[2] - (self._spin_left - 1) * self.look_turn * (1.0 + self.look_turn_error)
            )
        else:
            pose = np.asarray(self.setup.truth[i], dtype=np.float64)
            if self.laser_offset is None:
                ranges, angles = self.setup.scan(i)
            else:
                ranges, angles = self.setup.laser.scan(
                    self._laser_pose(pose), i, self.setup.circles(i)
                )
            o = np.asarray(self.setup.odom[i], dtype=np.float64)
        o = compose(self._odom_frame, o)
        self._last_odom = o
        ranges = np.asarray(ranges, dtype=np.float64)
        if len(angles) != len(ranges):
            raise ValueError("laser returned mismatched ranges/angles")
        odom = None
        if self.send_odom:
            odom = [float(v) for v in o]
        scan = Scan(
            seq=self.seq,
            stamp=float(stamp),
            angle_min=self.angle_min,
            angle_increment=self.angle_increment,
            range_min=self.range_min,
            range_max=self.range_max,
            ranges=ranges,
            odom=odom,
        )
        truth = Truth(seq=self.seq, stamp=float(stamp), pose=[float(v) for v in pose])
        self.seq += 1
        if spinning:
            self._spin_left -= 1
        else:
            self._advance()
        return scan, truth

    def _advance(self) -> None:
        nxt = self._pos + self._dir
        if not 0 <= nxt < len(self.indices):
            self._dir = -self._dir
            nxt = self._pos + self._dir
        self._pos = nxt


@dataclass(frozen=True)
class RobotSpec:
    """How to build one robot of a fleet (see :func:`build_fleet`)."""

    robot_id: str
    map_spec: str
    method: str
    setup: int
    seed: int
    start_fraction: float
    step_mm: float | None = None
    kidnap_at: int | None = None
    kidnap_to_fraction: float | None = None


def _cycle(values: Sequence[str], n: int) -> list[str]:
    if not values:
        raise ValueError("empty list of choices")
    return [values[k % len(values)] for k in range(n)]


def fleet_specs(
    n: int,
    maps: Sequence[str] = ("metric",),
    methods: Sequence[str] = ("shape",),
    *,
    setup: int | None = None,
    step_mm: float | None = None,
    seed: int = 0,
    starts: Sequence[float] | None = None,
    id_prefix: str = "sim-",
    kidnap_at: int | None = None,
    kidnap_to: float | None = None,
    kidnap_robots: int = 1,
) -> list[RobotSpec]:
    """Specs of ``n`` robots ``<id_prefix>0..n-1``: maps and methods cycle over the lists;
    each robot gets seed ``seed + k`` and starts at fraction ``starts[k]`` of the tour
    (default ``k / n``). ``setup`` defaults per map (metric: 1, schematic: 2). With
    ``kidnap_at`` (a scan seq) and ``kidnap_to`` (a tour fraction), the first
    ``kidnap_robots`` robots are carried to that tour position at that scan."""
    if (kidnap_at is None) != (kidnap_to is None):
        raise ValueError("kidnap_at and kidnap_to go together")
    if kidnap_at is not None and kidnap_at < 0:
        raise ValueError(f"kidnap_at must be >= 0, got {kidnap_at}")
    if kidnap_to is not None and not 0.0 <= kidnap_to <= 1.0:
        raise ValueError(f"kidnap fraction must be in [0, 1], got {kidnap_to}")
    if n < 1:
        raise ValueError(f"need at least one robot, got {n}")
    if starts is not None and len(starts) < n:
        raise ValueError(f"{n} robots but only {len(starts)} start fractions")
    if step_mm is not None and step_mm <= 0:
        raise ValueError(f"step must be > 0 mm, got {step_mm}")
    specs = []
    for k, (m, meth) in enumerate(zip(_cycle(maps, n), _cycle(methods, n), strict=True)):
        frac = float(starts[k]) if starts is not None else k / n
        if not 0.0 <= frac <= 1.0:
            raise ValueError(f"start fraction must be in [0, 1], got {frac}")
        st = setup if setup is not None else DEFAULT_SETUP.get(m, 1)
        if step_mm is not None:
            st = 1
        specs.append(
            RobotSpec(
                robot_id=f"{id_prefix}{k}",
                map_spec=m,
                method=meth,
                setup=st,
                seed=seed + k,
                start_fraction=frac,
                step_mm=step_mm,
                kidnap_at=kidnap_at if k < kidnap_robots else None,
                kidnap_to_fraction=kidnap_to if k < kidnap_robots else None,
            )
        )
    return specs


class SimFleet:
    """Robots plus the maps they are configured on (keyed by map id)."""

    def __init__(self, robots: Sequence[SimRobot], maps: dict[str, MapData]) -> None:
        self.robots = list(robots)
        self.maps = dict(maps)
        missing = {r.map_id for r in self.robots} - set(self.maps)
        if missing:
            raise ValueError(f"robots use maps that the fleet does not hold: {sorted(missing)}")

    @staticmethod
    def from_specs(
        specs: Sequence[RobotSpec],
        *,
        global_localization: bool = False,
        send_odom: bool = True,
        look_around: int = 0,
        look_turn: float = math.pi / 2,
        laser_offset: Sequence[float] | None = None,
    ) -> SimFleet:
        """Build robots (one setup per robot seed) and load their maps; ``look_around``,
        ``look_turn`` (radians) and ``laser_offset`` are passed to every robot (see
        :class:`SimRobot`)."""
        maps: dict[str, MapData] = {}
        by_spec: dict[str, str] = {}
        robots = []
        for sp in specs:
            if sp.map_spec not in by_spec:
                md = map_for(sp.map_spec)
                maps[md.map_id] = md
                by_spec[sp.map_spec] = md.map_id
            setup = make_setup(sp.setup, seed=sp.seed)
            n = len(setup.truth)
            stride = 1
            if sp.step_mm is not None:
                mean_mm = _mean_step_mm(setup.truth)
                stride = max(1, round(sp.step_mm / mean_mm))
            start = round(sp.start_fraction * (n - 1))
            kidnap_to = None
            if sp.kidnap_to_fraction is not None:
                kidnap_to = round(sp.kidnap_to_fraction * (n - 1))
            robots.append(
                SimRobot(
                    sp.robot_id,
                    setup,
                    by_spec[sp.map_spec],
                    sp.method,
                    start=start,
                    stride=stride,
                    global_localization=global_localization,
                    send_odom=send_odom,
                    kidnap_at=sp.kidnap_at,
                    kidnap_to=kidnap_to,
                    look_around=look_around,
                    look_turn=look_turn,
                    look_seed=sp.seed,
                    laser_offset=laser_offset,
                )
            )
        return SimFleet(robots, maps)

    def map_messages(self) -> list[Map]:
        """Wire map messages of every map in use."""
        return [map_message_of(md) for md in self.maps.values()]


def _mean_step_mm(truth: np.ndarray) -> float:
    d = np.linalg.norm(np.diff(np.asarray(truth)[:, :2], axis=0), axis=1)
    return float(max(d.mean() * 1000.0, 1e-6))


def random_free_poses(world: World, n: int, seed: int, margin: float = 0.3) -> np.ndarray:
    """``n`` poses ``[x, y, theta]`` (map frame, m, rad) uniformly over the free space of
    ``world`` with at least ``margin`` metres to every obstacle, headings uniform in
    (-pi, pi]; deterministic in ``seed`` (``numpy.random.default_rng``)."""
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    rng = np.random.default_rng(seed)
    x0, y0, x1, y1 = world.bounds
    out: list[np.ndarray] = []
    while len(out) < n:
        p = rng.uniform([x0, y0], [x1, y1], size=(4 * (n - len(out)) + 8, 2))
        th = rng.uniform(-np.pi, np.pi, size=len(p))
        ok = world.is_free(p, margin)
        out.extend(np.array([q[0], q[1], t]) for q, t in zip(p[ok], th[ok], strict=True))
    return np.vstack(out[:n]) if n else np.zeros((0, 3))
