"""The global search: :func:`search_steps` ranks pose hypotheses for one scan over the whole map
and :func:`self_similar_steps` looks for a twin place, both as steps spread over scans (their
work counted by :data:`WORK_MS`); :func:`run_steps` runs them to the end."""

from __future__ import annotations

import math
from collections.abc import Generator
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from service.core.pose import transform_points
from service.core.reloc.config import GlobalConfig
from service.core.reloc.view_index import ViewIndex
from service.core.reloc.view_index.build import anchor, shape_units
from service.core.reloc.view_index.viewpoints import SPACING
from service.core.sensor.pose_batch import fit_pairs
from service.core.sensor.scoring import BeamModel, SensorModel, subsample
from service.core.shapes.configuration import Configuration, scan_configuration
from service.core.shapes.matching import induced_alignment
from service.core.shapes.similarity import prepare, shape_complexity, shape_distance
from service.core.tracking.localizer import ShapeConfig
from service.core.types import wrap_angle

T = TypeVar("T")

#: The search compares the scan's this many most complex units (the rest repeat them), of at
#: least this shape complexity (m·rad): a straight wall tells nothing.
SCAN_UNITS = 5
MIN_UNIT_COMPLEXITY = 0.05
#: |range difference| (m) allowed between a scan unit and a view unit beyond the grid's
#: half-diagonal; view units less complex than this x the scan unit's are skipped.
RANGE_SLACK = 0.4
VIEW_COMPLEXITY_RATIO = 0.25
#: S* gate of a pair (m); corresponding anchor corners turn alike within this (rad).
MAX_SHAPE_DISTANCE = 0.6
MAX_TURN_DIFFERENCE = 0.35
#: Induced poses per scan, shared by the chosen scan units.
PAIRS_BUDGET = 360
#: Scan points of the support ranking, the fits and every polish.
SUPPORT_POINTS = 80
#: Coarse pose cell (m), heading width (rad) and quick-check beams of GlobalConfig.shortlist.
SHORTLIST_CELL = 0.4
SHORTLIST_ANGLE = 0.2
SHORTLIST_BEAMS = 90
#: Point-to-line fit steps per refinement stage.
REFINE_ITERATIONS = 6
#: Cauchy scale (m) of the tight fit stage and of the polish.
FINE_SCALE = 0.05
#: Hypotheses farther apart than this (m), or turned more than this (rad), are distinct places.
DISTINCT_DISTANCE = 0.8
DISTINCT_ANGLE = 0.5
#: Cost of a beam through a drawn wall, in unexplained beams: a wall in the way contradicts a
#: pose, a missing one only fails to confirm it.
VIOLATION_WEIGHT = 2.0
#: Added to every beam cost.
COST_FLOOR = 0.05


@dataclass
class Hypothesis:
    """A pose ``[x, y, theta]`` (map frame) verified on one scan: ``cost`` (lower is better),
    ``hit`` / ``violation`` the shares of beams returned where the map predicts / through a
    wall, ``explained`` the length share of the scan's polylines lying on the map."""

    pose: np.ndarray
    cost: float
    hit: float = 0.0
    violation: float = 0.0
    explained: float = 0.0


def beam_model(config: ShapeConfig, gconfig: GlobalConfig, short_scale: float = 0.0) -> BeamModel:
    """The beam model of the search's checks (``short_scale``: the keyframe evidence's)."""
    return BeamModel(
        tolerance=config.support_tolerance,
        margin=gconfig.violation_margin,
        max_range=config.view_max_range,
        see_through=gconfig.see_through,
        short_scale=short_scale,
        short_credit=gconfig.short_credit,
        violation_weight=VIOLATION_WEIGHT,
        floor=COST_FLOOR,
    )


def beam_costs(
    sensor: SensorModel,
    poses: np.ndarray,
    ranges: np.ndarray,
    angles: np.ndarray,
    beams: int,
    config: ShapeConfig,
    gconfig: GlobalConfig,
) -> np.ndarray:
    """The beam part of :func:`verify`'s cost for each of ``poses`` ``(k, 3)`` on ``beams``
    valid beams: a quick ranking that, unlike the point support, sees beams through walls."""
    sel = subsample(np.nonzero(np.isfinite(ranges))[0], beams)
    if sel.size == 0:
        return np.full(len(poses), np.inf)
    m = beam_model(config, gconfig)
    fr = sensor.beams(np.asarray(poses, dtype=np.float64), ranges[sel], angles[sel], m)
    return np.array([f.beam_cost(m) for f in fr])


