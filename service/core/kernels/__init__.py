"""Conventions and shared helpers of the shape-based localiser's compiled inner loops
(implementation details, numba).

The kernels live in one module per concept; each is called by the public function that owns
the concept and its docstring:

- :mod:`service.core.kernels.similarity`: S*'s arc tables and DP
  (:mod:`service.core.shapes.similarity`);
- :mod:`service.core.kernels.dce`: fixed-threshold DCE (:func:`service.core.shapes.dce.dce`);
- :mod:`service.core.kernels.extract`: the cut into pieces, the map view's hit segments and
  the DCE and cut of a whole reading (:mod:`service.core.shapes.configuration`);
- :mod:`service.core.kernels.matching`: eq. 5's angular intervals, candidate blocks, their
  centroids and the extended DP (:mod:`service.core.shapes.matching`,
  :mod:`service.core.shapes.order_dp`);
- :mod:`service.core.kernels.shape`: the same, batched over many pairs / blocks in one call;
- :mod:`service.core.kernels.grid`: an exact bucket grid of points
  (:mod:`service.core.shapes.two_step`, :mod:`service.core.tracking.scan_odometry`);
- :mod:`service.core.kernels.pose` (the pose fits), :mod:`service.core.kernels.map` (the map
  model), :mod:`service.core.kernels.odometry` (the odometry check),
  :mod:`service.core.kernels.search` (global search's scores) and
  :mod:`service.core.kernels.raycast` (the ray casting).

They take ``njit`` and the shared helpers (``wrap``, ``solve3``, ``TWO_PI``) from here
(this package's ``__init__``, which imports none of them: no import ring). The
arithmetic follows the numpy reference implementations expression by expression (no
``fastmath``), so results agree with them to the last bits except where a libm call differs;
tests compare both on random inputs.

numba is optional: without it (``HAVE_NUMBA`` is ``False``) the callers run their numpy
reference code; they read the flag here (``kernels.HAVE_NUMBA``) on every call. Kernels are
compiled with ``cache=True`` (on-disk cache next to their module, or under
``NUMBA_CACHE_DIR``), so a fresh process loads them instead of compiling;
:func:`service.core.warmup.warm_up` compiles or loads them all.
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


TWO_PI = 2.0 * math.pi


@njit(cache=True, nogil=True)
def wrap(a: float) -> float:
    """(-pi, pi] like :func:`service.core.types.wrap_angle`."""
    return math.pi - ((math.pi - a) % TWO_PI)


@njit(cache=True, nogil=True)
def solve3(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``A x = b`` for a 3x3 ``A``: LU with partial pivoting in LAPACK's order (dgetf2 +
    dgetrs), without the per-call overhead of ``np.linalg.solve``. ``A`` is overwritten."""
    x = b.copy()
    solve3_into(A, x)
    return x


@njit(cache=True, nogil=True)
def solve3_into(A: np.ndarray, x: np.ndarray) -> None:
    """:func:`solve3` in place: ``x`` holds ``b`` on entry and the solution on return."""
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
