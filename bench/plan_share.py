"""How much of a drive the map shows: a benchmark diagnostic, not part of the localiser.

A floor plan draws walls, not furniture. Where the robot drives through a hall whose plan is
an outline, most returns land on things the plan does not have, and no localiser that only
has the plan can tell that hall's places apart until the robot leaves it. To tell such
trials from the localiser's own failures, each drive trial records its *plan share*: per
scan with a reference pose, the share of returns (up to ``max_range``) that lie within
``tolerance`` of a mapped wall when the scan is placed at the reference pose; averaged over
the trial's scans. It uses the reference pose, so it describes the map and the place, and
reads nothing the localiser computed.

On fr079's schematised map (tuning log, 40 starts, seed 11, commit 136fd58) every trial
whose drive had a plan share below 0.5 (all in the hall at the east end, x 4-13 m,
y 0-6 m) went unfixed within 15 m; 31 of the 33 others were fixed within 15 m.
"""

from __future__ import annotations

import numpy as np

from service.core.sensor.mapmodel import MapModel
from service.core.types import MapData

#: The map holds at a scan when at least this share of its returns lies within the tolerance
#: (0.3 m) of a mapped wall: the map shows most of what the robot sees.
HOLDS_SHARE = 0.5


class PlanShare:
    """The plan-share test of one map: the map's own nearest-wall query
    (:meth:`service.core.sensor.mapmodel.MapModel.nearest`, exact point-to-segment distances)."""

    def __init__(self, map_data: MapData, tolerance: float = 0.3, max_range: float = 15.0) -> None:
        self._model = MapModel(map_data, reach=max(1.0, tolerance))
        self.tolerance = tolerance
        self.max_range = max_range

    def scan_share(self, pose: np.ndarray, ranges: np.ndarray, angles: np.ndarray) -> float:
        """Share of the scan's returns within ``tolerance`` of a wall with the robot at
        ``pose`` ``[x, y, theta]``; NaN without a finite pose or without returns."""
        p = np.asarray(pose, dtype=np.float64)
        r = np.asarray(ranges, dtype=np.float64)
        a = np.asarray(angles, dtype=np.float64)
        ok = np.isfinite(r) & (r > 0.0) & (r <= self.max_range)
        if not np.all(np.isfinite(p)) or not ok.any():
            return float("nan")
        th = p[2] + a[ok]
        xy = np.column_stack([p[0] + r[ok] * np.cos(th), p[1] + r[ok] * np.sin(th)])
        d = self._model.nearest(xy, self.tolerance).distance
        return float(np.mean(d <= self.tolerance))
