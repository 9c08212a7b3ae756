"""The sensor model: how well a pose explains a scan, against one map (beluga's and AMCL's seam).

One :class:`SensorModel` per map, shared by every part of the localiser that scores a pose:
the tracker (beams through drawn walls, :meth:`SensorModel.through`), the global search (point
support, the polish, beams marched on the distance field, the beam check and the
verification), the hypotheses over a drive (re-scoring and keyframe evidence) and the
relocalisation's decision (:meth:`SensorModel.score`). It asks one :class:`~service.core.
sensor.mapmodel.MapModel` (one distance field, one bucket grid, one ray caster) and nothing
else. The point-to-line solvers' own objective (the robust point likelihood the tracker's fit
maximises, :mod:`service.core.sensor.refine`) is the solvers'; everything that compares poses
after a fit asks this model.

Two families of measurements, cheap and exact:

* **points on the distance field** -- :meth:`~SensorModel.support` (share of points within a
  tolerance of a wall), :meth:`~SensorModel.field_score` (mean ``exp(-d² / 2 s²)``),
  :meth:`~SensorModel.polish` (a local grid search maximising that score),
  :meth:`~SensorModel.window` (a correlative search of that score over a whole window, and
  how distinct its peak is),
  :meth:`~SensorModel.crossings` (beams marched on the field: the share that passes through a
  drawn wall);
* **beams by ray casting** -- :meth:`~SensorModel.beams` classifies each beam of a scan from a
  pose as a *hit* (within the tolerance of the predicted wall), *through* (beyond the predicted
  wall: the beam passed through a wall the map draws), *short* (ended in front of it:
  something the map does not hold), or none of these (no wall predicted within range);
  :meth:`~SensorModel.score` turns that into the scan's log-likelihood under a categorical
  beam model, the share the map explains and the share through walls (:class:`PoseScores`).

Units: metres, radians; poses ``[x, y, theta]`` in the map frame, scans in the robot frame.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from service.core import kernels, numeric
from service.core.kernels import search as search_kernels
from service.core.pose import transform_points
from service.core.sensor.mapmodel import DistanceField, MapModel
from service.core.sensor.raycast import RayCaster
from service.core.types import MapData, wrap_angle

#: Cell size (m) of the distance field the sensor model scores on (5 cm: a laser's range
#: noise; the polish's finest step is 1.5 cm, below which the field is quantised anyway).
FIELD_RESOLUTION = 0.05
#: Distance-field values are capped at this (m) in the field score.
FIELD_CAP = 10.0
#: Steps of a beam's march on the distance field (:meth:`SensorModel.crossings`) before it is
#: given up as crossing nothing (a beam along a wall advances by a few centimetres per step).
MARCH_STEPS = 200
#: Scales (m, rad) of the polish's motion prior (:meth:`SensorModel.polish`).
PRIOR_XY, PRIOR_TH = 0.1, 0.04
#: Finest steps (m, rad) of :meth:`SensorModel.window`'s grid: the first polish stage's reach
#: (+-0.1 m, +-0.04 rad) covers two of them, so no peak falls between the grid and the polish.
WINDOW_STEP_XY, WINDOW_STEP_TH = 0.1, 0.02
#: Offsets per axis of :meth:`SensorModel.window`'s grid at most (its steps grow beyond): a
#: window of 41 x 41 positions x 11 headings scores in ~10 ms at WINDOW_POINTS points.
WINDOW_CELLS_XY, WINDOW_CELLS_TH = 41, 11
#: The window's half-widths (m, rad) at least (smaller adds nothing to a fit from its centre)
#: and at most (beyond, the grid coarsens past the polish's reach: a search's job).
WINDOW_MIN_XY, WINDOW_MIN_TH = 0.3, 0.02
WINDOW_MAX_XY, WINDOW_MAX_TH = 2.0, 0.2
#: Points the window scores (evenly chosen): the field score of 180 is as sharp as of all.
WINDOW_POINTS = 180
#: Grid cells the window polishes (a coarse grid's best may not polish best).
WINDOW_POLISH = 5
#: A place this far (m) from the window's peak is another place: a precise fit from the peak
#: reaches half a metre (its first association distance).
WINDOW_SEPARATION = 0.5


@dataclass(frozen=True)
class WindowPeak:
    """:meth:`SensorModel.window`'s result: the polished best ``pose`` and its ``score``; ``grid``
    the best grid score and ``runner_up`` the best grid score farther than the separation from
    it (0 when none is): how distinct the peak is."""

    pose: np.ndarray
    score: float
    grid: float
    runner_up: float

    @property
    def distinct(self) -> float:
        """``1 - runner_up / grid`` (0: an equal place elsewhere in the window)."""
        return 0.0 if self.grid <= 0.0 else 1.0 - self.runner_up / self.grid


@dataclass(frozen=True)
class BeamModel:
    """How beams are judged (:meth:`SensorModel.beams`). ``tolerance`` (m): a hit lies within
    it of the predicted range; ``margin`` (m): a return beyond the predicted wall by more than
    ``max(tolerance, margin)`` passed through it; ``max_range`` (m) of the prediction;
    ``see_through``: a return beyond the predicted wall on a mapped surface the beam crosses
    behind it is no violation (the map holds an object the laser now sees past);
    ``short_scale`` (m, 0 = off): a short return counts ``exp(-(pred - r) / short_scale)``
    instead of one. The cost weights: ``short_credit`` per short return,
    ``violation_weight`` per beam through a wall, ``floor`` added to every cost."""

    tolerance: float
    margin: float = 0.0
    max_range: float = 15.0
    see_through: bool = False
    short_scale: float = 0.0
    short_credit: float = 0.0
    violation_weight: float = 2.0
    floor: float = 0.05


@dataclass(frozen=True)
class BeamFractions:
    """Per pose, the shares of a scan's beams that hit, passed through a wall, ended short."""

    hit: float
    through: float
    short: float

    def beam_cost(self, m: BeamModel) -> float:
        """``1 - hit - short_credit * short + violation_weight * through``: 0 for a scan the
        map explains whole, 1 for one it explains nothing of."""
        return 1.0 - self.hit - m.short_credit * self.short + m.violation_weight * self.through

    def cost(self, m: BeamModel) -> float:
        """:meth:`beam_cost` plus the model's ``floor``."""
        return self.beam_cost(m) + m.floor


