"""Scale benchmark of the localizer service: N simulated robots at R Hz against one service.

Starts ``python -m service`` on a free loopback port and puts the maps the rows need. Each
row configures N *tracked* robots (initial pose = their true start pose) and K *searching*
robots (initial pose null: global localisation), primes every robot with one scan (so cold
costs — map models, the global-search view index, numba caches — stay out of the window),
then a separate publisher process sends every robot's scans at ``--rate`` Hz (robots
staggered within the period) while this process receives the poses. After the row the
robots' configs are deleted, so every row starts from an empty service with the same maps.

Worlds and maps (``--world``, ``--map``): ``office`` is the paper's office world; an integer
is a generated building (``sim_publisher.generator``, default parameters, no moving people;
seeds 0-19 are the tuning split of ``bench/bench_worlds.py``, >= 1000 held out). ``metric``
gives the service the exact metric map (setup 1's), ``schematic`` the schematic map (setup
2's). Scans are always simulated against the TRUE world (furniture included) along the
world's tour, sampled every 11 mm (setup 1) and taken every ``--stride`` samples (default 5:
~55 mm and ~19 deg mean turn between consecutive scans; the run prints the measured
statistics), with the setup's laser (361 beams over 180 deg, 15 m, 1 cm noise, 1 % dropouts).

Motion and odometry: every robot walks back and forth along the tour from its own start
(reversing, heading kept, at either end). ``--odom`` (default) sends an odometry pose with each
scan: the walk's true poses run through the simulator's odometry error model
(``sim_publisher.trajectory.simulate_odometry``: scale error, translational noise, rotational
drift per metre and noise), one noise stream per robot, over the whole walk including the
turnarounds, so the error accumulates continuously and the increments always match the motion
actually driven. The odometry is expressed in its own frame (the robot's first pose is the
origin), as a real robot's would be.

Searching robots (``--searching K``, ``--search-mode``): ``refix`` (default) sends them real
scans of the same world along the tour and re-puts their config with a null pose as soon as
one of their poses reports ``tracking``, so they run global searches back to back for the
whole window (the search, its confirmation and the twin check included; between a fix and
the new config a few scans are tracked, which the row reports as their tracking share).
``foreign`` sends them mirror images of the world's scans (beams reversed, odometry mirrored):
a building that does not exist, so the search never ends (a fix is re-put the same way).
They are assigned to workers like any robot (the least-loaded worker, after the tracked
robots), so about half the tracked robots share a worker with a searcher on two workers.

Figures per row, over the window (``--duration`` minus ``--warmup`` s; scans are assigned to
the window by their scheduled send time): *answered* = poses received / scans sent (mean over
tracked robots and the worst robot; below 100 % the service skipped older scans: latest
wins, or a pose came more than 1 s after the publisher stopped); latency p50/p99 = pose
receipt minus the scan's ``stamp`` (its send time: both Zenoh hops, decoding, queueing and the
localisation); *starved* = some tracked robot got no pose, or answered less than half the
mean; *correct* = answered poses within ``--correct-m`` (0.5 m) and ``--correct-deg``
(10 deg) of the scan's true pose, whatever their status; *confident wrong* = poses with status
``tracking`` failing that test; *lost* = tracked robots' poses whose status is not
``tracking``. The CPU columns are the service (with its workers) and the load generator (this
process and the publisher) in % of one core, and the 1-min load average at the window's end:
both share the machine's cores with the service.

``--acceptance`` runs issue 15's acceptance table in one command: office metric and
schematic, held-out building 1000 metric and schematic, N=20 at 10 Hz; office metric N=40 at
5 Hz; and office metric N=20 at 10 Hz with K=0 and K=1 searching robots. It prints PASS/FAIL
per line: >= 99 % answered, p99 <= 50 ms, none starved; a searching robot adds <= 5 ms to the
tracked robots' p99. ``--out docs/scale.md`` writes the tables as markdown with the command,
the git commit and the date.

Usage: ``python bench/bench_service.py [--robots 1,5,10,20,30] [--method shape]
[--world office,1000] [--map metric,schematic] [--rate 10] [--searching 0,1]
[--workers 2] [--duration 10] [--out FILE] [--json FILE]`` (every comma list is crossed into
rows), or ``python bench/bench_service.py --acceptance [--duration 20] --out docs/scale.md``.
Numbers depend on the machine load; the load average is printed with every row.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import json
import math
import multiprocessing as mp
import os
import platform
import queue
import shlex
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import zenoh  # noqa: E402

from schemas.codec import decode, encode  # noqa: E402
from schemas.messages import Health, RobotConfig  # noqa: E402

P = "shapeloc"
MSGPACK = "application/msgpack"

#: Acceptance thresholds of issue 15.
ACCEPT_ANSWERED = 0.99
ACCEPT_P99_MS = 50.0
ACCEPT_SEARCH_ADDS_MS = 5.0


def free_endpoint() -> str:
    """An unused ``tcp/127.0.0.1:PORT``."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def client_config(endpoint: str) -> zenoh.Config:
    """Loopback-only client config."""
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps("client"))
    c.insert_json5("connect/endpoints", json.dumps([endpoint]))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("scouting/delay", "0")
    return c


