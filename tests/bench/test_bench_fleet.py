"""The pure helpers of the fleet, flood and soak benchmarks: a run's figures from the received
poses, the acceptance verdicts, the largest fleet per world, the flood's garbage repertoire
and the soak's results page."""

from __future__ import annotations

import math

import numpy as np

from bench.bench_fleet import cold_ok, largest, line_ok
from bench.bench_flood import flood_messages
from bench.fleet_run import summarise_fleet
from bench.scale_walks import RobotPlan
from bench.soak_report import page


def _plan(rid: str, n: int) -> RobotPlan:
    truth = np.c_[np.arange(n) * 0.1, np.zeros(n), np.zeros(n)]
    return RobotPlan(rid, False, False, np.arange(n), truth, None)


def test_summarise_counts_answered_first_scans_and_poses_off() -> None:
    plans = [_plan("a", 4), _plan("b", 4)]
    rows = [
        ("a", 0, 10.0, 10.010, [0.0, 0.0, 0.0], "tracking"),
        ("a", 1, 10.1, 10.130, [0.1, 0.0, 0.0], "tracking"),
        ("a", 1, 10.1, 10.200, [9.0, 0.0, 0.0], "tracking"),  # a repeat: the first counts
        ("a", 3, 10.3, 10.320, [0.5, 0.0, 0.3], "lost"),  # 0.2 m and 17 deg off: wrong
        ("b", 2, 10.2, 10.260, [0.2, 0.0, 0.0], "tracking"),  # its first scan was replaced
        ("b", 9, 10.9, 10.950, [0.0, 0.0, 0.0], "tracking"),  # not a scan of the run
    ]
    r = summarise_fleet(plans, rows, 4)
    assert r["poses"] == 4 and math.isclose(r["answered"], 0.5)
    assert math.isclose(r["answered_min"], 0.25)
    assert r["first_answered"] == 1 and math.isinf(r["first_max"])
    assert r["off"] == 1 and math.isclose(r["err_max"], 0.2) and r["wrong"] == 1
    assert r["not_tracking"] == 1
    assert math.isclose(r["max"], 60.0, abs_tol=1e-6)


def test_verdicts_and_the_largest_fleet() -> None:
    good = {
        "answered": 0.995,
        "off": 0,
        "wrong": 0,
        "p99": 40.0,
        "first_max": 30.0,
        "map": "metric",
    }
    assert cold_ok(good) and line_ok(good)
    assert not cold_ok({**good, "first_max": math.inf})
    assert not cold_ok({**good, "p99": 60.0}) and line_ok({**good, "p99": 60.0})
    assert not line_ok({**good, "off": 1}) and not line_ok({**good, "wrong": 1})
    # a floor plan's scale error puts tracked poses 0.1-0.2 m from the truth: only wrong counts
    assert line_ok({**good, "map": "schematic", "off": 9})
    assert not line_ok({**good, "map": "schematic", "off": 9, "wrong": 1})
    runs = [
        {**good, "world": "office", "map": "metric", "n": 10},
        {**good, "world": "office", "map": "metric", "n": 50},
        {**good, "world": "office", "map": "metric", "n": 50, "answered": 0.9},
        {**good, "world": "office", "map": "metric", "n": 100, "p99": 300.0},
        {**good, "world": "1000", "map": "metric", "n": 10, "off": 2},
    ]
    assert largest(runs) == {("office", "metric"): 10, ("1000", "metric"): 0}


def test_flood_messages_hit_every_kind_of_key() -> None:
    keys = {k for _n, k, _p, _d, _e in flood_messages("r1", 1)}
    assert "shapeloc/robots/r1/scan" in keys and "shapeloc/robots/r1/config" in keys
    assert any(k.startswith("shapeloc/maps/") for k in keys)
    assert any(k.startswith("shapeloc/robots/ghost") for k in keys)
    assert "shapeloc/robots/r1/scan/extra" in keys and "shapeloc/robots/r@b/scan" in keys


def test_soak_page_states_the_verdicts() -> None:
    row = {
        "t_s": 60.0, "sent": 100, "answered": 90, "answered_share": 0.9, "p50_ms": 5.0,
        "p99_ms": math.nan, "robots_served": 2, "min_per_robot": 40,
        "rss_service_kib": 1024, "rss_workers_kib": 2048,
        "errors": {"scan.Skipped": 10, "scan.InvalidMessage": 7},
    }  # fmt: skip
    report = {
        "robots": 2, "rate_hz": 10.0, "method": "shape", "garbage_rate": 100.0, "workers": 2,
        "minutes": 1.0, "interval_s": 60.0, "odom": True,
        "load_before": (0.5, 0.5, 0.5), "load_after": (0.6, 0.6, 0.6), "rows": [row],
        "summary": {
            "rss_growth_after_s": 60.0,
            "rss_growth": {"rss_service_kib": 0.01, "rss_workers_kib": 0.07},
            "crashes": 0, "intervals_with_a_starved_robot": [], "poses_total": 90,
            "sent_total": 100, "errors_total": {"scan.InvalidMessage": 7},
        },
    }  # fmt: skip
    text = page(report, "python -m bench.soak")
    assert "| 60 | 100 | 90 | 90.0 % | 5 | n/a | 2 | 40 | 1.0 | 2.0 | 7 |" in text
    assert "workers +7.0 %: **FAIL**" in text
    assert "Crashes (service exit or worker restart): 0: **PASS**" in text
