"""The kidnapped robot over Zenoh with the real processes.

The service and the simulator run as separate processes on a free loopback port. The
simulator (``--lockstep``: every scan is localised, none skipped) drives ``sim-0`` on the
metric office map from a known start; at scan ``KIDNAP_AT`` the truth jumps to another room
(``--kidnap-at/--kidnap-to``) without the service being told. Asserted from what comes back
over Zenoh: status ``lost`` within 3 scans of the jump, ``tracking`` again within 20 scans
(the service spreads a global search over scans within ``search_budget_ms``, 25 reference
ms by default: a whole search of this map and its twin check take about 10 scans), the lost
poses carry the live hypotheses and the best candidates once a search has finished, and
every ``tracking`` pose after the loss passes the proximity test (< 0.5 m, < 10 deg).
The service builds the map's view index in memory on the first global search (no cache dir
is wired yet). Also a unit test of the simulator's kidnap option.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from sim_publisher.publisher import SimFleet, fleet_specs

KIDNAP_AT = 8
KIDNAP_TO = 0.6
START = 0.1
SCANS = 34


def _passes(p: np.ndarray, t: np.ndarray) -> bool:
    dth = abs((p[2] - t[2] + math.pi) % (2 * math.pi) - math.pi)
    return math.hypot(p[0] - t[0], p[1] - t[1]) < 0.5 and math.degrees(dth) < 10.0


def test_sim_kidnap_option_moves_the_truth() -> None:
    specs = fleet_specs(
        2, ["metric"], starts=[START, START], step_mm=50, kidnap_at=3, kidnap_to=KIDNAP_TO
    )
    fleet = SimFleet.from_specs(specs)
    kid, other = fleet.robots
    truths = [[kid.step(float(k))[1].pose for k in range(6)], [other.step(0.0)[1].pose]]
    jumps = [math.dist(a[:2], b[:2]) for a, b in zip(truths[0], truths[0][1:], strict=False)]
    assert max(jumps[:2]) < 0.2 and jumps[2] > 3.0 and max(jumps[3:]) < 0.2
    n = len(kid.setup.truth)
    target = kid.setup.truth[round(KIDNAP_TO * (n - 1))]
    assert math.dist(truths[0][3][:2], target[:2]) < 0.1  # within one stride of the target
    assert other.kidnap_at is None  # only the first robot is carried away by default
    with pytest.raises(ValueError, match="go together"):
        fleet_specs(1, ["metric"], kidnap_at=3)


@pytest.mark.integration
@pytest.mark.timeout(240)
def test_kidnapped_robot_over_zenoh(spawn_service, lockstep_sim, tmp_path: Path) -> None:
    svc = spawn_service(tmp_path / "state", workers=1)
    args = ["--map", "metric", "--step-mm", "50", "--starts", str(START)]
    args += ["--kidnap-at", str(KIDNAP_AT), "--kidnap-to", str(KIDNAP_TO)]
    est, truth = lockstep_sim(svc, args, SCANS)
    assert sorted(est) == list(range(SCANS)), f"missing poses: {sorted(est)}\n{svc.log()}"
    assert sorted(truth) == list(range(SCANS))
    assert math.dist(truth[KIDNAP_AT - 1][:2], truth[KIDNAP_AT][:2]) > 3.0  # the jump
    for seq in range(KIDNAP_AT):
        assert est[seq].status == "tracking" and _passes(np.asarray(est[seq].pose), truth[seq])
    status = [est[s].status for s in range(KIDNAP_AT, SCANS)]
    print("statuses after the jump:", status)
    assert "lost" in status[:3], status
    lost = status.index("lost")
    assert "tracking" in status[lost : lost + 20], status
    fixed = status.index("tracking", lost)
    held = [est[KIDNAP_AT + k] for k in range(lost, fixed) if est[KIDNAP_AT + k].hypotheses]
    assert held, "no lost pose reported its hypotheses"
    for p in held:
        assert p.candidates is not None and 1 <= len(p.candidates) <= p.hypotheses
    for k in range(lost, len(status)):
        p = est[KIDNAP_AT + k]
        assert p.explained is not None and 0.0 <= p.explained <= 1.0
        if p.status == "tracking":
            assert _passes(np.asarray(p.pose), truth[KIDNAP_AT + k]), (k, p.pose, truth)
        else:
            assert p.ambiguity is not None
    assert status[-1] == "tracking"
