"""Shared fixtures of the integration tests: real service processes on loopback.

The processes themselves are :mod:`bench.harness`'s (one copy for the tests and the
benchmarks); the fixtures here clean them up at teardown:

* ``spawn_service(state_dir, *args, workers=1, endpoint=None)``: start
  ``python -m service --listen <endpoint> --state-dir <state_dir> ...`` and wait until it
  answers ``get shapeloc/service/health``; returns a :class:`bench.harness.ServiceProc`. Every
  spawned process is killed at teardown.
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
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from bench.harness import (
    PREFIX,
    REPO,
    RouterProc,
    ServiceProc,
    client_config,
    get_health,
    project_env,
    start_service,
    wait_ready,
)


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
        svc = start_service(Path(state_dir), *args, endpoint=endpoint, workers=workers)
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
            env=project_env(),
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
