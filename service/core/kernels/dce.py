"""Compiled fixed-threshold Discrete Curve Evolution (implementation details, numba; the
conventions of :mod:`service.core.kernels`).

:func:`dce_kept` is the kernel of :func:`service.core.shapes.dce.dce`, with the removal order of its
reference :class:`service.core.shapes.dce.CurveEvolution`; the interior vertices wait in a binary
heap (:func:`_sift_up`, :func:`_sift_down`, ordered by :func:`_rel_less`).
:func:`service.core.kernels.extract.simplify_groups` runs it on every group of a reading.
"""

from __future__ import annotations

import math

import numpy as np

from service.core.kernels import njit


@njit(cache=True, nogil=True)
def _rel_less(rel: np.ndarray, a: int, b: int) -> bool:
    """DCE's removal order: lower relevance first, ties by lower vertex index."""
    return rel[a] < rel[b] or (rel[a] == rel[b] and a < b)


@njit(cache=True, nogil=True)
def _sift_up(heap: np.ndarray, pos: np.ndarray, rel: np.ndarray, c: int) -> None:
    v = heap[c]
    while c > 0:
        par = (c - 1) // 2
        pv = heap[par]
        if not _rel_less(rel, v, pv):
            break
        heap[c] = pv
        pos[pv] = c
        c = par
    heap[c] = v
    pos[v] = c


@njit(cache=True, nogil=True)
def _sift_down(heap: np.ndarray, pos: np.ndarray, rel: np.ndarray, c: int, n: int) -> None:
    v = heap[c]
    while True:
        m = 2 * c + 1
        if m >= n:
            break
        if m + 1 < n and _rel_less(rel, heap[m + 1], heap[m]):
            m += 1
        mv = heap[m]
        if not _rel_less(rel, mv, v):
            break
        heap[c] = mv
        pos[mv] = c
        c = m
    heap[c] = v
    pos[v] = c


@njit(cache=True, nogil=True)
def dce_kept(p: np.ndarray, threshold: float) -> np.ndarray:
    """Kernel of :func:`service.core.shapes.dce.dce`: fixed-threshold DCE (eq. 2) of ``p``
    ``(k, 2)`` with the same removal order as :class:`service.core.shapes.dce.CurveEvolution` (least
    relevance first, ties by lower index). Returns the kept vertex indices, sorted.

    The interior vertices sit in a binary heap indexed by vertex (a neighbour's new
    relevance moves it in place); ``el[v]`` keeps the length of the edge from ``v`` to its
    next kept vertex, computed once as ``hypot(x[next] - x[v], y[next] - y[v])``, the same
    expression each relevance uses."""
    k = p.shape[0]
    x = p[:, 0]
    y = p[:, 1]
    prev = np.arange(-1, k - 1)
    nxt = np.arange(1, k + 1)
    rel = np.full(k, np.inf)
    el = np.empty(k)
    for i in range(k - 1):
        el[i] = math.hypot(x[i + 1] - x[i], y[i + 1] - y[i])
    heap = np.empty(k, dtype=np.intp)
    pos = np.full(k, -1, dtype=np.intp)
    n = 0
    for i in range(1, k - 1):
        rel[i] = el[i - 1] + el[i] - math.hypot(x[i + 1] - x[i - 1], y[i + 1] - y[i - 1])
        heap[n] = i
        n += 1
        _sift_up(heap, pos, rel, n - 1)
    last = k - 1
    removed = 0
    while n > 0:
        i = heap[0]
        if rel[i] >= threshold:
            break
        n -= 1
        if n > 0:
            heap[0] = heap[n]
            _sift_down(heap, pos, rel, 0, n)
        removed += 1
        u = prev[i]
        w = nxt[i]
        nxt[u] = w
        prev[w] = u
        xu = x[u]
        yu = y[u]
        xw = x[w]
        yw = y[w]
        duw = math.hypot(xw - xu, yw - yu)
        el[u] = duw
        if u > 0:
            old = rel[u]
            uu = prev[u]
            rel[u] = el[uu] + duw - math.hypot(xw - x[uu], yw - y[uu])
            if rel[u] < old:
                _sift_up(heap, pos, rel, pos[u])
            else:
                _sift_down(heap, pos, rel, pos[u], n)
        if w < last:
            old = rel[w]
            ww = nxt[w]
            rel[w] = duw + el[w] - math.hypot(x[ww] - xu, y[ww] - yu)
            if rel[w] < old:
                _sift_up(heap, pos, rel, pos[w])
            else:
                _sift_down(heap, pos, rel, pos[w], n)
    out = np.empty(k - removed, dtype=np.intp)
    j = 0
    i = 0
    while True:
        out[j] = i
        j += 1
        if i == last:
            break
        i = nxt[i]
    return out


def warm_up() -> None:
    """Compile (or load) this module's kernel on a tiny input."""
    p = np.array([[0.0, 0.0], [1.0, 0.1], [2.0, 0.0], [2.0, 1.0]])
    dce_kept(p, 0.04)
