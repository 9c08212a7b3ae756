"""Configuration matching (service/core/shapes/matching.py): eq. 4, penalty R, the eq. 5 DP
(service/core/shapes/order_dp.py), S* as its shape cost (service/core/shapes/shape_cost.py); and the
parts of the two-step matching (service/core/shapes/two_step.py) that check it bit for bit.

Runs in about a second.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import numpy as np
import pytest

from service.core import kernels
from service.core.pose import invert, pose_from_matches, transform_points
from service.core.shapes import matching, order_dp, shape_cost, two_step
from service.core.shapes.configuration import Configuration, Feature
from service.core.shapes.matching import (
    angular_interval,
    induced_alignment,
    match_configurations,
    match_with_cost,
    penalty_R,
    pose_consistency,
)
from service.core.shapes.order_dp import order_preserving_dp
from service.core.shapes.similarity import shape_distance
from service.core.tracking.localizer import ShapeConfig

# --------------------------------------------------------------------------------------------
# eq. 4 and R
# --------------------------------------------------------------------------------------------


def test_pose_consistency_is_eq4() -> None:
    assert pose_consistency([0.3, 0.4], 0.1) == pytest.approx(0.5 + 10 * 0.1)
    assert pose_consistency([0.0, 0.0], -0.05) == pytest.approx(0.5)
    # dPhi is wrapped before |.|: a full turn plus 0.1 rad counts as 0.1 rad
    assert pose_consistency([0.0, 0.0], 2 * math.pi + 0.1) == pytest.approx(1.0)
    assert pose_consistency([1.0, 0.0], 0.1, rot_weight=2.0) == pytest.approx(1.2)


def _arc(radius: float, a0: float, a1: float, n: int = 50) -> np.ndarray:
    t = np.linspace(a0, a1, n)
    return np.column_stack([radius * np.cos(t), radius * np.sin(t)])


def test_penalty_r_grows_linearly_with_angular_size() -> None:
    sizes = [0.1, 0.2, 0.4, 0.8]
    r = [penalty_R(_arc(3.0, -0.2, -0.2 + s), weight=2.0) for s in sizes]
    assert r == pytest.approx([2.0 * s for s in sizes], rel=1e-9)
    # independent of range: the same angle at 1 m and at 8 m costs the same
    assert penalty_R(_arc(1.0, 0, 0.3)) == pytest.approx(penalty_R(_arc(8.0, 0, 0.3)))


def test_penalty_r_counts_only_the_part_inside_the_field_of_view() -> None:
    pts = _arc(2.0, 1.0, 2.0)  # 1 rad wide, from 57 to 115 deg
    fov = (-math.pi / 2, math.pi / 2)
    assert penalty_R(pts, fov=fov) == pytest.approx(math.pi / 2 - 1.0)
    assert penalty_R(_arc(2.0, 2.0, 2.5), fov=fov) == 0.0
    # seen from a viewpoint turned by pi/2, the same polyline is centred in the view
    assert penalty_R(pts, viewpoint=np.array([0.0, 0.0, 1.5]), fov=fov) == pytest.approx(1.0)


def test_induced_alignment_of_a_corner_is_the_displacement() -> None:
    corner = np.array([[3.0, -2.0], [3.0, 1.0], [1.0, 1.0]])
    moved = np.array([0.4, -0.3, 0.35])
    a = induced_alignment(corner, transform_points(moved, corner))
    assert np.allclose(a, moved, atol=1e-6)


# --------------------------------------------------------------------------------------------
# The DP (eq. 5)
# --------------------------------------------------------------------------------------------


def _brute_force_1to1(skip_p: list[float], skip_q: list[float], cost: np.ndarray) -> float:
    """Minimum of eq. 5 over all order-preserving 1:1 matchings (small n, m only)."""
    n, m = len(skip_p), len(skip_q)
    best = sum(skip_p) + sum(skip_q)
    for k in range(1, min(n, m) + 1):
        for ps in itertools.combinations(range(n), k):
            for qs in itertools.combinations(range(m), k):
                c = sum(cost[i, j] for i, j in zip(ps, qs, strict=True))
                c += sum(skip_p[i] for i in range(n) if i not in ps)
                c += sum(skip_q[j] for j in range(m) if j not in qs)
                best = min(best, c)
    return best


def test_dp_is_optimal_and_order_preserving_on_random_instances() -> None:
    rng = np.random.default_rng(7)
    for _ in range(60):
        n, m = int(rng.integers(1, 5)), int(rng.integers(1, 5))
        skip_p = rng.uniform(0.2, 1.5, n).tolist()
        skip_q = rng.uniform(0.2, 1.5, m).tolist()
        cost = rng.uniform(0.0, 2.5, (n, m))
        blocks = {(i, j): [(i, j, float(cost[i, j]))] for i in range(n) for j in range(m)}
        total, path = order_preserving_dp(skip_p, skip_q, blocks)
        assert total == pytest.approx(_brute_force_1to1(skip_p, skip_q, cost))
        # the reported path reproduces the cost and respects the order
        matched_p = {i for i_s, i_e, _, _ in path for i in range(i_s, i_e + 1)}
        matched_q = {j for _, _, j_s, j_e in path for j in range(j_s, j_e + 1)}
        c = sum(cost[i_s, j_s] for i_s, _, j_s, _ in path)
        c += sum(skip_p[i] for i in range(n) if i not in matched_p)
        c += sum(skip_q[j] for j in range(m) if j not in matched_q)
        assert c == pytest.approx(total)
        for a, b in itertools.pairwise(path):
            assert a[1] < b[0] and a[3] < b[2]


def test_dp_never_violates_order_with_random_blocks() -> None:
    rng = np.random.default_rng(8)
    for _ in range(100):
        n, m = int(rng.integers(2, 12)), int(rng.integers(2, 12))
        blocks: dict = {}
        for _k in range(int(rng.integers(1, 40))):
            i_s = int(rng.integers(0, n))
            j_s = int(rng.integers(0, m))
            i_e = min(n - 1, i_s + int(rng.integers(0, 3)))
            j_e = min(m - 1, j_s + int(rng.integers(0, 3)))
            blocks.setdefault((i_e, j_e), []).append((i_s, j_s, float(rng.uniform(0, 1))))
        _, path = order_preserving_dp([1.0] * n, [1.0] * m, blocks)
        for a, b in itertools.pairwise(path):
            assert a[1] < b[0], path
            assert a[3] < b[2], path


def test_dp_reconsiders_previous_correspondence_for_a_split() -> None:
    """p ~ q1 alone is poor, p ~ (q1, q2) is good: the DP must find the 1:2 block."""
    blocks = {
        (0, 0): [(0, 0, 1.9)],  # p ~ q1: dissimilar
        (0, 1): [(0, 1, 1.9), (0, 0, 0.1)],  # p ~ q2 poor, p ~ q1+q2 good
    }
    total, path = order_preserving_dp([1.0], [1.0, 1.0], blocks)
    assert path == [(0, 0, 0, 1)]
    assert total == pytest.approx(0.1)


# --------------------------------------------------------------------------------------------
# match_configurations on synthetic configurations (real S*)
# --------------------------------------------------------------------------------------------


def _dense(vertices: np.ndarray, step: float = 0.02) -> np.ndarray:
    out = [vertices[0]]
    for a, b in itertools.pairwise(vertices):
        k = max(1, int(np.ceil(np.hypot(*(b - a)) / step)))
        t = np.linspace(0, 1, k + 1)[1:]
        out.extend(a + t[:, None] * (b - a))
    return np.array(out)


def _feature(vertices: list[list[float]], segments: bool) -> Feature:
    v = np.array(vertices, dtype=float)
    pts = _dense(v)
    start, span = angular_interval(pts, np.zeros(3))
    segs = np.hstack([v[:-1], v[1:]]) if segments else None
    return Feature(
        vertices=v,
        points=pts,
        bearing_start=start,
        bearing_end=float(np.arctan2(pts[-1, 1], pts[-1, 0])),
        angular_size=span,
        segments=segs,
    )


# A scene in front of a robot at the origin (map frame = robot frame, estimate = identity):
CORNER = [[3.0, -2.0], [3.0, 1.0], [1.0, 1.0]]  # right wall, corner, front-left wall
CORNER_A = [[3.0, -2.0], [3.0, 1.0]]
CORNER_B = [[3.0, 1.0], [1.0, 1.0]]
SHELF = [[0.9, 2.5], [0.2, 2.5], [0.2, 3.2]]  # a small corner further left
BOX = [[1.0, 1.6], [0.75, 1.8], [0.65, 1.6]]  # furniture between the two (scan only)


def _config(features: list[Feature], frame: str) -> Configuration:
    return Configuration(
        features=features,
        frame=frame,
        viewpoint=np.zeros(3),
        cyclic=frame == "map",
        fov=(-math.pi / 2, math.pi / 2) if frame == "robot" else (-math.pi, math.pi),
    )


CFG = ShapeConfig()


def test_match_finds_one_to_two_split_scan_side() -> None:
    P = _config(
        [_feature(CORNER_A, False), _feature(CORNER_B, False), _feature(SHELF, False)], "robot"
    )
    Q = _config([_feature(CORNER, True), _feature(SHELF, True)], "map")
    m = match_configurations(P, Q, np.zeros(3), CFG)
    assert [(x.scan, x.map) for x in m] == [((0, 1), (0,)), ((2,), (1,))]
    assert all(x.pose_consistency < 0.05 for x in m)


def test_match_finds_two_to_one_split_map_side() -> None:
    P = _config([_feature(CORNER, False), _feature(SHELF, False)], "robot")
    Q = _config([_feature(CORNER_A, True), _feature(CORNER_B, True), _feature(SHELF, True)], "map")
    m = match_configurations(P, Q, np.zeros(3), CFG)
    assert [(x.scan, x.map) for x in m] == [((0,), (0, 1)), ((1,), (2,))]


def test_match_leaves_furniture_unmatched() -> None:
    P = _config([_feature(CORNER, False), _feature(BOX, False), _feature(SHELF, False)], "robot")
    Q = _config([_feature(CORNER, True), _feature(SHELF, True)], "map")
    res = match_with_cost(P, Q, np.zeros(3), CFG)
    assert [(x.scan, x.map) for x in res.matches] == [((0,), (0,)), ((2,), (1,))]
    # the eq. 5 cost then contains exactly the box's penalty R (plus near-zero pair costs)
    r_box = CFG.penalty_weight * P.features[1].angular_size
    assert res.cost == pytest.approx(r_box, abs=0.05)


def test_match_under_displacement_still_pairs_the_right_shapes() -> None:
    """The robot moved 8 cm and turned 3 degrees since the estimate."""
    moved = np.array([0.08, -0.05, math.radians(3.0)])
    # scan features are the map features seen from the moved pose (robot frame)
    inv = invert(moved)
    scan = []
    for verts in (CORNER, SHELF):
        v = transform_points(inv, np.array(verts))
        scan.append(_feature(v.tolist(), False))
    P = _config(scan, "robot")
    Q = _config([_feature(CORNER, True), _feature(SHELF, True)], "map")
    res = match_with_cost(P, Q, np.zeros(3), CFG)
    # corner ~ corner and shelf ~ shelf (as two 1:1 pairs or as one joined 2:2 block)
    assert {i for x in res.matches for i in x.scan} == {0, 1}
    assert all(x.scan == x.map for x in res.matches)
    # each pair's induced pose is the true displacement
    for pose in res.induced:
        assert np.hypot(*(pose[:2] - moved[:2])) < 0.02
        assert abs(pose[2] - moved[2]) < math.radians(0.5)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_compiled_dp_agrees_with_the_python_reference_including_ties() -> None:
    rng = np.random.default_rng(41)
    for trial in range(300):
        n, m = int(rng.integers(0, 9)), int(rng.integers(0, 9))
        # integer costs: many ties, so the tie order of the kernel is checked too
        skip_p = rng.integers(0, 4, size=n).astype(float).tolist()
        skip_q = rng.integers(0, 4, size=m).astype(float).tolist()
        blocks: dict = {}
        for _ in range(int(rng.integers(0, 3 * (n + m) + 1))):
            if n == 0 or m == 0:
                break
            i_s, j_s = int(rng.integers(0, n)), int(rng.integers(0, m))
            i_e = min(n - 1, i_s + int(rng.integers(0, 3)))
            j_e = min(m - 1, j_s + int(rng.integers(0, 3)))
            c = float(rng.integers(0, 6)) if trial % 2 else float(rng.uniform(0, 5))
            blocks.setdefault((i_e, j_e), []).append((i_s, j_s, c))
        got = order_preserving_dp(skip_p, skip_q, blocks)
        ref = order_dp._order_preserving_dp_python(skip_p, skip_q, blocks)
        assert got[0] == ref[0]
        assert got[1] == ref[1]


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_grid_near_agrees_with_a_kd_tree() -> None:
    """The bucket-grid test behind support() and the heading sweep is exact."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(51)
    for tol in (0.1, 0.25, 0.03):
        feats = [
            _feature(np.cumsum(rng.uniform(-2, 2, size=(4, 2)), axis=0).tolist(), True)
            for _ in range(5)
        ]
        Q = _config(feats, "map")
        pts = np.vstack([f.points for f in Q.features])
        q = pts[rng.integers(0, len(pts), 3000)] + rng.normal(0, tol, size=(3000, 2))
        q = np.vstack([q, rng.uniform(-10, 10, size=(500, 2))])
        d, _ = cKDTree(pts).query(q, k=1, distance_upper_bound=tol)
        got = two_step._near(Q, q[:, 0], q[:, 1], tol)
        assert np.array_equal(got, np.isfinite(d))
        assert 0 < got.sum() < len(q)


