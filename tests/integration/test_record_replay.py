"""``python -m clients.record`` end to end: a real service, the fr079 excerpt (tests/data/real,
300 scans) replayed in lockstep by ``shapeloc-sim replay`` as a real process, the recorder as
another; the MCAP file read back with the ``mcap`` package's reader holds every scan and every
pose of the run, in order, with the schemas Foxglove recognises."""

from __future__ import annotations

import base64
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from clients.client import ShapelocClient
from service.adapters.logs import read_log

pytestmark = [pytest.mark.integration, pytest.mark.timeout(400)]

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data" / "real"
BAG = DATA / "fr079.300.bag"
REFERENCE = DATA / "fr079.300.gfs_reference_per_scan.txt"
MAP = DATA / "fr079.300.map.json"


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("RUST_LOG", None)
    return env


def test_a_replayed_real_log_reads_back_whole(spawn_service, tmp_path: Path) -> None:
    svc = spawn_service(tmp_path / "state")
    log_scans = list(read_log(BAG)[1])
    out = tmp_path / "run.mcap"
    with ShapelocClient(svc.endpoint, timeout=5.0) as client:
        client.put_map(MAP, confirm=True)
        poses = client.watch_poses(["fr079"])
        rec = subprocess.Popen(
            [sys.executable, "-m", "clients.record", str(out), "--connect", svc.endpoint],
            cwd=REPO,
            env=_env(),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            assert rec.stdout is not None
            assert "recording to" in rec.stdout.readline()
            replay = subprocess.run(
                [sys.executable, "-m", "sim_publisher", "replay", str(BAG), "--robot", "fr079",
                 "--map", "fr079-300", "--reference", str(REFERENCE), "--rate", "max",
                 "--lockstep", "--no-progress", "--connect", svc.endpoint],
                cwd=REPO, env=_env(), capture_output=True, text=True, timeout=300,
            )  # fmt: skip
            assert replay.returncode == 0, replay.stderr
            time.sleep(1.0)
        finally:
            rec.send_signal(signal.SIGINT)
            tail, _ = rec.communicate(timeout=60)
        assert rec.returncode == 0, tail
        published = [p for _k, p in poses.drain()]
    assert "recorded" in tail and "0 rejected, 0 dropped" in tail, tail
    assert len(published) == len(log_scans) == 300

    topics: dict[str, list] = {}
    with open(out, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json")
            topics.setdefault(channel.topic, []).append((schema.name, json.loads(message.data)))
    assert {n for n, _m in topics["/maps/fr079-300"]} == {"foxglove.SceneUpdate"}

    # every scan of the log, in order, its returns in the robot frame at the log's stamps
    scans = topics["/robots/fr079/scan"]
    assert {n for n, _m in scans} == {"foxglove.PointCloud"}
    assert len(scans) == 300
    stamps = [m["timestamp"]["sec"] + m["timestamp"]["nsec"] * 1e-9 for _n, m in scans]
    np.testing.assert_allclose(stamps, [s.stamp for s in log_scans], atol=1e-6)
    k = 150
    pts = np.frombuffer(base64.b64decode(scans[k][1]["data"]), "<f4").reshape(-1, 2)
    r = np.asarray(log_scans[k].ranges)
    assert len(pts) == int(np.sum(np.isfinite(r) & (r > 0)))

    # every published pose, in order, equal to what the service published
    est = [m for _n, m in topics["/robots/fr079/estimate"]]
    assert [m["seq"] for m in est] == [p.seq for p in published] == list(range(300))
    np.testing.assert_allclose([m["pose"] for m in est], [p.pose for p in published], atol=1e-12)
    fox = [m for n, m in topics["/robots/fr079/pose"] if n == "foxglove.PoseInFrame"]
    assert len(fox) == 300 and all(m["frame_id"] == "fr079-300" for m in fox)
    assert [m["pose"]["position"]["x"] for m in fox] == [p.pose[0] for p in published]
    tf = [m for n, m in topics["/tf"] if n == "foxglove.FrameTransform"]
    assert len(tf) == 300 and tf[0]["child_frame_id"] == "fr079"
    assert {n for n, _m in topics["/status"]} == {"foxglove.Log"}
