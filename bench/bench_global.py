"""Global localisation acceptance measurement (prints tables).

``python bench/bench_global.py [--poses 200] [--seed 1] [--maps metric,schematic]
[--motions creep,look-around] [--setup-scans N] [--no-setups]``

1. Precompute per map: the view index built cold (into an empty cache dir) and loaded from
   that cache (a fresh process' view: the in-memory copy is dropped first).
2. Random free-space poses (``sim_publisher.publisher.random_free_poses``, >= 0.3 m from any
   obstacle, heading uniform; seeded) per map, no initial pose, up to 3 scans each. The robot
   MOVES 3 cm along its heading between the scans (``creep``: it stays put if that would leave
   free space; no odometry), or TURNS 90 deg in place (``look-around``: odometry sent, the
   localiser fuses the scans). Found = the first ``tracking`` estimate is within 0.5 m and
   10 deg of the truth; a ``tracking`` estimate outside that is a confident wrong pose. Time
   to first fix = wall time of the ``update`` calls up to the fix (one process, one core; the
   machine's load is printed).
3. No confident wrong poses: both full setups (``sim_publisher.scenario.make_setup``) run with
   ``initial_pose`` null; of all estimates with status ``tracking``, the fraction passing the
   setup's proximity test (setup 1: 100 mm / 45 deg, setup 2: 500 mm / 45 deg).

Drive trials (``--drive``, issue 13): global localisation WHILE THE ROBOT DRIVES
-------------------------------------------------------------------------------
``python bench/bench_global.py --drive [--groups office,worlds,real] [--starts 200]
[--worlds 8] [--real-starts 40] [--logs intel,fr079,mit-csail] [--data DIR] [--jobs 2]
[--quick N] [--stride1 1] [--seed 1] [--cache build/bench_global/index] [--out docs/global]``

A trial picks a random start scan on a tour, creates ``create_localizer("shape", map, None,
search_budget_ms=--budget-ms)`` (no initial pose; the service's default budget of 50 reference
ms per scan, 0 = a whole search per scan as offline) and feeds that scan and every
following one WITH its odometry
(``update(ranges, angles, odom)``) until the travel since the start exceeds the map's travel
limit + 5 m (the margin; the first scan beyond it is the trial's last) or the tour ends.

Maps (one table row each):

- ``office``: ``make_setup(1)`` (the office's metric map, a scan every 11 mm) and
  ``make_setup(2)`` (its schematic floor plan, a scan every 104 mm), ``--starts`` starts each.
- ``worlds``: held-out generated buildings (``bench_worlds._building(seed, 0)``: seeds 1000 ..
  999 + ``--worlds``, no moving people) with ``building_setup(b, 1 | 2, seed=0)``. Per setup
  the ``--starts`` starts are spread evenly over the worlds (``starts // worlds`` each, the
  first ``starts % worlds`` worlds one more), so each setup's row has ``--starts`` trials in
  all. Their tours are 25 m long: a setup-2 trial needs 20 m, so its starts lie in the first
  5 m of the tour.
- ``real``: the logs intel, fr079 (tuning) and mit-csail (HELD OUT) on the committed metric
  and schematised maps (``docs/real/maps/{log}.geojson``, ``{log}_schematic.geojson``), the
  log's laser odometry on, ``--real-starts`` starts per log and map, the scans read from
  ``--data`` with ``bench_real.load_log``.

Definitions:

- travel: in simulation the sum of the TRUE step lengths (translation only) since the start
  scan; on the real logs the sum of the (laser) odometry step lengths, since the per-scan
  references jump at GMapping's corrections (their sum on intel is 790 m against 593 m).
- travel limit: 5 m on metric maps (office and worlds, setup 1); 15 m on floor plans
  (setup 2) and on both maps of the real logs (the issue: "fixed correctly within 15 m of
  travel on every log").
- start scans: distinct scans drawn uniformly (``numpy.random.default_rng([--seed, group,
  world, map])``) among those after which at least limit + 5 m of travel remain; on real logs
  only scans with a reference. A tour without such a scan is skipped, and the output says so.
  ``--stride1 K`` feeds only every K-th scan on setup-1 tours (default 1: the 11 mm spacing
  of the paper; each fed scan carries its own odometry pose, so the increments stay
  consistent); the table states the stride. ``--real-stride K`` does the same on the real logs,
  each block of K scans feeding its first referenced scan (:func:`fed_scans`). It asks a tuning
  log what a faster robot would see: a search's work is spread over scans, so it costs travel
  in proportion to the distance between scans. Median step while moving: intel 0.06 m (every
  0.09 s, 0.65 m/s), fr079 0.10 m (0.21 s, 0.45 m/s), mit-csail 0.21 m (0.21 s, 1.0 m/s);
  fr079 with K = 2 steps as far as mit-csail, intel with K = 4.
- scored scan: in simulation every scan; on a real log a scan with a flag-1 (GMapping-
  corrected) reference, as in ``bench_real.py`` (a scan without one is not scored). intel has
  one every ~17 scans (~0.8 m), mit-csail every ~4 scans (~1 m), fr079 nearly every scan, so
  on intel and mit-csail the travel to a fix is rounded up to the next scored scan.
- found (correctly fixed): the first scored estimate with status ``tracking`` that is within
  0.5 m and 10 deg of the truth (the real logs' truth: the scan's reference laser pose).
  Travel to fix: the travel at that scan. "found <= limit": that travel is at most the travel
  limit; "found at all": anywhere in the trial (up to limit + 5 m).
- confident wrong, first fix: the trial published a scored ``tracking`` estimate that failed
  the 0.5 m / 10 deg test before its correct fix (or had no correct fix): the robot was
  declared found at a wrong place.
- confident wrong after the fix: scored ``tracking`` estimates after the first correct fix
  that fail the tour's own test: ``Setup.passed`` (setup 1: 100 mm / 45 deg, setup 2:
  500 mm / 45 deg) in simulation, 0.5 m on the real logs. Reported as trials with any, and as
  % of the scored tracking estimates after the fix.
- searching again after fix: trials in which the localiser, after the correct fix, lost
  the track and fed scans to the global search again (``search_after_fix`` in the CSV: how
  many scans).
- CPU to fix: ``time.process_time`` summed over the ``update`` calls from the start scan up
  to and including the fix (the worker process' CPU time, unaffected by the other process).
- search-scan ms: wall time (``perf_counter``) of single ``update`` calls made while the
  localiser was searching (``GlobalShapeLocalizer.searching`` before the call; for a
  localiser without that flag: the previous status was not ``tracking``), i.e. how long one
  scan's search blocks a worker. Max and p99 pooled over all trials of the row.
- search work max: the largest deterministic work (``GlobalShapeLocalizer.work_ms``,
  reference ms of ``global_search.WORK_MS``) one searching scan spent: what the budget bounds,
  independent of the machine's load.
- hypotheses: the live hypotheses the estimate reports, read as ``est.hypotheses`` when the
  core has that field, else ``est.extras["hypotheses"]`` (a count, or the length of a list);
  mean over the search scans that report it; "–" when none does.
- percentiles of travel and CPU to fix are over ALL trials of a row, a trial without a correct
  fix counting as infinite ("n/f": the percentile falls on such trials).
- s / trial: mean wall time of a trial in its worker (the machine's load is in the output).

Cost (measured at commit 312191d, CPU s per trial): setup 1 ~3 (911 scans tracked at ~3 ms;
the fix itself ~0.3), setup 2 ~2-4, real logs ~25 on average (a trial that never fixes
searches every scan: ~95 on fr079's metric map); a new world's two view indexes ~40 once
(then cached). The defaults (800 simulated + 60 real trials) are ~4200 CPU s, ~35 min on two
free cores; ``--starts 100`` ~2700 CPU s; ``--stride1 4`` saves ~3/4 of setup 1's cost.

Work is spread over ``--jobs`` processes (spawned; one trial per task). Each map's view index
is first made ready once (built, or loaded from ``--cache``, git-ignored ``build/``) by one task
per map, then every process loads it from that cache once and keeps it in memory for all its
trials. Writes ``docs/global/drive.md`` (tables, command, commit, date, load) and
``docs/global/drive.csv`` (one row per trial) under ``--out``.
"""

