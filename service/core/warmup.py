"""Compile or load every compiled kernel of the core before the first scan needs one.

A leaf module: nothing in the core imports it (the service's workers and the benchmarks call
:func:`warm_up` at start-up), so it may import every layer it exercises without an import
ring through the kernels' package.
"""

from __future__ import annotations

import time

import numpy as np

from service.core import kernels, numeric
from service.core.kernels import dce as dce_kernels
from service.core.kernels import extract as extract_kernels
from service.core.kernels import grid as grid_kernels
from service.core.kernels import matching as matching_kernels
from service.core.kernels import pose as pose_kernels
from service.core.kernels import raycast as raycast_kernels
from service.core.kernels import search as search_kernels
from service.core.kernels import shape as shape_kernels
from service.core.kernels import similarity as similarity_kernels
from service.core.sensor.mapmodel import MapModel
from service.core.sensor.refine import RefineParams, refine_pose
from service.core.tracking.motion import MotionConfig
from service.core.tracking.scan_odometry import ScanOdometry
from service.core.types import MapData


def warm_up() -> float:
    """Compile (first run after an install or a change of a kernel module, ~10 s) or load from
    the on-disk cache (~0.3 s) every kernel, on tiny inputs; returns the seconds taken. Call it
    once at image build / install time so that services and tests start warm."""
    t0 = time.perf_counter()
    if not kernels.HAVE_NUMBA:
        return 0.0

    p = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [2.0, 1.0]])
    segs = np.array([[0.0, -0.1, 2.0, -0.1], [2.1, -0.1, 2.1, 1.0]])
    own = np.zeros(4, dtype=np.intp)
    z = np.zeros(1, dtype=np.intp)
    two = np.array([2], dtype=np.intp)
    pose_kernels.fit_blocks(
        p, np.arange(4), z, np.array([4]), segs, z, two, np.zeros((1, 3)), 2, 0.1, 0.05
    )
    pose_kernels.pose_iterations(
        p, own, segs, z, two, np.zeros(3), 2, 0.3, 0.05, 1e-3, 1e-6, np.zeros(3), 0.0
    )
    similarity_kernels.warm_up()
    dce_kernels.warm_up()
    extract_kernels.warm_up()
    matching_kernels.warm_up()
    grid_kernels.warm_up()
    # the batch kernels of the shape matching
    whole = np.array([[0, -1]], dtype=np.intp)
    off = np.array([0, 4], dtype=np.intp)
    shape_kernels.shape_distances(p, off, whole, p, off, whole, 4, 0.1, 0.5, 1.0)
    shape_kernels.piece_means(p, off, whole)
    shape_kernels.interval_gates(np.zeros((1, 2)), np.ones((2, 2)), 0.1, -1.0, 1.0)
    shape_kernels.block_pieces(np.zeros((1, 4), dtype=np.intp), z, 3, 2)
    shape_kernels.order_dp_blocks(np.ones(1), np.ones(1), z, z, z, z, np.ones(1))
    search_kernels.warm_up(p)
    raycast_kernels.warm_up()
    # the map model's kernels (service.core.kernels.map)

    model = MapModel(MapData.from_lists("warm-up", "metric", [p]))
    refine_pose(model, p, np.zeros(3), RefineParams(iterations=2))
    model.nearest(p, 0.5, np.full_like(p, np.nan))
    # the scan-to-scan fit of the odometry check (service.core.kernels.odometry)

    check = ScanOdometry(MotionConfig().scan_odometry, MotionConfig())
    beams = np.linspace(-1.5, 1.5, 40)
    wall = 1.0 / np.maximum(np.cos(beams), 0.2)
    check.correct(wall, beams, np.zeros(3))
    check.correct(wall, beams, np.array([0.01, 0.0, 0.0]))
    # the machine-independent elementwise functions and small solves (service.core.numeric)

    numeric.atan2(p[:, 1], p[:, 0])
    numeric.exp(p[:, 0])
    numeric.log(p[:, 0])
    numeric.tanh(p[:, 0])
    numeric.solve(np.eye(3), np.ones(3))
    return time.perf_counter() - t0
