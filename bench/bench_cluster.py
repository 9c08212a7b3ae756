"""Cluster benchmark: take-over time after ``kill -9``, and robots served with 1 vs 3 instances.

Everything on loopback: a Zenoh router (``python -m service.node.router``), service instances
``python -m service --mode client --shard hash`` connected to it, a publisher process sending
every robot's setup-1 scans at ``--rate`` Hz (robots staggered within the period, as in
bench_service.py), and this process receiving poses and asking for them.

**Take-over** (``--reps`` repetitions, default 3): three instances serve ``--robots`` robots
(default 12); each repetition SIGKILLs one instance (A, B, C in turn) and measures, per robot
it served, the time from the kill to (a) the first pose published for a scan sent after the
kill and (b) the first ``get <prefix>/robots/<id>/pose`` answered with such a pose (polled
every 20 ms). Then the instance is started again (same id, same state directory): the hash
gives its robots back, and (c) is the longest gap between two poses of those robots from its
start on (the planned hand-back: the previous owner lets go when it sees the new token, the
joiner takes over ``handover_delay_s`` later and prepares their localisers).

The "seen" column is the time from the signal to the first survivor's log line saying the
victim's token vanished.

With ``--freeze`` the instance is SIGSTOPped instead (a hung or unplugged host: its TCP link
stays open, so only the link's lease tells the router; the instances then run with
``docker/service-cluster.json5``, a 2 s lease), and killed before it is started again.

**Throughput** (``--throughput N1,N2,...``, default ``10,20,30``; ``--throughput ''`` skips it):
for each N, N robots at 10 Hz against one instance (``--workers`` = ``--single-workers``,
default the number of cores) and against three (``--workers`` = ``--instance-workers`` each,
default 1), ``--duration`` s per run. Latency is pose receipt minus scan
send. Prints p50/p99, poses/s and the answered fraction (poses / scans sent; below 1 the
instances skipped older scans, latest wins).

Usage: ``python -m bench.bench_cluster [--method icp] [--robots 12] [--reps 3] [--freeze]
[--throughput 10,20,30] [--duration 8] [--instance-workers 1] [--single-workers CORES]
[--keep] [--fanout 5000]``; ``--fanout RATE`` also measures what a client subscribed to
``<prefix>/**`` spends on RATE scans/s that it drops (every instance receives every robot's
scans). The load average is printed with each table: the machine's cores are shared by
the router, the instances, the publisher and this process.
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing as mp
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

from bench.harness import REPO, client_config, free_endpoint, project_env
from bench.soak import publisher_main, scan_pool
from schemas.codec import decode, encode
from schemas.messages import Health, RobotConfig
from service.node.mirror import hrw_owner

P = "shapeloc"
NONE = zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE)


def _load() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


class Proc:
    """A child process in its own process group, its output in a log file."""

    def __init__(self, cmd: list[str], log: Path) -> None:
        self.log = log
        with open(log, "ab") as f:
            self.p = subprocess.Popen(
                cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT, env=project_env(),
                start_new_session=True,
            )  # fmt: skip

    def freeze(self) -> None:
        """SIGSTOP the whole process group: alive to the kernel, silent on the network."""
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.p.pid, signal.SIGSTOP)

    def kill(self) -> None:
        """SIGKILL the whole process group (the service and its workers)."""
        if self.p.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.p.pid, signal.SIGKILL)
        self.p.wait(timeout=10)

    def stop(self) -> None:
        """SIGTERM, then SIGKILL after 20 s."""
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGTERM)
            try:
                self.p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                self.kill()


def start_router(endpoint: str, tmp: Path) -> Proc:
    r = Proc(
        [sys.executable, "-m", "service.node.router", "--listen", endpoint], tmp / "router.log"
    )
    deadline = time.time() + 30
    while "ready" not in r.log.read_text(errors="replace"):
        if r.p.poll() is not None or time.time() > deadline:
            raise RuntimeError(f"router did not start: {r.log.read_text()}")
        time.sleep(0.05)
    return r


#: Zenoh settings of the instances with ``--freeze``: a 2 s lease (docs/cluster.md).
LEASE_CONFIG = REPO / "docker" / "service-cluster.json5"


def start_instance(
    name: str, endpoint: str, tmp: Path, workers: int, short_lease: bool = False
) -> Proc:
    cmd = [
        sys.executable, "-m", "service", "--mode", "client", "--connect", endpoint,
        "--shard", "hash", "--instance-id", name, "--state-dir", str(tmp / name),
        "--workers", str(workers), "--log-level", "info",
    ]  # fmt: skip
    if short_lease:
        cmd += ["--zenoh-config", str(LEASE_CONFIG)]
    return Proc(cmd, tmp / f"{name}.log")


def healths(s: zenoh.Session) -> dict[str, Health]:
    out = {}
    for r in s.get(f"{P}/service/health", timeout=2.0, consolidation=NONE):
        if r.ok is not None:
            h = decode(Health, r.ok.payload.to_bytes())
            out[h.instance_id] = h
    return out


def wait(pred: Any, timeout: float, what: str) -> None:
    deadline = time.time() + timeout
    while not pred():
        if time.time() > deadline:
            raise RuntimeError(f"timed out: {what}")
        time.sleep(0.05)


class Poses:
    """(robot, seq, stamp = send time, receipt time) of every pose."""

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

    def longest_gap(self, robot: str, t: float) -> float:
        """Longest time without a pose of ``robot`` after ``t`` (receipt times)."""
        with self.lock:
            ts = sorted(tr for r, _s, _st, tr in self.rows if r == robot and tr > t)
        return float(np.max(np.diff([t, *ts]))) if ts else float("inf")

    def first_after(self, robot: str, t: float) -> float | None:
        """Receipt time of the first pose of ``robot`` for a scan sent after ``t``."""
        with self.lock:
            ts = [tr for r, _s, st, tr in self.rows if r == robot and st > t]
        return min(ts) if ts else None


class Cluster:
    """Router + named instances + a session; robots configured and spread by hash."""

    def __init__(self, tmp: Path, names: list[str], workers: int, lease: bool = False) -> None:
        self.tmp, self.workers = tmp, workers
        self.endpoint = free_endpoint()
        self.router = start_router(self.endpoint, tmp)
        self.procs = {n: start_instance(n, self.endpoint, tmp, workers, lease) for n in names}
        self.session = zenoh.open(client_config(self.endpoint))
        wait(lambda: set(healths(self.session)) == set(names), 90, "instances up")

    def put_map(self, names: list[str]) -> None:
        from service.adapters.convert import map_message_of
        from sim_publisher.office import office_metric_map

        payload = encode(map_message_of(office_metric_map()))

        def everywhere() -> bool:
            self.session.put(f"{P}/maps/office", payload)
            time.sleep(0.2)
            hs = healths(self.session)
            return set(hs) == set(names) and all(h.maps >= 1 for h in hs.values())

        wait(everywhere, 30, "map on every instance")

    def configure(self, robots: list[str], method: str, truth: np.ndarray, starts: list[int]):
        for r, st in zip(robots, starts, strict=True):
            cfg = RobotConfig(map_id="office", method=method, initial_pose=list(truth[st]))
            self.session.put(f"{P}/robots/{r}/config", encode(cfg))

    def spread_ok(self, robots: list[str], live: list[str]) -> bool:
        hs = healths(self.session)
        want = {n: sum(1 for r in robots if hrw_owner(r, live) == n) for n in live}
        return set(hs) == set(live) and {n: hs[n].robots for n in live} == want

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.session.close()
        for p in self.procs.values():
            p.stop()
        self.router.stop()


def publisher(endpoint: str, robots: list[str], starts: list[int], pool: Any, rate: float,
              duration: float) -> mp.Process:  # fmt: skip
    _truth, ranges, info = pool
    ctx = mp.get_context("spawn")
    sent = ctx.Array("l", len(robots), lock=False)  # soak's publisher counts what it sent
    proc = ctx.Process(
        target=publisher_main,
        args=(endpoint, robots, starts, ranges, info, rate, duration, time.time() + 0.3, sent),
        daemon=True,
    )
    proc.start()
    return proc


def vanished_seen(tmp: Path, names: list[str], victim: str, t_wall: float) -> float:
    """Seconds from ``t_wall`` to the first survivor's log line saying the victim's token
    vanished (log time stamps have millisecond resolution)."""
    import datetime as dt
    import re

    pat = re.compile(
        r"^(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3}) .*token of instance "
        + re.escape(victim)
        + " vanished"
    )
    best = float("inf")
    for n in names:
        if n == victim:
            continue
        for line in (tmp / f"{n}.log").read_text(errors="replace").splitlines():
            m = pat.match(line)
            if m:
                t = dt.datetime.strptime(m.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp()
                if t >= t_wall - 0.002:
                    best = min(best, t - t_wall)
    return best


def query_served_after(s: zenoh.Session, robot: str, t: float) -> bool:
    """Whether a pose query for ``robot`` is answered with a pose of a scan sent after ``t``."""
    for r in s.get(f"{P}/robots/{robot}/pose", timeout=0.5, consolidation=NONE):
        if r.ok is not None and msgpack.unpackb(r.ok.payload.to_bytes())["stamp"] > t:
            return True
    return False


@contextlib.contextmanager
def _workdir(keep: bool) -> Any:
    """A temporary directory for logs and state (kept, and named, with ``--keep``)."""
    if keep:
        d = Path(tempfile.mkdtemp(prefix="bench_cluster-"))
        print(f"# logs and state in {d}")
        yield d
    else:
        with tempfile.TemporaryDirectory() as d:
            yield Path(d)


def takeover(args: argparse.Namespace, pool: Any) -> None:
    names = ["A", "B", "C"]
    robots = [f"r{i}" for i in range(args.robots)]
    truth = pool[0]
    starts = [(i * 37) % len(truth) for i in range(len(robots))]
    with _workdir(args.keep) as tmp:
        cl = Cluster(tmp, names, args.instance_workers, args.freeze)
        try:
            cl.put_map(names)
            cl.configure(robots, args.method, truth, starts)
            wait(lambda: cl.spread_ok(robots, names), 30, "robots spread")
            poses = Poses(cl.session)
            dur = args.reps * 20.0 + 10.0
            pub = publisher(cl.endpoint, robots, starts, pool, args.rate, dur)
            how = "SIGSTOP, 2 s lease" if args.freeze else "SIGKILL"
            print(
                f"# take-over ({how}): 3 instances (--workers {args.instance_workers}), "
                f"{len(robots)} robots x {args.rate:g} Hz, method {args.method}; load before: "
                f"{_load()}"
            )
            print(
                f"{'rep':>3} {'killed':>6} {'seen ms':>10} {'robots':>6} {'pose p50 s':>10} "
                f"{'pose max s':>10} "
                f"{'query max s':>11} {'back gap s':>10}"
            )
            time.sleep(3.0)
            all_pose: list[float] = []
            all_query: list[float] = []
            all_back: list[float] = []
            all_seen: list[float] = []
            for rep in range(args.reps):
                victim = names[rep % len(names)]
                moved = [r for r in robots if hrw_owner(r, names) == victim]
                t_kill_wall = time.time()
                if args.freeze:
                    cl.procs[victim].freeze()
                else:
                    cl.procs[victim].kill()
                served: dict[str, float] = {}
                while len(served) < len(moved) and time.time() - t_kill_wall < 15:
                    for r in moved:
                        if r not in served and query_served_after(cl.session, r, t_kill_wall):
                            served[r] = time.time() - t_kill_wall
                    time.sleep(0.02)
                seen = vanished_seen(tmp, names, victim, t_kill_wall)
                pose_t = []
                for r in moved:
                    t = poses.first_after(r, t_kill_wall)
                    pose_t.append(float("inf") if t is None else t - t_kill_wall)
                query_t = [served.get(r, float("inf")) for r in moved]
                survivors = [n for n in names if n != victim]
                wait(lambda s=survivors: cl.spread_ok(robots, s), 15, "survivors' spread")
                cl.procs[victim].kill()
                # the killed instance comes back (same id and state directory)
                t_start = time.time()
                cl.procs[victim] = start_instance(
                    victim, cl.endpoint, tmp, args.instance_workers, args.freeze
                )
                wait(lambda: cl.spread_ok(robots, names), 90, "spread after the restart")
                time.sleep(2.0)
                back = [poses.longest_gap(r, t_start) for r in moved]
                all_pose += pose_t
                all_query += query_t
                all_back += back
                all_seen.append(seen)
                print(
                    f"{rep:>3} {victim:>6} {seen * 1e3:>10.0f} {len(moved):>6} "
                    f"{np.median(pose_t):>10.2f} "
                    f"{max(pose_t):>10.2f} {max(query_t):>11.2f} "
                    f"{max(back):>10.2f}",
                    flush=True,
                )
                poses.take()
            print(
                f"# token seen vanishing {min(all_seen) * 1e3:.0f}-{max(all_seen) * 1e3:.0f} ms "
                f"after the signal; all {len(all_pose)} moved robots: pose p50 "
                f"{np.median(all_pose):.2f} s, "
                f"max {max(all_pose):.2f} s; query max {max(all_query):.2f} s; longest gap "
                f"between poses while the restarted instance took them back {max(all_back):.2f} "
                f"s; load after: {_load()}"
            )
            pub.kill()
        finally:
            cl.close()


def throughput(args: argparse.Namespace, pool: Any, ns: list[int]) -> None:
    truth = pool[0]
    print(
        f"# throughput: method {args.method}, {args.rate:g} Hz per robot, window "
        f"{args.duration - 2:g} s per row; one instance with --workers {args.single_workers}, "
        f"three with --workers {args.instance_workers} each; load before: {_load()}"
    )
    print(
        f"{'instances':>9} {'workers':>7} {'N':>4} {'p50 ms':>7} {'p99 ms':>7} {'pose/s':>7} "
        f"{'answered':>8} {'robots per instance':>19}"
    )
    for k, workers in ((1, args.single_workers), (3, args.instance_workers)):
        names = ["A", "B", "C"][:k]
        best = 0
        with _workdir(args.keep) as tmp:
            cl = Cluster(tmp, names, workers)
            try:
                cl.put_map(names)
                poses = Poses(cl.session)
                # warm-up, not measured: first use of the method in every worker process
                warm = [f"warm-{i}" for i in range(2 * len(names) * workers)]
                cl.configure(warm, args.method, truth, [37 * i for i in range(len(warm))])
                wait(lambda w=warm, cl=cl, m=names: cl.spread_ok(w, m), 60, "warm-up robots")
                pub = publisher(cl.endpoint, warm, [37 * i for i in range(len(warm))], pool,
                                args.rate, 5.0)  # fmt: skip
                pub.join(timeout=60)
                configured: list[str] = list(warm)
                for n in ns:
                    robots = [f"n{n}-{i}" for i in range(n)]
                    starts = [(i * 37) % len(truth) for i in range(n)]
                    cl.configure(robots, args.method, truth, starts)
                    configured += robots
                    wait(lambda c=configured, cl=cl, m=names: cl.spread_ok(c, m), 60, "configured")
                    poses.take()
                    t0 = time.time() + 0.3
                    pub = publisher(cl.endpoint, robots, starts, pool, args.rate, args.duration)
                    pub.join(timeout=args.duration + 60)
                    time.sleep(1.0)
                    lo, hi = t0 + 2.0, t0 + args.duration
                    rows = [x for x in poses.take() if x[0] in set(robots) and lo <= x[2] < hi]
                    lat = np.array([(tr - st) * 1e3 for _r, _s, st, tr in rows])
                    sent = (hi - lo) * args.rate * n
                    per = "/".join(
                        str(sum(1 for r in robots if hrw_owner(r, names) == m)) for m in names
                    )
                    p50, p99 = np.percentile(lat, [50, 99]) if lat.size else (np.nan, np.nan)
                    answered = len(rows) / sent
                    if p99 <= 50.0 and answered >= 0.9:
                        best = max(best, n)
                    print(
                        f"{k:>9} {k * workers:>7} {n:>4} {p50:>7.1f} {p99:>7.1f} "
                        f"{len(rows) / (hi - lo):>7.1f} {answered:>8.0%} {per:>19}",
                        flush=True,
                    )
            finally:
                cl.close()
        print(f"# {k} instance(s): largest N with p99 <= 50 ms and >= 90 % answered: {best}")
    print(f"# load after: {_load()}")


def _fanout_sub(endpoint: str, seconds: float, out: Any) -> None:
    """Child: a client session subscribed to ``<prefix>/**`` that only counts; reports its
    CPU time per received sample."""
    import resource

    n = [0]

    def cb(sample: zenoh.Sample) -> None:
        str(sample.key_expr)
        n[0] += 1

    with zenoh.open(client_config(endpoint)) as s:
        s.declare_subscriber(f"{P}/**", cb)
        out.put("ready")
        time.sleep(1.5)
        r0, n0, t0 = resource.getrusage(resource.RUSAGE_SELF), n[0], time.time()
        time.sleep(seconds)
        r1, n1, t1 = resource.getrusage(resource.RUSAGE_SELF), n[0], time.time()
        cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
        out.put(((n1 - n0) / (t1 - t0), cpu / (t1 - t0), cpu / max(1, n1 - n0)))


def _fanout_pub(endpoint: str, rate: float, seconds: float, size: int) -> None:
    """Child: ``rate`` samples per second of ``size`` bytes over 500 robots' scan keys."""
    payload = os.urandom(size)
    per_tick = max(1, int(rate / 10))
    with zenoh.open(client_config(endpoint)) as s:
        pubs = [s.declare_publisher(f"{P}/robots/fan-{i}/scan") for i in range(per_tick)]
        t0, k = time.time(), 0
        while time.time() - t0 < seconds:
            for p in pubs:
                p.put(payload)
            k += 1
            time.sleep(max(0.0, t0 + k * 0.1 - time.time()))


def fanout(rate: float) -> None:
    """What receiving (and dropping) every robot's scans costs an instance: a subscriber's CPU
    per sample at ``rate`` scans/s of 1 594 bytes (361 float32 beams)."""
    with _workdir(False) as tmp:
        ep = free_endpoint()
        router = start_router(ep, tmp)
        ctx = mp.get_context("spawn")
        q = ctx.Queue()
        sub = ctx.Process(target=_fanout_sub, args=(ep, 6.0, q))
        sub.start()
        q.get(timeout=60)
        pub = ctx.Process(target=_fanout_pub, args=(ep, rate, 9.0, 1594))
        pub.start()
        got, cpu, per = q.get(timeout=60)
        pub.join(timeout=30)
        sub.join(timeout=30)
        router.stop()
    print(
        f"# fan-out: a client subscribed to {P}/** received {got:.0f} scans/s of 1 594 bytes "
        f"using {cpu * 100:.1f} % of a core ({per * 1e6:.1f} us a scan); load {_load()}"
    )


def main(argv: list[str] | None = None) -> int:
    """Run the take-over table, then the throughput table; returns 0."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--method", default="icp", choices=["shape", "icp", "lines"])
    ap.add_argument("--robots", type=int, default=12, help="robots in the take-over runs")
    ap.add_argument("--reps", type=int, default=3, help="take-over repetitions (0: none)")
    ap.add_argument("--rate", type=float, default=10.0, help="scans per second per robot")
    ap.add_argument("--throughput", default="10,20,30", help="N values ('' to skip)")
    ap.add_argument("--duration", type=float, default=8.0, help="seconds per throughput run")
    ap.add_argument(
        "--instance-workers", type=int, default=1, help="--workers of each of 3 instances"
    )
    ap.add_argument(
        "--single-workers",
        type=int,
        default=os.cpu_count() or 1,
        help="--workers of the single instance (default: cores)",
    )
    ap.add_argument("--keep", action="store_true", help="keep the logs and state directories")
    ap.add_argument(
        "--fanout",
        type=float,
        default=0.0,
        metavar="RATE",
        help="also measure the CPU a subscriber to <prefix>/** spends on RATE scans/s",
    )
    ap.add_argument(
        "--freeze",
        action="store_true",
        help="take-over: SIGSTOP the instance instead of SIGKILL (a hung or unplugged host; "
        "the instances run with docker/service-cluster.json5, a 2 s lease)",
    )
    args = ap.parse_args(argv)
    pool = scan_pool(400, 5)  # 400 scans 5 samples apart
    if args.reps > 0:
        takeover(args, pool)
    ns = [int(x) for x in args.throughput.split(",") if x.strip()]
    if ns:
        throughput(args, pool, ns)
    if args.fanout > 0:
        fanout(args.fanout)
    return 0


if __name__ == "__main__":
    sys.exit(main())
