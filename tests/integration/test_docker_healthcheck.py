"""The image's HEALTHCHECK command, run as the container runs it, against a real service.

No Docker engine is needed: the command is read from docker/Dockerfile and run with
``SHAPELOC_CONFIG`` naming a copy of docker/shapeloc.toml whose endpoints point at a service
on a free loopback port instead of ``tcp/router:7447``. Healthy (exit 0) while the service
answers; unhealthy (exit 1, one line) within the check's own timeout once it is gone.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]


def _healthcheck_command() -> list[str]:
    text = (REPO / "docker" / "Dockerfile").read_text().replace("\\\n", " ")
    line = next(ln for ln in text.splitlines() if ln.startswith("HEALTHCHECK "))
    return json.loads(line[line.index("[") : line.rindex("]") + 1])


def test_the_image_healthcheck_follows_the_service(spawn_service, tmp_path: Path) -> None:
    svc = spawn_service(tmp_path / "state", workers=0)
    config = tmp_path / "shapeloc.toml"
    config.write_text(
        (REPO / "docker" / "shapeloc.toml").read_text().replace("tcp/router:7447", svc.endpoint)
    )
    env = dict(os.environ, SHAPELOC_CONFIG=str(config))
    env.pop("RUST_LOG", None)
    cmd = _healthcheck_command()
    assert cmd[0] == "shapeloc"
    # the console script is what the image runs; the module is the same code
    argv = [str(REPO / ".venv" / "bin" / "shapeloc"), *cmd[1:]]
    if not Path(argv[0]).exists():
        argv = [sys.executable, "-m", "clients", *cmd[1:]]
    ok = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=30)
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.startswith("ok: shapeloc ")
    svc.kill()
    t0 = time.monotonic()
    bad = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=30)
    took = time.monotonic() - t0
    assert bad.returncode == 1
    err = bad.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("shapeloc: error: "), bad.stderr
    assert took < 10.0  # within the HEALTHCHECK's --timeout=10s
