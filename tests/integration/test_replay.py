"""``shapeloc-sim replay`` end to end: a real service process, the replay as a real process,
the fr079 excerpt (tests/data/real, first 300 scans) against a map built from the same scans at
their reference poses: the accuracy summary, a refused configuration, a missing map, and the
same log replayed as a robot base carrying its laser at a known offset."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from clients.client import ShapelocClient
from service.adapters.logs import attach_reference, load_reference, read_log
from service.core.mounting import to_base
from service.core.pose import relative

pytestmark = pytest.mark.integration

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data" / "real"
BAG = DATA / "fr079.300.bag"
REFERENCE = DATA / "fr079.300.gfs_reference_per_scan.txt"
RELATIONS = DATA / "fr079.300.relations"
MAP = DATA / "fr079.300.map.json"
#: Largest distance (m) of a pose from the flag-1 reference.
TOLERANCE_M = 0.3
#: The laser 0.3 m forward, 0.1 m left, turned 0.2 rad on the replayed robot's base.
OFFSET = (0.3, 0.1, 0.2)


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("RUST_LOG", None)
    env.pop("SHAPELOC_CONFIG", None)
    return env


def _replay(endpoint: str, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "sim_publisher", "replay", str(BAG), "--connect", endpoint, *args],
        cwd=REPO,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def _lockstep(endpoint: str, *args: str) -> subprocess.CompletedProcess:
    return _replay(
        endpoint,
        "--robot",
        "fr079",
        "--map",
        "fr079-300",
        "--reference",
        str(REFERENCE),
        "--speed",
        "max",
        "--lockstep",
        "--no-progress",
        *args,
    )


def test_replay_fr079_excerpt_in_lockstep_with_an_accuracy_summary(
    spawn_service, tmp_path: Path
) -> None:
    svc = spawn_service(tmp_path / "state")
    scans = list(attach_reference(read_log(BAG)[1], load_reference(REFERENCE)))
    with ShapelocClient(svc.endpoint, timeout=5.0) as client:
        client.put_map(MAP, confirm=True)
        poses = client.watch_poses(["fr079"])
        truths = client.watch_truth(["fr079"])
        t0 = time.monotonic()
        replay = _lockstep(svc.endpoint, "--relations", str(RELATIONS), "--json")
        elapsed = time.monotonic() - t0
        assert replay.returncode == 0, replay.stderr
        assert "lockstep: no pose" not in replay.stderr, replay.stderr
        assert "warning" not in replay.stderr, replay.stderr  # nothing deprecated used
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
    # the summary on stdout says the same as what came over Zenoh
    summary = json.loads(replay.stdout)
    print("summary:", summary)
    assert summary["scans"] == 300 and summary["poses"] == 300 and summary["rejected"] == 0
    ref = summary["reference"]
    assert ref["scans"] == 292 and ref["answered"] == 292
    assert ref["within_0.3_m"] == pytest.approx(float(np.mean(errors <= 0.3)))
    assert ref["within_0.1_m"] == pytest.approx(float(np.mean(errors <= 0.1)))
    assert ref["error_max_m"] == pytest.approx(float(errors.max()), abs=1e-9)
    rel = summary["relations"]
    assert rel["used"] == 64 and rel["skipped"] == 0 and rel["translation_mean_m"] < 0.1


def test_replay_as_a_base_with_a_mounted_laser_gives_the_same_accuracy(
    spawn_service, tmp_path: Path
) -> None:
    """The log replayed as a robot base carrying the laser 0.3 m forward, 0.1 m left and
    turned 0.2 rad: odometry and truth go out as the base's, the configuration carries the
    offset, and the poses that come back are the base's, as accurate as the laser's."""
    svc = spawn_service(tmp_path / "state")
    with ShapelocClient(svc.endpoint, timeout=5.0) as client:
        client.put_map(MAP, confirm=True)
        replay = _lockstep(svc.endpoint, "--laser-offset", *map(str, OFFSET), "--json")
        assert replay.returncode == 0, replay.stderr
        pm = client.get_pose("fr079")
    summary = json.loads(replay.stdout)
    ref = summary["reference"]
    print("mounted:", ref)
    assert summary["poses"] == 300 and ref["answered"] == 292
    assert ref["within_0.3_m"] == 1.0 and ref["error_max_m"] <= TOLERANCE_M
    # the last pose is the base's: 0.32 m from the laser's reference, not on it
    last = [s for s in attach_reference(read_log(BAG)[1], load_reference(REFERENCE))][-1]
    base = to_base(np.asarray(last.reference), np.asarray(OFFSET))
    assert np.hypot(*(pm.pose[:2] - base[:2])) < 0.1
    assert np.hypot(*(pm.pose[:2] - np.asarray(last.reference)[:2])) > 0.2


def test_replay_with_a_mistyped_map_fails_fast(spawn_service, tmp_path: Path) -> None:
    svc = spawn_service(tmp_path / "state")
    t0 = time.monotonic()
    r = _replay(
        svc.endpoint, "--robot", "fr079", "--map", "fr079-3OO", "--reference", str(REFERENCE)
    )
    assert r.returncode == 1, r.stderr
    assert time.monotonic() - t0 < 15.0
    err = [ln for ln in r.stderr.splitlines() if "error" in ln]
    assert err == [
        "shapeloc-sim replay: error: the service holds no map 'fr079-3OO'; store it first "
        "with shapeloc map put FILE --id fr079-3OO"
    ]


def test_replay_fails_with_the_services_reason_when_it_refuses_the_config(
    spawn_service, tmp_path: Path
) -> None:
    """icp cannot localise globally: the service refuses the configuration and the replay
    stops at once with that reason (exit 1)."""
    svc = spawn_service(tmp_path / "state")
    with ShapelocClient(svc.endpoint, timeout=5.0) as client:
        client.put_map(MAP, confirm=True)
    t0 = time.monotonic()
    r = _replay(
        svc.endpoint, "--robot", "fr079", "--map", "fr079-300", "--method", "icp", "--global"
    )
    assert r.returncode == 1, r.stderr
    assert time.monotonic() - t0 < 15.0
    err = [ln for ln in r.stderr.splitlines() if "error" in ln]
    assert len(err) == 1, r.stderr
    assert err[0].startswith(
        "shapeloc-sim replay: error: the service refused the configuration of robot 'fr079': "
    )
    assert "initial pose" in err[0]


def test_replay_without_a_service_says_so(spawn_router) -> None:
    """A router but no service on the prefix: exit 1 after --wait-service, saying where it
    asked (it used to replay into the void and exit 0 with "0 poses seen")."""
    router = spawn_router(f"tcp/127.0.0.1:{_free_port()}")
    r = _replay(
        router.endpoint, "--robot", "fr079", "--map", "m", "--global", "--wait-service", "1"
    )
    assert r.returncode == 1, r.stderr
    assert (
        "shapeloc-sim replay: error: no shapeloc service answered on shapeloc/service/health "
        "within 1 s" in r.stderr
    )


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])
