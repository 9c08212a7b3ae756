"""Tables and the report of the service scale benchmark (``bench/bench_service.py``).

The staggered fleet's acceptance: its thresholds, the rows (:func:`acceptance_rows`) and the
PASS/FAIL lines (:func:`acceptance_lines`, :func:`row_ok`); what a searching robot adds to the
tracked robots' latency (:func:`search_pairs`); the cells of the rows, searchers and pairs tables as
plain text (:func:`text_table`) or markdown (:func:`markdown_table`); and the markdown report
``--out`` writes (:func:`report`, with the commit from :func:`git_commit` and
:data:`METHOD_TEXT`).
"""

from __future__ import annotations

import math
import subprocess
from pathlib import Path
from typing import Any

from bench.scale_row import RowSpec
from bench.scale_walks import world_name

REPO = Path(__file__).resolve().parents[1]

#: Acceptance thresholds of the staggered fleet (20 robots x 10 Hz, starts spread).
ACCEPT_ANSWERED = 0.99
ACCEPT_P99_MS = 50.0
ACCEPT_SEARCH_ADDS_MS = 5.0


def row_ok(r: dict[str, Any]) -> bool:
    """Acceptance of one scale row: >= 99 % answered, p99 <= 50 ms, none starved."""
    t = r["tracked"]
    return t["answered_mean"] >= ACCEPT_ANSWERED and t["p99"] <= ACCEPT_P99_MS and not t["starved"]


def search_pairs(results: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Each row with K > 0 against the nearest K = 0 row of the same world, map, N and rate:
    what the searching robots add to the tracked robots' p50/p99."""
    out = []
    for i, r in enumerate(results):
        if not r["k"]:
            continue
        same = [
            (abs(j - i), b)
            for j, b in enumerate(results)
            if not b["k"] and all(b[f] == r[f] for f in ("world", "map", "n", "rate"))
        ]
        if not same:
            continue
        b = min(same, key=lambda x: x[0])[1]
        out.append(
            {
                "label": f"{world_name(r['world'])} {r['map']} N={r['n']}@{r['rate']:g}Hz",
                "k": r["k"],
                "p50_with": r["tracked"]["p50"],
                "p50_without": b["tracked"]["p50"],
                "p99_with": r["tracked"]["p99"],
                "p99_without": b["tracked"]["p99"],
                "adds_p50": r["tracked"]["p50"] - b["tracked"]["p50"],
                "adds_p99": r["tracked"]["p99"] - b["tracked"]["p99"],
                "worst_with": r["tracked"]["worst_robot_p99"],
                "worst_without": b["tracked"]["worst_robot_p99"],
                "max_with": r["tracked"].get("max", math.nan),
                "max_without": b["tracked"].get("max", math.nan),
                "ok": r["tracked"]["p99"] - b["tracked"]["p99"] <= ACCEPT_SEARCH_ADDS_MS,
            }
        )
    return out


def fmt_num(v: float, fmt: str = ".1f") -> str:
    return "nan" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, fmt)


ROW_HEAD = (
    "world",
    "map",
    "N",
    "Hz",
    "K",
    "answered mean / worst",
    "p50 ms",
    "p99 ms",
    "starved",
    "correct",
    "confident wrong",
    "lost",
    "svc CPU %",
    "gen CPU %",
    "send lag p99 ms",
    "load",
)


def row_cells(r: dict[str, Any]) -> list[str]:
    t = r["tracked"]
    return [
        world_name(r["world"]),
        r["map"],
        str(r["n"]),
        f"{r['rate']:g}",
        str(r["k"]),
        f"{100 * t['answered_mean']:.1f} / {100 * t['answered_min']:.1f} %",
        fmt_num(t["p50"]),
        fmt_num(t["p99"]),
        "yes" if t["starved"] else "no",
        f"{fmt_num(100 * t['correct'], '.2f')} %",
        f"{t['confident_wrong']} / {t['poses']}",
        str(t["not_tracking"]),
        f"{r['svc_cpu']:.0f}",
        f"{r['gen_cpu']:.0f}",
        fmt_num(r["pub_lag_p99"]),
        f"{r['load']:.2f}",
    ]


SEARCH_HEAD = (
    "row",
    "K",
    "answered mean / worst",
    "p50 ms",
    "p99 ms",
    "searching share",
    "fixes (correct)",
)


