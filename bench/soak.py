"""Soak test of the localizer service: many robots, a garbage publisher, bounded in time.

Starts ``python -m service`` on a free loopback port (its own temporary state directory), puts
the two office maps (``sim_publisher.office``: the exact metric map and the schematic floor
plan), configures ``--robots`` robots (alternately on the metric and the schematic map, method
``--method``, start pose given) and runs two child processes beside the service:

* a publisher sending every robot's scans at ``--rate`` Hz (robots staggered within the
  period; each walks back and forth along the first part of the office tour from its own
  starting point, ~11 mm per scan; ranges as float32 bytes, ``stamp`` = send time; with
  ``--odom`` each scan carries exact odometry, else none: the shape matching runs on every
  scan);
* a garbage publisher at ``--garbage-rate`` msg/s: malformed msgpack, wrong types, non-finite
  numbers, too many beams, oversize payloads, bad JSON, scan deletes -- most of them on the
  real robots' own scan keys -- plus scans of unknown robots and invalid maps/configs.

Every ``--interval`` seconds it prints one row: poses answered (share of scans sent), pose
latency p50/p99 (receipt minus send time, so both Zenoh hops, intake, queueing and the
method), robots served in that interval, RSS of the service process and of its workers,
the rejections counted in health during the interval by kind, and tracking statuses. It ends
with a summary: RSS growth after the first two minutes (the service must stay flat, <= 5 %),
crashes (service exit or worker restarts: must be 0) and starved robots (a robot with no pose
in some interval after the first: must be none). ``--json FILE`` writes all of it, ``--out
FILE`` the results page (:mod:`bench.soak_report`; docs/results/soak.md). The robots start
once the service reports both maps ready (``Health.maps_ready``).

The run is bounded: it stops by itself after ``--minutes`` (plus start-up and a few seconds
of drain) and sends only to 127.0.0.1. Reads nothing outside the repository.

Usage: ``python -m bench.soak [--minutes 10] [--robots 50] [--rate 10] [--garbage-rate 100]
[--method shape] [--odom] [--workers N] [--interval 60] [--json out.json] [--out page.md]``;
``python -m bench.soak
--garbage-only --connect tcp/127.0.0.1:PORT --garbage-rate R --duration S --targets id,...``
runs only the garbage publisher (used by the flood test).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

# the loopback helpers of the service benchmark
from bench.fleet_run import map_ready
from bench.harness import client_config, free_endpoint, start_service, wait_ready
from bench.scale_load import health as scale_health
from bench.scale_walks import odometry_frame
from bench.soak_report import page
from schemas.codec import encode
from schemas.messages import Health, RobotConfig

P = "shapeloc"
MAPS = ("office", "office-schematic")


def health(session: zenoh.Session) -> Health | None:
    """The service's Health, or None (3 s: the soak's service is busy)."""
    return scale_health(session, timeout=3.0)


# --------------------------------------------------------------------------- scans


def scan_pool(n: int, stride: int = 1) -> tuple[np.ndarray, list[bytes], dict[str, float]]:
    """``n`` setup-1 scans of the true office world ``stride`` samples (11 mm) apart: true
    poses ``(n, 3)``, ranges as little-endian float32 bytes (NaN: no return), laser info."""
    from sim_publisher.scenario import make_setup

    setup = make_setup(1, seed=11, max_scans=stride * n)
    idx = np.arange(0, stride * n, stride)
    ranges = [np.asarray(setup.scan(int(i))[0], dtype="<f4").tobytes() for i in idx]
    lz = setup.laser
    info = {
        "angle_min": float(lz.angle_min),
        "angle_increment": float(lz.angle_increment),
        "range_max": float(lz.config.max_range),
    }
    return setup.truth[idx], ranges, info


def robot_ids(n: int) -> list[str]:
    """``soak-000`` ... (even: metric map, odd: schematic map)."""
    return [f"soak-{i:03d}" for i in range(n)]


def starts_of(n: int, m: int) -> list[int]:
    """Starting pool index of each robot (spread over the pool)."""
    return [(i * 37) % m for i in range(n)]


def publisher_main(
    endpoint: str,
    robots: list[str],
    starts: list[int],
    ranges: list[bytes],
    info: dict[str, float],
    rate: float,
    duration: float,
    t0: float,
    counts: Any,
    truth: np.ndarray | None = None,
) -> None:
    """Child process: each robot's scans at ``rate`` Hz from ``t0`` for ``duration`` s;
    ``counts[i]`` = scans sent by robot ``i``. With ``truth`` (the pool's true poses) every
    scan carries exact odometry (the true pose in the robot's own odometry frame)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    n, m = len(robots), len(ranges)
    enc = zenoh.Encoding("application/msgpack")
    with zenoh.open(client_config(endpoint)) as s:
        pubs = [s.declare_publisher(f"{P}/robots/{r}/scan", encoding=enc) for r in robots]
        pos = list(starts)
        direction = [1] * n
        k = 0
        while True:
            tick = t0 + k / rate
            if tick - t0 >= duration:
                break
            for i in range(n):
                dt = tick + i / (rate * n) - time.time()
                if dt > 0:
                    time.sleep(dt)
                msg = {
                    "seq": k,
                    "stamp": time.time(),
                    "angle_min": info["angle_min"],
                    "angle_increment": info["angle_increment"],
                    "range_min": 0.0,
                    "range_max": info["range_max"],
                    "ranges": ranges[pos[i]],
                }
                if truth is not None:
                    pair = odometry_frame(truth[[starts[i], pos[i]]])
                    msg["odom"] = [float(v) for v in pair[1]]
                pubs[i].put(msgpack.packb(msg))
                counts[i] += 1
                nxt = pos[i] + direction[i]
                if not 0 <= nxt < m:
                    direction[i] = -direction[i]
                    nxt = pos[i] + direction[i]
                pos[i] = nxt
            k += 1


def garbage_messages(targets: list[str], seed: int) -> list[tuple[str, str, bytes, bool, str]]:
    """The garbage repertoire: ``(name, key, payload, delete, encoding)``; most target the
    real robots' own scan keys (``targets``), the rest unknown robots, maps and configs."""
    rng = np.random.default_rng(seed)
    good = {
        "seq": 1,
        "stamp": 1.0,
        "angle_min": -np.pi / 2,
        "angle_increment": np.pi / 360,
        "range_min": 0.0,
        "range_max": 30.0,
        "ranges": np.asarray(rng.uniform(1, 8, 361), "<f4").tobytes(),
    }
    mp_, js = "application/msgpack", "application/json"
    out: list[tuple[str, str, bytes, bool, str]] = []
    for t in targets:
        k = f"{P}/robots/{t}/scan"
        out += [
            ("not-msgpack", k, b"\xc1\xc1\xc1 garbage", False, mp_),
            ("not-a-map", k, msgpack.packb([1, 2, 3]), False, mp_),
            ("seq-string", k, msgpack.packb({**good, "seq": "seven"}), False, mp_),
            ("stamp-nan", k, msgpack.packb({**good, "stamp": float("nan")}), False, mp_),
            ("odom-nan", k, msgpack.packb({**good, "odom": [0.0, float("nan"), 0.0]}), False, mp_),
            ("too-many-beams", k, msgpack.packb({**good, "ranges": [1.0] * 9000}), False, mp_),
            ("oversize", k, b"\x00" * (600 * 1024), False, mp_),
            ("json-seq-negative", k, b'{"seq": -1}', False, js),
            ("json-broken", k, b'{"seq": 1, "stamp": ', False, js),
            ("scan-delete", k, b"", True, mp_),
        ]
    out += [
        ("unknown-robot", f"{P}/robots/ghost-{i}/scan", msgpack.packb(good), False, mp_)
        for i in range(3)
    ]
    out += [
        ("map-garbage", f"{P}/maps/office", b"{not json", False, js),
        ("map-garbage", f"{P}/maps/{MAPS[1]}", msgpack.packb({"map_id": MAPS[1]}), False, mp_),
        ("map-id-mismatch", f"{P}/maps/x", msgpack.packb({"map_id": "y"}), False, mp_),
        ("config-garbage", f"{P}/robots/ghost-0/config", msgpack.packb({"map_id": 5}), False, mp_),
        (
            "config-unknown-map",
            f"{P}/robots/ghost-1/config",
            encode(RobotConfig(map_id="nowhere")),
            False,
            mp_,
        ),
    ]
    return out


def garbage_main(
    endpoint: str, targets: list[str], rate: float, duration: float, seed: int, counts: Any
) -> None:
    """Child process: ``rate`` garbage messages per second for ``duration`` s, drawn with a
    seeded generator from :func:`garbage_messages`; ``counts[0]`` = messages sent."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    msgs = garbage_messages(targets, seed)
    rng = np.random.default_rng(seed)
    with zenoh.open(client_config(endpoint)) as s:
        t0 = time.time()
        k = 0
        while True:
            tick = t0 + k / rate
            if tick - t0 >= duration:
                break
            dt = tick - time.time()
            if dt > 0:
                time.sleep(dt)
            _name, key, payload, delete, enc = msgs[int(rng.integers(len(msgs)))]
            if delete:
                s.delete(key)
            else:
                s.put(key, payload, encoding=zenoh.Encoding(enc))
            counts[0] += 1
            k += 1


# --------------------------------------------------------------------------- monitoring


def rss_kib(pid: int) -> int:
    """Resident set size of a process in KiB (0 if gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


def workers_of(pid: int) -> list[int]:
    """The service's worker processes: its children except multiprocessing's resource
    tracker."""
    out: list[int] = []
    for task in Path(f"/proc/{pid}/task").glob("*"):
        with contextlib.suppress(OSError, ValueError):
            for c in (task / "children").read_text().split():
                cmd = Path(f"/proc/{c}/cmdline").read_bytes()
                if b"resource_tracker" not in cmd:
                    out.append(int(c))
    return out


class PoseLog:
    """(robot, seq, send stamp, receipt time) of every pose, plus statuses."""

    def __init__(self, session: zenoh.Session) -> None:
        self.lock = threading.Lock()
        self.rows: list[tuple[str, int, float, float]] = []
        self.status: dict[str, str] = {}
        self.sub = session.declare_subscriber(f"{P}/robots/*/pose", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        t = time.time()
        m = msgpack.unpackb(sample.payload.to_bytes())
        with self.lock:
            self.rows.append((m["robot_id"], m["seq"], m["stamp"], t))
            self.status[m["robot_id"]] = m["status"]

    def take(self) -> tuple[list[tuple[str, int, float, float]], dict[str, str]]:
        with self.lock:
            rows, self.rows = self.rows, []
            return rows, dict(self.status)


def _pct(a: np.ndarray, q: float) -> float:
    return float(np.percentile(a, q)) if a.size else float("nan")


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The whole soak; returns the report (also printed)."""
    from service.adapters.convert import map_message_of
    from sim_publisher.office import office_metric_map, office_schematic_map

    truth, ranges, info = scan_pool(args.pool)
    robots = robot_ids(args.robots)
    starts = starts_of(args.robots, len(ranges))
    endpoint = free_endpoint()
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
    report: dict[str, Any] = {
        "command": " ".join(sys.argv),
        "robots": args.robots,
        "rate_hz": args.rate,
        "garbage_rate": args.garbage_rate,
        "odom": args.odom,
        "method": args.method,
        "workers": workers,
        "minutes": args.minutes,
        "interval_s": args.interval,
        "cores": os.cpu_count(),
        "load_before": os.getloadavg(),
        "rows": [],
    }
    with tempfile.TemporaryDirectory() as tmp:
        service = start_service(
            Path(tmp) / "state",
            endpoint=endpoint,
            workers=workers,
            log_path=Path(tmp) / "service.log",
        )
        svc = service.proc
        ctx = mp.get_context("spawn")
        procs: list[Any] = []
        try:
            wait_ready(service, 90.0)
            session = zenoh.open(client_config(endpoint))
            with session:
                for md in (office_metric_map(MAPS[0]), office_schematic_map(MAPS[1])):
                    session.put(f"{P}/maps/{md.map_id}", encode(map_message_of(md)))
                deadline = time.time() + 120  # the maps' acknowledgement (Health.maps_ready)
                while not all(map_ready(health(session), m) for m in MAPS):
                    if time.time() > deadline:
                        raise RuntimeError("maps not ready in 120 s")
                    time.sleep(0.1)
                for i, (r, st) in enumerate(zip(robots, starts, strict=True)):
                    cfg = RobotConfig(
                        map_id=MAPS[i % 2], method=args.method, initial_pose=list(truth[st])
                    )
                    session.put(f"{P}/robots/{r}/config", encode(cfg))
                _wait_configured(session, len(robots))
                poses = PoseLog(session)
                duration = args.minutes * 60.0
                t0 = time.time() + 1.0
                sent = ctx.Array("l", len(robots), lock=False)
                junk = ctx.Array("l", 1, lock=False)
                pub_args = (
                    endpoint, robots, starts, ranges, info, args.rate, duration, t0, sent,
                    truth if args.odom else None,
                )  # fmt: skip
                procs = [
                    ctx.Process(target=publisher_main, args=pub_args),
                    ctx.Process(
                        target=garbage_main,
                        args=(endpoint, robots, args.garbage_rate, duration, args.seed, junk),
                    ),
                ]  # fmt: skip
                for pr in procs:
                    pr.start()
                _print_header(report, endpoint)
                h_prev = health(session)
                sent_prev = [0] * len(robots)
                t_next = t0 + args.interval
                crashed = None
                while t_next <= t0 + duration + 1e-6:
                    time.sleep(max(0.0, t_next - time.time()))
                    row, h_prev, sent_prev = _interval(
                        session, svc, poses, robots, sent, sent_prev, h_prev, junk, t_next - t0
                    )
                    report["rows"].append(row)
                    _print_row(row)
                    if svc.poll() is not None:
                        crashed = f"service exited with {svc.returncode}"
                        break
                    t_next += args.interval
                for pr in procs:
                    pr.join(timeout=30)
                time.sleep(2.0)  # drain
                final = health(session)
                report["final_health"] = None if final is None else final.to_wire()
                report["service_exit"] = crashed
        finally:
            for pr in procs:
                if pr.is_alive():
                    pr.kill()
            alive = svc.poll() is None
            if alive:
                svc.send_signal(signal.SIGTERM)
                try:
                    report["service_exit_code"] = svc.wait(timeout=60)
                except subprocess.TimeoutExpired:
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(svc.pid, signal.SIGKILL)
                    svc.wait()
                    report["service_exit_code"] = "killed after 60 s"
            report["service_log_tail"] = service.log()[-4000:]
    report["load_after"] = os.getloadavg()
    _summarise(report)
    return report


def _wait_configured(session: zenoh.Session, n: int) -> None:
    deadline = time.time() + 120
    while True:
        h = health(session)
        if h is not None and h.robots >= n and h.maps == 2:
            return
        if time.time() > deadline:
            raise RuntimeError(f"robots not configured in 120 s: {h}")
        time.sleep(0.2)


def _interval(
    session: zenoh.Session,
    svc: subprocess.Popen[bytes],
    poses: PoseLog,
    robots: list[str],
    sent: Any,
    sent_prev: list[int],
    h_prev: Health | None,
    junk: Any,
    t_rel: float,
) -> tuple[dict[str, Any], Health | None, list[int]]:
    rows, status = poses.take()
    sent_now = list(sent)
    n_sent = sum(sent_now) - sum(sent_prev)
    lat = np.array([(t - st) * 1e3 for _r, _s, st, t in rows])
    per_robot = Counter(r for r, _s, _st, _t in rows)
    h = health(session)
    errors: dict[str, int] = {}
    if h is not None and h.errors is not None:
        before = (h_prev.errors or {}) if h_prev is not None else {}
        errors = {k: v - before.get(k, 0) for k, v in sorted(h.errors.items())}
        errors = {k: v for k, v in errors.items() if v}
    kids = workers_of(svc.pid)
    row = {
        "t_s": round(t_rel, 1),
        "sent": n_sent,
        "answered": len(rows),
        "answered_share": len(rows) / n_sent if n_sent else float("nan"),
        "p50_ms": _pct(lat, 50),
        "p99_ms": _pct(lat, 99),
        "robots_served": sum(1 for r in robots if per_robot[r] > 0),
        "min_per_robot": min(per_robot[r] for r in robots),
        "rss_service_kib": rss_kib(svc.pid),
        "rss_workers_kib": sum(rss_kib(k) for k in kids),
        "workers": len(kids),
        "errors": errors,
        "garbage_sent_total": int(junk[0]),
        "statuses": dict(Counter(status.get(r, "none") for r in robots)),
        "service_alive": svc.poll() is None,
    }
    return row, h or h_prev, sent_now


def _print_header(report: dict[str, Any], endpoint: str) -> None:
    print(
        f"# soak: {report['robots']} robots x {report['rate_hz']:g} Hz, method "
        f"{report['method']}, {report['workers']} workers, garbage {report['garbage_rate']:g} "
        f"msg/s, {report['minutes']:g} min on {endpoint}; {report['cores']} cores, load before "
        + " ".join(f"{v:.2f}" for v in report["load_before"]),
        flush=True,
    )
    print(
        f"{'t s':>6} {'sent':>6} {'poses':>6} {'share':>6} {'p50 ms':>7} {'p99 ms':>7} "
        f"{'served':>6} {'min/rb':>6} {'svc MiB':>8} {'wrk MiB':>8}  errors (this interval)",
        flush=True,
    )


def _print_row(r: dict[str, Any]) -> None:
    errs = ", ".join(f"{k} {v}" for k, v in r["errors"].items())
    print(
        f"{r['t_s']:>6.0f} {r['sent']:>6} {r['answered']:>6} {r['answered_share']:>6.1%} "
        f"{r['p50_ms']:>7.0f} {r['p99_ms']:>7.0f} {r['robots_served']:>6} "
        f"{r['min_per_robot']:>6} {r['rss_service_kib'] / 1024:>8.1f} "
        f"{r['rss_workers_kib'] / 1024:>8.1f}  {errs}",
        flush=True,
    )


def _summarise(report: dict[str, Any]) -> None:
    rows = report["rows"]
    settle = 120.0 if report["minutes"] * 60 >= 240 else rows[0]["t_s"] if rows else 0.0
    late = [r for r in rows if r["t_s"] >= settle]
    growth: dict[str, float | None] = {}
    for key in ("rss_service_kib", "rss_workers_kib"):
        if late and late[0][key]:
            growth[key] = max(r[key] for r in late) / late[0][key] - 1.0
        else:
            growth[key] = None
    fh = report.get("final_health") or {}
    restarts = int((fh.get("errors") or {}).get("worker.Restarted", 0))
    starved = sorted({i for i, r in enumerate(rows[1:], 1) if r["min_per_robot"] == 0})
    errors_total: Counter[str] = Counter()
    for r in rows:
        errors_total.update(r["errors"])
    report["summary"] = {
        "rss_growth_after_s": settle,
        "rss_growth": growth,
        "crashes": (1 if report.get("service_exit") else 0) + restarts,
        "worker_restarts": restarts,
        "intervals_with_a_starved_robot": starved,
        "poses_total": sum(r["answered"] for r in rows),
        "sent_total": sum(r["sent"] for r in rows),
        "errors_total": dict(sorted(errors_total.items())),
    }
    s = report["summary"]
    share = s["poses_total"] / s["sent_total"] if s["sent_total"] else float("nan")
    print(
        f"# poses {s['poses_total']} of {s['sent_total']} scans ({share:.1%}); RSS growth after "
        f"{settle:.0f} s: service "
        + ", workers ".join(
            "n/a" if g is None else f"{g:+.1%}"
            for g in (growth["rss_service_kib"], growth["rss_workers_kib"])
        )
        + f"; crashes {s['crashes']}; intervals with a starved robot: {starved or 'none'}",
        flush=True,
    )
    print(f"# errors by kind: {s['errors_total']}", flush=True)
    print("# load after: " + " ".join(f"{v:.2f}" for v in report["load_after"]), flush=True)


def main(argv: list[str] | None = None) -> int:
    """Run the soak (or only the garbage publisher); returns 0, or 1 on a crash."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=10.0, help="length of the run")
    ap.add_argument("--robots", type=int, default=50)
    ap.add_argument("--rate", type=float, default=10.0, help="scans per second per robot")
    ap.add_argument("--garbage-rate", type=float, default=100.0, help="garbage msg/s")
    ap.add_argument("--method", default="shape", choices=["shape", "icp", "lines"])
    ap.add_argument("--workers", type=int, default=None, help="service workers (default: cores)")
    ap.add_argument("--interval", type=float, default=60.0, help="seconds per report row")
    ap.add_argument("--pool", type=int, default=400, help="scans in the tour pool")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", type=Path, help="write the report here")
    ap.add_argument("--out", type=Path, help="write the markdown results page here")
    ap.add_argument(
        "--odom", action=argparse.BooleanOptionalAction, default=False, help="send odometry"
    )
    ap.add_argument("--garbage-only", action="store_true", help="only the garbage publisher")
    ap.add_argument("--connect", help="--garbage-only: the service's endpoint")
    ap.add_argument("--duration", type=float, default=10.0, help="--garbage-only: seconds")
    ap.add_argument("--targets", default="", help="--garbage-only: robot ids to hit, a,b,...")
    args = ap.parse_args(argv)
    if args.garbage_only:
        if not args.connect:
            ap.error("--garbage-only needs --connect")
        counts = [0]
        targets = [t for t in args.targets.split(",") if t]
        garbage_main(args.connect, targets, args.garbage_rate, args.duration, args.seed, counts)
        print(json.dumps({"garbage_sent": counts[0]}), flush=True)
        return 0
    if args.minutes <= 0 or args.robots < 1 or args.rate <= 0 or args.interval <= 0:
        ap.error("--minutes, --robots, --rate and --interval must be positive")
    report = run(args)
    if args.json:
        args.json.write_text(json.dumps(report, indent=1, default=float))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        cmd = "python -m bench.soak " + " ".join(sys.argv[1:] if argv is None else argv)
        args.out.write_text(page(report, cmd))
    return 1 if report["summary"]["crashes"] else 0


if __name__ == "__main__":
    sys.exit(main())