from __future__ import annotations

import argparse
import csv
import math
import multiprocessing
import os
import shlex
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
if str(Path(__file__).resolve().parent) not in sys.path:
    sys.path.insert(1, str(Path(__file__).resolve().parent))  # bench_real, bench_worlds

from plan_share import PlanShare

from service.core import global_localization as gl
from service.core.factory import create_localizer
from service.core.types import MapData, wrap_angle
from sim_publisher.office import office_metric_map, office_schematic_map, office_world
from sim_publisher.publisher import random_free_poses
from sim_publisher.scenario import make_setup
from sim_publisher.trajectory import simulate_odometry

MAPS = {"metric": (office_metric_map, 1), "schematic": (office_schematic_map, 2)}


def _load() -> str:
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


def precompute(name: str, cache: Path) -> tuple[float, float, int, int]:
    """(cold build s, cached load s, viewpoints, units) of one map."""
    md = MAPS[name][0]()
    gl.clear_memory_cache()
    t0 = time.perf_counter()
    idx = gl.load_or_build_index(md, cache_dir=cache)
    cold = time.perf_counter() - t0
    gl.clear_memory_cache()
    t0 = time.perf_counter()
    gl.load_or_build_index(md, cache_dir=cache)
    warm = time.perf_counter() - t0
    return cold, warm, len(idx.viewpoints), len(idx)


def office_room(x: float, y: float) -> str:
    """Room of a point of the office world (``sim_publisher/worlds/make_office.py``): west rooms
    W1-W4 (walls at y = 6, 12, 17), the corridor C (5.6 < x < 7.6), east rooms E1-E3 (walls at
    y = 8, 15). W1 and W4 are congruent within 0.2 m (their doors sit 3.0 m and 2.8 m above
    their south walls)."""
    if x < 5.6:
        return "W" + str(1 + int(y > 6.0) + int(y > 12.0) + int(y > 17.0))
    if x > 7.6:
        return "E" + str(1 + int(y > 8.0) + int(y > 15.0))
    return "C"


def trial_poses(start: np.ndarray, motion: str, world, turn: float = np.pi / 2) -> np.ndarray:
    """The up to 3 true poses of one trial (map frame). ``creep``: 3 cm forward per scan (stays
    put if that would leave free space). ``look-around``: turns in place by ``turn`` per scan."""
    if motion == "look-around":
        return np.array([[start[0], start[1], wrap_angle(start[2] + s * turn)] for s in range(3)])
    out = []
    for s in range(3):
        p = start + np.array([0.03 * s * np.cos(start[2]), 0.03 * s * np.sin(start[2]), 0.0])
        out.append(p if world.is_free(p[:2], 0.25)[0] else start.copy())
    return np.array(out)


def random_trials(name: str, n: int, seed: int, motion: str = "creep") -> dict[str, float]:
    """Found / wrong / unresolved fractions and time-to-first-fix percentiles. ``motion`` as in
    :func:`trial_poses`; look-around trials send odometry (``simulate_odometry``: about 1-3 %
    rotation error), creep trials send none."""
    md = MAPS[name][0]()
    su = make_setup(MAPS[name][1], max_scans=2)
    world = office_world()
    found = wrong = 0
    ttf: list[float] = []
    scans_needed: list[int] = []
    rooms: dict[str, list[int]] = {}  # room -> [trials, found, wrong]
    for k, start in enumerate(random_free_poses(world, n, seed)):
        room = rooms.setdefault(office_room(start[0], start[1]), [0, 0, 0])
        room[0] += 1
        truth = trial_poses(start, motion, world)
        odom = simulate_odometry(truth, seed=1000 + k) if motion == "look-around" else None
        loc = create_localizer("shape", md, None)
        spent = 0.0
        for s in range(3):
            p = truth[s]
            r, a = su.laser.scan(p, 1000 * k + s)
            t0 = time.perf_counter()
            est = loc.update(r, a, None if odom is None else odom[s])
            spent += time.perf_counter() - t0
            if est.status == "tracking":
                ok = np.hypot(*(est.pose[:2] - p[:2])) < 0.5 and abs(
                    wrap_angle(float(est.pose[2] - p[2]))
                ) < np.deg2rad(10.0)
                found += bool(ok)
                wrong += not ok
                room[1 if ok else 2] += 1
                if ok:
                    ttf.append(spent)
                    scans_needed.append(s + 1)
                break
    t = np.asarray(ttf) if ttf else np.full(1, np.nan)
    return {
        "n": n,
        "found": found / n,
        "wrong": wrong / n,
        "none": (n - found - wrong) / n,
        "ttf50": float(np.percentile(t, 50)),
        "ttf95": float(np.percentile(t, 95)),
        "scans_mean": float(np.mean(scans_needed)) if scans_needed else float("nan"),
        "rooms": rooms,
    }


