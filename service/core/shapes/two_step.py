"""The shape-complexity-based two-step matching of the paper's §5.3, on the matching of
ordered configurations of :mod:`service.core.shapes.matching` (eq. 5).

* :func:`step1_hypotheses` — step 1: the most complex scan units (polylines, or stacks of
  them) matched against every map unit by shape similarity (S*), each correspondence inducing
  a displacement estimate (a robot pose, map frame).
* :func:`heading_hypotheses` — with a motion prior, estimates from the prior's heading.
* :func:`two_step_match` — step 2: eq. 5 from each estimate, the best by cost and support.
* :func:`support` — the fraction of scan points a pose explains within a tolerance.

Frames and units as in :mod:`service.core.shapes.matching` (metres, radians; poses
``[x, y, theta]``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from service.core import kernels
from service.core.kernels import grid as grid_kernels
from service.core.pose import pose_from_matches, transform_points
from service.core.sensor.pose_batch import fit_pairs
from service.core.shapes.configuration import Configuration, Feature
from service.core.shapes.matching import (
    ConfigurationMatch,
    induced_alignment,
    match_with_cost,
    matched_stack,
)
from service.core.shapes.shape_cost import (
    ShapeCost,
    batched_shape_cost,
    gated_shape_cost,
    shape_arcs,
)
from service.core.shapes.similarity import (
    complexity_of,
    shape_complexity,
)
from service.core.shapes.stacked import (
    piece_means,
    stacked_points,
    subsample,
)
from service.core.types import wrap_angle

if TYPE_CHECKING:
    from service.core.tracking.localizer import ShapeConfig


@dataclass
class TwoStepResult:
    """Result of :func:`two_step_match`.

    ``estimate`` the displacement estimate of step 1 (a robot pose, map frame) that step 2
    used; ``match`` step 2's correspondence; ``support`` the fraction of scan points the
    estimate explains; ``ambiguity`` best-vs-second-best eq. 5 cost ratio in [0, 1] over the
    hypotheses tried (1 = tie, 0 = only one hypothesis); ``hypotheses`` how many were tried.
    """

    estimate: np.ndarray
    match: ConfigurationMatch
    support: float
    ambiguity: float
    hypotheses: int


def _view_tree(Q: Configuration) -> cKDTree | None:
    tree = Q.__dict__.get("_tree")
    if tree is None and Q.features:
        tree = cKDTree(np.vstack([f.points for f in Q.features]))
        Q.__dict__["_tree"] = tree
    return tree


def _near(Q: Configuration, x: np.ndarray, y: np.ndarray, tol: float) -> np.ndarray:
    """Per point ``(x[i], y[i])`` (map frame): is a map view point closer than ``tol``? A
    bucket grid in a numba kernel (exact), else the view's KD-tree."""
    if not kernels.HAVE_NUMBA:
        tree = _view_tree(Q)
        assert tree is not None
        d, _ = tree.query(np.column_stack([x, y]), k=1, distance_upper_bound=tol)
        return np.isfinite(d)
    key = ("_grid", tol)
    grid = Q.__dict__.get(key)
    if grid is None:
        pts = stacked_points(Q)[0]
        cell = 1.01 * tol  # > tol, so the 3 x 3 neighbouring cells hold every near point
        x0, y0, nx, ny, start, order = grid_kernels.grid_build(pts, cell)
        sx, sy = (np.ascontiguousarray(pts[order, k]) for k in (0, 1))
        grid = (sx, sy, x0, y0, nx, ny, start, cell)
        Q.__dict__[key] = grid
    sx, sy, x0, y0, nx, ny, start, cell = grid
    return grid_kernels.grid_near(
        sx,
        sy,
        x0,
        y0,
        nx,
        ny,
        start,
        cell,
        np.ascontiguousarray(x, dtype=np.float64),
        np.ascontiguousarray(y, dtype=np.float64),
        float(tol),
    )


def support(Q: Configuration, scan_points: np.ndarray, pose: np.ndarray, tol: float) -> float:
    """Fraction of ``scan_points`` (robot frame) that lie within ``tol`` metres of the map
    view's points when placed at ``pose`` — how much of the scan a hypothesis explains."""
    if not Q.features or len(scan_points) == 0:
        return 0.0
    q = transform_points(pose, scan_points)
    return float(np.mean(_near(Q, q[:, 0], q[:, 1], tol)))


