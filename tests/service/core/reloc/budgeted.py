"""Helpers shared by the tests of the budgeted multi-hypothesis search
(test_drive_search.py, test_probation.py): a localiser with a per-scan search budget, a drive
until the first fix, and the test of a fix against the truth."""

from __future__ import annotations

import numpy as np

from service.core.reloc.global_config import GlobalConfig
from service.core.reloc.global_localization import GlobalShapeLocalizer
from service.core.types import MapData, wrap_angle


def _ok(pose: np.ndarray, truth: np.ndarray) -> bool:
    return bool(
        np.hypot(*(pose[:2] - truth[:2])) < 0.5
        and abs(wrap_angle(float(pose[2] - truth[2]))) < np.deg2rad(10.0)
    )


def _budgeted(md: MapData, budget: float) -> GlobalShapeLocalizer:
    g = GlobalConfig.for_kind(md.kind).model_copy(update={"search_budget_ms": budget})
    return GlobalShapeLocalizer(md, None, gconfig=g)


def _drive(loc: GlobalShapeLocalizer, su, start: int, n: int) -> list:  # type: ignore[no-untyped-def]
    out = []
    for i in range(start, start + n):
        r, a = su.scan(i)
        est = loc.update(r, a, su.odom[i])
        out.append((i, est, loc.work_ms))
        if est.status == "tracking":
            break
    return out