@dataclass(frozen=True)
class PoseScores:
    """:meth:`SensorModel.score` of poses ``(k,)`` on one scan: ``loglik`` the scan's
    log-likelihood up to a constant (nats), ``explained`` the share of beams the map explains
    (hits), ``through`` the share that passed through a drawn wall, ``cost`` the beam cost
    (:meth:`BeamFractions.cost`)."""

    loglik: np.ndarray
    explained: np.ndarray
    through: np.ndarray
    cost: np.ndarray


#: Independent observations one scan's beams count as in :meth:`SensorModel.score`:
#: neighbouring beams see the same wall, their errors are not independent (the tracker's
#: ``effective_points`` makes the same correction for its points).
EFFECTIVE_BEAMS = 20.0


@lru_cache(maxsize=4096)
def _subsample_rows(n: int, k: int) -> np.ndarray:
    """``k`` evenly spread row indices of ``n`` rows (kept: the same few sizes recur)."""
    rows = np.linspace(0, n - 1, k).round().astype(int)
    rows.setflags(write=False)
    return rows


def subsample(rows: np.ndarray, k: int) -> np.ndarray:
    """At most ``k`` evenly spread rows of ``rows`` (all of them if there are no more)."""
    if len(rows) <= k:
        return rows
    return rows[_subsample_rows(len(rows), k)]


