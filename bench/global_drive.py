"""The drive benchmark of ``bench_global.py --drive``: its maps, tours and trials.

What a trial is and how it is scored: the constants (travel limits, the first fix's test),
:class:`DriveMap` (a tour and map), :class:`DriveSource` (the tour as a trial reads it,
:func:`drive_source`), :class:`DriveTask` / :class:`DriveTrial` (a trial in and out), the start
choice (:func:`choose_starts`), the fed scans (:func:`trial_end`, :func:`fed_scans`), the
classification (:func:`classify`) and the map list (:func:`drive_maps`); also
:func:`office_room` and :func:`load_average`, which the single-scan benchmark shares. Running
the trials: ``global_drive_run.py``; the tables and CSV: ``global_drive_tables.py``; the full
definitions: the docstring of ``bench_global.py``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bench.plan_share import HOLDS_SHARE
from service.adapters.maps.index_files import IndexFiles
from service.core.factory import create_localizer
from service.core.types import MapData, wrap_angle
from sim_publisher.scenario import make_setup

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


def load_average() -> str:
    """The 1, 5 and 15 min load averages as printed with the results ("n/a" where unknown)."""
    try:
        return " ".join(f"{v:.2f}" for v in os.getloadavg())
    except OSError:
        return "n/a"


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
    #: calibration (``--calibrate DIR``): the decision never fixes; each searching scan's LLR,
    #: its leader's position error and whether its twin check ran go to ``DIR``
    calibrate: str | None = None
    #: the probation's calibration (``--calibrate-pass DIR``): no probation ever passes; on each
    #: scan one is judged, its LLR, its winner's error and whether the winner led go to ``DIR``
    calibrate_pass: str | None = None


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
    #: travel (m) from which the map holds (:func:`holds_from`; inf: never; NaN: no references)
    holds_from_m: float = math.nan
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


#: The map holds from the first of this many scored scans in a row where it holds
#: (:data:`bench.plan_share.HOLDS_SHARE`): one scan's share is noisy (a doorway, a person).
HOLDS_RUN = 3


def holds_from(travel: Sequence[float], shares: Sequence[float]) -> float:
    """The travel (m) of the first of :data:`HOLDS_RUN` scored scans in a row whose plan share
    (``shares``, one per scored scan at ``travel``) is at least :data:`HOLDS_SHARE`: where the
    map starts to show what the robot sees. ``inf`` if it never does, NaN without scans."""
    if len(shares) == 0:
        return math.nan
    run = 0
    for i, share in enumerate(shares):
        run = run + 1 if share >= HOLDS_SHARE else 0
        if run == HOLDS_RUN:
            return float(travel[i - HOLDS_RUN + 1])
    return math.inf


def pose_error(pose: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """``pose``'s position error (m) and absolute heading error (rad) against ``truth``."""
    d = math.hypot(float(pose[0] - truth[0]), float(pose[1] - truth[1]))
    return d, abs(float(wrap_angle(float(pose[2] - truth[2]))))


def fix_ok(pose: np.ndarray, truth: np.ndarray) -> bool:
    """The first fix's test: within FIX_DIST m and FIX_DEG deg of ``truth``."""
    d, dth = pose_error(pose, truth)
    return d < FIX_DIST and dth < math.radians(FIX_DEG)


def classify(
    status: Sequence[str],
    close: Sequence[bool | None],
    after: Sequence[bool | None],
    travel: Sequence[float],
    limit: float,
) -> Outcome:
    """Score one trial's scans. Per fed scan: its estimate's ``status``; ``close`` the first
    fix's test (None: not scored); ``after`` the after-fix test (None: not scored);
    ``travel`` since the start (m). See the docstring of ``bench_global.py`` for found /
    confident wrong."""
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
        from bench.bench_real import load_log, map_path
        from service.adapters.maps.files import load_map_file

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
            from bench.bench_worlds import generated_building
            from sim_publisher.scenario import building_setup

            su = building_setup(generated_building(m.seed, 0, m.clutter), setup, seed=0)
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


def drive_localizer(md: MapData, cache: str | None, budget: float | None = None) -> Any:
    """``create_localizer("shape", md, None)``, with the directory of the view index files and
    the per-scan search budget (reference ms; ``None``: a whole search per scan)."""
    store = IndexFiles(Path(cache)) if cache else None
    return create_localizer("shape", md, None, index_store=store, search_budget_ms=budget)


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
