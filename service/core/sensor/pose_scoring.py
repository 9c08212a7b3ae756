"""Scoring one pose against the map, shared by global search, the hypotheses kept over a
drive and the drive's evidence: the point support and the polish on the distance field
(:func:`_support_many`, :func:`_polish`) and the beam-by-beam verification (:func:`verify`,
:class:`Hypothesis`). The search that produces the poses is
:mod:`service.core.reloc.global_search`."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from service.core import kernels, numeric
from service.core.kernels import search as search_kernels
from service.core.pose import transform_points
from service.core.reloc.global_config import GlobalConfig
from service.core.reloc.view_index import ViewIndex
from service.core.shapes.configuration import Configuration
from service.core.tracking.localizer import ShapeConfig
from service.core.types import wrap_angle


@dataclass
class Hypothesis:
    """A pose hypothesis ``[x, y, theta]`` (map frame) with its verification on one scan:
    ``hit`` fraction of beams returned where the map predicts (within the support tolerance),
    ``violation`` fraction of beams that passed through a map wall, ``cost`` (lower is
    better), ``explained`` length fraction of the scan's polylines lying on the map there."""

    pose: np.ndarray
    cost: float
    hit: float = 0.0
    violation: float = 0.0
    explained: float = 0.0
    short: float = 0.0


@lru_cache(maxsize=4096)
def _subsample_rows(n: int, k: int) -> np.ndarray:
    """``k`` evenly spread row indices of ``n`` rows (kept: the same few sizes recur)."""
    rows = np.linspace(0, n - 1, k).round().astype(int)
    rows.setflags(write=False)
    return rows


def _subsample(points: np.ndarray, k: int) -> np.ndarray:
    if len(points) <= k:
        return points
    return points[_subsample_rows(len(points), k)]


