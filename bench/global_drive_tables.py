"""The tables and CSV of ``bench_global.py --drive``: one row per map
(:func:`summarise_drive`, :func:`drive_table`), the office by room of the start
(:func:`room_table`), the trials by plan share (:func:`share_table`) and one CSV row per trial
(:func:`write_drive_csv`). The figures are defined in the docstring of ``bench_global.py``.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Iterator, Sequence
from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import numpy as np

from bench.global_drive import HELD_OUT_FIRST_SEED, DriveMap, DriveTrial

DRIVE_FIELDS_SKIP = ("search_ms",)
#: share_table's split of the trials by plan share (:mod:`plan_share`)
SHARE_SPLIT = 0.5
#: share_table lists at most this many trials not fixed within the limit per map
MISSES_SHOWN = 6


def _miss(t: DriveTrial) -> str:
    """A trial not fixed within its limit: where the map starts to hold / where it was fixed
    (m of travel; ``never``: not within the trial)."""
    fixed = _cell(t.fix_travel_m, ".1f", "never") if t.found else "never"
    return f"{t.start}: {_cell(t.holds_from_m, '.1f', 'never')} / {fixed}"


def share_table(trials: Sequence[DriveTrial], maps: Sequence[DriveMap]) -> str:
    """Found within the limit / trials, split by the trial's plan share (:mod:`plan_share`)
    below or at least ``SHARE_SPLIT``, per map row of :func:`drive_table`; and each trial not
    fixed within its limit: its start scan, the travel from which the map holds
    (:func:`global_drive.holds_from`) and the travel to its fix."""
    lines = [
        f"| map | plan share < {SHARE_SPLIT} | plan share >= {SHARE_SPLIT} "
        "| not fixed within the limit: start: map holds from / fixed at (m) |",
        "|---|---|---|---|",
    ]
    for m, ts in table_groups(trials, maps):
        cells = []
        for low in (True, False):
            sel = [
                t for t in ts if math.isfinite(t.plan_share) and (t.plan_share < SHARE_SPLIT) == low
            ]
            ok = sum(t.within_limit for t in sel)
            cells.append(f"{ok}/{len(sel)}" if sel else "–")
        misses = [t for t in sorted(ts, key=lambda t: t.start) if not t.within_limit]
        cells.append("; ".join(_miss(t) for t in misses[:MISSES_SHOWN]) or "–")
        if len(misses) > MISSES_SHOWN:
            cells[-1] += f"; {len(misses) - MISSES_SHOWN} more"
        name = f"{m.group} {m.world if m.group != 'worlds' else 'worlds'} {m.kind}"
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def pct_inf(x: Sequence[float], q: float) -> float:
    """Percentile ``q`` with NaN (not found) counted as infinite; inf when it falls on them."""
    a = np.asarray(x, dtype=np.float64)
    if a.size == 0:
        return math.nan
    a = np.sort(np.where(np.isfinite(a), a, np.inf))
    # linear interpolation, but any neighbour at infinity gives infinity
    pos = (a.size - 1) * q / 100.0
    lo, hi = math.floor(pos), math.ceil(pos)
    if not (math.isfinite(a[lo]) and math.isfinite(a[hi])):
        return math.inf
    return float(a[lo] + (a[hi] - a[lo]) * (pos - lo))


def summarise_drive(trials: Sequence[DriveTrial]) -> dict[str, Any]:
    """One table row over the trials of one map (see the docstring of ``bench_global.py``)."""
    n = len(trials)
    ms = np.asarray([v for t in trials for v in t.search_ms], dtype=np.float64)
    hyp_n = sum(t.hyp_scans for t in trials)
    trk_after = sum(t.tracking_after_fix for t in trials)
    return {
        "trials": n,
        "limit": trials[0].limit_m if trials else math.nan,
        "stride": max((t.stride for t in trials), default=1),
        "within": 100.0 * sum(t.within_limit for t in trials) / n if n else math.nan,
        "found": 100.0 * sum(t.found for t in trials) / n if n else math.nan,
        "travel50": pct_inf([t.fix_travel_m for t in trials], 50),
        "travel90": pct_inf([t.fix_travel_m for t in trials], 90),
        "cpu50": pct_inf([t.cpu_to_fix_s for t in trials], 50),
        "cpu95": pct_inf([t.cpu_to_fix_s for t in trials], 95),
        "ffw": sum(t.first_fix_wrong for t in trials),
        "afw_trials": sum(t.wrong_after_fix > 0 for t in trials),
        "relost": sum(t.search_after_fix > 0 for t in trials),
        "afw_pct": 100.0 * sum(t.wrong_after_fix for t in trials) / trk_after
        if trk_after
        else math.nan,
        "ms_max": float(ms.max()) if ms.size else math.nan,
        "ms_p99": float(np.percentile(ms, 99)) if ms.size else math.nan,
        "hyp": sum(t.hyp_sum for t in trials) / hyp_n if hyp_n else math.nan,
        "work_max": max(
            (t.work_max for t in trials if not math.isnan(t.work_max)), default=math.nan
        ),
        "wall": float(np.mean([t.wall_s for t in trials])) if n else math.nan,
        "truncated": sum(t.truncated for t in trials),
    }


def _cell(x: float, spec: str, inf: str = "n/f") -> str:
    if math.isnan(x):
        return "–"
    if math.isinf(x):
        return inf
    return format(x, spec)


DRIVE_HEAD = (
    "| group | map | limit m | trials | found <= limit | found at all "
    "| travel to fix p50 / p90 m | CPU to fix p50 / p95 s | confident wrong: first fix "
    "| after fix: trials (% of tracking) | searching again after fix | search scan ms "
    "max / p99 | search work max (ref. ms) | hypotheses | s / trial |\n"
    "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
)


def drive_row(group: str, name: str, r: dict[str, Any]) -> str:
    """One markdown table row of :func:`summarise_drive`'s figures."""
    stride = f" (every {r['stride']}th scan)" if r["stride"] > 1 else ""
    return (
        f"| {group} | {name}{stride} | {r['limit']:.0f} | {r['trials']} "
        f"| {_cell(r['within'], '.1f')} % | {_cell(r['found'], '.1f')} % "
        f"| {_cell(r['travel50'], '.2f')} / {_cell(r['travel90'], '.2f')} "
        f"| {_cell(r['cpu50'], '.2f')} / {_cell(r['cpu95'], '.2f')} "
        f"| {r['ffw']} ({_cell(100.0 * r['ffw'] / max(r['trials'], 1), '.1f')} %) "
        f"| {r['afw_trials']} ({_cell(r['afw_pct'], '.2f')} %) | {r['relost']} "
        f"| {_cell(r['ms_max'], '.0f')} / {_cell(r['ms_p99'], '.0f')} "
        f"| {_cell(r['work_max'], '.0f')} | {_cell(r['hyp'], '.1f')} | {_cell(r['wall'], '.1f')} |"
    )


