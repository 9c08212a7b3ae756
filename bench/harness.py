"""Real processes on loopback, for the benchmarks and the integration tests (one copy for both).

* :func:`free_port` / :func:`free_endpoint`: an unused ``tcp/127.0.0.1:PORT`` (bind to port 0).
* :func:`client_config`: a loopback-only Zenoh *client* configuration (multicast scouting off,
  an explicit endpoint; ``extra`` adds TLS or user/password settings).
* :func:`get_health`: the decoded ``Health`` of the (first) service that answers.
* :func:`start_service` / :class:`ServiceProc`: ``python -m service --listen <endpoint>
  --state-dir <dir> --workers N ...`` in its own process group, output in a log file;
  :func:`wait_ready` polls its health until it answers (raising with its log if it exits or
  does not answer in time).
* :class:`RouterProc`: a Zenoh router (a Python session in router mode) on an endpoint.
* :func:`project_env`: the environment for a child process of the project (the repository on
  ``PYTHONPATH``, no ``RUST_LOG``).

Why here: ``bench/`` is the top of the project's layers (it may import every package; none
imports it) and is not installed with the package, which suits support code for measuring
and testing; the tests (``tests/integration/conftest.py``) import it with the repository root
on ``sys.path`` (``pythonpath`` in pyproject.toml's pytest options), and the benchmarks run as
``python -m bench.<name>`` from the repository root.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from schemas.codec import decode
from schemas.messages import Health

REPO = Path(__file__).resolve().parents[1]
PREFIX = "shapeloc"
#: Seconds a spawned service may take to answer its first health query.
STARTUP_TIMEOUT_S = 60.0


class ServiceStartError(RuntimeError):
    """A spawned service exited or did not answer in time; the message holds its log."""


def free_port() -> int:
    """A TCP port on 127.0.0.1 that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_endpoint() -> str:
    """``tcp/127.0.0.1:<free port>``."""
    return f"tcp/127.0.0.1:{free_port()}"


