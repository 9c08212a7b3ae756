"""The loopback Zenoh side of the service scale benchmark (``bench/bench_service.py``).

Client sessions to the service on a loopback endpoint (:func:`free_endpoint` and
:func:`client_config` of :mod:`bench.harness`, :func:`health`); the load generator: the
msgpack scans (:func:`scan_payload`) and the publisher process sending every robot's scans
on schedule (:func:`publisher_main`, run in a ``spawn`` child, so it lives in this importable
module); the :class:`Receiver` collecting every pose and re-configuring searching robots on a
fix; and the CPU accounting of a process tree from /proc (:func:`tree_cpu_s`).

Run from the repository root as part of the ``bench`` package
(``python -m bench.bench_service``).
"""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import threading
import time
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

from bench.harness import client_config, get_health
from schemas.codec import encode
from schemas.messages import Health, RobotConfig

P = "shapeloc"
MSGPACK = "application/msgpack"


def health(session: zenoh.Session, timeout: float = 2.0) -> Health | None:
    """The service's Health, or None (no answer within ``timeout`` s)."""
    return get_health(session, P, timeout)


def scan_payload(info: dict[str, float], seq: int, ranges: bytes, odom: np.ndarray | None) -> bytes:
    """A msgpack Scan (``stamp`` = now)."""
    msg: dict[str, Any] = {
        "seq": seq,
        "stamp": time.time(),
        "angle_min": info["angle_min"],
        "angle_increment": info["angle_increment"],
        "range_min": info["range_min"],
        "range_max": info["range_max"],
        "ranges": ranges,
    }
    if odom is not None:
        msg["odom"] = [float(v) for v in odom]
    return msgpack.packb(msg)


def publisher_main(
    endpoint: str,
    robots: list[str],
    walks: list[np.ndarray],
    odoms: list[np.ndarray | None],
    mirrored: list[bool],
    ranges: list[bytes],
    ranges_mirrored: list[bytes],
    info: dict[str, float],
    rate: float,
    count: int,
    ctl: Any,
    out: Any,
) -> None:
    """Child process: once its publishers are declared it puts ``"ready"`` on ``out`` and
    gets ``t0`` from ``ctl``; robot ``i`` sends seq ``k`` (1 .. count-1) at ``t0 + (k-1)/rate
    + i/(rate*n)``. Puts ``(scans sent, send lag p99 ms, max lag ms)`` on ``out`` at the end."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    n = len(robots)
    enc = zenoh.Encoding(MSGPACK)
    lags = []
    sent = 0
    with zenoh.open(client_config(endpoint)) as s:
        pubs = [s.declare_publisher(f"{P}/robots/{r}/scan", encoding=enc) for r in robots]
        out.put("ready")
        t0 = ctl.get()
        for k in range(1, count):
            for i in range(n):
                t_send = t0 + (k - 1) / rate + i / (rate * n)
                dt_ = t_send - time.time()
                if dt_ > 0:
                    time.sleep(dt_)
                lags.append(time.time() - t_send)
                pool = ranges_mirrored if mirrored[i] else ranges
                o = odoms[i]
                pubs[i].put(
                    scan_payload(info, k, pool[int(walks[i][k])], None if o is None else o[k])
                )
                sent += 1
    lag = np.asarray(lags) * 1e3
    out.put((sent, float(np.percentile(lag, 99)) if lag.size else 0.0, float(lag.max(initial=0))))


class Receiver:
    """Collects every pose: (robot, seq, stamp, receipt time, pose, status). Robots in
    :attr:`refix` are re-configured with a null pose (by a helper thread) when they report
    ``tracking``: :attr:`fixes` keeps (robot, seq, pose) of those fixes."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.lock = threading.Lock()
        self.rows: list[tuple[str, int, float, float, list[float], str]] = []
        self.refix: dict[str, str] = {}  # robot -> map id
        self.method = "shape"
        self.fixes: list[tuple[str, int, list[float]]] = []
        self._last_put: dict[str, float] = {}
        self._q: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        self._thread = threading.Thread(target=self._refixer, daemon=True)
        self._thread.start()
        self.sub = session.declare_subscriber(f"{P}/robots/*/pose", self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        t = time.time()
        m = msgpack.unpackb(sample.payload.to_bytes())
        row = (m["robot_id"], m["seq"], m["stamp"], t, m["pose"], m["status"])
        with self.lock:
            self.rows.append(row)
            if m["status"] == "tracking" and m["robot_id"] in self.refix:
                self.fixes.append((m["robot_id"], m["seq"], m["pose"]))
                self._q.put(m["robot_id"])

    def _refixer(self) -> None:
        while True:
            rid = self._q.get()
            if rid is None:
                return
            with self.lock:
                map_id = self.refix.get(rid)
            now = time.monotonic()
            if map_id is None or now - self._last_put.get(rid, -1e9) < 0.5:
                continue  # one re-put per fix (the poses in flight report it too)
            self._last_put[rid] = now
            cfg = RobotConfig(map_id=map_id, method=self.method, initial_pose=None)
            with contextlib.suppress(zenoh.ZError):
                self.session.put(f"{P}/robots/{rid}/config", encode(cfg), encoding=MSGPACK)

    def take(self) -> tuple[list[tuple[str, int, float, float, list[float], str]], list]:
        with self.lock:
            rows, self.rows = self.rows, []
            fixes, self.fixes = self.fixes, []
        return rows, fixes

    def close(self) -> None:
        self._q.put(None)


# --------------------------------------------------------------------------- CPU accounting


def _proc_ticks(pid: int) -> tuple[int, int] | None:
    """(ppid, utime + stime clock ticks) of a process, from /proc (None if gone)."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            raw = f.read().decode()
    except OSError:
        return None
    fields = raw[raw.rfind(")") + 2 :].split()
    return int(fields[1]), int(fields[11]) + int(fields[12])


def tree_cpu_s(root: int) -> float:
    """CPU seconds (user + system) of ``root`` and its descendants (Linux /proc; 0 elsewhere)."""
    if not Path("/proc").is_dir():
        return 0.0
    table = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            got = _proc_ticks(int(d))
            if got is not None:
                table[int(d)] = got
    keep = {root}
    grew = True
    while grew:
        grew = False
        for pid, (ppid, _t) in table.items():
            if ppid in keep and pid not in keep:
                keep.add(pid)
                grew = True
    ticks = sum(table[p][1] for p in keep if p in table)
    return ticks / os.sysconf("SC_CLK_TCK")
