"""Pose estimation from matched pairs (service/core/pose.py). Runs in well under a second."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.errors import LocalizationError
from service.core.pose import (
    compose,
    fit_pairs,
    invert,
    pose_from_matches,
    rigid_transform_2d,
    transform_points,
)


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


def _room_pairs(truth: np.ndarray, rng: np.random.Generator, noise: float):
    """Scan points (robot frame) of three walls of a 6 x 4 m room, paired with the walls."""
    walls = [
        np.array([[0.0, 0.0, 6.0, 0.0]]),
        np.array([[6.0, 0.0, 6.0, 4.0]]),
        np.array([[6.0, 4.0, 0.0, 4.0]]),
    ]
    inv = invert(truth)
    pairs = []
    for w in walls:
        t = rng.uniform(0.05, 0.95, size=40)
        pts = w[0, :2] + t[:, None] * (w[0, 2:] - w[0, :2])
        pts = pts + rng.normal(0.0, noise, size=pts.shape)
        pairs.append((transform_points(inv, pts), w))
    return pairs


def test_pose_from_matches_recovers_pose_within_1mm_and_005deg() -> None:
    rng = np.random.default_rng(3)
    truth = np.array([2.5, 1.7, 0.6])
    pairs = _room_pairs(truth, rng, noise=0.0)
    start = truth + np.array([0.15, -0.12, 0.08])  # 15 cm / 4.6 deg off
    fit = pose_from_matches(pairs, start)
    assert np.hypot(*(fit.pose[:2] - truth[:2])) < 1e-3
    assert abs(np.rad2deg(fit.pose[2] - truth[2])) < 0.05
    assert fit.rms < 1e-3
    assert fit.inlier_fraction == 1.0
    assert fit.covariance is not None and fit.covariance.shape == (3, 3)


def test_pose_from_matches_with_1cm_noise_stays_within_3mm() -> None:
    rng = np.random.default_rng(4)
    truth = np.array([3.0, 2.0, -0.4])
    pairs = _room_pairs(truth, rng, noise=0.01)
    fit = pose_from_matches(pairs, truth + np.array([-0.1, 0.1, -0.05]))
    assert np.hypot(*(fit.pose[:2] - truth[:2])) < 3e-3
    assert abs(np.rad2deg(fit.pose[2] - truth[2])) < 0.1
    assert 0.005 < fit.rms < 0.02


def test_pose_from_matches_uses_each_pair_only_with_its_own_segments() -> None:
    """A scan wall paired with the WRONG wall pulls the pose there: pairs are not mixed."""
    rng = np.random.default_rng(5)
    truth = np.array([2.0, 2.0, 0.0])
    pairs = _room_pairs(truth, rng, noise=0.0)
    # Swap the segments of the bottom and top walls (parallel, 4 m apart).
    bad = [(pairs[0][0], pairs[2][1]), pairs[1], (pairs[2][0], pairs[0][1])]
    fit = pose_from_matches(bad, truth, inlier_distance=10.0, robust_scale=10.0)
    good = pose_from_matches(pairs, truth)
    assert np.hypot(*(good.pose[:2] - truth[:2])) < 1e-6
    assert np.hypot(*(fit.pose[:2] - truth[:2])) > 0.5


def test_pose_from_matches_rejects_empty_pairs() -> None:
    with pytest.raises(LocalizationError, match="no matched pair"):
        pose_from_matches([(np.zeros((0, 2)), np.zeros((1, 4)))], np.zeros(3))


def test_fit_pairs_fits_each_pair_independently() -> None:
    rng = np.random.default_rng(6)
    truth = np.array([1.0, 1.0, 0.3])
    pairs = _room_pairs(truth, rng, noise=0.0)
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
