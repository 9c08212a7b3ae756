"""Conventions and shared helpers of the shape-based localiser's compiled inner loops
(implementation details, numba).

The kernels live in one module per concept; each is called by the public function that owns
the concept and its docstring:

- :mod:`service.core._similarity_kernels`: S*'s arc tables and DP
  (:mod:`service.core.similarity`);
- :mod:`service.core._dce_kernels`: fixed-threshold DCE (:func:`service.core.dce.dce`);
- :mod:`service.core._extract_kernels`: the cut into pieces, the map view's hit segments and
  the DCE and cut of a whole reading (:mod:`service.core.configuration`);
- :mod:`service.core._matching_kernels`: eq. 5's angular intervals, candidate blocks, their
  centroids and the extended DP (:mod:`service.core.matching`, :mod:`service.core.order_dp`);
- :mod:`service.core._shape_kernels`: the same, batched over many pairs / blocks in one call;
- :mod:`service.core._grid_kernels`: an exact bucket grid of points
  (:mod:`service.core.two_step`, :mod:`service.core.scan_odometry`);
- :mod:`service.core._pose_kernels` (the pose fits), :mod:`service.core._map_kernels` (the map
  model), :mod:`service.core._odometry_kernels` (the odometry check),
  :mod:`service.core._search_kernels` (global search's scores) and
  :mod:`service.core._raycast_kernels` (the ray casting).

They take ``njit`` and the shared helpers (``_wrap``, ``_solve3``, ``_TWO_PI``) from here. The
arithmetic follows the numpy reference implementations expression by expression (no
``fastmath``), so results agree with them to the last bits except where a libm call differs;
tests compare both on random inputs.

numba is optional: without it (``HAVE_NUMBA`` is ``False``) the callers run their numpy
reference code; they read the flag here (``_kernels.HAVE_NUMBA``) on every call. Kernels are
compiled with ``cache=True`` (on-disk cache next to their module, or under
``NUMBA_CACHE_DIR``), so a fresh process loads them instead of compiling; :func:`warm_up`
compiles or loads them all.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

try:  # pragma: no cover - exercised by whichever environment runs the tests
    from numba import njit

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False

    def njit(*_args: Any, **_kwargs: Any) -> Any:  # type: ignore[no-redef]
        def deco(fn: Any) -> Any:
            return fn

        return deco


_TWO_PI = 2.0 * math.pi


@njit(cache=True, nogil=True)
def _wrap(a: float) -> float:
    """(-pi, pi] like :func:`service.core.types.wrap_angle`."""
    return math.pi - ((math.pi - a) % _TWO_PI)


@njit(cache=True, nogil=True)
def _solve3(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A x = b`` for a 3x3 ``A``: LU with partial pivoting in LAPACK's order (dgetf2 +
    dgetrs), without the per-call overhead of ``np.linalg.solve``. ``A`` is overwritten."""
    x = b.copy()
    _solve3_into(A, x)
    return x


@njit(cache=True, nogil=True)
def _solve3_into(A: np.ndarray, x: np.ndarray) -> None:
    """:func:`_solve3` in place: ``x`` holds ``b`` on entry and the solution on return."""
    for j in range(3):
        p = j
        big = abs(A[j, j])
        for i in range(j + 1, 3):
            if abs(A[i, j]) > big:
                big = abs(A[i, j])
                p = i
        if p != j:
            for k in range(3):
                t = A[j, k]
                A[j, k] = A[p, k]
                A[p, k] = t
            t = x[j]
            x[j] = x[p]
            x[p] = t
        if A[j, j] != 0.0:
            r = 1.0 / A[j, j]
            for i in range(j + 1, 3):
                A[i, j] *= r
        for i in range(j + 1, 3):
            for k in range(j + 1, 3):
                A[i, k] -= A[i, j] * A[j, k]
    for k in range(3):  # L y = b (unit lower)
        if x[k] != 0.0:
            for i in range(k + 1, 3):
                x[i] -= x[k] * A[i, k]
    for k in range(2, -1, -1):  # U x = y
        if x[k] != 0.0:
            x[k] /= A[k, k]
            for i in range(k):
                x[i] -= x[k] * A[i, k]


