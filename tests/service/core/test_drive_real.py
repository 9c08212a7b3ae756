"""The budgeted search over a drive on a real log, against the log's schematised map
(``tests/data/real/README.md``): fr079 scans 1174-1329, the robot starting unknown in a small
room at the west end and driving out along the corridor; scans 4361-4510 at the east end."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.core.factory import create_localizer
from service.core.types import wrap_angle
from service.maps.files import load_map_file

DATA = Path(__file__).resolve().parents[2] / "data" / "real"


def test_a_twin_the_drive_has_judged_does_not_block_the_fix(tmp_path: Path) -> None:
    """The true place wins the drive's evidence by ~0.2 from 7.6 m on, but its
    self-similarity check keeps finding an alias 31 m away that fits single scans better.
    Once that twin has joined the hypotheses and lost the drive by the margin, the check is
    answered (``twin_judged``) and the robot is fixed at the true place; before, the check
    found the same twin again on every try and the start was never fixed within 20 m."""
    md = load_map_file(DATA / "fr079.schematic.geojson", kind="schematic")
    z = np.load(DATA / "fr079.1174-1329.npz")
    loc = create_localizer("shape", md, None, cache_dir=tmp_path, search_budget_ms=50.0)
    judged, fix = False, None
    for i in range(len(z["ranges"])):
        est = loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
        judged |= "twin_judged" in est.extras
        if est.status == "tracking":
            fix = i
            break
    assert judged, "the drive never answered the twin check"
    assert fix is not None, "not fixed within the excerpt"
    ref = z["reference"][fix]
    assert z["flag"][fix]
    assert np.hypot(*(est.pose[:2] - ref[:2])) < 0.5, (est.pose, ref)
    assert abs(wrap_angle(float(est.pose[2] - ref[2]))) < np.deg2rad(10.0)


def test_a_probation_that_slides_off_the_odometry_into_walls_is_put_back(tmp_path: Path) -> None:
    """fr079 scans 4361-4510, east end of the floor plan: the search's winner is the true
    place (0.13 m off), but on its probation the tracker slides along furniture, 0.34 m from
    the odometry's reckoning and into walls (24 % of beams through them, 8 % from the
    reckoned pose). Unchecked, it passed the probation and was published 0.52 m off; put
    back on the reckoned pose, no pose is published that far off."""
    md = load_map_file(DATA / "fr079.schematic.geojson", kind="schematic")
    z = np.load(DATA / "fr079.4361-4510.npz")
    loc = create_localizer("shape", md, None, cache_dir=tmp_path, search_budget_ms=50.0)
    put_back = 0
    for i in range(len(z["ranges"])):
        est = loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
        put_back += "slide_reset" in est.extras
        if est.status == "tracking" and z["flag"][i]:
            ref = z["reference"][i]
            assert np.hypot(*(est.pose[:2] - ref[:2])) < 0.5, (i, est.pose, ref)
    assert put_back >= 1