class _Unit:
    """A feature or two consecutive features joined, as used by step 1: ``pieces`` their
    indices in the configuration, ``key`` their identity; the joined arrays are stacked on
    first use (most units only need their mean point and their S*)."""

    __slots__ = ("_points", "_segments", "_vertices", "feats", "key", "pieces")

    def __init__(self, feats: tuple[Feature, ...], pieces: tuple[int, ...]) -> None:
        self.feats = feats
        self.pieces = pieces
        self.key = ("u", *(id(f) for f in feats))
        one = feats[0] if len(feats) == 1 else None
        self._vertices = None if one is None else one.vertices
        self._points = None if one is None else one.points
        self._segments = None if one is None else one.segments

    @property
    def vertices(self) -> np.ndarray:
        if self._vertices is None:
            self._vertices = np.vstack([f.vertices for f in self.feats])
        return self._vertices

    @property
    def points(self) -> np.ndarray:
        if self._points is None:
            self._points = np.vstack([f.points for f in self.feats])
        return self._points

    @property
    def has_segments(self) -> bool:
        return all(f.segments is not None for f in self.feats)

    @property
    def segments(self) -> np.ndarray | None:
        if self._segments is None and self.has_segments:
            self._segments = np.vstack([f.segments for f in self.feats])  # type: ignore[misc]
        return self._segments


def _units(C: Configuration, cyclic: bool) -> list[_Unit]:
    out = [_Unit((f,), (i,)) for i, f in enumerate(C.features)]
    n = len(C.features)
    last = n if (cyclic and n > 2) else n - 1
    for i in range(max(last, 0)):
        j = (i + 1) % n
        out.append(_Unit((C.features[i], C.features[j]), (i, j)))
    return out


def _unit_pieces(units: Sequence[_Unit]) -> np.ndarray:
    """``(len(units), 2)`` feature indices of each unit, ``-1`` padded."""
    return np.array([(*u.pieces, -1)[:2] for u in units], dtype=np.intp).reshape(-1, 2)


def _unit_complexity(u: _Unit) -> float:
    """:func:`service.core.shapes.similarity.shape_complexity` of the unit's joined vertices."""
    if len(u.feats) == 1:
        return shape_complexity(u.vertices)
    xs: list[float] = []
    ys: list[float] = []
    for f in u.feats:
        xs += f.vertices[:, 0].tolist()
        ys += f.vertices[:, 1].tolist()
    return complexity_of(xs, ys)


def step1_hypotheses(
    P: Configuration, Q: Configuration, prior: np.ndarray, config: ShapeConfig, cache: dict
) -> list[tuple[np.ndarray, float]]:
    """Step 1 of §5.3: pose hypotheses from the most complex and most similar pairs.

    Units are single features and pairs of consecutive features (a corner is often cut in
    two). Scan units are ranked by shape complexity; the ``config.step1_features`` most complex
    ones (complexity >= ``config.step1_min_complexity``) are compared by S* with every map unit
    whose distance from the prior position differs by at most ``config.step1_range_gate``
    metres from the scan unit's range (a test that does not depend on the unknown rotation).
    The ``config.step1_pairs_per_feature`` most similar map units (S* <=
    ``config.step1_max_shape_distance``) each induce an alignment (:func:`induced_alignment`),
    i.e. a pose hypothesis, refined on that pair alone by a few point-to-line steps.
    Returns ``[(pose, S*), ...]``.
    """
    if not P.features or not Q.features:
        return []
    p_units = _units(P, False)
    comp = []
    for k, u in enumerate(p_units):
        c = cache.get(("C", *u.key))
        if c is None:
            c = _unit_complexity(u)
            cache[("C", *u.key)] = c
        comp.append((c, k))
    comp.sort(key=lambda t: (-t[0], t[1]))
    chosen = [k for c, k in comp[: config.step1_features] if c >= config.step1_min_complexity]
    if not chosen:
        return []
    got = Q.__dict__.get("_step1_units")
    if got is None:
        q_units = [u for u in _units(Q, Q.cyclic) if u.has_segments]
        q_pieces = _unit_pieces(q_units)
        got = (q_units, piece_means(Q, q_pieces), q_pieces)
        Q.__dict__["_step1_units"] = got
    q_units, q_mean, q_pieces = got
    q_rng = np.hypot(q_mean[:, 0] - prior[0], q_mean[:, 1] - prior[1])
    gate = config.step1_max_shape_distance
    p_pieces = _unit_pieces(p_units)
    p_mean = piece_means(P, p_pieces[chosen])
    cand = []
    for k, mean in zip(chosen, p_mean, strict=True):
        r = float(np.hypot(*mean))
        cand.append((k, np.nonzero(np.abs(q_rng - r) <= config.step1_range_gate)[0]))
    if kernels.HAVE_NUMBA:
        # every pair of step 1 in one compiled call (the same S* as the loop below computes)
        ks = np.repeat([k for k, _ in cand], [len(js) for _, js in cand])
        js_all = np.concatenate([js for _, js in cand])
        vals = batched_shape_cost(P, Q, p_pieces[ks], q_pieces[js_all], config, gate)
        pos = 0
        svals = []
        for _, js in cand:
            svals.append(vals[pos : pos + len(js)])
            pos += len(js)
    else:
        sd = gated_shape_cost(config, gate)
        svals = [
            [
                float(sd(shape_arcs(p_units[k].key, p_units[k].vertices, cache), qa))
                for qa in (shape_arcs(q_units[j].key, q_units[j].vertices, cache) for j in js)
            ]
            for k, js in cand
        ]
    out: list[tuple[np.ndarray, float]] = []
    pair_pts: list[np.ndarray] = []
    pair_segs: list[np.ndarray] = []
    for (k, js), vals_k in zip(cand, svals, strict=True):
        pu = p_units[k]
        scored = sorted((s, int(j)) for s, j in zip(vals_k, js.tolist(), strict=True) if s <= gate)
        if not scored:
            continue
        pa = shape_arcs(pu.key, pu.vertices, cache)
        pts = subsample(pu.points, config.align_points)
        for s, j in scored[: config.step1_pairs_per_feature]:
            qu = q_units[j]
            qa = shape_arcs(qu.key, qu.vertices, cache)
            out.append((induced_alignment(pa, qa), s))
            pair_pts.append(pts)
            pair_segs.append(qu.segments)  # type: ignore[arg-type]
    if out and config.step1_refine_iterations > 0:
        # Refine each induced alignment on its own pair (point-to-line, from the S* alignment).
        # A pair that only fixes the rotation and one offset (a straight wall) leaves the shift
        # along it to S*'s guess; so each pair also yields the variant that keeps the prior's
        # position and only takes the rotation, refined with damping (the along-wall shift
        # then stays at the prior's).
        init = np.array([p for p, _ in out])
        rot_only = np.column_stack([np.tile(prior[:2], (len(out), 1)), init[:, 2]])
        poses, _ = fit_pairs(
            pair_pts + pair_pts,
            pair_segs + pair_segs,
            np.vstack([init, rot_only]),
            iterations=config.step1_refine_iterations,
            robust_scale=config.align_robust_scale,
            damping=config.align_damping,
        )
        n = len(out)
        out = [(poses[k], s) for k, (_, s) in enumerate(out)] + [
            (poses[n + k], s) for k, (_, s) in enumerate(out)
        ]
    return out


