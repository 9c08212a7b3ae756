"""Floating point that gives the same bits on every x86-64 CPU with FMA: the few numpy
operations whose result depends on the machine, done another way.

Why: the same scan, map and odometry must give the same pose wherever the service runs, and a
global search decides between near-equal places by comparing floats, so one differing last bit
can change which place is fixed. Two numpy paths differ between CPUs of the same architecture:

* numpy dispatches ``arctan2``, ``arctan``, ``exp``, ``log``, ``log1p``, ``power`` and ``tanh``
  to AVX-512 code (SVML; ``tanh`` also to AVX2 code) on CPUs that have it and to the C library
  (libm) elsewhere; the two differ in the last bit for a few percent of the inputs (measured:
  ``arctan2`` 7 %, ``exp`` 4.5 %, ``log`` 0.06 % of 200 000 random inputs). ``sin``, ``cos``,
  ``hypot``, ``sqrt``, the arithmetic operators, ``sum`` and ``einsum`` gave the same bits with
  every dispatch level.
* matrix products (``@``, ``np.dot``, ``np.matmul``), ``np.convolve`` / ``np.correlate`` and
  ``np.linalg`` go to OpenBLAS, which picks its kernels by CPU (Haswell, SkylakeX, Zen, ...):
  different summation orders and fused multiply-adds, so different bits.

Here the transcendental functions call the C library's own functions element by element
(compiled loops; the same bits as :mod:`math` and as numpy on a CPU without AVX-512), products
are :func:`numpy.einsum` (numpy's own loops, no BLAS) and small linear systems are solved by
compiled LU with partial pivoting in LAPACK's order. The C library picks its variant by CPU
too, but every x86-64 CPU with FMA (all since 2013) takes the same one.
``tests/service/core/test_numeric.py`` runs a drive under several emulated CPUs (numpy's
dispatch and OpenBLAS's kernels switched by environment) and requires the same bits.

Use these in the core (and in whatever produces its inputs: the simulator, map import) instead
of ``np.arctan2`` / ``np.exp`` / ``np.log`` / ``@`` / ``np.linalg``.
"""

from __future__ import annotations

import math

import numpy as np

from service.core.kernels import HAVE_NUMBA, njit

__all__ = [
    "atan2",
    "dot",
    "eigh_sym2",
    "exp",
    "inv",
    "log",
    "matmul",
    "matvec",
    "quadratic",
    "solve",
    "tanh",
]


@njit(cache=True, nogil=True)
def _atan2_loop(y: np.ndarray, x: np.ndarray, out: np.ndarray) -> None:
    for i in range(out.size):
        out[i] = math.atan2(y[i], x[i])


@njit(cache=True, nogil=True)
def _exp_loop(x: np.ndarray, out: np.ndarray) -> None:
    for i in range(out.size):
        out[i] = math.exp(x[i])


@njit(cache=True, nogil=True)
def _tanh_loop(x: np.ndarray, out: np.ndarray) -> None:
    for i in range(out.size):
        out[i] = math.tanh(x[i])


@njit(cache=True, nogil=True)
def _log_loop(x: np.ndarray, out: np.ndarray) -> None:
    for i in range(out.size):
        v = x[i]
        # math.log raises on <= 0 in Python; numpy's conventions (-inf, nan) are kept here
        if v > 0.0:
            out[i] = math.log(v)
        elif v == 0.0:
            out[i] = -math.inf
        else:
            out[i] = math.nan


def _flat(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64).reshape(-1)


def atan2(y: np.ndarray | float, x: np.ndarray | float) -> np.ndarray | float:
    """``arctan2(y, x)`` elementwise (broadcast like numpy), in (-pi, pi]; a float for two
    scalars."""
    if np.ndim(y) == 0 and np.ndim(x) == 0:
        return math.atan2(float(y), float(x))
    yb, xb = np.broadcast_arrays(np.asarray(y, dtype=np.float64), np.asarray(x, dtype=np.float64))
    out = np.empty(yb.shape)
    if HAVE_NUMBA:
        _atan2_loop(_flat(yb), _flat(xb), out.reshape(-1))
    else:  # pragma: no cover - numba is a dependency
        out.reshape(-1)[:] = [math.atan2(a, b) for a, b in zip(_flat(yb), _flat(xb), strict=True)]
    return out


