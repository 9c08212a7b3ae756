"""Shared fixtures of the core tests."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest

from service.core.pose import compose, invert, transform_points
from service.core.reloc import drive as dr
from service.core.reloc.config import GlobalConfig
from service.core.reloc.global_localization import load_or_build_index
from service.core.sensor.mapmodel import MapModel
from service.core.shapes.configuration import Configuration, map_view, scan_configuration
from service.core.tracking.localizer import ShapeConfig
from service.core.types import MapData
from sim_publisher.scenario import make_setup


@dataclass
class RealScene:
    """One simulated scan as the shape tracker sees it: the scan configuration ``P``, the map
    view ``Q`` from the scan's true pose, the setup's :class:`ShapeConfig`, the true poses of
    the scans up to this one, the scan's ranges / angles and the map."""

    P: Configuration
    Q: Configuration
    config: ShapeConfig
    truth: np.ndarray
    ranges: np.ndarray
    angles: np.ndarray
    map_data: MapData


@pytest.fixture
def real_scene() -> Callable[[int, int], RealScene]:
    """``real_scene(setup_id, scan)``: scan ``scan`` of setup 1 (metric map) or 2 (schematic
    floor plan), seed 0."""

    def make(setup_id: int, scan: int) -> RealScene:
        s = make_setup(setup_id, seed=0, max_scans=scan + 1)
        cfg = ShapeConfig.for_kind(s.map_data.kind)
        r, a = s.scan(scan)
        P = scan_configuration(r, a, cfg.extraction())
        Q = map_view(
            s.map_data,
            s.truth[scan],
            beams=cfg.view_beams,
            max_range=cfg.view_max_range,
            params=cfg.extraction(),
            model=MapModel(s.map_data),
        )
        return RealScene(P, Q, cfg, np.asarray(s.truth), r, a, s.map_data)

    return make


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


def _random_pairs(rng: np.random.Generator, k: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Random walls: a few connected segments per pair, noisy points near them (robot frame
    = map frame shifted a little, so the fits have something to do)."""
    out = []
    for _ in range(k):
        v = np.cumsum(rng.uniform(-1.0, 1.0, size=(int(rng.integers(2, 6)), 2)), axis=0)
        segs = np.column_stack([v[:-1], v[1:]])
        u = rng.uniform(0, 1, size=int(rng.integers(3, 20)))
        s = rng.integers(0, len(segs), size=len(u))
        pts = segs[s, 0:2] + u[:, None] * (segs[s, 2:4] - segs[s, 0:2])
        pts += rng.normal(0, 0.02, size=pts.shape) + np.array([0.05, -0.03])
        out.append((pts, segs))
    return out


@pytest.fixture
def room_pairs() -> Callable:
    """``room_pairs(truth, rng, noise)``: matched pairs of three walls of a room
    (:func:`_room_pairs`)."""
    return _room_pairs


@pytest.fixture
def random_pairs() -> Callable:
    """``random_pairs(rng, k)``: ``k`` random wall pairs (:func:`_random_pairs`)."""
    return _random_pairs


def _office_window(first: int, last: int):  # type: ignore[no-untyped-def]
    """The office floor plan's tour and index, and the window of keyframes its scans
    ``first``..``last`` give with odometry: (setup, shape config, global config, index,
    keyframes)."""
    su = make_setup(2)
    cfg = ShapeConfig.for_kind(su.map_data.kind)
    g = GlobalConfig.for_kind(su.map_data.kind)
    idx = load_or_build_index(su.map_data, cfg, g)
    frames: list[dr.Frame] = []
    travel = 0.0
    for i in range(first, last + 1):
        if i > first:
            d = compose(invert(su.odom[i - 1]), su.odom[i])
            travel += float(np.hypot(d[0], d[1]))
        if dr.frame_due(frames, su.odom[i], travel):
            frames.append(dr.make_frame(len(frames), *su.scan(i), su.odom[i], travel, g))
    return su, cfg, g, idx, dr.window(frames, g)


@pytest.fixture
def office_window() -> Callable:
    """``office_window(first, last)``: the office floor plan's drive window over its tour's
    scans ``first``..``last`` (:func:`_office_window`)."""
    return _office_window
