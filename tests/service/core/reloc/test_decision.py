"""The decision rule (service/core/reloc/decision.py): the LLR of the best place against the rest
over the drive's frames, with a prior; dead reckoning's propagation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.core.pose import propagate
from service.core.reloc.config import GlobalConfig
from service.core.reloc.decision import Prior, decide
from service.core.reloc.drive import Frame, Track
from service.core.reloc.global_search import COST_FLOOR, Hypothesis
from service.core.sensor.scoring import EFFECTIVE_BEAMS

G = GlobalConfig.for_kind("metric")


def _frames(n: int) -> tuple[list[Frame], list[int]]:
    z = np.zeros(0)
    frames = [Frame(k, z, z, np.zeros((0, 2)), np.zeros(3), 0.3 * k) for k in range(n)]
    return frames, [f.key for f in frames]


def _track(x: float, ll: list[float] | None, keys: int | None = None) -> Track:
    p = np.array([x, 0.0, 0.0])
    t = Track(p, Hypothesis(pose=p.copy(), cost=0.1))
    if ll is not None:
        t.ll = {k: v for k, v in enumerate(ll) if keys is None or k < keys}
    return t


UNIFORM = Prior(None, None, 1.0, 1.0)


def test_the_llr_is_the_leaders_evidence_over_the_rest_and_the_unseen_place() -> None:
    frames, keys = _frames(4)
    best = _track(0.0, [-2.0] * 4)
    alt = _track(5.0, [-5.0] * 4)
    v = decide([alt, best], frames, keys, UNIFORM, G)
    assert v.leader is best
    unseen = 4 * -20.0 * (G.null_cost - COST_FLOOR)
    want = -8.0 - math.log(math.exp(-20.0) + math.exp(unseen))
    assert v.llr == pytest.approx(want)
    assert v.ambiguity == pytest.approx(1.0 / (1.0 + math.exp(want)))
    assert v.unseen == pytest.approx(-8.0 - unseen)  # against the unseen place alone


def test_a_place_at_the_leaders_place_is_no_alternative() -> None:
    frames, keys = _frames(3)
    best = _track(0.0, [-2.0] * 3)
    same = _track(0.3, [-2.1] * 3)  # within distinct_distance: the same place
    assert decide([best, same], frames, keys, UNIFORM, G).llr > 30.0


def test_an_alternative_not_yet_scored_counts_as_the_leader_and_only_lowers_the_llr() -> None:
    frames, keys = _frames(6)
    best = _track(0.0, [-2.0] * 6)
    young = _track(5.0, [-9.0] * 6, keys=2)  # scored on the first two frames only
    v = decide([best, young], frames, keys, UNIFORM, G)
    # 4 frames tied, 2 frames 7 nats each: the LLR is at most 14
    assert v.leader is best and v.llr <= 14.0 + 1e-9
    young.ll.update({k: -9.0 for k in range(2, 6)})
    assert decide([best, young], frames, keys, UNIFORM, G).llr > v.llr + 20.0


def test_no_leader_until_a_track_is_scored_on_the_whole_window() -> None:
    frames, keys = _frames(3)
    t = _track(0.0, [-1.0] * 3, keys=2)
    v = decide([t], frames, keys, UNIFORM, G)
    assert v.leader is None and v.llr == -math.inf and v.ambiguity == 1.0


def test_a_dead_reckoned_prior_favours_the_place_near_it() -> None:
    """Two places explaining the frames equally: with nothing known it is a tie; with the
    dead-reckoned pose next to one of them, that one wins by the prior's ratio (the far one
    carries only kidnap_weight of the mass, spread over the map's places)."""
    frames, keys = _frames(4)
    near, far = _track(0.0, [-3.0] * 4), _track(20.0, [-3.0] * 4)
    tie = decide([near, far], frames, keys, UNIFORM, G)
    assert abs(tie.llr) < 1.0
    cells = 5000.0
    prior = Prior(np.zeros(3), np.diag([0.3**2, 0.3**2, 0.1**2]), G.kidnap_weight, cells)
    v = decide([far, near], frames, keys, prior, G)
    assert v.leader is near
    assert v.llr > -math.log(G.kidnap_weight / cells) - 2.0
    # a far place explaining each frame clearly better still wins eventually (a kidnap)
    far.ll = {k: 2.0 for k in range(4)}
    assert decide([far, near], frames, keys, prior, G).leader is far
    assert prior.log(near.pose) > prior.log(far.pose)


