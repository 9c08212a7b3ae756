"""Acceptance bars of the shape-based localiser on the paper's two setups (section 6).

Whole tour of each setup, initial pose = truth[0], no odometry. About 20 s for setup 1
(~3900 scans) and 7 s for setup 2 (~410 scans) with the compiled kernels (numba), 1.5 min
and 0.5 min without.
"""

from __future__ import annotations

import numpy as np
import pytest

from service.core.tracking.localizer import ShapeLocalizer
from sim_publisher.scenario import make_setup


def _run(setup_id: int) -> dict[str, float]:
    s = make_setup(setup_id, seed=0)
    loc = ShapeLocalizer(s.map_data, s.truth[0])
    pos, head, passed = [], [], 0
    for i in range(len(s)):
        ranges, angles = s.scan(i)
        est = loc.update(ranges, angles)
        t = s.truth[i]
        pos.append(1000.0 * np.hypot(est.pose[0] - t[0], est.pose[1] - t[1]))
        head.append(np.rad2deg(abs((est.pose[2] - t[2] + np.pi) % (2 * np.pi) - np.pi)))
        passed += int(s.passed(i, est.pose))
    return {
        "n": float(len(s)),
        "mean_mm": float(np.mean(pos)),
        "mean_deg": float(np.mean(head)),
        "proximity": passed / len(s),
    }


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_setup1_metric_map_accuracy() -> None:
    r = _run(1)
    assert r["n"] > 3800
    assert r["proximity"] >= 0.99, r
    assert r["mean_mm"] <= 20.0, r
    assert r["mean_deg"] <= 0.5, r


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_setup2_schematic_map_accuracy() -> None:
    r = _run(2)
    assert r["n"] > 400
    assert r["proximity"] >= 0.97, r
    assert r["mean_mm"] <= 120.0, r
    assert r["mean_deg"] <= 2.0, r
