"""Where the map does not match the building: partial maps and maps from another day.

``python -m bench.bench_partial [--logs intel,fr079,mit-csail] [--seeds 1-6]
[--worlds 0-7,1000-1007] [--jobs 2] [--budget-ms 50] [--data /work/shared/data/real]
[--out docs/results]``

READS /work/shared (the real logs, as ``bench/bench_real.py``); the generated buildings need
nothing outside the repository. intel, fr079 and buildings 0-999 are the TUNING split;
mit-csail and buildings >= 1000 are HELD OUT (marked so; nothing is tuned on them).

Maps (one table row each; the rule is seeded and deterministic):

- **partial** (real logs): the committed metric map ``docs/real/maps/{log}.geojson`` with whole
  corridor stretches removed, one map per ``--seeds`` seed (each draw removes other
  corridors: one draw alone is one building's story). A stretch is the robot's reference
  path over :data:`STRETCH_M` metres of odometry travel from a start scan drawn uniformly
  (``numpy.random.default_rng([seed, log number])``) among the flag-1 scans; everything of
  the map within :data:`STRETCH_WIDTH_M` of that piece of path is removed (both walls of the
  corridor and the door jambs along it). Stretches are drawn until at least
  :data:`REMOVE_SHARE` of the map's wall length is gone; a stretch that would remove any map
  within :data:`START_KEEP_M` of the first scan's pose is skipped (the run starts from a
  known pose on a mapped spot).
- **another day** (generated buildings, ``sim_publisher.generator``): the exact metric map
  of building ``seed`` (setup 1: walls and furniture), each piece of furniture deleted from
  the map with probability :data:`DELETE_P` and otherwise moved with probability
  :data:`MOVE_P` (0.3-1.0 m in a uniform direction, turned by up to 30 degrees;
  ``default_rng([seed, 7])``). The scans are the true world's, every scan of the setup-1
  tour (11 mm apart) with its simulated odometry.

Each run starts at the first scan's true (reference) pose with odometry on, every scan fed,
``create_localizer("shape", map, pose, search_budget_ms=--budget-ms)`` (the service's default
budget, 50 reference ms per scan). Scored scans: the real logs' flag-1 references, every
scan in simulation. Columns:

- ``<0.5 m``: share of scored scans whose published pose (whatever its status) is within
  0.5 m of the truth;
- ``tracking > 0.5 m``: share of the scored scans published ``tracking`` that are more than
  0.5 m off (confident wrong), and their count;
- ``tracking`` / ``dead reckoning`` / ``lost``: shares of scored scans by the published
  status (``dead reckoning``: the optional state field, where the localiser has one);
- ``map holds``: share of scored scans whose returns the map explains at the true pose
  (plan share >= ``bench.plan_share.HOLDS_SHARE``, with the partial map);
- re-fix: each time the map holds again (a scored scan where it holds after at least
  :data:`GAP_M` metres of travel where it did not), the odometry travel from there to the
  first scan published ``tracking`` within 0.5 m (0 when it already is); ``p50 / max`` over
  those events, ``> 5 m``: events not re-fixed within 5 m (never re-fixed counts as the
  travel to the end of the log); ``> 5 m where it holds``: the same, counting only the travel
  over scans where the map holds (a map that holds for a scan and then not for 30 m again
  gives nothing to re-fix on; the first count charges all 30 m to the localiser).

The page also lists each re-fix over 5 m where the map holds, and each episode of
confident-wrong scans (consecutive scored scans ``tracking`` more than 0.5 m off: its first
scan, length and metres off), which tells a slide (centimetres past the bar) from a fix at
another place (metres).

Writes ``--out``/partial-maps.md (command, commit, machine and load, table) and one
``.npz`` per run under ``--cache`` (poses, statuses, truth) for inspection.
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = Path("/work/shared/data/real")
REAL_LOGS = ("intel", "fr079", "mit-csail")
HELD_OUT_LOGS = frozenset({"mit-csail"})
HELD_OUT_FIRST_SEED = 1000
#: Travel (m) of one removed corridor stretch and its half width (m) around the path.
STRETCH_M = 12.0
STRETCH_WIDTH_M = 2.5
#: Share of the map's wall length removed at least.
REMOVE_SHARE = 0.30
#: No map within this distance (m) of the first pose is removed.
START_KEEP_M = 4.0
#: Another day: furniture deleted / moved with these probabilities.
DELETE_P = 0.3
MOVE_P = 0.3
#: A re-fix event needs at least this much travel (m) where the map did not hold before it.
GAP_M = 1.0
#: The acceptance's re-fix distance (m).
REFIX_M = 5.0
#: Off by more than this (m) is wrong.
WRONG_M = 0.5


@dataclass
class Case:
    """One run: a real log's partial map or a building's map from another day."""

    kind: str  # "partial" | "another-day"
    name: str  # log name or building seed
    held_out: bool
    seed: int = 0  # the draw of a partial map's stretches

    @property
    def label(self) -> str:
        what = f"building {self.name}"
        if self.kind == "partial":
            what = f"{self.name} partial, seed {self.seed}"
        return what + (" (HELD-OUT)" if self.held_out else "")


# --------------------------------------------------------------------------- maps
def _lines_minus(polylines: tuple[np.ndarray, ...], area: object) -> list[np.ndarray]:
    """The polylines with the parts inside the shapely ``area`` cut away."""
    import shapely
    from shapely.geometry import LineString

    out: list[np.ndarray] = []
    for p in polylines:
        rest = LineString(p).difference(area)
        for g in getattr(rest, "geoms", [rest]):
            if g.is_empty or g.geom_type != "LineString":
                continue
            xy = np.asarray(shapely.get_coordinates(g), dtype=np.float64)
            if len(xy) >= 2 and float(np.hypot(*np.diff(xy, axis=0).T).sum()) > 0.05:
                out.append(xy)
    return out


def _length(polylines: list[np.ndarray] | tuple[np.ndarray, ...]) -> float:
    return float(sum(np.hypot(*np.diff(p, axis=0).T).sum() for p in polylines))


def partial_map(
    log: str, reference: np.ndarray, ok: np.ndarray, travel: np.ndarray, seed: int
) -> tuple[object, float, int]:
    """The log's metric map with corridor stretches removed (module docstring); returns the
    map, the removed share of its wall length and the number of stretches."""
    import shapely
    from shapely.geometry import LineString, Point

    from bench.bench_real import map_path
    from service.adapters.maps.files import load_map_file
    from service.core.types import MapData

    full = load_map_file(map_path(log, "metric"), kind="metric")
    total = _length(full.polylines)
    rng = np.random.default_rng([seed, REAL_LOGS.index(log)])
    scored = np.flatnonzero(ok)
    keep = Point(*reference[scored[0], :2]).buffer(START_KEEP_M)
    areas: list[object] = []
    lines: list[np.ndarray] = list(full.polylines)
    for _ in range(200):
        if _length(lines) <= (1.0 - REMOVE_SHARE) * total:
            break
        i = int(rng.choice(scored))
        sel = scored[(travel[scored] >= travel[i]) & (travel[scored] <= travel[i] + STRETCH_M)]
        if len(sel) < 2:
            continue
        area = LineString(reference[sel, :2]).buffer(STRETCH_WIDTH_M)
        if area.intersects(keep):
            continue
        trial = _lines_minus(tuple(lines), area)
        if _length(trial) >= _length(lines) - 0.5:
            continue  # removes nothing new
        areas.append(area)
        lines = trial
    removed = 1.0 - _length(lines) / total
    md = MapData.from_lists(f"{log}-partial", "metric", lines)
    del shapely
    return md, removed, len(areas)


def another_day_map(building: object, seed: int) -> tuple[object, int, int]:
    """The building's exact metric map with furniture deleted or moved (module docstring);
    returns the map and the numbers deleted and moved."""
    from shapely import affinity

    from service.adapters.maps.world import Obstacle, World

    rng = np.random.default_rng([seed, 7])
    obstacles = []
    deleted = moved = 0
    for o in building.world.obstacles:  # type: ignore[attr-defined]
        if o.kind == "wall":
            obstacles.append(o)
            continue
        u = rng.random()
        if u < DELETE_P:
            deleted += 1
            continue
        if u < DELETE_P + MOVE_P:
            d = rng.uniform(0.3, 1.0)
            phi = rng.uniform(-np.pi, np.pi)
            turn = rng.uniform(-30.0, 30.0)
            g = affinity.rotate(o.geometry, turn, origin="centroid")
            g = affinity.translate(g, d * np.cos(phi), d * np.sin(phi))
            obstacles.append(Obstacle(g, o.name, o.kind))
            moved += 1
            continue
        obstacles.append(o)
    md = World(obstacles).to_map_data(f"building-{seed}-another-day")
    return md, deleted, moved


# --------------------------------------------------------------------------- runs
def _travel(xy_or_odom: list[np.ndarray | None] | np.ndarray) -> np.ndarray:
    """Cumulative translation (m) along a sequence of poses (``None``: no step)."""
    out = np.zeros(len(xy_or_odom))
    prev = None
    for i, p in enumerate(xy_or_odom):
        step = 0.0
        if p is not None and prev is not None:
            step = float(np.hypot(p[0] - prev[0], p[1] - prev[1]))
        out[i] = (out[i - 1] if i else 0.0) + step
        prev = p if p is not None else prev
    return out


def _feed(loc: object, scans: object, n: int, odom: list) -> tuple[np.ndarray, list[str], list]:
    poses = np.full((n, 3), np.nan)
    status: list[str] = []
    states: list[str] = []
    for i in range(n):
        r, a = scans(i)  # type: ignore[operator]
        est = loc.update(r, a, odom[i])  # type: ignore[attr-defined]
        poses[i] = est.pose
        status.append(est.status)
        states.append(str(getattr(est, "state", None) or est.status))
    return poses, status, states


def run_case(case: Case, data: str, budget: float, cache: str) -> dict[str, object]:
    """Run one case; returns its table row (and writes its per-scan arrays to ``cache``)."""
    from bench.plan_share import HOLDS_SHARE, PlanShare
    from service.core.factory import create_localizer

    t0 = time.perf_counter()
    info: dict[str, object] = {}
    if case.kind == "partial":
        from bench.bench_real import load_log

        log = load_log(Path(data), case.name, None)
        travel = _travel(log.odom)
        md, removed, stretches = partial_map(case.name, log.reference, log.ok, travel, case.seed)
        info = {"removed": removed, "stretches": stretches}
        truth = log.reference
        scored = log.ok.copy()
        n = len(log.ranges)

        def scans(i: int) -> tuple[np.ndarray, np.ndarray]:
            return log.ranges[i], log.angles[i]

        odom = list(log.odom)
    else:
        from bench.bench_worlds import generated_building
        from sim_publisher.scenario import building_setup

        b = generated_building(int(case.name), 0)
        s = building_setup(b, 1, seed=0)
        md, deleted, moved = another_day_map(b, int(case.name))
        info = {"deleted": deleted, "moved": moved}
        truth = s.reference
        n = len(s)
        scored = np.ones(n, dtype=bool)
        travel = _travel(truth)
        scans = s.scan
        odom = [s.odom[i] for i in range(n)]
    loc = create_localizer("shape", md, truth[0].copy(), search_budget_ms=budget)
    poses, status, states = _feed(loc, scans, n, odom)
    share = PlanShare(md)
    holds = np.zeros(n, dtype=bool)
    for i in np.flatnonzero(scored):
        r, a = scans(i)
        holds[i] = share.scan_share(truth[i], r, a) >= HOLDS_SHARE
    tag = f"{case.kind}_{case.name}" + (f"_{case.seed}" if case.kind == "partial" else "")
    Path(cache).mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        Path(cache) / f"{tag}.npz",
        poses=poses,
        truth=truth,
        scored=scored,
        holds=holds,
        travel=travel,
        status=np.array(status),
        state=np.array(states),
    )
    row = summarise(poses, truth, scored, holds, travel, status, states)
    row.update(info)
    row.update({"case": case.label, "kind": case.kind, "seconds": time.perf_counter() - t0})
    return row


class Refix(NamedTuple):
    """A re-fix event: the scan where the map holds again, the travel (m) from there to a
    correct ``tracking`` pose (``inf``: never) and the part of it where the map holds."""

    scan: int
    travel: float
    holding: float


def refix_events(
    good: np.ndarray, scored: np.ndarray, holds: np.ndarray, travel: np.ndarray
) -> list[Refix]:
    """Per scored scan where the map holds again after at least :data:`GAP_M` of travel where
    it did not (module docstring), its :class:`Refix`."""
    idx = np.flatnonzero(scored)
    steps = np.diff(travel[idx], prepend=travel[idx[0]]) if len(idx) else np.zeros(0)
    holding = np.cumsum(np.where(holds[idx], steps, 0.0))
    out: list[Refix] = []
    gap_from: float | None = None
    for k, i in enumerate(idx):
        if not holds[i]:
            if gap_from is None:
                gap_from = float(travel[i])
            continue
        if gap_from is not None and travel[i] - gap_from >= GAP_M and k > 0:
            later = np.flatnonzero(good[idx[k:]])
            if len(later):
                j = k + int(later[0])
                out.append(
                    Refix(int(i), float(travel[idx[j]] - travel[i]), float(holding[j] - holding[k]))
                )
            else:
                out.append(Refix(int(i), float("inf"), float(holding[-1] - holding[k])))
        gap_from = None
    return out


def wrong_episodes(
    err: np.ndarray, tracking: np.ndarray, scored: np.ndarray
) -> list[tuple[int, int, float, float]]:
    """The confident-wrong scans (scored, ``tracking``, more than :data:`WRONG_M` off) in
    episodes of consecutive scored scans: ``(first scan, scans, least and most metres off)``.
    A few centimetres past the bar is a slide; many metres is a fix at another place."""
    out: list[tuple[int, int, float, float]] = []
    run: list[int] = []
    for i in [*np.flatnonzero(scored), -1]:
        if i >= 0 and tracking[i] and err[i] > WRONG_M:
            run.append(int(i))
            continue
        if run:
            e = err[run]
            out.append((run[0], len(run), float(e.min()), float(e.max())))
            run = []
    return out


def summarise(
    poses: np.ndarray,
    truth: np.ndarray,
    scored: np.ndarray,
    holds: np.ndarray,
    travel: np.ndarray,
    status: list[str],
    states: list[str],
) -> dict[str, object]:
    st = np.array(status)
    sta = np.array(states)
    err = np.hypot(*(poses[:, :2] - truth[:, :2]).T)
    err = np.where(np.isfinite(err), err, np.inf)
    trk = st == "tracking"
    good = trk & (err <= WRONG_M)
    s = scored
    ns = max(int(s.sum()), 1)
    wrong = int((s & trk & (err > WRONG_M)).sum())
    events = refix_events(good, scored, holds, travel)
    ev = np.array([e.travel for e in events])
    on_map = np.array([e.holding for e in events])
    fin = ev[np.isfinite(ev)]
    return {
        "scored": int(s.sum()),
        "within": float((s & (err <= WRONG_M)).sum()) / ns,
        "wrong": wrong,
        "wrong_share": wrong / max(int((s & trk).sum()), 1),
        "tracking": float((s & trk).sum()) / ns,
        "dead": float((s & (sta == "dead_reckoning")).sum()) / ns,
        "lost": float((s & (st == "lost")).sum()) / ns,
        "holds": float((s & holds).sum()) / ns,
        "events": len(events),
        "refix_p50": float(np.median(ev)) if len(ev) else float("nan"),
        "refix_max": float(ev.max()) if len(ev) else float("nan"),
        "refix_late": int((ev > REFIX_M).sum()),
        "refix_late_holding": int((on_map > REFIX_M).sum()),
        "refix_never": int((~np.isfinite(ev)).sum()),
        "fin_max": float(fin.max()) if len(fin) else float("nan"),
        "late": [tuple(e) for e in events if e.holding > REFIX_M],
        "wrong_runs": wrong_episodes(err, trk, s),
    }


def _job(args: tuple) -> dict[str, object]:
    return run_case(*args)


# --------------------------------------------------------------------------- output
def _pct(x: object) -> str:
    return f"{100.0 * float(x):.1f} %"  # type: ignore[arg-type]


def _m(x: object) -> str:
    v = float(x)  # type: ignore[arg-type]
    return "–" if np.isnan(v) else ("never" if np.isinf(v) else f"{v:.1f}")


def table(rows: list[dict[str, object]]) -> str:
    head = (
        "| map | changed | scored | <0.5 m | tracking > 0.5 m (n) | tracking | dead reckoning "
        "| lost | map holds | re-fix events | re-fix p50 / max m | > 5 m (never) "
        "| > 5 m where it holds |\n"
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|\n"
    )
    lines = []
    for r in rows:
        if r["kind"] == "partial":
            changed = f"{100 * float(r['removed']):.0f} % of walls, {r['stretches']} stretches"
        else:
            changed = f"{r['deleted']} deleted, {r['moved']} moved"
        lines.append(
            f"| {r['case']} | {changed} | {r['scored']} | {_pct(r['within'])} | "
            f"{_pct(r['wrong_share'])} ({r['wrong']}) | {_pct(r['tracking'])} | "
            f"{_pct(r['dead'])} | {_pct(r['lost'])} | {_pct(r['holds'])} | {r['events']} | "
            f"{_m(r['refix_p50'])} / {_m(r['refix_max'])} | {r['refix_late']} "
            f"({r['refix_never']}) | {r['refix_late_holding']} |"
        )
    return head + "\n".join(lines) + "\n"


def _by_map(rows: list[dict[str, object]], key: str, item: Callable[[tuple], str]) -> str:
    """A bullet per map listing its ``key`` entries, each rendered by ``item``."""
    out = [
        f"- {r['case']}: " + "; ".join(item(x) for x in r[key])  # type: ignore[union-attr]
        for r in rows
        if r.get(key)
    ]
    return "\n".join(out or ["- none"]) + "\n"


def late_list(rows: list[dict[str, object]]) -> str:
    """Each re-fix taking more than :data:`REFIX_M` of travel where the map holds, by map: the
    scan where the map holds again and the travel to the re-fix, in all and where it holds."""
    return _by_map(rows, "late", lambda e: f"scan {e[0]}: {_m(e[1])} / {_m(e[2])} m")


def wrong_list(rows: list[dict[str, object]]) -> str:
    """Each episode of confident-wrong scans, by map: its first scan, how many scored scans
    and how far off (m)."""
    return _by_map(
        rows,
        "wrong_runs",
        lambda w: f"scan {w[0]}: {w[1]} scan{'s' if w[1] > 1 else ''}, {w[2]:.1f}-{w[3]:.1f} m",
    )


def pooled(rows: list[dict[str, object]]) -> str:
    """Pooled figures per group (tuning / held-out, real / buildings), by scored scans."""
    out = [
        "| group | scored | <0.5 m | tracking > 0.5 m | re-fix > 5 m / events "
        "| > 5 m where it holds |",
        "|---|---|---|---|---|---|",
    ]
    groups: dict[str, list[dict[str, object]]] = {}
    for r in rows:
        split = "held-out" if "HELD-OUT" in str(r["case"]) else "tuning"
        groups.setdefault(f"{r['kind']} {split}", []).append(r)
    for g, rs in groups.items():
        n = sum(int(r["scored"]) for r in rs)  # type: ignore[arg-type]
        within = sum(float(r["within"]) * int(r["scored"]) for r in rs) / max(n, 1)  # type: ignore[arg-type]
        trk = sum(float(r["tracking"]) * int(r["scored"]) for r in rs)  # type: ignore[arg-type]
        wrong = sum(int(r["wrong"]) for r in rs)  # type: ignore[arg-type]
        late = sum(int(r["refix_late"]) for r in rs)  # type: ignore[arg-type]
        late_on = sum(int(r["refix_late_holding"]) for r in rs)  # type: ignore[arg-type]
        ev = sum(int(r["events"]) for r in rs)  # type: ignore[arg-type]
        out.append(
            f"| {g} | {n} | {100 * within:.1f} % | {100 * wrong / max(trk, 1):.2f} % ({wrong}) "
            f"| {late} / {ev} | {late_on} |"
        )
    return "\n".join(out) + "\n"


def _commit() -> str:
    try:
        out = subprocess.run(
            ["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(REPO), "status", "--porcelain", "--", "service"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        return out + ("+uncommitted" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _load() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def parse_worlds(text: str) -> list[int]:
    out: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        if "-" in part:
            a, b = part.split("-")
            out.extend(range(int(a), int(b) + 1))
        else:
            out.append(int(part))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--logs", default=",".join(REAL_LOGS))
    ap.add_argument("--worlds", default="0-7,1000-1007", help="building seeds (a-b or a,b)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--budget-ms", type=float, default=50.0)
    ap.add_argument("--seeds", default="1-6", help="partial maps: the draws (a-b or a,b)")
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "results")
    ap.add_argument("--cache", type=Path, default=REPO / "build" / "bench_partial")
    args = ap.parse_args(argv)
    logs = [x for x in args.logs.split(",") if x]
    worlds = parse_worlds(args.worlds)
    seeds = parse_worlds(args.seeds) if args.seeds else []
    cases = [Case("partial", log, log in HELD_OUT_LOGS, s) for log in logs for s in seeds]
    cases += [Case("another-day", str(w), w >= HELD_OUT_FIRST_SEED) for w in worlds]
    if logs and not args.data.is_dir():
        raise SystemExit(f"{args.data}: no data directory (the real logs are read from there)")
    load0 = _load()
    t0 = time.perf_counter()
    jobs = [(c, str(args.data), args.budget_ms, str(args.cache)) for c in cases]
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as ex:
            rows = list(ex.map(_job, jobs))
    else:
        rows = [_job(j) for j in jobs]
    wall = time.perf_counter() - t0
    cmd = "python -m bench.bench_partial " + " ".join(sys.argv[1:] if argv is None else argv)
    text = (
        "# Partial maps and maps from another day\n\n"
        f"Written by `{cmd.strip()}` at commit {_commit()} on "
        f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.machine()} "
        f"{os.cpu_count()} cores, {args.jobs} process(es), {wall:.0f} s wall; load average at "
        f"start {load0}, at end {_load()}. Definitions: `bench/bench_partial.py`'s docstring. "
        f"Odometry on, every scan, search budget {args.budget_ms:g} reference ms per scan.\n\n"
        + table(rows)
        + "\nPooled by scored scans:\n\n"
        + pooled(rows)
        + f"\nRe-fixes taking more than {REFIX_M:g} m of travel where the map holds (the scan "
        "where it holds again: travel to the re-fix in all / where it holds):\n\n"
        + late_list(rows)
        + "\nConfident wrong poses (`tracking` more than 0.5 m off), by episode of consecutive "
        "scored scans:\n\n" + wrong_list(rows)
    )
    print(text)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "partial-maps.md").write_text(text, encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
