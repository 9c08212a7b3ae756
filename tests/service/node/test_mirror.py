"""service.node.mirror: rendezvous ownership (hrw) and the mirror of other instances' robots."""

from __future__ import annotations

import pytest

from schemas.codec import encode
from schemas.messages import PoseMsg, RobotConfig
from service.node.mirror import Mirror, hrw_owner, hrw_score


def test_hrw_is_stable_balanced_and_moves_only_what_it_must() -> None:
    ids = [f"robot-{i}" for i in range(3000)]
    three = ["A", "B", "C"]
    owner3 = {r: hrw_owner(r, three) for r in ids}
    assert owner3 == {r: hrw_owner(r, list(reversed(three))) for r in ids}  # order-free
    assert hrw_score("A", "robot-1") == hrw_score("A", "robot-1")
    shares = {n: sum(o == n for o in owner3.values()) / len(ids) for n in three}
    assert all(0.29 < s < 0.38 for s in shares.values()), shares
    # B leaves: only B's robots move, spread over A and C
    owner2 = {r: hrw_owner(r, ["A", "C"]) for r in ids}
    assert all(owner2[r] == o for r, o in owner3.items() if o != "B")
    moved = [owner2[r] for r, o in owner3.items() if o == "B"]
    assert 0.4 < moved.count("A") / len(moved) < 0.6
    # D joins: robots move only to D
    owner4 = {r: hrw_owner(r, [*three, "D"]) for r in ids}
    assert all(owner4[r] in (owner3[r], "D") for r in ids)
    assert hrw_owner("x", []) is None


# --------------------------------------------------------------------------- mirror


def _pose(robot: str, seq: int, x: float, odom: list[float] | None = None) -> PoseMsg:
    return PoseMsg(
        robot_id=robot, seq=seq, stamp=0.1 * seq, pose=[x, 1.0, 0.0], status="tracking",
        score=1.0, method="icp", map_id="room", latency_ms=3.0, odom=odom,
    )  # fmt: skip


def test_mirror_keeps_the_newest_valid_pose_of_known_robots_only() -> None:
    m = Mirror(capacity=2)
    cfg = RobotConfig(map_id="room", method="icp", initial_pose=[1.0, 1.0, 0.0])
    m.offer_raw("r1", encode(_pose("r1", 1, 1.0)), None)  # not mirrored yet: ignored
    assert m.set_config("r1", cfg) and m.set_config("r2", cfg)
    assert not m.set_config("r3", cfg)  # full
    m.offer_raw("r1", encode(_pose("r1", 1, 1.0)), None)
    m.offer_raw("r1", encode(_pose("r1", 2, 1.5, [5.0, 6.0, 0.1])), None)
    m.offer_raw("r2", b"\xc1garbage", None)
    saves = m.saves()
    assert set(saves) == {"r1"} and saves["r1"].x == 1.5
    assert saves["r1"].odom == pytest.approx((5.0, 6.0, 0.1))
    assert m.invalid == 1
    wrong_map = PoseMsg.parse({**_pose("r1", 3, 9.0).to_wire(), "map_id": "other"})
    m.offer_raw("r1", encode(wrong_map), None)
    assert m.saves() == {} and m.invalid == 2
    assert not m.offer_pose("r1", _pose("r1", 1, 0.5))  # older than the mirrored one
    assert m.offer_pose("r1", _pose("r1", 7, 2.0))
    got = m.take("r1")
    assert got is not None and got[1] is not None and got[1].seq == 7 and got[2] is None
    assert not m.known("r1")
    assert m.set_config("r2", cfg) and m.snapshot() == [("r2", cfg, None, None)]
