"""The relations metric (Kümmerle et al. 2009) on synthetic cases with known answers, and on the
excerpts' reference tracks."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from service.adapters.logs import Relations, load_reference, load_relations, relations_error
from service.core.pose import compose, relative
from service.errors import LogFormatError

DATA = Path(__file__).resolve().parents[3] / "data" / "real"


def _trajectory(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    poses = [np.zeros(3)]
    for _ in range(n - 1):
        step = np.array([rng.uniform(0.1, 0.5), rng.normal(0, 0.05), rng.normal(0, 0.2)])
        poses.append(compose(poses[-1], step))
    return np.arange(n, dtype=np.float64) * 0.5 + 100.0, np.array(poses)


def _relations(stamps: np.ndarray, poses: np.ndarray, pairs: list[tuple[int, int]]) -> Relations:
    return Relations(
        t1=stamps[[a for a, _ in pairs]],
        t2=stamps[[b for _, b in pairs]],
        delta=np.array([relative(poses[a], poses[b]) for a, b in pairs]),
    )


def test_exact_and_rigidly_moved_estimates_score_zero() -> None:
    t, p = _trajectory(40, seed=1)
    rel = _relations(t, p, [(i, i + 1) for i in range(39)] + [(0, 39), (5, 30)])
    err = relations_error(t, p, rel)
    assert err.used == 41 and err.skipped == 0
    assert err.translation_max < 1e-12 and err.rotation_max < 1e-9
    # the metric ignores the estimate's global frame
    moved = np.array([compose([3.0, -2.0, 1.2], q) for q in p])
    assert relations_error(t, moved, rel).translation_max < 1e-9


def test_known_translation_and_rotation_errors() -> None:
    t, p = _trajectory(10, seed=2)
    rel = _relations(t, p, [(0, 1), (1, 2), (2, 3), (4, 5)])
    est = p.copy()
    est[2] = compose(p[2], [0.1, 0.0, 0.0])  # 0.1 m ahead in its own frame
    est[5] = compose(p[5], [0.0, 0.0, 0.05])  # 0.05 rad turned
    err = relations_error(t, est, rel)
    # (1,2): 0.1 m; (2,3): the error seen from the moved pose 2 -> 0.1 m too; (0,1): 0
    assert err.translation == pytest.approx([0.0, 0.1, 0.1, 0.0], abs=1e-12)
    assert err.rotation == pytest.approx([0.0, 0.0, 0.0, math.degrees(0.05)], abs=1e-9)
    assert err.translation_mean == pytest.approx(0.05)
    assert err.translation_std == pytest.approx(0.05)
    assert err.translation_max == pytest.approx(0.1)
    assert err.rotation_mean == pytest.approx(math.degrees(0.05) / 4)


def test_invalid_estimates_and_stamp_tolerance_skip_relations() -> None:
    t, p = _trajectory(6, seed=3)
    rel = _relations(t, p, [(0, 1), (1, 2), (3, 4)])
    valid = np.array([True, False, True, True, True, True])
    err = relations_error(t, p, rel, valid)
    assert err.used == 1 and err.skipped == 2
    nan = p.copy()
    nan[3] = np.nan
    assert relations_error(t, nan, rel).used == 2
    # estimates 2 us off the relation stamps: outside the default 1 us, inside 1e-5
    assert relations_error(t + 2e-6, p, rel).used == 0
    assert relations_error(t + 2e-6, p, rel, tolerance=1e-5).used == 3
    none = relations_error(t[:0], p[:0], rel)
    assert none.used == 0 and math.isnan(none.translation_mean)
    with pytest.raises(LogFormatError, match="6 stamps but 5 poses"):
        relations_error(t, p[:5], rel)


@pytest.mark.parametrize(
    ("name", "count", "tolerance", "mean"),
    [("intel", 4, 1e-6, 0.0508), ("fr079", 64, 1e-6, 0.0323), ("mit-csail", 154, 1e-5, 0.0720)],
)
def test_reference_tracks_of_the_excerpts(
    name: str, count: int, tolerance: float, mean: float
) -> None:
    track = load_reference(DATA / f"{name}.300.gfs_reference_per_scan.txt")
    rel = load_relations(DATA / f"{name}.300.relations")
    assert len(rel) == count and rel.tolerance == pytest.approx(tolerance)
    err = relations_error(track.stamps, track.poses, rel)
    assert err.used == count and err.skipped == 0
    assert err.translation_mean == pytest.approx(mean, abs=5e-5)


def test_malformed_relations_name_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.relations"
    path.write_text("1.0 2.0 0.1 0 0 0 0 0.01\n2.0 3.0 0.1 0 0 0 0\n")
    with pytest.raises(LogFormatError, match=r"bad\.relations:2: expected 't1 t2 x y z roll"):
        load_relations(path)
    path.write_text("1.0 2.0 0.1 0 0 0 0 0.01\n2.0 3.0 0.1 0 0 0 0 nan\n")
    with pytest.raises(LogFormatError, match=r"bad\.relations:2: non-finite"):
        load_relations(path)
