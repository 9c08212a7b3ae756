"""Many candidate poses fitted at once (service/core/sensor/pose_batch.py): each pair alone, and the
compiled kernels against the numpy reference."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from service.core import kernels
from service.core.kernels import matching as matching_kernels
from service.core.sensor import pose_batch
from service.core.sensor.pose_batch import fit_pairs


def test_fit_pairs_fits_each_pair_independently(room_pairs: Callable) -> None:
    rng = np.random.default_rng(6)
    truth = np.array([1.0, 1.0, 0.3])
    pairs = room_pairs(truth, rng, noise=0.0)
    corner_pts = np.vstack([pairs[0][0], pairs[1][0]])
    corner_segs = np.vstack([pairs[0][1], pairs[1][1]])
    # pair 0: a corner (fully observable); pair 1: the same corner shifted by 0.5 m in x.
    shifted = corner_segs + np.array([0.5, 0.0, 0.5, 0.0])
    start = truth + np.array([0.05, -0.05, 0.03])
    poses, rms = fit_pairs(
        [corner_pts, corner_pts], [corner_segs, shifted], start, iterations=15, damping=1e-4
    )
    assert np.allclose(poses[0], truth, atol=2e-3)
    assert np.allclose(poses[1], truth + np.array([0.5, 0.0, 0.0]), atol=2e-3)
    assert np.all(rms < 5e-3)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_compiled_fit_pairs_agrees_with_the_numpy_reference(random_pairs: Callable) -> None:
    rng = np.random.default_rng(11)
    for trial in range(20):
        pairs = random_pairs(rng, int(rng.integers(1, 12)))
        pts = [p for p, _ in pairs]
        segs = [s for _, s in pairs]
        init = rng.normal(0, 0.05, size=(len(pairs), 3)) if trial % 2 else np.zeros(3)
        counts = [len(p) for p in pts]
        own = np.repeat(np.arange(len(pts)), counts)
        smax = max(len(s) for s in segs)
        Sg = np.zeros((len(segs), smax, 4))
        valid = np.zeros((len(segs), smax), dtype=bool)
        for k, s in enumerate(segs):
            Sg[k, : len(s)] = s
            valid[k, : len(s)] = True
        ref = pose_batch._fit_pairs_stacked_numpy(
            np.vstack(pts), own, Sg, valid, init, iterations=3, robust_scale=0.1, damping=0.05
        )
        got = fit_pairs(pts, segs, init, iterations=3, robust_scale=0.1, damping=0.05)
        assert np.allclose(got[0], ref[0], rtol=0, atol=1e-9)
        assert np.allclose(got[1], ref[1], rtol=0, atol=1e-9)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
@pytest.mark.parametrize(("setup_id", "scan"), [(2, 40), (1, 80)])
def test_compiled_fit_of_real_candidate_blocks_agrees_with_the_numpy_reference(
    setup_id: int, scan: int, real_scene: Callable, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The ΔA fits of every block of up to 3 features (1:1, 1:2, 2:1, ...) of a real scan
    against its map view, as match_with_cost forms them (sampled scan points, the blocks'
    map segments): the compiled kernel, which tries each segment for all points of a block at
    once, and the numpy reference agree to 1e-9, from the truth and from a pose 0.3 m /
    0.2 rad off (schematic floor plan and metric map)."""
    from service.core.shapes import matching, stacked

    sc = real_scene(setup_id, scan)
    P, Q, cfg = sc.P, sc.Q, sc.config
    p_all, p_off = stacked.scan_samples(P, max(3, cfg.align_points // 2))
    for est in (sc.truth[scan], sc.truth[scan] + np.array([0.3, -0.2, 0.2])):
        q_ord, _ = matching._map_order_arrays(Q, est)
        q_all, q_off = stacked.view_segments(Q, q_ord)
        ca = matching_kernels.block_candidates(np.ones((len(P), len(q_ord)), dtype=bool), 3, True)
        assert len(ca) > 200
        args = (p_all, p_off[ca[:, 0]], p_off[ca[:, 1] + 1], q_all)
        seg = (q_off[ca[:, 2]], q_off[ca[:, 3] + 1] - q_off[ca[:, 2]])
        kw = {"iterations": 3, "robust_scale": cfg.align_robust_scale, "damping": 0.05}
        got = pose_batch.fit_pairs_ranges(*args, *seg, est, **kw)
        with monkeypatch.context() as m:
            m.setattr(pose_batch.kernels, "HAVE_NUMBA", False)
            ref = pose_batch.fit_pairs_ranges(*args, *seg, est, **kw)
        assert np.allclose(got[0], ref[0], rtol=0, atol=1e-9)
        assert np.allclose(got[1], ref[1], rtol=0, atol=1e-9)
        moved = np.hypot(got[0][:, 0] - est[0], got[0][:, 1] - est[1])
        assert np.ptp(moved) > 0.1  # real fits: the blocks pull the pose different ways
