"""Map fidelity: exact distances of scan returns at their poses to a map's polylines."""

from __future__ import annotations

import math

import numpy as np
import pytest
import shapely

from service.adapters.maps.fidelity import distances_to_map, map_fidelity, scan_points
from service.core.types import MapData
from service.errors import InvalidMessage


def _wall_map() -> MapData:
    # one wall along y = 0 from x = 0 to 10 m, one along x = 10 from y = 0 to 5 m
    return MapData.from_lists("w", "metric", [np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 5.0]])])


def test_known_offsets_give_known_statistics() -> None:
    # a laser 2 m above the wall looking straight down (theta = -pi/2, beam angle 0): a range
    # of 2 - d puts the return d metres off the wall (above it for d > 0, below for d < 0)
    offsets = np.array([0.01, -0.02, 0.03, -0.04, 0.05, 0.06, -0.07, 0.08, 0.09, -0.10])
    scans = [(np.array([2.0 - d]), np.array([0.0])) for d in offsets]
    poses = np.column_stack(
        (np.linspace(1.0, 8.0, offsets.size), np.full(offsets.size, 2.0), np.full(10, -math.pi / 2))
    )
    f = map_fidelity(_wall_map(), scans, poses)
    a = np.abs(offsets)
    assert f.n_points == 10
    assert f.median == pytest.approx(np.median(a), abs=1e-9)
    assert f.p90 == pytest.approx(np.percentile(a, 90), abs=1e-9)
    assert f.mean == pytest.approx(a.mean(), abs=1e-9)


def test_stride_and_range_limits() -> None:
    a = np.array([-0.1, 0.0, 0.1])
    scans = [(np.array([1.0, np.nan, 40.0]), a), (np.array([0.01, 2.0, 3.0]), a)]
    poses = np.array([[5.0, 2.0, -math.pi / 2], [5.0, 2.0, -math.pi / 2]])
    pts = scan_points(scans, poses)  # NaN, >= max_range (30 m) and < min_range (5 cm) skipped
    assert pts.shape == (3, 2)
    assert scan_points(scans, poses, stride=2).shape == (1, 2)
    assert scan_points(scans, poses, max_range=2.5).shape == (2, 2)
    b = -math.pi / 2 - 0.1
    assert np.allclose(pts[0], [5.0 + math.cos(b), 2.0 + math.sin(b)])
    with pytest.raises(InvalidMessage, match="no scan return"):
        map_fidelity(_wall_map(), [(np.array([np.nan]), np.array([0.0]))], poses[:1])
    with pytest.raises(InvalidMessage, match="2 scans but 1 poses"):
        scan_points(scans, poses[:1])
    with pytest.raises(InvalidMessage, match="stride"):
        scan_points(scans, poses, stride=0)


def test_distances_are_exact_against_shapely() -> None:
    # many short segments (a jagged wall and a ring) and points near and far: the k-d tree
    # candidates and the STRtree fallback together must equal shapely's exact distance
    rng = np.random.default_rng(3)
    xs = np.linspace(0.0, 20.0, 400)
    jag = np.column_stack((xs, 0.05 * rng.standard_normal(xs.size)))
    t = np.linspace(0.0, 2.0 * math.pi, 60)
    ring = np.column_stack((10.0 + 3.0 * np.cos(t), 6.0 + 2.0 * np.sin(t)))
    ring[-1] = ring[0]
    m = MapData.from_lists("j", "metric", [jag, ring, np.array([[25.0, -3.0], [25.5, 9.0]])])
    pts = np.vstack(
        (
            rng.uniform([-5.0, -5.0], [30.0, 12.0], (3000, 2)),
            jag[::7] + rng.normal(0.0, 0.02, (58, 2)),
        )
    )
    d = distances_to_map(m, pts)
    lines = shapely.MultiLineString([shapely.LineString(p) for p in m.polylines])
    ref = shapely.distance(lines, shapely.points(pts))
    assert np.max(np.abs(d - ref)) < 1e-9
    assert distances_to_map(m, np.zeros((0, 2))).shape == (0,)
