"""Matching of ordered shape configurations (paper §5.2 and §5.3).

Frames: the scan configuration ``P`` is in the robot frame, the map view ``Q`` in the map frame
(see :mod:`service.core.shapes.configuration`). A pose / rigid transform is ``[tx, ty, phi]``
(metres, radians). Every corresponding pair ``(P_ij, Q_i'j')`` *induces an alignment*: the
robot pose that would lay the scan polylines onto the map polylines (robot frame -> map frame).
The difference ``ΔA`` of that induced alignment to the estimated pose is measured by eq. 4,
with ``dt`` the displacement of the scan polylines' centroid and ``dPhi`` the rotation.

Functions, with their place in the paper:

* :func:`penalty_R` — penalty ``R`` for a polyline without counterpart (§5.2), linear in its
  angular size in the field of view.
* :func:`pose_consistency` — eq. 4, ``D(dt, dPhi) = ||dt|| + 10 |dPhi|``.
* :func:`induced_alignment` — ``A(P, Q)`` from the shape correspondence of S* (§5.1/§5.2).
* :func:`match_configurations` — eq. 5 for two configurations given an estimate.

The extended dynamic programme of §5.2 that solves eq. 5,
:func:`service.core.shapes.order_dp.order_preserving_dp`, is :mod:`service.core.shapes.order_dp`; S*
as the shape cost of eq. 5 (single pairs, gated, batched) is :mod:`service.core.shapes.shape_cost`.
The two-step matching of §5.3 built on these is :mod:`service.core.shapes.two_step`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from service.core import kernels, numeric
from service.core.kernels import matching as matching_kernels
from service.core.kernels import shape as shape_kernels
from service.core.pose import StackedPairs, transform_points
from service.core.sensor.pose_batch import fit_pairs_ranges
from service.core.shapes.configuration import Configuration, Feature
from service.core.shapes.order_dp import BlockArrays, order_preserving_dp
from service.core.shapes.shape_cost import (
    ShapeCost,
    batched_shape_cost,
    gated_shape_cost,
    shape_arcs,
)
from service.core.shapes.similarity import ShapeArcs, shape_alignment
from service.core.shapes.stacked import scan_intervals, scan_samples, stacked_points, view_segments
from service.core.types import Match, wrap_angle

if TYPE_CHECKING:
    from service.core.tracking.localizer import ShapeConfig

_TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------------------------
# Cost terms of eq. 5
# --------------------------------------------------------------------------------------------


def angular_interval(points: np.ndarray, viewpoint: np.ndarray) -> tuple[float, float]:
    """``(start, span)`` (rad) of the bearings of ``points`` seen from ``viewpoint`` (pose),
    relative to its heading; ``start`` in (-pi, pi], span >= 0, following the point order."""
    d = points - viewpoint[:2]
    b = numeric.atan2(d[:, 1], d[:, 0]) - viewpoint[2]
    steps = np.mod(np.diff(b) + math.pi, _TWO_PI) - math.pi
    cum = np.concatenate(([0.0], np.cumsum(steps)))
    lo, hi = float(cum.min()), float(cum.max())
    return float(wrap_angle(b[0] + lo)), hi - lo


def _overlap(start: float, span: float, lo: float, hi: float) -> float:
    """Length (rad) of the intersection of the circular interval ``[start, start + span]``
    with ``[lo, hi]`` (``hi - lo <= 2 pi``)."""
    if hi - lo >= _TWO_PI - 1e-9:
        return min(span, _TWO_PI)
    total = 0.0
    for shift in (-_TWO_PI, 0.0, _TWO_PI):
        a = start + shift
        total += max(0.0, min(a + span, hi) - max(a, lo))
    return total


def penalty_R(  # noqa: N802 (the paper names it R)
    points: np.ndarray,
    weight: float = 1.0,
    viewpoint: np.ndarray | None = None,
    fov: tuple[float, float] | None = None,
) -> float:
    """Penalty ``R`` for a polyline left without counterpart (paper §5.2, eq. 5's last term).

    ``R = weight * (angular size of the polyline inside the field of view)``: linear in the
    angle (radians) the polyline subtends seen from ``viewpoint`` (pose ``[x, y, theta]``,
    default the origin of the polyline's frame), clipped to ``fov = (lo, hi)`` radians relative
    to the viewpoint heading (default: no clipping). ``points`` ``(k, 2)`` metres, in angular
    order; ``weight`` in cost units (metres-like, as S* and eq. 4) per radian.
    """
    vp = np.zeros(3) if viewpoint is None else np.asarray(viewpoint, dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    start, span = angular_interval(pts, vp)
    if fov is not None:
        span = _overlap(start, span, fov[0], fov[1])
    return weight * span


def pose_consistency(
    dt: np.ndarray | Sequence[float], dphi: float, rot_weight: float = 10.0
) -> float:
    """Eq. 4: ``D(dt, dPhi) = ||dt|| + 10 |dPhi|`` (``rot_weight`` = 10 in the paper).

    ``dt`` ``(2,)`` metres (displacement of the aligned shapes), ``dphi`` radians (wrapped to
    (-pi, pi] before taking the absolute value). Result in metres.
    """
    d = np.asarray(dt, dtype=np.float64)
    return float(math.hypot(d[0], d[1]) + rot_weight * abs(wrap_angle(float(dphi))))


def induced_alignment(p: np.ndarray | ShapeArcs, q: np.ndarray | ShapeArcs) -> np.ndarray:
    """``A(P, Q)`` (§5.2): the rigid transform ``[tx, ty, phi]`` that lays polyline ``p`` onto
    its corresponding polyline ``q`` (``x_q ~ R(phi) x_p + t``), from the optimal arc
    correspondence of S* (:func:`service.core.shapes.similarity.shape_alignment`).

    With ``p`` a scan polyline in the robot frame and ``q`` a map polyline in the map frame the
    result is the robot pose this pair alone implies. Either may be given already prepared
    (:class:`~service.core.shapes.similarity.ShapeArcs`; the same result, without preparing it
    again).
    """
    ang, t = shape_alignment(p, q)
    return np.array([float(t[0]), float(t[1]), float(wrap_angle(ang))])


def alignment_difference(
    induced: np.ndarray, estimate: np.ndarray, at: np.ndarray
) -> tuple[np.ndarray, float]:
    """``ΔA``: how far the induced pose moves the shape at robot-frame point ``at`` (m)
    compared with the estimated pose, and the rotation difference (rad)."""
    a = transform_points(induced, np.asarray(at, dtype=np.float64).reshape(1, 2))[0]
    b = transform_points(estimate, np.asarray(at, dtype=np.float64).reshape(1, 2))[0]
    return a - b, float(wrap_angle(induced[2] - estimate[2]))


# --------------------------------------------------------------------------------------------
# Configuration matching (eq. 5)
# --------------------------------------------------------------------------------------------


@dataclass
class ConfigurationMatch:
    """Result of :func:`match_with_cost`: ``matches`` (indices into the configurations'
    feature lists), the eq. 5 ``cost``, and per match the pose its pair induced."""

    matches: list[Match]
    cost: float
    induced: list[np.ndarray] = field(default_factory=list)


def _concat(feats: Sequence[Feature], attr: str) -> np.ndarray:
    return np.vstack([getattr(f, attr) for f in feats])


def map_order(
    Q: Configuration, estimate: np.ndarray
) -> tuple[list[int], list[tuple[float, float]]]:
    """Cut the cyclic map view into a linear order for the DP (§5.2's cyclic order).

    Features are ordered by the bearing of their middle seen from ``estimate`` (relative to
    its heading) in (-pi, pi], i.e. the cycle is cut right behind the robot, where a forward
    facing scan has no polylines. Returns the order and each feature's ``(start, span)``
    angular interval (rad) seen from the estimate.
    """
    order, arr = _map_order_arrays(Q, estimate)
    return order.tolist(), [(float(s), float(w)) for s, w in arr]


def _map_order_arrays(Q: Configuration, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`map_order` as arrays: the order ``(m,)`` and the intervals ``(m, 2)`` (indexed
    by feature, not by order)."""
    if not Q.features:
        return np.zeros(0, dtype=np.intp), np.zeros((0, 2))
    if kernels.HAVE_NUMBA:
        pts, off = stacked_points(Q)
        arr = matching_kernels.angular_intervals(pts, off, np.asarray(estimate, dtype=np.float64))
    else:
        arr = np.array([angular_interval(f.points, estimate) for f in Q.features])
    mids = wrap_angle(arr[:, 0] + 0.5 * arr[:, 1])
    return np.argsort(np.atleast_1d(mids), kind="stable"), arr


def _overlaps(start: np.ndarray, span: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """:func:`_overlap` for arrays of intervals (same arithmetic, elementwise)."""
    if hi - lo >= _TWO_PI - 1e-9:
        return np.minimum(span, _TWO_PI)
    total = np.zeros(len(start))
    for shift in (-_TWO_PI, 0.0, _TWO_PI):
        a = start + shift
        total = total + np.maximum(0.0, np.minimum(a + span, hi) - np.maximum(a, lo))
    return total


def _single_overlaps(piv: np.ndarray, qiv: np.ndarray, tol: float) -> np.ndarray:
    """``(n, m)`` bool: scan interval i and map interval j (``(start, span)`` rows, rad)
    overlap within ``tol`` radians (map intervals tested at 0 and +-2 pi)."""
    ps = piv[:, 0:1] - tol
    pe = piv[:, 0:1] + piv[:, 1:2] + tol
    out = np.zeros((len(piv), len(qiv)), dtype=bool)
    for shift in (-_TWO_PI, 0.0, _TWO_PI):
        qs = qiv[None, :, 0] + shift
        qe = qs + qiv[None, :, 1]
        out |= (ps < qe) & (qs < pe)
    return out


def match_with_cost(
    P: Configuration,
    Q: Configuration,
    estimate: np.ndarray,
    config: ShapeConfig,
    shape_cost: ShapeCost | None = None,
    cache: dict | None = None,
    bearing_gate: float | None = None,
) -> ConfigurationMatch:
    """Eq. 5 for the scan configuration ``P`` (robot frame) and map view ``Q`` (map frame) given
    the estimated pose ``estimate`` ``[x, y, theta]``; see :func:`match_configurations`.
    ``bearing_gate`` (rad) overrides ``config.bearing_gate``; ``cache`` memoises S* within one
    scan."""
    est = np.asarray(estimate, dtype=np.float64)
    cache = {} if cache is None else cache
    sd = shape_cost or gated_shape_cost(config, config.max_shape_distance)
    n = len(P)
    q_ord, q_iv = _map_order_arrays(Q, est)
    q_order = q_ord.tolist()
    m = len(q_order)
    Qiv = q_iv[q_ord].reshape(-1, 2)
    fov = P.fov
    # Penalties R (angular size inside the scan's field of view, seen from the estimate).
    w_r = config.penalty_weight
    skip_p = [w_r * f.angular_size for f in P.features]
    gate = config.bearing_gate if bearing_gate is None else bearing_gate
    if n and m and kernels.HAVE_NUMBA:
        single, inside = shape_kernels.interval_gates(scan_intervals(P), Qiv, gate, *fov)
    else:
        inside = _overlaps(Qiv[:, 0], Qiv[:, 1], fov[0], fov[1])
    skip_q = (w_r * config.map_penalty_factor) * inside
    if n == 0 or m == 0:
        cost, _ = order_preserving_dp(skip_p, skip_q, {})
        return ConfigurationMatch(matches=[], cost=cost)
    if not kernels.HAVE_NUMBA:
        single = _single_overlaps(scan_intervals(P), Qiv, gate)
    # Candidate blocks P[i_s..i_e] ~ Q[j_s..j_e] (runs of up to max_join polylines) whose
    # first and last singles overlap, in the order (i_s, j_s) row-major, then a, then b.
    K = config.max_join
    if kernels.HAVE_NUMBA:
        ca = matching_kernels.block_candidates(single, K, config.join_total)
    else:
        combos = [(a, b) for a in range(K) for b in range(K - a if config.join_total else K)]
        ii, jj = np.nonzero(single)
        ok = np.zeros((len(ii), len(combos)), dtype=bool)
        for c, (a, b) in enumerate(combos):
            ie, je = ii + a, jj + b
            v = (ie < n) & (je < m)
            ok[v, c] = single[ie[v], je[v]]
        r_idx, c_idx = np.nonzero(ok)
        comb = np.array(combos, dtype=np.intp).reshape(-1, 2)
        ca = np.column_stack(
            [ii[r_idx], ii[r_idx] + comb[c_idx, 0], jj[r_idx], jj[r_idx] + comb[c_idx, 1]]
        ).astype(np.intp)
    cand = ca
    if len(cand) == 0:
        cost, _ = order_preserving_dp(skip_p, skip_q, {})
        return ConfigurationMatch(matches=[], cost=cost)
    # Induced alignment of every candidate block (vectorised point-to-line fit from the
    # estimate) and its ΔA (eq. 4) at the block's centroid; the ΔA gate comes first because it
    # is cheap for all blocks at once, S* only for the survivors. Blocks are runs of
    # consecutive features, so their points / segments are contiguous rows of the stacked
    # per-feature arrays.
    p_all, p_off = scan_samples(P, max(3, config.align_points // 2))
    q_all, q_off = view_segments(Q, q_ord)
    p_beg, p_end = p_off[ca[:, 0]], p_off[ca[:, 1] + 1]
    s_start, s_len = q_off[ca[:, 2]], q_off[ca[:, 3] + 1] - q_off[ca[:, 2]]
    smax = int(s_len.max()) if len(s_len) else 0
    if smax == 0 or len(q_all) == 0:
        cost, _ = order_preserving_dp(skip_p, skip_q, {})
        return ConfigurationMatch(matches=[], cost=cost)
    poses, _rms = fit_pairs_ranges(
        p_all,
        p_beg,
        p_end,
        q_all,
        s_start,
        s_len,
        est,
        iterations=config.align_iterations,
        robust_scale=config.align_robust_scale,
        damping=config.align_damping,
    )
    if kernels.HAVE_NUMBA:
        cen = matching_kernels.range_means(p_all, p_beg.astype(np.intp), p_end.astype(np.intp))
    else:
        p_len = p_end - p_beg
        own = np.repeat(np.arange(len(cand)), p_len)
        rows = np.arange(int(p_len.sum())) - np.repeat(np.cumsum(p_len) - p_len, p_len)
        pts_all = p_all[np.repeat(p_beg, p_len) + rows]
        cnt = np.bincount(own, minlength=len(cand)).astype(float)
        cen = np.column_stack(
            [
                np.bincount(own, weights=pts_all[:, 0], minlength=len(cand)) / cnt,
                np.bincount(own, weights=pts_all[:, 1], minlength=len(cand)) / cnt,
            ]
        )
    c_h, s_h = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    c_e, s_e = np.cos(est[2]), np.sin(est[2])
    dx = (c_h * cen[:, 0] - s_h * cen[:, 1] + poses[:, 0]) - (
        c_e * cen[:, 0] - s_e * cen[:, 1] + est[0]
    )
    dy = (s_h * cen[:, 0] + c_h * cen[:, 1] + poses[:, 1]) - (
        s_e * cen[:, 0] + c_e * cen[:, 1] + est[1]
    )
    dphi = np.abs(np.mod(poses[:, 2] - est[2] + math.pi, _TWO_PI) - math.pi)
    dA = np.hypot(dx, dy) + config.rotation_weight * dphi
    # S* of every surviving block pair, cached per scan block and map features (a map block
    # is identified by its features' indices in Q, independent of the cut of the order).
    surv = np.nonzero(dA <= config.max_consistency)[0]
    cs = ca[surv]
    # the features of every block (-1 padded): scan features i_s.., view features (by index
    # in Q) in the cut order j_s..; and its key
    M = len(Q.features) + 1
    if kernels.HAVE_NUMBA:
        p_pieces, q_pieces, key_arr = shape_kernels.block_pieces(cs, q_ord, K, M)
    else:
        steps = np.arange(K)
        p_pieces = np.where(steps <= cs[:, 1:2] - cs[:, 0:1], cs[:, 0:1] + steps, -1)
        q_pieces = np.where(
            steps <= cs[:, 3:4] - cs[:, 2:3], q_ord[np.minimum(cs[:, 2:3] + steps, m - 1)], -1
        )
        qkey = (q_pieces.astype(np.int64) + 1) @ (M ** steps.astype(np.int64))
        key_arr = (cs[:, 0] * K + (cs[:, 1] - cs[:, 0])) * (M**K) + qkey
    keys = key_arr.tolist()
    sstore = cache.setdefault(("S2", id(P), id(Q)), {})
    get = sstore.get
    svals = [get(kk) for kk in keys]
    if None in svals and shape_cost is None and kernels.HAVE_NUMBA:
        # every missing pair in one compiled call (the same S* as the loop below computes)
        miss = [r for r, v in enumerate(svals) if v is None]
        got = batched_shape_cost(
            P, Q, p_pieces[miss], q_pieces[miss], config, config.max_shape_distance
        )
        for r, v in zip(miss, got, strict=True):
            sstore[keys[r]] = v
            svals[r] = v
    if None in svals:
        pid = id(P)
        Qf = [Q.features[j] for j in q_order]
        qid = [id(f) for f in Qf]
        for r, kk in enumerate(keys):
            if svals[r] is not None:
                continue
            sdist = sstore.get(kk)
            if sdist is None:
                i_s, i_e, j_s, j_e = cs[r].tolist()
                if i_s == i_e:
                    pa = shape_arcs(P.features[i_s], P.features[i_s].vertices, cache)
                else:
                    pa = shape_arcs(
                        ("P", pid, i_s, i_e),
                        lambda: _concat(P.features[i_s : i_e + 1], "vertices"),  # noqa: B023
                        cache,
                    )
                if j_s == j_e:
                    qa = shape_arcs(Qf[j_s], Qf[j_s].vertices, cache)
                else:
                    qf = Qf[j_s : j_e + 1]
                    qa = shape_arcs(
                        ("Q", *qid[j_s : j_e + 1]),
                        lambda: _concat(qf, "vertices"),  # noqa: B023
                        cache,
                    )
                sdist = float(sd(pa, qa))
                sstore[kk] = sdist
            svals[r] = sdist
    s_arr = np.asarray(svals, dtype=np.float64)
    keep = s_arr <= config.max_shape_distance
    rows = surv[keep]
    cb = cs[keep]
    s_kept = s_arr[keep]
    d_kept = dA[rows]
    blocks = BlockArrays(
        cb[:, 0], cb[:, 1], cb[:, 2], cb[:, 3], s_kept + config.consistency_weight * d_kept
    )
    total, path = order_preserving_dp(skip_p, skip_q, blocks)
    matches = []
    induced = []
    # the row of each block on the path (rows coded as one integer; the last of equal rows)
    code = ((cb[:, 0] * n + cb[:, 1]) * m + cb[:, 2]) * m + cb[:, 3]
    row_of = dict(zip(code.tolist(), range(len(cb)), strict=True))
    for key in path:
        i_s, i_e, j_s, j_e = key
        r = row_of[((i_s * n + i_e) * m + j_s) * m + j_e]
        matches.append(
            Match(
                scan=tuple(range(i_s, i_e + 1)),
                map=tuple(q_order[j] for j in range(j_s, j_e + 1)),
                shape_distance=float(s_kept[r]),
                pose_consistency=float(d_kept[r]),
            )
        )
        induced.append(poses[rows[r]])
    return ConfigurationMatch(matches=matches, cost=total, induced=induced)


def match_configurations(
    P: Configuration,
    Q: Configuration,
    estimate: np.ndarray,
    config: ShapeConfig,
    shape_cost: ShapeCost | None = None,
) -> list[Match]:
    """Optimal correspondence of eq. 5 between scan configuration ``P`` and map view ``Q``.

    Minimises ``sum over pairs (S(P_ij, Q_i'j') + w * ΔA(P_ij, Q_i'j')) + sum of R over
    unmatched polylines`` by :func:`order_preserving_dp`, where

    * ``P_ij`` / ``Q_i'j'`` are concatenations of up to ``config.max_join`` consecutive
      polylines (1:1, 1:n, n:1, n:m);
    * only pairs whose angular intervals (seen from ``estimate``) overlap within
      ``config.bearing_gate`` radians are considered, and only similar shapes may correspond
      (``S* <= config.max_shape_distance``);
    * ``ΔA`` is eq. 4 (:func:`pose_consistency`) between the pose the pair induces and the
      estimate, gated by ``config.max_consistency``; ``w = config.consistency_weight``;
    * the cyclic map view is cut behind the robot (:func:`map_order`); order is a hard
      constraint.

    ``estimate`` ``[x, y, theta]`` map frame. ``shape_cost`` replaces S* (for tests). Returns
    the matches with indices into ``P.features`` and ``Q.features``.
    """
    return match_with_cost(P, Q, estimate, config, shape_cost).matches


# --------------------------------------------------------------------------------------------
# Two-step matching (§5.3)
# --------------------------------------------------------------------------------------------


def matched_pairs(
    P: Configuration, Q: Configuration, matches: Sequence[Match]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """For :func:`service.core.pose.pose_from_matches`: per match, the scan points (robot
    frame) of its scan polylines and the map segments (map frame) of its map polylines."""
    out = []
    for m in matches:
        pts = np.vstack([P.features[i].points for i in m.scan])
        segs = [Q.features[j].segments for j in m.map]
        segs = [x for x in segs if x is not None]
        if segs:
            out.append((pts, np.vstack(segs)))
    return out


def matched_stack(P: Configuration, Q: Configuration, matches: Sequence[Match]) -> StackedPairs:
    """:func:`matched_pairs` stacked (one copy of all points and of all segments) and without
    the pairs :func:`service.core.pose.pose_from_matches` skips (no points or no segments)."""
    pts: list[np.ndarray] = []
    segs: list[np.ndarray] = []
    counts: list[int] = []
    seg_len: list[int] = []
    for m in matches:
        fs = [P.features[i].points for i in m.scan]
        ss = [x for x in (Q.features[j].segments for j in m.map) if x is not None]
        n_p = sum(len(x) for x in fs)
        n_s = sum(len(x) for x in ss)
        if n_p and n_s:
            pts += fs
            segs += ss
            counts.append(n_p)
            seg_len.append(n_s)
    lens = np.array(seg_len, dtype=np.intp)
    return StackedPairs(
        points=np.vstack(pts) if pts else np.zeros((0, 2)),
        counts=np.array(counts, dtype=np.intp),
        segments=np.vstack(segs) if segs else np.zeros((0, 4)),
        seg_start=(np.cumsum(lens) - lens).astype(np.intp),
        seg_len=lens,
    )
