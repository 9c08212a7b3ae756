"""Stacked per-configuration arrays (service/core/shapes/stacked.py): the row samples and the unit
mean points the matcher takes, against numpy's own expressions."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from service.core import kernels
from service.core.shapes import stacked, two_step


def test_subsample_takes_the_rounded_linspace_rows() -> None:
    for n in range(1, 300, 7):
        pts = np.column_stack([np.arange(n), -np.arange(n)]).astype(float)
        for k in (12, 24, 120):
            want = pts if n <= k else pts[np.linspace(0, n - 1, k).round().astype(int)]
            assert np.array_equal(stacked.subsample(pts, k), want)
            assert np.array_equal(stacked.subsample(pts, k), want)  # memoised rows


@pytest.mark.parametrize("compiled", [True, False])
def test_piece_means_are_numpys_mean_of_the_joined_points(
    compiled: bool, real_scene: Callable, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Mean points of step 1's units (single features and consecutive pairs, wrapping round
    the view): exactly ``np.vstack(points).mean(axis=0)``."""
    if compiled and not kernels.HAVE_NUMBA:
        pytest.skip("numba kernels not installed")
    monkeypatch.setattr(kernels, "HAVE_NUMBA", compiled)
    sc = real_scene(2, 140)
    for C, cyclic in ((sc.P, False), (sc.Q, True)):
        units = two_step._units(C, cyclic)
        pieces = two_step._unit_pieces(units)
        got = stacked.piece_means(C, pieces)
        want = np.array([np.vstack([f.points for f in u.feats]).mean(axis=0) for u in units])
        assert len(units) > 10 and np.array_equal(got, want)
