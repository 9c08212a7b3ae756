"""Configurations and the map's abstract sensor reading (service/core/shapes/configuration.py).

Runs in well under a second.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable

import numpy as np
import pytest

from service.core import kernels
from service.core.kernels import extract as extract_kernels
from service.core.pose import transform_points
from service.core.sensor.mapmodel import MapModel
from service.core.sensor.raycast import RayCaster
from service.core.shapes import configuration as conf_mod
from service.core.shapes.configuration import (
    ExtractionParams,
    MapViewCache,
    map_view,
    scan_configuration,
    scan_groups,
    split_pieces,
)
from service.core.shapes.dce import dce
from service.core.shapes.polylines import group_polylines
from service.core.types import MapData
from service.errors import LocalizationError

# A 8 x 5 m room with a 1 x 1 m pillar.
ROOM = MapData.from_lists(
    "room",
    "metric",
    [
        [[0, 0], [8, 0], [8, 5], [0, 5], [0, 0]],
        [[5, 2], [6, 2], [6, 3], [5, 3], [5, 2]],
    ],
)
POSE = np.array([2.0, 2.5, 0.3])


def _dist_to_segments(points: np.ndarray, segs: np.ndarray) -> np.ndarray:
    a = segs[:, :2]
    e = segs[:, 2:] - a
    d = points[:, None, :] - a[None]
    t = np.clip(np.einsum("kij,ij->ki", d, e) / np.einsum("ij,ij->i", e, e), 0, 1)
    r = d - t[..., None] * e[None]
    return np.min(np.hypot(r[..., 0], r[..., 1]), axis=1)


def test_scan_configuration_is_in_angular_order_and_robot_frame() -> None:
    angles = np.linspace(-math.pi / 2, math.pi / 2, 361)
    ranges = RayCaster(ROOM.segments()).cast(POSE, angles, 15.0)
    P = scan_configuration(ranges, angles)
    assert P.frame == "robot" and not P.cyclic
    assert len(P) >= 3
    starts = [f.bearing_start for f in P.features]
    assert starts == sorted(starts)
    # robot-frame points placed with the true pose lie on the map's walls
    for f in P.features:
        d = _dist_to_segments(transform_points(POSE, f.points), ROOM.segments())
        assert np.max(d) < 1e-9
        assert f.vertices.shape[0] >= 2 and f.vertices.shape[0] <= f.points.shape[0]


def test_map_view_equals_scan_of_the_same_rays() -> None:
    """The abstract sensor reading is built by exactly the same code as a scan."""
    view = map_view(ROOM, POSE, fov=math.pi, beams=361)
    angles = np.linspace(-math.pi / 2, math.pi / 2, 361)
    ranges = RayCaster(ROOM.segments()).cast(POSE, angles, 15.0)
    scan = scan_configuration(ranges, angles)
    assert len(view) == len(scan)
    for fv, fs in zip(view.features, scan.features, strict=True):
        assert np.allclose(fv.vertices, transform_points(POSE, fs.vertices), atol=1e-9)
        assert fv.angular_size == pytest.approx(fs.angular_size)


def test_full_map_view_is_cyclic_and_knows_its_segments() -> None:
    view = map_view(ROOM, POSE, beams=720)
    assert view.frame == "map" and view.cyclic
    total = sum(f.angular_size for f in view.features)
    assert total > 1.9 * math.pi  # the room surrounds the robot (minus pillar shadows)
    for f in view.features:
        assert f.segments is not None and len(f.segments) >= 1
        # every point lies on one of the feature's own segments
        assert np.max(_dist_to_segments(f.points, f.segments)) < 1e-9


def test_split_pieces_cuts_long_edges_and_shares_cut_vertices() -> None:
    pts = np.column_stack([np.linspace(0, 6, 301), np.zeros(301)])  # 6 m straight, 2 cm steps
    keep = np.array([0, 300])
    pieces = split_pieces(keep, pts, 1.5)
    assert len(pieces) == 4
    for a, b in itertools.pairwise(pieces):
        assert a[-1] == b[0]
    lengths = [pts[p[-1], 0] - pts[p[0], 0] for p in pieces]
    assert lengths == pytest.approx([1.5] * 4, abs=0.03)
    assert split_pieces(keep, pts, 0.0) == [keep]


def test_pieces_respect_piece_length_param() -> None:
    angles = np.linspace(-math.pi / 2, math.pi / 2, 361)
    ranges = RayCaster(ROOM.segments()).cast(POSE, angles, 15.0)
    few = scan_configuration(ranges, angles, ExtractionParams(piece_length=0.0))
    many = scan_configuration(ranges, angles, ExtractionParams(piece_length=1.0))
    assert len(many) > len(few)
    assert max(f.length for f in many.features) < max(f.length for f in few.features)


def test_map_view_cache_reuses_view_until_moved() -> None:
    cache = MapViewCache(ROOM, beams=360, reuse_distance=0.1)
    v1 = cache.view(POSE)
    v2 = cache.view(POSE + np.array([0.05, 0.0, 1.0]))  # moved 5 cm, turned: reused
    assert v2 is v1 and cache.casts == 1
    v3 = cache.view(POSE + np.array([0.2, 0.0, 0.0]))
    assert v3 is not v1 and cache.casts == 2
    assert np.allclose(v3.viewpoint, POSE + np.array([0.2, 0.0, 0.0]))


def test_bad_input_raises_localization_error() -> None:
    with pytest.raises(LocalizationError, match="equal length"):
        scan_configuration(np.ones(5), np.zeros(4))
    with pytest.raises(LocalizationError, match="empty"):
        scan_configuration(np.zeros(0), np.zeros(0))
    with pytest.raises(LocalizationError, match="pose"):
        map_view(ROOM, np.array([0.0, np.nan, 0.0]))


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_compiled_hit_segments_agree_with_numpy() -> None:
    """The nearest-segment kernel returns the numpy version's indices (incl. ties: points on
    shared vertices of a closed ring go to the first segment)."""
    rng = np.random.default_rng(61)
    for _ in range(20):
        v = rng.uniform(-5, 5, size=(int(rng.integers(3, 40)), 2))
        segs = np.column_stack([v, np.roll(v, -1, axis=0)])
        pts = np.vstack([rng.uniform(-6, 6, size=(300, 2)), v])
        got = extract_kernels.nearest_segment(pts, segs)
        flag = kernels.HAVE_NUMBA
        try:
            kernels.HAVE_NUMBA = False
            ref = conf_mod._hit_segments(pts, segs, chunk=64)
        finally:
            kernels.HAVE_NUMBA = flag
        assert np.array_equal(got, ref)


@pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")
def test_compiled_split_pieces_agrees_with_numpy() -> None:
    from service.core.shapes.dce import dce

    rng = np.random.default_rng(62)
    multi = 0
    for trial in range(400):
        k = int(rng.integers(3, 300))
        if trial % 2:  # long noisy walls: extra vertices and several pieces
            p = np.column_stack([np.linspace(0, rng.uniform(0.5, 12), k), rng.normal(0, 0.01, k)])
        else:
            p = np.cumsum(rng.normal(size=(k, 2)) * rng.uniform(0.01, 0.3), axis=0)
        keep = dce(p, float(rng.uniform(0.01, 0.3)))
        pl = float(rng.choice([0.5, 1.5, 3.0]))
        got = conf_mod.split_pieces(keep, p, pl)
        ref = conf_mod._split_pieces_numpy(keep, p, pl)
        multi += len(ref) > 1
        assert len(got) == len(ref)
        assert all(np.array_equal(a, b) for a, b in zip(got, ref, strict=True))
    assert multi > 100


# --------------------------------------------------------------------------------------------
# One pass over all groups / features (the batched paths) gives the per-feature results
# --------------------------------------------------------------------------------------------


def _groups(ranges: np.ndarray, angles: np.ndarray, params: ExtractionParams, wrap: bool) -> list:
    groups = group_polylines(
        ranges,
        angles,
        min_object_distance=params.min_object_distance,
        range_factor=params.range_factor,
        min_points=params.min_points,
        wrap=wrap,
    )
    return [g for g in groups if g.length >= params.min_length]


def _per_group_reference(
    ranges: np.ndarray, angles: np.ndarray, params: ExtractionParams, wrap: bool
) -> list[tuple]:
    """_features_from_ranges as it runs group by group (dce, split_pieces and _piece per
    group, Polyline's own length and angular size)."""
    out = []
    for g in _groups(ranges, angles, params, wrap):
        keep = dce(g.points, params.dce_threshold)
        pieces = split_pieces(keep, g.points, params.piece_length)
        if len(pieces) == 1:
            out.append((g, g.points[keep]))
            continue
        for pk in pieces:
            out.append((conf_mod._piece(g, int(pk[0]), int(pk[-1])), g.points[pk]))
    return out


@pytest.mark.parametrize(("setup_id", "scan"), [(2, 15), (2, 300), (1, 60)])
def test_batched_extraction_and_map_view_equal_the_per_feature_results(
    setup_id: int, scan: int, real_scene: Callable
) -> None:
    """Scan and 720-beam map view of real poses: the one-call DCE / cuts of all groups, the
    lengths and angular sizes of all polylines in one numpy pass, and the map view's features
    transformed and given their hit segments all at once are, bit for bit, what the group by
    group and feature by feature code gives."""
    sc = real_scene(setup_id, scan)
    params = sc.config.extraction()
    pose = sc.truth[scan]
    n = sc.config.view_beams
    view_angles = -np.pi + (np.arange(n) + 0.5) * (2.0 * np.pi / n)
    caster = RayCaster(sc.map_data.segments())
    view_ranges = caster.cast(pose, view_angles, sc.config.view_max_range)
    cuts = 0  # groups cut into pieces: extra features
    for r, a, wrap in ((sc.ranges, sc.angles, False), (view_ranges, view_angles, True)):
        got = conf_mod._features_from_ranges(r, a, params, wrap)
        ref = _per_group_reference(r, a, params, wrap)
        assert len(got) == len(ref) >= 5
        stacked = np.vstack([g.points for g in _groups(r, a, params, wrap)])
        cuts += len(ref) - len(_groups(r, a, params, wrap))
        for (g, v, first), (h, w) in zip(got, ref, strict=True):
            assert np.array_equal(v, w) and np.array_equal(g.points, h.points)
            # each piece's rows among the groups' stacked points
            assert np.array_equal(stacked[first : first + len(g.points)], g.points)
            assert np.array_equal(g.idx, h.idx)
            assert (g.bearing_start, g.bearing_end) == (h.bearing_start, h.bearing_end)
        sizes = conf_mod._angular_sizes([g.points for g, _v, _f in got])
        assert sizes == [g.angular_size for g, _ in ref]
        assert conf_mod._lengths([g.points for g, _v, _f in got]) == [g.length for g, _ in ref]
    assert cuts > 0
    model = MapModel(sc.map_data)
    Q = map_view(caster, pose, beams=n, params=params, model=model)
    raw = _per_group_reference(view_ranges, view_angles, params, True)
    assert len(Q.features) == len(raw)
    for f, (g, v) in zip(Q.features, raw, strict=True):
        pts = transform_points(pose, g.points)
        ids = np.unique(model.nearest(pts, 0.05).segment)
        assert np.array_equal(f.points, pts)
        assert np.array_equal(f.vertices, transform_points(pose, v))
        assert f.angular_size == g.angular_size
        assert np.array_equal(f.segments, caster.segments[ids]) and len(ids) >= 1
    P = scan_configuration(sc.ranges, sc.angles, params)
    ref = _per_group_reference(sc.ranges, sc.angles, params, False)
    assert [f.angular_size for f in P.features] == [g.angular_size for g, _ in ref]


def test_scan_groups_give_the_configuration_and_each_points_feature(real_scene: Callable) -> None:
    """The grouped polylines a tracked scan's precise fit uses are the configuration's points
    (every row of every feature, pieces sharing their cut vertex), and ``feature_of_point``
    names, for each row, a feature that holds that very point."""
    sc = real_scene(1, 60)
    params = sc.config.extraction()
    sg = scan_groups(sc.ranges, sc.angles, params)
    P = scan_configuration(sc.ranges, sc.angles, params)
    assert len(sg.configuration.features) == len(P.features) > len(sg.groups)  # some cut
    for f, g in zip(sg.configuration.features, P.features, strict=True):
        assert np.array_equal(f.vertices, g.vertices) and np.array_equal(f.points, g.points)
    assert len(sg.points) == sum(len(g.points) for g in sg.groups)
    assert sum(len(f.points) for f in P.features) > len(sg.points)  # shared cut vertices
    own = sg.feature_of_point
    for row in range(len(sg.points)):
        f = sg.configuration.features[own[row]]
        assert f.first_point <= row < f.first_point + len(f.points)
        assert np.array_equal(f.points[row - f.first_point], sg.points[row])
