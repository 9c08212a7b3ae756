"""A planar tf buffer, as AMCL reads tf: a tree of frames, static and timed edges, lookups
interpolated at a stamp.

Each frame has at most one parent (the latest transform naming it as child wins, as in tf2;
a new parent clears the old edge's history). A static edge (``tf_static``) holds for every
time; a timed edge (``tf``, or ``nav_msgs/Odometry`` where a robot publishes no tf) keeps
the last :attr:`TfBuffer.cache_s` seconds of samples and is linearly interpolated between the
two samples around the stamp asked for (the yaw along the shorter arc). Like tf2, it never
extrapolates: a stamp after the newest sample of an edge on the chain raises
:class:`TfWait` (the caller may wait for more data), one before the oldest kept sample, or a
chain that does not exist, raises :class:`TfError`.

Poses are ``(x, y, yaw)``; ``lookup(target, source, t)`` is the pose of ``source`` in
``target`` (the transform that maps ``source`` coordinates into ``target``'s).
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, field

from service.core.pose import compose, invert

Pose2 = tuple[float, float, float]

#: Most timed samples kept per edge, whatever their age.
MAX_SAMPLES = 2000


class TfError(LookupError):
    """No transform: unknown frame, no chain, or a stamp older than the kept samples."""


class TfWait(TfError):
    """The transform at that stamp needs samples that have not arrived yet."""


@dataclass
class _Edge:
    parent: str
    static: Pose2 | None = None
    times: list[int] = field(default_factory=list)
    poses: deque[Pose2] = field(default_factory=deque)
    source: str = "tf"

    def at(self, t_ns: int, child: str) -> Pose2:
        if self.static is not None:
            return self.static
        times = self.times
        if not times:
            raise TfWait(f"no transform {self.parent} -> {child} yet")
        if t_ns > times[-1]:
            raise TfWait(f"{self.parent} -> {child} at {t_ns} ns is after the newest sample")
        if t_ns < times[0]:
            raise TfError(
                f"{self.parent} -> {child} at {t_ns} ns is before the oldest kept sample "
                f"({times[0]} ns)"
            )
        k = bisect.bisect_left(times, t_ns)
        if times[k] == t_ns:
            return self.poses[k]
        t0, t1 = times[k - 1], times[k]
        p0, p1 = self.poses[k - 1], self.poses[k]
        a = (t_ns - t0) / (t1 - t0)
        dyaw = math.remainder(p1[2] - p0[2], 2.0 * math.pi)
        yaw = math.remainder(p0[2] + a * dyaw, 2.0 * math.pi)
        return (p0[0] + a * (p1[0] - p0[0]), p0[1] + a * (p1[1] - p0[1]), yaw)


class TfBuffer:
    """Static and timed planar transforms of one robot (frame ids without leading ``/``)."""

    def __init__(self, cache_s: float = 10.0) -> None:
        if not cache_s > 0.0:
            raise ValueError(f"cache_s must be > 0, got {cache_s}")
        self.cache_s = float(cache_s)
        self._edges: dict[str, _Edge] = {}

    def frames(self) -> set[str]:
        """Every frame named by a transform."""
        return set(self._edges) | {e.parent for e in self._edges.values()}

    def has_edge(self, child: str, source: str | None = None) -> bool:
        """Whether ``child`` has a parent (from ``source`` if given: ``tf``, ``static`` or
        ``odom``)."""
        e = self._edges.get(child)
        return e is not None and (source is None or e.source == source)

    def set_static(self, parent: str, child: str, pose: Pose2) -> None:
        """A static transform (``tf_static``): ``child``'s pose in ``parent`` at any time."""
        self._edges[child] = _Edge(parent, static=_pose(pose), source="static")

    def add(self, parent: str, child: str, t_ns: int, pose: Pose2, source: str = "tf") -> None:
        """A timed transform at ``t_ns`` (integer nanoseconds). A sample older than the
        newest one of its edge is inserted in order; one equal to a kept stamp replaces it."""
        e = self._edges.get(child)
        if e is None or e.parent != parent or e.static is not None:
            e = _Edge(parent, source=source)
            self._edges[child] = e
        e.source = source
        p = _pose(pose)
        times = e.times
        if not times or t_ns > times[-1]:
            times.append(t_ns)
            e.poses.append(p)
        else:
            k = bisect.bisect_left(times, t_ns)
            if times[k] == t_ns:
                e.poses[k] = p
            else:
                times.insert(k, t_ns)
                e.poses.insert(k, p)
        horizon = times[-1] - int(self.cache_s * 1e9)
        while len(times) > 2 and (times[0] < horizon or len(times) > MAX_SAMPLES):
            times.pop(0)
            e.poses.popleft()

    def _chain(self, frame: str, t_ns: int) -> list[tuple[str, Pose2]]:
        """``[(frame, pose of frame in root), ...]`` from ``frame`` up to the tree's root."""
        out: list[tuple[str, Pose2]] = []
        seen = set()
        pose: Pose2 = (0.0, 0.0, 0.0)
        out.append((frame, pose))
        while frame in self._edges:
            if frame in seen:
                raise TfError(f"tf loop through {frame!r}")
            seen.add(frame)
            e = self._edges[frame]
            pose = _pose(compose(e.at(t_ns, frame), pose))
            frame = e.parent
            out.append((frame, pose))
        return out

    def lookup(self, target: str, source: str, t_ns: int) -> Pose2:
        """Pose of ``source`` in ``target`` at ``t_ns`` (see the module docstring)."""
        if target == source:
            return (0.0, 0.0, 0.0)
        if target not in self.frames() or source not in self.frames():
            missing = target if target not in self.frames() else source
            raise TfWait(f"frame {missing!r} has not been published yet")
        up_s = self._chain(source, t_ns)
        up_t = self._chain(target, t_ns)
        # each chain holds its first frame's pose in every ancestor
        source_in = dict(up_s)
        for f, target_in_f in up_t:  # the nearest common ancestor
            if f in source_in:
                return _pose(compose(invert(target_in_f), source_in[f]))
        raise TfError(f"frames {target!r} and {source!r} are not connected")


def _pose(p: object) -> Pose2:
    return (float(p[0]), float(p[1]), float(p[2]))  # type: ignore[index]
