"""Batched S* (service/core/kernels/shape.py behind similarity.shape_distances): many pairs
of joined polylines in one call give exactly the per-pair S*, on the real scan and map-view
polylines of the schematic floor plan (setup 2) and of the metric map (setup 1).

Runs in a few seconds.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import numpy as np
import pytest

from service.core import kernels
from service.core.kernels import matching as matching_kernels
from service.core.shapes import similarity as sim
from service.core.shapes.configuration import Configuration
from service.core.shapes.similarity import shape_distance, shape_distances
from service.errors import LocalizationError


def _stack(C: Configuration) -> tuple[np.ndarray, np.ndarray]:
    v = np.vstack([f.vertices for f in C.features])
    off = np.concatenate(([0], np.cumsum([len(f.vertices) for f in C.features])))
    return v, off


def _runs(n: int, k: int, cyclic: bool) -> list[tuple[int, ...]]:
    """Every run of 1..k consecutive features (wrapping round when ``cyclic``)."""
    last = n if cyclic else n - k + 1
    out = [tuple(range(i, i + 1)) for i in range(n)]
    for w in range(2, k + 1):
        out += [tuple((i + t) % n for t in range(w)) for i in range(max(last, 0))]
    return out


def _pieces(runs: list[tuple[int, ...]], k: int) -> np.ndarray:
    return np.array([(*r, *([-1] * (k - len(r)))) for r in runs], dtype=np.intp)


def _joined(C: Configuration, run: tuple[int, ...]) -> np.ndarray:
    return np.vstack([C.features[i].vertices for i in run])


@pytest.mark.parametrize(("setup_id", "scan"), [(2, 5), (2, 100), (1, 10)])
def test_batched_shape_distances_equal_the_per_pair_distance(
    setup_id: int, scan: int, real_scene: Callable
) -> None:
    """All runs of up to 3 scan features against all runs of up to 3 view features (view runs
    wrapping round the 360-degree view; 660-2400 pairs), with the configuration's
    partial-matching weights, unbounded, at the matcher's gate and at a tight bound that
    prunes: every batched value is the per-pair S* to the bit."""
    sc = real_scene(setup_id, scan)
    P, Q, cfg = sc.P, sc.Q, sc.config
    assert len(P) >= 5 and len(Q) >= 10
    pr, qr = _runs(len(P), 3, False), _runs(len(Q), 3, True)
    pairs = list(itertools.product(range(len(pr)), range(len(qr))))
    pp = _pieces([pr[a] for a, _ in pairs], 3)
    qp = _pieces([qr[b] for _, b in pairs], 3)
    pv, po = _stack(P)
    qv, qo = _stack(Q)
    kw = {"end_weight": cfg.shape_end_weight, "skip_weight": cfg.shape_skip_weight}
    for bound in (math.inf, math.nextafter(cfg.max_shape_distance, math.inf), 0.3):
        got = shape_distances(pv, po, pp, qv, qo, qp, upper_bound=bound, **kw)
        ref = np.array(
            [
                shape_distance(_joined(P, pr[a]), _joined(Q, qr[b]), upper_bound=bound, **kw)
                for a, b in pairs
            ]
        )
        assert got.shape == (len(pairs),)
        assert np.array_equal(got, ref)
        finite = np.isfinite(ref)
        assert finite.all() if bound == math.inf else np.all(ref[finite] < bound)
        if bound == 0.3:  # pruned: some pairs come back as inf, some below the bound
            assert 0 < finite.sum() < len(ref)


def test_batched_shape_distances_reference_agrees_with_the_kernel(
    monkeypatch: pytest.MonkeyPatch, real_scene: Callable
) -> None:
    """The numpy / Python reference (what runs without numba) gives the same distances as
    the compiled call, to rounding (the Python S* uses CPython's math, the kernel libm)."""
    sc = real_scene(2, 20)
    P, Q, cfg = sc.P, sc.Q, sc.config
    pr, qr = _runs(len(P), 2, False), _runs(len(Q), 2, True)
    pairs = list(itertools.product(range(len(pr)), range(len(qr))))[::3]
    pp = _pieces([pr[a] for a, _ in pairs], 2)
    qp = _pieces([qr[b] for _, b in pairs], 2)
    pv, po = _stack(P)
    qv, qo = _stack(Q)
    kw = {"end_weight": cfg.shape_end_weight, "skip_weight": cfg.shape_skip_weight}
    compiled = shape_distances(pv, po, pp, qv, qo, qp, **kw)
    monkeypatch.setattr(sim.kernels, "HAVE_NUMBA", False)
    ref = shape_distances(pv, po, pp, qv, qo, qp, **kw)
    assert ref.shape == compiled.shape == (len(pairs),)
    assert np.allclose(ref, compiled, rtol=1e-12, atol=1e-12)
    assert np.all(ref > 0.0) and np.ptp(ref) > 0.3  # real, varied distances


@pytest.mark.parametrize("compiled", [True, False])
def test_batched_shape_distances_check_their_polylines(
    compiled: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    if compiled and not kernels.HAVE_NUMBA:
        pytest.skip("numba kernels not installed")
    monkeypatch.setattr(sim.kernels, "HAVE_NUMBA", compiled)
    v = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [5.0, 5.0], [5.0, 5.0], [0.0, np.nan]])
    off = np.array([0, 3, 5, 6])  # piece 0 a corner, 1 two equal points, 2 one non-finite
    one = np.array([[0]])
    # the corner against itself and against itself joined with a repeated vertex
    got = shape_distances(v, off, np.array([[0, -1], [0, -1]]), v, off, np.array([[0, -1], [0, 1]]))
    assert got[0] == 0.0 and got[1] == pytest.approx(shape_distance(v[:5], v[:3]))
    with pytest.raises(LocalizationError, match="zero length"):
        shape_distances(v, off, np.array([[1]]), v, off, one)
    with pytest.raises(LocalizationError, match="non-finite"):
        shape_distances(v, off, one, v, off, np.array([[0, 2]]))
    with pytest.raises(LocalizationError, match="k >= 2"):
        shape_distances(v, off, np.array([[-1]]), v, off, one)
    with pytest.raises(LocalizationError, match="pieces"):
        shape_distances(v, off, np.array([0]), v, off, one)
    empty = np.zeros((0, 2), dtype=np.intp)
    assert shape_distances(v, off, empty, v, off, empty).shape == (0,)


