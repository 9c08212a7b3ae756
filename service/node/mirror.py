"""Who owns a robot among several service instances, and what an instance keeps of the
robots the others serve (:class:`Mirror`). The design is in :mod:`service.node.cluster` and
docs/cluster.md."""

from __future__ import annotations

import hashlib
import logging
import threading
from collections.abc import Iterable
from typing import TYPE_CHECKING

from schemas import codec
from schemas.messages import PoseMsg, RobotConfig
from service.errors import InvalidMessage, ShapelocError
from service.node.state import SavedPose

if TYPE_CHECKING:
    pass

log = logging.getLogger("shapeloc.service")

#: Largest pose sample mirrored from another instance (a pose is ~200 bytes).
MAX_POSE_BYTES = 64 * 1024


def hrw_score(instance_id: str, robot_id: str) -> int:
    """Rendezvous weight of ``robot_id`` on ``instance_id`` (BLAKE2b, the same everywhere)."""
    h = hashlib.blake2b(f"{instance_id}\x00{robot_id}".encode(), digest_size=8).digest()
    return int.from_bytes(h, "big")


def hrw_owner(robot_id: str, members: Iterable[str]) -> str | None:
    """The member with the highest weight for ``robot_id`` (ties: the larger id); ``None``
    without members."""
    best: tuple[int, str] | None = None
    for m in members:
        k = (hrw_score(m, robot_id), m)
        if best is None or k > best:
            best = k
    return None if best is None else best[1]


def fresher(a: PoseMsg, b: PoseMsg | None) -> bool:
    """Whether pose ``a`` answers a later scan than ``b`` (stamp, then seq)."""
    return b is None or (a.stamp, a.seq) > (b.stamp, b.seq)


def odom_of(pm: PoseMsg | None) -> tuple[float, float, float] | None:
    if pm is None or pm.odom is None:
        return None
    return (float(pm.odom[0]), float(pm.odom[1]), float(pm.odom[2]))


def pose_matches(pm: PoseMsg, robot_id: str, cfg: RobotConfig) -> bool:
    """A pose belongs to a robot's current configuration (same robot, map and method)."""
    return pm.robot_id == robot_id and pm.map_id == cfg.map_id and pm.method == cfg.method


