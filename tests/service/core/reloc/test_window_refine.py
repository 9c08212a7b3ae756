"""The verdict's refinement (service/core/reloc/window_refine.py): a track's keyframe poses moved
as one rigid body to where the drive's beams fit them best, spread over calls within a work
budget, resumable after a pickle."""

from __future__ import annotations

import pickle
from collections.abc import Callable

import numpy as np

from service.core.reloc import evidence as ev
from service.core.reloc import global_search as gs
from service.core.reloc import hypotheses as hy
from service.core.reloc import window_refine as wr
from service.core.reloc.global_config import GlobalConfig


def _scored_track(idx, su, frames, cfg, g, offset):  # type: ignore[no-untyped-def]
    """A track whose pose on every keyframe is the truth there moved by the world-frame
    ``offset``, scored on every keyframe (as the drive's back-scoring leaves one that a
    distance-field polish held off the place)."""
    last = su.truth[-1]
    t = hy.Track(last.copy(), [0.5], gs.Hypothesis(pose=last.copy(), cost=0.5))
    for f in frames:
        i = int(np.argmin(np.linalg.norm(su.odom[:, :2] - f.odom[:2], axis=1)))
        pose = su.truth[i] + np.asarray(offset, dtype=float)
        t.ev[f.key] = ev.frame_cost(idx, pose, f, cfg, g)
        t.ev_pose[f.key] = pose
        t.ev_odom[f.key] = f.odom
    t.pose = su.truth[_index_of(su, frames[-1])] + np.asarray(offset, dtype=float)
    return t


def _index_of(su, f: ev.Keyframe) -> int:  # type: ignore[no-untyped-def]
    return int(np.argmin(np.linalg.norm(su.odom[:, :2] - f.odom[:2], axis=1)))


def test_rigid_move_turns_about_the_pivot_and_translates() -> None:
    pose = np.array([2.0, 1.0, 0.3])
    got = wr.moved(pose, np.array([1.0, 1.0]), np.array([0.5, -0.2, np.pi / 2]))
    assert np.allclose(got, [1.5, 1.8, 0.3 + np.pi / 2])
    assert np.allclose(wr.moved(pose, np.zeros(2), np.zeros(3)), pose)


def test_a_track_held_off_the_place_is_moved_onto_it_and_judged_there(
    office_window: Callable,
) -> None:
    """Office floor plan, the tour's scans 270-300: a track whose keyframe poses all sit
    0.23 m off the truth costs clearly more than the truth; refined, its poses are within
    6 cm of the truth on every keyframe and its mean cost is the truth's within 0.03. A
    track already at the truth is not moved (no shift gains ``_MIN_GAIN`` there). The pose
    the track goes on from is moved with its keyframes."""
    su, cfg, g, idx, frames = office_window(270, 300)
    assert len(frames) >= 6
    truth = _scored_track(idx, su, frames, cfg, g, [0.0, 0.0, 0.0])
    held = _scored_track(idx, su, frames, cfg, g, [0.12, 0.2, 0.0])
    at_truth = ev.evidence(truth, frames)[0]
    before = ev.evidence(held, frames)[0]
    assert before > at_truth + 0.05, (before, at_truth)
    ref = wr.Refinement(queue=[truth, held], frames=list(frames))
    spent, done = wr.advance(ref, idx, cfg, g, 0.0, float("inf"))
    assert done and spent > 0.0
    for f in frames:
        i = _index_of(su, f)
        assert np.hypot(*(held.ev_pose[f.key][:2] - su.truth[i][:2])) < 0.06, f.key
        assert np.array_equal(truth.ev_pose[f.key], su.truth[i]), f.key
    after = ev.evidence(held, frames)[0]
    assert after < at_truth + 0.03, (after, at_truth)
    assert np.hypot(*(held.pose[:2] - su.truth[_index_of(su, frames[-1])][:2])) < 0.06
    # the scores written are the beams' cost at the poses written
    for f in frames:
        assert abs(held.ev[f.key] - ev.frame_cost(idx, held.ev_pose[f.key], f, cfg, g)) < 1e-12


def test_spread_over_calls_and_pickled_midway_it_ends_where_one_call_ends(
    office_window: Callable,
) -> None:
    """Work is counted and bounded per call (at least one probe each); a refinement pickled
    between calls (a localiser moved to another worker) resumes; both end with the same
    poses and scores as one unbounded call."""
    su, cfg, g, idx, frames = office_window(270, 300)
    whole = _scored_track(idx, su, frames, cfg, g, [0.1, -0.15, 0.03])
    wr.advance(wr.Refinement(queue=[whole], frames=list(frames)), idx, cfg, g, 0.0, np.inf)

    part = _scored_track(idx, su, frames, cfg, g, [0.1, -0.15, 0.03])
    ref = wr.Refinement(queue=[part], frames=list(frames))
    calls, done = 0, False
    while not done:
        spent, done = wr.advance(ref, idx, cfg, g, 40.0, 50.0)
        assert spent > 40.0
        calls += 1
        ref = pickle.loads(pickle.dumps(ref))
        part = ref.queue[0]
    assert calls > 3
    assert all(np.allclose(part.ev_pose[k], whole.ev_pose[k]) for k in whole.ev_pose)
    assert part.ev == whole.ev


def test_start_queues_the_winner_and_its_closest_distinct_rivals() -> None:
    """The winner first, then distinct alternatives within ``evidence_drop`` of its mean,
    closest first, at most ``verdict_refine_tracks``; a copy at the winner's place, a track
    judged on too few keyframes and one clearly worse are left out."""
    g = GlobalConfig(evidence_drop_frames=3, evidence_drop=0.3, verdict_refine_tracks=2)
    frames = [
        ev.Keyframe(k, np.ones(4), np.zeros(4), np.ones((4, 2)), np.array([0.3 * k, 0, 0]), 0.3 * k)
        for k in range(6)
    ]

    def track(x: float, mean: float, keys: range = range(6)) -> hy.Track:
        p = np.array([x, 0.0, 0.0])
        t = hy.Track(p.copy(), [mean], gs.Hypothesis(pose=p.copy(), cost=mean))
        t.ev = {k: mean for k in keys}
        return t

    best = track(0.0, 0.30)
    copy = track(0.1, 0.20)
    near, nearer, third = track(5.0, 0.40), track(9.0, 0.33), track(13.0, 0.45)
    worse, young = track(17.0, 0.70), track(21.0, 0.31, range(4, 6))
    ref = wr.start(best, [best, copy, near, worse, young, third, nearer], frames, g)
    assert ref.queue == [best, nearer, near]
    assert wr.start(best, [best], frames, g).queue == [best]
