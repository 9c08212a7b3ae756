"""Modules of the flat core of earlier versions import under their old names, and localiser
states pickled by an earlier version load and go on (service.core.MOVED)."""

from __future__ import annotations

import gzip
import importlib
import pickle
from pathlib import Path

import numpy as np
import pytest

import service.core
from service.core.reloc import states as st
from service.core.reloc.config import GlobalConfig
from service.core.reloc.global_localization import GlobalShapeLocalizer
from sim_publisher.laser import LaserSimulator

PICKLES = Path(__file__).resolve().parents[2] / "data" / "pickles"


@pytest.mark.parametrize("old", sorted(service.core.MOVED))
def test_an_old_module_name_imports_as_the_module_that_holds_its_code(old: str) -> None:
    module = importlib.import_module(f"service.core.{old}")
    assert module is importlib.import_module(f"service.core.{service.core.MOVED[old]}")


def test_a_class_pickled_under_its_old_module_name_loads() -> None:
    from service.core.tracking.localizer import ShapeLocalizer

    assert pickle.loads(b"cservice.core.localizer\nShapeLocalizer\n.") is ShapeLocalizer
    assert pickle.loads(b"cservice.core.drive_search\nProbation\n.") is st.Probation


def _load(name: str) -> GlobalShapeLocalizer:
    with gzip.open(PICKLES / f"localizer-{name}-0b1a718.pkl.gz", "rb") as fh:
        loc = pickle.load(fh)
    assert isinstance(loc, GlobalShapeLocalizer)
    return loc


def test_a_tracking_localiser_pickled_by_an_earlier_version_goes_on_tracking() -> None:
    loc = _load("tracking")
    assert isinstance(loc.state, st.Tracking)
    assert loc.gconfig.search_budget_ms == 50.0
    truth = np.array([4.95, 2.0, 0.88])  # where it was fixed when it was pickled
    np.testing.assert_allclose(loc.pose, truth, atol=0.02)
    laser = LaserSimulator(loc.map_data.segments(), seed=3)
    est = loc.update(*laser.scan(truth, 99), None)
    assert est.status == "tracking" and est.state == "tracking"
    assert np.hypot(*(est.pose[:2] - truth[:2])) < 0.05


def test_a_searching_localiser_pickled_by_an_earlier_version_searches_again() -> None:
    loc = _load("searching")
    assert isinstance(loc.state, st.Searching) and loc.state.status == "initializing"
    laser = LaserSimulator(loc.map_data.segments(), seed=3)
    est = loc.update(*laser.scan(np.array([3.65, 2.0, 0.36]), 99), None)
    assert est.status == "initializing" and est.state == "searching"


def test_settings_pickled_with_a_field_removed_since_load_without_it() -> None:
    g = GlobalConfig.for_kind("schematic")
    state = g.__getstate__()
    state["__dict__"] = {**state["__dict__"], "spacing": 0.6}  # a field of earlier versions
    old = pickle.dumps(g)
    loaded = pickle.loads(old)
    loaded.__setstate__(state)
    assert "spacing" not in loaded.__dict__
    assert loaded == g and loaded.model_dump() == g.model_dump()
