"""A fresh service and a fresh map, with real processes on loopback.

* The map put's acknowledgement: ``put_map(..., ready=True)`` returns once the service lists
  the map in ``Health.maps_ready`` and ``Health.ready`` is true, by then with all of its
  first-use work done: every worker holds it prepared and the search worker has built its
  view index into the state directory (``maps_indexed``).
* Scans skipped on purpose keep the odometry chain exact: while the worker is busy with a
  searching robot's scan, a tracked robot's first scans (and later, a burst of them) replace
  each other unprocessed in its latest-wins slot; every pose it gets is within 0.1 m of the
  truth. Before, the robot's first processed scan was localised from its initial pose with
  no odometry increment at all (a cold start of 20 robots: 7.7-8.4 % of the answered
  poses more than 0.1 m off).

The office of the paper (``sim_publisher.office``), scans of setup 1 along its tour, exact
odometry in a frame of its own. ~30 s on the 2-core machine.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zenoh

from clients.client import ShapelocClient
from schemas.codec import decode
from schemas.messages import Health, PoseMsg

pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.timeout(240)]

P = "shapeloc"


def _odom(pose: np.ndarray) -> list[float]:
    """Exact odometry in a frame moved by (5 m, -3 m) and turned by 1 rad from the map's."""
    c, s = np.cos(1.0), np.sin(1.0)
    return [
        float(c * pose[0] - s * pose[1] + 5.0),
        float(s * pose[0] + c * pose[1] - 3.0),
        float(pose[2] + 1.0),
    ]


@pytest.fixture(scope="module")
def office() -> dict[str, Any]:
    """The office map and 60 setup-1 scans 5 tour samples (~55 mm, ~19 deg) apart."""
    from service.adapters.convert import map_message_of
    from sim_publisher.office import office_metric_map
    from sim_publisher.scenario import make_setup

    setup = make_setup(1, seed=3, max_scans=300)
    idx = np.arange(0, 300, 5)
    lz = setup.laser
    return {
        "map": map_message_of(office_metric_map("office")),
        "truth": setup.truth[idx],
        "ranges": [np.asarray(setup.scan(int(i))[0], dtype="<f4").tobytes() for i in idx],
        "info": {
            "angle_min": float(lz.angle_min),
            "angle_increment": float(lz.angle_increment),
            "range_min": 0.0,
            "range_max": float(lz.config.max_range),
        },
    }


def _scan(office: dict[str, Any], k: int, odom: bool = True) -> bytes:
    msg = {"seq": k, "stamp": time.time(), **office["info"], "ranges": office["ranges"][k]}
    if odom:
        msg["odom"] = _odom(office["truth"][k])
    return msgpack.packb(msg)


class Poses:
    def __init__(self, session: zenoh.Session, robot: str) -> None:
        self.lock = threading.Lock()
        self.got: dict[int, PoseMsg] = {}
        self.sub = session.declare_subscriber(f"{P}/robots/{robot}/pose", self._on)

    def _on(self, s: zenoh.Sample) -> None:
        m = decode(PoseMsg, s.payload.to_bytes(), str(s.encoding))
        with self.lock:
            self.got[m.seq] = m

    def wait(self, seq: int, timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                if seq in self.got:
                    return
            time.sleep(0.02)
        raise AssertionError(f"no pose for seq {seq} in {timeout_s} s; got {sorted(self.got)}")


def test_a_map_put_is_acknowledged_ready_and_indexed(
    tmp_path: Path, spawn_service: Callable[..., Any], office: dict[str, Any]
) -> None:
    svc = spawn_service(tmp_path / "state", workers=1)
    with ShapelocClient(svc.endpoint, timeout=5.0) as client:
        client.put_map(office["map"], ready=True, within=120.0)
        h = client.health()
        # ready means indexed too: no index build left to share the cores with the robots
        assert h.maps_ready == ["office"] and h.ready is True and h.maps_indexed == ["office"]
        assert list((tmp_path / "state" / "viewcache").iterdir())  # in the on-disk cache


def test_scans_skipped_on_purpose_keep_every_pose_within_0_1_m(
    tmp_path: Path,
    spawn_service: Callable[..., Any],
    open_session: Callable[..., zenoh.Session],
    office: dict[str, Any],
) -> None:
    # one tracking worker; no search worker, so a searching robot's scan (a global search
    # step, tens of milliseconds) holds the tracked robot's worker while its scans arrive
    svc = spawn_service(tmp_path / "state", "--no-search-worker", workers=1)
    with ShapelocClient(svc.endpoint, timeout=5.0) as client:
        client.put_map(office["map"], ready=True, within=120.0)
        truth = office["truth"]
        client.configure("tracked", "office", "shape", truth[0], confirm=True)
        client.configure("searcher", "office", "shape", None, confirm=True)
    s = open_session(svc.endpoint)
    poses = Poses(s, "tracked")
    enc = zenoh.Encoding("application/msgpack")

    def burst(seqs: range) -> None:
        s.put(f"{P}/robots/searcher/scan", _scan(office, 30, odom=False), encoding=enc)
        for k in seqs:
            s.put(f"{P}/robots/tracked/scan", _scan(office, k), encoding=enc)
        poses.wait(seqs[-1])

    burst(range(0, 12))  # its first scans: 11 of them replaced while the worker searches
    burst(range(12, 30))  # later ones: the chain goes on from the last processed scan
    for k in range(30, 40):  # and at the robot's pace, nothing skipped
        s.put(f"{P}/robots/tracked/scan", _scan(office, k), encoding=enc)
        poses.wait(k)
    with poses.lock:
        got = dict(poses.got)
    h = decode_health(s)
    assert h.errors is not None and h.errors.get("scan.Skipped", 0) >= 5, h.errors
    # most of the first burst was replaced (its first scan too, unless the worker took it in
    # the same batch as the searcher's scan): the odometry chain must survive the gaps
    assert sum(k not in got for k in range(12)) >= 5, sorted(got)
    errs = {k: float(np.hypot(*(p.pose[:2] - truth[k][:2]))) for k, p in got.items()}
    assert all(e < 0.1 for e in errs.values()), errs
    assert all(p.status == "tracking" for p in got.values())


def decode_health(s: zenoh.Session) -> Health:
    for r in s.get(f"{P}/service/health", timeout=5.0):
        if r.ok is not None:
            return decode(Health, r.ok.payload.to_bytes(), str(r.ok.encoding))
    raise AssertionError("no health reply")
