"""Value types shared by every localisation method (shape, icp, lines).

Conventions (REP 103): map frame x/y in metres; robot frame x forward, y left; a pose is
``np.array([x, y, theta])`` (float64) with theta in radians, counter-clockwise from the map x
axis, normalised to (-pi, pi]. The laser sits at the robot origin facing forward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
from pydantic import BaseModel

from service.errors import LocalizationError

_TWO_PI = 2.0 * math.pi

MapKind = Literal["metric", "schematic"]
Status = Literal["tracking", "lost", "initializing"]
#: The relocalisation state behind an estimate (:mod:`service.core.reloc.states`): the wire's
#: optional ``state`` field. ``dead_reckoning``, ``searching`` and ``probation`` publish the
#: status ``lost`` (or ``initializing`` before any fix): the pose is not confirmed by the map.
State = Literal["tracking", "dead_reckoning", "searching", "probation"]
#: The methods :func:`service.core.factory.create_localizer` builds. The wire owns the names
#: (``schemas.messages.METHODS``); the core cannot import it, so this copy must stay equal
#: (tests/test_layers.py checks).
METHODS: tuple[str, ...] = ("shape", "icp", "lines")


def wrap_angle(a: float | np.ndarray) -> float | np.ndarray:
    """Normalise angle(s) to (-pi, pi]."""
    if isinstance(a, float):  # a scalar: Python's float % is numpy's np.mod, bit for bit
        return float(math.pi - ((math.pi - a) % _TWO_PI))
    w = np.pi - np.mod(np.pi - np.asarray(a, dtype=np.float64), 2.0 * np.pi)
    return float(w) if np.ndim(w) == 0 else w


def scan_arrays(ranges: object, angles: object) -> tuple[np.ndarray, np.ndarray]:
    """``ranges`` and ``angles`` as float64 arrays of one non-empty 1-D shape, or
    :class:`LocalizationError` (the shape part of :func:`check_scan`; the scan's
    configuration needs no more)."""
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    if r.ndim != 1 or a.ndim != 1 or r.shape != a.shape:
        raise LocalizationError(
            f"ranges and angles must be 1-D of equal length, got {r.shape} and {a.shape}"
        )
    if r.size == 0:
        raise LocalizationError("empty scan")
    return r, a


def check_scan(ranges: object, angles: object) -> tuple[np.ndarray, np.ndarray]:
    """``ranges`` and ``angles`` as float64 arrays, or :class:`LocalizationError` for an empty,
    mismatched, non-finite-angle or negative-range scan (every localiser's one check; NaN
    ranges mean no return)."""
    r, a = scan_arrays(ranges, angles)
    # ndarray methods, not np.all / np.any (their wrappers cost more than the test on a scan
    # checked at each of a tracked scan's three localiser layers); NaN < 0 is false
    if not np.isfinite(a).all():
        raise LocalizationError("beam angles must be finite")
    if np.isinf(r).any() or (r < 0).any():
        raise LocalizationError("ranges must be >= 0 or NaN (no return)")
    return r, a


@dataclass(frozen=True)
class MapData:
    """A map as the core sees it: a kind and a tuple of polylines, each ``(k, 2)`` float64, k >= 2.

    A closed ring repeats its first point last (as on the wire).
    """

    map_id: str
    kind: MapKind
    polylines: tuple[np.ndarray, ...]

    @staticmethod
    def from_lists(map_id: str, kind: MapKind, polylines: list) -> MapData:
        """Build from nested lists/arrays, checking shapes and finiteness."""
        out = []
        for i, p in enumerate(polylines):
            a = np.asarray(p, dtype=np.float64)
            if a.ndim != 2 or a.shape[1] != 2 or a.shape[0] < 2:
                raise LocalizationError(f"polyline {i}: expected (k>=2, 2) points, got {a.shape}")
            if not np.all(np.isfinite(a)):
                raise LocalizationError(f"polyline {i}: non-finite coordinate")
            a.setflags(write=False)
            out.append(a)
        if not out:
            raise LocalizationError("map has no polylines")
        return MapData(map_id=map_id, kind=kind, polylines=tuple(out))

    def segments(self) -> np.ndarray:
        """All polyline edges as an ``(s, 4)`` array ``[x0, y0, x1, y1]``."""
        segs = [np.hstack([p[:-1], p[1:]]) for p in self.polylines]
        return np.vstack(segs)

    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of all points."""
        pts = np.vstack(self.polylines)
        return (
            float(pts[:, 0].min()),
            float(pts[:, 1].min()),
            float(pts[:, 0].max()),
            float(pts[:, 1].max()),
        )