def setup_run(setup: int, max_scans: int | None) -> dict[str, float]:
    """Full setup with initial_pose null: tracking poses passing the proximity test."""
    su = make_setup(setup, max_scans=max_scans)
    loc = create_localizer("shape", su.map_data, None)
    tracking = passed = first_fix = lost = 0
    first = None
    t0 = time.perf_counter()
    for i in range(len(su)):
        est = loc.update(*su.scan(i))
        if est.status == "tracking":
            tracking += 1
            passed += su.passed(i, est.pose)
            if first is None:
                first = i
        elif est.status == "lost":
            lost += 1
    first_fix = -1 if first is None else first
    return {
        "scans": len(su),
        "tracking": tracking,
        "passed": passed / tracking if tracking else float("nan"),
        "first_fix_scan": first_fix,
        "lost": lost,
        "seconds": time.perf_counter() - t0,
    }


# --------------------------------------------------------------------------------------------
# Drive trials (--drive): global localisation while the robot drives (module docstring)
# --------------------------------------------------------------------------------------------

#: Travel (m) fed beyond the travel limit, so that "found at all" sees late fixes too.
DRIVE_MARGIN = 5.0
#: Travel limit (m) per map kind in simulation; the real logs use REAL_LIMIT on both maps.
SIM_LIMITS = {"metric": 5.0, "schematic": 15.0}
REAL_LIMIT = 15.0
#: The first fix's test: within FIX_DIST m and FIX_DEG deg of the truth.
FIX_DIST = 0.5
FIX_DEG = 10.0
#: The after-fix test on real logs (m); simulation uses Setup.passed.
REAL_AFTER_DIST = 0.5
GROUPS = ("office", "worlds", "real")
REAL_LOGS = ("intel", "fr079", "mit-csail")
HELD_OUT_FIRST_SEED = 1000
DRIVE_FIELDS_SKIP = ("search_ms",)
#: share_table's split of the trials by plan share (:mod:`plan_share`)
SHARE_SPLIT = 0.5


@dataclass(frozen=True)
class DriveMap:
    """One tour and map of the drive benchmark. ``group`` office | worlds | real; ``world``
    "office", a building seed ("1003") or a log name; ``kind`` metric | schematic."""

    group: str
    world: str
    kind: str

    @property
    def limit(self) -> float:
        """Travel limit (m) for a correct fix."""
        return REAL_LIMIT if self.group == "real" else SIM_LIMITS[self.kind]

    @property
    def setup(self) -> int | None:
        """The scenario setup (1 metric, 2 schematic) of a simulated tour, None on real logs."""
        return None if self.group == "real" else (1 if self.kind == "metric" else 2)

    @property
    def seed(self) -> int:
        """A building's seed (``world`` is "<seed>" or "<seed>@<clutter>")."""
        return int(self.world.split("@")[0])

    @property
    def clutter(self) -> float | None:
        """A building's furniture density when not the generator's default (``--clutter``)."""
        return float(self.world.split("@")[1]) if "@" in self.world else None

    def code(self) -> list[int]:
        """Integers naming this map in the start-choice seed (stable across runs; a building
        with ``--clutter`` draws the same start scans as without)."""
        w = REAL_LOGS.index(self.world) if self.group == "real" else 0
        if self.group == "worlds":
            w = self.seed
        return [GROUPS.index(self.group), w, 0 if self.kind == "metric" else 1]

    def label(self) -> str:
        if self.group == "real":
            split = " (HELD-OUT)" if self.world == "mit-csail" else ""
            return f"{self.world}{split} {'metric' if self.kind == 'metric' else 'schematised'}"
        name = "office" if self.group == "office" else f"building {self.seed}"
        if self.clutter is not None:
            name += f" (clutter {self.clutter:g})"
        return f"{name} setup {self.setup} ({self.kind})"


@dataclass
class DriveSource:
    """A tour as a trial reads it (built once per process, :func:`drive_source`).

    ``travel`` ``(n,)`` cumulative travel (m) from scan 0 (true steps in simulation, odometry
    steps on real logs); ``truth`` ``(n, 3)``, NaN rows on scans that are not scored;
    ``stride`` feed every ``stride``-th scan; ``scan(i)`` -> (ranges, angles); ``odom(i)`` the
    odometry pose; ``after(i, pose)`` the after-fix test of a scored scan."""

    map_data: MapData
    travel: np.ndarray
    truth: np.ndarray
    stride: int
    scan: Callable[[int], tuple[np.ndarray, np.ndarray]]
    odom: Callable[[int], np.ndarray | None]
    after: Callable[[int, np.ndarray], bool]

    @property
    def scored(self) -> np.ndarray:
        return np.all(np.isfinite(self.truth), axis=1)


@dataclass(frozen=True)
class DriveTask:
    """One trial: the map, the start scan, where the real logs and the index cache are."""

    map: DriveMap
    start: int
    trial: int
    data: str
    cache: str
    stride: int
    budget: float | None = 50.0


@dataclass
class DriveTrial:
    """The outcome of one drive trial (one CSV row; ``search_ms`` is pooled, not written)."""

    group: str
    world: str
    map: str
    setup: str
    trial: int
    start: int
    start_x: float
    start_y: float
    room: str
    stride: int
    limit_m: float
    scans: int
    scored: int
    travel_m: float
    truncated: bool
    found: bool
    within_limit: bool
    fix_scans: int  # scans fed up to and including the fix (-1: not found)
    fix_travel_m: float
    cpu_to_fix_s: float
    cpu_total_s: float
    first_fix_wrong: bool
    wrong_before_fix: int
    wrong_after_fix: int
    tracking_after_fix: int
    search_after_fix: int  # scans after the fix fed while the localiser was searching again
    search_scans: int
    search_ms_max: float
    search_ms_p99: float
    work_max: float
    hyp_sum: float
    hyp_scans: int
    wall_s: float
    #: mean share of the trial's returns on a mapped wall at the reference pose
    #: (:mod:`plan_share`; NaN without references)
    plan_share: float = math.nan
    search_ms: list[float] = field(default_factory=list, repr=False)