@lru_cache(maxsize=64)
def polish_axes(step_xy: float, step_th: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The offsets along x, y and heading of one polish stage (5 each)."""
    o = np.arange(-2, 3)
    axes = (o * step_xy, o * step_xy, o * step_th)
    for a in axes:
        a.setflags(write=False)
    return axes


@lru_cache(maxsize=64)
def polish_offsets(step_xy: float, step_th: float) -> np.ndarray:
    """The 5 x 5 x 5 offsets ``(125, 3)`` of one polish stage, heading fastest."""
    dx, dy, dth = np.meshgrid(*polish_axes(step_xy, step_th), indexing="ij")
    grid = np.column_stack([dx.ravel(), dy.ravel(), dth.ravel()])
    grid.setflags(write=False)
    return grid


def beam_fractions(
    r: np.ndarray, pred: np.ndarray, m: BeamModel, landed: np.ndarray | None = None
) -> BeamFractions:
    """Fractions of beams (measured ``r``, map-predicted ``pred``, NaN = nothing within range)
    that hit, pass through a wall, fall short (:class:`BeamModel`); ``landed`` (see-through:
    the beams whose return lies on a mapped surface the beam crosses) are no violation."""
    # fractions as counts / n: the values np.mean gives, without its per-call overhead
    n = max(r.size, 1)
    hit = np.count_nonzero(np.abs(r - pred) <= m.tolerance) / n  # NaN compares False
    through = np.isfinite(pred) & (r > pred + max(m.tolerance, m.margin))
    if landed is not None:
        through &= ~landed
    viol = np.count_nonzero(through) / n
    below = r < pred - m.tolerance
    if m.short_scale > 0.0:
        gap = np.where(below, pred - r, np.inf)
        return BeamFractions(hit, viol, float(numeric.exp(-gap / m.short_scale).sum() / n))
    return BeamFractions(hit, viol, np.count_nonzero(below) / n)


class SensorModel:
    """Scores poses against one map for one scan (see the module docstring). ``model`` the
    map's :class:`MapModel` (shared with the tracker's fit). Pickled as its map (a process
    that loads it shares its own model of that map, :func:`sensor_model`)."""

    def __init__(self, model: MapModel, resolution: float = FIELD_RESOLUTION) -> None:
        self.model = model
        self.resolution = float(resolution)
        self._tables: dict[tuple[float, float], tuple[np.ndarray, float]] = {}

    @property
    def field(self) -> DistanceField:
        """The map's distance field (built on first use, kept by the map model)."""
        return self.model.distance_field(self.resolution)

    def __reduce__(self) -> tuple[object, tuple[MapData]]:
        return sensor_model, (self.model.map_data,)

    # ------------------------------------------------------------------ the map model
    @property
    def caster(self) -> RayCaster:
        """The map's ray caster."""
        return self.model.caster

    @property
    def segments(self) -> np.ndarray:
        """The map's segments ``(s, 4)``."""
        return self.model.segments

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (m) from map-frame points ``(n, 2)`` to the map (distance field, error at
        most one cell); ``inf`` outside the field."""
        f = self.field
        ij = np.floor((points - f.origin) / f.resolution).astype(np.int64)
        h, w = f.values.shape
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        out = np.full(len(points), np.inf)
        out[ok] = f.values[ij[ok, 1], ij[ok, 0]]
        return out

    def score_table(self, sigma: float) -> tuple[np.ndarray, float]:
        """``exp(-0.5 (min(d, cap) / sigma)²)`` per field cell and outside the field (kept
        per sigma)."""
        key = (float(sigma), FIELD_CAP)
        got = self._tables.get(key)
        if got is None:
            table = search_kernels.score_table(self.field.values, key[0], key[1])
            outside = float(search_kernels.outside_score(key[0], key[1]))
            got = (table, outside)
            self._tables[key] = got
        return got

    def _field_args(self) -> tuple[float, float, float]:
        f = self.field
        return float(f.origin[0]), float(f.origin[1]), float(f.resolution)

    # ------------------------------------------------------------------ points on the field
    def support(self, poses: np.ndarray, pts: np.ndarray, tol: float) -> np.ndarray:
        """Share of robot-frame ``pts`` within ``tol`` of the map at each of ``poses``
        ``(k, 3)``."""
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        if kernels.HAVE_NUMBA and len(pts) and len(poses):
            n = search_kernels.support_counts(
                self.field.values,
                *self._field_args(),
                np.ascontiguousarray(c),
                np.ascontiguousarray(s),
                np.ascontiguousarray(poses, dtype=np.float64),
                np.ascontiguousarray(pts, dtype=np.float64),
                float(tol),
            )
            return n / len(pts)
        x = c[:, None] * pts[None, :, 0] - s[:, None] * pts[None, :, 1] + poses[:, 0:1]
        y = s[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1] + poses[:, 1:2]
        d = self.distance(np.column_stack([x.ravel(), y.ravel()])).reshape(len(poses), -1)
        return np.mean(d <= tol, axis=1)

    def field_score(self, poses: np.ndarray, pts: np.ndarray, sigma: float) -> np.ndarray:
        """Mean of ``exp(-d² / 2 sigma²)`` over robot-frame ``pts`` at each of ``poses``
        ``(m, 3)``, ``d`` the distance-field value capped at :data:`FIELD_CAP`."""
        if len(pts) == 0 or len(poses) == 0:
            return np.zeros(len(poses))
        if kernels.HAVE_NUMBA:
            table, outside = self.score_table(float(sigma))
            return search_kernels.table_scores(
                table,
                outside,
                *self._field_args(),
                np.ascontiguousarray(poses, dtype=np.float64),
                np.ascontiguousarray(pts, dtype=np.float64),
            )
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        x = c[:, None] * pts[None, :, 0] - s[:, None] * pts[None, :, 1] + poses[:, 0:1]
        y = s[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1] + poses[:, 1:2]
        d = self.distance(np.column_stack([x.ravel(), y.ravel()])).reshape(len(poses), -1)
        return np.mean(numeric.exp(-0.5 * (np.minimum(d, FIELD_CAP) / sigma) ** 2), axis=1)

    def polish(
        self,
        poses: np.ndarray,
        pts: np.ndarray,
        sigma: float,
        stages: tuple[tuple[float, float], ...] = ((0.05, 0.02), (0.015, 0.006)),
        prior: float = 0.0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Local search around each pose ``(k, 3)``: per stage a 5 x 5 x 5 grid of ``(step_xy
        m, step_theta rad)`` maximising :meth:`field_score` of the robot-frame ``pts`` with
        ``s = max(sigma, step_xy)`` (default +-0.1 m / +-0.04 rad, then +-0.03 m / +-0.012
        rad). Unlike a least-squares fit it cannot be dragged by points the map lacks.
        ``prior`` > 0 makes the given poses a motion prior: the objective is the score less
        ``prior`` x ((offset / 0.1 m)² + (turn / 0.04 rad)²). Returns the poses and their
        scores ``(k,)`` (without the prior's term)."""
        out = np.asarray(poses, dtype=np.float64).copy()
        start = out.copy()
        best_score = np.zeros(len(out))
        for step_xy, step_th in stages:
            s_eff = max(sigma, step_xy)
            delta = polish_offsets(float(step_xy), float(step_th))
            cand = out[:, None, :] + delta[None, :, :]  # (k, 125, 3)
            if kernels.HAVE_NUMBA and len(pts) and len(out):
                # each point's field row and column computed once per heading and offset (the
                # same bits as field_score on cand)
                table, outside = self.score_table(float(s_eff))
                score = search_kernels.grid_scores(
                    table,
                    outside,
                    *self._field_args(),
                    np.ascontiguousarray(out),
                    *polish_axes(float(step_xy), float(step_th)),
                    np.ascontiguousarray(pts, dtype=np.float64),
                )
            else:
                score = self.field_score(cand.reshape(-1, 3), pts, s_eff).reshape(len(out), -1)
            obj = score
            if prior > 0.0:
                off = cand - start[:, None, :]
                obj = score - prior * (
                    (off[..., 0] ** 2 + off[..., 1] ** 2) / PRIOR_XY**2
                    + (off[..., 2] / PRIOR_TH) ** 2
                )
            best = np.argmax(obj, axis=1)
            rows = np.arange(len(out))
            best_score = score[rows, best]
            out = cand[rows, best]
        out[:, 2] = wrap_angle(out[:, 2])
        return out, best_score

    def window(
        self, center: np.ndarray, half_xy: float, half_th: float, pts: np.ndarray
    ) -> WindowPeak | None:
        """Correlative search (Olson's; Cartographer's real-time matcher) of robot-frame ``pts``
        (:data:`WINDOW_POINTS` of them) over every pose within ``+-half_xy`` m and ``+-half_th``
        rad of ``center`` (clamped to :data:`WINDOW_MIN_XY` ... :data:`WINDOW_MAX_XY`, likewise
        for the heading): the :meth:`field_score` (s = the grid's step) on a grid of
        :data:`WINDOW_STEP_XY` / :data:`WINDOW_STEP_TH`, coarser where an axis would need more
        than :data:`WINDOW_CELLS_XY` / :data:`WINDOW_CELLS_TH` offsets, the best
        :data:`WINDOW_POLISH` cells polished (s = 0.05 m). Unlike a fit from ``center`` it
        finds a place anywhere in the window, and says how well the best place at least
        :data:`WINDOW_SEPARATION` away scores (a corridor's length scores alike). ``None``
        without points."""
        pts = np.ascontiguousarray(pts, dtype=np.float64).reshape(-1, 2)
        if len(pts) == 0:
            return None
        pts = pts[subsample(np.arange(len(pts)), WINDOW_POINTS)]
        c = np.asarray(center, dtype=np.float64).reshape(3)
        half_xy = min(max(half_xy, WINDOW_MIN_XY), WINDOW_MAX_XY)
        half_th = min(max(half_th, WINDOW_MIN_TH), WINDOW_MAX_TH)
        step = max(WINDOW_STEP_XY, 2.0 * half_xy / (WINDOW_CELLS_XY - 1))
        step_th = max(WINDOW_STEP_TH, 2.0 * half_th / (WINDOW_CELLS_TH - 1))
        xs = np.arange(-int(half_xy / step + 1e-9), int(half_xy / step + 1e-9) + 1) * step
        ths = np.arange(-int(half_th / step_th + 1e-9), int(half_th / step_th + 1e-9) + 1)
        ths = ths * step_th
        dx, dy, dth = np.meshgrid(xs, xs, ths, indexing="ij")
        cand = c[None, :] + np.column_stack([dx.ravel(), dy.ravel(), dth.ravel()])
        if kernels.HAVE_NUMBA:
            table, outside = self.score_table(step)
            args = (*self._field_args(), c[None, :].copy(), xs, xs, ths, pts)
            score = search_kernels.grid_scores(table, outside, *args)[0]
        else:
            score = self.field_score(cand, pts, step)
        k = int(np.argmax(score))
        far = np.hypot(cand[:, 0] - cand[k, 0], cand[:, 1] - cand[k, 1]) > WINDOW_SEPARATION
        runner_up = float(score[far].max()) if far.any() else 0.0
        top = np.argsort(-score, kind="stable")[:WINDOW_POLISH]
        poses, polished = self.polish(cand[top], pts, 0.05)
        b = int(np.argmax(polished))
        return WindowPeak(poses[b], float(polished[b]), float(score[k]), runner_up)

    def crossings(
        self, poses: np.ndarray, ranges: np.ndarray, angles: np.ndarray, margin: float
    ) -> np.ndarray:
        """Share of beams (robot-frame ``angles``, measured ``ranges``, all finite) that pass
        through a drawn wall at each of ``poses`` ``(m, 3)``: the beam reaches a cell next to
        a wall (field value at most one cell) more than ``margin`` before its return. Each beam
        marches from the sensor by the field's clearance under it less 1.5 cells (never into a
        wall cell), at least half a cell, for at most :data:`MARCH_STEPS` steps. The distance-
        field counterpart of :meth:`beams`' violation, ~20x cheaper than a ray cast."""
        poses = np.asarray(poses, dtype=np.float64)
        k = len(ranges)
        if len(poses) == 0 or k == 0:
            return np.zeros(len(poses))
        th = poses[:, 2:3] + np.asarray(angles, dtype=np.float64)[None, :]
        cb, sb = np.cos(th), np.sin(th)
        lim = np.asarray(ranges, dtype=np.float64) - margin
        ox, oy, res = self._field_args()
        dist = self.field.values
        px, py = np.ascontiguousarray(poses[:, 0]), np.ascontiguousarray(poses[:, 1])
        if kernels.HAVE_NUMBA:
            n = search_kernels.field_crossings(dist, ox, oy, res, px, py, cb, sb, lim, MARCH_STEPS)
            return n / k
        h, w = dist.shape
        t = np.zeros(cb.shape)
        live = np.ones(cb.shape, dtype=bool)
        crossed = np.zeros(cb.shape, dtype=bool)
        for _ in range(MARCH_STEPS):
            live &= t < lim[None, :]
            if not live.any():
                break
            ci = np.floor((px[:, None] + t * cb - ox) / res)
            cj = np.floor((py[:, None] + t * sb - oy) / res)
            live &= (ci >= 0) & (ci < w) & (cj >= 0) & (cj < h)
            d = np.zeros(cb.shape)
            d[live] = dist[cj[live].astype(np.int64), ci[live].astype(np.int64)]
            hit = live & (d <= res)
            crossed |= hit
            live &= ~hit
            t = np.where(live, t + np.maximum(d - 1.5 * res, 0.5 * res), t)
        return np.count_nonzero(crossed, axis=1) / k

    # ------------------------------------------------------------------ beams by ray casting
    def predict(
        self, pose: np.ndarray, ranges: np.ndarray, angles: np.ndarray, m: BeamModel
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The map's predicted ranges from ``pose`` over beams ``angles`` and, with
        ``m.see_through``, which measured ``ranges`` lie on a mapped surface behind the
        predicted one (``None`` without)."""
        if m.see_through:
            return self.caster.cast_layered(pose, angles, ranges, m.tolerance, m.max_range)
        return self.caster.cast(pose, angles, m.max_range), None

    def beams(
        self, poses: np.ndarray, ranges: np.ndarray, angles: np.ndarray, m: BeamModel
    ) -> list[BeamFractions]:
        """:class:`BeamFractions` of each of ``poses`` ``(k, 3)`` for the beams ``ranges`` /
        ``angles`` (all finite: the caller chooses them). Without see-through all poses go
        through one cast (each pose's ranges have the bits of its own cast)."""
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        if m.see_through:
            out = []
            for p in poses:
                pred, landed = self.predict(p, ranges, angles, m)
                out.append(beam_fractions(ranges, pred, m, landed))
            return out
        pred = self.caster.cast_many(poses, angles, m.max_range)
        return [beam_fractions(ranges, pred[k], m) for k in range(len(poses))]

    def through(
        self,
        poses: np.ndarray,
        ranges: np.ndarray,
        angles: np.ndarray,
        margin: float,
        max_range: float,
    ) -> np.ndarray:
        """Share of the beams (all finite) that return from more than ``margin`` beyond the
        wall the map predicts from each of ``poses`` (through a drawn wall), one cast for
        all poses."""
        pred = self.caster.cast_many(np.asarray(poses, dtype=np.float64), angles, max_range)
        return np.array(
            [float(np.mean(np.isfinite(e) & (ranges > e + margin))) for e in pred], dtype=float
        )

    def score(
        self, poses: np.ndarray, ranges: np.ndarray, angles: np.ndarray, m: BeamModel
    ) -> PoseScores:
        """The scan's log-likelihood at each of ``poses`` ``(k, 3)`` under a categorical beam
        model (per beam: a hit costs nothing, a beam the map cannot explain one unit, a short
        one ``1 - short_credit``, one through a wall ``1 + violation_weight``; the scan's
        beams count as :data:`EFFECTIVE_BEAMS` independent ones): ``-EFFECTIVE_BEAMS x
        cost``, with the cost's floor left out; the explained and through shares beside it.
        ``ranges`` / ``angles`` the beams to judge (all finite)."""
        fr = self.beams(poses, ranges, angles, m)
        return PoseScores(
            loglik=np.array([-EFFECTIVE_BEAMS * f.beam_cost(m) for f in fr]),
            explained=np.array([f.hit for f in fr]),
            through=np.array([f.through for f in fr]),
            cost=np.array([f.cost(m) for f in fr]),
        )

    def explained_length(self, pose: np.ndarray, features: list, tol: float) -> float:
        """Length share of the scan's polylines (``features`` with ``points`` and ``length``)
        that lie on the map at ``pose``: at least half of 16 evenly chosen points of each
        within ``tol`` of a wall."""
        if not features:
            return 0.0
        subs = [subsample(f.points, 16) for f in features]
        near = self.distance(transform_points(pose, np.vstack(subs))) <= tol
        total = good = 0.0
        start = 0
        for f, sub in zip(features, subs, strict=True):
            total += f.length
            if 2 * np.count_nonzero(near[start : start + len(sub)]) >= len(sub):
                good += f.length
            start += len(sub)
        return good / total if total > 0 else 0.0


#: ``id(MapModel) -> its sensor model`` while something uses the sensor model
#: (:func:`sensor_model`). Keyed by id, not weakly by the model: the sensor model holds its map
#: model, so a weak key would never be released.
_SENSORS: weakref.WeakValueDictionary[int, SensorModel] = weakref.WeakValueDictionary()


def sensor_model(map_data: MapData) -> SensorModel:
    """The :class:`SensorModel` of ``map_data``, one per map content in this process while it
    is used (on :meth:`~service.core.sensor.mapmodel.MapModel.shared`)."""
    model = MapModel.shared(map_data)
    got = _SENSORS.get(id(model))
    if got is None or got.model is not model:
        got = SensorModel(model)
        _SENSORS[id(model)] = got
    return got
