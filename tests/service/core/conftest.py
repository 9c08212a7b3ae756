"""Shared fixtures of the core tests."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pytest

from service.core.configuration import Configuration, map_view, scan_configuration
from service.core.localizer import ShapeConfig
from service.core.mapmodel import MapModel
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
