"""Shared fixtures of the integration tests: real service processes on loopback.

* ``free_port()`` / ``free_endpoint()``: an unused ``tcp/127.0.0.1:PORT`` (bind to port 0).
* ``spawn_service(state_dir, *args, workers=1, endpoint=None)``: start
  ``python -m service --listen <endpoint> --state-dir <state_dir> ...`` and wait until it
  answers ``get shapeloc/service/health``; returns a :class:`ServiceProc`. Every spawned
  process is killed at teardown.
* ``open_session(endpoint, extra=None)``: a loopback-only Zenoh *client* session connected to
  ``endpoint`` (multicast scouting off; ``extra`` maps config paths to values, e.g. TLS or
  user/password); closed at teardown.
* ``spawn_router(endpoint)``: a Zenoh router (a Python session in router mode) listening on
  ``endpoint``; ``RouterProc.kill()`` / ``restart()``. Killed at teardown.
* ``lockstep_sim(svc, sim_args, scans)``: run one simulated robot in lockstep against a
  spawned service and return its pose messages and true poses by ``seq``.

Zenoh is never used with its default peer configuration here.
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
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import zenoh

REPO = Path(__file__).resolve().parents[2]
PREFIX = "shapeloc"
STARTUP_TIMEOUT_S = 60.0


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
    conf.insert_json5("scouting/delay", "0")
    for path, value in (extra or {}).items():
        conf.insert_json5(path, json.dumps(value))
    return conf


def get_health(session: zenoh.Session, prefix: str = PREFIX, timeout_s: float = 2.0) -> Any:
    """The decoded Health reply of the (first) service, or ``None`` if none answered."""
    from schemas.codec import decode
    from schemas.messages import Health

    for reply in session.get(f"{prefix}/service/health", timeout=timeout_s):
        if reply.ok is not None:
            return decode(Health, reply.ok.payload.to_bytes(), str(reply.ok.encoding))
    return None


@dataclass
class ServiceProc:
    """A running ``python -m service`` child process."""

    proc: subprocess.Popen[bytes]
    endpoint: str
    state_dir: Path
    log_path: Path
    args: tuple[str, ...] = field(default_factory=tuple)

    @property
    def port(self) -> int:
        """TCP port the service listens on."""
        return int(self.endpoint.rsplit(":", 1)[1])

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


def _start(state_dir: Path, args: tuple[str, ...], endpoint: str, workers: int) -> ServiceProc:
    state_dir = Path(state_dir)
    log_path = state_dir.parent / f"service-{state_dir.name}-{free_port()}.log"
    cmd = [
        sys.executable,
        "-m",
        "service",
        "--listen",
        endpoint,
        "--state-dir",
        str(state_dir),
        "--workers",
        str(workers),
        *args,
    ]
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("RUST_LOG", None)
    with open(log_path, "ab") as logf:
        proc = subprocess.Popen(
            cmd, cwd=REPO, stdout=logf, stderr=subprocess.STDOUT, env=env, start_new_session=True
        )
    return ServiceProc(proc, endpoint, state_dir, log_path, tuple(args))


def wait_ready(
    svc: ServiceProc,
    timeout_s: float = STARTUP_TIMEOUT_S,
    prefix: str = PREFIX,
    via: str | None = None,
    extra: dict[str, Any] | None = None,
) -> Any:
    """Poll health until the service answers (through ``via``, default the service's own
    endpoint, with client config ``extra``); fail with its log if it exits or times out."""
    deadline = time.monotonic() + timeout_s
    session = None
    try:
        while time.monotonic() < deadline:
            if svc.proc.poll() is not None:
                raise AssertionError(
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
    raise AssertionError(f"service not healthy after {timeout_s} s:\n{svc.log()}")


@pytest.fixture
def spawn_service() -> Iterator[Callable[..., ServiceProc]]:
    """Factory: ``spawn_service(state_dir, *args, workers=1, endpoint=None, wait=True,
    via=None, extra=None)`` (``via``/``extra``: where and how the readiness check connects,
    e.g. a router's endpoint for a client-mode service, or TLS settings)."""
    procs: list[ServiceProc] = []

    def spawn(
        state_dir: Path | str,
        *args: str,
        workers: int = 1,
        endpoint: str | None = None,
        wait: bool = True,
        via: str | None = None,
        extra: dict[str, Any] | None = None,
    ) -> ServiceProc:
        svc = _start(Path(state_dir), tuple(args), endpoint or free_endpoint(), workers)
        procs.append(svc)
        if wait:
            wait_ready(svc, prefix=_prefix_of(args), via=via, extra=extra)
        return svc

    yield spawn
    for svc in procs:
        svc.kill()


def _prefix_of(args: tuple[str, ...]) -> str:
    if "--prefix" in args:
        i = args.index("--prefix")
        if i + 1 < len(args):
            return args[i + 1]
    return PREFIX


@pytest.fixture
def open_session() -> Iterator[Callable[..., zenoh.Session]]:
    """Factory: ``open_session(endpoint, extra=None)`` -> client session, closed at
    teardown."""
    sessions: list[zenoh.Session] = []

    def opener(endpoint: str, extra: dict[str, Any] | None = None) -> zenoh.Session:
        s = zenoh.open(client_config(endpoint, extra))
        sessions.append(s)
        return s

    yield opener
    for s in reversed(sessions):
        with contextlib.suppress(Exception):
            s.close()


@pytest.fixture
def service_health() -> Callable[..., Any]:
    """``service_health(session, prefix="shapeloc", timeout_s=2.0)`` -> Health or ``None``.

    (Test modules cannot import this conftest under ``--import-mode=importlib``.)"""
    return get_health


def _sim_env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("RUST_LOG", None)
    return env


def run_lockstep_sim(
    svc: ServiceProc, sim_args: list[str], scans: int, robot: str = "sim-0"
) -> tuple[dict[int, Any], dict[int, Any]]:
    """Run ``python -m sim_publisher run --connect <svc> --robots 1 --scans <scans> --max-rate
    --lockstep <sim_args>`` to completion and return what came back over Zenoh for
    ``robot``: its pose messages and its true poses (numpy ``(3,)``), each by ``seq``."""
    import numpy as np

    from clients.client import ShapelocClient

    with ShapelocClient(svc.endpoint, timeout=5.0) as client:
        poses = client.watch_poses([robot])
        truths = client.watch_truth([robot])
        sim = subprocess.run(
            [
                sys.executable,
                "-m",
                "sim_publisher",
                "run",
                "--connect",
                svc.endpoint,
                "--robots",
                "1",
                "--scans",
                str(scans),
                "--max-rate",
                "--lockstep",
                *sim_args,
            ],
            cwd=REPO,
            env=_sim_env(),
            capture_output=True,
            text=True,
            timeout=200,
        )
        assert sim.returncode == 0, sim.stderr
        assert "lockstep: no pose" not in sim.stderr, sim.stderr
        time.sleep(0.5)
        est = {p.seq: p for _, p in poses.drain()}
        truth = {t.seq: np.asarray(t.pose) for _, t in truths.drain()}
    return est, truth


@pytest.fixture
def lockstep_sim() -> Callable[..., tuple[dict[int, Any], dict[int, Any]]]:
    """``lockstep_sim(svc, sim_args, scans, robot="sim-0")`` -> (poses by seq, truths by seq):
    one simulated robot driven in lockstep against a spawned service (see
    :func:`run_lockstep_sim`)."""
    return run_lockstep_sim


# A Zenoh router for the fault tests: a Python session in router mode (the compose file's
# zenohd is the production form). Prints "ready" once listening; SIGTERM closes it.
_ROUTER_CODE = """
import json, signal, sys, threading, zenoh
conf = zenoh.Config()
conf.insert_json5("mode", '"router"')
conf.insert_json5("listen/endpoints", json.dumps([sys.argv[1]]))
conf.insert_json5("scouting/multicast/enabled", "false")
conf.insert_json5("scouting/delay", "0")
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
            env=_sim_env(),
            start_new_session=True,
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # "ready", or b"" if it exited
        if line.strip() != b"ready":
            raise AssertionError(f"router on {self.endpoint} did not start: {line!r}")

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


@pytest.fixture
def spawn_router() -> Iterator[Callable[[str], RouterProc]]:
    """Factory: ``spawn_router(endpoint)`` -> a started :class:`RouterProc`."""
    routers: list[RouterProc] = []

    def spawn(endpoint: str) -> RouterProc:
        r = RouterProc(endpoint)
        routers.append(r)
        r.start()
        return r

    yield spawn
    for r in routers:
        r.kill()
