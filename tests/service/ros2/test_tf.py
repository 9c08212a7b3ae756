"""The planar tf buffer of the ROS 2 front (service/ros2/tf.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.core.pose import compose
from service.ros2.tf import TfBuffer, TfError, TfWait

S = 1_000_000_000


def test_interpolates_odom_to_base_at_the_stamp() -> None:
    tf = TfBuffer()
    tf.add("odom", "base_link", 1 * S, (0.0, 0.0, 3.0))
    tf.add("odom", "base_link", 2 * S, (1.0, 2.0, -3.0))  # yaw crosses pi: the short way
    x, y, yaw = tf.lookup("odom", "base_link", S + S // 4)
    assert (x, y) == pytest.approx((0.25, 0.5))
    short = math.remainder(-3.0 - 3.0, 2 * math.pi)
    assert yaw == pytest.approx(math.remainder(3.0 + 0.25 * short, 2 * math.pi))
    assert tf.lookup("odom", "base_link", 2 * S) == (1.0, 2.0, -3.0)


def test_never_extrapolates() -> None:
    tf = TfBuffer()
    tf.add("odom", "base_link", 10 * S, (0.0, 0.0, 0.0))
    with pytest.raises(TfWait):
        tf.lookup("odom", "base_link", 11 * S)  # newer than the data: wait for it
    with pytest.raises(TfError) as err:
        tf.lookup("odom", "base_link", 9 * S)  # older than the data: gone
    assert not isinstance(err.value, TfWait)
    with pytest.raises(TfWait):
        tf.lookup("odom", "laser", 10 * S)  # a frame nobody published yet


def test_chains_static_and_timed_edges_through_the_common_ancestor() -> None:
    tf = TfBuffer()
    tf.set_static("base_link", "laser", (0.2, 0.0, math.pi / 2))
    tf.set_static("base_footprint", "base_link", (0.0, 0.0, 0.0))
    tf.add("odom", "base_footprint", 0, (1.0, 1.0, 0.5))
    tf.add("odom", "base_footprint", S, (2.0, 1.0, 0.5))
    got = tf.lookup("odom", "laser", S // 2)
    want = compose(np.array([1.5, 1.0, 0.5]), np.array([0.2, 0.0, math.pi / 2]))
    assert np.allclose(got, want)
    # the inverse direction and a lookup between two leaves
    back = tf.lookup("laser", "odom", S // 2)
    assert np.allclose(compose(np.array(got), np.array(back)), 0.0, atol=1e-12)
    assert np.allclose(tf.lookup("base_link", "laser", 123), (0.2, 0.0, math.pi / 2))


def test_unconnected_trees_and_old_samples() -> None:
    tf = TfBuffer(cache_s=1.0)
    tf.add("odom", "base_link", 0, (0.0, 0.0, 0.0))
    tf.add("map2", "other", 0, (0.0, 0.0, 0.0))
    with pytest.raises(TfError, match="not connected"):
        tf.lookup("odom", "other", 0)
    for k in range(1, 40):
        tf.add("odom", "base_link", k * S // 10, (k, 0.0, 0.0))
    with pytest.raises(TfError):
        tf.lookup("odom", "base_link", 0)  # pruned after cache_s
    assert tf.lookup("odom", "base_link", 3 * S) == (30.0, 0.0, 0.0)


def test_out_of_order_samples_are_sorted_in() -> None:
    tf = TfBuffer()
    tf.add("odom", "base_link", 2 * S, (2.0, 0.0, 0.0))
    tf.add("odom", "base_link", 0, (0.0, 0.0, 0.0))
    tf.add("odom", "base_link", S, (5.0, 0.0, 0.0))
    assert tf.lookup("odom", "base_link", S // 2)[0] == pytest.approx(2.5)