# --------------------------------------------------------------------------------------------
# The matcher on real views: batched S* and cached per-scan / per-view arrays change nothing
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("setup_id", "scan"), [(2, 30), (2, 120), (1, 50)])
def test_batched_shape_distances_give_the_per_pair_match(
    setup_id: int, scan: int, real_scene: Callable
) -> None:
    """match_with_cost's one batched S* call (the default) and its per-pair loop (taken for
    an explicit shape cost, here the same gated S*) store the same S* for every block pair
    and return the same matches, eq. 5 cost and induced poses, bit for bit, from the truth,
    from the previous pose and from an estimate 0.2 m / 0.15 rad off."""
    sc = real_scene(setup_id, scan)
    P, Q, cfg, truth = sc.P, sc.Q, sc.config, sc.truth
    loop_cost = shape_cost.gated_shape_cost(cfg, cfg.max_shape_distance)
    off = truth[scan] + np.array([0.2, -0.1, 0.15])
    c1: dict = {}  # one cache over the estimates, as two_step_match keeps it for a scan
    c2: dict = {}
    for k, est in enumerate((truth[scan], truth[scan - 1], off)):
        got = match_with_cost(P, Q, est, cfg, cache=c1)
        ref = match_with_cost(P, Q, est, cfg, shape_cost=loop_cost, cache=c2)
        assert c1[("S2", id(P), id(Q))] == c2[("S2", id(P), id(Q))]
        assert got.cost == ref.cost
        assert got.matches == ref.matches and (k > 0 or len(got.matches) >= 3)
        assert all(np.array_equal(a, b) for a, b in zip(got.induced, ref.induced, strict=True))
    assert len(c1[("S2", id(P), id(Q))]) > 50  # block pairs whose S* was computed