def verify(
    index: ViewIndex,
    pose: np.ndarray,
    ranges: np.ndarray,
    angles: np.ndarray,
    P: Configuration,
    config: ShapeConfig,
    gconfig: GlobalConfig,
) -> Hypothesis:
    """Check a pose against the map on ``gconfig.verify_beams`` valid beams and by the length
    share of the scan's polylines lying on the map (``explained``)."""
    sensor = index.sensor
    assert sensor is not None
    idx = subsample(np.nonzero(np.isfinite(ranges))[0], gconfig.verify_beams)
    if idx.size == 0:
        return Hypothesis(pose=pose.copy(), cost=1.0 + COST_FLOOR)
    m = beam_model(config, gconfig)
    f = sensor.beams(pose[None, :], ranges[idx], angles[idx], m)[0]
    explained = sensor.explained_length(pose, P.features, config.support_tolerance)
    return Hypothesis(pose.copy(), f.cost(m), f.hit, f.through, explained)


@dataclass
class SearchResult:
    """Distinct hypotheses, best first, and how many poses the shape pairs induced."""

    hypotheses: list[Hypothesis]
    candidates: int


def support_sample(P: Configuration) -> np.ndarray:
    """:data:`SUPPORT_POINTS` of the scan's feature points (robot frame) for the fits."""
    pts = np.vstack([f.points for f in P.features]) if P.features else np.zeros((0, 2))
    return subsample(pts, SUPPORT_POINTS)


def refine(index: ViewIndex, poses: np.ndarray, sp: np.ndarray, config: ShapeConfig) -> np.ndarray:
    """Refine poses ``(k, 3)`` on the robot-frame scan points ``sp``: a point-to-line fit, a
    tight one, a polish on the distance field and a last continuous fit."""
    sensor = index.sensor
    assert sensor is not None

    def fit(start: np.ndarray, reach: float, scale: float) -> np.ndarray:
        out, _ = fit_pairs(
            [sp] * len(start),
            [sensor.model.nearby_segments(transform_points(p, sp), reach) for p in start],
            start,
            iterations=REFINE_ITERATIONS,
            robust_scale=scale,
            damping=config.align_damping,
        )
        return out

    refined = fit(np.asarray(poses, dtype=np.float64), 0.5, config.align_robust_scale)
    # the segments right under the points only, a small robust scale: unmapped furniture
    # stops pulling; the last fit, as the distance field is quantised to its cells
    refined = fit(refined, 2.0 * FINE_SCALE, FINE_SCALE)
    refined, _ = sensor.polish(refined, sp, FINE_SCALE)
    return fit(refined, 2.0 * FINE_SCALE, FINE_SCALE)


