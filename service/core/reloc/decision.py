"""The one decision rule of relocalisation: a log-likelihood ratio of the best place against
the rest, over the drive's frames, with a prior.

A hypothesis' evidence is ``E_h = sum_k L_h,k + log pi(h)``: its log-likelihoods (nats) on the
drive's frames (:mod:`.drive`) and its prior. The *rest* are the distinct alternatives and the
*unseen place* (what the search has not found), which explains every frame at ``null_cost``;
after a loss, only the window's, and a keyframe that left it as the leader. The leader, the
largest ``E`` among the tracks scored on every frame, wins when

    LLR = E_leader - log(sum over the rest of exp(E_a))  >=  fix_llr,

the posterior odds of the leader against everything else. An alternative not yet scored on a
keyframe counts there as the leader (it can only lower the LLR); on a plain scan from before
it was found, as its own mean. The prior (:class:`Prior`): uniform while nothing is known;
after a loss the dead-reckoned Gaussian, ``kidnap_weight`` spread over the map, its mass no
track holds the unseen place's (a corridor the map lacks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from service.core import numeric
from service.core.pose import mahalanobis2, propagate
from service.core.reloc.config import GlobalConfig
from service.core.reloc.drive import Frame, Track, judged
from service.core.reloc.global_search import COST_FLOOR, DISTINCT_ANGLE, DISTINCT_DISTANCE, distinct
from service.core.sensor.scoring import EFFECTIVE_BEAMS


@dataclass
class Prior:
    """Where the robot may be before the scans say: ``mean`` / ``cov`` the last pose (``None``:
    uniform), dead-reckoned by wheel odometry if ``carried``, ``kidnap`` the share of the
    mass spread evenly over ``cells`` places (free area x 2 pi / a place's volume)."""

    mean: np.ndarray | None
    cov: np.ndarray | None
    kidnap: float
    cells: float
    carried: bool = False

    def gaussian_mass(self, pose: np.ndarray) -> float:
        """The dead-reckoned Gaussian's mass in the place ``pose`` (0 while uniform)."""
        if self.mean is None or self.cov is None:
            return 0.0
        det = max(numeric.det3(self.cov), 1e-300)
        density = math.exp(-0.5 * mahalanobis2(pose, self.mean, self.cov))
        return min(1.0, density / math.sqrt((2.0 * math.pi) ** 3 * det) * CELL_VOLUME)

    def log(self, pose: np.ndarray | None, held: float = 0.0) -> float:
        """Log prior mass (nats) of the place ``pose`` (a cell of :data:`CELL_VOLUME`); ``None``:
        of the places the search has not found, ``held`` the Gaussian's mass the found hold."""
        mass = self.gaussian_mass(pose) if pose is not None else max(0.0, 1.0 - held)
        uniform = self.kidnap / max(self.cells, 1.0)
        return math.log((1.0 - self.kidnap) * mass + uniform + 1e-300)

    def moved(self, delta: np.ndarray, noise: np.ndarray) -> Prior:
        """The prior after a robot-frame motion ``delta`` with process noise ``noise``."""
        if self.mean is None or self.cov is None:
            return self
        mean, cov = propagate(self.mean, self.cov, delta, noise)
        return replace(self, mean=mean, cov=cov)


@dataclass(frozen=True)
class Verdict:
    """The ``leader`` scored on the whole window (or ``None``), its ``llr`` (nats) against the
    rest, and against the ``unseen`` place alone (the difference: what the places found cost)."""

    leader: Track | None
    llr: float
    unseen: float = -math.inf

    @property
    def ambiguity(self) -> float:
        """The posterior probability that the leader is not the place: ``1 / (1 + e^llr)``."""
        if self.leader is None:
            return 1.0
        return 1.0 / (1.0 + math.exp(min(max(self.llr, -700.0), 700.0)))


#: Volume (m² rad) of one distinct place: a disc of DISTINCT_DISTANCE by twice DISTINCT_ANGLE.
CELL_VOLUME = math.pi * DISTINCT_DISTANCE**2 * 2.0 * DISTINCT_ANGLE


def decide(
    tracks: list[Track], frames: list[Frame], keys: list[int], prior: Prior, g: GlobalConfig
) -> Verdict:
    """The leader of ``tracks`` and its LLR against the rest (module docstring), summed over
    the frames ``keys``. The leader must be scored on the window's frames that
    :func:`.drive.judged` names; a frame it lacks otherwise counts as the unseen place's."""
    need = judged(frames)
    full = [t for t in tracks if all(k in t.ll for k in need)]
    if not frames or not full:
        return Verdict(None, -math.inf)
    unseen = -EFFECTIVE_BEAMS * (g.null_cost - COST_FLOOR)
    plain = {f.key for f in frames if f.odom is None}

    def evidence(t: Track, fill: Track | None = None) -> float:
        own = [t.ll[k] for k in keys if k in t.ll]
        rate = sum(own) / len(own) if own else unseen
        # the leader (fill) lends the frames this track lacks
        lent = {k: rate if k in plain else fill.ll.get(k, unseen) for k in keys} if fill else {}
        return sum(t.ll.get(k, lent.get(k, unseen)) for k in keys) + prior.log(t.pose)

    best_e, leader = max(((evidence(t), t) for t in full), key=lambda x: x[0])
    # the unseen place: as the true place in the leader's region; after a loss, before the window
    # as the leader (the corridor that lost it is no evidence for a place elsewhere); its prior:
    # a place's kidnap share and, if fixes are final, the dead-reckoned mass left
    lost = prior.mean is not None
    gone = {k: leader.ll[k] for k in set(leader.ll) - {f.key for f in frames}} if lost else {}
    null = sum(
        gone.get(k, -EFFECTIVE_BEAMS * (leader.null.get(k, g.null_cost) - COST_FLOOR)) for k in keys
    )
    final = prior.carried and not g.probation_travel  # floor plans' probation guards theirs
    null += prior.log(None, sum(prior.gaussian_mass(t.pose) for t in tracks) if final else 1.0)
    rest = [null] + [
        evidence(t, fill=leader)
        for t in tracks
        if t is not leader and distinct(t.pose, leader.pose)
    ]
    top = max(rest)
    return Verdict(
        leader, best_e - top - math.log(sum(math.exp(e - top) for e in rest)), best_e - null
    )
