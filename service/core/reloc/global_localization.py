"""The ``shape`` method's localiser (:class:`GlobalShapeLocalizer`): the parts every state uses
(the tracker, the map's view index, the odometry) and the state (:mod:`.states`); each scan is
one :func:`.states.step`. REP 103, metres and radians; poses ``[x, y, theta]`` in the map frame.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.core.reloc import states as st
from service.core.reloc.config import GlobalConfig
from service.core.reloc.view_index import IndexStore, ViewIndex, load_or_build_index
from service.core.tracking.localizer import ShapeConfig, ShapeLocalizer
from service.core.tracking.motion import check_pose3
from service.core.tracking.scan_odometry import Odometry
from service.core.types import Estimate, MapData, check_scan
from service.errors import LocalizationError

__all__ = ["GlobalConfig", "GlobalShapeLocalizer", "ShapeConfig", "load_or_build_index"]


class GlobalShapeLocalizer:
    """Shape-based localisation with relocalisation (a :class:`service.core.types.Localizer`,
    method ``shape``). ``initial_pose`` ``None``: unknown (global localisation); ``config`` and
    ``gconfig`` default to the map kind's presets; ``index_store``: where the map's
    :class:`ViewIndex` is kept between runs (``None``: in memory only), loaded or built on the
    first scan that searches. Each estimate carries its state (:class:`.states.State`'s name)."""

    method = "shape"

    def __init__(
        self,
        map_data: MapData,
        initial_pose: np.ndarray | None,
        config: ShapeConfig | None = None,
        *,
        gconfig: GlobalConfig | None = None,
        index_store: IndexStore | None = None,
    ) -> None:
        if config is not None and not isinstance(config, ShapeConfig):
            raise LocalizationError(f"config must be a ShapeConfig, got {type(config).__name__}")
        self.map_data = map_data
        self.config = config or ShapeConfig.for_kind(map_data.kind)
        self.gconfig = gconfig or GlobalConfig.for_kind(map_data.kind)
        self.index_store = index_store
        self.tracker = ShapeLocalizer(map_data, initial_pose, self.config)
        self.odometry = Odometry(self.config.motion)
        self._index: ViewIndex | None = None
        self.state: st.State = st.Tracking()
        self.work_ms = 0.0  # reference ms of search work on the last scan
        self.reset(initial_pose)

    def __getstate__(self) -> dict[str, object]:
        """Picklable state without the view index (a new process loads it on first use)."""
        return {**self.__dict__, "_index": None}

    def __setstate__(self, state: dict[str, Any]) -> None:
        if "state" not in state:
            state = _from_earlier(state)
        # an earlier version kept its index files' directory: the index is shared or built here
        state.pop("cache_dir", None)
        self.__dict__.update({"index_store": None, **state})

    @property
    def index(self) -> ViewIndex:
        """The map's view index (loaded or built on first use)."""
        if self._index is None:
            self._index = load_or_build_index(
                self.map_data, self.config, self.gconfig, self.index_store
            )
        return self._index

    @property
    def pose(self) -> np.ndarray | None:
        """The last tracked (or dead-reckoned) pose, ``None`` while searching."""
        if isinstance(self.state, st.Tracking):
            return self.tracker.pose
        if isinstance(self.state, st.DeadReckoning):
            return self.state.pose.copy()
        return None

    @property
    def searching(self) -> bool:
        """``True`` while the pose is unknown: searching, or a winner on probation."""
        return isinstance(self.state, st.Searching | st.Probation)

    @property
    def unsettled(self) -> bool:
        """Searching, or fixed by a search fewer than ``settle_scans`` scans ago: where a
        service keeps the robot on its search worker."""
        s = self.state
        return not isinstance(s, st.Tracking) or s.since_fix < self.gconfig.settle_scans

    def set_search_budget(self, ms: float) -> None:
        """Set the per-scan work budget of a budgeted search (a search without a budget
        stays whole). The service halves it while other robots share this robot's worker."""
        g = self.gconfig
        if g.search_budget_ms is not None and g.search_budget_ms != ms:
            self.gconfig = g.model_copy(update={"search_budget_ms": float(ms)})

    def reset(self, initial_pose: np.ndarray | None, odom: np.ndarray | None = None) -> None:
        """Forget the history; ``None`` starts a global search (status ``initializing``).
        ``odom``: odometry pose at ``initial_pose`` (the next increment starts from it)."""
        self.tracker.reset(initial_pose, odom)
        o = None if odom is None else check_pose3(odom, "odom")
        self.odometry.reset(o if initial_pose is not None else None)
        self.state = st.Searching() if initial_pose is None else st.Tracking()
        self.work_ms = 0.0

    def update(
        self,
        ranges: np.ndarray,
        angles: np.ndarray,
        odom: np.ndarray | None = None,
        odom_spread: np.ndarray | None = None,
        from_scans: bool = False,
    ) -> Estimate:
        """Localise one scan (:meth:`service.core.types.Localizer.update`). ``odom_spread``:
        the increment's translation variance beyond the odometry model's; ``from_scans``:
        ``odom`` was measured from the scans (laser odometry) and cannot vouch for a pose the
        scan contradicts (``GlobalConfig.scan_odometry_violation``)."""
        r, a = check_scan(ranges, angles)
        o = None if odom is None else check_pose3(odom, "odom")
        step = self.odometry.step(r, a, o, odom_spread)
        use = step.reading is not None and self.config.motion.use_odometry
        scan = st.Scan(r, a, step, use, from_scans and step.reading is not None)
        self.work_ms = 0.0
        self.state, est = st.step(self, self.state, scan)
        return est


def _from_earlier(old: dict[str, Any]) -> dict[str, Any]:
    """The state of a localiser pickled by an earlier version (one class with a search
    mode): its tracker, map and settings are kept; a robot that was tracking goes on
    tracking from its pose, one that was searching starts a new search."""
    new = {k: old[k] for k in ("map_data", "config", "tracker") if k in old}
    g = GlobalConfig.for_kind(new["map_data"].kind)
    budget = getattr(old.get("gconfig"), "search_budget_ms", None)
    if budget is not None:
        g = g.model_copy(update={"search_budget_ms": float(budget)})
    new.update(gconfig=g, _index=None, work_ms=0.0)
    odo = Odometry(new["config"].motion)
    last = old.get("_last_odom")
    odo.reset(None if last is None else np.asarray(last, dtype=np.float64))
    new["odometry"] = odo
    tracking = not old.get("_searching", True) and old.get("_probation") is None
    if tracking and new["tracker"].pose is not None:
        new["state"] = st.Tracking()
    else:
        status = "lost" if old.get("_search_status") == "lost" else "initializing"
        new["state"] = st.Searching(status=status)
    return new
