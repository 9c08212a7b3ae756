"""A robot whose laser is not at its base's origin, end to end with the real processes.

The simulator drives ``sim-0`` along the office tour with its laser 0.3 m forward, 0.1 m left
and turned 0.2 rad on the base (``shapeloc-sim run --laser-offset 0.3 0.1 0.2``): scans are
taken from the laser, odometry and truth are the base's, and the configuration carries the
offset. The poses that come back over Zenoh must be the base's and as close to its truth as
those of the same drive with the laser at the origin.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

SCANS = 80
OFFSET = ("0.3", "0.1", "0.2")


def _errors(est: dict, truth: dict) -> tuple[np.ndarray, np.ndarray]:
    seqs = sorted(set(est) & set(truth))
    p = np.array([est[s].pose for s in seqs])
    t = np.array([truth[s] for s in seqs])
    pos = np.hypot(p[:, 0] - t[:, 0], p[:, 1] - t[:, 1])
    head = np.abs(np.angle(np.exp(1j * (p[:, 2] - t[:, 2]))))
    return pos, head


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_a_mounted_laser_gives_the_base_pose_over_zenoh(
    spawn_service, lockstep_sim, tmp_path: Path
) -> None:
    svc = spawn_service(tmp_path / "state", workers=1)
    args = ["--map", "metric", "--starts", "0.3", "--seed", "7"]
    est0, truth0 = lockstep_sim(svc, args, SCANS)
    est1, truth1 = lockstep_sim(svc, [*args, "--laser-offset", *OFFSET], SCANS)
    assert sorted(est1) == list(range(SCANS)), svc.log()
    # the same drive: the base's truth is the same with and without the mounting
    assert all(np.allclose(truth0[s], truth1[s]) for s in truth0)
    pos0, head0 = _errors(est0, truth0)
    pos1, head1 = _errors(est1, truth1)
    print(
        f"position error mean / max: origin {pos0.mean():.4f} / {pos0.max():.4f} m, "
        f"mounted {pos1.mean():.4f} / {pos1.max():.4f} m; heading max {np.degrees(head0.max()):.2f}"
        f" / {np.degrees(head1.max()):.2f} deg"
    )
    assert pos1.mean() <= pos0.mean() + 0.01 and pos1.max() < 0.1
    assert head1.max() < 0.05
    assert all(est1[s].status == "tracking" for s in est1)