def test_step1_batched_shape_distances_equal_the_per_pair_distances(
    monkeypatch: pytest.MonkeyPatch, real_scene: Callable
) -> None:
    """Step 1 computes all its S* in one call; replacing that call by per-pair S* of the
    joined units gives the same hypotheses and distances, bit for bit (schematic map)."""
    sc = real_scene(2, 60)
    P, Q, cfg, prior = sc.P, sc.Q, sc.config, sc.truth[59]
    got = two_step.step1_hypotheses(P, Q, prior, cfg, {})

    def per_pair(pv, po, pp, qv, qo, qp, **kw):  # type: ignore[no-untyped-def]
        def join(v, o, row):  # type: ignore[no-untyped-def]
            return np.vstack([v[o[f] : o[f + 1]] for f in row if f >= 0])

        pairs = zip(pp, qp, strict=True)
        return np.array([shape_distance(join(pv, po, a), join(qv, qo, b), **kw) for a, b in pairs])

    monkeypatch.setattr(shape_cost, "shape_distances", per_pair)
    Q.__dict__.pop("_step1_units", None)
    ref = two_step.step1_hypotheses(P, Q, prior, cfg, {})
    assert len(got) == len(ref) >= 4
    for (pg, sg), (pr, sr) in zip(got, ref, strict=True):
        assert sg == sr and np.array_equal(pg, pr)


