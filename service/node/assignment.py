"""Which worker owns which robot: configured robots go to the least-loaded worker and stay.

:class:`Assignment` is read by every thread of the node (:mod:`service.node.node`) and written
by the control thread (configurations) and a link thread (a robot moved to or from the search
worker); :func:`shard_of` is the stable hash an unassigned robot id maps to.
"""

from __future__ import annotations

import hashlib
import threading


def shard_of(robot_id: str, n: int) -> int:
    """Stable hash index of a robot id in ``[0, n)`` (BLAKE2b of the id; same on every run)."""
    h = hashlib.blake2b(robot_id.encode("utf-8"), digest_size=8).digest()
    return int.from_bytes(h, "little") % max(1, n)


class Assignment:
    """Which worker owns which robot: configured robots go to the worker with the fewest
    robots (ties: lowest index) and stay there; an unassigned id maps to :func:`shard_of`.

    Hashing alone spreads few robots badly (two robots share one of two workers half of the
    time), which halves throughput when the method is CPU-bound. Not thread-safe for writers
    (the control thread assigns); readers may call :meth:`index_of` from any thread.
    """

    def __init__(self, n: int, extra: int = 0) -> None:
        self.n = max(1, n)
        self._owner: dict[str, int] = {}
        self._load = [0] * (self.n + max(0, extra))
        self._lock = threading.Lock()

    def assign(self, robot_id: str) -> int:
        """Owner of ``robot_id``, choosing the least-loaded worker on first assignment (among
        the first ``n``: the ``extra`` ones, e.g. the search worker, are only moved to)."""
        with self._lock:
            idx = self._owner.get(robot_id)
            if idx is None:
                idx = self._least()
                self._load[idx] += 1
                self._owner[robot_id] = idx
            return idx

    def _least(self) -> int:
        return min(range(self.n), key=lambda i: (self._load[i], i))

    def least_loaded(self) -> int:
        """The least-loaded of the first ``n`` workers."""
        with self._lock:
            return self._least()

    def move(self, robot_id: str, idx: int) -> None:
        """Make worker ``idx`` (any, extra ones included) the robot's owner."""
        with self._lock:
            old = self._owner.get(robot_id)
            if old is not None:
                self._load[old] -= 1
            self._load[idx] += 1
            self._owner[robot_id] = idx

    def release(self, robot_id: str) -> None:
        """Forget the robot's owner."""
        with self._lock:
            idx = self._owner.pop(robot_id, None)
            if idx is not None:
                self._load[idx] -= 1

    def index_of(self, robot_id: str) -> int:
        """Assigned owner, else the hash index."""
        idx = self._owner.get(robot_id)
        return shard_of(robot_id, self.n) if idx is None else idx

    def load(self) -> list[int]:
        """Robots per worker."""
        return list(self._load)
