"""The README's and the guide's robot snippets, run as a user would run them: against a real
service on a free loopback port (the snippets' endpoint replaced by it), with the office map
stored and a simulated laser and odometry standing in for the user's drivers."""

from __future__ import annotations

import contextlib
import io
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from clients.client import ShapelocClient
from sim_publisher.laser import LaserSimulator
from sim_publisher.office import office_metric_map, office_world
from tests.docs_snippets import snippets

pytestmark = pytest.mark.integration

START = np.array([9.4, 1.95, 0.0])  # the pose the snippets configure


def _drivers() -> tuple[dict[str, Any], list[np.ndarray]]:
    """``read_laser`` / ``read_odometry`` for a robot driving 5 cm a scan straight ahead from
    the snippets' initial pose, and the true poses of its scans."""
    laser = LaserSimulator(office_world().segments(), seed=3)
    truth: list[np.ndarray] = []

    def read_laser() -> list[float]:
        pose = START + np.array([0.05 * len(truth), 0.0, 0.0])
        truth.append(pose)
        ranges, _angles = laser.scan(pose, len(truth))
        return ranges.tolist()

    def read_odometry() -> list[float]:
        return truth[-1].tolist()  # odometry frame = map frame, no drift

    return {"read_laser": read_laser, "read_odometry": read_odometry}, truth


@pytest.mark.parametrize("name", ["robot", "client"])
def test_a_documented_robot_is_localised(name: str, tmp_path: Path, spawn_service) -> None:
    page, code = snippets()[name]
    assert "tcp/127.0.0.1:7447" in code, f"{page.name}: the snippet names no endpoint"
    svc = spawn_service(tmp_path / "state")
    with ShapelocClient(svc.endpoint) as client:
        client.put_map(office_metric_map("office"), ready=True)
    namespace, truth = _drivers()
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(
            compile(code.replace("tcp/127.0.0.1:7447", svc.endpoint), str(page), "exec"), namespace
        )
    estimate = namespace["estimate"]
    status = estimate["status"] if isinstance(estimate, dict) else estimate.status
    pose = np.asarray(estimate["pose"] if isinstance(estimate, dict) else estimate.pose)
    assert status == "tracking", out.getvalue()[-500:]
    assert np.hypot(*(pose[:2] - truth[-1][:2])) < 0.1, (pose, truth[-1])
    assert out.getvalue().count("tracking") >= len(truth) - 2, out.getvalue()[-500:]
