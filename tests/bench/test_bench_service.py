"""The pure helpers of ``bench/bench_service.py``: the back-and-forth walk, its odometry, the
correctness test, a row's figures and the acceptance lines."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest


@pytest.fixture(scope="module")
def bs():
    return importlib.import_module("bench.bench_service")


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Motion from poses a to b in a's frame."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    d = b[:, :2] - a[:, :2]
    th = (b[:, 2] - a[:, 2] + np.pi) % (2 * np.pi) - np.pi
    return np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], th]


def test_ping_pong_reverses_without_repeating_the_end(bs) -> None:
    assert bs.ping_pong(0, 4, 9).tolist() == [0, 1, 2, 3, 2, 1, 0, 1, 2]
    assert bs.ping_pong(2, 4, 5).tolist() == [2, 3, 2, 1, 0]
    assert np.all(np.abs(np.diff(bs.ping_pong(5, 7, 40))) == 1)
    with pytest.raises(ValueError):
        bs.ping_pong(0, 1, 3)


def test_odometry_frame_starts_at_origin_and_keeps_increments(bs) -> None:
    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(-5, 5, (20, 2)), rng.uniform(-np.pi, np.pi, 20)]
    o = bs.odometry_frame(p)
    np.testing.assert_allclose(o[0], [0.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(_rel(o[:-1], o[1:]), _rel(p[:-1], p[1:]), atol=1e-9)


def test_walk_odometry_follows_the_walk_across_turnarounds(bs) -> None:
    # a straight 1 m tour in 21 scans walked there and back twice
    m = 21
    tour = np.c_[np.linspace(0, 1, m), np.zeros(m), np.full(m, 0.3)]
    walk = tour[bs.ping_pong(3, m, 90)]
    odom = bs.walk_odometry(walk, seed=4)
    assert odom.shape == walk.shape
    np.testing.assert_allclose(odom[0], 0.0, atol=1e-12)
    true_inc, odo_inc = _rel(walk[:-1], walk[1:]), _rel(odom[:-1], odom[1:])
    # every increment (the reversals included) is the true one up to the error model
    np.testing.assert_allclose(odo_inc[:, 0], true_inc[:, 0], atol=0.01)
    assert np.all(np.sign(odo_inc[:, 0]) == np.sign(true_inc[:, 0]))
    assert np.all(np.abs(odo_inc[:, 2]) < math.radians(1.0))
    # same seed, same odometry
    np.testing.assert_array_equal(odom, bs.walk_odometry(walk, seed=4))


def test_mirror_poses(bs) -> None:
    out = bs.mirror_poses(np.array([[1.0, 2.0, 0.5]]))
    np.testing.assert_allclose(out, [[1.0, -2.0, -0.5]])


def test_pose_correct_thresholds_and_wrap(bs) -> None:
    t = np.array([[0.0, 0.0, np.pi - 0.01]] * 4)
    e = np.array(
        [
            [0.3, 0.3, -np.pi + 0.05],  # 0.42 m, 3.4 deg across the wrap
            [0.4, 0.4, np.pi - 0.01],  # 0.57 m
            [0.0, 0.0, np.pi - 0.2],  # 10.9 deg
            [0.0, 0.0, np.pi - 0.01],
        ]
    )
    assert bs.pose_correct(e, t, 0.5, 10.0).tolist() == [True, False, False, True]


def _plan(bs, rid: str, n: int, searching: bool = False):
    truth = np.c_[np.arange(n) * 0.05, np.zeros(n), np.zeros(n)]
    return bs.RobotPlan(rid, searching, False, np.arange(n), truth, None)


def test_summarise_row_counts_window_answers_correctness_and_fixes(bs) -> None:
    rate, t0 = 10.0, 100.0
    plans = [_plan(bs, "r0", 11), _plan(bs, "r1", 11), _plan(bs, "s0", 11, searching=True)]
    # window [t0 + 0.2, t0 + 1.0): seqs 3..10 of every robot (scheduled t0 + (k-1)/10 + j/30)
    rows = []
    for seq in range(1, 11):
        stamp = t0 + (seq - 1) / rate
        good = [seq * 0.05, 0.0, 0.0]
        rows.append(("r0", seq, stamp, stamp + 0.010, good, "tracking"))
        if seq % 2 == 0:  # r1: every other scan, one of them confidently wrong
            pose = [seq * 0.05 + (1.0 if seq == 6 else 0.0), 0.0, 0.0]
            rows.append(("r1", seq, stamp, stamp + 0.030, pose, "tracking"))
        status = "tracking" if seq in (5, 6) else "initializing"
        rows.append(("s0", seq, stamp, stamp + 0.050, good, status))
    rows.append(("r0", 4, t0, t0 + 5.0, [0.0, 0.0, 0.0], "tracking"))  # duplicate: ignored
    fixes = [("s0", 5, [0.25, 0.0, 0.0]), ("s0", 6, [0.3, 0.0, 0.0])]
    spec = bs.RowSpec("office", "metric", 2, rate, 1)
    r = bs.summarise_row(
        spec, plans, rows, fixes, t0=t0, lo=t0 + 0.2, hi=t0 + 1.0, correct_m=0.5, correct_deg=10
    )
    t = r["tracked"]
    assert t["robots"] == 2 and t["poses"] == 8 + 4
    assert t["answered_mean"] == pytest.approx((1.0 + 0.5) / 2)
    assert t["answered_min"] == pytest.approx(0.5)
    assert not t["starved"]  # 0.5 is not below half of the mean 0.75
    assert t["confident_wrong"] == 1 and t["correct"] == pytest.approx(11 / 12)
    assert t["p50"] == pytest.approx(10.0, abs=1e-6)
    assert t["max"] == pytest.approx(30.0, abs=1e-6)  # the slowest tracked pose (r1's)
    s = r["searchers"]
    assert s["robots"] == 1 and s["answered_mean"] == 1.0
    assert s["fixes"] == 1 and s["fixes_correct"] == 1  # the 2 tracking poses are one fix
    assert s["searching_share"] == pytest.approx(6 / 8)
    assert s["p50"] == pytest.approx(50.0, abs=1e-6)


def test_starved_robot_is_flagged(bs) -> None:
    plans = [_plan(bs, "r0", 11), _plan(bs, "r1", 11)]
    rows = [("r0", k, 100.0, 100.01, [k * 0.05, 0, 0], "tracking") for k in range(1, 11)]
    spec = bs.RowSpec("office", "metric", 2, 10.0)
    r = bs.summarise_row(
        spec, plans, rows, [], t0=100.0, lo=100.0, hi=101.0, correct_m=0.5, correct_deg=10
    )
    assert r["tracked"]["starved"] and r["tracked"]["answered_min"] == 0.0
    assert "searchers" not in r


def _result(world, mk, n, rate, k, answered, p99, starved=False):
    tracked = {
        "answered_mean": answered,
        "answered_min": answered,
        "p50": p99 / 2,
        "p99": p99,
        "worst_robot_p99": p99,
        "starved": starved,
    }
    return {"world": world, "map": mk, "n": n, "rate": rate, "k": k, "tracked": tracked}


def test_acceptance_lines_and_search_pairs(bs) -> None:
    results = [
        _result("office", "metric", 20, 10.0, 0, 0.995, 30.0),
        _result("office", "schematic", 20, 10.0, 0, 0.98, 30.0),
        _result("1000", "metric", 20, 10.0, 0, 1.0, 60.0),
        _result("office", "metric", 40, 5.0, 0, 1.0, 20.0, starved=True),
        _result("office", "metric", 20, 10.0, 0, 1.0, 31.0),
        _result("office", "metric", 20, 10.0, 1, 1.0, 34.0),
    ]
    lines = bs.acceptance_lines(results)
    assert [ok for _n, ok, _f in lines] == [True, False, False, False, True]
    assert lines[-1][0].startswith("searching: office metric N=20@10Hz K=1")
    (pair,) = bs.search_pairs(results)
    assert pair["p99_without"] == 31.0  # the nearest K=0 row of the same world/map/N/rate
    assert pair["adds_p99"] == pytest.approx(3.0)
    results[-1]["tracked"]["max"] = 48.0
    assert bs.pair_cells(bs.search_pairs(results)[0])[-1] == "nan / 48.0"
    results[-1]["tracked"]["p99"] = 37.0
    assert not bs.search_pairs(results)[0]["ok"]


def test_acceptance_rows_cover_the_issue(bs) -> None:
    rows = bs.acceptance_rows()
    labels = [r.label for r in rows]
    assert "office metric N=20@10Hz K=0" in labels
    assert "office schematic N=20@10Hz K=0" in labels
    assert "building-1000 metric N=20@10Hz K=0" in labels
    assert "building-1000 schematic N=20@10Hz K=0" in labels
    assert "office metric N=40@5Hz K=0" in labels
    assert labels[-2:] == ["office metric N=20@10Hz K=0", "office metric N=20@10Hz K=1"]
