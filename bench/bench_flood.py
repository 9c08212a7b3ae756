"""Flood benchmark: one robot at 20 Hz while malformed messages arrive on every key.

Every run starts its own service (empty state directory), puts the map as soon as the service
answers, waits until the service reports it ready (``Health.maps_ready``), configures one robot
(``shape``, its true start pose, **no odometry**: the shape matching runs on every scan) and
then, from the same instant for ``--duration`` s, a publisher process sends the robot's scans
at ``--rate`` Hz while a garbage process sends ``--garbage-rate`` malformed messages per
second drawn from :func:`flood_messages`: on the robot's own scan key (undecodable msgpack,
wrong types, NaN, too many beams, oversize payloads, broken JSON, deletes), on its own
configuration key, on unknown robots' keys, on maps (invalid, mismatched ids), and on keys
that are not the service's shape at all (ids too long or with bad characters, extra levels,
unknown leaves). The robot's scans are those of ``bench.scale_walks`` (setup 1's laser
against the true world, walking back and forth along the tour, ``--stride`` tour samples
apart).

Figures per run: the robot's scans answered (of those sent), replaced unprocessed
(``scan.Skipped``), latency p50/p99 (receipt minus the scan's stamp), poses more than 0.1 m
off, garbage sent and rejected (per kind, from health), and where the CPU went: the service
process (intake, notices, scheduling), the robot's worker, and the service's own account of
the robot's scans (``Health.scan_cpu_ms``). Acceptance: >= 95 % of the
robot's scans answered in every run.

Usage: ``python -m bench.bench_flood [--runs 5] [--rate 20] [--garbage-rate 150]
[--duration 3] [--world office] [--out docs/results/flood.md]``.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as dt
import math
import multiprocessing as mp
import os
import shlex
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

from bench.bench_fleet import machine, md_table
from bench.fleet_run import OFF_M, map_ready
from bench.harness import client_config, start_service, wait_ready
from bench.scale_load import MSGPACK, P, Receiver, health, scan_payload
from bench.scale_report import git_commit
from bench.scale_walks import Pool, make_pool, plan_robots, world_name
from bench.soak import garbage_messages
from schemas.codec import encode
from schemas.messages import RobotConfig

ROBOT = "flooded"
#: The acceptance: share of the robot's scans answered in every run.
ACCEPT_ANSWERED = 0.95


def flood_messages(target: str, seed: int) -> list[tuple[str, str, bytes, bool, str]]:
    """The soak's garbage repertoire for ``target`` (its scan key, unknown robots, maps,
    configurations) plus garbage on its own configuration key and on keys the service does
    not define: ``(name, key, payload, delete, encoding)``."""
    out = garbage_messages([target], seed)
    rng = np.random.default_rng(seed)
    good = msgpack.packb(
        {
            "seq": 1,
            "stamp": 1.0,
            "angle_min": -np.pi / 2,
            "angle_increment": np.pi / 360,
            "range_min": 0.0,
            "range_max": 30.0,
            "ranges": np.asarray(rng.uniform(1, 8, 361), "<f4").tobytes(),
        }
    )
    mp_, js = "application/msgpack", "application/json"
    own_cfg = f"{P}/robots/{target}/config"
    out += [
        ("own-config-garbage", own_cfg, msgpack.packb({"map_id": 5}), False, mp_),
        ("own-config-json", own_cfg, b'{"map_id": ', False, js),
        ("id-too-long", f"{P}/robots/{'x' * 80}/scan", good, False, mp_),
        ("id-bad-chars", f"{P}/robots/r@b/scan", good, False, mp_),
        ("id-bad-chars-config", f"{P}/robots/r@b/config", good, False, mp_),
        ("extra-level", f"{P}/robots/{target}/scan/extra", good, False, mp_),
        ("unknown-leaf", f"{P}/robots/{target}/odom", good, False, mp_),
        ("map-extra-level", f"{P}/maps/a/b", good, False, mp_),
        ("map-bad-id", f"{P}/maps/m@p", msgpack.packb({"map_id": "m@p"}), False, mp_),
        ("prefix-only", f"{P}/robots", good, False, mp_),
    ]
    return out


def garbage_main(
    endpoint: str, target: str, rate: float, t0: float, duration: float, seed: int, counts: Any
) -> None:
    """Child process: ``rate`` messages per second drawn (seeded) from
    :func:`flood_messages` from ``t0`` for ``duration`` s; ``counts[0]`` = messages sent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    msgs = flood_messages(target, seed)
    rng = np.random.default_rng(seed)
    with zenoh.open(client_config(endpoint)) as s:
        k = 0
        while k / rate < duration:
            dt_ = t0 + k / rate - time.time()
            if dt_ > 0:
                time.sleep(dt_)
            _name, key, payload, delete, enc = msgs[int(rng.integers(len(msgs)))]
            if delete:
                s.delete(key)
            else:
                s.put(key, payload, encoding=zenoh.Encoding(enc))
            counts[0] += 1
            k += 1


