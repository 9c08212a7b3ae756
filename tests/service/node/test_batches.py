"""Scans in batches (service/node/scheduler.py, workers.py) with a real worker process: a batch
is one request answered request by request, in order; a worker that dies in a batch is
restarted and every request it did not answer gets an error; the slots hand out up to a
batch of pending robots at once. ~3 s (two worker processes start)."""

from __future__ import annotations

import os
import signal
import threading
from typing import Any

from service.node.scheduler import LatestSlots, WorkerLink
from service.node.workers import ProcessWorker


class _Host:
    """The least a WorkerLink needs from its node."""

    def __init__(self) -> None:
        self.stopping = threading.Event()
        self.clock = None
        self.worker_timeout_s = 30.0
        self.index_timeout_s = 30.0
        self.restarts = 0

    def new_worker(self, index: int) -> ProcessWorker:
        return ProcessWorker(index, log_level="warning")

    def restart_worker(self, link: WorkerLink) -> None:
        self.restarts += 1
        link.worker.close()
        link.worker = self.new_worker(link.index)

    def process_batch(self, link: WorkerLink, scans: list[Any]) -> None:
        raise AssertionError("not used here")


def test_a_batch_is_answered_request_by_request_and_survives_a_dead_worker() -> None:
    host = _Host()
    link = WorkerLink(host, 0, 8, batch=4)
    try:
        got: list[tuple[int, tuple[str, Any]]] = []
        reqs = [("ping",), ("no-such-request",), ("ping",)]
        link.call_batch(reqs, lambda i, r: got.append((i, r)))
        assert [i for i, _ in got] == [0, 1, 2]
        assert got[0][1] == ("ok", "pong") and got[2][1] == ("ok", "pong")
        assert got[1][1][0] == "err"
        pid = link.worker.pid
        assert pid is not None
        os.kill(pid, signal.SIGKILL)
        got.clear()
        link.call_batch(reqs, lambda i, r: got.append((i, r)))
        assert [i for i, _ in got] == [0, 1, 2]
        assert all(r[0] == "err" and "died" in r[1] for _i, r in got)
        assert host.restarts == 1
        assert link.worker.call(("ping",), 30.0) == ("ok", "pong")  # the new one serves
    finally:
        link.worker.close()


def test_slots_hand_out_a_batch_of_pending_robots_oldest_first() -> None:
    s = LatestSlots(capacity=10)
    for rid in ("a", "b", "c", "d"):
        s.offer(rid, rid.upper())
    first = s.take(0.0)
    assert first == ("a", "A")
    assert s.take_more(2) == [("b", "B"), ("c", "C")]
    assert s.take_more(5) == [("d", "D")] and s.take_more(5) == []