@dataclass(frozen=True)
class Match:
    """One correspondence of the configuration matching: consecutive scan polylines
    ``scan`` (indices into the scan's configuration) matched to consecutive map polylines
    ``map`` (indices into the map's abstract sensor reading), with its cost terms."""

    scan: tuple[int, ...]
    map: tuple[int, ...]
    shape_distance: float
    pose_consistency: float


@dataclass
class Estimate:
    """Result of one :meth:`Localizer.update`.

    ``score`` is a match quality in [0, 1], higher is better (1: every scan feature explained
    at zero cost). ``explained`` is the share of the scan the map explains at the published
    pose (the shape tracker: scan points within ``inlier_tolerance`` of the map; the global
    search: polyline length matched); ``ambiguity`` is best-vs-second-best hypothesis cost
    ratio in [0, 1] (1: tie), both ``None`` where a method does not compute them.
    ``covariance`` is 3x3 or ``None``. While a global search runs, ``hypotheses`` is the
    number of live pose hypotheses and ``candidates`` the best few, ``(k, 4)`` rows
    ``[x, y, theta, cost]`` best first (lower cost is better); both ``None`` otherwise.
    ``state`` is the relocalisation state behind it (:data:`State`; ``None`` for the
    baselines, which have none).
    """

    pose: np.ndarray
    status: Status
    score: float
    matches: tuple[Match, ...] = ()
    explained: float | None = None
    ambiguity: float | None = None
    covariance: np.ndarray | None = None
    extras: dict[str, float] = field(default_factory=dict)
    hypotheses: int | None = None
    candidates: np.ndarray | None = None
    state: State | None = None


class Localizer(Protocol):
    """What every method implements. One instance per robot; not thread-safe.

    ``ranges`` are metres with NaN for "no return"; ``angles`` are the beam angles in the
    robot frame (same length). ``odom`` (optional) is the odometry pose in its own frame; a
    method may use it only to seed its estimate.
    """

    method: str
    map_data: MapData

    def update(
        self, ranges: np.ndarray, angles: np.ndarray, odom: np.ndarray | None = None
    ) -> Estimate: ...

    def reset(self, initial_pose: np.ndarray | None, odom: np.ndarray | None = None) -> None:
        """Forget the history; ``None`` means global localisation (unknown pose). ``odom``:
        the odometry pose at ``initial_pose`` (e.g. saved with it before a restart), so the
        next scan's odometry increment is measured from it."""
        ...

    @property
    def pose(self) -> np.ndarray | None:
        """Last pose estimate, or ``None`` before the first fix."""
        ...


class LocalizerWrapper:
    """Base of a localiser that wraps another (the laser's mounting, the laser odometry):
    ``method``, ``map_data`` (read and set) and :attr:`pose` are the wrapped localiser's, and
    every attribute the wrapper does not have itself is read from it. Picklable when the
    wrapped localiser is (``__getattr__`` answers nothing before ``inner`` is restored)."""

    def __init__(self, inner: Localizer) -> None:
        self.inner = inner

    @property
    def method(self) -> str:
        """The wrapped localiser's method name."""
        return self.inner.method

    @property
    def map_data(self) -> MapData:
        """The wrapped localiser's map."""
        return self.inner.map_data

    @map_data.setter
    def map_data(self, value: MapData) -> None:
        self.inner.map_data = value

    @property
    def pose(self) -> np.ndarray | None:
        """The wrapped localiser's last estimate."""
        return self.inner.pose

    def __getattr__(self, name: str) -> Any:
        inner = self.__dict__.get("inner")
        if inner is None or name.startswith("__"):
            raise AttributeError(name)
        return getattr(inner, name)


class Settings(BaseModel):
    """A settings model whose state pickled by an earlier version loads: a field added since
    takes its default, a field removed since is dropped (a robot's localiser is pickled when
    the service moves it between worker processes, and may have been pickled before an
    upgrade)."""

    def __setstate__(self, state: dict[Any, Any]) -> None:
        super().__setstate__(state)
        fields = type(self).model_fields
        for name in [n for n in self.__dict__ if n not in fields]:
            del self.__dict__[name]
        for name, f in fields.items():
            if name not in self.__dict__:
                self.__dict__[name] = f.get_default(call_default_factory=True)
