"""The extended dynamic programme of the paper's §5.2: eq. 5 solved over two linearly ordered
vectors of polylines, with 1:n, n:1 and n:m blocks (the "update step") and order as a hard
constraint.

:func:`order_preserving_dp` takes the penalties ``R`` of leaving each polyline unmatched and
the admissible blocks with their costs (a :data:`Blocks` dict, or :class:`BlockArrays` as
:func:`service.core.shapes.matching.match_with_cost` builds them). With numba the recurrence runs in
one compiled call (:func:`service.core.kernels.shape.order_dp_blocks`, over
:func:`service.core.kernels.matching.order_dp`), else in :func:`_order_preserving_dp_python`,
the reference (same recurrence and tie order).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from service.core import kernels
from service.core.kernels import shape as shape_kernels

#: Candidate correspondences for the DP: ``{(i_end, j_end): [(i_start, j_start, cost), ...]}``
#: meaning ``P[i_start..i_end] ~ Q[j_start..j_end]`` (inclusive, concatenated) at ``cost``.
Blocks = dict[tuple[int, int], list[tuple[int, int, float]]]


@dataclass(frozen=True)
class BlockArrays:
    """:data:`Blocks` as flat arrays (what :func:`service.core.shapes.matching.match_with_cost`
    builds): block ``t`` is ``P[i_s[t]..i_e[t]] ~ Q[j_s[t]..j_e[t]]`` at ``cost[t]``; blocks
    ending at the same cell are tried in array order (as the lists of a :data:`Blocks` dict)."""

    i_s: np.ndarray
    i_e: np.ndarray
    j_s: np.ndarray
    j_e: np.ndarray
    cost: np.ndarray


def _blocks_to_arrays(blocks: Blocks) -> BlockArrays:
    rows = [(ie, je, i_s, j_s, c) for (ie, je), lst in blocks.items() for i_s, j_s, c in lst]
    if not rows:
        z = np.zeros(0, dtype=np.intp)
        return BlockArrays(z, z, z, z, np.zeros(0))
    ie, je, i_s, j_s, c = zip(*rows, strict=True)
    a = [np.asarray(x, dtype=np.intp) for x in (i_s, ie, j_s, je)]
    return BlockArrays(*a, np.asarray(c, dtype=np.float64))


def order_preserving_dp(
    skip_p: Sequence[float], skip_q: Sequence[float], blocks: Blocks | BlockArrays
) -> tuple[float, list[tuple[int, int, int, int]]]:
    """Solve eq. 5 over two linearly ordered vectors of polylines (§5.2's extended DP).

    ``skip_p[i]`` / ``skip_q[j]`` are the penalties ``R`` of leaving ``p_i`` / ``q_j``
    unmatched; ``blocks`` the admissible correspondences with their cost ``S + ΔA``. Cell
    ``C[i][j]`` is the optimal cost of the prefixes ``p_1..p_i`` and ``q_1..q_j``:

        C[i][j] = min( C[i-1][j] + R(p_i),  C[i][j-1] + R(q_j),
                       min over blocks ending at (i, j):  C[i_s - 1][j_s - 1] + cost )

    A block ``P[i_s..i] ~ Q[j_s..j]`` with more than one polyline on a side is the paper's
    *update step*: when ``q_j`` is considered, the correspondence of the previous polyline
    ``q_{j-1}`` with ``p_i`` is reconsidered and may be replaced by ``p_i ~ (q_{j-1}, q_j)``
    concatenated (1:n, n:1 and n:m), so a split object is still matched. Order is a hard
    constraint by construction. Returns ``(total cost, [(i_s, i_e, j_s, j_e), ...])`` in order.

    ``blocks`` may also be a :class:`BlockArrays`. With numba the blocks are grouped by end
    cell and the recurrence runs in one compiled call
    (:func:`service.core.kernels.shape.order_dp_blocks`), else in
    :func:`_order_preserving_dp_python` (the reference; same recurrence and tie order).
    """
    if not kernels.HAVE_NUMBA:
        if isinstance(blocks, BlockArrays):
            d: Blocks = {}
            for i_s, i_e, j_s, j_e, c in zip(
                blocks.i_s.tolist(),
                blocks.i_e.tolist(),
                blocks.j_s.tolist(),
                blocks.j_e.tolist(),
                blocks.cost.tolist(),
                strict=True,
            ):
                d.setdefault((i_e, j_e), []).append((i_s, j_s, c))
            blocks = d
        return _order_preserving_dp_python(skip_p, skip_q, blocks)
    ba = blocks if isinstance(blocks, BlockArrays) else _blocks_to_arrays(blocks)
    total, path = shape_kernels.order_dp_blocks(
        np.asarray(skip_p, dtype=np.float64).reshape(-1),
        np.asarray(skip_q, dtype=np.float64).reshape(-1),
        *(np.ascontiguousarray(x, dtype=np.intp) for x in (ba.i_s, ba.i_e, ba.j_s, ba.j_e)),
        np.ascontiguousarray(ba.cost, dtype=np.float64),
    )
    return float(total), [tuple(r) for r in path.tolist()]  # type: ignore[misc]


def _order_preserving_dp_python(
    skip_p: Sequence[float], skip_q: Sequence[float], blocks: Blocks
) -> tuple[float, list[tuple[int, int, int, int]]]:
    """Pure-Python reference of :func:`order_preserving_dp` for a :data:`Blocks` dict."""
    n, m = len(skip_p), len(skip_q)
    C = np.empty((n + 1, m + 1))
    back: list[list[tuple[int, int, int, int] | None]] = [[None] * (m + 1) for _ in range(n + 1)]
    C[0, 0] = 0.0
    for i in range(1, n + 1):
        C[i, 0] = C[i - 1, 0] + skip_p[i - 1]
        back[i][0] = (i - 1, 0, -1, -1)
    for j in range(1, m + 1):
        C[0, j] = C[0, j - 1] + skip_q[j - 1]
        back[0][j] = (0, j - 1, -1, -1)
    for i in range(1, n + 1):
        sp = skip_p[i - 1]
        for j in range(1, m + 1):
            best = C[i - 1, j] + sp
            arg = (i - 1, j, -1, -1)
            c = C[i, j - 1] + skip_q[j - 1]
            if c < best:
                best, arg = c, (i, j - 1, -1, -1)
            for i_s, j_s, cost in blocks.get((i - 1, j - 1), ()):
                c = C[i_s, j_s] + cost
                if c < best:
                    best, arg = c, (i_s, j_s, 1, 1)
            C[i, j] = best
            back[i][j] = arg
    out: list[tuple[int, int, int, int]] = []
    i, j = n, m
    while i > 0 or j > 0:
        pi, pj, flag, _ = back[i][j]  # type: ignore[misc]
        if flag == 1:
            out.append((pi, i - 1, pj, j - 1))
        i, j = pi, pj
    out.reverse()
    return float(C[n, m]), out
