"""One cold-start fleet run of ``bench/bench_fleet.py``: a fresh service, a fresh map, N robots
that start together.

:func:`run_fleet` starts ``python -m service`` on a free loopback port with an empty state
directory, puts the map as soon as the service answers, waits until the service reports the
map *ready* (``Health.maps_ready``; a service without that field: until it counts the map),
configures the N robots (each with its true start pose as ``initial_pose``), waits until the
service counts them, then starts a publisher process in which every robot sends its scans at
``rate`` Hz *in the same instant* (no staggering: the whole fleet's scans of one tick arrive
together, so queueing counts), each scan with its odometry. The poses are received here and
judged against the true poses (:func:`summarise_fleet`); the service's CPU comes from /proc
(the service process and its workers) and, per scan, from the service's own accounting
(``Health.scan_cpu_ms``). The service is stopped at the end of the run.

The worlds, walks and odometry are those of the scale benchmark (``scale_walks``): each robot
walks back and forth along the world's tour from its own start with drifting odometry in its
own frame; scans are simulated against the true world (setup 1's laser, 361 beams).
"""

from __future__ import annotations

import math
import multiprocessing as mp
import os
import queue
import signal
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from bench.harness import client_config, start_service, wait_ready
from bench.scale_load import MSGPACK, P, Receiver, health, scan_payload, tree_cpu_s
from bench.scale_walks import Pool, RobotPlan, plan_robots
from schemas.codec import encode
from schemas.messages import Health, RobotConfig

#: A pose farther than this (m) from the scan's true pose is "off".
OFF_M = 0.1
#: A pose is *wrong* beyond these (the scale benchmark's correctness, bench_service): a floor
#: plan's own scale error keeps a well-tracked robot 0.1-0.2 m from its true pose there.
WRONG_M, WRONG_DEG = 0.5, 10.0


@dataclass
class FleetSpec:
    """One run: N robots at ``rate`` Hz for ``duration`` s on (world, map)."""

    world: str
    map_kind: str
    n: int
    rate: float = 10.0
    duration: float = 20.0
    method: str = "shape"
    odom: bool = True
    workers: int | None = None