def _support_many(index: ViewIndex, poses: np.ndarray, pts: np.ndarray, tol: float) -> np.ndarray:
    """Fraction of robot-frame ``pts`` within ``tol`` of the map at each of ``poses`` (k, 3)."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    if kernels.HAVE_NUMBA and len(pts) and len(poses):
        n = search_kernels.support_counts(
            index.dist,
            float(index.origin[0]),
            float(index.origin[1]),
            float(index.resolution),
            np.ascontiguousarray(c),
            np.ascontiguousarray(s),
            np.ascontiguousarray(poses, dtype=np.float64),
            np.ascontiguousarray(pts, dtype=np.float64),
            float(tol),
        )
        return n / len(pts)
    x = c[:, None] * pts[None, :, 0] - s[:, None] * pts[None, :, 1] + poses[:, 0:1]
    y = s[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1] + poses[:, 1:2]
    d = index.distance(np.column_stack([x.ravel(), y.ravel()])).reshape(len(poses), -1)
    return np.mean(d <= tol, axis=1)


#: Steps of a beam's march on the distance field (:func:`_field_violations`) before it is
#: given up as crossing nothing (a beam along a wall advances by a few centimetres per step).
_MARCH_STEPS = 200


def _field_violations(
    index: ViewIndex,
    poses: np.ndarray,
    ranges: np.ndarray,
    angles: np.ndarray,
    margin: float,
) -> np.ndarray:
    """Fraction of beams (robot-frame ``angles``, measured ``ranges``, all finite) that pass
    through a drawn wall at each of ``poses`` ``(m, 3)``: the beam reaches a cell next to a
    wall (field value at most one cell) more than ``margin`` before its return. Each beam
    marches from the sensor by the field's clearance under it less 1.5 cells (the field is
    quantised to cells: such a step never enters a wall cell), at least half a cell, for at
    most :data:`_MARCH_STEPS` steps; leaving the field ends it. The distance-field
    counterpart of :func:`verify`'s violation (a ray cast of the same beams costs ~20x more
    in the search's work model), cheap enough for every coarse pose cell of
    a search. A numba kernel when available, else this numpy reference (the same steps)."""
    poses = np.asarray(poses, dtype=np.float64)
    k = len(ranges)
    if len(poses) == 0 or k == 0:
        return np.zeros(len(poses))
    th = poses[:, 2:3] + np.asarray(angles, dtype=np.float64)[None, :]
    cb, sb = np.cos(th), np.sin(th)
    lim = np.asarray(ranges, dtype=np.float64) - margin
    ox, oy, res = float(index.origin[0]), float(index.origin[1]), float(index.resolution)
    px, py = np.ascontiguousarray(poses[:, 0]), np.ascontiguousarray(poses[:, 1])
    if kernels.HAVE_NUMBA:
        n = search_kernels.field_crossings(
            index.dist, ox, oy, res, px, py, cb, sb, lim, _MARCH_STEPS
        )
        return n / k
    h, w = index.dist.shape
    t = np.zeros(cb.shape)
    live = np.ones(cb.shape, dtype=bool)
    crossed = np.zeros(cb.shape, dtype=bool)
    for _ in range(_MARCH_STEPS):
        live &= t < lim[None, :]
        if not live.any():
            break
        ci = np.floor((px[:, None] + t * cb - ox) / res)
        cj = np.floor((py[:, None] + t * sb - oy) / res)
        live &= (ci >= 0) & (ci < w) & (cj >= 0) & (cj < h)
        d = np.zeros(cb.shape)
        d[live] = index.dist[cj[live].astype(np.int64), ci[live].astype(np.int64)]
        hit = live & (d <= res)
        crossed |= hit
        live &= ~hit
        t = np.where(live, t + np.maximum(d - 1.5 * res, 0.5 * res), t)
    return np.count_nonzero(crossed, axis=1) / k


#: Distance-field values are capped at this (m) in the polish's score.
_FIELD_CAP = 10.0


def _field_scores(index: ViewIndex, poses: np.ndarray, pts: np.ndarray, sigma: float) -> np.ndarray:
    """Mean of ``exp(-d² / 2 sigma²)`` over robot-frame ``pts`` at each of ``poses`` ``(m, 3)``,
    ``d`` the distance-field value (capped at 10 m). A numba kernel when available, else the
    numpy reference (same arithmetic)."""
    if len(pts) == 0 or len(poses) == 0:
        return np.zeros(len(poses))
    if kernels.HAVE_NUMBA:
        table, outside = index.score_table(float(sigma), _FIELD_CAP)
        return search_kernels.table_scores(
            table,
            outside,
            float(index.origin[0]),
            float(index.origin[1]),
            float(index.resolution),
            np.ascontiguousarray(poses, dtype=np.float64),
            np.ascontiguousarray(pts, dtype=np.float64),
        )
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    x = c[:, None] * pts[None, :, 0] - s[:, None] * pts[None, :, 1] + poses[:, 0:1]
    y = s[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1] + poses[:, 1:2]
    d = index.distance(np.column_stack([x.ravel(), y.ravel()])).reshape(len(poses), -1)
    return np.mean(numeric.exp(-0.5 * (np.minimum(d, _FIELD_CAP) / sigma) ** 2), axis=1)


@lru_cache(maxsize=64)
def _axes(step_xy: float, step_th: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The offsets along x, y and heading of one :func:`_polish` stage (5 each)."""
    o = np.arange(-2, 3)
    axes = (o * step_xy, o * step_xy, o * step_th)
    for a in axes:
        a.setflags(write=False)
    return axes


@lru_cache(maxsize=64)
def _grid(step_xy: float, step_th: float) -> np.ndarray:
    """The 5 x 5 x 5 offsets ``(125, 3)`` of one :func:`_polish` stage (kept: few recur),
    heading fastest (``meshgrid(*_axes(...), indexing="ij")``)."""
    dx, dy, dth = np.meshgrid(*_axes(step_xy, step_th), indexing="ij")
    grid = np.column_stack([dx.ravel(), dy.ravel(), dth.ravel()])
    grid.setflags(write=False)
    return grid


#: Scales (m, rad) of the polish's motion prior (:func:`_polish`).
_PRIOR_XY, _PRIOR_TH = 0.1, 0.04