# --------------------------------------------------------------------------------------------
# The other batch kernels of match_with_cost and step 1, against their numpy references
# --------------------------------------------------------------------------------------------


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
@pytest.mark.parametrize(("setup_id", "scan"), [(2, 50), (1, 70)])
def test_interval_gates_and_block_pieces_equal_the_numpy_expressions(
    setup_id: int, scan: int, real_scene: Callable
) -> None:
    """The scan / view interval tests (both field-of-view cases) and the blocks' features and
    S* keys of match_with_cost: the kernels give the numpy reference's values exactly."""
    from service.core.kernels import shape as sk
    from service.core.shapes import matching, stacked

    sc = real_scene(setup_id, scan)
    P, Q, cfg = sc.P, sc.Q, sc.config
    est = sc.truth[scan] + np.array([0.1, 0.05, -0.1])
    q_ord, q_iv = matching._map_order_arrays(Q, est)
    qiv = q_iv[q_ord].reshape(-1, 2)
    piv = stacked.scan_intervals(P)
    for lo, hi in (P.fov, (-math.pi, math.pi), (-0.3, 2.0)):
        for tol in (cfg.bearing_gate, cfg.fast_bearing_gate, 0.0):
            single, inside = sk.interval_gates(piv, qiv, tol, lo, hi)
            assert np.array_equal(single, matching._single_overlaps(piv, qiv, tol))
            assert np.array_equal(inside, matching._overlaps(qiv[:, 0], qiv[:, 1], lo, hi))
    assert 0 < single.sum() < single.size and np.ptp(inside) > 0
    K, M, m = cfg.max_join, len(Q.features) + 1, len(q_ord)
    cs = matching_kernels.block_candidates(np.ones((len(P), m), dtype=bool), K, cfg.join_total)
    pp, qp, keys = sk.block_pieces(cs, q_ord, K, M)
    steps = np.arange(K)
    want_p = np.where(steps <= cs[:, 1:2] - cs[:, 0:1], cs[:, 0:1] + steps, -1)
    want_q = np.where(
        steps <= cs[:, 3:4] - cs[:, 2:3], q_ord[np.minimum(cs[:, 2:3] + steps, m - 1)], -1
    )
    qkey = (want_q.astype(np.int64) + 1) @ (M ** steps.astype(np.int64))
    want_k = (cs[:, 0] * K + (cs[:, 1] - cs[:, 0])) * (M**K) + qkey
    assert np.array_equal(pp, want_p) and np.array_equal(qp, want_q)
    assert np.array_equal(keys, want_k) and len(set(keys.tolist())) == len(cs)
