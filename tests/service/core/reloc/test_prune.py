"""The tracks a drive lets go (service.core.reloc.drive.prune): a track trailing the leader by
evidence_drop nats on the frames both were scored on goes, one closer stays; one trailing the
unseen place by as much goes, the unseen place weighed as the decision weighs it."""

from __future__ import annotations

import numpy as np

from service.core.reloc.config import GlobalConfig
from service.core.reloc.drive import EVIDENCE_DROP, Frame, Track, prune
from service.core.reloc.global_search import Hypothesis


def _frames(n: int) -> tuple[list[Frame], list[int]]:
    empty = np.zeros(0)
    frames = [Frame(k, empty, empty, np.zeros((0, 2)), np.zeros(3), 0.3 * k) for k in range(n)]
    return frames, list(range(n))


def _track(x: float, per_frame: float, frames: int) -> Track:
    pose = np.array([x, 0.0, 0.0])
    return Track(pose, Hypothesis(pose.copy(), 0.3), ll={k: per_frame for k in range(frames)})


def test_a_track_trailing_the_leader_by_evidence_drop_in_all_goes() -> None:
    g = GlobalConfig.for_kind("schematic")
    n = 10
    frames, keys = _frames(n)
    leader = _track(0.0, -1.0, n)
    # 7 nats a frame behind (a mean beam cost 0.35 worse) over 10 frames: 70 > evidence_drop
    behind = _track(5.0, -8.0, n)
    # 4 nats a frame behind: 40 in all, within evidence_drop
    close = _track(10.0, -5.0, n)
    kept = prune([leader, behind, close], frames, keys, leader, g)
    assert EVIDENCE_DROP == 60.0
    assert leader in kept and close in kept
    assert behind not in kept


def test_a_track_trailing_the_unseen_place_goes_as_the_decision_weighs_it() -> None:
    """The unseen place's cost on a frame rises where the map's walls stand far (null_slope):
    the true place explains less there. A track is let go only if it trails the unseen place
    so weighed, as in the decision, not the flat null_cost (mit-csail's floor plan: the true
    place, found after 6 m, went on its first scan over the window)."""
    g = GlobalConfig.for_kind("schematic")
    assert g.null_cost == 0.7 and g.null_slope > 0.0
    n = 12
    frames, keys = _frames(n)
    # 19 nats a frame (the clip): 228 in all, 72 below the flat unseen place (13 a frame)
    far, near = _track(0.0, -19.0, n), _track(5.0, -19.0, n)
    far.null = {k: 0.9 for k in keys}  # far walls: the unseen place at 17 a frame, 204 in all
    near.null = {k: 0.7 for k in keys}
    kept = prune([far, near], frames, keys, None, g)
    assert far in kept
    assert near not in kept


def test_after_a_loss_the_unseen_place_lets_go_of_a_track_on_the_window_only() -> None:
    """After a loss, a track that followed the robot through a corridor the map lacks (16
    keyframes at the clip, 6 nats a frame below the unseen place, 96 in all) and explains the
    window's 4 better (4 nats a frame above) is kept, as the decision judges it; a first search,
    or the same frames all still in the window, let it go."""
    g = GlobalConfig.for_kind("schematic")
    n = 20
    frames, keys = _frames(n)
    t = _track(0.0, -19.0, n)
    t.ll.update({k: -9.0 for k in range(16, n)})
    t.null = {k: 0.7 for k in keys}
    assert t in prune([t], frames[16:], keys, None, g, lost=True)
    assert t not in prune([t], frames[16:], keys, None, g)
    assert t not in prune([t], frames, keys, None, g, lost=True)
