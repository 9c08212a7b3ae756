"""One row of the service scale benchmark (``bench/bench_service.py``).

:class:`RowSpec` is a row (world, map, N tracked robots at a rate, K searching ones) and
:class:`Context` what every row shares (the session, the receiver, the options). :func:`run_row`
configures the row's robots, primes each with one scan, runs the publisher process over the
window, measures the service's and the generator's CPU and deletes the robots again;
:func:`summarise_row` turns the received poses into the row's figures (answered, latency,
starved, correct, confident wrong, lost; the searching robots' share and fixes).

Run from the repository root as part of the ``bench`` package
(``python -m bench.bench_service``).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import queue
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from bench.scale_load import MSGPACK, P, Receiver, health, publisher_main, scan_payload, tree_cpu_s
from bench.scale_walks import Pool, RobotPlan, plan_robots, pose_correct, world_name
from schemas.codec import encode
from schemas.messages import RobotConfig


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
