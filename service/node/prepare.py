"""The work of first use, done before any robot needs it: worker warm-up and map preparation.

A fresh worker process pays, on its first robot, for importing the methods' modules (~1.6 s
for ``shape`` on the 2-core machine), loading every compiled kernel from numba's on-disk
cache (~0.9 s) and the first run of each code path (the shape matching's first use ~0.3 s);
a stored map pays, on its first global search, for its view index (3.6 s for the office,
26 s for a 160-polyline generated building, under load). Measured on a cold start of 20
robots: the first configuration took 2.1-2.6 s per worker, one worker after the other, and the
first scans queued behind the first-use costs until latest-wins replaced them.

* :func:`warm_up_worker` runs in every worker process before it reports itself ready: it
  imports the methods, loads the kernels and localises a few synthetic scans with each method
  in a small synthetic room (tracking with and without odometry, so the shape matching runs).
* :func:`prepare_map` runs when a map is put (and restored): it localises one synthetic scan
  against *that* map, so per-map first-use work (the map model's grids, the ray caster) is
  done before the service reports the map ready.
* :func:`build_index` builds (or loads) the map's view index of global localisation into the
  on-disk cache every worker reads; the service runs it on the search worker after the map is
  stored, off the tracking workers.

No Zenoh here; every function is pure computation on the core.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

import numpy as np

from service.core.types import MapData

if TYPE_CHECKING:
    from service.core.reloc.view_index import IndexStore

log = logging.getLogger("shapeloc.service.worker")

#: The synthetic room of the warm-up: an outer wall with a recess and a door gap, a pillar and
#: a cabinet (corners, short and long segments: every stage of the shape extraction has work).
_ROOM = [
    [[0.0, 0.0], [8.0, 0.0], [8.0, 2.0], [7.0, 2.0], [7.0, 3.0], [8.0, 3.0], [8.0, 6.0]],
    [[8.0, 6.0], [3.0, 6.0]],
    [[2.2, 6.0], [0.0, 6.0], [0.0, 0.0]],
    [[3.0, 2.5], [3.6, 2.5], [3.6, 3.1], [3.0, 3.1], [3.0, 2.5]],
    [[5.0, 4.6], [6.2, 4.6], [6.2, 5.2], [5.0, 5.2], [5.0, 4.6]],
]
_PATH = np.array(
    [[1.0, 1.0, 0.3], [1.08, 1.03, 0.32], [1.16, 1.07, 0.36], [1.25, 1.1, 0.4], [1.33, 1.15, 0.5]]
)
_ANGLES = np.linspace(-np.pi / 2, np.pi / 2, 181)


def _scans(md: MapData, path: np.ndarray, angles: np.ndarray) -> list[np.ndarray]:
    from service.core.sensor.raycast import RayCaster

    caster = RayCaster(md.segments())
    return [caster.cast(p, angles, 15.0) for p in path]


def _drive(md: MapData, method: str, path: np.ndarray, odom: bool) -> None:
    """One localiser of ``method`` along ``path`` (true poses), with or without odometry."""
    from service.core.factory import create_localizer

    loc = create_localizer(method, md, path[0])
    for p, r in zip(path, _scans(md, path, _ANGLES), strict=True):
        loc.update(r, _ANGLES, p if odom else None)


def warm_up_worker() -> float:
    """Import every method, load every compiled kernel and run each method's code paths once
    on a synthetic room; returns the seconds taken. Never raises (a warm-up that fails only
    leaves the first-use cost to the first robot)."""
    t0 = time.perf_counter()
    try:
        from service.core.warmup import warm_up

        warm_up()
        md = MapData.from_lists("~warm-up", "metric", _ROOM)
        for method, odom in (("shape", True), ("shape", False), ("icp", True), ("lines", True)):
            _drive(md, method, _PATH, odom)
    except Exception:  # a warm-up must never keep a worker from serving
        log.exception("worker warm-up failed; the first robots pay the first-use cost")
    return time.perf_counter() - t0


def free_pose(md: MapData) -> np.ndarray | None:
    """A pose inside the map's extent with clearance from every segment (>= 0.3 m), found on a
    coarse grid from the centre outwards; ``None`` when there is none."""
    segs = md.segments()
    if len(segs) == 0:
        return None
    lo = np.minimum(segs[:, 0:2], segs[:, 2:4]).min(axis=0)
    hi = np.maximum(segs[:, 0:2], segs[:, 2:4]).max(axis=0)
    centre = 0.5 * (lo + hi)
    xs = np.linspace(lo[0], hi[0], 21)[1:-1]
    ys = np.linspace(lo[1], hi[1], 21)[1:-1]
    grid = np.array([(x, y) for x in xs for y in ys])
    if grid.size == 0:
        return None
    grid = grid[np.argsort(np.hypot(*(grid - centre).T))]
    a, b = segs[:, 0:2], segs[:, 2:4]
    d = b - a
    dd = np.maximum(np.einsum("ij,ij->i", d, d), 1e-12)
    for p in grid[:64]:
        t = np.clip(np.einsum("ij,ij->i", p - a, d) / dd, 0.0, 1.0)
        if np.min(np.hypot(*(a + t[:, None] * d - p).T)) >= 0.3:
            return np.array([p[0], p[1], 0.0])
    return None


def prepare_map(md: MapData) -> float:
    """Localise a short synthetic drive against ``md`` with the ``shape`` tracker (the map's
    own first-use work: model grids, ray caster, view extraction at this map's size); returns
    the seconds taken. Never raises."""
    t0 = time.perf_counter()
    try:
        p = free_pose(md)
        if p is not None:
            path = p + (_PATH - _PATH[0]) * np.array([0.5, 0.5, 1.0])
            _drive(md, "shape", path, odom=True)
    except Exception:
        log.exception("preparing map %s failed; its first robot pays the first-use cost", md.map_id)
    return time.perf_counter() - t0


def build_index(md: MapData, store: IndexStore | None) -> float:
    """Build (or load) ``md``'s view index of global localisation into ``store`` (the files
    every worker reads), with the shape method's default configuration for the
    map's kind; returns the seconds taken. Raises on failure (the caller reports it)."""
    from service.core.reloc.config import GlobalConfig
    from service.core.reloc.global_localization import load_or_build_index
    from service.core.tracking.shape_config import ShapeConfig

    t0 = time.perf_counter()
    load_or_build_index(md, ShapeConfig.for_kind(md.kind), GlobalConfig.for_kind(md.kind), store)
    return time.perf_counter() - t0
