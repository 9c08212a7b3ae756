"""Composite scans (service.core.reloc.composite): several scans at known relative poses fused into
one virtual 360-degree scan from the newest pose."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.reloc.composite import composite_scan
from service.core.sensor.raycast import RayCaster
from service.errors import LocalizationError

# a 6 x 4 m rectangle room, robot at (2, 1.5)
_ROOM = np.array(
    [[0, 0, 6, 0], [6, 0, 6, 4], [6, 4, 0, 4], [0, 4, 0, 0]],
    dtype=float,
)
_CASTER = RayCaster(_ROOM)
_ANGLES = np.linspace(-np.pi / 2, np.pi / 2, 361)  # a 180-degree laser


def _scan(pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return _CASTER.cast(pose, _ANGLES, 15.0), _ANGLES.copy(), pose


def test_spin_in_place_gives_the_full_room_from_the_last_pose() -> None:
    poses = [np.array([2.0, 1.5, th]) for th in (0.3, 0.3 + np.pi / 2, 0.3 + np.pi)]
    r, a = composite_scan([_scan(p) for p in poses], bins=720)
    assert r.shape == a.shape == (720,)
    assert np.all(np.diff(a) > 0) and a[0] > -np.pi and a[-1] < np.pi
    assert np.all(np.isfinite(r))  # 3 x 180 degrees 90 degrees apart cover every direction
    truth = _CASTER.cast(poses[-1], a, 15.0)
    # bins hold the nearest return within 0.5 degrees of the bin centre
    assert np.max(np.abs(r - truth)) < 0.1
    assert np.median(np.abs(r - truth)) < 0.02


def test_single_scan_keeps_its_sector_only_and_no_return_is_nan() -> None:
    pose = np.array([2.0, 1.5, 0.0])
    r, a = composite_scan([_scan(pose)], bins=360)
    front = np.abs(a) < np.pi / 2 - 0.02
    back = np.abs(a) > np.pi / 2 + 0.02
    assert np.all(np.isfinite(r[front]))
    assert np.all(np.isnan(r[back]))


def test_newest_scan_owns_its_bins_and_older_ones_fill_the_rest() -> None:
    old = (np.full(361, 1.0), _ANGLES.copy(), np.array([0.0, 0.0, 0.0]))  # looks forward
    new = (np.full(361, 3.0), _ANGLES.copy(), np.array([0.0, 0.0, 0.0]))  # same sector
    r, a = composite_scan([old, new], bins=360)
    front = np.abs(a) < np.pi / 2 - 0.02
    assert np.allclose(r[front], 3.0)  # the older, nearer return does not override
    # an older scan looking backwards fills the back half, in the newest frame
    back_scan = (np.full(361, 2.0), _ANGLES.copy(), np.array([0.0, 0.0, np.pi]))
    r, a = composite_scan([back_scan, new], bins=360)
    back = np.abs(a) > np.pi / 2 + 0.02
    assert np.allclose(r[back], 2.0)
    assert np.allclose(r[front], 3.0)


def test_older_points_are_moved_into_the_newest_frame() -> None:
    # the robot moved 0.5 m forward between the scans: a wall 2 m ahead of the first pose
    # is 1.5 m ahead of the second
    wall_first = (np.full(361, np.nan), _ANGLES.copy(), np.array([0.0, 0.0, np.pi]))
    wall_first[0][180] = 2.0  # straight ahead of the first pose (heading pi): x = -2
    second = (np.full(361, np.nan), _ANGLES.copy(), np.array([-0.5, 0.0, 0.0]))
    r, a = composite_scan([wall_first, second], bins=720)
    k = int(np.nanargmin(r))
    assert np.isclose(abs(a[k]), np.pi, atol=0.01)  # behind the second pose
    assert np.isclose(r[k], 1.5, atol=1e-9)


@pytest.mark.parametrize(
    "scans, bins",
    [
        ([], 720),
        ([(np.ones(3), np.zeros(3), np.zeros(3))], 4),
        ([(np.ones(3), np.zeros(2), np.zeros(3))], 720),
        ([(np.ones(3), np.zeros(3), np.zeros(2))], 720),
    ],
)
def test_bad_input_raises(scans: list, bins: int) -> None:
    with pytest.raises(LocalizationError):
        composite_scan(scans, bins=bins)


def test_all_nan_scans_give_an_all_nan_composite() -> None:
    s = (np.full(10, np.nan), np.linspace(-1, 1, 10), np.zeros(3))
    r, _ = composite_scan([s, s], bins=64)
    assert np.all(np.isnan(r))
