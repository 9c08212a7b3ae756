"""The segment bucket grid returns exactly the brute-force selection (same rows, same order)."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.sensor.segment_grid import SegmentGrid, nearby_segments_brute


def _random_map(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.uniform(-20.0, 20.0, size=(n, 2))
    # short clutter pieces and a few long walls
    length = np.where(rng.random(n) < 0.9, rng.uniform(0.05, 1.0, n), rng.uniform(5.0, 30.0, n))
    ang = rng.uniform(-np.pi, np.pi, n)
    b = a + length[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    return np.column_stack([a, b])


@pytest.mark.parametrize("radius", [0.05, 0.2, 0.5, 1.0, 2.5])
def test_grid_selects_the_same_segments_as_brute_force(radius: float) -> None:
    rng = np.random.default_rng(3)
    seg = _random_map(rng, 600)
    grid = SegmentGrid(seg, cell=1.0)
    for _ in range(40):
        centre = rng.uniform(-25.0, 25.0, 2)
        pts = centre + rng.normal(size=(int(rng.integers(1, 300)), 2)) * rng.uniform(0.1, 8.0)
        want = nearby_segments_brute(seg, pts, radius)
        got = grid.nearby(pts, radius)
        assert np.array_equal(got, want)


def test_grid_selects_a_strict_subset_near_scan_like_points() -> None:
    rng = np.random.default_rng(4)
    seg = _random_map(rng, 600)
    grid = SegmentGrid(seg, cell=1.0)
    # points lying on three segments: those segments are selected, far ones are not
    pts = np.concatenate(
        [s[:2] + np.linspace(0, 1, 20)[:, None] * (s[2:] - s[:2]) for s in seg[:3]]
    )
    got = grid.nearby(pts, 0.1)
    for s in seg[:3]:
        assert any(np.array_equal(s, g) for g in got)
    assert len(got) < len(seg) / 4
    assert np.array_equal(got, nearby_segments_brute(seg, pts, 0.1))


def test_no_segment_near_returns_all_like_the_reference() -> None:
    seg = np.array([[0.0, 0.0, 1.0, 0.0], [5.0, 5.0, 5.0, 6.0]])
    grid = SegmentGrid(seg)
    far = np.array([[100.0, 100.0], [-50.0, 3.0]])
    assert np.array_equal(grid.nearby(far, 0.5), seg)
    assert np.array_equal(nearby_segments_brute(seg, far, 0.5), seg)
    # a point just inside the radius of the first segment only, from outside the grid's cells
    near = np.array([[0.5, -0.49]])
    assert np.array_equal(grid.nearby(near, 0.5), seg[:1])


def test_empty_grid_and_empty_points() -> None:
    empty = SegmentGrid(np.zeros((0, 4)))
    assert empty.nearby(np.array([[0.0, 0.0]]), 0.5).shape == (0, 4)
    seg = np.array([[0.0, 0.0, 1.0, 0.0]])
    assert np.array_equal(SegmentGrid(seg).nearby(np.zeros((0, 2)), 0.5), seg)


def test_compiled_near_mask_equals_the_numpy_reference() -> None:
    """search_kernels.near_mask (used where numba is installed) decides every segment as
    the numpy reference does, degenerate segments and points on the radius included."""
    from service.core import kernels
    from service.core.sensor import segment_grid

    if not kernels.HAVE_NUMBA:
        pytest.skip("numba kernels not installed")
    rng = np.random.default_rng(5)
    seen = 0
    for k in range(300):
        seg = _random_map(rng, int(rng.integers(1, 80)))
        if k % 5 == 0:
            seg[:, 2:] = seg[:, :2]  # zero-length segments
        pts = rng.uniform(-22.0, 22.0, size=(int(rng.integers(1, 200)), 2))
        radius = float(rng.uniform(0.05, 3.0))
        got = segment_grid._near_mask(seg, pts, radius)
        want = segment_grid._near_mask_reference(seg, pts, radius)
        assert np.array_equal(got, want)
        seen += int(got.any() and not got.all())
    assert seen > 100  # mixed answers, not all-or-nothing
