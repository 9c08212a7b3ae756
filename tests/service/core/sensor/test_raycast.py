"""Exact ray casting: hand-computed ranges, circles, no-hit NaN, agreement with brute force."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.sensor.raycast import RayCaster
from service.errors import LocalizationError


def _square(x0: float, y0: float, x1: float, y1: float) -> np.ndarray:
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]])
    return np.hstack([c[:-1], c[1:]])


def _brute(seg: np.ndarray, pose: np.ndarray, angles: np.ndarray, max_range: float) -> np.ndarray:
    out = np.full(len(angles), np.nan)
    for i, a in enumerate(angles):
        d = np.array([np.cos(a + pose[2]), np.sin(a + pose[2])])
        best = np.inf
        for s in seg:
            e = s[2:] - s[:2]
            w = s[:2] - pose[:2]
            den = d[0] * e[1] - d[1] * e[0]
            if den == 0:
                continue
            t = (w[0] * e[1] - w[1] * e[0]) / den
            u = (w[0] * d[1] - w[1] * d[0]) / den
            if 0 <= t <= max_range and 0 <= u <= 1:
                best = min(best, t)
        if np.isfinite(best):
            out[i] = best
    return out


def test_square_room_hand_computed_ranges() -> None:
    rc = RayCaster(_square(0, 0, 4, 4))
    pose = np.array([1.0, 1.5, 0.0])
    ang = np.deg2rad([0, 45, 90, 135, 180, -90, -45])
    r = rc.cast(pose, ang, 10.0)
    s2 = np.sqrt(2.0)
    expected = [3.0, 2.5 * s2, 2.5, 1.0 * s2, 1.0, 1.5, 1.5 * s2]
    np.testing.assert_allclose(r, expected, rtol=0, atol=1e-12)


def test_rotated_pose_rotates_beams() -> None:
    rc = RayCaster(_square(0, 0, 4, 4))
    # Facing +y: the forward beam hits the top wall (2.5 m), left beam (+90) the west wall.
    r = rc.cast(np.array([1.0, 1.5, np.pi / 2]), np.deg2rad([0, 90, -90, 180]), 10.0)
    np.testing.assert_allclose(r, [2.5, 1.0, 3.0, 1.5], atol=1e-12)


def test_circle_range_within_polygonisation_error() -> None:
    n, rad, c = 64, 0.4, np.array([3.0, 2.0])
    a = np.linspace(0, 2 * np.pi, n + 1)
    ring = c + rad * np.c_[np.cos(a), np.sin(a)]
    rc = RayCaster(np.hstack([ring[:-1], ring[1:]]))
    pose = np.array([0.5, 2.0, 0.0])
    beams = np.deg2rad(np.linspace(-5, 5, 21))
    r = rc.cast(pose, beams, 10.0)
    # True circle: distance along beam b to a circle at distance D straight ahead.
    D = 2.5
    disc = rad**2 - (D * np.sin(beams)) ** 2
    true = D * np.cos(beams) - np.sqrt(np.where(disc > 0, disc, np.nan))
    hit = np.isfinite(true)
    assert hit.sum() >= 9
    tol = rad * (1 - np.cos(np.pi / n)) / np.cos(np.deg2rad(5)) + 1e-9
    np.testing.assert_array_less(np.abs(r[hit] - true[hit]), tol * 3)
    assert abs(r[10] - (D - rad)) <= rad * (1 - np.cos(np.pi / n)) + 1e-12


def test_no_hit_and_max_range_give_nan() -> None:
    rc = RayCaster(np.array([[2.0, -1.0, 2.0, 1.0]]))
    r = rc.cast(np.zeros(3), np.array([0.0, np.pi, np.pi / 2]), 10.0)
    assert r[0] == pytest.approx(2.0)
    assert np.isnan(r[1]) and np.isnan(r[2])
    assert np.all(np.isnan(rc.cast(np.zeros(3), np.array([0.0]), 1.5)))
    assert rc.cast(np.zeros(3), np.array([0.0]), 2.0)[0] == pytest.approx(2.0)


def test_nearest_of_several_segments_and_wrapped_unsorted_angles() -> None:
    seg = np.array([[3.0, -1.0, 3.0, 1.0], [1.0, -1.0, 1.0, 1.0], [-2.0, -1.0, -2.0, 1.0]])
    rc = RayCaster(seg)
    ang = np.array([np.pi, 0.0, 2 * np.pi, -np.pi, 4 * np.pi + 0.1])
    r = rc.cast(np.zeros(3), ang, 10.0)
    np.testing.assert_allclose(r[:4], [2.0, 1.0, 1.0, 2.0], atol=1e-12)
    assert r[4] == pytest.approx(1.0 / np.cos(0.1))


@pytest.mark.parametrize("seed", range(12))
def test_matches_brute_force_on_random_segments(seed: int) -> None:
    rng = np.random.default_rng(seed)
    seg = rng.uniform(-5, 5, (40, 4))
    pose = np.array([*rng.uniform(-3, 3, 2), rng.uniform(-np.pi, np.pi)])
    ang = rng.uniform(-4, 4, 90) if seed % 2 else np.linspace(-np.pi, np.pi, 181)
    max_range = float(rng.uniform(1, 8))
    got = RayCaster(seg).cast(pose, ang, max_range)
    want = _brute(seg, pose, ang, max_range)
    np.testing.assert_array_equal(np.isnan(got), np.isnan(want))
    np.testing.assert_allclose(got[~np.isnan(got)], want[~np.isnan(want)], atol=1e-9)


def test_shared_vertex_is_hit() -> None:
    rc = RayCaster(_square(-1, -1, 1, 1))
    r = rc.cast(np.zeros(3), np.deg2rad([45.0, 135.0, -135.0, -45.0]), 5.0)
    np.testing.assert_allclose(r, np.sqrt(2.0), atol=1e-12)


def test_rejects_bad_input() -> None:
    with pytest.raises(LocalizationError, match=r"shape \(s, 4\)"):
        RayCaster(np.zeros((3, 3)))
    with pytest.raises(LocalizationError, match="non-finite"):
        RayCaster(np.array([[0.0, 0.0, np.nan, 1.0]]))
    rc = RayCaster(_square(0, 0, 1, 1))
    with pytest.raises(LocalizationError, match="pose"):
        rc.cast(np.zeros(2), np.zeros(3), 1.0)
    with pytest.raises(LocalizationError, match="max_range"):
        rc.cast(np.zeros(3), np.zeros(3), -1.0)
    with pytest.raises(LocalizationError, match="non-finite"):
        rc.cast(np.zeros(3), np.array([np.inf]), 1.0)


def test_sensor_on_a_segment_or_at_its_end_point() -> None:
    # Sensor on the segment's interior: every non-collinear beam hits it at range 0.
    rc = RayCaster(np.array([[-1.0, 0.0, 1.0, 0.0], [-1.0, 2.0, 1.0, 2.0]]))
    r = rc.cast(np.zeros(3), np.deg2rad([90.0, -90.0, 45.0]), 5.0)
    np.testing.assert_allclose(r, [0.0, 0.0, 0.0])
    # Sensor at a segment's end point: beams that leave the segment see the other one.
    rc = RayCaster(np.array([[0.0, 0.0, 1.0, 1.0], [-1.0, 2.0, 1.0, 2.0]]))
    r = rc.cast(np.zeros(3), np.deg2rad([90.0, 135.0]), 5.0)
    assert r[0] == pytest.approx(0.0)  # the end point itself is on every ray
    assert r[1] == pytest.approx(0.0)


@pytest.mark.parametrize("seed", range(6))
def test_cast_many_is_cast_pose_by_pose(seed: int) -> None:
    """Several poses in one pass give each pose's own ranges bit for bit: random segments and
    a floor plan's rooms, poses far apart (some with nothing in range, some on a wall), sorted
    and unsorted beams."""
    rng = np.random.default_rng(100 + seed)
    if seed % 2:
        seg = rng.uniform(-5, 5, (40, 4))
    else:
        seg = np.vstack([_square(0, 0, 4, 3), _square(4, 0, 9, 6), _square(1, 1, 1.5, 1.4)])
    poses = np.column_stack([rng.uniform(-2, 10, 7), rng.uniform(-2, 7, 7), rng.uniform(-4, 4, 7)])
    poses[0] = [50.0, 50.0, 0.0]  # nothing within range
    poses[1] = [2.0, 0.0, 0.3]  # on a wall
    ang = rng.uniform(-4, 4, 90) if seed % 3 else np.linspace(-np.pi, np.pi, 361)
    caster = RayCaster(seg)
    many = caster.cast_many(poses, ang, 6.0)
    assert many.shape == (7, len(ang))
    for k in range(7):
        np.testing.assert_array_equal(many[k], caster.cast(poses[k], ang, 6.0))
    assert np.isnan(many[0]).all() and np.isfinite(many[2:]).any()
    assert caster.cast_many(np.zeros((0, 3)), ang, 6.0).shape == (0, len(ang))
    with pytest.raises(LocalizationError):
        caster.cast_many(poses[:, :2], ang, 6.0)
    with pytest.raises(LocalizationError):
        caster.cast_many(np.array([[0.0, np.nan, 0.0]]), ang, 6.0)


def test_cast_layered_finds_returns_on_surfaces_behind_the_nearest() -> None:
    """Two parallel walls at x = 2 and x = 5: a return at 5 m lies on the farther one (seen
    past the nearer), one at 3.5 m on neither, NaN on none; the predicted ranges are
    :meth:`cast`'s, bit for bit."""
    segs = np.array([[2.0, -1.0, 2.0, 1.0], [5.0, -3.0, 5.0, 3.0]])
    caster = RayCaster(segs)
    pose = np.array([0.0, 0.0, 0.0])
    ang = np.array([0.0, 0.0, 0.0, 0.0, np.pi])
    r = np.array([5.05, 3.5, 2.0, np.nan, 1.0])
    pred, on_map = caster.cast_layered(pose, ang, r, 0.1, 10.0)
    assert np.array_equal(pred, caster.cast(pose, ang, 10.0), equal_nan=True)
    assert pred[0] == 2.0 and np.isnan(pred[4])
    assert on_map.tolist() == [True, False, True, False, False]
    with pytest.raises(LocalizationError):
        caster.cast_layered(pose, ang, r[:3], 0.1, 10.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_cast_gives_the_numpy_references_bits(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """service/core/kernels/raycast.py walks the same beam runs as the numpy reference
    (RayCaster._spans / _pairs) and does the same arithmetic: the same ranges to the bit,
    the same beams on the map, for several poses at once, beams in any order, segments
    through the sensor and wrapped bearing intervals."""
    from service.core import kernels

    if not kernels.HAVE_NUMBA:
        pytest.skip("numba kernels not installed")
    rng = np.random.default_rng(seed)
    seg = rng.uniform(-8, 8, size=(120, 4))
    seg[:5, :2] = 0.0  # segments starting at the sensor of the first pose
    caster = RayCaster(seg)
    poses = np.column_stack([rng.uniform(-6, 6, 6), rng.uniform(-6, 6, 6), rng.uniform(-4, 4, 6)])
    poses[0] = [0.0, 0.0, 0.3]
    got, ref = [], []
    for ang in (np.linspace(-np.pi, np.pi, 721), rng.uniform(-7, 7, 300)):
        ranges = caster.cast(poses[1], ang, 6.0) + rng.normal(0, 0.05, ang.shape[0])
        ranges[rng.random(ang.shape[0]) < 0.1] = np.nan
        for out in (got, ref):
            monkeypatch.setattr(kernels, "HAVE_NUMBA", out is got)
            out.append(caster.cast_many(poses, ang, 6.0))
            out.extend(caster.cast_layered(poses[1], ang, ranges, 0.1, 6.0))
    monkeypatch.undo()
    for g, r in zip(got, ref, strict=True):
        assert g.dtype == r.dtype
        assert np.array_equal(g, r, equal_nan=True)
    assert np.isfinite(got[0]).mean() > 0.5  # most beams hit something
    assert got[2].any() and not got[2].all()  # some beams on the map, some not