def heading_hypotheses(
    Q: Configuration,
    scan_points: np.ndarray,
    prior: np.ndarray,
    config: ShapeConfig,
    sweep: float | None = None,
    step: float | None = None,
) -> list[tuple[float, np.ndarray]]:
    """Plausible cut points of the cyclic order (§5.2): headings at the prior position.

    Turning the robot only rotates the cyclic map view, i.e. moves the point where the cyclic
    configuration is cut to line up with the scan. Headings within ``sweep`` (default
    ``config.heading_sweep``, at most ``config.max_turn``) radians of the prior, every ``step``
    (default ``config.heading_step``) radians, are scored by :func:`support`; the
    ``config.heading_hypotheses`` best local maxima are returned as ``[(support, pose), ...]``,
    best first.
    """
    if not Q.features or len(scan_points) == 0:
        return []
    sweep = min(config.heading_sweep if sweep is None else sweep, config.max_turn)
    step = config.heading_step if step is None else step
    offs = np.arange(-sweep, sweep + 1e-9, step)
    th = prior[2] + offs
    c, s_ = np.cos(th), np.sin(th)
    x = c[:, None] * scan_points[None, :, 0] - s_[:, None] * scan_points[None, :, 1] + prior[0]
    y = s_[:, None] * scan_points[None, :, 0] + c[:, None] * scan_points[None, :, 1] + prior[1]
    near = _near(Q, x.ravel(), y.ravel(), config.support_tolerance)
    sup = near.reshape(len(th), -1).mean(axis=1)
    left = np.concatenate(([-1.0], sup[:-1]))
    right = np.concatenate((sup[1:], [-1.0]))
    peaks = np.nonzero((sup >= left) & (sup >= right))[0]
    peaks = sorted(peaks, key=lambda k: (-sup[k], abs(offs[k])))[: config.heading_hypotheses]
    return [
        (float(sup[k]), np.array([prior[0], prior[1], float(wrap_angle(th[k]))])) for k in peaks
    ]


