"""Global search's distance-field kernels (service/core/kernels/search.py) against their
references: the table lookup gives the direct kernel's scores to the bit, the support count
gives the numpy reference's fractions exactly."""

from __future__ import annotations

import numpy as np
import pytest

from service.core import kernels
from service.core.kernels import search as search_kernels
from service.core.reloc.global_localization import load_or_build_index
from service.core.sensor import scoring as gs
from sim_publisher.office import office_schematic_map

pytestmark = pytest.mark.skipif(not kernels.HAVE_NUMBA, reason="numba kernels not installed")


def _poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack([rng.uniform(-1, 15, n), rng.uniform(-1, 24, n), rng.uniform(-4, 4, n)])


@pytest.mark.parametrize("sigma", [0.015, 0.05, 0.1])
def test_table_scores_equal_the_direct_kernel_bit_for_bit(sigma: float) -> None:
    idx = load_or_build_index(office_schematic_map())
    rng = np.random.default_rng(7)
    poses, pts = _poses(rng, 400), rng.uniform(-6, 6, size=(80, 2))
    f = idx.sensor.field
    args = (float(f.origin[0]), float(f.origin[1]), float(f.resolution))
    direct = search_kernels.field_scores(f.values, *args, poses, pts, sigma, 10.0)
    table, outside = idx.sensor.score_table(sigma)
    looked_up = search_kernels.table_scores(table, outside, *args, poses, pts)
    assert np.array_equal(direct, looked_up)
    assert np.ptp(direct) > 0.02  # inside and outside the field both occur
    assert idx.sensor.score_table(sigma)[0] is table  # built once


def test_table_scores_with_repeated_headings_equal_the_direct_kernel() -> None:
    # a polish's grids as poses: each base pose's 5 headings recur 25 times, interleaved (12
    # base poses, 60 distinct headings), in order and shuffled
    idx = load_or_build_index(office_schematic_map())
    rng = np.random.default_rng(9)
    grid = gs.polish_offsets(0.05, 0.02)
    poses = (_poses(rng, 12)[:, None, :] + grid[None, :, :]).reshape(-1, 3)
    shuffled = poses[rng.permutation(len(poses))]
    pts = rng.uniform(-6, 6, size=(80, 2))
    f = idx.sensor.field
    args = (float(f.origin[0]), float(f.origin[1]), float(f.resolution))
    table, outside = idx.sensor.score_table(0.05)
    for ps in (poses, shuffled):
        direct = search_kernels.field_scores(f.values, *args, ps, pts, 0.05, 10.0)
        assert np.array_equal(direct, search_kernels.table_scores(table, outside, *args, ps, pts))


@pytest.mark.parametrize("steps", [(0.05, 0.02), (0.015, 0.006), (0.15, 0.06)])
def test_grid_scores_equal_the_scores_of_every_grid_pose(steps: tuple[float, float]) -> None:
    # the polish's grid kernel computes each point's field row and column once per heading
    # and offset: the scores of the 125 poses must be those the per-pose kernels give
    idx = load_or_build_index(office_schematic_map())
    rng = np.random.default_rng(10)
    base, pts = _poses(rng, 12), rng.uniform(-6, 6, size=(80, 2))
    cand = (base[:, None, :] + gs.polish_offsets(*steps)[None, :, :]).reshape(-1, 3)
    f = idx.sensor.field
    args = (float(f.origin[0]), float(f.origin[1]), float(f.resolution))
    table, outside = idx.sensor.score_table(0.05)
    grid = search_kernels.grid_scores(table, outside, *args, base, *gs.polish_axes(*steps), pts)
    direct = search_kernels.field_scores(f.values, *args, cand, pts, 0.05, 10.0)
    assert grid.shape == (12, 125)
    assert np.array_equal(grid.reshape(-1), direct)
    assert np.ptp(direct) > 0.02


def test_polish_with_the_grid_kernel_equals_the_numpy_reference(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    idx = load_or_build_index(office_schematic_map())
    rng = np.random.default_rng(11)
    poses, pts = _poses(rng, 20), rng.uniform(-6, 6, size=(80, 2))
    got, got_score = idx.sensor.polish(poses, pts, 0.05, prior=0.02)
    monkeypatch.setattr(gs.kernels, "HAVE_NUMBA", False)
    ref, ref_score = idx.sensor.polish(poses, pts, 0.05, prior=0.02)
    assert np.array_equal(got, ref)
    assert np.max(np.abs(got_score - ref_score)) < 1e-12


def test_support_kernel_equals_the_numpy_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    idx = load_or_build_index(office_schematic_map())
    rng = np.random.default_rng(8)
    poses, pts = _poses(rng, 300), rng.uniform(-6, 6, size=(80, 2))
    got = idx.sensor.support(poses, pts, 0.1)
    monkeypatch.setattr(gs.kernels, "HAVE_NUMBA", False)
    ref = idx.sensor.support(poses, pts, 0.1)
    assert np.array_equal(got, ref)
    assert np.ptp(ref) > 0.05


def test_field_crossings_equal_the_numpy_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    # the beams' march on the distance field: the kernel's count per pose must be the numpy
    # reference's, on poses inside and outside the office and beams of every length
    idx = load_or_build_index(office_schematic_map())
    rng = np.random.default_rng(11)
    poses = _poses(rng, 300)
    angles = np.sort(rng.uniform(-np.pi, np.pi, 40))
    ranges = rng.uniform(0.3, 25.0, 40)
    compiled = idx.sensor.crossings(poses, ranges, angles, 0.5)
    monkeypatch.setattr(kernels, "HAVE_NUMBA", False)
    reference = idx.sensor.crossings(poses, ranges, angles, 0.5)
    assert np.array_equal(compiled, reference)
    assert compiled.min() == 0.0 and compiled.max() > 0.3  # crossing and clear poses occur
