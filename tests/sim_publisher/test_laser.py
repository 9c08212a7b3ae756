"""Laser simulator: beam geometry, determinism by (seed, index), noise and dropout rates."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.errors import InvalidMessage
from sim_publisher.laser import LaserConfig, LaserSimulator


def _room() -> np.ndarray:
    c = np.array([[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]], dtype=float)
    return np.hstack([c[:-1], c[1:]])


def test_default_beam_geometry() -> None:
    sim = LaserSimulator(_room())
    assert sim.angles.shape == (361,)
    assert sim.angle_min == pytest.approx(-math.pi / 2)
    assert sim.angle_increment == pytest.approx(math.pi / 360)
    assert sim.angles[-1] == pytest.approx(math.pi / 2)
    full = LaserSimulator(_room(), LaserConfig(beams=360, fov=2 * math.pi))
    assert full.angle_increment == pytest.approx(2 * math.pi / 360)


def test_scan_is_deterministic_by_seed_and_index() -> None:
    pose = np.array([3.0, 4.0, 0.3])
    a = LaserSimulator(_room(), seed=5).scan(pose, 17)
    b = LaserSimulator(_room(), seed=5).scan(pose, 17)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    c = LaserSimulator(_room(), seed=5).scan(pose, 18)[0]
    d = LaserSimulator(_room(), seed=6).scan(pose, 17)[0]
    assert not np.array_equal(a[0], c, equal_nan=True)
    assert not np.array_equal(a[0], d, equal_nan=True)


def test_noise_and_dropout_rates_match_config() -> None:
    cfg = LaserConfig(beams=2000, fov=2 * math.pi, noise_sigma=0.02, dropout=0.1)
    sim = LaserSimulator(_room(), cfg, seed=1)
    pose = np.array([5.0, 5.0, 0.0])
    exact = sim.exact(pose)
    assert not np.any(np.isnan(exact))
    err, drops = [], 0
    for i in range(10):
        r, _ = sim.scan(pose, i)
        drops += int(np.isnan(r).sum())
        err.append((r - exact)[~np.isnan(r)])
    e = np.concatenate(err)
    assert drops / 20000 == pytest.approx(0.1, abs=0.015)
    assert np.std(e) == pytest.approx(0.02, rel=0.05)
    assert abs(np.mean(e)) < 0.001


def test_out_of_range_is_nan() -> None:
    cfg = LaserConfig(beams=3, fov=math.pi, max_range=4.0, noise_sigma=0.0, dropout=0.0)
    r, _ = LaserSimulator(_room(), cfg).scan(np.array([2.0, 5.0, 0.0]), 0)
    # right beam: 5 m to y=0 -> beyond 4 m; forward: 8 m; left: 5 m
    assert np.all(np.isnan(r))
    r, _ = LaserSimulator(_room(), cfg).scan(np.array([7.0, 5.0, 0.0]), 0)
    assert r[1] == pytest.approx(3.0) and np.isnan(r[0]) and np.isnan(r[2])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"beams": 1}, "beams must be in"),
        ({"beams": 3.5}, "beams must be an integer"),
        ({"fov": 0.0}, "fov"),
        ({"fov": 7.0}, "fov"),
        ({"max_range": float("nan")}, "max_range must be a finite"),
        ({"range_min": 20.0}, "range_min < max_range"),
        ({"noise_sigma": -0.1}, "noise_sigma"),
        ({"dropout": 1.0}, "dropout"),
    ],
)
def test_config_validation(kwargs: dict, match: str) -> None:
    with pytest.raises(InvalidMessage, match=match):
        LaserConfig(**kwargs)


def test_moving_circles_are_seen_exactly_and_only_in_that_scan() -> None:
    cfg = LaserConfig(beams=361, noise_sigma=0.0, dropout=0.0)
    sim = LaserSimulator(_room(), cfg)
    pose = np.array([2.0, 5.0, 0.0])
    static = sim.exact(pose)
    person = np.array([[5.0, 5.0, 0.5]])
    seen = sim.exact(pose, person)
    assert seen[180] == pytest.approx(2.5, abs=1e-12)  # straight ahead: 3 m minus the radius
    # every changed beam ends on the circle, every other beam is the static range
    changed = ~np.isclose(seen, static)
    assert changed.sum() == np.sum(np.abs(sim.angles) < math.asin(0.5 / 3.0))  # 19.2 deg
    ang = sim.angles[changed]
    hits = pose[:2] + seen[changed, None] * np.c_[np.cos(ang), np.sin(ang)]
    np.testing.assert_allclose(np.hypot(*(hits - person[0, :2]).T), 0.5, atol=1e-9)
    np.testing.assert_array_equal(seen[~changed], static[~changed])
    # no circles, an empty array, a circle around the sensor, one behind a wall: static ranges
    np.testing.assert_array_equal(sim.exact(pose, None), static)
    np.testing.assert_array_equal(sim.exact(pose, np.zeros((0, 3))), static)
    np.testing.assert_array_equal(sim.exact(pose, np.array([[2.1, 5.0, 0.3]])), static)
    np.testing.assert_array_equal(sim.exact(pose, np.array([[12.0, 5.0, 0.5]])), static)
    # a circle fills a beam that saw nothing within max_range
    short = LaserSimulator(_room(), LaserConfig(max_range=4.0, noise_sigma=0.0, dropout=0.0))
    r = short.exact(pose, person)
    assert np.isnan(short.exact(pose)[180]) and r[180] == pytest.approx(2.5)


def test_noisy_scans_with_circles_share_the_static_noise_draws() -> None:
    sim = LaserSimulator(_room(), seed=3)
    pose = np.array([2.0, 5.0, 0.2])
    person = np.array([[5.0, 5.5, 0.3]])
    plain, _ = sim.scan(pose, 9)
    busy, _ = sim.scan(pose, 9, person)
    hit = ~np.isclose(sim.exact(pose, person), sim.exact(pose))
    np.testing.assert_array_equal(np.isnan(plain), np.isnan(busy))  # same dropouts
    np.testing.assert_array_equal(plain[~hit], busy[~hit])
    assert np.nanmax(np.abs(busy[hit] - plain[hit])) > 1.0
