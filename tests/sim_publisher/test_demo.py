"""The demo's accuracy bookkeeping (``python -m sim_publisher.demo``; the whole demo runs in
tests/integration/test_sim_and_cli.py)."""

from __future__ import annotations

import pytest

from schemas.messages import PoseMsg


def test_demo_accuracy_numbers_from_known_poses() -> None:
    import numpy as np

    from sim_publisher.demo import Track, accuracy_table

    t = Track("sim-9", "metric", 100.0)
    truth = [(0.0, 0.0, 0.0), (1.0, 0.0, 3.1), (2.0, 0.0, -3.1)]
    est = [(0.05, 0.0, 0.1), (1.0, 0.2, -3.1), (2.0, 0.0, 3.1)]  # 50 mm, 200 mm, 0 mm
    for seq, (tr, e) in enumerate(zip(truth, est, strict=True)):
        t.truth[seq] = np.asarray(tr)
        t.poses.append(
            PoseMsg(
                robot_id="sim-9",
                seq=seq,
                stamp=0.0,
                pose=list(e),
                status="tracking",
                score=1.0,
                method="shape",
                map_id="office",
                latency_ms=10.0 * (seq + 1),
            )
        )
    r = t.row()
    assert r["poses"] == 3 and r["scans"] == 3
    assert r["pos_mm"] == pytest.approx((50.0 + 200.0 + 0.0) / 3)
    # heading errors wrap: 0.1 rad, |(-3.1) - 3.1| -> 2*pi - 6.2, same for the third
    wrapped = np.degrees(2 * np.pi - 6.2)
    assert r["head_deg"] == pytest.approx((np.degrees(0.1) + 2 * wrapped) / 3)
    assert r["proximity"] == pytest.approx(200.0 / 3)  # the 200 mm pose fails the 100 mm test
    assert r["p50"] == pytest.approx(20.0)
    table = accuracy_table([t])
    assert "sim-9" in table.splitlines()[2] and "66.7" in table
    empty = Track("sim-8", "schematic", 500.0).row()
    assert empty["poses"] == 0 and np.isnan(empty["pos_mm"])