def client_config(endpoint: str, extra: dict[str, Any] | None = None) -> zenoh.Config:
    """Loopback-only client configuration connecting to ``endpoint``; ``extra`` maps Zenoh
    config paths (``transport/link/tls/root_ca_certificate``, ...) to JSON values."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    for path, value in (extra or {}).items():
        conf.insert_json5(path, json.dumps(value))
    return conf


def get_health(
    session: zenoh.Session, prefix: str = PREFIX, timeout_s: float = 2.0
) -> Health | None:
    """The decoded Health reply of the (first) service, or ``None`` if none answered."""
    for reply in session.get(f"{prefix}/service/health", timeout=timeout_s):
        if reply.ok is not None:
            return decode(Health, reply.ok.payload.to_bytes(), str(reply.ok.encoding))
    return None


def exit_on_sigterm() -> None:
    """Make SIGTERM end this process the way Ctrl-C does (``SystemExit`` in the main thread),
    so that the ``finally`` blocks which stop the services a benchmark started still run; by
    default a SIGTERM ends the process at once and leaves them running."""

    def stop(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)


def machine_probe_ms(repeats: int = 3) -> float:
    """Wall milliseconds of a fixed CPU workload (a Python loop and a numpy sort, one thread;
    the fastest of ``repeats``): how much CPU this machine gives right now. On the project's
    2-vCPU machine it is ~12 ms when quiet (27 ms beside two busy processes); a timing
    benchmark reports it beside each run, because the same commit's latencies there move
    with it (another tenant of the host, or other work on the machine)."""
    import numpy as np

    data = np.random.default_rng(0).random(200_000)
    best = float("inf")
    for _ in range(max(1, repeats)):
        t0 = time.perf_counter()
        acc = 0.0
        for k in range(100_000):
            acc += (k % 7) * 0.5
        np.sort(data)
        best = min(best, time.perf_counter() - t0)
    return 1000.0 * best


def project_env() -> dict[str, str]:
    """This process's environment with the repository first on ``PYTHONPATH`` and without
    ``RUST_LOG`` (Zenoh's log level), for child processes of the project."""
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("RUST_LOG", None)
    return env


@dataclass
class ServiceProc:
    """A running ``python -m service`` child process (its own process group)."""

    proc: subprocess.Popen[bytes]
    endpoint: str
    state_dir: Path
    log_path: Path
    args: tuple[str, ...] = field(default_factory=tuple)

    @property
    def port(self) -> int:
        """TCP port the service listens on."""
        return int(self.endpoint.rsplit(":", 1)[1])

    @property
    def pid(self) -> int:
        """The service process's id."""
        return self.proc.pid

    def log(self) -> str:
        """Everything the process wrote so far (stdout and stderr)."""
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def kill(self) -> None:
        """SIGKILL the service and its workers (its own process group) and reap it."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=10)

    def terminate(self, timeout_s: float = 30.0) -> int:
        """SIGTERM, wait for a clean exit, return the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        return self.proc.wait(timeout=timeout_s)

    def stop(self, timeout_s: float = 20.0) -> None:
        """SIGTERM; SIGKILL the process group if it has not exited after ``timeout_s``."""
        try:
            self.terminate(timeout_s)
        except subprocess.TimeoutExpired:
            self.kill()


def start_service(
    state_dir: Path | str,
    *args: str,
    endpoint: str | None = None,
    workers: int | None = 1,
    log_path: Path | None = None,
) -> ServiceProc:
    """Start ``python -m service --listen <endpoint> --state-dir <state_dir> [--workers N]
    <args>`` (``endpoint`` default: a free one; ``workers`` ``None``: the service's default)
    with its output appended to ``log_path`` (default: beside the state directory). Returns at
    once; see :func:`wait_ready`."""
    state_dir = Path(state_dir)
    endpoint = endpoint or free_endpoint()
    if log_path is None:
        log_path = state_dir.parent / f"service-{state_dir.name}-{free_port()}.log"
    cmd = [sys.executable, "-m", "service", "--listen", endpoint, "--state-dir", str(state_dir)]
    if workers is not None:
        cmd += ["--workers", str(workers)]
    cmd += list(args)
    with open(log_path, "ab") as logf:
        proc = subprocess.Popen(
            cmd,
            cwd=REPO,
            stdout=logf,
            stderr=subprocess.STDOUT,
            env=project_env(),
            start_new_session=True,
        )
    return ServiceProc(proc, endpoint, state_dir, log_path, tuple(args))


def wait_ready(
    svc: ServiceProc,
    timeout_s: float = STARTUP_TIMEOUT_S,
    prefix: str = PREFIX,
    via: str | None = None,
    extra: dict[str, Any] | None = None,
) -> Health:
    """Poll health until the service answers (through ``via``, default the service's own
    endpoint, with client config ``extra``); raise :class:`ServiceStartError` with its log if
    it exits or does not answer within ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    session = None
    try:
        while time.monotonic() < deadline:
            if svc.proc.poll() is not None:
                raise ServiceStartError(
                    f"service exited with {svc.proc.returncode} during start-up:\n{svc.log()}"
                )
            if session is None:
                try:
                    session = zenoh.open(client_config(via or svc.endpoint, extra))
                except zenoh.ZError:
                    time.sleep(0.2)
                    continue
            h = get_health(session, prefix, timeout_s=1.0)
            if h is not None:
                return h
            time.sleep(0.1)
    finally:
        if session is not None:
            session.close()
    raise ServiceStartError(f"service not healthy after {timeout_s} s:\n{svc.log()}")


# A Zenoh router for tests and benchmarks: a Python session in router mode (the compose file's
# zenohd is the production form). Prints "ready" once listening; SIGTERM closes it.
_ROUTER_CODE = """
import json, signal, sys, threading, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"router"')
conf.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
conf.insert_json5("scouting/multicast/enabled", "false")
stop = threading.Event()
signal.signal(signal.SIGTERM, lambda *a: stop.set())
with zenoh.open(conf):
    print("ready", flush=True)
    stop.wait()
"""


@dataclass
class RouterProc:
    """A running Zenoh router process on ``endpoint``."""

    endpoint: str
    proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        """Start it and wait until it listens (it prints "ready")."""
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _ROUTER_CODE, self.endpoint],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            env=project_env(),
            start_new_session=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # "ready", or b"" if it exited
        if line.strip() != b"ready":
            raise RuntimeError(f"router on {self.endpoint} did not start: {line!r}")

    def kill(self) -> None:
        """SIGKILL (no goodbye on the links) and reap."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
        if self.proc is not None:
            self.proc.wait(timeout=10)

    def restart(self) -> None:
        """Kill, then start again on the same endpoint."""
        self.kill()
        self.start()
