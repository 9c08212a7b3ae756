"""Scale benchmark of the localizer service: N simulated robots at 10 Hz against one service.

Starts ``python -m service`` on a free loopback port, puts the exact office map, and for each N
configures N robots and runs a separate publisher process that sends each robot's scans at
``--rate`` Hz (robots staggered within the period, walking back and forth along the office
tour from different starting points). The bench process receives the poses. Latency is
pose receipt minus scan send (the scan's ``stamp`` carries the send time, ``time.time()``),
so it includes both Zenoh hops, decoding, queueing and the localisation itself.

Per N it prints latency p50/p99 (ms) over the poses of the measuring window, poses/s per
robot (mean and minimum), the answered fraction (poses / scans sent; below 1 means the
service skipped older scans: latest wins) and whether a robot starved (no pose at all, or
answered fraction below half the mean). It ends with the largest N meeting p99 <= 50 ms with
no robot starved and every robot answered at >= 90 %.

Usage: ``python bench/bench_service.py [--robots 1,5,10,20,30] [--method shape]
[--workers 2] [--duration 10]``. Numbers depend on the machine load; the load average is
printed with the table.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing as mp
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
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


def scan_pool(stride: int, n: int) -> tuple[np.ndarray, list[list[float]], dict[str, float]]:
    """``n`` setup-1 scans ``stride`` samples apart: (true poses, ranges lists, laser info)."""
    from sim_publisher.scenario import make_setup

    setup = make_setup(1, seed=7, max_scans=stride * n)
    idx = np.arange(0, stride * n, stride)
    ranges = []
    for i in idx:
        r, _a = setup.scan(int(i))
        ranges.append([float(v) for v in r])
    lz = setup.laser
    info = {
        "angle_min": float(lz.angle_min),
        "angle_increment": float(lz.angle_increment),
        "range_max": float(lz.config.max_range),
    }
    return setup.truth[idx], ranges, info


def publisher_main(
    endpoint: str,
    robots: list[str],
    starts: list[int],
    ranges: list[list[float]],
    info: dict[str, float],
    rate: float,
    duration: float,
    t0: float,
) -> None:
    """Child process: send each robot's scans at ``rate`` Hz from ``t0`` for ``duration`` s."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    n = len(robots)
    m = len(ranges)
    with zenoh.open(client_config(endpoint)) as s:
        pubs = [s.declare_publisher(f"{P}/robots/{r}/scan") for r in robots]
        pos = list(starts)
        direction = [1] * n
        k = 0
        while True:
            tick = t0 + k / rate
            if tick - t0 >= duration:
                break
            for i in range(n):
                t_send = tick + i / (rate * n)
                dt = t_send - time.time()
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
                pubs[i].put(msgpack.packb(msg))
                nxt = pos[i] + direction[i]
                if not 0 <= nxt < m:
                    direction[i] = -direction[i]
                    nxt = pos[i] + direction[i]
                pos[i] = nxt
            k += 1


