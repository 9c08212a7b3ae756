"""Pose estimation from matched pairs (service/core/pose.py). Runs in well under a second."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from service.core import kernels
from service.core import pose as pose_mod
from service.core.pose import (
    compose,
    invert,
    pose_from_matches,
    rigid_transform_2d,
    transform_points,
)
from service.errors import LocalizationError


def test_rigid_transform_recovers_synthetic_transform_exactly() -> None:
    rng = np.random.default_rng(1)
    src = rng.uniform(-5, 5, size=(50, 2))
    truth = np.array([1.234, -0.567, 0.789])
    dst = transform_points(truth, src)
    est = rigid_transform_2d(src, dst)
    assert np.allclose(est, truth, atol=1e-9)


def test_rigid_transform_weights_ignore_outliers_with_zero_weight() -> None:
    rng = np.random.default_rng(2)
    src = rng.uniform(-3, 3, size=(30, 2))
    truth = np.array([-0.3, 0.2, -1.1])
    dst = transform_points(truth, src)
    dst[:5] += 10.0  # gross outliers
    w = np.ones(30)
    w[:5] = 0.0
    assert np.allclose(rigid_transform_2d(src, dst, w), truth, atol=1e-9)


def test_rigid_transform_never_reflects() -> None:
    src = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 2.0]])
    dst = src * np.array([1.0, -1.0])  # mirror image: no rotation reproduces it
    est = rigid_transform_2d(src, dst)
    # a proper rotation: transformed source keeps its orientation (positive signed area)
    t = transform_points(est, src)
    u, v = t[1] - t[0], t[2] - t[0]
    area = u[0] * v[1] - u[1] * v[0]
    assert area > 0


def test_rigid_transform_rejects_bad_input() -> None:
    with pytest.raises(LocalizationError, match="differ"):
        rigid_transform_2d(np.zeros((3, 2)), np.zeros((4, 2)))
    with pytest.raises(LocalizationError, match="no points"):
        rigid_transform_2d(np.zeros((0, 2)), np.zeros((0, 2)))
    with pytest.raises(LocalizationError, match="non-finite"):
        rigid_transform_2d(np.full((2, 2), np.nan), np.zeros((2, 2)))
    with pytest.raises(LocalizationError, match="weights"):
        rigid_transform_2d(np.zeros((2, 2)), np.zeros((2, 2)), np.array([1.0, -1.0]))


def test_compose_and_invert_are_consistent() -> None:
    a = np.array([1.0, 2.0, 0.5])
    b = np.array([-0.4, 0.3, -2.0])
    p = np.array([[0.7, -0.2]])
    assert np.allclose(
        transform_points(compose(a, b), p), transform_points(a, transform_points(b, p))
    )
    assert np.allclose(compose(a, invert(a)), np.zeros(3), atol=1e-12)


def test_pose_from_matches_recovers_pose_within_1mm_and_005deg(room_pairs: Callable) -> None:
    rng = np.random.default_rng(3)
    truth = np.array([2.5, 1.7, 0.6])
    pairs = room_pairs(truth, rng, noise=0.0)
    start = truth + np.array([0.15, -0.12, 0.08])  # 15 cm / 4.6 deg off
    fit = pose_from_matches(pairs, start)
    assert np.hypot(*(fit.pose[:2] - truth[:2])) < 1e-3
    assert abs(np.rad2deg(fit.pose[2] - truth[2])) < 0.05
    assert fit.rms < 1e-3
    assert fit.inlier_fraction == 1.0
    assert fit.covariance is not None and fit.covariance.shape == (3, 3)


def test_pose_from_matches_with_1cm_noise_stays_within_3mm(room_pairs: Callable) -> None:
    rng = np.random.default_rng(4)
    truth = np.array([3.0, 2.0, -0.4])
    pairs = room_pairs(truth, rng, noise=0.01)
    fit = pose_from_matches(pairs, truth + np.array([-0.1, 0.1, -0.05]))
    assert np.hypot(*(fit.pose[:2] - truth[:2])) < 3e-3
    assert abs(np.rad2deg(fit.pose[2] - truth[2])) < 0.1
    assert 0.005 < fit.rms < 0.02


def test_pose_from_matches_uses_each_pair_only_with_its_own_segments(room_pairs: Callable) -> None:
    """A scan wall paired with the WRONG wall pulls the pose there: pairs are not mixed."""
    rng = np.random.default_rng(5)
    truth = np.array([2.0, 2.0, 0.0])
    pairs = room_pairs(truth, rng, noise=0.0)
    # Swap the segments of the bottom and top walls (parallel, 4 m apart).
    bad = [(pairs[0][0], pairs[2][1]), pairs[1], (pairs[2][0], pairs[0][1])]
    fit = pose_from_matches(bad, truth, inlier_distance=10.0, robust_scale=10.0)
    good = pose_from_matches(pairs, truth)
    assert np.hypot(*(good.pose[:2] - truth[:2])) < 1e-6
    assert np.hypot(*(fit.pose[:2] - truth[:2])) > 0.5


def test_pose_from_matches_rejects_empty_pairs() -> None:
    with pytest.raises(LocalizationError, match="no matched pair"):
        pose_from_matches([(np.zeros((0, 2)), np.zeros((1, 4)))], np.zeros(3))


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_compiled_pose_from_matches_agrees_with_the_numpy_reference(random_pairs: Callable) -> None:
    rng = np.random.default_rng(12)
    well_posed = 0
    for trial in range(20):
        pairs = random_pairs(rng, int(rng.integers(1, 8)))
        start = rng.normal(0, 0.05, size=3)
        kw = {"prior": np.zeros(3), "prior_weight": 2.0} if trial % 3 == 0 else {}
        ref = pose_mod._pose_from_matches_numpy(pairs, start, robust_scale=0.05, **kw)
        got = pose_from_matches(pairs, start, robust_scale=0.05, **kw)
        assert np.allclose(got.pose, ref.pose, rtol=0, atol=1e-9)
        assert got.inliers == ref.inliers and got.iterations == ref.iterations
        assert abs(got.rms - ref.rms) < 1e-9
        assert (got.covariance is None) == (ref.covariance is None)
        if ref.covariance is not None:
            # A lone straight wall leaves H singular to rounding (condition ~1e15): its
            # inverse along the unconstrained direction is noise (numba and numpy inverting
            # equal H differed by 50 % there, at 1e11 m^2, and even in sign). Well-posed fits
            # must agree; degenerate ones must both report the unconstrained direction as such,
            # a variance of huge magnitude.
            if np.linalg.cond(ref.covariance) < 1e8:
                scale = float(np.abs(ref.covariance).max())
                assert np.allclose(got.covariance, ref.covariance, rtol=0, atol=1e-6 * scale)
                well_posed += 1
            else:
                for cov in (got.covariance, ref.covariance):
                    assert np.abs(np.linalg.eigvalsh(0.5 * (cov + cov.T))).max() > 1e6
    assert well_posed >= 10