@dataclass
class Outcome:
    """:func:`classify` of a trial's scan sequence."""

    fix: int | None  # position of the first correct fix in the sequence
    fix_travel: float
    found: bool
    within_limit: bool
    first_fix_wrong: bool
    wrong_before_fix: int
    wrong_after_fix: int
    tracking_after_fix: int


def cumulative_travel(xy: np.ndarray) -> np.ndarray:
    """``(n,)`` travel (m) from the first point along the ``(n, 2)`` points (translation only;
    a non-finite step counts as 0)."""
    xy = np.asarray(xy, dtype=np.float64)
    if xy.shape[0] == 0:
        return np.zeros(0)
    step = np.hypot(*np.diff(xy[:, :2], axis=0).T)
    step = np.where(np.isfinite(step), step, 0.0)
    return np.concatenate([[0.0], np.cumsum(step)])


def choose_starts(
    travel: np.ndarray,
    need: float,
    n: int,
    rng: np.random.Generator,
    eligible: np.ndarray | None = None,
) -> np.ndarray:
    """Up to ``n`` distinct scan indices, sorted, drawn uniformly among the scans after which
    at least ``need`` metres of travel remain (and ``eligible``, when given). Fewer when fewer
    qualify; empty when none does."""
    travel = np.asarray(travel, dtype=np.float64)
    ok = (travel[-1] - travel >= need) if travel.size else np.zeros(0, dtype=bool)
    if eligible is not None:
        ok &= np.asarray(eligible, dtype=bool)
    cand = np.flatnonzero(ok)
    if cand.size == 0 or n <= 0:
        return np.zeros(0, dtype=np.int64)
    return np.sort(rng.choice(cand, size=min(n, cand.size), replace=False)).astype(np.int64)


def trial_end(travel: np.ndarray, start: int, need: float) -> int:
    """Exclusive end of a trial from ``start``: its last scan is the first whose travel since
    ``start`` exceeds ``need``, or the tour's last scan."""
    j = int(np.searchsorted(travel, travel[start] + need, side="right"))
    return min(j + 1, len(travel))


def fed_scans(start: int, end: int, stride: int, scored: np.ndarray) -> list[int]:
    """The scans a trial feeds from ``start`` to ``end`` (exclusive), one per ``stride`` scans:
    in each block ``[start + k * stride, start + (k + 1) * stride)`` the first scored scan, or
    the block's first scan where none is (a real log's references can fall on every 17th scan
    only, intel, and a fixed stride could skip all of them), and always ``end - 1`` last."""
    idx = []
    for b in range(start, end, stride):
        ok = np.flatnonzero(scored[b : min(b + stride, end)])
        idx.append(b + int(ok[0]) if ok.size else b)
    if idx[-1] != end - 1:
        idx.append(end - 1)  # the scan beyond the limit + margin is always fed
    return idx


def spread(total: int, parts: int) -> list[int]:
    """``total`` split over ``parts``: ``total // parts`` each, the first ``total % parts`` one
    more."""
    if parts <= 0:
        return []
    q, r = divmod(total, parts)
    return [q + (k < r) for k in range(parts)]


def fix_ok(pose: np.ndarray, truth: np.ndarray) -> bool:
    """The first fix's test: within FIX_DIST m and FIX_DEG deg of ``truth``."""
    d = math.hypot(float(pose[0] - truth[0]), float(pose[1] - truth[1]))
    return d < FIX_DIST and abs(float(wrap_angle(float(pose[2] - truth[2])))) < math.radians(
        FIX_DEG
    )


def classify(
    status: Sequence[str],
    close: Sequence[bool | None],
    after: Sequence[bool | None],
    travel: Sequence[float],
    limit: float,
) -> Outcome:
    """Score one trial's scans. Per fed scan: its estimate's ``status``; ``close`` the first
    fix's test (None: not scored); ``after`` the after-fix test (None: not scored);
    ``travel`` since the start (m). See the module docstring for found / confident wrong."""
    fix = None
    before = 0
    for k, (s, c) in enumerate(zip(status, close, strict=True)):
        if s != "tracking" or c is None:
            continue
        if c:
            fix = k
            break
        before += 1
    wrong = tracked = 0
    if fix is not None:
        for s, a in zip(status[fix + 1 :], after[fix + 1 :], strict=True):
            if s == "tracking" and a is not None:
                tracked += 1
                wrong += not a
    ft = float(travel[fix]) if fix is not None else math.nan
    return Outcome(
        fix=fix,
        fix_travel=ft,
        found=fix is not None,
        within_limit=fix is not None and ft <= limit,
        first_fix_wrong=before > 0,
        wrong_before_fix=before,
        wrong_after_fix=wrong,
        tracking_after_fix=tracked,
    )


def hypotheses_of(est: Any) -> float | None:
    """The live hypotheses an estimate reports: ``est.hypotheses`` (optional field) or
    ``est.extras["hypotheses"]``; a number, or a list's length; None when absent."""
    h = getattr(est, "hypotheses", None)
    if h is None:
        extras = getattr(est, "extras", None) or {}
        h = extras.get("hypotheses") if isinstance(extras, dict) else None
    if h is None:
        return None
    if isinstance(h, int | float | np.number):
        return float(h)
    try:
        return float(len(h))
    except TypeError:
        return None


_SOURCES: dict[tuple[DriveMap, str, int], DriveSource] = {}


def map_stride(m: DriveMap, stride1: int, real_stride: int) -> int:
    """The stride of ``m``'s trials: ``--real-stride`` on a real log, ``--stride1`` on a
    setup-1 (metric) tour in simulation, 1 on a floor-plan tour."""
    if m.group == "real":
        return real_stride
    return stride1 if m.kind == "metric" else 1


