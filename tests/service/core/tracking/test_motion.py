"""The motion seam (service/core/tracking/motion.py): odometry increments, stale odometry,
velocity."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.pose import compose
from service.core.tracking.motion import Motion, MotionConfig
from service.errors import LocalizationError


def test_odometry_increment_is_applied_in_the_robot_frame() -> None:
    m = Motion()
    pose = np.array([1.0, 2.0, np.pi / 2])
    first = m.predict(pose, np.array([10.0, 0.0, 0.0]))
    assert first.source == "odometry"
    np.testing.assert_allclose(first.pose, pose)  # no previous reading: no motion
    # odometry frame: 1 m along its x and a 0.1 rad turn; the robot faces map +y
    nxt = m.predict(pose, np.array([11.0, 0.0, 0.1]))
    np.testing.assert_allclose(nxt.pose, [1.0, 3.0, np.pi / 2 + 0.1], atol=1e-12)
    np.testing.assert_allclose(nxt.delta, [1.0, 0.0, 0.1], atol=1e-12)
    # sigmas grow with the motion: floor + alpha * distance (+ alpha * angle)
    c = MotionConfig()
    s = nxt.sigma
    assert s[0] == pytest.approx(c.sigma_xy_floor + c.alpha_trans_trans + 0.1 * c.alpha_trans_rot)
    assert s[2] == pytest.approx(c.sigma_theta_floor + 0.1 * c.alpha_rot_rot + c.alpha_rot_trans)
    assert s[0] > first.sigma[0]


def test_a_scan_matched_turn_is_not_given_the_raw_odometrys_turn_noise() -> None:
    """``MotionConfig.matched_turn_noise``: an increment measured by a kept scan-to-scan fit
    from the motion model's previous reading gets the sigmas of a straight step; a raw one,
    or one matched from another reading, keeps the turn terms."""
    c = MotionConfig()
    first = np.array([0.0, 0.0, 0.0])
    turned = np.array([-0.07, -0.04, -2.6])  # a 150 deg turn between two scans

    def prior(matched_from: np.ndarray | None) -> np.ndarray:
        m = Motion(c)
        m.predict(np.zeros(3), first)
        return m.predict(np.zeros(3), turned, matched_from).sigma

    raw, matched, elsewhere = prior(None), prior(first.copy()), prior(np.array([0.0, 0.0, 0.1]))
    d = float(np.hypot(0.07, 0.04))
    assert raw[2] == pytest.approx(
        c.sigma_theta_floor + 2.6 * c.alpha_rot_rot + d * c.alpha_rot_trans
    )
    assert matched[2] == pytest.approx(c.sigma_theta_floor + d * c.alpha_rot_trans)
    assert matched[0] == pytest.approx(c.sigma_xy_floor + d * c.alpha_trans_trans)
    assert raw[2] > 5 * matched[2] and raw[0] > 3 * matched[0]
    np.testing.assert_allclose(elsewhere, raw)
    # the share kept is configurable: 1 gives the raw model back
    m = Motion(c.model_copy(update={"matched_turn_noise": 1.0}))
    m.predict(np.zeros(3), first)
    np.testing.assert_allclose(m.predict(np.zeros(3), turned, first.copy()).sigma, raw)


def test_a_stale_reading_holds_and_the_catch_up_is_not_counted_twice() -> None:
    """mit-csail's odometry freezes for a few scans and then jumps: the held scans follow the
    scan, and the jump is applied from where the frozen reading was taken."""
    m = Motion()
    start = np.array([0.0, 0.0, 0.0])
    m.predict(start, np.array([0.0, 0.0, 0.0]))
    moved = m.predict(start, np.array([0.2, 0.0, 0.0]))
    np.testing.assert_allclose(moved.pose, [0.2, 0.0, 0.0], atol=1e-12)
    here = moved.pose  # the scan confirms it
    # frozen: the same reading three times while the robot drives on 0.2 m per scan; the
    # localiser's scan fits move the pose
    for _ in range(3):
        held = m.predict(here, np.array([0.2, 0.0, 0.0]))
        assert held.source == "held"
        np.testing.assert_allclose(held.pose, here)
        assert held.sigma[0] == pytest.approx(MotionConfig().velocity_sigma_xy)
        here = here + np.array([0.2, 0.0, 0.0])
    # the catch-up reading: 0.8 m since the frozen one; applied from where that was taken
    # (x = 0.2), not from the current estimate (x = 0.8)
    caught = m.predict(here, np.array([1.0, 0.0, 0.0]))
    assert caught.source == "odometry"
    np.testing.assert_allclose(caught.pose, [1.0, 0.0, 0.0], atol=1e-12)
    # and after that, increments are from the newest estimate again
    after = m.predict(np.array([1.05, 0.0, 0.0]), np.array([1.1, 0.0, 0.0]))
    np.testing.assert_allclose(after.pose, [1.15, 0.0, 0.0], atol=1e-12)


def test_no_odometry_uses_the_velocity_model_and_odometry_can_be_switched_off() -> None:
    m = Motion()
    p0 = np.array([0.0, 0.0, 0.3])
    assert m.predict(p0, None).source == "velocity"
    m.accepted(p0, np.array([0.1, 0.0, 0.3]))
    pred = m.predict(np.array([0.1, 0.0, 0.3]), None)
    assert pred.pose[0] > 0.1  # keeps (part of) its recent translation
    assert pred.pose[2] == pytest.approx(0.3)
    off = Motion(MotionConfig(use_odometry=False))
    assert off.predict(p0, np.array([5.0, 5.0, 1.0])).source == "velocity"
    with pytest.raises(LocalizationError):
        off.predict(p0, np.array([np.nan, 0.0, 0.0]))  # validated even when unused


def test_reset_with_odometry_bridges_a_restart() -> None:
    m = Motion()
    pose = np.array([2.0, 1.0, 0.5])
    m.reset(np.array([4.0, 4.0, 0.0]))
    pred = m.predict(pose, np.array([4.0, 4.0, 0.4]))  # turned 0.4 rad since the saved reading
    np.testing.assert_allclose(pred.pose, compose(pose, np.array([0.0, 0.0, 0.4])), atol=1e-12)


def test_the_scan_on_the_reset_reading_anchors_the_next_increment_at_its_fit() -> None:
    """A global fix is confirmed by resetting the tracker to the hypothesis with this scan's
    odometry and fitting this scan: the next increment applies to the fit, not to the
    hypothesis (fr079 start 1714: anchored at the hypothesis, the track stayed 0.3 m off)."""
    m = Motion()
    reading = np.array([5.0, 5.0, 0.0])
    hypothesis = np.array([1.0, 1.0, 0.0])
    m.reset(reading)
    held = m.predict(hypothesis, reading)  # the confirming scan: same reading as the reset
    assert held.source == "held"
    np.testing.assert_allclose(held.pose, hypothesis)
    fit = np.array([1.0, 1.3, 0.0])  # the scan moved the pose 0.3 m
    nxt = m.predict(fit, np.array([5.1, 5.0, 0.0]))
    assert nxt.source == "odometry"
    np.testing.assert_allclose(nxt.pose, [1.1, 1.3, 0.0], atol=1e-12)
    # a reading that stays frozen after that scan is stale as before: the jump is applied
    # from the fit of the scan where it was taken
    m.reset(reading)
    m.predict(hypothesis, reading)
    m.predict(fit, reading)  # frozen on the next scan too; the robot drove on
    caught = m.predict(fit + np.array([0.1, 0.0, 0.0]), np.array([5.2, 5.0, 0.0]))
    np.testing.assert_allclose(caught.pose, [1.2, 1.3, 0.0], atol=1e-12)


def test_a_reset_pose_known_to_some_precision_is_the_prior_of_the_scan_taken_there() -> None:
    """A global fix the drive's evidence found is confirmed under a prior of the precision
    the caller gives (``GlobalConfig.confirm_drive_prior``): the scan on the reset reading
    gets the reset pose with those sigmas as an odometry prior (the scan refines it, it does
    not decide alone); the anchoring at that scan's fit is unchanged, and the precision is
    used once -- a later frozen reading holds with the weak sigmas again."""
    m = Motion()
    reading = np.array([5.0, 5.0, 0.0])
    hypothesis = np.array([1.0, 1.0, 0.7])
    m.reset(reading, known=(0.1, 0.03))
    pred = m.predict(hypothesis, reading)
    assert pred.source == "odometry"
    np.testing.assert_allclose(pred.pose, hypothesis)
    np.testing.assert_allclose(pred.sigma, [0.1, 0.1, 0.03], rtol=1e-9)
    fit = np.array([1.0, 1.1, 0.7])
    nxt = m.predict(fit, np.array([5.1, 5.0, 0.0]))
    np.testing.assert_allclose(nxt.pose, compose(fit, np.array([0.1, 0.0, 0.0])), atol=1e-12)
    frozen = m.predict(nxt.pose, np.array([5.1, 5.0, 0.0]))
    assert frozen.source == "held"
    assert frozen.sigma[0] == pytest.approx(MotionConfig().velocity_sigma_xy)
    # without a precision, or when the first reading after the reset is fresh, nothing changes
    m.reset(reading)
    assert m.predict(hypothesis, reading).source == "held"
    m.reset(reading, known=(0.1, 0.03))
    moved = m.predict(hypothesis, np.array([5.1, 5.0, 0.0]))
    assert moved.source == "odometry"
    assert moved.sigma[0] == pytest.approx(0.03 + 0.1 * 0.1)  # the increment's own sigma
    later = m.predict(moved.pose, np.array([5.1, 5.0, 0.0]))
    assert later.source == "held"
