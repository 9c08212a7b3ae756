"""The localisers a benchmark runs by name: the service's methods (``shape``, ``icp``,
``lines``, as :func:`service.core.factory.create_localizer` builds them) and ``shape-paper``.

``shape`` is what the service gives a robot: on a scan without odometry its laser odometry
(:mod:`service.core.tracking.laser_odometry`) measures the motion from the previous scan.
``shape-paper`` is the same localiser without it, the seed paper's own mode (no odometry of any
kind: the robot's recent velocity is the prior); with odometry on every scan the two are the
same bit for bit.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from service.core.factory import create_localizer
from service.core.types import METHODS, Localizer, MapData

__all__ = ["BENCH_METHODS", "PAPER", "make_localizer"]

#: ``shape`` without the laser odometry: the seed paper's mode.
PAPER = "shape-paper"
#: Every name a benchmark accepts, in table order.
BENCH_METHODS: tuple[str, ...] = ("shape", PAPER, *(m for m in METHODS if m != "shape"))


def make_localizer(
    method: str, map_data: MapData, initial_pose: np.ndarray | None, **kw: Any
) -> Localizer:
    """``create_localizer(method, ...)``; ``shape-paper``: ``shape`` with
    ``laser_odometry=False``."""
    if method == PAPER:
        return create_localizer("shape", map_data, initial_pose, laser_odometry=False, **kw)
    return create_localizer(method, map_data, initial_pose, **kw)
