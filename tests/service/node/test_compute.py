"""The compute side of the node (service/node/compute.py) without a network: a killed worker
process is restarted with the maps and configs replayed, and a valid scan waiting in its
robot's latest-wins slot while the worker is busy is neither displaced by invalid payloads on
the same key nor kept from being replaced by a newer valid scan. A fake Zenoh session
(tests/service/node/harness.py), ICP on a small room."""

from __future__ import annotations

import threading
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from tests.service.node.harness import START, Harness, wait_for, wait_notices


def test_worker_process_crash_is_survived(tmp_path: Path) -> None:
    """A killed worker process costs one scan (with a notice); it is restarted with the maps
    and configs replayed, and the robot keeps tracking from its last pose. ~2 s (spawn)."""
    import os
    import signal

    h = Harness(tmp_path, workers=1)
    try:
        h.put_map()
        h.put_config()
        h.put_scan("r1", 0, START)
        wait_for(lambda: len(h.poses()) == 1)
        link = h.node.links[0]
        old_pid = link.worker.pid  # type: ignore[union-attr]
        assert old_pid is not None and old_pid != os.getpid()
        os.kill(old_pid, signal.SIGKILL)
        h.put_scan("r1", 1, START)
        notes = wait_notices(h, 1)
        assert "died" in notes[-1].error
        assert link.worker.pid != old_pid  # type: ignore[union-attr]
        p = START + np.array([0.02, 0.0, 0.0])
        h.put_scan("r1", 2, p)
        wait_for(lambda: len(h.poses()) == 2)
        assert h.poses()[-1].seq == 2
        assert np.linalg.norm(h.poses()[-1].pose[:2] - p[:2]) < 0.05
    finally:
        h.node.stop()


class GatedWorker:
    """Wraps the in-process worker: scan requests wait for ``gate`` (a busy worker)."""

    def __init__(self, inner: Any) -> None:
        self.inner = inner
        self.core = inner.core
        self.gate = threading.Event()
        self.entered = threading.Event()

    def call(self, req: tuple[Any, ...], timeout_s: float | None = None) -> tuple[str, Any]:
        if req[0] == "scan":
            self.entered.set()
            assert self.gate.wait(20.0)
        return self.inner.call(req, timeout_s)

    def close(self) -> None:
        self.inner.close()


def test_garbage_on_a_busy_robots_key_never_displaces_its_valid_scan(harness: Harness) -> None:
    """While the robot's worker is busy, one valid scan waits in its latest-wins slot; 30
    invalid payloads on the same key are rejected on arrival (with notices) and the valid
    scan is still the one computed next. A newer valid scan does replace it (latest wins)."""
    h = harness
    h.put_map()
    h.put_config()
    gated = GatedWorker(h.node.links[0].worker)
    h.node.links[0].worker = gated  # type: ignore[assignment]
    h.put_scan("r1", 0, START)
    assert gated.entered.wait(10.0)
    h.put_scan("r1", 1, START)
    good = h.scan_msg(2, START)
    garbage = [
        b"\xc1 not msgpack",
        msgpack.packb({**good, "seq": "two"}),
        msgpack.packb({**good, "ranges": "lots"}),
    ]
    for g in garbage * 10:
        h.put("shapeloc/robots/r1/scan", g)
    # every rejection is counted; each gets a notice unless the burst overflowed the robot's
    # backlog (16 samples here), where the surplus is counted only (one summary notice)
    wait_for(lambda: h.health().scans_rejected == 30)
    dropped = h.node.intake.queue.notices_dropped
    notes = wait_notices(h, 30 - dropped)
    per_scan = [n for n in notes if n.key == "shapeloc/robots/r1/scan"]
    assert len(per_scan) == 30 - dropped
    assert all("InvalidMessage" in n.error for n in per_scan)
    assert (h.health().errors or {}).get("scan.InvalidMessage") == 30
    assert "scan.Skipped" not in (h.health().errors or {})
    gated.gate.set()
    wait_for(lambda: len(h.poses()) == 2)
    assert [p.seq for p in h.poses()] == [0, 1]
    hl = h.health()
    assert (hl.scans_processed, hl.scans_rejected) == (2, 30)
    # valid replaces valid: the older of two pending valid scans is skipped
    gated.gate.clear()
    gated.entered.clear()
    h.put_scan("r1", 2, START)
    assert gated.entered.wait(10.0)
    h.put_scan("r1", 3, START)
    h.put_scan("r1", 4, START)
    wait_for(lambda: (h.health().errors or {}).get("scan.Skipped") == 1)
    gated.gate.set()
    wait_for(lambda: len(h.poses()) == 4)
    assert [p.seq for p in h.poses()] == [0, 1, 2, 4]
