"""One global search (service/core/global_search.py) on a real log's floor plan."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.core.global_config import GlobalConfig
from service.core.global_localization import load_or_build_index
from service.core.global_search import global_search
from service.core.localizer import ShapeConfig
from service.core.types import wrap_angle
from service.maps.files import load_map_file

DATA = Path(__file__).resolve().parents[2] / "data" / "real"


def test_ranking_the_shortlist_by_violations_finds_the_true_pose_in_a_furnished_hall() -> None:
    """fr079 scans 4361-4510 (every 5th with a reference), the east end of the floor plan,
    where the plan shows less than half of what the laser sees. Ranked by point support
    alone, places whose walls the furniture happens to fit fill the shortlist and one search
    finds the true pose (0.5 m / 10 deg) among its hypotheses on 3 of 29 scans; those places
    let a third or more of their beams through drawn walls, the true pose hardly any, and
    ranked by support less that share (``shortlist_violation_beams``, the floor-plan default)
    it is found on 11 (measured)."""
    md = load_map_file(DATA / "fr079.schematic.geojson", kind="schematic")
    z = np.load(DATA / "fr079.4361-4510.npz")
    cfg = ShapeConfig.for_kind("schematic")
    default = GlobalConfig.for_kind("schematic")
    assert default.shortlist_violation_beams > 0
    found = {}
    for beams in (0, default.shortlist_violation_beams):
        g = default.model_copy(update={"shortlist_violation_beams": beams})
        idx = load_or_build_index(md, cfg, g)
        hits = 0
        scans = [i for i in range(0, len(z["ranges"]), 5) if z["flag"][i]]
        for i in scans:
            res = global_search(idx, z["ranges"][i], z["angles"][i], cfg, g)
            ref = z["reference"][i]
            hits += any(
                np.hypot(*(h.pose[:2] - ref[:2])) < 0.5
                and abs(wrap_angle(float(h.pose[2] - ref[2]))) < np.deg2rad(10.0)
                for h in res.hypotheses
            )
        found[beams] = hits
    assert len(scans) == 29
    assert found[0] <= 4, found
    assert found[default.shortlist_violation_beams] >= 9, found