def drive_source(m: DriveMap, data: Path, stride: int = 1) -> DriveSource:
    """The tour of ``m`` (kept in this process; the last 4), its trials feeding one scan per
    ``stride`` (:func:`map_stride`)."""
    key = (m, str(data), stride)
    if key in _SOURCES:
        return _SOURCES[key]
    if m.group == "real":
        from bench_real import load_log, map_path

        from service.maps.files import load_map_file

        log = load_log(Path(data), m.world, None)
        md = load_map_file(map_path(m.world, m.kind), kind=m.kind)
        od = np.array([np.full(3, np.nan) if o is None else o for o in log.odom])
        truth = np.where(log.ok[:, None], log.reference, np.nan)

        def after_real(i: int, pose: np.ndarray) -> bool:
            t = truth[i]
            return math.hypot(float(pose[0] - t[0]), float(pose[1] - t[1])) < REAL_AFTER_DIST

        src = DriveSource(
            map_data=md,
            travel=cumulative_travel(od[:, :2]),
            truth=truth,
            stride=stride,
            scan=lambda i: (log.ranges[i], log.angles[i]),
            odom=lambda i: log.odom[i],
            after=after_real,
        )
    else:
        setup = 1 if m.kind == "metric" else 2
        if m.group == "office":
            su = make_setup(setup)
        else:
            from bench_worlds import _building

            from sim_publisher.scenario import building_setup

            su = building_setup(_building(m.seed, 0, m.clutter), setup, seed=0)
        src = DriveSource(
            map_data=su.map_data,
            travel=cumulative_travel(su.truth[:, :2]),
            truth=su.reference,
            stride=stride,
            scan=su.scan,
            odom=lambda i: su.odom[i],
            after=su.passed,
        )
    while len(_SOURCES) >= 4:
        _SOURCES.pop(next(iter(_SOURCES)))
    _SOURCES[key] = src
    return src


def _localizer(md: MapData, cache: str | None, budget: float | None = None) -> Any:
    """``create_localizer("shape", md, None)``, with the index cache dir and the per-scan
    search budget (reference ms; ``None``: a whole search per scan)."""
    return create_localizer(
        "shape", md, None, cache_dir=Path(cache) if cache else None, search_budget_ms=budget
    )


_PLANS: dict[DriveMap, PlanShare] = {}


def plan_share_of(m: DriveMap, src: DriveSource) -> PlanShare:
    """The plan-share test of ``m``'s map (kept in this process)."""
    if m not in _PLANS:
        _PLANS[m] = PlanShare(src.map_data)
    return _PLANS[m]


def share_table(trials: Sequence[DriveTrial], maps: Sequence[DriveMap]) -> str:
    """Found within the limit / trials, split by the trial's plan share (:mod:`plan_share`)
    below or at least ``SHARE_SPLIT``, per map row of :func:`drive_table`."""
    lines = [
        f"| map | plan share < {SHARE_SPLIT} | plan share >= {SHARE_SPLIT} |",
        "|---|---|---|",
    ]
    for m, ts in table_groups(trials, maps):
        cells = []
        for low in (True, False):
            sel = [
                t for t in ts if math.isfinite(t.plan_share) and (t.plan_share < SHARE_SPLIT) == low
            ]
            ok = sum(t.within_limit for t in sel)
            cells.append(f"{ok}/{len(sel)}" if sel else "–")
        name = f"{m.group} {m.world if m.group != 'worlds' else 'worlds'} {m.kind}"
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def prepare_drive_map(m: DriveMap, data: str, cache: str, stride: int) -> dict[str, Any]:
    """Load the tour and make its map's view index ready (built or loaded from ``cache``);
    returns the tour's travel and scored scans for the start choice, and the index figures."""
    t0 = time.perf_counter()
    src = drive_source(m, Path(data), stride)
    t1 = time.perf_counter()
    loc = _localizer(src.map_data, cache)
    idx = getattr(loc, "index", None)
    t2 = time.perf_counter()
    return {
        "map": m,
        "travel": src.travel,
        "scored": src.scored,
        "scans": len(src.travel),
        "tour_m": float(src.travel[-1]) if len(src.travel) else 0.0,
        "load_s": t1 - t0,
        "index_s": t2 - t1,
        "viewpoints": len(idx.viewpoints) if idx is not None else -1,
        "units": len(idx) if idx is not None else -1,
    }


def _prepare_job(args: tuple[DriveMap, str, str, int]) -> dict[str, Any]:
    return prepare_drive_map(*args)


_WARM: set[DriveMap] = set()


def _warm(m: DriveMap, src: DriveSource, cache: str) -> None:
    """Before the first timed trial of ``m`` in this process: its view index into memory (the
    service loads it once per map, not per robot) and, on this process' first map, a few
    untimed searching and tracking updates (numba kernels loaded from their on-disk cache, or
    compiled)."""
    if m in _WARM:
        return
    loc = _localizer(src.map_data, cache)
    getattr(loc, "index", None)
    if not _WARM:
        scored = np.flatnonzero(src.scored)
        i0 = int(scored[0]) if scored.size else 0
        n = min(3, len(src.travel) - i0)
        for i in range(i0, i0 + n):
            loc.update(*src.scan(i), src.odom(i))
        trk = create_localizer("shape", src.map_data, src.truth[i0].copy())
        for i in range(i0, i0 + n):
            trk.update(*src.scan(i), src.odom(i))
    _WARM.add(m)