def _polish(
    index: ViewIndex,
    poses: np.ndarray,
    pts: np.ndarray,
    sigma: float,
    stages: tuple[tuple[float, float], ...] = ((0.05, 0.02), (0.015, 0.006)),
    prior: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Local search around each pose ``(k, 3)`` on the distance field: per stage a 5 x 5 x 5
    grid of ``(step_xy m, step_theta rad)`` (default +-0.1 m / +-0.04 rad, then +-0.03 m /
    +-0.012 rad) maximising the mean of ``exp(-d² / 2 s²)`` over the robot-frame ``pts``,
    ``s = max(sigma, step_xy)``. Unlike the least-squares fit it cannot be dragged by points
    that have no counterpart in the map. ``prior`` > 0 makes the given poses a motion prior:
    the objective is the score less ``prior`` x ((offset / 0.1 m)² + (turn / 0.04 rad)²) from
    them. Returns the poses and their final scores ``(k,)`` (without the prior's term)."""
    out = np.asarray(poses, dtype=np.float64).copy()
    start = out.copy()
    best_score = np.zeros(len(out))
    for step_xy, step_th in stages:
        s_eff = max(sigma, step_xy)
        delta = _grid(float(step_xy), float(step_th))
        cand = out[:, None, :] + delta[None, :, :]  # (k, 125, 3)
        if kernels.HAVE_NUMBA and len(pts) and len(out):
            # the grid's scores with each point's field row and column computed once per
            # heading and offset (the same bits as _field_scores on cand)
            table, outside = index.score_table(float(s_eff), _FIELD_CAP)
            score = search_kernels.grid_scores(
                table,
                outside,
                float(index.origin[0]),
                float(index.origin[1]),
                float(index.resolution),
                np.ascontiguousarray(out),
                *_axes(float(step_xy), float(step_th)),
                np.ascontiguousarray(pts, dtype=np.float64),
            )
        else:
            score = _field_scores(index, cand.reshape(-1, 3), pts, s_eff).reshape(len(out), -1)
        obj = score
        if prior > 0.0:
            off = cand - start[:, None, :]
            obj = score - prior * (
                (off[..., 0] ** 2 + off[..., 1] ** 2) / _PRIOR_XY**2
                + (off[..., 2] / _PRIOR_TH) ** 2
            )
        best = np.argmax(obj, axis=1)
        rows = np.arange(len(out))
        best_score = score[rows, best]
        out = cand[rows, best]
    out[:, 2] = wrap_angle(out[:, 2])
    return out, best_score


def _beam_fractions(
    r: np.ndarray,
    pred: np.ndarray,
    tol: float,
    gconfig: GlobalConfig,
    landed: np.ndarray | None = None,
    short_scale: float = 0.0,
) -> tuple[float, float, float]:
    """Fractions of beams (measured ``r``, map-predicted ``pred``, NaN = nothing within range)
    that hit (within ``tol``), violate (return beyond the predicted wall by more than
    ``max(tol, gconfig.violation_margin)``) and fall short (something unmapped in front).
    With ``landed`` (``gconfig.see_through``: the beams whose return lies on a mapped surface
    the beam crosses) a beam that passed the predicted wall and ended on mapped structure
    behind it is no violation: the map holds an object the laser now sees past (a chair or
    cabinet that moved, a door open), not a wall the pose puts in the way.

    With ``short_scale`` > 0 (``GlobalConfig.evidence_short_scale``) a short return counts
    ``exp(-(pred - r) / short_scale)`` of one: furniture stands just in front of the walls
    of the room it is in, while a pose that puts the walls far behind the returns is
    explained by nothing; 0 counts every short return as one."""
    # fractions as counts / n: the values np.mean gives, without its per-call overhead (these
    # run for every beam check of a search)
    n = max(r.size, 1)
    hit = np.count_nonzero(np.abs(r - pred) <= tol) / n  # NaN prediction compares False
    through = np.isfinite(pred) & (r > pred + max(tol, gconfig.violation_margin))
    if landed is not None:
        through &= ~landed
    viol = np.count_nonzero(through) / n
    below = r < pred - tol
    if short_scale > 0.0:
        gap = np.where(below, pred - r, np.inf)
        return hit, viol, float(numeric.exp(-gap / short_scale).sum() / n)
    return hit, viol, np.count_nonzero(below) / n


def _predict(
    index: ViewIndex,
    pose: np.ndarray,
    r: np.ndarray,
    ang: np.ndarray,
    tol: float,
    max_range: float,
    gconfig: GlobalConfig,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The map's predicted ranges from ``pose`` over beams ``ang`` and, with
    ``gconfig.see_through``, which measured returns ``r`` lie on a mapped surface behind the
    predicted one (:meth:`RayCaster.cast_layered`; ``None`` without)."""
    if gconfig.see_through:
        return index.caster.cast_layered(pose, ang, r, tol, max_range)
    return index.caster.cast(pose, ang, max_range), None


def _beam_cost(hit: float, viol: float, short: float, gconfig: GlobalConfig) -> float:
    """The beam part of :func:`verify`'s cost from its beam fractions:
    ``1 - hit - short_credit * short + violation_weight * violation``."""
    return 1.0 - hit - gconfig.short_credit * short + gconfig.violation_weight * viol


def _beam_costs(
    index: ViewIndex,
    poses: np.ndarray,
    ranges: np.ndarray,
    angles: np.ndarray,
    beams: int,
    config: ShapeConfig,
    gconfig: GlobalConfig,
) -> np.ndarray:
    """The beam part of :func:`verify`'s cost for each of ``poses`` ``(k, 3)`` on ``beams``
    evenly chosen valid beams: ``1 - hit - short_credit * short + violation_weight *
    violation``. A quick ranking: unlike the point support it sees beams that pass through a
    wall, and it does not reward a wrong place for lining up furniture with map walls."""
    ok = np.nonzero(np.isfinite(ranges))[0]
    sel = _subsample(ok, beams)
    out = np.full(len(poses), np.inf)
    if sel.size == 0:
        return out
    r = ranges[sel]
    ang = angles[sel]
    tol = config.support_tolerance
    poses = np.asarray(poses, dtype=np.float64)
    # without see-through all poses in one cast (each pose's ranges have the bits of its own)
    batch = (
        None if gconfig.see_through else index.caster.cast_many(poses, ang, config.view_max_range)
    )
    for k, pose in enumerate(poses):
        if batch is None:
            pred, landed = _predict(index, pose, r, ang, tol, config.view_max_range, gconfig)
        else:
            pred, landed = batch[k], None
        out[k] = _beam_cost(*_beam_fractions(r, pred, tol, gconfig, landed), gconfig)
    return out


def verify(
    index: ViewIndex,
    pose: np.ndarray,
    ranges: np.ndarray,
    angles: np.ndarray,
    P: Configuration,
    config: ShapeConfig,
    gconfig: GlobalConfig,
) -> Hypothesis:
    """Check a pose against the map beam by beam and feature by feature.

    ``gconfig.verify_beams`` valid beams of the scan are compared with the ranges the map
    predicts from ``pose``: a *hit* lies within ``config.support_tolerance`` of the predicted
    range, a *violation* is a return beyond the predicted range plus the tolerance (the beam
    went through a map wall), a *short* one ends before the predicted wall (something
    unmapped in front of it). ``explained`` is the length fraction of the scan's polylines with
    at least half their points within the tolerance of the map. Cost
    ``1 - hit + violation_weight * violation + cost_floor``.
    """
    tol = config.support_tolerance
    ok = np.isfinite(ranges)
    idx = np.nonzero(ok)[0]
    idx = _subsample(idx, gconfig.verify_beams)
    if idx.size == 0:
        return Hypothesis(pose=pose.copy(), cost=1.0 + gconfig.cost_floor)
    r = ranges[idx]
    pred, landed = _predict(index, pose, r, angles[idx], tol, config.view_max_range, gconfig)
    hit, viol, short = _beam_fractions(r, pred, tol, gconfig, landed)
    total = 0.0
    good = 0.0
    if P.features:
        # one distance lookup for every feature's points (the same values as one per feature)
        subs = [_subsample(f.points, 16) for f in P.features]
        near = index.distance(transform_points(pose, np.vstack(subs))) <= tol
        start = 0
        for f, sub in zip(P.features, subs, strict=True):
            total += f.length
            if 2 * np.count_nonzero(near[start : start + len(sub)]) >= len(sub):
                good += f.length
            start += len(sub)
    explained = good / total if total > 0 else 0.0
    cost = _beam_cost(hit, viol, short, gconfig) + gconfig.cost_floor
    return Hypothesis(
        pose=pose.copy(),
        cost=cost,
        hit=hit,
        violation=viol,
        explained=explained,
        short=short,
    )