def warm_up() -> float:
    """Compile (first run after an install or a change of a kernel module, ~10 s) or load from
    the on-disk cache (~0.3 s) every kernel, on tiny inputs; returns the seconds taken. Call it
    once at image build / install time so that services and tests start warm."""
    import time

    t0 = time.perf_counter()
    if not HAVE_NUMBA:
        return 0.0
    # the kernel modules import this one, so they are imported here, not at module level
    from service.core import (
        _dce_kernels,
        _extract_kernels,
        _grid_kernels,
        _matching_kernels,
        _pose_kernels,
        _raycast_kernels,
        _search_kernels,
        _shape_kernels,
        _similarity_kernels,
    )

    p = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [2.0, 1.0]])
    segs = np.array([[0.0, -0.1, 2.0, -0.1], [2.1, -0.1, 2.1, 1.0]])
    own = np.zeros(4, dtype=np.intp)
    z = np.zeros(1, dtype=np.intp)
    two = np.array([2], dtype=np.intp)
    _pose_kernels.fit_blocks(
        p, np.arange(4), z, np.array([4]), segs, z, two, np.zeros((1, 3)), 2, 0.1, 0.05
    )
    _pose_kernels.pose_iterations(
        p, own, segs, z, two, np.zeros(3), 2, 0.3, 0.05, 1e-3, 1e-6, np.zeros(3), 0.0
    )
    _similarity_kernels.warm_up()
    _dce_kernels.warm_up()
    _extract_kernels.warm_up()
    _matching_kernels.warm_up()
    _grid_kernels.warm_up()
    # the batch kernels of the shape matching
    whole = np.array([[0, -1]], dtype=np.intp)
    off = np.array([0, 4], dtype=np.intp)
    _shape_kernels.shape_distances(p, off, whole, p, off, whole, 4, 0.1, 0.5, 1.0)
    _shape_kernels.piece_means(p, off, whole)
    _shape_kernels.interval_gates(np.zeros((1, 2)), np.ones((2, 2)), 0.1, -1.0, 1.0)
    _shape_kernels.block_pieces(np.zeros((1, 4), dtype=np.intp), z, 3, 2)
    _shape_kernels.order_dp_blocks(np.ones(1), np.ones(1), z, z, z, z, np.ones(1))
    _search_kernels.warm_up(p)
    _raycast_kernels.warm_up()
    # the map model's kernels (service.core._map_kernels; imported here, not at module level,
    # because that module imports this one)
    from service.core.mapmodel import MapModel
    from service.core.refine import RefineParams, refine_pose
    from service.core.types import MapData

    model = MapModel(MapData.from_lists("warm-up", "metric", [p]))
    refine_pose(model, p, np.zeros(3), RefineParams(iterations=2))
    model.nearest(p, 0.5, np.full_like(p, np.nan))
    # the scan-to-scan fit of the odometry check (service.core._odometry_kernels)
    from service.core.motion import MotionConfig
    from service.core.scan_odometry import ScanOdometry

    check = ScanOdometry(MotionConfig().scan_odometry, MotionConfig())
    beams = np.linspace(-1.5, 1.5, 40)
    wall = 1.0 / np.maximum(np.cos(beams), 0.2)
    check.correct(wall, beams, np.zeros(3))
    check.correct(wall, beams, np.array([0.01, 0.0, 0.0]))
    # the machine-independent elementwise functions and small solves (service.core.numeric)
    from service.core import numeric

    numeric.atan2(p[:, 1], p[:, 0])
    numeric.exp(p[:, 0])
    numeric.log(p[:, 0])
    numeric.tanh(p[:, 0])
    numeric.solve(np.eye(3), np.ones(3))
    return time.perf_counter() - t0