def run_drive_trial(task: DriveTask) -> DriveTrial:
    """Run one trial (see the module docstring)."""
    m = task.map
    src = drive_source(m, Path(task.data), task.stride)
    _warm(m, src, task.cache)
    need = m.limit + DRIVE_MARGIN
    end = trial_end(src.travel, task.start, need)
    idx = fed_scans(task.start, end, src.stride, src.scored)
    loc = _localizer(src.map_data, task.cache, task.budget)
    status: list[str] = []
    work: list[float] = []
    close: list[bool | None] = []
    after: list[bool | None] = []
    travel: list[float] = []
    cpu: list[float] = []
    search_ms: list[float] = []
    hyps: list[float] = []
    flags: list[bool] = []
    shares: list[float] = []
    plan = plan_share_of(m, src)
    prev = "initializing"
    t_start = time.perf_counter()
    t0_travel = float(src.travel[task.start])
    for i in idx:
        r, a = src.scan(i)
        searching = getattr(loc, "searching", None)
        if not isinstance(searching, bool):
            searching = prev != "tracking"
        c0 = time.process_time()
        w0 = time.perf_counter()
        est = loc.update(r, a, src.odom(i))
        w1 = time.perf_counter()
        cpu.append(time.process_time() - c0)
        prev = est.status
        status.append(est.status)
        travel.append(float(src.travel[i]) - t0_travel)
        t = src.truth[i]
        scored = bool(np.all(np.isfinite(t)))
        if scored:
            shares.append(plan.scan_share(t, r, a))
        close.append(fix_ok(est.pose, t) if scored else None)
        after.append(bool(src.after(i, est.pose)) if scored else None)
        flags.append(searching)
        if searching:
            search_ms.append(1e3 * (w1 - w0))
            work.append(float(getattr(loc, "work_ms", math.nan)))
            h = hypotheses_of(est)
            if h is not None:
                hyps.append(h)
    wall = time.perf_counter() - t_start
    out = classify(status, close, after, travel, m.limit)
    s0 = src.truth[task.start]
    sm = np.asarray(search_ms)
    return DriveTrial(
        group=m.group,
        world=m.world,
        map=m.kind,
        setup="" if m.setup is None else str(m.setup),
        trial=task.trial,
        start=task.start,
        start_x=float(s0[0]),
        start_y=float(s0[1]),
        room=office_room(float(s0[0]), float(s0[1])) if m.group == "office" else "",
        stride=src.stride,
        limit_m=m.limit,
        scans=len(idx),
        scored=sum(c is not None for c in close),
        travel_m=travel[-1],
        truncated=travel[-1] <= need,
        found=out.found,
        within_limit=out.within_limit,
        fix_scans=-1 if out.fix is None else out.fix + 1,
        fix_travel_m=out.fix_travel,
        cpu_to_fix_s=math.nan if out.fix is None else float(sum(cpu[: out.fix + 1])),
        cpu_total_s=float(sum(cpu)),
        first_fix_wrong=out.first_fix_wrong,
        wrong_before_fix=out.wrong_before_fix,
        wrong_after_fix=out.wrong_after_fix,
        tracking_after_fix=out.tracking_after_fix,
        search_after_fix=0 if out.fix is None else sum(flags[out.fix + 1 :]),
        search_scans=int(sm.size),
        search_ms_max=float(sm.max()) if sm.size else math.nan,
        search_ms_p99=float(np.percentile(sm, 99)) if sm.size else math.nan,
        work_max=float(np.nanmax(work)) if work and not np.all(np.isnan(work)) else math.nan,
        hyp_sum=float(sum(hyps)),
        hyp_scans=len(hyps),
        wall_s=wall,
        plan_share=float(np.nanmean(shares)) if np.any(np.isfinite(shares)) else math.nan,
        search_ms=search_ms,
    )


def _pct_inf(x: Sequence[float], q: float) -> float:
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
    """One table row over the trials of one map (see the module docstring)."""
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
        "travel50": _pct_inf([t.fix_travel_m for t in trials], 50),
        "travel90": _pct_inf([t.fix_travel_m for t in trials], 90),
        "cpu50": _pct_inf([t.cpu_to_fix_s for t in trials], 50),
        "cpu95": _pct_inf([t.cpu_to_fix_s for t in trials], 95),
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
            med = _pct_inf([t.fix_travel_m for t in rs], 50)
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


def parse_worlds(text: str) -> list[int]:
    """``--worlds``: a count N (seeds 1000 .. 999 + N), a range ``a-b`` or a comma list."""
    text = text.strip()
    if "," in text:
        return [int(x) for x in text.split(",") if x.strip()]
    if "-" in text:
        a, b = (int(x) for x in text.split("-", 1))
        return list(range(a, b + 1))
    return list(range(HELD_OUT_FIRST_SEED, HELD_OUT_FIRST_SEED + int(text)))


def drive_maps(
    groups: Sequence[str],
    seeds: Sequence[int],
    logs: Sequence[str],
    kinds: Sequence[str] = ("metric", "schematic"),
    clutter: float | None = None,
) -> list[DriveMap]:
    """The maps of the selected groups and map kinds, in table order; the buildings with
    furniture density ``clutter`` instead of the generator's default when given."""
    out: list[DriveMap] = []
    tag = "" if clutter is None else f"@{clutter:g}"
    for g in groups:
        for kind in (k for k in ("metric", "schematic") if k in kinds):
            if g == "office":
                out.append(DriveMap("office", "office", kind))
            elif g == "worlds":
                out += [DriveMap("worlds", f"{s}{tag}", kind) for s in seeds]
            else:
                out += [DriveMap("real", log, kind) for log in logs]
    if "real" in groups:  # real rows: log by log, metric then schematised
        real = sorted(
            (m for m in out if m.group == "real"),
            key=lambda m: (REAL_LOGS.index(m.world), m.kind != "metric"),
        )
        out = [m for m in out if m.group != "real"] + real
    return out


def _pool_map(
    fn: Callable[[Any], Any], items: Sequence[Any], jobs: int
) -> Iterator[tuple[int, Any]]:
    """``(position, fn(item))`` in completion order; in this process when ``jobs`` <= 1.
    Every process first compiles or loads the core's numba kernels
    (:func:`service.core._kernels.warm_up`), as the service does at start-up, so no trial's
    CPU counts it (after a kernel changes, compiling took ~5 s of the first trial per process)."""
    from service.core._kernels import warm_up

    if jobs <= 1:
        warm_up()
        for k, it in enumerate(items):
            yield k, fn(it)
        return
    from concurrent.futures import as_completed

    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=jobs, mp_context=ctx, initializer=warm_up) as ex:
        futs = {ex.submit(fn, it): k for k, it in enumerate(items)}
        for f in as_completed(futs):
            yield futs[f], f.result()


