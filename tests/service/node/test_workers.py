"""service.node.workers: a worker process's start-up is not charged to its first request, a hung
or slow one times out, and the assignment of robots to workers balances and sticks."""

from __future__ import annotations

import os
import signal

import pytest

from service.errors import ServiceTimeout
from service.node.assignment import Assignment, shard_of
from service.node.workers import ProcessWorker


def test_a_starting_worker_is_not_killed_by_the_request_timeout() -> None:
    # A new interpreter plus the imports take far longer than 50 ms; the first request's
    # timeout must only start once the child says it is ready.
    w = ProcessWorker(0, log_level="warning")
    try:
        assert w.call(("ping",), timeout_s=0.05) == ("ok", "pong")
        assert w.call(("ping",), timeout_s=5.0) == ("ok", "pong")
        assert w.alive()
    finally:
        w.close()


def test_a_worker_that_does_not_start_in_time_is_killed() -> None:
    w = ProcessWorker(0, log_level="warning", start_timeout_s=0.001)
    try:
        with pytest.raises(ServiceTimeout, match="did not start within"):
            w.call(("ping",), timeout_s=30.0)
        assert not w.alive()
    finally:
        w.close()


def test_a_hung_request_times_out_as_a_timeout_not_as_a_death() -> None:
    w = ProcessWorker(0, log_level="warning")
    try:
        w.wait_ready()
        assert w.pid is not None
        os.kill(w.pid, signal.SIGSTOP)  # hung: it cannot answer
        with pytest.raises(ServiceTimeout, match="took longer than"):
            w.call(("ping",), timeout_s=0.2)
        assert not w.alive()
    finally:
        w.close()


def test_assignment_balances_and_sticks() -> None:
    a = Assignment(2)
    assert [a.assign(f"b2-{i}") for i in range(2)] == [0, 1]  # hashing put both on 1
    assert [a.assign(r) for r in ("x", "y", "z")] == [0, 1, 0]
    assert a.assign("b2-1") == 1 and a.load() == [3, 2]  # sticky
    a.release("x")
    a.release("x")
    assert a.load() == [2, 2]
    assert a.assign("w") == 0
    assert a.index_of("never-configured") == shard_of("never-configured", 2)
    assert shard_of("r", 3) == shard_of("r", 3) and 0 <= shard_of("r", 3) < 3
