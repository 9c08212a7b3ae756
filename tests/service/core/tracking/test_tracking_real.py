"""What ends a track on a real log's floor plan with odometry (``tests/data/real/README.md``):
fr079 scans 4100-4199, the robot driving into the east hall, which the floor plan draws as its
outline, and a kidnap from there into the scans of a small room at the west end (scans
1174-1329) with the odometry running on as if nothing had happened."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from service.adapters.maps.files import load_map_file
from service.core.factory import create_localizer
from service.core.pose import compose, relative
from service.core.reloc.global_localization import GlobalShapeLocalizer
from service.core.reloc.states import Tracking
from service.core.tracking.laser_odometry import LaserOdometryLocalizer

DATA = Path(__file__).resolve().parents[3] / "data" / "real"


def _localizer(pose: np.ndarray) -> LaserOdometryLocalizer:
    md = load_map_file(DATA / "fr079.schematic.geojson", kind="schematic")
    loc = create_localizer("shape", md, pose.copy())
    assert isinstance(loc, LaserOdometryLocalizer)  # the factory default
    assert isinstance(loc.inner, GlobalShapeLocalizer)
    return loc


def test_the_odometry_bridges_a_hall_the_floor_plan_draws_as_its_outline() -> None:
    """In the east hall the plan explains a quarter to a third of each scan, so the tracker
    rejects scan after scan: the robot dead-reckons and says so (status ``lost``, state
    ``dead_reckoning``, a covariance that grows), and the odometry holds the pose within
    0.3 m of the reference on every scan; it is never published as ``tracking`` off the
    reference. Where the scan-to-scan fit breaks (scan 4176 matches 47 % of its points to
    the one before) the odometry is no longer checked by the laser: a search starts with the
    dead-reckoned pose as its prior and publishes that pose, lost, until a place is more
    probable."""
    z = np.load(DATA / "fr079.4100-4199.npz")
    loc = _localizer(z["reference"][0])
    states, errors, sigmas = [], [], []
    for i in range(len(z["ranges"])):
        est = loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
        states.append(est.state)
        if est.state == "dead_reckoning":
            assert est.status == "lost" and est.covariance is not None
            sigmas.append(float(np.sqrt(np.max(np.linalg.eigvalsh(est.covariance[:2, :2])))))
        if z["flag"][i]:
            err = float(np.hypot(*(est.pose[:2] - z["reference"][i][:2])))
            errors.append(err)
            assert est.status != "tracking" or err < 0.3, (i, err)
    assert states[0] == "tracking"
    assert states.count("dead_reckoning") >= 15, states
    assert states[-1] in ("dead_reckoning", "searching") and "probation" not in states, states
    assert min(sigmas) == sigmas[0] < sigmas[-1], sigmas  # it grows as the robot drives
    assert max(errors) < 0.3, max(errors)


@pytest.mark.parametrize("at", [20, 90])
def test_a_kidnapped_robot_is_still_lost_within_three_scans(at: int) -> None:
    """Followed into the hall for ``at`` scans (tracked, or dead-reckoned where the plan shows
    only the hall's outline), the robot is carried to the small room at the west end (about
    30 m away) while its odometry reports the room's drive as if it went on from the hall.
    The scan-to-scan fit breaks at the jump; from then on every scan the map fits poorly
    contradicts the pose, accepted by the tracker or not (the plan's outline half explains
    some of the room's scans from the hall). Within three scans it searches, no longer
    carrying the hall pose, and from then on it is never published as ``tracking`` more than
    0.5 m off."""
    z = np.load(DATA / "fr079.4100-4199.npz")
    w = np.load(DATA / "fr079.1174-1329.npz")
    loc = _localizer(z["reference"][0])
    for i in range(at):
        est = loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
        assert np.hypot(*(est.pose[:2] - z["reference"][i][:2])) < 0.3, i
    base = z["odom"][at - 1]
    states = []
    for j in range(1, 40):
        odom = compose(base, relative(w["odom"][0], w["odom"][j]))
        est = loc.update(w["ranges"][j], w["angles"][j], odom)
        states.append(est.state)
        if est.status == "tracking" and "searching" in states:
            assert np.hypot(*(est.pose[:2] - w["reference"][j][:2])) < 0.5, (j, states)
    assert "searching" in states[:3], states


def test_a_state_saved_before_the_break_flag_existed_still_loads() -> None:
    """A robot's localiser persisted by an earlier version (its tracking state without the
    ``broken`` flag) is restored and tracks on: the flag falls back to its class default (no
    break seen)."""
    z = np.load(DATA / "fr079.4100-4199.npz")
    loc = _localizer(z["reference"][0])
    for i in range(5):
        loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
    assert isinstance(loc.state, Tracking)
    del loc.state.__dict__["broken"]
    old = pickle.loads(pickle.dumps(loc))
    assert isinstance(old.state, Tracking) and old.state.broken is False
    for i in range(5, 15):
        est = old.update(z["ranges"][i], z["angles"][i], z["odom"][i])
        assert est.status == "tracking"
        assert np.hypot(*(est.pose[:2] - z["reference"][i][:2])) < 0.3