def two_step_match(
    P: Configuration,
    Q: Configuration,
    prior: np.ndarray,
    config: ShapeConfig,
    scan_points: np.ndarray | None = None,
    shape_cost: ShapeCost | None = None,
    max_step: float | None = None,
) -> TwoStepResult:
    """Shape-complexity-based two-step matching (§5.3).

    Step 1 (:func:`step1_hypotheses`) estimates the displacement from the most complex, most
    similar pairs alone. Their hypotheses and the ``prior`` (last pose) form a robust
    consensus: each is scored by the fraction of all scan points it explains against the map
    view (:func:`support`, tolerance ``config.support_tolerance`` metres), and the
    ``config.step2_hypotheses`` best go to step 2 — the full eq. 5 matching
    (:func:`match_with_cost`) with ``ΔA`` measured against that estimate. The hypothesis with
    the lowest eq. 5 cost wins (plus ``config.prior_distance_weight`` per metre from the
    prior). When the prior alone already explains ``config.fast_support`` of the scan points
    (tracking with small motion), step 1 is skipped and step 2 runs on the prior only.

    ``prior`` ``[x, y, theta]`` map frame; ``scan_points`` robot-frame points used for the
    support (default: all feature points); ``max_step`` (m) overrides ``config.max_step``.
    """
    prior = np.asarray(prior, dtype=np.float64)
    max_step = config.max_step if max_step is None else max_step
    cache: dict = {}
    if scan_points is None:
        scan_points = np.vstack([f.points for f in P.features]) if P.features else np.zeros((0, 2))
    sp = subsample(scan_points, config.support_points)
    hyps = [(prior, 0.0)]
    # Fast path: small motion. A fine heading sweep near the prior; if its best heading
    # already explains config.fast_support of the scan, step 1 is not needed.
    near = heading_hypotheses(
        Q, sp[:: max(1, len(sp) // 60)], prior, config, config.fast_sweep, config.fast_step
    )
    fast = bool(near) and near[0][0] >= config.fast_support
    if fast:
        hyps = [(near[0][1], 0.0)]
    if config.two_step and not fast:
        # The robot cannot have moved farther than max_step nor turned more than max_turn
        # since the prior (§5.2: views differ little if the robot has not travelled far).
        hyps += [
            (h, s)
            for h, s in step1_hypotheses(P, Q, prior, config, cache)
            if np.hypot(*(h[:2] - prior[:2])) <= max_step
            and abs(wrap_angle(h[2] - prior[2])) <= config.max_turn
        ]
    scored = []
    for k, (pose, _s) in enumerate(hyps):
        sup = support(Q, sp, pose, config.support_tolerance)
        scored.append((sup, -k, pose))
    if config.heading_sweep > 0 and not fast:
        for sup, pose in heading_hypotheses(Q, sp, prior, config):
            scored.append((sup, -len(scored), pose))
    scored.sort(key=lambda t: (t[0], t[1]), reverse=True)
    # keep the best distinct hypotheses (and always the prior if it is competitive)
    picked: list[tuple[float, np.ndarray]] = []
    for sup, _k, pose in scored:
        if len(picked) >= config.step2_hypotheses:
            break
        if any(
            np.hypot(*(pose[:2] - p[:2])) < 0.05 and abs(wrap_angle(pose[2] - p[2])) < 0.02
            for _s, p in picked
        ):
            continue
        picked.append((sup, pose))
    results = []
    gate = config.fast_bearing_gate if fast else config.bearing_gate
    for sup, pose in picked:
        res = match_with_cost(P, Q, pose, config, shape_cost, cache, gate)
        for _ in range(0 if fast else config.step2_refinements):
            # Re-estimate the displacement from step 2's own correspondences and match again
            # against it (ΔA is then measured against a better estimate).
            if not res.matches:
                break
            pose = pose_from_matches(
                matched_stack(P, Q, res.matches),
                pose,
                iterations=config.pose_iterations,
                inlier_distance=config.pose_inlier_distance,
                robust_scale=config.pose_robust_scale,
                prior=prior,
                prior_weight=config.pose_prior_weight,
                covariance=False,
            ).pose
            res = match_with_cost(P, Q, pose, config, shape_cost, cache, gate)
        # Motion continuity: a hypothesis far from the prior position pays for the distance
        # (weighted like eq. 4's ||dt||); decides between poses a corridor cannot tell apart.
        rank = res.cost + config.prior_distance_weight * float(np.hypot(*(pose[:2] - prior[:2])))
        results.append((rank, sup, pose, res))
    results.sort(key=lambda t: t[0])
    best_cost, best_sup, best_pose, best_res = results[0]
    ambiguity = 0.0
    if len(results) > 1 and results[1][0] > 0:
        ambiguity = float(min(1.0, best_cost / results[1][0]))
    return TwoStepResult(
        estimate=best_pose,
        match=best_res,
        support=best_sup,
        ambiguity=ambiguity,
        hypotheses=len(hyps),
    )