def table_groups(
    trials: Sequence[DriveTrial], maps: Sequence[DriveMap]
) -> Iterator[tuple[DriveMap, list[DriveTrial]]]:
    """The trials of each table row, in ``maps`` order: one row per office setup, per worlds
    setup (all worlds pooled) and per real log and map; rows without trials are left out."""
    seen: set[tuple[str, str, str]] = set()
    for m in maps:
        key = (m.group, m.world if m.group != "worlds" else "*", m.kind)
        if key in seen:
            continue
        seen.add(key)
        ts = [t for t in trials if (t.group, t.world if t.group != "worlds" else "*", t.map) == key]
        if ts:
            yield m, ts


def drive_table(trials: Sequence[DriveTrial], maps: Sequence[DriveMap]) -> str:
    """The markdown table: one row per office setup, per worlds setup (all worlds pooled) and
    per real log and map, in ``maps`` order."""
    rows = []
    for m, ts in table_groups(trials, maps):
        if m.group == "worlds":
            seeds = sorted({DriveMap(t.group, t.world, t.map).seed for t in ts})
            split = "held-out" if min(seeds) >= HELD_OUT_FIRST_SEED else "incl. TUNING seeds"
            name = f"{len(seeds)} {split} worlds ({_seed_list(seeds)}) setup {m.setup} ({m.kind})"
            if m.clutter is not None:
                name += f", clutter {m.clutter:g}"
        else:
            name = m.label()
        rows.append(drive_row(m.group, name, summarise_drive(ts)))
    return DRIVE_HEAD + "\n".join(rows) + "\n"


def _seed_list(seeds: Sequence[int]) -> str:
    if len(seeds) > 2 and list(seeds) == list(range(seeds[0], seeds[-1] + 1)):
        return f"seeds {seeds[0]}-{seeds[-1]}"
    return "seeds " + ",".join(str(s) for s in seeds)


def room_table(trials: Sequence[DriveTrial]) -> str:
    """Office trials by room of the start pose: found <= limit / trials, median travel to a
    fix, and the first-fix confident wrong count when any."""
    office = [t for t in trials if t.group == "office"]
    if not office:
        return ""
    names = sorted({t.room for t in office})
    lines = [
        "| office map | " + " | ".join(names) + " |",
        "|---|" + "---|" * len(names),
    ]
    for kind in ("metric", "schematic"):
        ts = [t for t in office if t.map == kind]
        if not ts:
            continue
        cells = []
        for room in names:
            rs = [t for t in ts if t.room == room]
            if not rs:
                cells.append("–")
                continue
            ok = sum(t.within_limit for t in rs)
            wrong = sum(t.first_fix_wrong for t in rs)
            med = pct_inf([t.fix_travel_m for t in rs], 50)
            cells.append(
                f"{ok}/{len(rs)}, {_cell(med, '.1f')} m" + (f" ({wrong} wrong)" if wrong else "")
            )
        lines.append(
            f"| setup {1 if kind == 'metric' else 2} ({kind}) | " + " | ".join(cells) + " |"
        )
    return "\n".join(lines) + "\n"


def write_drive_csv(path: Path, trials: Sequence[DriveTrial]) -> None:
    """One row per trial (all :class:`DriveTrial` fields but the pooled search times)."""
    names = [f.name for f in fields(DriveTrial) if f.name not in DRIVE_FIELDS_SKIP]
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.DictWriter(fh, fieldnames=names, extrasaction="ignore")
        w.writeheader()
        for t in trials:
            row = asdict(t)
            w.writerow(
                {
                    k: (f"{v:.6g}" if isinstance(v, float) and math.isfinite(v) else v)
                    for k, v in row.items()
                    if k in names
                }
            )