def drive_main(args: argparse.Namespace, argv: Sequence[str]) -> int:
    """Run the drive trials and write the tables (see the module docstring)."""
    from bench_real import git_commit

    groups = [g.strip() for g in args.groups.split(",") if g.strip()]
    bad = [g for g in groups if g not in GROUPS]
    logs = [g.strip() for g in args.logs.split(",") if g.strip()]
    bad += [g for g in logs if g not in REAL_LOGS]
    if bad or not groups:
        raise SystemExit(f"unknown group or log: {bad or args.groups}")
    if "real" in groups and not Path(args.data).is_dir():
        raise SystemExit(f"{args.data}: no real-log directory (--data, or drop group 'real')")
    seeds = parse_worlds(args.worlds)
    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    if not kinds or any(k not in ("metric", "schematic") for k in kinds):
        raise SystemExit(f"--kinds: metric and/or schematic, got {args.kinds!r}")
    maps = drive_maps(groups, seeds, logs, kinds, args.clutter)
    cap = args.quick if args.quick is not None else 1 << 30
    cache = str(Path(args.cache).resolve())
    data = str(Path(args.data).resolve())
    command = "python bench/bench_global.py " + shlex.join(argv)
    commit = git_commit()
    load0 = _load()
    date = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    print(f"{command}\ncommit {commit}, {date}, load average at start: {load0}", flush=True)
    t_all = time.perf_counter()

    # 1. tours loaded and view indexes made ready, one task per map
    info: dict[DriveMap, dict[str, Any]] = {}
    strides = {m: map_stride(m, args.stride1, args.real_stride) for m in maps}
    prep = [(m, data, cache, strides[m]) for m in maps]
    for k, r in _pool_map(_prepare_job, prep, args.jobs):
        info[maps[k]] = r
        print(
            f"ready: {maps[k].label()}: {r['scans']} scans, {r['tour_m']:.1f} m tour, "
            f"index {r['index_s']:.1f} s ({r['viewpoints']} viewpoints)",
            flush=True,
        )
    t_prep = time.perf_counter() - t_all

    # 2. start scans
    per_world = {
        kind: dict(zip(seeds, spread(args.starts, len(seeds)), strict=True))
        for kind in ("metric", "schematic")
    }
    notes: list[str] = []
    tasks: list[DriveTask] = []
    for m in maps:
        if m.group == "office":
            want = args.starts
        elif m.group == "worlds":
            want = per_world[m.kind][m.seed]
        else:
            want = args.real_starts
        want = min(want, cap)
        r = info[m]
        need = m.limit + DRIVE_MARGIN
        rng = np.random.default_rng([args.seed, *m.code()])
        eligible = r["scored"] if m.group == "real" else None
        starts = choose_starts(r["travel"], need, want, rng, eligible)
        if want > 0 and starts.size == 0:
            notes.append(
                f"{m.label()}: SKIPPED, the tour ({r['tour_m']:.1f} m) leaves no start scan with "
                f"{need:.0f} m of travel after it"
            )
        elif starts.size < want:
            notes.append(f"{m.label()}: only {starts.size} distinct start scans (of {want})")
        budget = args.budget_ms if args.budget_ms > 0 else None
        tasks += [
            DriveTask(m, int(s), k, data, cache, strides[m], budget) for k, s in enumerate(starts)
        ]
    for n in notes:
        print(n)

    # 3. trials: grouped by map, so that each process loads each index once; the longest
    # (real logs, then floor plans) first, so that both processes finish together
    order = {m: k for k, m in enumerate(maps)}
    rank = {"real": 0, "worlds": 1, "office": 1}
    tasks.sort(key=lambda t: (rank[t.map.group], t.map.kind == "metric", order[t.map], t.trial))
    trials: list[DriveTrial] = []
    t_run = time.perf_counter()
    for done, (_, t) in enumerate(_pool_map(run_drive_trial, tasks, args.jobs), 1):
        trials.append(t)
        fix = f"fixed at {t.fix_travel_m:.2f} m" if t.found else "NOT found"
        print(
            f"[{done}/{len(tasks)}] {DriveMap(t.group, t.world, t.map).label()} start {t.start}: "
            f"{fix}{' FIRST-FIX WRONG' if t.first_fix_wrong else ''}"
            f"{f' after-fix wrong {t.wrong_after_fix}' if t.wrong_after_fix else ''}, "
            f"{t.scans} scans, cpu {t.cpu_total_s:.1f} s, wall {t.wall_s:.1f} s "
            f"({time.perf_counter() - t_run:.0f} s)",
            flush=True,
        )
    wall = time.perf_counter() - t_all
    trials.sort(key=lambda t: (order[DriveMap(t.group, t.world, t.map)], t.trial))
    load1 = _load()

    # 4. tables
    table = drive_table(trials, maps)
    rooms = room_table(trials)
    shares = share_table(trials, maps)
    idx_lines = [
        "| map | scans | tour m | index ready s | viewpoints | units |",
        "|---|---|---|---|---|---|",
    ]
    idx_lines += [
        f"| {m.label()} | {info[m]['scans']} | {info[m]['tour_m']:.1f} | "
        f"{info[m]['index_s']:.1f} | {info[m]['viewpoints']} | {info[m]['units']} |"
        for m in maps
    ]
    print("\n" + table)
    if rooms:
        print("Office, by room of the start pose: found <= limit / trials, median travel to fix")
        print(rooms)
    summary = (
        f"{len(trials)} trials in {wall:.0f} s wall ({t_prep:.0f} s loading tours and indexes) "
        f"with {args.jobs} process(es); load average at start {load0}, at end {load1}"
    )
    print("Found <= limit / trials by the drive's plan share (bench/plan_share.py):")
    print(shares)
    print(summary)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_drive_csv(out / "drive.csv", trials)
    md = [
        "# Global localisation while driving (issue 13)",
        "",
        f"Generated by `{command}` at commit {commit} on {date}, on the shared 2-core "
        f"machine: {summary}.",
        "",
        *(
            [
                f"**Smoke run** (`--quick {args.quick}`: at most {args.quick} starts per map and "
                "world): a check of the benchmark, too few trials for its figures.",
                "",
            ]
            if args.quick is not None
            else []
        ),
        "Each trial starts at a random scan of a tour with no initial pose and feeds every "
        "following scan with its odometry until the travel exceeds the limit + "
        f"{DRIVE_MARGIN:.0f} m. Found = the first `tracking` estimate within {FIX_DIST} m and "
        f"{FIX_DEG:.0f} deg of the truth; travel = true step lengths in simulation, odometry "
        "step lengths on the real logs (scored only on scans with a flag-1 reference); "
        "confident wrong first fix = a `tracking` estimate failing that test before the "
        "correct fix; after the fix = `tracking` estimates failing the tour's own test "
        "(setup 1: 100 mm / 45 deg, setup 2: 500 mm / 45 deg, real logs: 0.5 m); searching "
        "again = trials that lost the track after the correct fix and searched again; CPU = "
        "`time.process_time` of the updates up to the fix; percentiles over all trials, a "
        "trial not found counts as infinite (n/f). Full definitions: the docstring of "
        "`bench/bench_global.py`. One row per trial in `drive.csv`.",
        "",
        table,
    ]
    if notes:
        md += ["Notes:", "", *[f"- {n}" for n in notes], ""]
    md += [
        "Found <= limit / trials by the trial's plan share (`bench/plan_share.py`): the mean "
        "share of its returns within 0.3 m of a mapped wall at the reference pose. Below "
        f"{SHARE_SPLIT} the map shows less than half of what the robot sees (a hall drawn as "
        "its outline on a floor plan): a limit of the map rather than of the localiser.",
        "",
        shares,
    ]
    if rooms:
        md += [
            "Office, by room of the start pose (`office_room`): found <= limit / trials, "
            "median travel to a fix (over all trials, n/f = not found), first-fix confident "
            "wrong if any.",
            "",
            rooms,
        ]
    md += ["Tours and view indexes (index ready: built, or loaded from the cache):", ""]
    md += [*idx_lines, ""]
    (out / "drive.md").write_text("\n".join(md), encoding="utf-8")
    print(f"wrote {out / 'drive.md'} and {out / 'drive.csv'}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Run the measurements and print the tables."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--poses", type=int, default=200, help="random poses per map")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--maps", default="metric,schematic")
    ap.add_argument("--setup-scans", type=int, default=None, help="truncate the setups")
    ap.add_argument("--no-setups", action="store_true", help="skip the full-setup runs")
    ap.add_argument(
        "--motions", default="creep,look-around", help="trial motions (creep, look-around)"
    )
    drive = ap.add_argument_group("drive trials (--drive; see the module docstring)")
    drive.add_argument("--drive", action="store_true", help="run the drive trials instead")
    drive.add_argument("--groups", default="office,worlds,real", help="office,worlds,real")
    drive.add_argument(
        "--starts", type=int, default=200, help="starts per office setup and per worlds setup"
    )
    drive.add_argument(
        "--worlds", default="8", help="held-out worlds: a count N (seeds 1000..999+N), a-b or a,b"
    )
    drive.add_argument(
        "--kinds", default="metric,schematic", help="map kinds: metric and/or schematic"
    )
    drive.add_argument(
        "--clutter",
        type=float,
        default=None,
        help="the buildings' furniture density (generator's BuildingParams.clutter, at most "
        "0.25; default the office's 0.089): the floor plan is the same, the scans see more "
        "furniture (a plan share below 0.5 on some tours, as in real furnished halls)",
    )
    drive.add_argument("--real-starts", type=int, default=40, help="starts per real log and map")
    drive.add_argument("--logs", default=",".join(REAL_LOGS), help="real logs")
    drive.add_argument("--data", type=Path, default=Path("/work/shared/data/real"))
    drive.add_argument("--jobs", type=int, default=2, help="processes (1: in this process)")
    drive.add_argument(
        "--quick", type=int, default=None, help="smoke run: at most N starts per map and world"
    )
    drive.add_argument("--stride1", type=int, default=1, help="feed every k-th setup-1 scan")
    drive.add_argument("--real-stride", type=int, default=1, help="feed every k-th real scan")
    drive.add_argument(
        "--budget-ms",
        type=float,
        default=50.0,
        help="per-scan search budget, reference ms (the service's default 50; 0: whole search)",
    )
    drive.add_argument(
        "--cache",
        type=Path,
        default=Path(__file__).resolve().parents[1] / "build" / "bench_global" / "index",
    )
    drive.add_argument(
        "--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "global"
    )
    args = ap.parse_args(argv)
    if args.drive:
        if args.stride1 < 1 or args.real_stride < 1:
            ap.error("--stride1 and --real-stride must be >= 1")
        return drive_main(args, sys.argv[1:] if argv is None else argv)
    maps = [m.strip() for m in args.maps.split(",") if m.strip()]
    print(f"load average at start: {_load()}")
    with tempfile.TemporaryDirectory() as tmp:
        print("\n| map | viewpoints | units | precompute cold s | cached load s |")
        print("|---|---|---|---|---|")
        for m in maps:
            cold, warm, v, u = precompute(m, Path(tmp))
            print(f"| {m} | {v} | {u} | {cold:.1f} | {warm:.2f} |")
    motions = [m.strip() for m in args.motions.split(",") if m.strip()]
    print(
        f"\n{args.poses} random free-space poses per map (seed {args.seed}), no initial pose, "
        "<= 3 scans; creep: 3 cm forward between scans, no odometry; look-around: turning "
        "90 deg in place between scans, odometry sent"
    )
    print(
        "| map | motion | found < 0.5 m, < 10 deg | confident wrong | no fix in 3 scans "
        "| scans to fix (mean) | first fix p50 s | p95 s |"
    )
    print("|---|---|---|---|---|---|---|---|")
    by_room = {}
    for m in maps:
        for motion in motions:
            r = random_trials(m, args.poses, args.seed, motion)
            by_room[(m, motion)] = r["rooms"]
            print(
                f"| {m} | {motion} | {100 * r['found']:.1f} % | {100 * r['wrong']:.1f} % | "
                f"{100 * r['none']:.1f} % | {r['scans_mean']:.2f} | {r['ttf50']:.2f} | "
                f"{r['ttf95']:.2f} |",
                flush=True,
            )
    names = sorted({k for rooms in by_room.values() for k in rooms})
    print("\nBy room of the start pose: found / trials (confident wrong, if any)")
    print("| map | motion | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for (m, motion), rooms in by_room.items():
        cells = []
        for k in names:
            t, f, w = rooms.get(k, [0, 0, 0])
            cells.append(f"{f}/{t}" + (f" ({w})" if w else ""))
        print(f"| {m} | {motion} | " + " | ".join(cells) + " |")
    print(f"load average: {_load()}")
    if not args.no_setups:
        print("\nFull setups with initial_pose null (no confident wrong poses)")
        print(
            "| setup | scans | tracking | tracking poses passing | first fix at scan | lost | s |"
        )
        print("|---|---|---|---|---|---|---|")
        for st in (1, 2):
            r = setup_run(st, args.setup_scans)
            print(
                f"| {st} | {r['scans']} | {r['tracking']} | {100 * r['passed']:.2f} % | "
                f"{r['first_fix_scan']} | {r['lost']} | {r['seconds']:.0f} |"
            )
        print(f"load average: {_load()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