# distinct and near compare every pair of poses: scalar differences, no temporary arrays
def distinct(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether poses ``a`` and ``b`` are distinct places."""
    return bool(
        np.hypot(a[0] - b[0], a[1] - b[1]) > DISTINCT_DISTANCE
        or abs(wrap_angle(float(a[2] - b[2]))) > DISTINCT_ANGLE
    )


def near(a: np.ndarray, b: np.ndarray, dist: float = 0.3, ang: float = 0.15) -> bool:
    """Whether poses ``a`` and ``b`` lie within ``dist`` (m) and ``ang`` (rad): one pose."""
    return bool(
        np.hypot(a[0] - b[0], a[1] - b[1]) < dist and abs(wrap_angle(float(a[2] - b[2]))) < ang
    )


#: Work model (ms of one reference core per item): a budgeted search gives the same poses on any
#: machine and load (docs/decisions/0005); at or above bench/bench_work_model.py's slowest map.
WORK_MS = {
    "sstar": 0.0105,  # one S* comparison (shape_distance with an upper bound)
    "induced": 0.045,  # one S*-induced alignment
    "support": 0.000012,  # one pose x one point of the support ranking
    "field_beam": 0.00012,  # one pose x one beam marched on the distance field
    "polish": 0.000006,  # one pose x grid cell x point of a distance-field polish ...
    "polish_call": 0.15,  # ... and one call's fixed part (a keyframe polishes one pose)
    "beam": 0.0023,  # one pose x one beam of a ray cast check ...
    "cast_segment": 0.00018,  # ... and one pose x one segment of the map (any ray cast)
    "layered": 0.1,  # a verification's see-through cast (GlobalConfig.see_through)
    "refine": 0.6,  # one pose through the four refinement stages ...
    "refine_segment": 0.00035,  # ... and x one segment of the map (denser segment grid)
    "verify": 0.3,  # one verification's fixed part (the feature check) ...
    "verify_beam": 0.0002,  # ... and per beam (plus its ray cast)
}

_CHUNK_SSTAR = 96  # S* comparisons between two yields
_CHUNK_POSES = 800  # poses of the support ranking between two yields
_CHUNK_POLISH = 12  # poses polished between two yields
_CHUNK_REFINE = 2  # poses refined / verified between two yields


def polish_ms(points: int) -> float:
    """Work (reference ms) of one pose's polish (two 5 x 5 x 5 grids) on ``points``."""
    return 250 * max(points, 1) * WORK_MS["polish"]


def cast_ms(index: ViewIndex) -> float:
    """Work (reference ms) of one pose's ray cast per the map's segments."""
    assert index.sensor is not None
    return len(index.sensor.segments) * WORK_MS["cast_segment"]


def refine_ms(index: ViewIndex) -> float:
    """Work (reference ms) of one pose's :func:`refine` on ``index``'s map."""
    assert index.sensor is not None
    return WORK_MS["refine"] + len(index.sensor.segments) * WORK_MS["refine_segment"]


def beams_ms(index: ViewIndex, gconfig: GlobalConfig, beams: int) -> float:
    """Work (reference ms) of one pose's cast and beam fractions over ``beams`` beams."""
    layered = WORK_MS["layered"] if gconfig.see_through else 0.0
    return beams * WORK_MS["verify_beam"] + cast_ms(index) + layered


def verify_ms(index: ViewIndex, gconfig: GlobalConfig) -> float:
    """Work (reference ms) of one pose's :func:`verify`."""
    return WORK_MS["verify"] + beams_ms(index, gconfig, gconfig.verify_beams)


def _first_rows(rows: np.ndarray) -> np.ndarray:
    """Positions (ascending) of the first occurrence of each distinct row of ``rows`` ``(n,
    k)`` (whole numbers as floats), on one integer key per row: a row-wise ``np.unique``
    sorts structured records, ~100x slower."""
    if rows.size == 0:
        return np.zeros(0, dtype=np.int64)
    if not np.all(np.isfinite(rows)):
        return np.sort(np.unique(rows, axis=0, return_index=True)[1])
    q = rows.astype(np.int64)
    lo = q.min(axis=0)
    span = q.max(axis=0) - lo + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0**62:
        return np.sort(np.unique(rows, axis=0, return_index=True)[1])
    key = np.zeros(len(q), dtype=np.int64)
    for j in range(q.shape[1]):
        key = key * span[j] + (q[:, j] - lo[j])
    return np.sort(np.unique(key, return_index=True)[1])


def advance(
    steps: Generator[float, None, T], spent: float, budget: float
) -> tuple[float, bool, T | None]:
    """Run a step generator until the scan's work ``spent`` reaches ``budget`` (at least one
    step, so a search always progresses). Returns ``(spent, done, result)``."""
    while True:
        try:
            w = next(steps)
        except StopIteration as stop:
            return spent, True, stop.value
        spent += w
        if spent >= budget:
            return spent, False, None


def run_steps(steps: Generator[float, None, T]) -> T:
    """Run a step generator to the end and return its result."""
    return advance(steps, 0.0, math.inf)[2]  # type: ignore[return-value]


def search_steps(
    index: ViewIndex,
    ranges: np.ndarray,
    angles: np.ndarray,
    config: ShapeConfig,
    gconfig: GlobalConfig,
    seeds: list[np.ndarray] | tuple[np.ndarray, ...] = (),
    P: Configuration | None = None,
) -> Generator[float, None, SearchResult]:
    """The global search for one scan over the whole map: a generator yielding each chunk's
    work (reference ms, :data:`WORK_MS`) and returning the :class:`SearchResult`.

    The :data:`SCAN_UNITS` most complex scan units are compared by S* with every index unit
    at a similar range from its viewpoint; the most similar pairs (:data:`PAIRS_BUDGET`) each
    induce a pose. These and the ``seeds`` (the kept hypotheses) are ranked by support on the
    distance field; the best ``refine_top`` distinct ones are refined and verified. ``P``: the
    scan's configuration if already computed."""
    sensor = index.sensor
    assert sensor is not None
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    if P is None:
        P = scan_configuration(r, a, config.extraction())
    poses: list[np.ndarray] = [np.asarray(s, dtype=np.float64) for s in seeds]
    anchor_poses: list[np.ndarray] = []
    n_induced = 0
    if P.features and len(index):
        units = shape_units(P, config.dce_threshold, cyclic=False)
        comp = sorted(
            ((shape_complexity(u), k) for k, u in enumerate(units)), key=lambda t: (-t[0], t[1])
        )
        chosen = [k for c, k in comp[:SCAN_UNITS] if c >= MIN_UNIT_COMPLEXITY]
        gate = 0.5 * np.sqrt(2.0) * SPACING + RANGE_SLACK
        sstar = {
            "end_weight": config.shape_end_weight,
            "skip_weight": config.shape_skip_weight,
            "upper_bound": MAX_SHAPE_DISTANCE,
        }
        for k in chosen:
            pu = units[k]
            pa = prepare(pu)
            dp = np.hypot(pu[:, 0], pu[:, 1])
            cp = shape_complexity(pu)
            p_anc, p_dir, p_turn = anchor(pu)
            cand = np.nonzero(
                (index.unit_rmin <= dp.max() + gate)
                & (index.unit_rmax >= dp.min() - gate)
                & (index.unit_complexity >= VIEW_COMPLEXITY_RATIO * cp)
            )[0]
            cornered = abs(p_turn) > 0.2
            if cornered:  # corresponding corners turn alike
                dturn = np.mod(index.unit_anchor[cand, 3] - p_turn + np.pi, 2.0 * np.pi) - np.pi
                cand = cand[np.abs(dturn) < MAX_TURN_DIFFERENCE]
            # one S* per group of views of the same corner, and a similar group lends every view
            # its anchor: the alignments cover many places, not one corner many times
            groups = index.unit_group[cand]
            _, first = np.unique(groups, return_index=True)
            scored = []
            for j, u in enumerate(cand[np.sort(first)].tolist()):
                s = shape_distance(pa, index.arcs(u), **sstar)
                if s < MAX_SHAPE_DISTANCE:
                    scored.append((s, u))
                if (j + 1) % _CHUNK_SSTAR == 0:
                    yield _CHUNK_SSTAR * WORK_MS["sstar"]
            scored.sort()
            top = scored[: PAIRS_BUDGET // len(chosen)]
            poses += [induced_alignment(pa, index.arcs(u)) for _s, u in top]
            n_induced += len(top)
            if scored and cornered:
                # each view of a similar group fixes a pose by its anchor (vectorised: cheap)
                similar = np.isin(groups, index.unit_group[[u for _s, u in scored]])
                qa = index.unit_anchor[cand[similar]]
                phi = np.mod(qa[:, 2] - p_dir + np.pi, 2.0 * np.pi) - np.pi
                c, s_ = np.cos(phi), np.sin(phi)
                tx = qa[:, 0] - (c * p_anc[0] - s_ * p_anc[1])
                ty = qa[:, 1] - (s_ * p_anc[0] + c * p_anc[1])
                anchor_poses.append(np.column_stack([tx, ty, phi]))
                n_induced += len(qa)
            yield len(top) * WORK_MS["induced"] + (len(first) % _CHUNK_SSTAR) * WORK_MS["sstar"]
    sp = support_sample(P)
    if (not poses and not anchor_poses) or len(sp) == 0:
        return SearchResult(hypotheses=[], candidates=n_induced)
    H = np.vstack([np.asarray(poses).reshape(-1, 3), *anchor_poses])
    parts = []
    for i in range(0, len(H), _CHUNK_POSES):
        block = H[i : i + _CHUNK_POSES]
        parts.append(sensor.support(block, sp, config.support_tolerance))
        yield len(block) * len(sp) * WORK_MS["support"]
    sup = np.concatenate(parts)
    order = np.argsort(-sup, kind="stable")
    if gconfig.shortlist > 0:
        # an induced pose near the truth is often decimetres off, its support below a wrong
        # place's: the best per coarse cell is polished and ranked by a quick beam check
        heading = (wrap_angle(H[:, 2]) + np.pi) / SHORTLIST_ANGLE
        cells = np.floor(np.column_stack([H[:, :2] / SHORTLIST_CELL, heading]))
        reps = order[_first_rows(cells[order])]
        nb = gconfig.shortlist_violation_beams
        beams = subsample(np.flatnonzero(np.isfinite(r)), nb) if nb > 0 else np.zeros(0, int)
        if beams.size and len(reps):
            # a wrong place whose walls the furniture fits out-scores the true one on support,
            # but most of its other beams pass through drawn walls, the true pose's hardly any
            margin = max(config.support_tolerance, gconfig.violation_margin)
            vparts = []
            for i in range(0, len(reps), _CHUNK_POSES):
                block = H[reps[i : i + _CHUNK_POSES]]
                vparts.append(sensor.crossings(block, r[beams], a[beams], margin))
                yield len(block) * beams.size * WORK_MS["field_beam"]
            score = sup[reps] - VIOLATION_WEIGHT * np.concatenate(vparts)
            reps = reps[np.argsort(-score, kind="stable")]
        short = reps[: gconfig.shortlist]
        polished_parts, quick_parts = [], []
        for i in range(0, len(short), _CHUNK_POLISH):
            block = H[short[i : i + _CHUNK_POLISH]]
            pol, _score = sensor.polish(block, sp, FINE_SCALE, stages=((0.15, 0.06), (0.05, 0.02)))
            polished_parts.append(pol)
            quick_parts.append(beam_costs(sensor, pol, r, a, SHORTLIST_BEAMS, config, gconfig))
            yield len(block) * (
                polish_ms(len(sp)) + SHORTLIST_BEAMS * WORK_MS["beam"] + cast_ms(index)
            )
        H = np.vstack(polished_parts)
        order = np.argsort(np.concatenate(quick_parts), kind="stable")
    picked: list[np.ndarray] = []
    for i in order.tolist():
        if len(picked) >= gconfig.refine_top:
            break
        if not any(near(H[i], p) for p in picked):
            picked.append(H[i])
    hyps: list[Hypothesis] = []
    for i in range(0, len(picked), _CHUNK_REFINE):
        block = np.vstack(picked[i : i + _CHUNK_REFINE])
        refined = refine(index, block, sp, config)
        hyps.extend(verify(index, p, r, a, P, config, gconfig) for p in refined)
        yield len(block) * (refine_ms(index) + verify_ms(index, gconfig))
    hyps.sort(key=lambda h: h.cost)
    out: list[Hypothesis] = []
    for h in hyps:
        if all(not near(h.pose, o.pose) for o in out):
            out.append(h)
    return SearchResult(hypotheses=out, candidates=n_induced)


def self_similar_steps(
    index: ViewIndex,
    best: Hypothesis,
    ranges: np.ndarray,
    angles: np.ndarray,
    P: Configuration,
    config: ShapeConfig,
    gconfig: GlobalConfig,
    count: int = 1,
) -> Generator[float, None, list[Hypothesis]]:
    """The map's own twins of ``best`` verified on the real scan, the best ``count`` first,
    as steps: a search can miss the true place (furniture hides its walls) and crown a
    congruent room. The scan the map gives at ``best.pose`` is searched for; each distinct place
    found is verified on the real scan as found and refined on its points, the better."""
    assert index.sensor is not None
    pred = index.sensor.caster.cast(best.pose, angles, config.view_max_range)
    pred = np.where(np.isfinite(ranges), pred, np.nan)
    if np.count_nonzero(np.isfinite(pred)) < 10:
        return []
    res = yield from search_steps(index, pred, angles, config, gconfig)
    cands = [h.pose for h in res.hypotheses if distinct(h.pose, best.pose)]
    sp = support_sample(P)
    if not cands or len(sp) == 0:
        return []
    out: list[Hypothesis] = []
    for i in range(0, len(cands), _CHUNK_REFINE):
        block = np.vstack(cands[i : i + _CHUNK_REFINE])
        refined = refine(index, block, sp, config)
        for pair in zip(block, refined, strict=True):
            kept = [q for q in pair if distinct(q, best.pose)]
            found = [verify(index, q, ranges, angles, P, config, gconfig) for q in kept]
            out += [min(found, key=lambda v: v.cost)] if found else []
        yield len(block) * (refine_ms(index) + 2.0 * verify_ms(index, gconfig))
    return sorted(out, key=lambda v: v.cost)[:count]