def exp(x: np.ndarray | float) -> np.ndarray | float:
    """``e**x`` elementwise; a float for a scalar."""
    if np.ndim(x) == 0:
        v = float(x)
        return math.exp(v) if v < 709.8 else math.inf
    xa = np.asarray(x, dtype=np.float64)
    out = np.empty(xa.shape)
    if HAVE_NUMBA:
        _exp_loop(_flat(xa), out.reshape(-1))
    else:  # pragma: no cover
        out.reshape(-1)[:] = [math.exp(v) if v < 709.8 else math.inf for v in _flat(xa)]
    return out


def log(x: np.ndarray | float) -> np.ndarray | float:
    """Natural logarithm elementwise (``-inf`` at 0, ``nan`` below, as numpy); a float for a
    scalar."""
    xa = np.asarray(x, dtype=np.float64)
    out = np.empty(xa.shape)
    if HAVE_NUMBA:
        _log_loop(_flat(xa), out.reshape(-1))
    else:  # pragma: no cover
        out.reshape(-1)[:] = [
            math.log(v) if v > 0 else (-math.inf if v == 0 else math.nan) for v in _flat(xa)
        ]
    return float(out) if np.ndim(x) == 0 else out


def tanh(x: np.ndarray | float) -> np.ndarray | float:
    """Hyperbolic tangent elementwise; a float for a scalar."""
    if np.ndim(x) == 0:
        return math.tanh(float(x))
    xa = np.asarray(x, dtype=np.float64)
    out = np.empty(xa.shape)
    if HAVE_NUMBA:
        _tanh_loop(_flat(xa), out.reshape(-1))
    else:  # pragma: no cover
        out.reshape(-1)[:] = [math.tanh(v) for v in _flat(xa)]
    return out


def dot(a: np.ndarray, b: np.ndarray) -> float:
    """Inner product of two 1-D vectors (``a @ b`` without BLAS)."""
    return float(np.einsum("i,i->", np.asarray(a, np.float64), np.asarray(b, np.float64)))


