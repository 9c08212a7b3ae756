"""Value types and helpers shared by every method (service/core/types.py)."""

from __future__ import annotations

import math

import numpy as np

from service.core.types import wrap_angle


def test_wrap_angle_of_a_float_is_the_array_result_bit_for_bit() -> None:
    """A Python float takes a scalar path (float %); it returns what the numpy path returns
    for the same value, including the ends of (-pi, pi], multiples of pi and signed zeros."""
    rng = np.random.default_rng(7)
    vals = np.concatenate(
        [
            rng.normal(0.0, 4.0, 200_000),
            rng.uniform(-1e4, 1e4, 50_000),
            np.arange(-40, 41) * (math.pi / 2),
            [0.0, -0.0, math.pi, -math.pi, 1e-300, -1e-300, 1e12, -1e12],
            [np.nextafter(math.pi, 0.0), np.nextafter(-math.pi, 0.0)],
        ]
    )
    arr = wrap_angle(vals)
    assert isinstance(arr, np.ndarray)
    one = [wrap_angle(v) for v in vals.tolist()]
    assert all(type(w) is float for w in one)
    assert np.array_equal(np.array(one), arr)
    assert np.array_equal(np.signbit(np.array(one)), np.signbit(arr))
    assert wrap_angle(-math.pi) == math.pi and wrap_angle(3 * math.pi) == math.pi
    assert np.all((arr > -math.pi) & (arr <= math.pi))
    assert wrap_angle(np.float64(7.0)) == wrap_angle(np.array([7.0]))[0]  # numpy scalars too