class Mirror:
    """Configurations and last poses of the robots this instance knows but does not serve.

    ``offer_raw`` is called from the Zenoh callback with a pose sample's bytes (O(1), only
    for robots whose configuration is mirrored); the bytes are decoded and validated later
    (:meth:`settle`), and invalid ones are counted in ``invalid``. Thread-safe.
    """

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self._lock = threading.Lock()
        self.configs: dict[str, RobotConfig] = {}
        self.poses: dict[str, PoseMsg] = {}
        self.odoms: dict[str, tuple[float, float, float]] = {}
        self._raw: dict[str, tuple[bytes, str | None]] = {}
        self._dirty: set[str] = set()
        self.invalid = 0

    def __len__(self) -> int:
        return len(self.configs)

    def known(self, robot_id: str) -> bool:
        """Whether the robot's configuration is mirrored."""
        return robot_id in self.configs

    def offer_raw(self, robot_id: str, payload: bytes, encoding: str | None) -> None:
        """Keep the newest pose sample of a mirrored robot (callback side)."""
        with self._lock:
            if robot_id in self.configs:
                self._raw[robot_id] = (payload, encoding)

    def set_config(self, robot_id: str, cfg: RobotConfig) -> bool:
        """Mirror a (new) configuration; its last pose is forgotten (a config put resets the
        robot). ``False`` if the mirror is full."""
        with self._lock:
            if robot_id not in self.configs and len(self.configs) >= self.capacity:
                return False
            self.configs[robot_id] = cfg
            self.poses.pop(robot_id, None)
            self.odoms.pop(robot_id, None)
            self._raw.pop(robot_id, None)
            self._dirty.discard(robot_id)
            return True

    def put(
        self,
        robot_id: str,
        cfg: RobotConfig,
        pose: PoseMsg | None,
        odom: tuple[float, float, float] | None,
        dirty: bool = False,
    ) -> None:
        """Mirror a robot with its last pose (restored, or handed over by this instance)."""
        with self._lock:
            self.configs[robot_id] = cfg
            self._raw.pop(robot_id, None)
            self.poses.pop(robot_id, None)
            self.odoms.pop(robot_id, None)
            if pose is not None:
                self.poses[robot_id] = pose
                if odom is not None:
                    self.odoms[robot_id] = odom
            if dirty and pose is not None:
                self._dirty.add(robot_id)

    def offer_pose(self, robot_id: str, pm: PoseMsg) -> bool:
        """Take a pose learnt from another instance if it is newer than the mirrored one and
        belongs to the mirrored configuration."""
        self.settle(robot_id)
        with self._lock:
            cfg = self.configs.get(robot_id)
            if cfg is None or not pose_matches(pm, robot_id, cfg):
                return False
            if not fresher(pm, self.poses.get(robot_id)):
                return False
            self.poses[robot_id] = pm
            self.odoms.pop(robot_id, None)
            if (o := odom_of(pm)) is not None:
                self.odoms[robot_id] = o
            self._dirty.add(robot_id)
            return True

    def forget(self, robot_id: str) -> bool:
        """Drop a robot (config deleted, or served here now); whether it was mirrored."""
        with self._lock:
            self.poses.pop(robot_id, None)
            self.odoms.pop(robot_id, None)
            self._raw.pop(robot_id, None)
            self._dirty.discard(robot_id)
            return self.configs.pop(robot_id, None) is not None

    def settle(self, robot_id: str) -> None:
        """Decode the newest pose sample of ``robot_id`` (if any) into ``poses``."""
        with self._lock:
            raw = self._raw.pop(robot_id, None)
            cfg = self.configs.get(robot_id)
        if raw is None or cfg is None:
            return
        try:
            pm = codec.decode(PoseMsg, raw[0], raw[1])
            if not pose_matches(pm, robot_id, cfg):
                raise InvalidMessage("pose does not match the mirrored configuration")
        except ShapelocError as e:
            log.debug("mirrored pose of %s ignored: %s", robot_id, e)
            with self._lock:
                self.invalid += 1
            return
        with self._lock:
            if self.configs.get(robot_id) is not cfg:
                return  # reconfigured meanwhile
            self.poses[robot_id] = pm
            self.odoms.pop(robot_id, None)
            if (o := odom_of(pm)) is not None:
                self.odoms[robot_id] = o
            self._dirty.add(robot_id)

    def take(
        self, robot_id: str
    ) -> tuple[RobotConfig, PoseMsg | None, tuple[float, float, float] | None] | None:
        """Remove a robot for serving it here: its config, newest pose and odometry."""
        self.settle(robot_id)
        with self._lock:
            cfg = self.configs.pop(robot_id, None)
            pm = self.poses.pop(robot_id, None)
            odom = self.odoms.pop(robot_id, None)
            self._dirty.discard(robot_id)
        return None if cfg is None else (cfg, pm, odom)

    def snapshot(
        self,
    ) -> list[tuple[str, RobotConfig, PoseMsg | None, tuple[float, float, float] | None]]:
        """Every mirrored robot with its newest pose (decoding what arrived)."""
        with self._lock:
            pending = list(self._raw)
        for rid in pending:
            self.settle(rid)
        with self._lock:
            return [
                (rid, cfg, self.poses.get(rid), self.odoms.get(rid))
                for rid, cfg in self.configs.items()
            ]

    def saves(self) -> dict[str, SavedPose]:
        """The mirrored poses that changed since the last call, for the state store."""
        with self._lock:
            pending = list(self._raw)
        for rid in pending:
            self.settle(rid)
        with self._lock:
            dirty, self._dirty = self._dirty, set()
        out: dict[str, SavedPose] = {}
        for rid in dirty:
            with self._lock:
                pm = self.poses.get(rid)
                odom = self.odoms.get(rid)
            if pm is not None:
                x, y, th = (float(v) for v in pm.pose)
                out[rid] = SavedPose(pm.map_id, x, y, th, pm.seq, pm.stamp, pm.status, odom)
        return out

    def mark_dirty(self, robot_ids: Iterable[str]) -> None:
        """Save these again next time (after a failed write)."""
        with self._lock:
            self._dirty.update(r for r in robot_ids if r in self.configs)
