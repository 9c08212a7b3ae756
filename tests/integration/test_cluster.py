"""Three service instances behind a Zenoh router, robots spread by rendezvous hash.

Real processes on loopback: a router (a Python session in router mode, as in
test_faults.py), three ``python -m service --mode client --shard hash`` instances connected to
it, and six simulated robots streaming setup-1 scans with odometry at 10 Hz from this process.

* Each robot is served by exactly one instance, the one :func:`service.node.mirror.hrw_owner`
  names: one reply to a pose query (reply consolidation off), one pose per scan.
* One instance is SIGKILLed: its robots are served again by the survivors within 5 s (pose
  queries answered with a pose of a scan sent after the kill, continuing from the last pose
  before it, not from the configured start), and still exactly one reply each.
* A replacement instance with an empty state directory joins: it catches up from the others
  (maps, configurations, last poses through Zenoh), takes over the robots the hash now gives
  it, and again exactly one instance answers each robot.

About 30-40 s on the 2-core machine; prints the takeover times.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zenoh

from schemas.codec import decode, encode
from schemas.messages import Health, PoseMsg, RobotConfig, Scan
from service.adapters.convert import map_message_of
from service.node.mirror import hrw_owner
from sim_publisher.office import office_metric_map
from sim_publisher.scenario import make_setup

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]

P = "shapeloc"
NONE = zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE)
PER_INSTANCE = 2  # robots per instance
STRIDE = 4  # setup-1 samples (~11 mm each) between two scans of a robot: 0.44 m/s


def free_endpoint() -> str:
    import socket

    with socket.socket() as so:
        so.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{so.getsockname()[1]}"


def pick_robots(instances: list[str]) -> dict[str, str]:
    """Robot id -> owner: the first ``PER_INSTANCE`` ids of ``bot-<k>`` owned by each."""
    out: dict[str, str] = {}
    count = dict.fromkeys(instances, 0)
    k = 0
    while min(count.values()) < PER_INSTANCE:
        rid = f"bot-{k}"
        owner = hrw_owner(rid, instances)
        assert owner is not None
        if count[owner] < PER_INSTANCE:
            out[rid] = owner
            count[owner] += 1
        k += 1
    return out


class Poses:
    """Every pose received: (receipt time, message)."""

    def __init__(self, session: zenoh.Session) -> None:
        self.lock = threading.Lock()
        self.rows: list[tuple[float, PoseMsg]] = []
        self.sub = session.declare_subscriber(f"{P}/robots/*/pose", self._on)

    def _on(self, s: zenoh.Sample) -> None:
        m = decode(PoseMsg, s.payload.to_bytes(), str(s.encoding))
        with self.lock:
            self.rows.append((time.monotonic(), m))

    def of(self, robot: str) -> list[tuple[float, PoseMsg]]:
        with self.lock:
            return [(t, m) for t, m in self.rows if m.robot_id == robot]


class Robots:
    """Simulated robots: each drives the office tour from its own start, one scan (with
    odometry) every 0.1 s."""

    def __init__(self, session: zenoh.Session, robots: list[str]) -> None:
        self.setup = make_setup(1, seed=5, max_scans=2500)
        self.session = session
        self.starts = {r: 60 * i for i, r in enumerate(robots)}
        self.k = 0
        self.sent_at: dict[int, float] = {}
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)

    def index(self, robot: str, seq: int) -> int:
        return self.starts[robot] + STRIDE * seq

    def truth(self, robot: str, seq: int) -> np.ndarray:
        return self.setup.truth[self.index(robot, seq)]

    def config(self, robot: str) -> RobotConfig:
        return RobotConfig(map_id="office", method="icp", initial_pose=list(self.truth(robot, 0)))

    def scan(self, robot: str, seq: int) -> bytes:
        i = self.index(robot, seq)
        r, _a = self.setup.scan(i)
        lz = self.setup.laser
        msg = Scan(
            seq=seq,
            stamp=float(seq) * 0.1,
            angle_min=float(lz.angle_min),
            angle_increment=float(lz.angle_increment),
            range_min=0.0,
            range_max=float(lz.config.max_range),
            ranges=np.asarray(r, dtype=np.float64),
            odom=list(self.setup.odom[i]),
        )
        return encode(msg, ranges_as_bytes=True)

    def _run(self) -> None:
        t0 = time.monotonic()
        while not self.stop.is_set() and max(self.starts.values()) + STRIDE * self.k < 2500:
            self.sent_at[self.k] = time.monotonic()
            for r in self.starts:
                self.session.put(f"{P}/robots/{r}/scan", self.scan(r, self.k))
            self.k += 1
            time.sleep(max(0.0, t0 + 0.1 * self.k - time.monotonic()))


def healths(s: zenoh.Session) -> dict[str, Health]:
    out = {}
    for r in s.get(f"{P}/service/health", timeout=2.0, consolidation=NONE):
        if r.ok is not None:
            h = decode(Health, r.ok.payload.to_bytes())
            out[h.instance_id] = h
    return out


def pose_replies(s: zenoh.Session, robot: str, timeout: float = 1.0) -> list[Any]:
    return list(s.get(f"{P}/robots/{robot}/pose", timeout=timeout, consolidation=NONE))


def wait_for(pred: Callable[[], bool], timeout_s: float, what: str, svcs: list[Any]) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            logs = "\n".join(f"--- {s.state_dir.name} ---\n{s.log()[-4000:]}" for s in svcs)
            raise AssertionError(f"timed out waiting for {what}\n{logs}")
        time.sleep(0.05)


def test_three_instances_kill_one_its_robots_are_served_again_within_5_s(
    tmp_path: Path,
    spawn_router: Callable[..., Any],
    spawn_service: Callable[..., Any],
    open_session: Callable[..., zenoh.Session],
) -> None:
    t_test = time.monotonic()
    ep = free_endpoint()
    spawn_router(ep)

    def instance(name: str) -> Any:
        return spawn_service(
            tmp_path / name,
            "--mode", "client", "--connect", ep, "--shard", "hash", "--instance-id", name,
            workers=0, wait=False,
        )  # fmt: skip

    names = ["A", "B", "C"]
    svcs = {n: instance(n) for n in names}
    s = open_session(ep)
    all_svcs = list(svcs.values())
    wait_for(lambda: set(healths(s)) == set(names), 60.0, "three instances", all_svcs)

    def maps_everywhere() -> bool:
        s.put(f"{P}/maps/office", encode(map_message_of(office_metric_map())))
        time.sleep(0.2)
        hs = healths(s)
        return set(hs) == set(names) and all(h.maps == 1 for h in hs.values())

    wait_for(maps_everywhere, 20.0, "the map on every instance", all_svcs)
    owners = pick_robots(names)
    robots = Robots(s, list(owners))
    for r in owners:
        s.put(f"{P}/robots/{r}/config", encode(robots.config(r)))

    def spread_as_hashed(expected: dict[str, str], live: list[str]) -> bool:
        hs = healths(s)
        want = {n: sum(1 for o in expected.values() if o == n) for n in live}
        return set(hs) == set(live) and {n: hs[n].robots for n in live} == want

    wait_for(lambda: spread_as_hashed(owners, names), 20.0, "robots spread by hash", all_svcs)
    poses = Poses(s)
    robots.thread.start()
    try:
        wait_for(
            lambda: all(len(poses.of(r)) >= 20 for r in owners), 30.0, "poses of all", all_svcs
        )
        # exactly one instance answers each robot, and publishes one pose per scan
        for r in owners:
            replies = pose_replies(s, r)
            assert [x.ok is not None for x in replies] == [True], (r, replies)
            seqs = [m.seq for _t, m in poses.of(r)]
            assert len(seqs) == len(set(seqs)), (r, seqs)

        victim = "B"
        moved = [r for r, o in owners.items() if o == victim]
        time.sleep(0.5)
        last_before = {r: poses.of(r)[-1][1] for r in moved}
        t_kill = time.monotonic()
        svcs[victim].kill()  # SIGKILL to its process group: no goodbye, no final save
        served_at: dict[str, float] = {}
        first_new: dict[str, PoseMsg] = {}
        while len(served_at) < len(moved) and time.monotonic() - t_kill < 10.0:
            for r in moved:
                if r in served_at:
                    continue
                for x in pose_replies(s, r, timeout=0.5):
                    if x.ok is None:
                        continue
                    m = decode(PoseMsg, x.ok.payload.to_bytes())
                    if robots.sent_at.get(m.seq, 0.0) > t_kill:  # a scan sent after the kill
                        served_at[r] = time.monotonic()
                        first_new[r] = m
            time.sleep(0.02)
        takeover = {r: served_at.get(r, float("inf")) - t_kill for r in moved}
        print(
            "takeover (kill -9 -> first pose query answered with a scan sent after it): "
            + ", ".join(f"{r} {t:.2f} s" for r, t in takeover.items())
        )
        assert max(takeover.values()) < 5.0, takeover
        survivors = [n for n in names if n != victim]
        new_owners = {r: hrw_owner(r, survivors) for r in owners}
        assert all(new_owners[r] == o for r, o in owners.items() if o != victim)  # HRW: only
        wait_for(lambda: spread_as_hashed(new_owners, survivors), 10.0, "new spread", all_svcs)
        for r in moved:
            m = first_new[r]
            err = float(np.hypot(*(m.pose[:2] - robots.truth(r, m.seq)[:2])))
            assert err < 0.15, (r, m.seq, m.pose, err)
            # continued from the last pose before the kill, not restarted from the config
            before = last_before[r]
            assert np.hypot(*(m.pose[:2] - before.pose[:2])) < 0.3, (r, m.pose, before.pose)
            assert np.hypot(*(before.pose[:2] - robots.truth(r, 0)[:2])) > 0.3
        for r in owners:
            assert [x.ok is not None for x in pose_replies(s, r)] == [True], r

        # a replacement instance with an empty state directory joins and takes its share
        t_join = time.monotonic()
        svcs["D"] = instance("D")
        all_svcs.append(svcs["D"])
        live = [*survivors, "D"]
        final_owners = {r: hrw_owner(r, live) for r in owners}
        wait_for(lambda: spread_as_hashed(final_owners, live), 60.0, "D's share", all_svcs)
        to_d = [r for r, o in final_owners.items() if o == "D"]
        t_share = time.monotonic()
        wait_for(
            lambda: all(
                any(m.seq > 0 and robots.sent_at.get(m.seq, 0) > t_share for _t, m in poses.of(r))
                for r in to_d
            ),
            10.0,
            "poses from D",
            all_svcs,
        )
        for r in owners:
            replies = pose_replies(s, r)
            assert [x.ok is not None for x in replies] == [True], r
            m = decode(PoseMsg, replies[0].ok.payload.to_bytes())
            assert np.hypot(*(m.pose[:2] - robots.truth(r, m.seq)[:2])) < 0.15, (r, m)
        t_served = time.monotonic()
        d_log = svcs["D"].log()
        assert "caught up from" in d_log, d_log[-3000:]
        print(
            f"replacement D: took {len(to_d)} robots ({', '.join(to_d)}) {t_share - t_join:.1f} s "
            f"after its process was started, their poses flowed again "
            f"{t_served - t_join:.1f} s after; test {time.monotonic() - t_test:.1f} s"
        )
    finally:
        robots.stop.set()
        robots.thread.join(timeout=5)


def test_static_shard_replacement_takes_over_from_the_mirrored_state(
    tmp_path: Path,
    spawn_router: Callable[..., Any],
    spawn_service: Callable[..., Any],
    open_session: Callable[..., zenoh.Session],
) -> None:
    """``--robots`` patterns: the shard serving ``b$*`` is SIGKILLed and a replacement with the
    same pattern but an empty state directory (another machine) starts: it learns the
    configurations and last poses of its robots from the other shard's mirror and continues
    them."""
    ep = free_endpoint()
    spawn_router(ep)

    def shard(name: str, pattern: str) -> Any:
        return spawn_service(
            tmp_path / name,
            "--mode", "client", "--connect", ep, "--robots", pattern, "--instance-id", name,
            workers=0, wait=False,
        )  # fmt: skip

    a, b = shard("A", "a$*"), shard("B", "b$*")
    svcs = [a, b]
    s = open_session(ep)
    wait_for(lambda: set(healths(s)) == {"A", "B"}, 60.0, "two shards", svcs)

    def maps_everywhere() -> bool:
        s.put(f"{P}/maps/office", encode(map_message_of(office_metric_map())))
        time.sleep(0.2)
        hs = healths(s)
        return set(hs) == {"A", "B"} and all(h.maps == 1 for h in hs.values())

    wait_for(maps_everywhere, 20.0, "the map on both shards", svcs)
    robots = Robots(s, ["a1", "b1", "b2"])
    for r in robots.starts:
        s.put(f"{P}/robots/{r}/config", encode(robots.config(r)))
    wait_for(lambda: {n: h.robots for n, h in healths(s).items()} == {"A": 1, "B": 2}, 20.0,
             "configs", svcs)  # fmt: skip
    poses = Poses(s)
    robots.thread.start()
    try:
        wait_for(lambda: all(len(poses.of(r)) >= 20 for r in robots.starts), 30.0, "poses", svcs)
        time.sleep(1.5)  # A's mirror has saved the last poses too (save interval 1 s)
        last_before = {r: poses.of(r)[-1][1] for r in ("b1", "b2")}
        b.kill()
        t_start = time.monotonic()
        svcs.append(shard("B2", "b$*"))
        served: dict[str, PoseMsg] = {}
        while len(served) < 2 and time.monotonic() - t_start < 30.0:
            for r in ("b1", "b2"):
                for x in pose_replies(s, r, timeout=0.5):
                    if x.ok is not None:
                        m = decode(PoseMsg, x.ok.payload.to_bytes())
                        if robots.sent_at.get(m.seq, 0.0) > t_start:
                            served.setdefault(r, m)
            time.sleep(0.05)
        elapsed = time.monotonic() - t_start
        assert set(served) == {"b1", "b2"}, svcs[-1].log()[-3000:]
        for r, m in served.items():
            assert np.hypot(*(m.pose[:2] - robots.truth(r, m.seq)[:2])) < 0.15, (r, m)
            before = last_before[r]
            assert np.hypot(*(before.pose[:2] - robots.truth(r, 0)[:2])) > 0.3  # had moved
        for r in robots.starts:
            assert [x.ok is not None for x in pose_replies(s, r)] == [True], r
        assert {n: h.robots for n, h in healths(s).items()} == {"A": 1, "B2": 2}
        print(f"static shard replaced: b1, b2 served again {elapsed:.1f} s after B2 was started")
    finally:
        robots.stop.set()
        robots.thread.join(timeout=5)


def test_frozen_instance_is_taken_over_and_resumes_without_stale_poses(
    tmp_path: Path,
    spawn_router: Callable[..., Any],
    spawn_service: Callable[..., Any],
    open_session: Callable[..., zenoh.Session],
) -> None:
    """SIGSTOP (a hung or unplugged host: its TCP link stays open): with the 2 s lease of
    docker/service-cluster.json5 the router drops it and the others take its robots over; on
    SIGCONT it comes back, gets its robots back, restarts them from the newer poses the others
    published meanwhile (not from where it froze), and each robot has one owner again."""
    import os
    import signal

    ep = free_endpoint()
    spawn_router(ep)
    lease = str(Path(__file__).resolve().parents[2] / "docker" / "service-cluster.json5")

    def instance(name: str) -> Any:
        return spawn_service(
            tmp_path / name,
            "--mode", "client", "--connect", ep, "--shard", "hash", "--instance-id", name,
            "--zenoh-config", lease, workers=0, wait=False,
        )  # fmt: skip

    names = ["A", "B", "C"]
    svcs = {n: instance(n) for n in names}
    all_svcs = list(svcs.values())
    s = open_session(ep)
    wait_for(lambda: set(healths(s)) == set(names), 60.0, "three instances", all_svcs)

    def maps_everywhere() -> bool:
        s.put(f"{P}/maps/office", encode(map_message_of(office_metric_map())))
        time.sleep(0.2)
        hs = healths(s)
        return set(hs) == set(names) and all(h.maps == 1 for h in hs.values())

    wait_for(maps_everywhere, 20.0, "the map on every instance", all_svcs)
    owners = pick_robots(names)
    robots = Robots(s, list(owners))
    for r in owners:
        s.put(f"{P}/robots/{r}/config", encode(robots.config(r)))

    def spread(live: list[str]) -> bool:
        hs = healths(s)
        want = {n: sum(1 for r in owners if hrw_owner(r, live) == n) for n in live}
        return set(hs) == set(live) and {n: hs[n].robots for n in live} == want

    wait_for(lambda: spread(names), 20.0, "robots spread by hash", all_svcs)
    poses = Poses(s)
    robots.thread.start()
    frozen = svcs["B"]
    try:
        wait_for(lambda: all(len(poses.of(r)) >= 10 for r in owners), 30.0, "poses", all_svcs)
        moved = [r for r, o in owners.items() if o == "B"]
        os.killpg(frozen.proc.pid, signal.SIGSTOP)
        t_stop = time.monotonic()
        wait_for(
            lambda: all(
                any(robots.sent_at.get(m.seq, 0.0) > t_stop for _t, m in poses.of(r)) for r in moved
            ),
            10.0,
            "the frozen instance's robots served by the others",
            all_svcs,
        )
        took = time.monotonic() - t_stop
        time.sleep(3.0)  # the robots drive on (> 2 m in all) while B is frozen
        os.killpg(frozen.proc.pid, signal.SIGCONT)
        t_cont = time.monotonic()
        wait_for(lambda: spread(names), 20.0, "B's robots back to B", all_svcs)
        time.sleep(1.0)
        for r in owners:
            replies = pose_replies(s, r)
            assert [x.ok is not None for x in replies] == [True], r
            m = decode(PoseMsg, replies[0].ok.payload.to_bytes())
            assert robots.sent_at.get(m.seq, 0.0) > t_cont, (r, m.seq)
            assert np.hypot(*(m.pose[:2] - robots.truth(r, m.seq)[:2])) < 0.15, (r, m)
        for r in moved:  # every pose after the resume is where the robot was
            late = [m for t, m in poses.of(r) if t > t_cont + 0.5]
            errs = [float(np.hypot(*(m.pose[:2] - robots.truth(r, m.seq)[:2]))) for m in late]
            assert late and max(errs) < 0.15, (r, errs)
        b_log = frozen.log()
        assert "this process did not run for" in b_log, b_log[-3000:]  # the freeze was seen
        assert f"{len(moved)} of our robots restart from a newer pose" in b_log, b_log[-3000:]
        print(f"frozen instance: its robots served by the others {took:.1f} s after SIGSTOP")
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(frozen.proc.pid, signal.SIGCONT)
        robots.stop.set()
        robots.thread.join(timeout=5)
