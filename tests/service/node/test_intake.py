"""The scan intake: raw queue bounds and fairness, validation before latest-wins, the control
clock and the rejection log limiter. No network, no workers."""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest

from service.errors import InvalidMessage, UnknownRobot
from service.node.intake import (
    ITEM_OVERHEAD_BYTES,
    ControlClock,
    RawScan,
    RawScanQueue,
    ScanIntake,
    ValidScan,
    validate_scan,
)
from service.node.node import RejectLog

N = 361


def wire(seq: int, **over: object) -> dict:
    rng = np.random.default_rng(seq)
    w = {
        "seq": seq,
        "stamp": 0.1 * seq,
        "angle_min": -np.pi / 2,
        "angle_increment": np.pi / (N - 1),
        "range_min": 0.0,
        "range_max": 10.0,
        "ranges": [float(v) for v in rng.uniform(0.5, 9.0, N)],
    }
    w.update(over)
    return w


def raw(robot: str, payload: bytes | None, t: float = 0.0, **kw: object) -> RawScan:
    return RawScan(robot, f"shapeloc/robots/{robot}/scan", payload, None, t, **kw)  # type: ignore[arg-type]


def test_validate_scan_gives_core_arrays() -> None:
    w = wire(3, odom=[1.0, 2.0, 3.5], ranges=[1.0, float("nan"), 20.0, 0.5] + [2.0] * (N - 4))
    s = validate_scan(raw("r1", msgpack.packb(w), t=12.5, ctl=4))
    assert (s.robot_id, s.seq, s.stamp, s.t_recv, s.ctl) == ("r1", 3, pytest.approx(0.3), 12.5, 4)
    assert s.ranges.shape == s.angles.shape == (N,)
    assert np.isnan(s.ranges[1]) and np.isnan(s.ranges[2])  # NaN and above range_max
    assert s.ranges[0] == 1.0
    assert s.angles[0] == pytest.approx(-np.pi / 2) and s.angles[-1] == pytest.approx(np.pi / 2)
    assert s.odom is not None and s.odom[2] == pytest.approx(3.5 - 2 * np.pi)  # normalised


@pytest.mark.parametrize(
    ("payload", "needle"),
    [
        (b"\xc1\xc1", "msgpack"),
        (msgpack.packb([1, 2]), "must be a map"),
        (msgpack.packb({**wire(0), "seq": "7"}), "seq"),
        (msgpack.packb(wire(0, stamp=float("nan"))), "stamp"),
        (msgpack.packb(wire(0, angle_increment=0.0)), "angle_increment"),
    ],
)
def test_validate_scan_rejects_with_reason(payload: bytes, needle: str) -> None:
    with pytest.raises(InvalidMessage, match=needle):
        validate_scan(raw("r1", payload))


def test_raw_queue_round_robin_without_overflow_is_o1() -> None:
    q = RawScanQueue(per_robot=8, max_bytes=1 << 20)
    for i in range(5):
        q.put(raw("a", b"x", t=i))
    q.put(raw("b", b"y", t=9))
    q.put(raw("a", b"x", t=10))
    assert q.compactions == 0 and len(q) == 7
    assert [it.t_recv for it in q.take(0.0)] == [0, 1, 2, 3, 4, 10]  # type: ignore[union-attr]
    assert [it.robot_id for it in q.take(0.0)] == ["b"]
    assert q.take(0.0) == [] and q.nbytes == 0


def test_overflow_compacts_and_keeps_the_valid_scan() -> None:
    """A robot's backlog overflows with garbage behind one valid scan: the backlog is
    validated in place; the valid scan survives, every rejection is either kept (with its
    reason, for a notice) or counted through ``overflow_reject``; none is lost."""
    counted: list[str] = []
    q = RawScanQueue(
        per_robot=4, max_bytes=1 << 20, overflow_reject=lambda k, e: counted.append(str(e))
    )
    q.put(raw("r", msgpack.packb(wire(5))))
    for _ in range(10):
        q.put(raw("r", b"\xc1"))
    assert q.compactions >= 1
    entries = q.take(0.0)
    valid = [e for e in entries if isinstance(e, ValidScan)]
    rejected = [e for e in entries if isinstance(e, RawScan) and e.reject is not None]
    raw_left = [e for e in entries if isinstance(e, RawScan) and e.reject is None]
    assert [v.seq for v in valid] == [5]
    assert len(rejected) + len(counted) + len(raw_left) == 10
    assert q.notices_dropped == len(counted) > 0
    assert all("msgpack" in c for c in counted)