def robot_main(
    endpoint: str,
    walk: np.ndarray,
    ranges: list[bytes],
    info: dict[str, float],
    rate: float,
    t0: float,
    counts: Any,
) -> None:
    """Child process: the robot's scans seq 0 .. len(walk)-1 at ``rate`` Hz from ``t0``, no
    odometry; ``counts[0]`` = scans sent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with zenoh.open(client_config(endpoint)) as s:
        pub = s.declare_publisher(f"{P}/robots/{ROBOT}/scan", encoding=zenoh.Encoding(MSGPACK))
        for k in range(len(walk)):
            dt_ = t0 + k / rate - time.time()
            if dt_ > 0:
                time.sleep(dt_)
            pub.put(scan_payload(info, k, ranges[int(walk[k])], None))
            counts[0] += 1


def _proc_cpu_s(pid: int) -> float:
    try:
        raw = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return 0.0
    f = raw[raw.rfind(")") + 2 :].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def _nice(pid: int) -> int:
    try:
        raw = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return 0
    return int(raw[raw.rfind(")") + 2 :].split()[16])


def _children(pid: int) -> list[int]:
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError, ValueError):
            out += [int(c) for c in (task / "children").read_text().split()]
    return out


def run_flood(args: argparse.Namespace, pool: Pool, rep: int) -> dict[str, Any]:
    """One run (see the module docstring)."""
    count = math.ceil(args.duration * args.rate)
    plan = plan_robots(pool, rep, 1, 0, count, False, "refix")[0]
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        svc = start_service(
            tmp / "state", "--log-level", "warning", workers=args.workers, log_path=tmp / "log"
        )
        rec = None
        try:
            wait_ready(svc, timeout_s=120)
            with zenoh.open(client_config(svc.endpoint)) as session:
                session.put(f"{P}/maps/{pool.map_id}", encode(pool.map_msg), encoding=MSGPACK)
                t_put = time.time()
                while not map_ready(health(session), pool.map_id):
                    if time.time() - t_put > 120:
                        raise RuntimeError("map not ready in 120 s")
                    time.sleep(0.02)
                ready_s = time.time() - t_put
                init = [float(v) for v in plan.truth[0]]
                cfg = RobotConfig(map_id=pool.map_id, method="shape", initial_pose=init)
                session.put(f"{P}/robots/{ROBOT}/config", encode(cfg), encoding=MSGPACK)
                while (h := health(session)) is None or h.robots != 1:
                    time.sleep(0.02)
                rec = Receiver(session)
                h0 = health(session)
                ctx = mp.get_context("spawn")
                sent, junk = ctx.Array("l", 1, lock=False), ctx.Array("l", 1, lock=False)
                t0 = time.time() + 2.0  # both children up and connected by then
                procs = [
                    ctx.Process(
                        target=robot_main,
                        args=(svc.endpoint, plan.walk, pool.ranges, pool.info, args.rate, t0, sent),
                    ),
                    ctx.Process(
                        target=garbage_main,
                        args=(
                            svc.endpoint,
                            ROBOT,
                            args.garbage_rate,
                            t0,
                            args.duration,
                            args.seed + rep,
                            junk,
                        ),
                    ),
                ]
                for p in procs:
                    p.start()
                time.sleep(max(0.0, t0 - time.time()))
                kids = _children(svc.pid)
                cpu0 = {pid: _proc_cpu_s(pid) for pid in [svc.pid, *kids]}
                nice = {pid: _nice(pid) for pid in kids}
                for p in procs:
                    p.join(timeout=args.duration + 60)
                time.sleep(1.0)
                cpu1 = {pid: _proc_cpu_s(pid) for pid in cpu0}
                h1 = health(session, timeout=3.0)
                rows, _ = rec.take()
        finally:
            if rec is not None:
                rec.close()
            svc.stop(30)
    got = {r[1]: r for r in rows if r[0] == ROBOT}
    lat = np.array([(r[3] - r[2]) * 1e3 for r in got.values()])
    err = np.array(
        [math.hypot(r[4][0] - plan.truth[s][0], r[4][1] - plan.truth[s][1]) for s, r in got.items()]
    )
    e0 = (h0.errors or {}) if h0 is not None else {}
    e1 = (h1.errors or {}) if h1 is not None else {}
    errors = {k: v - e0.get(k, 0) for k, v in e1.items() if v - e0.get(k, 0)}
    cpu = {pid: cpu1[pid] - cpu0[pid] for pid in cpu0}
    tracking = [pid for pid in cpu if pid != svc.pid and nice.get(pid, 0) == 0]
    return {
        "rep": rep,
        "world": pool.world,
        "sent": int(sent[0]),
        "answered": len(got),
        "share": len(got) / max(int(sent[0]), 1),
        "skipped": errors.get("scan.Skipped", 0),
        "p50": float(np.percentile(lat, 50)) if lat.size else math.nan,
        "p99": float(np.percentile(lat, 99)) if lat.size else math.nan,
        "off": int(np.sum(err > OFF_M)),
        "garbage": int(junk[0]),
        "rejected": sum(v for k, v in errors.items() if k != "scan.Skipped"),
        "errors": errors,
        "svc_cpu_s": cpu.get(svc.pid, 0.0),
        "worker_cpu_s": sum(cpu[p] for p in tracking),
        "search_cpu_s": sum(c for p, c in cpu.items() if p != svc.pid and p not in tracking),
        "scan_cpu_ms": None if h1 is None else h1.scan_cpu_ms,
        "ready_s": ready_s,
        "load": os.getloadavg()[0],
    }


HEAD = (
    "run", "answered", "skipped", "p50 ms", "p99 ms", "off > 0.1 m", "garbage sent / rejected",
    "service process CPU s", "tracking workers CPU s", "search worker CPU s",
    "CPU/scan p50 / p99 ms", "load", "ok",
)  # fmt: skip


def cells(r: dict[str, Any]) -> list[str]:
    c = r.get("scan_cpu_ms") or {}
    return [
        str(r["rep"]),
        f"{r['answered']} / {r['sent']} ({100 * r['share']:.1f} %)",
        str(r["skipped"]),
        f"{r['p50']:.1f}",
        f"{r['p99']:.1f}",
        str(r["off"]),
        f"{r['garbage']} / {r['rejected']}",
        f"{r['svc_cpu_s']:.2f}",
        f"{r['worker_cpu_s']:.2f}",
        f"{r['search_cpu_s']:.2f}",
        f"{c.get('p50', math.nan):.1f} / {c.get('p99', math.nan):.1f}",
        f"{r['load']:.2f}",
        "yes" if r["share"] >= ACCEPT_ANSWERED else "**no**",
    ]


def main(argv: list[str] | None = None) -> int:
    """Run the flood ``--runs`` times; 0, or 2 if a run misses the acceptance."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--rate", type=float, default=20.0, help="the robot's scans per second")
    ap.add_argument("--garbage-rate", type=float, default=150.0, help="malformed msg/s")
    ap.add_argument("--duration", type=float, default=3.0, help="seconds of scans per run")
    ap.add_argument("--world", default="office")
    ap.add_argument("--map", default="metric")
    ap.add_argument("--stride", type=int, default=3, help="tour samples (11 mm) between scans")
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--out", type=Path, default=None, help="write the markdown page here")
    args = ap.parse_args(argv)
    pool = make_pool(args.world, args.map, args.stride)
    load_before = " ".join(f"{v:.2f}" for v in os.getloadavg())
    runs = []
    for rep in range(args.runs):
        r = run_flood(args, pool, rep)
        runs.append(r)
        print(" | ".join(f"{h}: {c}" for h, c in zip(HEAD, cells(r), strict=True)), flush=True)
        print(f"    errors: {r['errors']}", flush=True)
    ok = sum(r["share"] >= ACCEPT_ANSWERED for r in runs)
    print(f"# {ok} of {len(runs)} runs with >= {100 * ACCEPT_ANSWERED:g} % answered")
    if args.out is not None:
        cmd = "python -m bench.bench_flood " + " ".join(
            shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv)
        )
        page = [
            "# Flood: one robot at 20 Hz beside malformed messages (bench/bench_flood.py)",
            "",
            f"Command: `{cmd}`  ",
            f"Commit: `{git_commit()}`, {dt.datetime.now(dt.UTC):%Y-%m-%d %H:%M UTC}; machine: "
            f"{machine()}; load average before {load_before}, after "
            + " ".join(f"{v:.2f}" for v in os.getloadavg())
            + ".  ",
            f"One robot on {world_name(args.world)} ({args.map} map), method `shape`, no "
            f"odometry, {args.rate:g} Hz for {args.duration:g} s; {args.garbage_rate:g} "
            "malformed messages per second on its own scan and configuration keys, unknown "
            "robots, maps and malformed keys; a fresh service and map every run. Runs with "
            f">= {100 * ACCEPT_ANSWERED:g} % of the robot's scans answered: **{ok} of "
            f"{len(runs)}**.",
            "",
            md_table(HEAD, [cells(r) for r in runs]),
            "",
        ]
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text("\n".join(page))
        print(f"# wrote {args.out}")
    return 0 if ok == len(runs) else 2


if __name__ == "__main__":
    sys.exit(main())