def matvec(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``m @ v`` for ``m`` of shape (..., r, c) and ``v`` of shape (c,) or (..., c)."""
    return np.einsum("...ij,...j->...i", np.asarray(m, np.float64), np.asarray(v, np.float64))


def matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for 2-D (or stacked, ``(..., n, k) @ (..., k, m)``) arrays, without BLAS."""
    return np.einsum("...ij,...jk->...ik", np.asarray(a, np.float64), np.asarray(b, np.float64))


def quadratic(e: np.ndarray, m: np.ndarray) -> float:
    """``e @ m @ e`` (a squared Mahalanobis distance for an information matrix ``m``)."""
    e = np.asarray(e, np.float64)
    return float(np.einsum("i,ij,j->", e, np.asarray(m, np.float64), e))


@njit(cache=True, nogil=True)
def _lu_solve_into(A: np.ndarray, X: np.ndarray) -> bool:
    """``A X = B`` in place (``X`` holds ``B``, n x r, on entry): LU with partial pivoting in
    LAPACK's order (dgetf2 + dgetrs). Returns False, leaving garbage, when a pivot is exactly
    zero (LAPACK's ``info > 0``). ``A`` is overwritten."""
    n = A.shape[0]
    r = X.shape[1]
    for j in range(n):
        p = j
        big = abs(A[j, j])
        for i in range(j + 1, n):
            if abs(A[i, j]) > big:
                big = abs(A[i, j])
                p = i
        if A[p, j] == 0.0:
            return False
        if p != j:
            for k in range(n):
                t = A[j, k]
                A[j, k] = A[p, k]
                A[p, k] = t
            for k in range(r):
                t = X[j, k]
                X[j, k] = X[p, k]
                X[p, k] = t
        inv = 1.0 / A[j, j]
        for i in range(j + 1, n):
            A[i, j] *= inv
        for i in range(j + 1, n):
            for k in range(j + 1, n):
                A[i, k] -= A[i, j] * A[j, k]
    for c in range(r):
        for k in range(n):  # L y = b (unit lower)
            if X[k, c] != 0.0:
                for i in range(k + 1, n):
                    X[i, c] -= X[k, c] * A[i, k]
        for k in range(n - 1, -1, -1):  # U x = y
            if X[k, c] != 0.0:
                X[k, c] /= A[k, k]
                for i in range(k):
                    X[i, c] -= X[k, c] * A[i, k]
    return True


@njit(cache=True, nogil=True)
def _lu_solve_many(A: np.ndarray, X: np.ndarray, ok: np.ndarray) -> None:
    for s in range(A.shape[0]):
        ok[s] = _lu_solve_into(A[s], X[s])


def solve(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.linalg.solve(a, b)`` for small systems (``a`` (n, n) or stacked (k, n, n); ``b``
    (n,), (n, r) or stacked alike), without LAPACK. Raises :class:`numpy.linalg.LinAlgError`
    on an exactly singular matrix, as numpy does."""
    A = np.array(a, dtype=np.float64)  # copies: the LU overwrites it
    B = np.array(b, dtype=np.float64)
    single = A.ndim == 2
    if single:
        A = A[None]
        B = B[None]
    vec = B.ndim == A.ndim - 1
    X = np.ascontiguousarray(B[..., None] if vec else B)
    A = np.ascontiguousarray(A)
    ok = np.ones(A.shape[0], dtype=np.bool_)
    if HAVE_NUMBA:
        _lu_solve_many(A, X, ok)
    else:  # pragma: no cover
        X = np.linalg.solve(A, X)
    if not ok.all():
        raise np.linalg.LinAlgError("Singular matrix")
    X = X[..., 0] if vec else X
    return X[0] if single else X


def inv(a: np.ndarray) -> np.ndarray:
    """``np.linalg.inv`` of a small square matrix without LAPACK (LinAlgError if singular)."""
    a = np.asarray(a, dtype=np.float64)
    return solve(a, np.eye(a.shape[-1]))


def det3(m: np.ndarray) -> float:
    """Determinant of a 3x3 matrix by cofactors along the first row (``np.linalg.det`` goes to
    LAPACK, whose kernels differ by CPU)."""
    return float(
        m[0, 0] * (m[1, 1] * m[2, 2] - m[1, 2] * m[2, 1])
        - m[0, 1] * (m[1, 0] * m[2, 2] - m[1, 2] * m[2, 0])
        + m[0, 2] * (m[1, 0] * m[2, 1] - m[1, 1] * m[2, 0])
    )


def eigh_sym2(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues (ascending) and unit eigenvectors (columns) of a symmetric 2x2 matrix, in
    closed form (``np.linalg.eigh`` up to the eigenvectors' signs)."""
    a, b, d = float(m[0, 0]), 0.5 * (float(m[0, 1]) + float(m[1, 0])), float(m[1, 1])
    mean = 0.5 * (a + d)
    rad = math.hypot(0.5 * (a - d), b)
    vals = np.array([mean - rad, mean + rad])
    if b == 0.0:
        if a <= d:
            return vals, np.eye(2)
        return vals, np.array([[0.0, 1.0], [1.0, 0.0]])
    phi = 0.5 * math.atan2(2.0 * b, a - d)  # direction of the larger eigenvalue
    c, s = math.cos(phi), math.sin(phi)
    return vals, np.array([[-s, c], [c, s]])