class Receiver:
    """Collects (robot, seq, stamp, receipt time) of every pose."""

    def __init__(self, session: zenoh.Session) -> None:
        self.lock = threading.Lock()
        self.rows: list[tuple[str, int, float, float]] = []
        self.sub = session.declare_subscriber(f"{P}/robots/*/pose", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        t = time.time()
        m = msgpack.unpackb(sample.payload.to_bytes())
        with self.lock:
            self.rows.append((m["robot_id"], m["seq"], m["stamp"], t))

    def take(self) -> list[tuple[str, int, float, float]]:
        with self.lock:
            rows, self.rows = self.rows, []
        return rows


def run_n(
    session: zenoh.Session,
    endpoint: str,
    rec: Receiver,
    n: int,
    method: str,
    truth: np.ndarray,
    ranges: list[list[float]],
    info: dict[str, float],
    rate: float,
    duration: float,
    warmup: float,
    total_robots: int,
) -> dict[str, Any]:
    """One row of the table (``total_robots``: configured robots including earlier rows,
    which stay configured but idle)."""
    robots = [f"b{n}-{i}" for i in range(n)]
    m = len(ranges)
    starts = [(i * 37) % m for i in range(n)]
    for r, st in zip(robots, starts, strict=True):
        cfg = RobotConfig(map_id="office", method=method, initial_pose=list(truth[st]))
        session.put(f"{P}/robots/{r}/config", encode(cfg))
    deadline = time.time() + 60
    while True:
        h = health(session)
        if h is not None and h.robots >= total_robots:
            break
        if time.time() > deadline:
            raise RuntimeError("robots not configured in 60 s")
        time.sleep(0.2)
    rec.take()
    t0 = time.time() + 0.5
    ctx = mp.get_context("spawn")
    proc = ctx.Process(
        target=publisher_main,
        args=(endpoint, robots, starts, ranges, info, rate, duration, t0),
    )
    proc.start()
    proc.join(timeout=duration + 60)
    if proc.is_alive():
        proc.kill()
    time.sleep(1.0)  # drain
    rows = rec.take()
    lo, hi = t0 + warmup, t0 + duration
    sent_per_robot = (duration - warmup) * rate
    lat = np.array([(t - st) * 1e3 for r, _s, st, t in rows if lo <= st < hi and r in robots])
    per_robot = {r: 0 for r in robots}
    for r, _s, st, _t in rows:
        if r in per_robot and lo <= st < hi:
            per_robot[r] += 1
    counts = np.array(list(per_robot.values()), dtype=float)
    frac = counts / sent_per_robot
    starved = bool(np.any(counts == 0) or np.any(frac < 0.5 * frac.mean()))
    return {
        "n": n,
        "p50": float(np.percentile(lat, 50)) if lat.size else float("nan"),
        "p99": float(np.percentile(lat, 99)) if lat.size else float("nan"),
        "rate_mean": float(counts.mean() / (duration - warmup)),
        "rate_min": float(counts.min() / (duration - warmup)),
        "answered_min": float(frac.min()),
        "answered_mean": float(frac.mean()),
        "starved": starved,
    }


def main(argv: list[str] | None = None) -> int:
    """Run the table; returns 0."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", default="1,5,10,20,30", help="comma-separated N values")
    ap.add_argument("--method", default="shape", choices=["shape", "icp", "lines"])
    ap.add_argument("--workers", type=int, default=None, help="service workers (default: cores)")
    ap.add_argument("--rate", type=float, default=10.0, help="scans per second per robot")
    ap.add_argument("--duration", type=float, default=10.0, help="seconds per N")
    ap.add_argument("--warmup", type=float, default=2.0, help="seconds ignored at the start")
    ap.add_argument("--stride", type=int, default=5, help="setup-1 samples between scans")
    args = ap.parse_args(argv)
    ns = [int(x) for x in args.robots.split(",") if x.strip()]
    truth, ranges, info = scan_pool(args.stride, 400)
    endpoint = free_endpoint()
    workers = args.workers if args.workers is not None else (os.cpu_count() or 1)
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
        with open(log_path, "wb") as logf:
            svc = subprocess.Popen(
                cmd, cwd=REPO, stdout=logf, stderr=subprocess.STDOUT, start_new_session=True
            )
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
                from service.convert import map_message_of
                from sim_publisher.office import office_metric_map

                session.put(f"{P}/maps/office", encode(map_message_of(office_metric_map())))
                rec = Receiver(session)
                print(
                    f"# service: method={args.method} workers={workers} rate={args.rate:g} Hz "
                    f"window={args.duration - args.warmup:g} s; load before: {_load()}"
                )
                print(
                    f"{'N':>4} {'p50 ms':>8} {'p99 ms':>8} {'pose/s mean':>12} "
                    f"{'pose/s min':>11} {'answered':>9} {'starved':>8}"
                )
                best = 0
                total = 0
                for n in ns:
                    total += n
                    r = run_n(
                        session,
                        endpoint,
                        rec,
                        n,
                        args.method,
                        truth,
                        ranges,
                        info,
                        args.rate,
                        args.duration,
                        args.warmup,
                        total,
                    )
                    ok = r["p99"] <= 50.0 and not r["starved"] and r["answered_min"] >= 0.9
                    if ok:
                        best = max(best, n)
                    print(
                        f"{r['n']:>4} {r['p50']:>8.1f} {r['p99']:>8.1f} {r['rate_mean']:>12.2f} "
                        f"{r['rate_min']:>11.2f} {r['answered_min']:>8.0%} "
                        f"{'yes' if r['starved'] else 'no':>8}",
                        flush=True,
                    )
                print(f"# largest N with p99 <= 50 ms, >= 90 % answered, none starved: {best}")
                print(f"# load after: {_load()}")
        finally:
            if svc.poll() is None:
                svc.send_signal(signal.SIGTERM)
                try:
                    svc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    with contextlib.suppress(ProcessLookupError):
                        os.killpg(svc.pid, signal.SIGKILL)
                    svc.wait()
    return 0


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


if __name__ == "__main__":
    sys.exit(main())
