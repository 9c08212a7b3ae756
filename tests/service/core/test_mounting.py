"""The laser's mounting (service/core/mounting.py): frames, covariance, the wrapper around
every method, and that a zero mounting changes nothing."""

from __future__ import annotations

import pickle

import numpy as np
import pytest

from service.core.factory import create_localizer
from service.core.mounting import (
    MountedLocalizer,
    base_covariance,
    check_offset,
    mount,
    to_base,
    to_laser,
)
from service.core.pose import compose, relative
from service.core.types import Estimate
from service.errors import LocalizationError
from sim_publisher.scenario import make_setup

#: The laser 0.3 m forward, 0.1 m left of the base, turned 0.2 rad (the simulator's
#: ``--laser-offset 0.3 0.1 0.2`` of the acceptance test).
OFFSET = np.array([0.3, 0.1, 0.2])


def test_frames_round_trip_and_match_compose() -> None:
    rng = np.random.default_rng(4)
    base = np.column_stack([rng.uniform(-5, 5, (50, 2)), rng.uniform(-3.1, 3.1, 50)])
    laser = to_laser(base, OFFSET)
    for b, lp in zip(base, laser, strict=True):
        assert np.allclose(relative(compose(b, OFFSET), lp), 0.0, atol=1e-12)
    back = to_base(laser, OFFSET)
    assert np.allclose(np.column_stack([back[:, :2] - base[:, :2]]), 0.0, atol=1e-12)
    assert np.allclose(np.angle(np.exp(1j * (back[:, 2] - base[:, 2]))), 0.0, atol=1e-12)
    # one pose as well as an array of poses
    assert to_laser(base[0], OFFSET).shape == (3,)


def test_base_covariance_is_the_jacobian_of_the_change_of_reference() -> None:
    rng = np.random.default_rng(5)
    lp = np.array([1.0, -2.0, 0.7])
    A = rng.normal(size=(3, 3))
    cov = A @ A.T * 1e-3
    got = base_covariance(lp, cov, OFFSET)
    # numerical Jacobian of l -> to_base(l)
    J = np.zeros((3, 3))
    h = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        diff = to_base(lp + d, OFFSET) - to_base(lp - d, OFFSET)
        J[:, k] = diff / (2 * h)
    assert np.allclose(got, J @ cov @ J.T, atol=1e-10)
    # a pure heading uncertainty of the laser moves the base sideways
    only_turn = np.diag([0.0, 0.0, 0.01])
    c = base_covariance(np.zeros(3), only_turn, np.array([0.5, 0.0, 0.0]))
    assert c[1, 1] == pytest.approx(0.25 * 0.01) and c[0, 0] == pytest.approx(0.0)


def test_offsets_are_checked() -> None:
    for bad in ([0, 0], [0, np.nan, 0], [np.inf, 0, 0]):
        with pytest.raises(LocalizationError, match="laser offset"):
            check_offset(bad)
    assert check_offset([0, 0, 4.0])[2] == pytest.approx(4.0 - 2 * np.pi)


def _drive(
    method: str, offset: np.ndarray | None, n: int, given_offset: bool = True
) -> tuple[np.ndarray, np.ndarray, list]:
    """Localise ``n`` scans of setup 1 with the laser mounted at ``offset`` (scans taken at
    truth ⊕ offset; odometry and initial pose the base's); returns (estimates, truth, ests)."""
    s = make_setup(1, seed=3, max_scans=n)
    m = np.zeros(3) if offset is None else offset
    loc = create_localizer(
        method, s.map_data, s.truth[0].copy(), laser_offset=offset if given_offset else None
    )
    ests = []
    for i in range(n):
        ranges, angles = s.laser.scan(compose(s.truth[i], m), i, s.circles(i))
        ests.append(loc.update(ranges, angles, np.asarray(s.odom[i])))
    return np.array([e.pose for e in ests]), np.asarray(s.truth[:n]), ests


@pytest.mark.parametrize("method", ["icp", "lines", "shape"])
def test_zero_offset_is_bit_identical_to_no_offset(method: str) -> None:
    a, _, _ = _drive(method, None, 25)
    b, _, _ = _drive(method, np.zeros(3), 25)
    assert np.array_equal(a, b)
    s = make_setup(1, seed=3, max_scans=2)
    plain = create_localizer(method, s.map_data, s.truth[0].copy())
    zero = create_localizer(method, s.map_data, s.truth[0].copy(), laser_offset=[0.0, 0.0, 0.0])
    assert type(plain) is type(zero)  # not wrapped at all


