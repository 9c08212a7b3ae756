"""Real service + simulator + CLI processes on free loopback ports.

* Accuracy over Zenoh: the simulator (``--lockstep``, so no scan is skipped) drives one robot on
  the metric map and one on the schematic map over a short stretch; the poses that come back
  over Zenoh are scored against the truth topic and compared with the same localiser run
  in-process on the same (wire-decoded) scans.
* The ``shapeloc`` CLI against the real service: health, map put/list/delete, configure,
  pose, watch, unknown robot and unreachable service.
* The demo (``python -m sim_publisher.demo``, what ``make demo`` runs), end to end.

Every spawned process is killed at teardown. Takes about 30-60 s on a loaded 2-core machine.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from clients.__main__ import cli
from clients.client import ShapelocClient
from schemas.codec import decode, encode, scan_arrays
from schemas.messages import Scan
from service.core.factory import create_localizer
from sim_publisher.publisher import SimFleet, fleet_specs

pytestmark = [pytest.mark.integration, pytest.mark.timeout(240)]

REPO = Path(__file__).resolve().parents[2]
MAPS = ["metric", "schematic"]
STARTS = [0.1, 0.1]
SEED = 5
SCANS = 25


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("RUST_LOG", None)
    return env


def _errors(est: dict[int, np.ndarray], truth: dict[int, np.ndarray]) -> tuple[float, float]:
    """Mean position error (mm) and mean heading error (deg) over the seqs of ``est``."""
    pos, head = [], []
    for seq, p in est.items():
        t = truth[seq]
        pos.append(1000.0 * math.hypot(p[0] - t[0], p[1] - t[1]))
        head.append(abs(math.degrees((p[2] - t[2] + math.pi) % (2 * math.pi) - math.pi)))
    return float(np.mean(pos)), float(np.mean(head))


def _in_process(method: str) -> list[tuple[dict[int, np.ndarray], dict[int, np.ndarray]]]:
    """Same robots, same scans (through the wire codec), localised in this process."""
    fleet = SimFleet.from_specs(fleet_specs(len(MAPS), MAPS, [method], seed=SEED, starts=STARTS))
    out = []
    for r in fleet.robots:
        cfg = r.config()
        loc = create_localizer(method, fleet.maps[r.map_id], cfg.initial_pose)
        est, truth = {}, {}
        for _ in range(SCANS):
            scan, tr = r.step(0.0)
            wire = decode(Scan, encode(scan, ranges_as_bytes=True))
            ranges, angles = scan_arrays(wire)
            e = loc.update(ranges, angles, None if wire.odom is None else np.asarray(wire.odom))
            est[scan.seq] = np.asarray(e.pose, dtype=np.float64)
            truth[tr.seq] = np.asarray(tr.pose)
        out.append((est, truth))
    return out


def test_accuracy_over_zenoh_matches_in_process(spawn_service, tmp_path: Path) -> None:
    svc = spawn_service(tmp_path / "state", workers=2)
    ids = [f"sim-{k}" for k in range(len(MAPS))]
    with ShapelocClient(svc.endpoint, timeout=5.0) as client:
        poses = client.watch_poses(ids)
        truths = client.watch_truth(ids)
        sim = subprocess.run(
            [
                sys.executable,
                "-m",
                "sim_publisher",
                "run",
                "--connect",
                svc.endpoint,
                "--robots",
                str(len(MAPS)),
                "--map",
                ",".join(MAPS),
                "--starts",
                ",".join(map(str, STARTS)),
                "--seed",
                str(SEED),
                "--scans",
                str(SCANS),
                "--max-rate",
                "--lockstep",
            ],
            cwd=REPO,
            env=_env(),
            capture_output=True,
            text=True,
            timeout=180,
        )
        assert sim.returncode == 0, sim.stderr
        assert "lockstep: no pose" not in sim.stderr, sim.stderr
        time.sleep(0.5)
        est = {rid: {} for rid in ids}
        truth = {rid: {} for rid in ids}
        for _, p in poses.drain():
            est[p.robot_id][p.seq] = np.asarray(p.pose)
        for key, t in truths.drain():
            truth[key.split("/")[-2]][t.seq] = np.asarray(t.pose)
        h = client.health()
    assert h.scans_processed == SCANS * len(MAPS) and h.scans_rejected == 0
    reference = _in_process("shape")
    for rid, (ref_est, ref_truth) in zip(ids, reference, strict=True):
        assert sorted(est[rid]) == list(range(SCANS)), f"{rid}: missing poses"
        assert sorted(truth[rid]) == list(range(SCANS)), f"{rid}: missing truth"
        for seq in range(SCANS):
            np.testing.assert_allclose(truth[rid][seq], ref_truth[seq], atol=1e-9)
        z_pos, z_head = _errors(est[rid], truth[rid])
        r_pos, r_head = _errors(ref_est, ref_truth)
        print(
            f"{rid}: over zenoh {z_pos:.0f} mm {z_head:.1f} deg; in-process {r_pos:.0f} mm "
            f"{r_head:.1f} deg"
        )
        assert abs(z_pos - r_pos) <= max(10.0, 0.1 * r_pos), (rid, z_pos, r_pos)
        assert abs(z_head - r_head) <= max(1.0, 0.1 * r_head), (rid, z_head, r_head)


def _run_cli(*args: str, timeout: float = 30.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "clients", *args],
        cwd=REPO,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_cli_against_the_real_service(spawn_service, tmp_path: Path, capsys) -> None:
    svc = spawn_service(tmp_path / "state")
    ep = svc.endpoint

    r = _run_cli("--connect", ep, "health")
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("ok: shapeloc ") and "0 maps" in r.stdout
    # a peer-mode client is answered too: its open waits for the link before the query
    r = _run_cli("--mode", "peer", "--connect", ep, "health")
    assert r.returncode == 0, r.stderr

    world = REPO / "sim_publisher" / "worlds" / "office.geojson"
    assert cli(["--connect", ep, "map", "put", str(world), "--id", "hq", "--kind", "metric"]) == 0
    assert "stored hq" in capsys.readouterr().out
    rooms = tmp_path / "rooms.geojson"
    rooms.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "features": [
                    {
                        "type": "Feature",
                        "properties": {},
                        "geometry": {
                            "type": "LineString",
                            "coordinates": [[0, 0], [6, 0], [6, 4], [0, 4], [0, 0]],
                        },
                    },
                    {
                        "type": "Feature",
                        "properties": {},
                        "geometry": {"type": "LineString", "coordinates": [[3, 0], [3, 1.5]]},
                    },
                ],
            }
        )
    )
    assert cli(["--connect", ep, "map", "put", str(rooms), "--kind", "schematic"]) == 0
    capsys.readouterr()
    assert cli(["--connect", ep, "maps"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [ln.split()[:2] for ln in lines] == [["hq", "metric"], ["rooms", "schematic"]]
    assert " 2 polylines" in lines[1]

    assert cli(["--connect", ep, "configure", "r1", "--map", "nope", "--global"]) == 1
    assert "holds no map 'nope'" in capsys.readouterr().err
    assert (
        cli(
            [
                "--connect",
                ep,
                "configure",
                "r1",
                "--map",
                "rooms",
                "--method",
                "icp",
                "--initial-pose",
                "1.0",
                "2.0",
                "0.0",
            ]
        )
        == 0
    )
    assert "configured r1: map rooms, icp" in capsys.readouterr().out
    assert (
        cli(["--connect", ep, "configure", "r2", "--map", "rooms", "--method", "icp", "--global"])
        == 1
    )
    err = capsys.readouterr().err
    assert err.startswith("shapeloc: error: the service rejected the configuration of 'r2': ")
    assert "initial pose" in err and len(err.strip().splitlines()) == 1

    # one scan of the 6 m x 4 m room from (1, 2) facing +x, then the pose must be there
    angles = np.linspace(-np.pi / 2, np.pi / 2, 181)
    with ShapelocClient(ep) as c:
        c.wait_configured("r1", 10.0)
        ranges = []
        for a in angles:
            dx, dy = math.cos(a), math.sin(a)
            cands = [
                t
                for t in (
                    (5.0 / dx) if dx > 1e-9 else math.inf,
                    (2.0 / dy) if dy > 1e-9 else math.inf,
                    (-2.0 / dy) if dy < -1e-9 else math.inf,
                )
            ]
            ranges.append(min(cands))
        scan = Scan(
            seq=0,
            stamp=1.0,
            angle_min=-np.pi / 2,
            angle_increment=np.pi / 180,
            range_min=0.05,
            range_max=15.0,
            ranges=ranges,
        )
        c.send_scan("r1", scan)
        end = time.monotonic() + 20.0
        while True:
            try:
                p = c.get_pose("r1")
                break
            except Exception:
                assert time.monotonic() < end, "no pose for r1"
                time.sleep(0.1)
    assert p.seq == 0 and p.map_id == "rooms" and p.method == "icp"
    r = _run_cli("--connect", ep, "pose", "r1")
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("r1: x=") and "map=rooms" in r.stdout

    # watch: a subprocess prints the pose of the next scan, then exits (--count 1)
    watcher = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "clients",
            "--connect",
            ep,
            "watch",
            "r1",
            "--count",
            "1",
            "--seconds",
            "20",
        ],
        cwd=REPO,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        with ShapelocClient(ep) as c:
            seq = 1
            while watcher.poll() is None and seq < 100:
                c.send_scan("r1", Scan(**{**scan.to_wire(), "seq": seq}))
                seq += 1
                time.sleep(0.2)
        out, err = watcher.communicate(timeout=25)
    finally:
        if watcher.poll() is None:
            watcher.kill()
            watcher.wait()
    assert watcher.returncode == 0, err
    assert out.startswith("r1: x=") and out.count("\n") == 1

    r = _run_cli("--connect", ep, "pose", "ghost")
    assert r.returncode == 1 and r.stdout == ""
    assert r.stderr.strip() == "shapeloc: error: unknown robot 'ghost'"

    assert cli(["--connect", ep, "map", "delete", "hq"]) == 0
    capsys.readouterr()
    deadline = time.monotonic() + 5.0
    while True:
        cli(["--connect", ep, "maps"])
        out = capsys.readouterr().out
        if "hq" not in out or time.monotonic() > deadline:
            break
        time.sleep(0.1)
    assert "hq" not in out and "rooms" in out
    assert cli(["--connect", ep, "map", "delete", "hq"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("shapeloc: error: ") and "unknown map" in err and "hq" in err

    svc.kill()
    t0 = time.monotonic()
    r = _run_cli("--connect", ep, "health")
    assert r.returncode == 1 and time.monotonic() - t0 < 10.0
    assert r.stderr.startswith("shapeloc: error: cannot reach") and ep in r.stderr
    assert "Traceback" not in r.stderr


def test_demo_runs_end_to_end(tmp_path: Path) -> None:
    png = tmp_path / "demo.png"
    r = subprocess.run(
        [sys.executable, "-m", "sim_publisher.demo", "--scans", "6", "--out", str(png)],
        cwd=REPO,
        env=_env(),
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    lines = r.stdout.splitlines()
    head = lines.index(next(ln for ln in lines if ln.startswith("robot ")))
    rows = [ln.split() for ln in lines[head + 2 : head + 5]]
    assert [row[:4] for row in rows] == [
        ["sim-0", "metric", "6", "6"],
        ["sim-1", "schematic", "6", "6"],
        ["sim-2", "metric", "6", "6"],
    ]
    assert png.stat().st_size > 10_000
    assert "demo: ok" in r.stdout