def search_cells(r: dict[str, Any]) -> list[str]:
    s = r["searchers"]
    return [
        f"{world_name(r['world'])} {r['map']} N={r['n']}@{r['rate']:g}Hz",
        str(r["k"]),
        f"{100 * s['answered_mean']:.1f} / {100 * s['answered_min']:.1f} %",
        fmt_num(s["p50"]),
        fmt_num(s["p99"]),
        f"{fmt_num(100 * s['searching_share'])} %",
        f"{s['fixes']} ({s['fixes_correct']})",
    ]


PAIR_HEAD = (
    "tracked robots",
    "K",
    "p50 without / with",
    "p99 without / with",
    "a searching robot adds (p99)",
    "worst robot p99 without / with",
    "max without / with",
)


def pair_cells(p: dict[str, Any]) -> list[str]:
    return [
        p["label"],
        str(p["k"]),
        f"{fmt_num(p['p50_without'])} / {fmt_num(p['p50_with'])}",
        f"{fmt_num(p['p99_without'])} / {fmt_num(p['p99_with'])}",
        f"{p['adds_p99']:+.1f} ms",
        f"{fmt_num(p['worst_without'])} / {fmt_num(p['worst_with'])}",
        f"{fmt_num(p['max_without'])} / {fmt_num(p['max_with'])}",
    ]


def markdown_table(head: tuple[str, ...], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(c) + " |" for c in rows]
    return "\n".join(lines)


def text_table(head: tuple[str, ...], rows: list[list[str]]) -> str:
    cols = list(zip(head, *rows, strict=True))
    widths = [max(len(c) for c in col) for col in cols]
    fmt = "  ".join(f"{{:>{w}}}" for w in widths)
    return "\n".join(fmt.format(*r) for r in [list(head), *rows])


def acceptance_rows() -> list[RowSpec]:
    """The staggered fleet's acceptance table."""
    return [
        RowSpec("office", "metric", 20, 10.0),
        RowSpec("office", "schematic", 20, 10.0),
        RowSpec("1000", "metric", 20, 10.0),
        RowSpec("1000", "schematic", 20, 10.0),
        RowSpec("office", "metric", 40, 5.0),
        RowSpec("office", "metric", 20, 10.0, 0),
        RowSpec("office", "metric", 20, 10.0, 1),
    ]


def acceptance_lines(results: list[dict[str, Any]]) -> list[tuple[str, bool, str]]:
    """(line, pass, figures) per acceptance line: every K = 0 scale row (the K = 0 row of the
    searching pair is its baseline only), then the searching check."""
    out = []
    seen = set()
    for r in results:
        key = (r["world"], r["map"], r["n"], r["rate"])
        if r["k"] or key in seen:
            continue
        seen.add(key)
        t = r["tracked"]
        out.append(
            (
                f"{world_name(r['world'])} {r['map']} N={r['n']} at {r['rate']:g} Hz",
                row_ok(r),
                f"answered {100 * t['answered_mean']:.1f} % (worst {100 * t['answered_min']:.1f}"
                f" %), p99 {fmt_num(t['p99'])} ms, starved {'yes' if t['starved'] else 'no'}",
            )
        )
    for p in search_pairs(results):
        out.append(
            (
                f"searching: {p['label']} K={p['k']} vs K=0",
                p["ok"],
                f"tracked p99 {fmt_num(p['p99_without'])} -> {fmt_num(p['p99_with'])} ms "
                f"(adds {p['adds_p99']:+.1f} ms; limit {ACCEPT_SEARCH_ADDS_MS:g})",
            )
        )
    return out


_TRACKED_DIRS = ("service", "schemas", "sim_publisher", "bench")


def git_commit() -> str:
    """Short HEAD commit, ``-dirty`` when service/, schemas/, sim_publisher/ or bench/ have
    uncommitted changes."""
    try:
        head = subprocess.run(
            ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(REPO), "status", "--porcelain", "--", *_TRACKED_DIRS],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head + ("-dirty" if dirty else "")


