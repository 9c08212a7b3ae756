"""The map model's bucket grid selects exactly the segments the brute force does (same rows,
same order): :meth:`service.core.sensor.mapmodel.MapModel.nearby_segments`."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.sensor import mapmodel
from service.core.sensor.mapmodel import MapModel, nearby_segments_brute
from service.core.types import MapData


def _random_map(rng: np.random.Generator, n: int) -> np.ndarray:
    a = rng.uniform(-20.0, 20.0, size=(n, 2))
    # short clutter pieces and a few long walls
    length = np.where(rng.random(n) < 0.9, rng.uniform(0.05, 1.0, n), rng.uniform(5.0, 30.0, n))
    ang = rng.uniform(-np.pi, np.pi, n)
    b = a + length[:, None] * np.column_stack([np.cos(ang), np.sin(ang)])
    return np.column_stack([a, b])


def _model(seg: np.ndarray) -> MapModel:
    """A map model of the segments (each its own polyline, in this order)."""
    return MapModel(MapData.from_lists("random", "metric", [s.reshape(2, 2) for s in seg]))


@pytest.mark.parametrize("radius", [0.05, 0.2, 0.5, 1.0])
def test_grid_selects_the_same_segments_as_brute_force(radius: float) -> None:
    rng = np.random.default_rng(3)
    seg = _random_map(rng, 600)
    grid = _model(seg)
    assert len(grid.segments) == len(seg) > mapmodel.BRUTE_SEGMENTS
    for _ in range(40):
        centre = rng.uniform(-25.0, 25.0, 2)
        pts = centre + rng.normal(size=(int(rng.integers(1, 300)), 2)) * rng.uniform(0.1, 8.0)
        want = nearby_segments_brute(seg, pts, radius)
        got = grid.nearby_segments(pts, radius)
        assert np.array_equal(got, want)


def test_grid_selects_a_strict_subset_near_scan_like_points() -> None:
    rng = np.random.default_rng(4)
    seg = _random_map(rng, 600)
    grid = _model(seg)
    assert len(grid.segments) == len(seg) > mapmodel.BRUTE_SEGMENTS
    # points lying on three segments: those segments are selected, far ones are not
    pts = np.concatenate(
        [s[:2] + np.linspace(0, 1, 20)[:, None] * (s[2:] - s[:2]) for s in seg[:3]]
    )
    got = grid.nearby_segments(pts, 0.1)
    for s in seg[:3]:
        assert any(np.array_equal(s, g) for g in got)
    assert len(got) < len(seg) / 4
    assert np.array_equal(got, nearby_segments_brute(seg, pts, 0.1))


def test_no_segment_near_returns_all_like_the_reference() -> None:
    rng = np.random.default_rng(6)
    seg = _random_map(rng, 300)
    grid = _model(seg)
    far = np.array([[100.0, 100.0], [-50.0, 3.0]])
    assert np.array_equal(grid.nearby_segments(far, 0.5), seg)
    assert np.array_equal(nearby_segments_brute(seg, far, 0.5), seg)
    assert np.array_equal(grid.nearby_segments(np.zeros((0, 2)), 0.5), seg)
    # a point just inside the radius of the first segment only
    a, b = seg[0, :2], seg[0, 2:]
    d = (b - a) / np.hypot(*(b - a))
    near = (0.5 * (a + b) + 0.49 * np.array([-d[1], d[0]]))[None, :]
    want = nearby_segments_brute(seg, near, 0.5)
    assert np.array_equal(grid.nearby_segments(near, 0.5), want)
    assert any(np.array_equal(seg[0], w) for w in want)


def test_compiled_near_mask_equals_the_numpy_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    """search_kernels.near_mask (used where numba is installed) decides every segment as
    the numpy reference does, degenerate segments and points on the radius included."""
    from service.core import kernels

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
        got = mapmodel.near_mask(seg, pts, radius)
        with monkeypatch.context() as m:
            m.setattr(kernels, "HAVE_NUMBA", False)
            want = mapmodel.near_mask(seg, pts, radius)
        assert np.array_equal(got, want)
        seen += int(got.any() and not got.all())
    assert seen > 100  # mixed answers, not all-or-nothing