def fleet_publisher_main(
    endpoint: str,
    robots: list[str],
    walks: list[np.ndarray],
    odoms: list[np.ndarray | None],
    ranges: list[bytes],
    info: dict[str, float],
    rate: float,
    count: int,
    ctl: Any,
    out: Any,
) -> None:
    """Child process: once its publishers are declared it puts ``"ready"`` on ``out`` and gets
    ``t0`` from ``ctl``; every robot sends seq ``k`` (0 .. count-1) at ``t0 + k / rate``, all
    robots in the same instant. Puts ``(scans sent, send lag p99 ms, max lag ms)`` on ``out``."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    enc = zenoh.Encoding(MSGPACK)
    lags = []
    sent = 0
    with zenoh.open(client_config(endpoint)) as s:
        pubs = [s.declare_publisher(f"{P}/robots/{r}/scan", encoding=enc) for r in robots]
        out.put("ready")
        t0 = ctl.get()
        for k in range(count):
            t_send = t0 + k / rate
            dt_ = t_send - time.time()
            if dt_ > 0:
                time.sleep(dt_)
            lags.append(time.time() - t_send)
            for i, pub in enumerate(pubs):
                o = odoms[i]
                pub.put(
                    scan_payload(info, k, ranges[int(walks[i][k])], None if o is None else o[k])
                )
                sent += 1
    lag = np.asarray(lags) * 1e3
    out.put((sent, float(np.percentile(lag, 99)) if lag.size else 0.0, float(lag.max(initial=0))))


def map_ready(h: Health | None, map_id: str) -> bool:
    """The service reports ``map_id`` ready (or, without ``maps_ready``, at least stores a
    map)."""
    if h is None:
        return False
    ready = getattr(h, "maps_ready", None)
    if ready is None:
        return h.maps >= 1
    return map_id in ready


def _poll(session: zenoh.Session, pred: Any, timeout: float, what: str) -> Health:
    deadline = time.time() + timeout
    while True:
        h = health(session, timeout=2.0)
        if h is not None and pred(h):
            return h
        if time.time() > deadline:
            raise RuntimeError(f"{what} not within {timeout:g} s (health {h})")
        time.sleep(0.02)


def run_fleet(spec: FleetSpec, pool: Pool, rep: int) -> dict[str, Any]:
    """One cold-start run (see the module docstring); returns its figures."""
    count = math.ceil(spec.duration * spec.rate)
    plans = plan_robots(pool, rep, spec.n, 0, count, spec.odom, "refix")
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        t_start = time.time()
        svc = start_service(
            tmp / "state",
            "--log-level",
            "warning",
            workers=spec.workers,
            log_path=tmp / "service.log",
        )
        endpoint = svc.endpoint
        rec = None
        try:
            wait_ready(svc, timeout_s=120)
            with zenoh.open(client_config(endpoint)) as session:
                t_up = time.time()
                session.put(f"{P}/maps/{pool.map_id}", encode(pool.map_msg), encoding=MSGPACK)
                _poll(session, lambda h: map_ready(h, pool.map_id), 120, "map ready")
                t_ready = time.time()
                for p in plans:
                    cfg = RobotConfig(
                        map_id=pool.map_id,
                        method=spec.method,
                        initial_pose=[float(v) for v in p.truth[0]],
                    )
                    session.put(f"{P}/robots/{p.robot_id}/config", encode(cfg), encoding=MSGPACK)
                _poll(session, lambda h: h.robots == spec.n, 120, f"{spec.n} robots configured")
                t_conf = time.time()
                rec = Receiver(session)
                result = _publish(spec, pool, plans, endpoint, count, rec, svc.pid)
                h_end = health(session, timeout=3.0)
        finally:
            if rec is not None:
                rec.close()
            svc.stop(30)
    result.update(
        rep=rep,
        up_s=t_up - t_start,
        ready_s=t_ready - t_up,
        configured_s=t_conf - t_ready,
        load_before=load_before[0],
        load_after=os.getloadavg()[0],
        skipped=0 if h_end is None or not h_end.errors else h_end.errors.get("scan.Skipped", 0),
        scan_cpu_ms=None if h_end is None else getattr(h_end, "scan_cpu_ms", None),
    )
    return result


def _publish(
    spec: FleetSpec,
    pool: Pool,
    plans: list[RobotPlan],
    endpoint: str,
    count: int,
    rec: Receiver,
    svc_pid: int,
) -> dict[str, Any]:
    ctx = mp.get_context("spawn")
    out, ctl = ctx.Queue(), ctx.Queue()
    proc = ctx.Process(
        target=fleet_publisher_main,
        args=(
            endpoint,
            [p.robot_id for p in plans],
            [p.walk for p in plans],
            [p.odom for p in plans],
            pool.ranges,
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
    t0 = time.time() + 0.3
    cpu0 = tree_cpu_s(svc_pid)
    ctl.put(t0)
    try:
        sent, lag_p99, lag_max = out.get(timeout=spec.duration + 120)
    except queue.Empty:
        sent, lag_p99, lag_max = 0, math.nan, math.nan
    proc.join(timeout=30)
    if proc.is_alive():
        proc.kill()
        proc.join()
    time.sleep(1.0)  # the last poses
    cpu1 = tree_cpu_s(svc_pid)
    rows, _fixes = rec.take()
    res = summarise_fleet(plans, rows, count)
    res.update(
        sent=sent,
        pub_lag_p99=lag_p99,
        pub_lag_max=lag_max,
        svc_cpu_s=cpu1 - cpu0,
        cpu_ms_per_pose=1e3 * (cpu1 - cpu0) / max(res["poses"], 1),
        svc_cpu_pct=100.0 * (cpu1 - cpu0) / (spec.duration + 1.0),
    )
    return res


def summarise_fleet(
    plans: list[RobotPlan],
    rows: list[tuple[str, int, float, float, list[float], str]],
    count: int,
) -> dict[str, Any]:
    """The run's figures from the received poses ``(robot, seq, stamp, receipt, pose,
    status)``: answered (poses over scans sent, mean and worst robot), latency (receipt minus
    the scan's stamp, its send time) p50 / p99 / max, the first scan's latency (each robot's
    seq 0; ``inf`` if it was not answered), poses more than :data:`OFF_M` from the truth and the
    largest error, *wrong* poses (:data:`WRONG_M`, :data:`WRONG_DEG`) and poses whose status is
    not ``tracking``."""
    got: dict[str, dict[int, tuple[float, list[float], str]]] = {p.robot_id: {} for p in plans}
    t_first = min((r[2] for r in rows), default=0.0)
    by_second: dict[int, list[float]] = {}
    for rid, seq, stamp, t, pose, status in rows:
        if rid in got and 0 <= seq < count and seq not in got[rid]:
            got[rid][seq] = ((t - stamp) * 1e3, pose, status)
            by_second.setdefault(int(stamp - t_first), []).append((t - stamp) * 1e3)
    frac = np.array([len(got[p.robot_id]) / count for p in plans])
    lat = np.array([v[0] for g in got.values() for v in g.values()])
    first = np.array([got[p.robot_id].get(0, (math.inf,))[0] for p in plans])
    err, not_tracking, wrong = [], 0, 0
    for p in plans:
        for seq, (_l, pose, status) in got[p.robot_id].items():
            t = p.truth[seq]
            err.append(math.hypot(pose[0] - t[0], pose[1] - t[1]))
            dth = abs((pose[2] - t[2] + math.pi) % (2 * math.pi) - math.pi)
            wrong += err[-1] >= WRONG_M or math.degrees(dth) >= WRONG_DEG
            not_tracking += status != "tracking"
    e = np.asarray(err)
    return {
        "n": len(plans),
        "scans_per_robot": count,
        "poses": int(sum(len(g) for g in got.values())),
        "answered": float(frac.mean()),
        "answered_min": float(frac.min()),
        "p50": float(np.percentile(lat, 50)) if lat.size else math.nan,
        "p99": float(np.percentile(lat, 99)) if lat.size else math.nan,
        "max": float(lat.max()) if lat.size else math.nan,
        "first_max": float(first.max()),
        "first_p50": float(np.median(first)),
        "first_answered": int(np.sum(np.isfinite(first))),
        "off": int(np.sum(e > OFF_M)),
        "wrong": int(wrong),
        "err_max": float(e.max()) if e.size else math.nan,
        "not_tracking": int(not_tracking),
        # latency p99 of the scans sent in each second of the run (the cold start's transient)
        "p99_by_second": [
            round(float(np.percentile(by_second[k], 99)), 1) for k in sorted(by_second)
        ],
    }
