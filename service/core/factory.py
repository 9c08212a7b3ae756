"""Select a localisation method by its wire name (``shape | icp | lines``)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from service.core.types import METHODS, Localizer, MapData
from service.errors import LocalizationError

if TYPE_CHECKING:
    from service.core.reloc.view_index import IndexStore


def create_localizer(
    method: str,
    map_data: MapData,
    initial_pose: np.ndarray | None,
    config: Any | None = None,
    *,
    index_store: IndexStore | None = None,
    search_budget_ms: float | None = None,
    laser_offset: Sequence[float] | np.ndarray | None = None,
    laser_odometry: bool | None = None,
) -> Localizer:
    """Return a fresh localiser for one robot.

    ``laser_offset`` is the laser's pose ``[x, y, theta]`` on the robot base (m, rad; ``None``
    or zero: the laser is the robot's origin). With a non-zero one the localiser works on the
    laser's pose as always, and is wrapped (:func:`service.core.mounting.mount`) so that
    ``initial_pose``, the odometry passed in and every estimate are the base's.

    ``initial_pose`` ``None`` asks for global localisation (only ``shape`` supports it; the
    baselines need a start pose). ``config`` is the method's own config model, or ``None`` for
    its defaults (which may depend on ``map_data.kind``); for ``shape`` a
    :class:`service.core.config.LocalizerConfig` (a preset and the user's knobs) or the
    tracker's :class:`~service.core.tracking.shape_config.ShapeConfig` alone.

    ``shape`` returns a :class:`service.core.reloc.global_localization.GlobalShapeLocalizer`: the
    shape tracker plus global search when the pose is unknown or lost. ``index_store`` is where
    its per-map view index is kept across restarts (the service's: files,
    :class:`service.adapters.maps.index_files.IndexFiles`; ``None``: built in memory on the
    first global search). ``search_budget_ms`` spreads its global search over scans within that
    per-scan work budget (``GlobalConfig.search_budget_ms``; ``None``: a whole search per
    scan).

    ``laser_odometry``: a scan that carries no odometry gets the motion measured between it
    and the previous scan as its odometry, decided per scan
    (:class:`service.core.tracking.laser_odometry.LaserOdometryLocalizer`; scans with odometry pass
    unchanged). ``False``: the method alone, as the seed paper runs it without odometry;
    ``None`` (default): on for ``shape``, off for the baselines (``icp`` and ``lines`` stay
    the paper's comparison methods, which start each scan from their previous estimate).
    """
    offset = None
    start = initial_pose
    if laser_offset is not None:
        from service.core.mounting import check_offset, to_laser

        offset = check_offset(laser_offset)
        if not np.any(offset):
            offset = None  # the laser is the origin: the method's localiser itself
        elif initial_pose is not None:
            start = to_laser(np.asarray(initial_pose, dtype=np.float64), offset)
    loc = _method_localizer(method, map_data, start, config, index_store, search_budget_ms)
    if laser_odometry or (laser_odometry is None and method == "shape"):
        from service.core.tracking.laser_odometry import with_laser_odometry

        loc = with_laser_odometry(loc)
    if offset is None:
        return loc
    from service.core.mounting import MountedLocalizer

    return MountedLocalizer(loc, offset)  # type: ignore[return-value]


def _method_localizer(
    method: str,
    map_data: MapData,
    initial_pose: np.ndarray | None,
    config: Any | None,
    index_store: IndexStore | None,
    search_budget_ms: float | None,
) -> Localizer:
    if method == "shape":
        from service.core.config import LocalizerConfig
        from service.core.reloc.config import GlobalConfig
        from service.core.reloc.global_localization import GlobalShapeLocalizer

        if isinstance(config, LocalizerConfig):
            config, g = config.tracking(), config.reloc()
        else:
            g = GlobalConfig.for_kind(map_data.kind)
        if search_budget_ms is not None:
            g = g.model_copy(update={"search_budget_ms": float(search_budget_ms)})
        return GlobalShapeLocalizer(
            map_data, initial_pose, config, gconfig=g, index_store=index_store
        )
    if method == "icp":
        from service.core.baselines.icp import ICPLocalizer

        return ICPLocalizer(map_data, initial_pose, config)
    if method == "lines":
        from service.core.baselines.lines import LineLocalizer

        return LineLocalizer(map_data, initial_pose, config)
    raise LocalizationError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