def health(session: zenoh.Session, timeout: float = 2.0) -> Health | None:
    """The service's Health, or None (no answer within ``timeout`` s)."""
    for r in session.get(f"{P}/service/health", timeout=timeout):
        if r.ok is not None:
            return decode(Health, r.ok.payload.to_bytes(), str(r.ok.encoding))
    return None


# --------------------------------------------------------------------------- worlds and walks


@dataclass
class Pool:
    """The scans of one (world, map): true poses ``(m, 3)`` along the tour, their ranges as
    little-endian float32 bytes (and the mirror images), the laser's geometry and the map the
    service gets."""

    world: str
    map_kind: str
    map_id: str
    map_msg: Any
    truth: np.ndarray
    ranges: list[bytes]
    mirrored: list[bytes]
    info: dict[str, float]
    beams: int
    #: step (m) and turn (deg) statistics between consecutive scans of a walk
    motion: dict[str, float] = field(default_factory=dict)

    @property
    def key(self) -> tuple[str, str]:
        return (self.world, self.map_kind)


def world_name(world: str) -> str:
    """``office`` or ``building-<seed>``."""
    return "office" if world == "office" else f"building-{int(world)}"


def make_pool(world: str, map_kind: str, stride: int, seed: int = 7) -> Pool:
    """Setup-1 scans of ``world`` (``office`` or a generated building's seed) every ``stride``
    samples (11 mm each) of the whole tour; the map of ``map_kind`` for the service."""
    from service.convert import map_message_of
    from sim_publisher.scenario import building_setup, make_setup

    if map_kind not in ("metric", "schematic"):
        raise ValueError(f"--map must be metric or schematic, got {map_kind!r}")
    if world == "office":
        setup = make_setup(1, seed=seed)
        if map_kind == "metric":
            map_data = setup.map_data
        else:
            from sim_publisher.office import office_schematic_map

            map_data = office_schematic_map()
    else:
        from sim_publisher.generator import BuildingParams, generate_building

        b = generate_building(int(world), BuildingParams())
        setup = building_setup(b, 1, seed=seed, people=False)
        map_data = setup.map_data if map_kind == "metric" else building_setup(b, 2).map_data
    idx = np.arange(0, len(setup), stride)
    ranges, mirrored = [], []
    for i in idx:
        r = np.asarray(setup.scan(int(i))[0], dtype="<f4")
        ranges.append(r.tobytes())
        mirrored.append(r[::-1].tobytes())
    lz = setup.laser
    info = {
        "angle_min": float(lz.angle_min),
        "angle_increment": float(lz.angle_increment),
        "range_min": float(lz.config.range_min),
        "range_max": float(lz.config.max_range),
    }
    # The mirror image needs a field of view symmetric about the robot's x axis.
    fov_end = info["angle_min"] + (lz.config.beams - 1) * info["angle_increment"]
    assert math.isclose(fov_end, -info["angle_min"], abs_tol=1e-9), "asymmetric laser"
    # the poses on the map's own frame (a generated plan's scale error applied; docs/worlds.md):
    # the robots start there, their odometry walks along them and the answers are judged on them
    truth = setup.reference[idx]
    m = len(idx)
    return Pool(
        world=world,
        map_kind=map_kind,
        map_id=map_data.map_id,
        map_msg=map_message_of(map_data),
        truth=truth,
        ranges=ranges,
        mirrored=mirrored,
        info=info,
        beams=int(lz.config.beams),
        # a walk there and back: every step a robot's consecutive scans can make, turnarounds too
        motion=motion_stats([truth[ping_pong(0, m, 2 * m - 1)]]),
    )


def ping_pong(start: int, m: int, count: int) -> np.ndarray:
    """Pool indices of ``count`` consecutive scans of a robot walking from ``start`` forward
    along a tour of ``m`` scans, reversing at either end (no scan repeated at a turnaround)."""
    if m < 2:
        raise ValueError("a walk needs at least 2 scans")
    period = 2 * (m - 1)
    k = (start + np.arange(count)) % period
    return np.where(k < m, k, period - k).astype(np.int64)


def odometry_frame(poses: np.ndarray) -> np.ndarray:
    """``poses`` ``(n, 3)`` expressed in the frame of the first one (which becomes 0, 0, 0)."""
    p = np.asarray(poses, dtype=np.float64)
    o = p[0]
    c, s = math.cos(o[2]), math.sin(o[2])
    d = p[:, :2] - o[:2]
    th = (p[:, 2] - o[2] + np.pi) % (2 * np.pi) - np.pi
    return np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], th]


def walk_odometry(truth_walk: np.ndarray, seed: int) -> np.ndarray:
    """Drifting odometry of one robot's walk (its own frame, starting at 0, 0, 0)."""
    from sim_publisher.trajectory import simulate_odometry

    return odometry_frame(simulate_odometry(truth_walk, seed=seed))