@pytest.mark.parametrize(("method", "n"), [("icp", 60), ("lines", 60), ("shape", 60)])
def test_a_mounted_laser_gives_the_base_pose(method: str, n: int) -> None:
    """The same drive with the laser 0.3 m forward, 0.1 m left, 0.2 rad turned: the poses
    out are the base's and as accurate as with the laser at the origin."""
    est0, truth, _ = _drive(method, None, n)
    est1, _, ests = _drive(method, OFFSET, n)
    e0 = np.hypot(*(est0[:, :2] - truth[:, :2]).T)
    e1 = np.hypot(*(est1[:, :2] - truth[:, :2]).T)
    h1 = np.abs(np.angle(np.exp(1j * (est1[:, 2] - truth[:, 2]))))
    print(f"{method}: mean error {e0.mean():.4f} m (origin) vs {e1.mean():.4f} m (mounted)")
    assert e1.mean() <= e0.mean() + 0.02 and e1.max() < 0.15 and h1.max() < 0.05
    # without telling the localiser, the poses are the laser's: 0.32 m off the base
    wrong, _, _ = _drive(method, OFFSET, 10, given_offset=False)
    assert np.hypot(*(wrong[:, :2] - truth[:10, :2]).T).mean() > 0.25
    assert all(isinstance(e, Estimate) for e in ests)


class _Fake:
    """A localiser that records what it was given and answers fixed estimates."""

    method = "fake"

    def __init__(self) -> None:
        self.map_data = "map-a"
        self.got: list = []
        self._pose = np.array([1.0, 2.0, 0.5])
        self.unsettled = True

    def update(self, ranges, angles, odom=None):
        self.got.append(("update", None if odom is None else np.array(odom)))
        cand = np.array([[1.0, 2.0, 0.5, 0.1], [4.0, 0.0, -1.0, 0.3]])
        return Estimate(
            pose=self._pose.copy(),
            status="initializing",
            score=0.5,
            covariance=np.diag([0.01, 0.02, 0.003]),
            candidates=cand,
            hypotheses=2,
        )

    def reset(self, initial_pose, odom=None):
        self.got.append(("reset", initial_pose, odom))

    @property
    def pose(self):
        return self._pose

    def set_search_budget(self, ms: float) -> None:
        self.got.append(("budget", ms))


def test_the_wrapper_moves_everything_between_frames() -> None:
    inner = _Fake()
    loc = mount(inner, OFFSET)
    assert isinstance(loc, MountedLocalizer) and mount(inner, None) is inner
    odom = np.array([3.0, 1.0, -0.4])
    est = loc.update(np.ones(3), np.zeros(3), odom)
    assert np.allclose(inner.got[0][1], to_laser(odom, OFFSET))
    assert np.allclose(est.pose, to_base(inner.pose, OFFSET))
    assert np.allclose(loc.pose, est.pose)
    assert np.allclose(
        est.candidates[:, :3], to_base(np.array([[1, 2, 0.5], [4, 0, -1.0]]), OFFSET)
    )
    assert np.allclose(est.candidates[:, 3], [0.1, 0.3]) and est.hypotheses == 2
    assert np.allclose(
        est.covariance, base_covariance(inner.pose, np.diag([0.01, 0.02, 0.003]), OFFSET)
    )
    loc.reset(np.array([0.0, 0.0, 1.0]), odom)
    _, start, o = inner.got[-1]
    assert np.allclose(start, to_laser(np.array([0.0, 0.0, 1.0]), OFFSET))
    assert np.allclose(o, to_laser(odom, OFFSET))
    loc.reset(None)
    assert inner.got[-1] == ("reset", None, None)
    # everything else is the wrapped localiser's
    assert loc.method == "fake" and loc.unsettled is True
    loc.set_search_budget(12.5)
    assert inner.got[-1] == ("budget", 12.5)
    loc.map_data = "map-b"
    assert inner.map_data == "map-b" and loc.map_data == "map-b"
    with pytest.raises(AttributeError):
        _ = loc.no_such_thing


def test_a_mounted_localizer_survives_pickling() -> None:
    """Workers hand a robot's localiser to another worker process by pickling it."""
    s = make_setup(1, seed=3, max_scans=3)
    loc = create_localizer("icp", s.map_data, s.truth[0].copy(), laser_offset=OFFSET)
    ranges, angles = s.laser.scan(compose(s.truth[0], OFFSET), 0)
    loc.update(ranges, angles, np.asarray(s.odom[0]))
    back = pickle.loads(pickle.dumps(loc))
    assert isinstance(back, MountedLocalizer) and np.array_equal(back.offset, loc.offset)
    assert np.allclose(back.pose, loc.pose)
