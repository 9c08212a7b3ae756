"""The shape localiser's configuration tree (service/core/config.py): presets, the user's knobs
and a reason for every setting."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import BaseModel

from service.core.config import Knobs, LocalizerConfig
from service.core.factory import create_localizer
from service.core.reloc.config import GlobalConfig
from service.core.tracking.shape_config import ShapeConfig
from service.core.types import MapData


def _models(model: type[BaseModel]) -> list[type[BaseModel]]:
    """``model`` and every settings model nested in it."""
    out = [model]
    for f in model.model_fields.values():
        t = f.annotation
        if isinstance(t, type) and issubclass(t, BaseModel):
            out += _models(t)
    return out


def test_a_user_has_at_most_20_knobs() -> None:
    assert len(Knobs.model_fields) <= 20


@pytest.mark.parametrize("model", [LocalizerConfig, Knobs, ShapeConfig, GlobalConfig])
def test_every_setting_says_what_it_is_for(model: type[BaseModel]) -> None:
    for m in _models(model):
        missing = [n for n, f in m.model_fields.items() if not (f.description or "").strip()]
        assert missing == [], f"{m.__name__}: {missing}"


def test_the_presets_are_the_map_kinds_defaults_and_knobs_override_them() -> None:
    plan = LocalizerConfig(preset="floor_plan")
    assert plan.tracking() == ShapeConfig.for_kind("schematic")
    assert plan.reloc() == GlobalConfig.for_kind("schematic")
    assert LocalizerConfig().reloc() == GlobalConfig.for_kind("metric")
    c = LocalizerConfig.for_kind(
        "schematic", use_odometry=False, odometry_noise=2.0, fix_llr=33.0, max_range=10.0
    )
    t, g = c.tracking(), c.reloc()
    assert not t.motion.use_odometry
    assert (
        t.motion.alpha_trans_trans
        == 2.0 * ShapeConfig.for_kind("schematic").motion.alpha_trans_trans
    )
    assert t.view_max_range == 10.0 and g.fix_llr == 33.0
    assert g.probation_travel == GlobalConfig.for_kind("schematic").probation_travel


def test_the_factory_takes_the_tree() -> None:
    md = MapData.from_lists("box", "metric", [[[0, 0], [4, 0], [4, 3], [0, 3], [0, 0]]])
    loc = create_localizer(
        "shape", md, np.array([2.0, 1.5, 0.0]), LocalizerConfig.for_kind("metric", keep=5)
    )
    assert loc.gconfig.keep == 5  # type: ignore[attr-defined]
    with pytest.raises(ValueError):
        Knobs(keep=0)