def test_overflow_keeps_only_the_newest_valid_scan() -> None:
    q = RawScanQueue(per_robot=3, max_bytes=1 << 20)
    for seq in range(3):
        q.put(raw("r", msgpack.packb(wire(seq))))
    q.put(raw("r", msgpack.packb(wire(3))))  # overflow: 0, 1, 2, 3 validated, 3 kept
    [only] = q.take(0.0)
    assert isinstance(only, ValidScan) and only.seq == 3 and q.superseded == 3


def test_byte_budget_compacts_instead_of_dropping() -> None:
    big = msgpack.packb(wire(1, note="z" * 20_000))
    budget = 3 * (ITEM_OVERHEAD_BYTES + len(big))
    q = RawScanQueue(per_robot=100, max_bytes=budget)
    for i in range(3):
        q.put(raw(f"r{i}", big))
    q.put(raw("r9", big))  # over budget: r9's sample is validated at once, not dropped
    assert q.compactions == 1 and q.nbytes <= budget + ITEM_OVERHEAD_BYTES + 2 * N * 8
    robots = []
    while entries := q.take(0.0):
        robots.append(entries[-1].robot_id)
    assert sorted(robots) == ["r0", "r1", "r2", "r9"]


def test_raw_queue_take_wakes_on_put_and_kick() -> None:
    q = RawScanQueue(per_robot=2, max_bytes=1 << 16)
    threading.Timer(0.05, q.put, args=(raw("r", b"1"),)).start()
    assert [it.robot_id for it in q.take(5.0)] == ["r"]
    threading.Timer(0.05, q.kick).start()
    t = time.monotonic()
    assert q.take(5.0) == []
    assert time.monotonic() - t < 2.0


def test_invalid_payloads_never_reach_latest_wins() -> None:
    """A valid scan followed by a burst of garbage on the same key: the valid one is accepted
    and every garbage payload is rejected with its reason (none replaces the valid one)."""
    accepted: list[ValidScan] = []
    rejected: list[tuple[str, str]] = []
    intake = ScanIntake(accepted.append, lambda k, e: rejected.append((k, str(e))))
    garbage = [b"\xc1", msgpack.packb(wire(1, stamp=float("inf"))), msgpack.packb({"seq": -1})]
    items: list = [raw("good", msgpack.packb(wire(7)))] + [raw("good", g) for g in garbage * 10]
    items.append(raw("good", None, reject=UnknownRobot("robot 'good' has no configuration")))
    intake.process(items)
    assert [s.seq for s in accepted] == [7]
    assert len(rejected) == 31
    assert all(k == "shapeloc/robots/good/scan" for k, _ in rejected)
    assert "no configuration" in rejected[-1][1]
    assert intake.validated == 1


def test_intake_thread_validates_in_arrival_order_per_robot() -> None:
    accepted: list[ValidScan] = []
    done = threading.Event()

    def accept(s: ValidScan) -> None:
        accepted.append(s)
        if len(accepted) == 20:
            done.set()

    intake = ScanIntake(accept, lambda k, e: None, per_robot=64)
    intake.start()
    try:
        for i in range(10):
            intake.put(raw("a", msgpack.packb(wire(i))))
            intake.put(raw("b", msgpack.packb(wire(100 + i))))
        assert done.wait(10.0)
    finally:
        intake.stop()
    assert [s.seq for s in accepted if s.robot_id == "a"] == list(range(10))
    assert [s.seq for s in accepted if s.robot_id == "b"] == list(range(100, 110))


def test_control_clock() -> None:
    c = ControlClock()
    assert c.next() == 1 and c.next() == 2
    assert not c.wait_applied(1, 0.01)
    threading.Timer(0.05, c.mark_applied, args=(2,)).start()
    assert c.wait_applied(2, 5.0)
    c.mark_applied(1)  # never goes back
    assert c.applied == 2


def test_reject_log_limits_lines_per_window() -> None:
    rl = RejectLog(burst=3, window_s=10.0)
    decisions = [rl.should_log("scan.InvalidMessage", now=float(i)) for i in range(8)]
    assert [d[0] for d in decisions] == [True] * 3 + [False] * 5
    assert rl.should_log("scan.UnknownRobot", now=5.0) == (True, 0)  # kinds are separate
    assert rl.should_log("scan.InvalidMessage", now=10.5) == (True, 5)  # next window: summary