def report(
    results: list[dict[str, Any]],
    meta: dict[str, Any],
    acceptance: bool,
) -> str:
    """The markdown report (what ``--out`` writes)."""
    lines = ["# Service scale (bench/bench_service.py)", ""]
    if meta.get("note"):
        lines += [f"> {meta['note']}", ""]
    lines += [
        f"Command: `{meta['command']}`  ",
        f"Commit: `{meta['commit']}`, date {meta['date']}, {meta['machine']}  ",
        f"Service: method `{meta['method']}`, {meta['workers']} workers, search budget "
        f"{meta['budget']}; odometry {'sent' if meta['odom'] else 'not sent'}; searching "
        f"robots: `{meta['search_mode']}`; window {meta['window']:g} s per row after "
        f"{meta['warmup']:g} s warm-up; load average before {meta['load_before']}, after "
        f"{meta['load_after']}.  ",
        f"Correct: within {meta['correct_m']:g} m and {meta['correct_deg']:g} deg of the true "
        "pose. CPU in % of one core (the generator shares the machine with the service).",
        "",
        "Scans (laser and motion between consecutive sent scans):",
        "",
    ]
    for w in meta["worlds"]:
        lines.append(
            f"- {w['world']} ({w['map']} map `{w['map_id']}`): {w['scans']} scans along the "
            f"tour, {w['beams']} beams; step mean {w['step_mean']:.3f} m, p95 "
            f"{w['step_p95']:.3f} m; turn mean {w['turn_mean']:.1f} deg, p95 "
            f"{w['turn_p95']:.1f} deg"
        )
    lines += ["", "Tracked robots:", "", markdown_table(ROW_HEAD, [row_cells(r) for r in results])]
    srch = [r for r in results if r["k"]]
    if srch:
        lines += [
            "",
            "Searching robots:",
            "",
            markdown_table(SEARCH_HEAD, [search_cells(r) for r in srch]),
        ]
        pairs = search_pairs(results)
        if pairs:
            lines += ["", markdown_table(PAIR_HEAD, [pair_cells(p) for p in pairs])]
    if acceptance:
        lines += ["", "Acceptance (staggered fleet of 20 robots):", ""]
        for name, ok, figs in acceptance_lines(results):
            lines.append(f"- **{'PASS' if ok else 'FAIL'}** {name}: {figs}")
    lines += ["", METHOD_TEXT]
    return "\n".join(lines) + "\n"


METHOD_TEXT = """## How it is measured

One `python -m service` (one worker process per core unless `--workers`) on a loopback
Zenoh port; the robots' scans come from one publisher process and the poses are received by
the bench process, both on the same machine (their CPU is the *gen CPU* column). Each row
starts from an empty service holding the maps, configures its robots, primes each with one
scan (cold costs: map models, the global-search view index, stay out of the window), then
sends every robot's scans at the row's rate, staggered within the period, and deletes the
robots at the end.

- Scans: simulated against the true world (furniture included) along the world's tour every
  `--stride` x 11 mm, with the paper's laser (361 beams over 180 deg, 15 m, 1 cm noise, 1 %
  dropouts); the statistics above are between consecutive scans of a robot. `office` is the
  paper's office; a number is a generated building (`sim_publisher.generator`, default
  parameters, no moving people; 1000 and up are held out from tuning).
- Motion: each robot walks back and forth along the tour from its own start (reversing at the
  ends, heading kept). Odometry (when sent) is the walk's true poses run through the
  simulator's odometry error model (scale error, translational noise, rotational drift per
  metre and noise), one noise stream per robot over the whole walk, turnarounds included,
  expressed in the robot's own odometry frame (origin at its first pose).
- Tracked robots get their true start pose as `initial_pose`. Searching robots get a null
  pose; `refix`: real scans of the same world, and their config is put again with a null
  pose as soon as they report `tracking`, so they search back to back (the searching share
  is the part of their poses that were not `tracking`); `foreign`: mirror images of the
  scans, a building that does not exist.
- Answered: poses received (up to 1 s after the last scan) over scans sent in the window
  (mean over the tracked robots / worst robot). Latency: pose receipt minus the scan's
  stamp, its send time. Starved: a robot with no pose, or answered below half the mean.
  Correct: the pose is within the stated distance and angle of the scan's true pose, any
  status; confident wrong: `tracking` poses that are not; lost: tracked robots' poses with
  another status. Send lag: how late the publisher sent scans against their schedule.
- A searching robot adds: tracked p99 of the K > 0 row minus that of the nearest K = 0 row
  with the same world, map, N and rate (run back to back).
- Acceptance lines: >= 99 % answered (mean over robots), p99 <= 50 ms and none starved for
  every K = 0 row; a searching robot adds <= 5 ms to the tracked robots' p99.
"""
