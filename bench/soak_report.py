"""The results page of the soak (``python -m bench.soak --out docs/results/soak.md``).

:func:`page` turns the soak's report (:func:`bench.soak.run`) into markdown: the command, the
commit, the machine (CPU model and cores) and the load average, one table row per interval
(scans sent, poses, latency, robots served, the fewest poses of a robot, the resident memory
of the service process and of its workers, the rejections counted in health) and the
verdicts: RSS growth after the warm-up (<= 5 %), crashes, intervals with a starved robot.
The page is written whole every time (no history).
"""

from __future__ import annotations

import datetime as dt
import math
from typing import Any

from bench.bench_fleet import machine, md_table
from bench.scale_report import git_commit

#: The soak's memory acceptance: RSS growth after the warm-up.
MAX_RSS_GROWTH = 0.05

HEAD = (
    "t s", "scans sent", "poses", "answered", "p50 ms", "p99 ms", "robots served",
    "fewest poses of a robot", "service RSS MiB", "workers RSS MiB", "rejected (this interval)",
)  # fmt: skip


def _cells(r: dict[str, Any]) -> list[str]:
    rejected = sum(v for k, v in r["errors"].items() if k != "scan.Skipped")
    p50, p99 = r["p50_ms"], r["p99_ms"]
    return [
        f"{r['t_s']:.0f}",
        str(r["sent"]),
        str(r["answered"]),
        f"{100 * r['answered_share']:.1f} %",
        "n/a" if math.isnan(p50) else f"{p50:.0f}",
        "n/a" if math.isnan(p99) else f"{p99:.0f}",
        str(r["robots_served"]),
        str(r["min_per_robot"]),
        f"{r['rss_service_kib'] / 1024:.1f}",
        f"{r['rss_workers_kib'] / 1024:.1f}",
        str(rejected),
    ]


def _pct(g: float | None) -> str:
    return "n/a" if g is None else f"{100 * g:+.1f} %"


def page(report: dict[str, Any], command: str) -> str:
    """The markdown page of one soak run."""
    s = report["summary"]
    g = s["rss_growth"]
    share = s["poses_total"] / s["sent_total"] if s["sent_total"] else math.nan
    ok_rss = all(v is not None and v <= MAX_RSS_GROWTH for v in g.values())
    load_b = " ".join(f"{v:.2f}" for v in report["load_before"])
    load_a = " ".join(f"{v:.2f}" for v in report["load_after"])
    odom = "with odometry"
    if not report.get("odom"):
        odom = "without odometry (the shape matching runs on every scan)"
    lines = [
        "# Soak (bench/soak.py)",
        "",
        f"Command: `{command}`  ",
        f"Commit: `{git_commit()}`, {dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M UTC}; machine: "
        f"{machine()}; load average before {load_b}, after {load_a}.  ",
        f"{report['robots']} robots x {report['rate_hz']:g} Hz, method `{report['method']}`, "
        f"{odom}, half on the office's metric map and half on its floor plan; "
        f"{report['garbage_rate']:g} malformed messages per second beside them (on the robots' "
        f"own scan keys, unknown robots, maps, configurations); {report['workers']} workers "
        f"(+ the search worker); {report['minutes']:g} minutes, a row every "
        f"{report['interval_s']:g} s. The load generator shares the cores.",
        "",
        md_table(HEAD, [_cells(r) for r in report["rows"]]),
        "",
        f"- Poses: {s['poses_total']} for {s['sent_total']} scans ({100 * share:.1f} %; the rest "
        "were replaced under latest-wins by the robot's next scan, counted as `scan.Skipped`).",
        f"- RSS growth after {s['rss_growth_after_s']:.0f} s (warm-up): service process "
        f"{_pct(g['rss_service_kib'])}, workers {_pct(g['rss_workers_kib'])}: "
        f"**{'PASS' if ok_rss else 'FAIL'}** (limit +{100 * MAX_RSS_GROWTH:g} %).",
        f"- Crashes (service exit or worker restart): {s['crashes']}: "
        f"**{'PASS' if s['crashes'] == 0 else 'FAIL'}**.",
        f"- Intervals in which some robot got no pose (after the first): "
        f"{s['intervals_with_a_starved_robot'] or 'none'}: "
        f"**{'PASS' if not s['intervals_with_a_starved_robot'] else 'FAIL'}**.",
        f"- Rejections counted in health, by kind: {s['errors_total']}.",
        "",
    ]
    return "\n".join(lines)