def mirror_poses(poses: np.ndarray) -> np.ndarray:
    """Mirror image (about the x axis) of poses ``(n, 3)``: ``(x, -y, -theta)``."""
    p = np.asarray(poses, dtype=np.float64)
    return np.c_[p[:, 0], -p[:, 1], -p[:, 2]]


def motion_stats(walks: list[np.ndarray]) -> dict[str, float]:
    """Mean and p95 step (m) and absolute turn (deg) between consecutive poses of the walks
    (true poses ``(n, 3)`` each)."""
    steps, turns = [], []
    for w in walks:
        if len(w) < 2:
            continue
        steps.append(np.hypot(*np.diff(w[:, :2], axis=0).T))
        turns.append(np.rad2deg(np.abs((np.diff(w[:, 2]) + np.pi) % (2 * np.pi) - np.pi)))
    if not steps:
        return dict.fromkeys(("step_mean", "step_p95", "turn_mean", "turn_p95"), math.nan)
    st, tu = np.concatenate(steps), np.concatenate(turns)
    return {
        "step_mean": float(st.mean()),
        "step_p95": float(np.percentile(st, 95)),
        "turn_mean": float(tu.mean()),
        "turn_p95": float(np.percentile(tu, 95)),
    }


def pose_correct(est: np.ndarray, truth: np.ndarray, max_m: float, max_deg: float) -> np.ndarray:
    """Per row: estimate within ``max_m`` and ``max_deg`` of the true pose (``(n, 3)`` each)."""
    e, t = np.asarray(est, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    d = np.hypot(e[:, 0] - t[:, 0], e[:, 1] - t[:, 1])
    dth = np.abs((e[:, 2] - t[:, 2] + np.pi) % (2 * np.pi) - np.pi)
    return (d < max_m) & (np.rad2deg(dth) < max_deg)


# --------------------------------------------------------------------------- robots


@dataclass
class RobotPlan:
    """One robot of a row: its id, pool indices and odometry per seq (seq 0 is the priming
    scan), true poses, and whether it searches (null initial pose) on mirrored scans."""

    robot_id: str
    searching: bool
    mirrored: bool
    walk: np.ndarray
    truth: np.ndarray
    odom: np.ndarray | None


def plan_robots(
    pool: Pool,
    row: int,
    n: int,
    k: int,
    count: int,
    odom: bool,
    search_mode: str,
) -> list[RobotPlan]:
    """N tracked robots spread evenly along the tour, then K searching ones between them;
    ``count`` scans each (seq 0 .. count-1)."""
    m = len(pool.ranges)
    plans = []
    total = n + k
    for j in range(total):
        searching = j >= n
        start = int((j * m) // max(total, 1) + (m // (2 * total) if searching else 0)) % m
        walk = ping_pong(start, m, count)
        truth = pool.truth[walk]
        mirrored = searching and search_mode == "foreign"
        if mirrored:
            truth = mirror_poses(truth)
        o = walk_odometry(truth, seed=1000 * row + j) if odom else None
        rid = f"{'s' if searching else 'r'}{row}-{j}"
        plans.append(RobotPlan(rid, searching, mirrored, walk, truth, o))
    return plans


def scan_payload(info: dict[str, float], seq: int, ranges: bytes, odom: np.ndarray | None) -> bytes:
    """A msgpack Scan (``stamp`` = now)."""
    msg: dict[str, Any] = {
        "seq": seq,
        "stamp": time.time(),
        "angle_min": info["angle_min"],
        "angle_increment": info["angle_increment"],
        "range_min": info["range_min"],
        "range_max": info["range_max"],
        "ranges": ranges,
    }
    if odom is not None:
        msg["odom"] = [float(v) for v in odom]
    return msgpack.packb(msg)


def publisher_main(
    endpoint: str,
    robots: list[str],
    walks: list[np.ndarray],
    odoms: list[np.ndarray | None],
    mirrored: list[bool],
    ranges: list[bytes],
    ranges_mirrored: list[bytes],
    info: dict[str, float],
    rate: float,
    count: int,
    ctl: Any,
    out: Any,
) -> None:
    """Child process: once its publishers are declared it puts ``"ready"`` on ``out`` and
    gets ``t0`` from ``ctl``; robot ``i`` sends seq ``k`` (1 .. count-1) at ``t0 + (k-1)/rate
    + i/(rate*n)``. Puts ``(scans sent, send lag p99 ms, max lag ms)`` on ``out`` at the end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    n = len(robots)
    enc = zenoh.Encoding(MSGPACK)
    lags = []
    sent = 0
    with zenoh.open(client_config(endpoint)) as s:
        pubs = [s.declare_publisher(f"{P}/robots/{r}/scan", encoding=enc) for r in robots]
        out.put("ready")
        t0 = ctl.get()
        for k in range(1, count):
            for i in range(n):
                t_send = t0 + (k - 1) / rate + i / (rate * n)
                dt_ = t_send - time.time()
                if dt_ > 0:
                    time.sleep(dt_)
                lags.append(time.time() - t_send)
                pool = ranges_mirrored if mirrored[i] else ranges
                o = odoms[i]
                pubs[i].put(
                    scan_payload(info, k, pool[int(walks[i][k])], None if o is None else o[k])
                )
                sent += 1
    lag = np.asarray(lags) * 1e3
    out.put((sent, float(np.percentile(lag, 99)) if lag.size else 0.0, float(lag.max(initial=0))))


class Receiver:
    """Collects every pose: (robot, seq, stamp, receipt time, pose, status). Robots in
    :attr:`refix` are re-configured with a null pose (by a helper thread) when they report
    ``tracking``: :attr:`fixes` keeps (robot, seq, pose) of those fixes."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.lock = threading.Lock()
        self.rows: list[tuple[str, int, float, float, list[float], str]] = []
        self.refix: dict[str, str] = {}  # robot -> map id
        self.method = "shape"
        self.fixes: list[tuple[str, int, list[float]]] = []
        self._last_put: dict[str, float] = {}
        self._q: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._refixer, daemon=True)
        self._thread.start()
        self.sub = session.declare_subscriber(f"{P}/robots/*/pose", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        t = time.time()
        m = msgpack.unpackb(sample.payload.to_bytes())
        row = (m["robot_id"], m["seq"], m["stamp"], t, m["pose"], m["status"])
        with self.lock:
            self.rows.append(row)
            if m["status"] == "tracking" and m["robot_id"] in self.refix:
                self.fixes.append((m["robot_id"], m["seq"], m["pose"]))
                self._q.put(m["robot_id"])

    def _refixer(self) -> None:
        while True:
            rid = self._q.get()
            if rid is None:
                return
            with self.lock:
                map_id = self.refix.get(rid)
            now = time.monotonic()
            if map_id is None or now - self._last_put.get(rid, -1e9) < 0.5:
                continue  # one re-put per fix (the poses in flight report it too)
            self._last_put[rid] = now
            cfg = RobotConfig(map_id=map_id, method=self.method, initial_pose=None)
            with contextlib.suppress(zenoh.ZError):
                self.session.put(f"{P}/robots/{rid}/config", encode(cfg), encoding=MSGPACK)

    def take(self) -> tuple[list[tuple[str, int, float, float, list[float], str]], list]:
        with self.lock:
            rows, self.rows = self.rows, []
            fixes, self.fixes = self.fixes, []
        return rows, fixes

    def close(self) -> None:
        self._q.put(None)


# --------------------------------------------------------------------------- CPU accounting


def _proc_ticks(pid: int) -> tuple[int, int] | None:
    """(ppid, utime + stime clock ticks) of a process, from /proc (None if gone)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            raw = f.read().decode()
    except OSError:
        return None
    fields = raw[raw.rfind(")") + 2 :].split()
    return int(fields[1]), int(fields[11]) + int(fields[12])


def tree_cpu_s(root: int) -> float:
    """CPU seconds (user + system) of ``root`` and its descendants (Linux /proc; 0 elsewhere)."""
    if not Path("/proc").is_dir():
        return 0.0
    table = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            got = _proc_ticks(int(d))
            if got is not None:
                table[int(d)] = got
    keep = {root}
    grew = True
    while grew:
        grew = False
        for pid, (ppid, _t) in table.items():
            if ppid in keep and pid not in keep:
                keep.add(pid)
                grew = True
    ticks = sum(table[p][1] for p in keep if p in table)
    return ticks / os.sysconf("SC_CLK_TCK")


# --------------------------------------------------------------------------- one row


@dataclass
class RowSpec:
    """One row of the table."""

    world: str
    map_kind: str
    n: int
    rate: float
    k: int = 0

    @property
    def label(self) -> str:
        return f"{world_name(self.world)} {self.map_kind} N={self.n}@{self.rate:g}Hz K={self.k}"


@dataclass
class Context:
    """What every row needs: the session, the receiver, the service's pid and the options."""

    session: zenoh.Session
    endpoint: str
    rec: Receiver
    svc_pid: int
    method: str
    duration: float
    warmup: float
    odom: bool
    search_mode: str
    correct_m: float
    correct_deg: float
    pools: dict[tuple[str, str], Pool] = field(default_factory=dict)


def _wait_robots(session: zenoh.Session, want: int, timeout: float = 60.0) -> None:
    deadline = time.time() + timeout
    while True:
        h = health(session)
        if h is not None and h.robots == want:
            return
        if time.time() > deadline:
            got = None if h is None else h.robots
            raise RuntimeError(f"service reports {got} robots, expected {want} within {timeout}s")
        time.sleep(0.2)


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else math.nan


def run_row(ctx: Context, spec: RowSpec, row: int) -> dict[str, Any]:
    """Configure, prime, publish, measure one row; deletes its robots at the end."""
    pool = ctx.pools[(spec.world, spec.map_kind)]
    count = math.ceil(ctx.duration * spec.rate) + 1  # seq 0 primes
    plans = plan_robots(pool, row, spec.n, spec.k, count, ctx.odom, ctx.search_mode)
    s, rec = ctx.session, ctx.rec
    for p in plans:
        init = None if p.searching else [float(v) for v in p.truth[0]]
        cfg = RobotConfig(map_id=pool.map_id, method=ctx.method, initial_pose=init)
        s.put(f"{P}/robots/{p.robot_id}/config", encode(cfg), encoding=MSGPACK)
    _wait_robots(s, len(plans))
    # Prime: seq 0 of every robot, wait for all answers (cold caches are built now).
    rec.take()
    t_prime = time.time()
    for p in plans:
        src = pool.mirrored if p.mirrored else pool.ranges
        o = None if p.odom is None else p.odom[0]
        payload = scan_payload(pool.info, 0, src[int(p.walk[0])], o)
        s.put(f"{P}/robots/{p.robot_id}/scan", payload, encoding=MSGPACK)
    pending = {p.robot_id for p in plans}
    primed_rows: list = []
    while pending and time.time() - t_prime < 300:
        time.sleep(0.1)
        got, _f = rec.take()
        primed_rows += got
        pending -= {r[0] for r in got if r[1] == 0}
    if pending:
        raise RuntimeError(f"no answer to the priming scan of {sorted(pending)} in 300 s")
    prime_s = time.time() - t_prime
    with rec.lock:
        rec.method = ctx.method
        rec.refix = {p.robot_id: pool.map_id for p in plans if p.searching}
    for p in plans:  # a searcher fixed on its priming scan: search again from the start
        if p.searching and any(r[0] == p.robot_id and r[5] == "tracking" for r in primed_rows):
            rec._q.put(p.robot_id)
    rec.take()
    # Publish.
    mpctx = mp.get_context("spawn")
    out, ctl = mpctx.Queue(), mpctx.Queue()
    proc = mpctx.Process(
        target=publisher_main,
        args=(
            ctx.endpoint,
            [p.robot_id for p in plans],
            [p.walk for p in plans],
            [p.odom for p in plans],
            [p.mirrored for p in plans],
            pool.ranges,
            pool.mirrored,
            pool.info,
            spec.rate,
            count,
            ctl,
            out,
        ),
    )
    proc.start()
    if out.get(timeout=120) != "ready":
        raise RuntimeError("publisher did not start")
    t0 = time.time() + 0.2
    ctl.put(t0)
    lo, hi = t0 + ctx.warmup, t0 + ctx.duration
    time.sleep(max(0.0, lo - time.time()))
    cpu0 = (tree_cpu_s(ctx.svc_pid), tree_cpu_s(proc.pid) + _own_cpu_s(), time.time())
    time.sleep(max(0.0, hi - time.time()))
    cpu1 = (tree_cpu_s(ctx.svc_pid), tree_cpu_s(proc.pid) + _own_cpu_s(), time.time())
    load1 = os.getloadavg()[0]
    try:
        sent, lag_p99, lag_max = out.get(timeout=ctx.duration + 60)
    except queue.Empty:
        sent, lag_p99, lag_max = 0, math.nan, math.nan
    proc.join(timeout=30)
    if proc.is_alive():
        proc.kill()
        proc.join()
    time.sleep(1.0)  # drain
    with rec.lock:
        rec.refix = {}
    rows, fixes = rec.take()
    wall = cpu1[2] - cpu0[2]
    result = summarise_row(
        spec,
        plans,
        rows,
        fixes,
        t0=t0,
        lo=lo,
        hi=hi,
        correct_m=ctx.correct_m,
        correct_deg=ctx.correct_deg,
    )
    result.update(
        svc_cpu=100.0 * (cpu1[0] - cpu0[0]) / wall,
        gen_cpu=100.0 * (cpu1[1] - cpu0[1]) / wall,
        load=load1,
        prime_s=prime_s,
        sent_total=sent,
        pub_lag_p99=lag_p99,
        pub_lag_max=lag_max,
    )
    # Forget the row's robots (configs deleted, workers' load released).
    for p in plans:
        s.delete(f"{P}/robots/{p.robot_id}/config")
    _wait_robots(s, 0)
    rec.take()
    return result


def _own_cpu_s() -> float:
    t = os.times()
    return t.user + t.system


def summarise_row(
    spec: RowSpec,
    plans: list[RobotPlan],
    rows: list[tuple[str, int, float, float, list[float], str]],
    fixes: list[tuple[str, int, list[float]]],
    *,
    t0: float,
    lo: float,
    hi: float,
    correct_m: float,
    correct_deg: float,
) -> dict[str, Any]:
    """The row's figures from the received poses (see the module docstring). Seq ``k`` of the
    ``j``-th of ``J`` robots is scheduled at ``t0 + (k-1)/rate + j/(rate*J)``; the window holds
    the scans scheduled in ``[lo, hi)``."""
    total = len(plans)
    by_id = {p.robot_id: (j, p) for j, p in enumerate(plans)}
    window: dict[str, set[int]] = {}
    for j, p in enumerate(plans):
        k = np.arange(1, len(p.walk))
        ts = t0 + (k - 1) / spec.rate + j / (spec.rate * total)
        window[p.robot_id] = set(k[(ts >= lo) & (ts < hi)].tolist())
    got: dict[str, dict[int, tuple[float, list[float], str]]] = {p.robot_id: {} for p in plans}
    for rid, seq, stamp, t, pose, status in rows:
        if rid in window and seq in window[rid] and seq not in got[rid]:
            got[rid][seq] = ((t - stamp) * 1e3, pose, status)

    def group(searching: bool) -> dict[str, Any]:
        ids = [p.robot_id for p in plans if p.searching == searching]
        if not ids:
            return {}
        frac = np.array([len(got[r]) / max(len(window[r]), 1) for r in ids])
        lat = np.array([v[0] for r in ids for v in got[r].values()])
        est, tru, trk = [], [], []
        for r in ids:
            p = by_id[r][1]
            for seq, (_l, pose, status) in got[r].items():
                est.append(pose)
                tru.append(p.truth[seq])
                trk.append(status == "tracking")
        ok = (
            pose_correct(np.array(est), np.array(tru), correct_m, correct_deg)
            if est
            else np.zeros(0, dtype=bool)
        )
        trk_a = np.array(trk, dtype=bool)
        per_robot_p99 = [_pct(np.array([v[0] for v in got[r].values()]), 99) for r in ids if got[r]]
        return {
            "robots": len(ids),
            "answered_mean": float(frac.mean()),
            "answered_min": float(frac.min()),
            "starved": bool(np.any(frac == 0) or np.any(frac < 0.5 * frac.mean())),
            "p50": _pct(lat, 50),
            "p99": _pct(lat, 99),
            "max": float(np.max(lat)) if np.size(lat) else math.nan,
            "worst_robot_p99": max(per_robot_p99) if per_robot_p99 else math.nan,
            "poses": int(ok.size),
            "correct": float(ok.mean()) if ok.size else math.nan,
            "confident_wrong": int(np.sum(trk_a & ~ok)),
            "not_tracking": int(np.sum(~trk_a)),
        }

    out: dict[str, Any] = {
        "world": spec.world,
        "map": spec.map_kind,
        "n": spec.n,
        "rate": spec.rate,
        "k": spec.k,
        "tracked": group(False),
    }
    if spec.k:
        srch = group(True)
        # fixes: correct against the (possibly mirrored) truth of that scan
        fx = [(r, s, pz) for r, s, pz in fixes if r in by_id and by_id[r][1].searching]
        if fx:
            ok = pose_correct(
                np.array([pz for _r, _s, pz in fx]),
                np.array([by_id[r][1].truth[s] for r, s, _p in fx]),
                correct_m,
                correct_deg,
            )
            # one fix is reported by the few poses before the new config: count first ones
            first = _first_of_runs([(r, s) for r, s, _p in fx])
            srch["fixes"] = int(sum(first))
            srch["fixes_correct"] = int(np.sum(ok[np.array(first, dtype=bool)]))
        else:
            srch["fixes"] = srch["fixes_correct"] = 0
        srch["searching_share"] = (
            srch["not_tracking"] / srch["poses"] if srch["poses"] else math.nan
        )
        out["searchers"] = srch
    return out


def _first_of_runs(items: list[tuple[str, int]]) -> list[bool]:
    """For (robot, seq) pairs in arrival order: True for the first tracking pose of each run
    (a later one of the same robot more than 3 seqs on starts a new run)."""
    last: dict[str, int] = {}
    out = []
    for r, s in items:
        out.append(r not in last or s - last[r] > 3)
        last[r] = s
    return out


# --------------------------------------------------------------------------- tables


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


def _f(v: float, fmt: str = ".1f") -> str:
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
        _f(t["p50"]),
        _f(t["p99"]),
        "yes" if t["starved"] else "no",
        f"{_f(100 * t['correct'], '.2f')} %",
        f"{t['confident_wrong']} / {t['poses']}",
        str(t["not_tracking"]),
        f"{r['svc_cpu']:.0f}",
        f"{r['gen_cpu']:.0f}",
        _f(r["pub_lag_p99"]),
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
        _f(s["p50"]),
        _f(s["p99"]),
        f"{_f(100 * s['searching_share'])} %",
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
        f"{_f(p['p50_without'])} / {_f(p['p50_with'])}",
        f"{_f(p['p99_without'])} / {_f(p['p99_with'])}",
        f"{p['adds_p99']:+.1f} ms",
        f"{_f(p['worst_without'])} / {_f(p['worst_with'])}",
        f"{_f(p['max_without'])} / {_f(p['max_with'])}",
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
    """Issue 15's acceptance table."""
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
                f" %), p99 {_f(t['p99'])} ms, starved {'yes' if t['starved'] else 'no'}",
            )
        )
    for p in search_pairs(results):
        out.append(
            (
                f"searching: {p['label']} K={p['k']} vs K=0",
                p["ok"],
                f"tracked p99 {_f(p['p99_without'])} -> {_f(p['p99_with'])} ms "
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
        lines += ["", "Acceptance (issue 15):", ""]
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


# --------------------------------------------------------------------------- main


def _csv(s: str) -> list[str]:
    return [x.strip() for x in s.split(",") if x.strip()]


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="1,5,10,20,30", help="comma-separated N values")
    ap.add_argument("--method", default="shape", choices=["shape", "icp", "lines"])
    ap.add_argument(
        "--world", default="office", help="comma list: office and/or generated building seeds"
    )
    ap.add_argument("--map", default="metric", help="comma list: metric and/or schematic")
    ap.add_argument("--workers", type=int, default=None, help="service workers (default: cores)")
    ap.add_argument("--search-budget-ms", type=float, default=None, help="service's (default 50)")
    ap.add_argument("--rate", default="10", help="comma list of scans per second per robot")
    ap.add_argument("--searching", default="0", help="comma list of K searching robots")
    ap.add_argument(
        "--search-mode",
        default="refix",
        choices=["refix", "foreign"],
        help="searching robots: real scans, re-configured on every fix; or mirrored scans",
    )
    ap.add_argument(
        "--odom", action=argparse.BooleanOptionalAction, default=True, help="send odometry"
    )
    ap.add_argument("--duration", type=float, default=None, help="s per row (10; acceptance 20)")
    ap.add_argument("--warmup", type=float, default=2.0, help="seconds ignored at the start")
    ap.add_argument("--stride", type=int, default=5, help="tour samples (11 mm) between scans")
    ap.add_argument("--correct-m", type=float, default=0.5)
    ap.add_argument("--correct-deg", type=float, default=10.0)
    ap.add_argument("--acceptance", action="store_true", help="issue 15's acceptance table")
    ap.add_argument("--out", type=Path, default=None, help="write the markdown report here")
    ap.add_argument("--json", type=Path, default=None, help="write the raw rows here")
    ap.add_argument("--note", default="", help="a line quoted at the top of the --out report")
    return ap


def main(argv: list[str] | None = None) -> int:
    """Run the table; returns 0 (1 if the service failed; 2 if an acceptance line FAILs)."""
    args = build_parser().parse_args(argv)
    duration = args.duration or (20.0 if args.acceptance else 10.0)
    if duration <= args.warmup:
        raise SystemExit("--duration must exceed --warmup")
    if args.acceptance:
        specs = acceptance_rows()
    else:
        specs = [
            RowSpec(w, mk, int(n), float(rt), int(k))
            for w in _csv(args.world)
            for mk in _csv(args.map)
            for rt in _csv(args.rate)
            for k in _csv(args.searching)
            for n in _csv(args.robots)
        ]
    if any(s.k for s in specs) and args.method != "shape":
        raise SystemExit("searching robots need --method shape (global localisation)")
    pools: dict[tuple[str, str], Pool] = {}
    for s in specs:
        if (s.world, s.map_kind) not in pools:
            pools[(s.world, s.map_kind)] = make_pool(s.world, s.map_kind, args.stride)
    endpoint = free_endpoint()
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
    load_before = _load()
    results: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        log_path = Path(tmp) / "service.log"
        cmd = [
            sys.executable,
            "-m",
            "service",
            "--listen",
            endpoint,
            "--state-dir",
            str(Path(tmp) / "state"),
            "--workers",
            str(workers),
            "--log-level",
            "warning",
        ]
        if args.search_budget_ms is not None:
            cmd += ["--search-budget-ms", str(args.search_budget_ms)]
        with open(log_path, "wb") as logf:
            svc = subprocess.Popen(
                cmd, cwd=REPO, stdout=logf, stderr=subprocess.STDOUT, start_new_session=True
            )
        rec = None
        try:
            session = None
            deadline = time.time() + 60
            while True:
                if svc.poll() is not None:
                    print(log_path.read_text(), file=sys.stderr)
                    return 1
                try:
                    session = session or zenoh.open(client_config(endpoint))
                    if health(session) is not None:
                        break
                except zenoh.ZError:
                    pass
                if time.time() > deadline:
                    raise RuntimeError("service did not start")
                time.sleep(0.2)
            assert session is not None
            with session:
                for pool in pools.values():
                    session.put(f"{P}/maps/{pool.map_id}", encode(pool.map_msg), encoding=MSGPACK)
                deadline = time.time() + 60
                while (h := health(session)) is None or h.maps < len(pools):
                    if time.time() > deadline:
                        raise RuntimeError("maps not stored in 60 s")
                    time.sleep(0.2)
                rec = Receiver(session)
                ctx = Context(
                    session=session,
                    endpoint=endpoint,
                    rec=rec,
                    svc_pid=svc.pid,
                    method=args.method,
                    duration=duration,
                    warmup=args.warmup,
                    odom=args.odom,
                    search_mode=args.search_mode,
                    correct_m=args.correct_m,
                    correct_deg=args.correct_deg,
                    pools=pools,
                )
                print(
                    f"# service: method={args.method} workers={workers} "
                    f"odom={'on' if args.odom else 'off'} search-mode={args.search_mode} "
                    f"window={duration - args.warmup:g} s; load before: {load_before}",
                    flush=True,
                )
                for i, spec in enumerate(specs):
                    r = run_row(ctx, spec, i)
                    results.append(r)
                    t = r["tracked"]
                    line = (
                        f"{spec.label}: answered {100 * t['answered_mean']:.1f} % (worst "
                        f"{100 * t['answered_min']:.1f} %), p50 {_f(t['p50'])} p99 "
                        f"{_f(t['p99'])} ms, starved {'yes' if t['starved'] else 'no'}, "
                        f"correct {_f(100 * t['correct'], '.2f')} %, confident wrong "
                        f"{t['confident_wrong']}, svc CPU {r['svc_cpu']:.0f} %, load "
                        f"{r['load']:.2f} (prime {r['prime_s']:.1f} s, publisher lag p99 "
                        f"{_f(r['pub_lag_p99'])} ms)"
                    )
                    if spec.k:
                        s = r["searchers"]
                        line += (
                            f"\n    searchers: answered {100 * s['answered_mean']:.1f} %, p50 "
                            f"{_f(s['p50'])} p99 {_f(s['p99'])} ms, searching "
                            f"{_f(100 * s['searching_share'])} % of their poses, fixes "
                            f"{s['fixes']} ({s['fixes_correct']} correct)"
                        )
                    print(line, flush=True)
        finally:
            if rec is not None:
                rec.close()
            if svc.poll() is None:
                svc.send_signal(signal.SIGTERM)
                try:
                    svc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(svc.pid, signal.SIGKILL)
                    svc.wait()
    load_after = _load()
    worlds = []
    for s in specs:
        key = (s.world, s.map_kind)
        if any(w["key"] == key for w in worlds):
            continue
        pool = pools[key]
        worlds.append(
            {
                "key": key,
                "world": world_name(s.world),
                "map": s.map_kind,
                "map_id": pool.map_id,
                "scans": len(pool.ranges),
                "beams": pool.beams,
                **pool.motion,
            }
        )
    meta = {
        "command": "python bench/bench_service.py "
        + " ".join(shlex.quote(a) for a in argv_of(argv)),
        "commit": git_commit(),
        "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "machine": f"{os.cpu_count()} cores ({platform.machine()})",
        "method": args.method,
        "workers": workers,
        "budget": (
            f"{args.search_budget_ms:g} ms" if args.search_budget_ms is not None else "default"
        ),
        "odom": args.odom,
        "search_mode": args.search_mode,
        "window": duration - args.warmup,
        "warmup": args.warmup,
        "load_before": load_before,
        "load_after": load_after,
        "correct_m": args.correct_m,
        "correct_deg": args.correct_deg,
        "worlds": worlds,
        "note": args.note,
    }
    print()
    for w in worlds:
        print(
            f"# {w['world']} {w['map']}: {w['scans']} scans, {w['beams']} beams; step mean "
            f"{w['step_mean']:.3f} m p95 {w['step_p95']:.3f} m; turn mean "
            f"{w['turn_mean']:.1f} deg p95 {w['turn_p95']:.1f} deg"
        )
    print(text_table(ROW_HEAD, [row_cells(r) for r in results]))
    srch = [r for r in results if r["k"]]
    if srch:
        print()
        print(text_table(SEARCH_HEAD, [search_cells(r) for r in srch]))
        pairs = search_pairs(results)
        if pairs:
            print(text_table(PAIR_HEAD, [pair_cells(p) for p in pairs]))
    groups: dict[tuple, list[dict[str, Any]]] = {}
    for r in results:
        groups.setdefault((r["world"], r["map"], r["rate"], r["k"]), []).append(r)
    for (w, mk, rt, k), rs in groups.items():
        if len(rs) > 1:
            best = max([r["n"] for r in rs if row_ok(r)], default=0)
            print(
                f"# {world_name(w)} {mk} {rt:g} Hz K={k}: largest N with p99 <= 50 ms, "
                f">= 99 % answered, none starved: {best}"
            )
    failed = False
    if args.acceptance:
        print("\n# acceptance (issue 15)")
        for name, ok, figs in acceptance_lines(results):
            failed |= not ok
            print(f"{'PASS' if ok else 'FAIL'}  {name}: {figs}")
    print(f"# load after: {load_after}")
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(report(results, meta, args.acceptance))
        print(f"# wrote {args.out}")
    if args.json is not None:
        args.json.write_text(
            json.dumps({"meta": _jsonable(meta), "rows": _jsonable(results)}, indent=1)
        )
    return 2 if failed else 0


def argv_of(argv: list[str] | None) -> list[str]:
    return list(sys.argv[1:] if argv is None else argv)


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return None if math.isnan(f) else f
    if isinstance(v, np.integer):
        return int(v)
    return v


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


if __name__ == "__main__":
    sys.exit(main())
