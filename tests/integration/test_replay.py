"""``shapeloc-sim replay`` end to end: a real service process, the replay as a real process,
the fr079 excerpt (tests/data/real, first 300 scans) in lockstep against a map built from the
same scans at their reference poses."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from clients.client import ShapelocClient
from service.adapters.logs import attach_reference, load_reference, read_log
from service.core.pose import relative

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data" / "real"
BAG = DATA / "fr079.300.bag"
REFERENCE = DATA / "fr079.300.gfs_reference_per_scan.txt"
MAP = DATA / "fr079.300.map.json"
#: Largest distance (m) of a pose from the flag-1 reference.
TOLERANCE_M = 0.3


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("RUST_LOG", None)
    return env


def test_replay_fr079_excerpt_in_lockstep(spawn_service, tmp_path: Path) -> None:
    svc = spawn_service(tmp_path / "state")
    scans = list(attach_reference(read_log(BAG)[1], load_reference(REFERENCE)))
    with ShapelocClient(svc.endpoint, timeout=5.0) as client:
        client.put_map(MAP, confirm=True)
        poses = client.watch_poses(["fr079"])
        truths = client.watch_truth(["fr079"])
        t0 = time.monotonic()
        replay = subprocess.run(
            [
                sys.executable,
                "-m",
                "sim_publisher",
                "replay",
                str(BAG),
                "--robot",
                "fr079",
                "--map",
                "fr079-300",
                "--reference",
                str(REFERENCE),
                "--rate",
                "max",
                "--lockstep",
                "--connect",
                svc.endpoint,
            ],
            cwd=REPO,
            env=_env(),
            capture_output=True,
            text=True,
            timeout=250,
        )
        elapsed = time.monotonic() - t0
        assert replay.returncode == 0, replay.stderr
        assert "lockstep: no pose" not in replay.stderr, replay.stderr
        # the progress line's final state
        assert "replay fr079.300.bag: 300/300 scans (100 %)" in replay.stderr, replay.stderr
        time.sleep(0.5)
        est = {p.seq: p for _, p in poses.drain()}
        truth = {t.seq: np.asarray(t.pose) for _, t in truths.drain()}
    print(f"replay of 300 scans in lockstep: {elapsed:.1f} s")
    # every scan was answered, for the scan it answers (seq and stamp as sent)
    assert sorted(est) == list(range(300))
    assert all(est[s.index].stamp == pytest.approx(s.stamp, abs=1e-6) for s in scans)
    # the truth key carries exactly the flag-1 references
    flag1 = {s.index: s.reference for s in scans if s.reference_ok}
    assert sorted(truth) == sorted(flag1) and len(truth) == 292
    # (theta compared on the circle: the wire wraps angles to (-pi, pi])
    assert all(np.allclose(relative(flag1[k], truth[k]), 0.0, atol=1e-9) for k in flag1)
    errors = np.array([np.hypot(*(est[k].pose[:2] - flag1[k][:2])) for k in flag1])
    worst = int(np.argmax(errors))
    print(
        f"flag-1 errors: median {np.median(errors):.3f} m, max {errors.max():.3f} m "
        f"({len(errors)} scans)"
    )
    assert errors.max() <= TOLERANCE_M, (
        f"{int((errors > TOLERANCE_M).sum())} of {len(errors)} flag-1 scans beyond "
        f"{TOLERANCE_M} m; worst {errors[worst]:.3f} m; median {np.median(errors):.3f} m"
    )
    # headings agree too (same frame: the laser's)
    dth = [abs(relative(flag1[k], est[k].pose)[2]) for k in flag1]
    assert max(dth) < 0.1