@pytest.mark.parametrize("compiled", [True, False])
def test_stacked_matches_give_the_pose_of_the_matched_pairs(
    compiled: bool, real_scene: Callable, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The matcher's stacked pairs (one copy of all points and segments) give the pose fit of
    matched_pairs bit for bit, with its covariance when asked for; a pair without segments is
    left out as pose_from_matches leaves it out."""
    if compiled and not kernels.HAVE_NUMBA:
        pytest.skip("numba kernels not installed")
    monkeypatch.setattr(kernels, "HAVE_NUMBA", compiled)
    sc = real_scene(2, 90)
    P, Q, cfg, est = sc.P, sc.Q, sc.config, sc.truth[90] + np.array([0.05, -0.05, 0.02])
    res = match_with_cost(P, Q, est, cfg)
    assert len(res.matches) >= 3
    kw = {"iterations": 12, "inlier_distance": 0.4, "robust_scale": 0.08, "prior": sc.truth[89]}
    ref = pose_from_matches(matching.matched_pairs(P, Q, res.matches), est, **kw)
    stack = matching.matched_stack(P, Q, res.matches)
    got = pose_from_matches(stack, est, **kw)
    assert np.array_equal(got.pose, ref.pose) and got.rms == ref.rms
    assert got.inliers == ref.inliers and got.iterations == ref.iterations
    assert ref.covariance is not None and np.array_equal(got.covariance, ref.covariance)
    bare = pose_from_matches(stack, est, covariance=False, **kw)
    assert bare.covariance is None and np.array_equal(bare.pose, ref.pose)
    # a match whose map features carry no segments (a scan-only feature matched by hand)
    Q.features[res.matches[0].map[0]].segments = None
    one = [
        matching.Match(scan=m.scan, map=m.map[:1], shape_distance=0.0, pose_consistency=0.0)
        for m in res.matches
    ]
    s1 = matching.matched_stack(P, Q, one)
    assert len(s1.counts) == len(one) - 1
    a = pose_from_matches(s1, est, **kw)
    b = pose_from_matches(matching.matched_pairs(P, Q, one), est, **kw)
    assert np.array_equal(a.pose, b.pose) and a.inliers == b.inliers


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_grid_near_agrees_with_a_kd_tree_on_a_heading_sweep(real_scene: Callable) -> None:
    """The heading sweep's queries on a real view (scan points turned through 2.6 rad round
    the true pose, both support tolerances): the grid answers what a KD-tree answers."""
    from scipy.spatial import cKDTree

    sc = real_scene(2, 75)
    Q, pose = sc.Q, sc.truth[75]
    scan = np.vstack([f.points for f in sc.P.features])
    tree = cKDTree(np.vstack([f.points for f in Q.features]))
    for tol in (0.25, 0.1):
        for dth in np.arange(-1.3, 1.31, 0.05):
            q = transform_points(pose + np.array([0.0, 0.0, dth]), scan)
            d, _ = tree.query(q, k=1, distance_upper_bound=tol)
            assert np.array_equal(two_step._near(Q, q[:, 0], q[:, 1], tol), np.isfinite(d))
    q = transform_points(pose, scan)
    assert two_step._near(Q, q[:, 0], q[:, 1], 0.25).mean() > 0.3