def test_dead_reckoning_grows_the_covariance_along_the_drive() -> None:
    pose, cov = np.zeros(3), np.diag([1e-4, 1e-4, 1e-4])
    noise = np.diag([0.01**2, 0.01**2, 0.005**2])
    for _ in range(20):
        pose, cov = propagate(pose, cov, np.array([0.1, 0.0, 0.0]), noise)
    np.testing.assert_allclose(pose, [2.0, 0.0, 0.0], atol=1e-12)
    assert np.allclose(cov, cov.T)
    # the heading's uncertainty swings the position sideways (y) more than along (x)
    assert cov[1, 1] > cov[0, 0] > 1e-4 and cov[2, 2] > 1e-4


def test_the_unseen_place_holds_the_dead_reckoned_mass_no_track_holds() -> None:
    """After a loss in a corridor the map lacks, no search finds the robot where its odometry
    says it is: the dead-reckoned Gaussian's mass is the unseen place's. A place 20 m off that
    explains each frame 3 nats better than the unseen place (a look-alike) then needs those
    odds of a kidnap, not only its frames' 12 nats, which it has with nothing known or with
    the last pose held without odometry."""
    frames, keys = _frames(4)
    unseen = -EFFECTIVE_BEAMS * (G.null_cost - COST_FLOOR)
    far = _track(20.0, [unseen + 3.0] * 4)
    assert decide([far], frames, keys, UNIFORM, G).llr == pytest.approx(12.0)
    k, cells = G.kidnap_weight, 5000.0
    prior = Prior(np.zeros(3), np.diag([0.3**2, 0.3**2, 0.1**2]), k, cells, carried=True)
    v = decide([far], frames, keys, prior, G)
    assert v.leader is far
    assert v.llr == pytest.approx(12.0 + math.log(k / cells) - math.log(1.0 - k + k / cells))
    assert v.llr < 0.0
    # a pose held without odometry says less: the unseen place keeps one place's share
    held = Prior(np.zeros(3), np.diag([0.3**2, 0.3**2, 0.1**2]), k, cells)
    assert decide([far], frames, keys, held, G).llr == pytest.approx(12.0)
    # the prior's odds are paid once: a longer drive explained as well wins
    frames, keys = _frames(12)
    far.ll = {key: unseen + 3.0 for key in keys}
    assert decide([far], frames, keys, prior, G).llr > v.llr + 20.0


def test_after_a_loss_the_unseen_place_is_judged_on_the_window_places_on_the_whole_drive() -> None:
    """A robot lost in a corridor the map lacks drove 6 keyframes there, then back where it
    holds: the true place found early explains those frames 4 nats each worse than the unseen
    place, the window's 3 better. After a loss the unseen place (what the search has not found)
    is judged on the window, so the corridor is no evidence against the place; a place
    elsewhere that explains the corridor better still wins on the whole drive. A first search
    (nothing known) weighs the unseen place on the whole drive."""
    frames, keys = _frames(10)
    window = frames[6:]
    unseen = -EFFECTIVE_BEAMS * (G.null_cost - COST_FLOOR)
    early = _track(0.0, [unseen - 4.0] * 6 + [unseen + 3.0] * 4)
    assert decide([early], window, keys, UNIFORM, G).llr == pytest.approx(-12.0)
    lost = Prior(np.zeros(3), np.diag([4.0, 4.0, 1.0]), G.kidnap_weight, 5000.0)
    odds = lost.log(early.pose) - lost.log(None, 1.0)
    assert decide([early], window, keys, lost, G).llr == pytest.approx(12.0 + odds)
    other = _track(20.0, [unseen - 1.0] * 6 + [unseen + 3.0] * 4)
    v = decide([early, other], window, keys, lost, G)
    assert v.leader is other
    e_other = 6 * (unseen - 1.0) + 4 * (unseen + 3.0) + lost.log(other.pose)
    e_early = 6 * (unseen - 4.0) + 4 * (unseen + 3.0) + lost.log(early.pose)
    e_null = 6 * (unseen - 1.0) + 4 * unseen + lost.log(None, 1.0)
    assert v.llr == pytest.approx(e_other - math.log(math.exp(e_early) + math.exp(e_null)))
