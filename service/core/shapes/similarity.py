"""Shape similarity of polylines: S* (paper §5.1), partial optimal similarity (§4.1/§5.1) and
shape complexity (§5.3).

Shapes here are metric: polylines are ``(k, 2)`` arrays of vertices in metres (any Cartesian
frame; scan polylines in the robot frame, map polylines in the viewpoint frame). Every measure
is invariant to translation and rotation of either polyline, not to scale or reflection.

S* in short. A (DCE-simplified) polyline is a chain of *arcs* (its edges), each with a metric
length and a direction. Two chains are compared in tangent space: a dynamic programme finds
the optimal correspondence of *maximal arcs*, where a run of up to ``max_merge`` consecutive
arcs of one polyline may correspond to a single arc of the other (1:1, 1:n, n:1); a merged run
is represented by its chord. The cost accumulated along the correspondence is, in metres:

* turn misfit: at every interior matched vertex, the difference of the turn angles (relative
  angular directions of consecutive matched arcs) of the two polylines, in radians, weighted by
  the shortest of the four adjacent matched arc lengths (metres);
* length misfit: ``|l_p - l_q|`` of every matched arc pair; for the first and the last pair
  only ``end_weight`` times that, because range scans truncate objects at occlusion
  boundaries, so an end arc may be shorter in one shape at little cost;
* merge cost: a merged run costs the length it loses, ``sum(arc lengths) - chord`` (the
  relevance of eq. 2 generalised to a run), so merging away noise vertices is cheap and merging
  away a corner is not;
* skipped ends: whole arcs at the start or end of one polyline left without counterpart (an
  occluded corner) cost ``skip_weight`` times their length.

The DP runs over matched vertex pairs ``(i, j)``; since the turn term needs the incoming
chords, each state keeps the incoming chords of its cheapest path only, so the length, merge
and skip terms are optimised exactly and the turn term greedily along the best path (a cost
within the same correspondence space, never below the true optimum of that space).

Scale: S* is 0 for identical shapes and is measured in metres. Measured for noisy
observations of the same object (361 beams over 180 deg, 1 cm range noise, first-stage DCE,
20-30 seeds; tests/service/core/shapes/test_similarity.py) it does NOT grow with the object's metric
size but with its number of corners, each costing about the error with which DCE localises it:
a straight wall 0.001-0.005, a right-angle corner 0.02, a wall with a 45-degree-chamfered
protrusion (6 vertices) 0.22 (max 0.6), the same whether the object is scaled 1x, 2x or 4x.
With :func:`service.core.shapes.dce.refine_vertices` those drop to 0.006 and 0.045 (max 0.08).
Different shapes cost on the order of their size: an L with 1 m legs vs a 2 m line 0.6, a
right-angle corner vs a quarter circle (r = 1 m) 0.63, a 2.8 m corner vs a straight wall of
the same extent >= 0.83. Occlusion: cutting 30 % off an end within the end arc costs 0.1 x
the cut length; hiding a whole end corner costs 0.5 per metre skipped. The matcher can add S*
directly to eq. 4's ``||dt|| + 10 dPhi`` (both metres-like) with a weight of order 1; pass its
acceptance gate as ``upper_bound`` to prune the search.

The DP's compiled kernels are in :mod:`service.core.kernels.similarity`, its pure-Python
reference in :mod:`service.core.shapes.similarity_reference`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service.core import kernels
from service.core.kernels import shape as shape_kernels
from service.core.kernels import similarity as similarity_kernels
from service.core.shapes.dce import DCE_NOISE_THRESHOLD, CurveEvolution, dce
from service.core.shapes.similarity_reference import dp_python
from service.errors import LocalizationError

#: Default weight of the length misfit of the first / last matched arc pair (occlusion cuts).
END_WEIGHT = 0.1
#: Default cost per metre of whole end arcs left without counterpart.
SKIP_WEIGHT = 0.5
#: Default maximal number of consecutive arcs merged into one chord.
MAX_MERGE = 4

_TWO_PI = 2.0 * math.pi


class ShapeArcs:
    """A polyline prepared for S*: vertices, cumulative arc length and chord tables.

    Build once per polyline (``prepare``) and reuse across many :func:`shape_distance` calls.
    ``points`` ``(k, 2)`` metres, k >= 2, finite. Zero-length edges are dropped.
    """

    __slots__ = (
        "_chord_dir",
        "_chord_len",
        "_merge_cost",
        "cum",
        "cum_a",
        "k",
        "max_merge",
        "tab",
        "x",
        "y",
    )

    def __init__(self, points: np.ndarray, max_merge: int = MAX_MERGE) -> None:
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 2:
            raise LocalizationError(f"expected (k >= 2, 2) points, got {p.shape}")
        if max_merge < 1:
            raise LocalizationError(f"max_merge must be >= 1, got {max_merge}")
        self.max_merge = max_merge
        #: numpy tables for the compiled S* kernel (``None`` without numba): ``cum_a`` (k,)
        #: and ``tab`` (3, max_merge + 1, k) = chord length / direction / merge cost.
        self.cum_a: np.ndarray | None = None
        self.tab: np.ndarray | None = None
        if kernels.HAVE_NUMBA:
            status, xa, ya, cum_a, tab = similarity_kernels.arc_tables(
                np.ascontiguousarray(p), max_merge
            )
            if status == 1:
                raise LocalizationError("polyline has non-finite coordinates")
            if status == 2:
                raise LocalizationError("polyline has zero length")
            self.x, self.y, self.cum = xa.tolist(), ya.tolist(), cum_a.tolist()
            self.k = len(self.x)
            self.cum_a, self.tab = cum_a, tab
            self._chord_len = self._chord_dir = self._merge_cost = None
            return
        # Plain Python from here: polylines have a handful of vertices, where numpy's per-call
        # overhead dominates.
        xs: list[float] = p[:, 0].tolist()
        ys: list[float] = p[:, 1].tolist()
        hypot = math.hypot
        x, y, cum = [xs[0]], [ys[0]], [0.0]
        for xi, yi in zip(xs, ys, strict=True):
            if not (math.isfinite(xi) and math.isfinite(yi)):
                raise LocalizationError("polyline has non-finite coordinates")
            d = hypot(xi - x[-1], yi - y[-1])
            if d > 1e-12:  # drop repeated vertices
                x.append(xi)
                y.append(yi)
                cum.append(cum[-1] + d)
        k = len(x)
        if k < 2:
            raise LocalizationError("polyline has zero length")
        self.x, self.y, self.k, self.cum = x, y, k, cum
        # chord tables indexed [a][i]: chord from vertex i over a arcs (a = 1..max_merge).
        chord_len: list[list[float]] = [[]]
        chord_dir: list[list[float]] = [[]]
        merge_cost: list[list[float]] = [[]]
        for a in range(1, max_merge + 1):
            ln, dr, mc = [], [], []
            for i in range(k - a):
                dx, dy = x[i + a] - x[i], y[i + a] - y[i]
                c = math.hypot(dx, dy)
                ln.append(c)
                dr.append(math.atan2(dy, dx))
                mc.append(max(cum[i + a] - cum[i] - c, 0.0))
            chord_len.append(ln)
            chord_dir.append(dr)
            merge_cost.append(mc)
        self._chord_len, self._chord_dir, self._merge_cost = chord_len, chord_dir, merge_cost

    def _lists(self) -> None:
        tab = self.tab
        assert tab is not None
        k = self.k
        rows = [
            [[]] + [tab[t, a, : k - a].tolist() for a in range(1, self.max_merge + 1)]
            for t in range(3)
        ]
        self._chord_len, self._chord_dir, self._merge_cost = rows

    @property
    def chord_len(self) -> list[list[float]]:
        """``[a][i]``: length (m) of the chord from vertex ``i`` over ``a`` arcs."""
        if self._chord_len is None:
            self._lists()
        return self._chord_len  # type: ignore[return-value]

    @property
    def chord_dir(self) -> list[list[float]]:
        """``[a][i]``: direction (rad) of the chord from vertex ``i`` over ``a`` arcs."""
        if self._chord_dir is None:
            self._lists()
        return self._chord_dir  # type: ignore[return-value]

    @property
    def merge_cost(self) -> list[list[float]]:
        """``[a][i]``: length lost (m) by merging ``a`` arcs from vertex ``i`` into a chord."""
        if self._merge_cost is None:
            self._lists()
        return self._merge_cost  # type: ignore[return-value]

    @property
    def length(self) -> float:
        """Total length in metres."""
        return self.cum[-1]

    def vertex(self, i: int) -> tuple[float, float]:
        """Vertex ``i`` as ``(x, y)`` metres."""
        return self.x[i], self.y[i]


def prepare(points: np.ndarray | ShapeArcs, max_merge: int = MAX_MERGE) -> ShapeArcs:
    """Return ``points`` as :class:`ShapeArcs` (no-op if it already is one with enough merges)."""
    if isinstance(points, ShapeArcs) and points.max_merge >= max_merge:
        return points
    if isinstance(points, ShapeArcs):
        points = np.column_stack((points.x, points.y))
    return ShapeArcs(points, max_merge)


@dataclass(frozen=True)
class ShapeMatch:
    """Result of :func:`shape_match`.

    ``distance`` S* (metres); ``pairs`` the arc correspondence as tuples
    ``(p_start, p_end, q_start, q_end)`` of vertex indices into the prepared polylines (a run
    ``p_start..p_end`` of p's vertices corresponds to ``q_start..q_end`` of q's);
    ``angle`` (radians) and ``t`` ``(2,)`` (metres) the rigid transform
    ``x_q = R(angle) @ x_p + t`` that the correspondence induces (least squares over points
    sampled by arc length along corresponding arcs).
    """

    distance: float
    pairs: tuple[tuple[int, int, int, int], ...]
    angle: float
    t: np.ndarray


def _dp(
    P: ShapeArcs,
    Q: ShapeArcs,
    max_merge: int,
    end_weight: float,
    skip_weight: float,
    want_path: bool,
    upper_bound: float = math.inf,
) -> tuple[float, list[tuple[int, int, int, int]]]:
    """Core DP of S*. States are matched vertex pairs (i, j); see the module docstring.

    Branches whose cost plus an admissible lower bound of the rest (every metre of length
    imbalance between the remaining parts costs at least ``min(end_weight, skip_weight, 1)``)
    reaches the best complete cost so far, or ``upper_bound``, are pruned; the result is exact
    whenever it is below ``upper_bound`` (else ``inf``).

    Runs the compiled kernel :func:`service.core.kernels.similarity.shape_dp` when both
    polylines carry numpy tables (numba available), else
    :func:`service.core.shapes.similarity_reference.dp_python` (the reference).
    """
    if P.tab is None or Q.tab is None:
        return dp_python(P, Q, max_merge, end_weight, skip_weight, want_path, upper_bound)
    best, s, s2, back = similarity_kernels.shape_dp(
        P.cum_a,
        P.tab,
        Q.cum_a,
        Q.tab,
        min(max_merge, P.max_merge),
        min(max_merge, Q.max_merge),
        float(end_weight),
        float(skip_weight),
        float(upper_bound),
    )
    if s < 0:
        return math.inf, []
    path: list[tuple[int, int, int, int]] = []
    if want_path:
        kq = Q.k
        while s >= 0:
            path.append((s // kq, s2 // kq, s % kq, s2 % kq))
            s2 = s
            s = int(back[s])
        path.reverse()
    return float(best), path


def shape_distance(
    p: np.ndarray | ShapeArcs,
    q: np.ndarray | ShapeArcs,
    *,
    max_merge: int = MAX_MERGE,
    end_weight: float = END_WEIGHT,
    skip_weight: float = SKIP_WEIGHT,
    upper_bound: float = math.inf,
) -> float:
    """Shape distance S* (paper §5.1) between two polylines, in metres (0 = identical shape).

    ``p``, ``q``: ``(k, 2)`` vertices in metres (typically DCE-simplified, 2-15 vertices) or
    :class:`ShapeArcs` prepared with :func:`prepare` (faster when reused). Tangent-space
    comparison with an optimal correspondence of maximal arcs by dynamic programming; see the
    module docstring for the cost terms and their scale. Invariant to translation and rotation,
    tolerant of ends cut by occlusion. Cost O(k_p * k_q * max_merge), less with pruning.

    ``upper_bound`` (metres): the caller does not care about distances at or above it (e.g.
    the matcher's acceptance limit); the search prunes against it and returns ``inf`` when S*
    is not below it. Below the bound the value is exactly the unbounded S*.
    """
    P = prepare(p, max_merge)
    Q = prepare(q, max_merge)
    d, _ = _dp(P, Q, max_merge, end_weight, skip_weight, False, upper_bound)
    return d


def shape_distances(
    p_verts: np.ndarray,
    p_off: np.ndarray,
    p_pieces: np.ndarray,
    q_verts: np.ndarray,
    q_off: np.ndarray,
    q_pieces: np.ndarray,
    *,
    max_merge: int = MAX_MERGE,
    end_weight: float = END_WEIGHT,
    skip_weight: float = SKIP_WEIGHT,
    upper_bound: float = math.inf,
) -> np.ndarray:
    """:func:`shape_distance` of many pairs of polylines that are joined pieces, in one call.

    Piece ``f`` of a side is the vertex rows ``verts[off[f] : off[f + 1]]`` (``(N, 2)``
    metres); row ``r`` of ``pieces`` ``(R, k)`` lists the pieces joined (in that order, as
    ``np.vstack``; ``-1`` = none) into pair ``r``'s polyline. Returns the ``(R,)`` distances,
    each exactly :func:`shape_distance` of the joined polylines (``inf`` at or above
    ``upper_bound``). One compiled call (:func:`service.core.kernels.shape.shape_distances`)
    with numba, else a loop over :func:`shape_distance` (the reference).
    """
    pp = np.asarray(p_pieces, dtype=np.intp)
    qp = np.asarray(q_pieces, dtype=np.intp)
    if pp.ndim != 2 or qp.ndim != 2 or len(pp) != len(qp):
        raise LocalizationError(f"pieces: expected (R, k) and (R, l), got {pp.shape}, {qp.shape}")
    if max_merge < 1:
        raise LocalizationError(f"max_merge must be >= 1, got {max_merge}")
    if not kernels.HAVE_NUMBA:
        pv, qv = np.asarray(p_verts, dtype=np.float64), np.asarray(q_verts, dtype=np.float64)

        def joined(v: np.ndarray, off: np.ndarray, row: np.ndarray) -> np.ndarray:
            return np.vstack([v[off[f] : off[f + 1]] for f in row if f >= 0] or [v[:0]])

        kw = {"end_weight": end_weight, "skip_weight": skip_weight, "upper_bound": upper_bound}
        out = [
            shape_distance(joined(pv, p_off, a), joined(qv, q_off, b), max_merge=max_merge, **kw)
            for a, b in zip(pp, qp, strict=True)
        ]
        return np.array(out, dtype=np.float64).reshape(-1)
    status, _, out = shape_kernels.shape_distances(
        np.ascontiguousarray(p_verts, dtype=np.float64),
        np.ascontiguousarray(p_off, dtype=np.intp),
        np.ascontiguousarray(pp),
        np.ascontiguousarray(q_verts, dtype=np.float64),
        np.ascontiguousarray(q_off, dtype=np.intp),
        np.ascontiguousarray(qp),
        int(max_merge),
        float(end_weight),
        float(skip_weight),
        float(upper_bound),
    )
    if status != 0:
        raise LocalizationError(
            {1: "polyline has non-finite coordinates", 2: "polyline has zero length"}.get(
                status, "expected (k >= 2, 2) points"
            )
        )
    return out


def _alignment(
    P: ShapeArcs, Q: ShapeArcs, pairs: list[tuple[int, int, int, int]]
) -> tuple[float, np.ndarray]:
    """Weighted least-squares rigid transform p -> q from points sampled on matched arcs."""
    sp: list[tuple[float, float, float]] = []  # (x, y, w) in p
    sq: list[tuple[float, float]] = []
    last = len(pairs) - 1
    for n, (i0, i1, j0, j1) in enumerate(pairs):
        ax, ay, bx, by = P.x[i0], P.y[i0], P.x[i1], P.y[i1]
        cx, cy, dx, dy = Q.x[j0], Q.y[j0], Q.x[j1], Q.y[j1]
        lp = math.hypot(bx - ax, by - ay)
        lq = math.hypot(dx - cx, dy - cy)
        m = min(lp, lq)
        if m <= 1e-12:
            continue
        upx, upy = (bx - ax) / lp, (by - ay) / lp
        uqx, uqy = (dx - cx) / lq, (dy - cy) / lq
        first, final = n == 0, n == last
        if first and final:  # both ends may be cut: anchor the middles
            op = ((ax + bx) / 2 - upx * m / 2, (ay + by) / 2 - upy * m / 2)
            oq = ((cx + dx) / 2 - uqx * m / 2, (cy + dy) / 2 - uqy * m / 2)
            samples = [(op, oq, s) for s in (0.0, 0.5 * m, m)]
        elif first:  # start may be cut: anchor at the (real) end vertex
            samples = [((bx, by), (dx, dy), -s) for s in (0.0, 0.5 * m, m)]
        elif final:  # end may be cut: anchor at the (real) start vertex
            samples = [((ax, ay), (cx, cy), s) for s in (0.0, 0.5 * m, m)]
        else:  # interior: same fractions of both chords
            w = m / 3.0
            for f in (0.0, 0.5, 1.0):
                sp.append((ax + f * (bx - ax), ay + f * (by - ay), w))
                sq.append((cx + f * (dx - cx), cy + f * (dy - cy)))
            continue
        w = m / 3.0
        for o_p, o_q, s in samples:
            sp.append((o_p[0] + upx * s, o_p[1] + upy * s, w))
            sq.append((o_q[0] + uqx * s, o_q[1] + uqy * s))
    if not sp:
        return 0.0, np.zeros(2)
    # the weighted sums in one pass, each accumulated in sample order (the bits of summing
    # each one separately)
    W = wpx = wpy = wqx = wqy = 0.0
    for (px, py, w), (qx, qy) in zip(sp, sq, strict=True):
        W += w
        wpx += px * w
        wpy += py * w
        wqx += qx * w
        wqy += qy * w
    mpx, mpy, mqx, mqy = wpx / W, wpy / W, wqx / W, wqy / W
    sxx = sxy = 0.0
    for (px, py, w), (qx, qy) in zip(sp, sq, strict=True):
        px -= mpx
        py -= mpy
        qx -= mqx
        qy -= mqy
        sxx += w * (px * qx + py * qy)
        sxy += w * (px * qy - py * qx)
    ang = math.atan2(sxy, sxx)
    c, s_ = math.cos(ang), math.sin(ang)
    t = np.array([mqx - (c * mpx - s_ * mpy), mqy - (s_ * mpx + c * mpy)])
    return ang, t


def shape_match(
    p: np.ndarray | ShapeArcs,
    q: np.ndarray | ShapeArcs,
    *,
    max_merge: int = MAX_MERGE,
    end_weight: float = END_WEIGHT,
    skip_weight: float = SKIP_WEIGHT,
) -> ShapeMatch:
    """S* together with its arc correspondence and the alignment it induces (§5.1, §5.2).

    Same DP as :func:`shape_distance`; see :class:`ShapeMatch` for the fields.
    """
    P = prepare(p, max_merge)
    Q = prepare(q, max_merge)
    d, pairs = _dp(P, Q, max_merge, end_weight, skip_weight, True)
    ang, t = _alignment(P, Q, pairs)
    return ShapeMatch(distance=d, pairs=tuple(pairs), angle=ang, t=t)


def shape_alignment(
    p: np.ndarray | ShapeArcs, q: np.ndarray | ShapeArcs, **kwargs: float
) -> tuple[float, np.ndarray]:
    """Rigid transform ``(angle [rad], t (2,) [m])`` with ``x_q ~ R(angle) x_p + t``.

    Estimated by least squares from points sampled by arc length along the arcs that S*
    puts in correspondence (end arcs are anchored at their uncut vertex, a lone arc pair at its
    middle). For a single straight arc the shift along it is unobservable and set by the middles.
    """
    m = shape_match(p, q, **kwargs)  # type: ignore[arg-type]
    return m.angle, m.t


def partial_optimal_similarity(
    p_points: np.ndarray,
    q_points: np.ndarray | ShapeArcs,
    stop_threshold: float = DCE_NOISE_THRESHOLD,
    *,
    simplify_q: bool = True,
    patience: int = 2,
    max_merge: int = MAX_MERGE,
    end_weight: float = END_WEIGHT,
    skip_weight: float = SKIP_WEIGHT,
) -> tuple[float, np.ndarray]:
    """Partial optimal similarity (paper §4.1 and §5.1): DCE of p continued under S*.

    ``p_points`` (a perceived polyline, metres) is first evolved by plain DCE up to
    ``stop_threshold`` (metres, the fixed first stage). Then DCE continues one vertex at a
    time (least relevance first) for as long as the simplified p' gets strictly more similar to
    ``q_points`` (the map polyline, the reference; DCE'd at ``stop_threshold`` first when
    ``simplify_q``; a prepared :class:`ShapeArcs` is used as is); it stops when a removal
    does not reduce S*(p', q). With ``patience = 1`` that is the first such removal (the
    paper's rule); the default 2 looks one removal further before stopping, which gets over
    plateaus where one noise vertex alone does not change S* (measured on noisy 6-vertex
    objects with a 1 cm first stage: mean S* 0.65 with patience 1, 0.22 with 2, no further
    gain with 3-5). Returns the best simplification seen.

    Returns ``(S*(p', q), kept)`` where ``kept`` are the indices into ``p_points`` of p's
    vertices (sorted, including both ends).
    """
    ce = CurveEvolution(p_points)
    ce.evolve_to(stop_threshold)
    if isinstance(q_points, ShapeArcs):
        Q = prepare(q_points, max_merge)
    else:
        q = np.asarray(q_points, dtype=np.float64)
        if simplify_q and q.ndim == 2 and q.shape[0] > 2:
            q = q[dce(q, stop_threshold)]
        Q = prepare(q, max_merge)
    p_all = np.asarray(p_points, dtype=np.float64)
    kept = ce.kept_indices()
    d, _ = _dp(prepare(p_all[kept], max_merge), Q, max_merge, end_weight, skip_weight, False)
    misses = 0
    while ce.step():
        cand = ce.kept_indices()
        d2, _ = _dp(prepare(p_all[cand], max_merge), Q, max_merge, end_weight, skip_weight, False)
        if d2 < d:
            d, kept = d2, cand
            misses = 0
        else:
            misses += 1
            if misses >= patience:
                break
    return d, kept


def shape_complexity(points: np.ndarray, simplify: float | None = None) -> float:
    """Shape complexity (paper §5.3), metres x radians.

    Sum over interior vertices of ``|turn angle| * min(adjacent edge lengths)``: a long
    featureless straight wall scores ~0, a right-angle corner with 1 m legs ~1.57, and
    zig-zags or curved objects (many turns with substantial arms) score high. Small wiggles
    score little because the shorter arm weights them. ``points`` ``(k, 2)`` metres; apply
    DCE first (``simplify`` = threshold in metres, or do it yourself) so sensor noise does
    not count as shape.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or p.shape[0] < 2:
        raise LocalizationError(f"expected (k >= 2, 2) points, got {p.shape}")
    if simplify is not None and p.shape[0] > 2:
        p = p[dce(p, simplify)]
    if p.shape[0] < 3:
        return 0.0
    # Plain Python: a handful of vertices, where numpy's per-call overhead dominates.
    return complexity_of(p[:, 0].tolist(), p[:, 1].tolist())


def complexity_of(xs: list[float], ys: list[float]) -> float:
    """:func:`shape_complexity` of the polyline ``(xs[i], ys[i])`` (metres, >= 2 vertices,
    already simplified)."""
    if len(xs) < 3:
        return 0.0
    total = 0.0
    pl = math.hypot(xs[1] - xs[0], ys[1] - ys[0])
    pd = math.atan2(ys[1] - ys[0], xs[1] - xs[0])
    for i in range(1, len(xs) - 1):
        dx, dy = xs[i + 1] - xs[i], ys[i + 1] - ys[i]
        ln = math.hypot(dx, dy)
        d = math.atan2(dy, dx)
        turn = abs((d - pd + math.pi) % _TWO_PI - math.pi)
        total += turn * (ln if ln < pl else pl)
        pl, pd = ln, d
    return total
