"""Evidence over a drive (service/core/reloc/evidence.py): keyframes, back-scoring of hypotheses on
the scans before a search found them, the evidence margin and the pruning that keeps a judged
hypothesis before unjudged newcomers."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from service.core.pose import compose
from service.core.reloc import evidence as ev
from service.core.reloc import global_search as gs
from service.core.reloc import hypotheses as hy
from service.core.reloc.global_config import GlobalConfig
from service.core.sensor import pose_scoring as ps
from service.core.types import wrap_angle


def _track(pose: np.ndarray, cost: float = 0.5) -> hy.Track:
    p = np.asarray(pose, dtype=float)
    return hy.Track(p.copy(), [cost], gs.Hypothesis(pose=p.copy(), cost=cost))


def _frame(key: int, travel: float, heading: float = 0.0) -> ev.Keyframe:
    return ev.Keyframe(
        key=key,
        ranges=np.ones(4),
        angles=np.linspace(-1.0, 1.0, 4),
        points=np.ones((4, 2)),
        odom=np.array([travel, 0.0, heading]),
        travel=travel,
    )


def test_keyframes_every_spacing_or_turn_and_a_bounded_window() -> None:
    g = GlobalConfig(evidence_spacing=0.3, evidence_turn=0.3, evidence_span=1.0, evidence_frames=4)
    frames: list[ev.Keyframe] = []
    assert ev.keyframe_due(frames, np.zeros(3), 0.0, g)  # the first scan always
    frames.append(_frame(0, 0.0))
    assert not ev.keyframe_due(frames, np.array([0.2, 0.0, 0.1]), 0.2, g)
    assert ev.keyframe_due(frames, np.array([0.3, 0.0, 0.0]), 0.3, g)  # driven
    assert ev.keyframe_due(frames, np.array([0.0, 0.0, -0.35]), 0.0, g)  # turned in place
    many = [_frame(k, 0.3 * k) for k in range(10)]
    win = ev.window(many, g)
    assert [f.key for f in win] == [6, 7, 8, 9]  # within 1 m of the newest, at most 4
    assert ev.window([], g) == []


def test_backfill_judges_a_hypothesis_on_the_scans_before_it_was_found(
    office_window: Callable,
) -> None:
    """Office floor plan, odometry: a hypothesis at the true pose of the last scan explains
    the keyframes of the last metres (it is moved back by the odometry); one 1.5 m off along
    the robot's heading, which a search could have found on the last scan alone, does not.
    Every track ends up scored on every keyframe, newest first."""
    last = 300
    su, cfg, g, idx, frames = office_window(270, last)
    assert len(frames) >= 6
    truth = su.truth[last]
    off = compose(truth, np.array([1.5, 0.0, 0.0]))
    true_t, off_t = _track(truth), _track(off)
    tracks = [off_t, true_t]
    spent = 0.0

    def pending() -> bool:
        best = ev.evidence(true_t, frames)[0] if ev.complete(true_t, frames) else float("inf")
        return not all(ev.complete(t, frames) or ev.dropped(t, frames, best, g) for t in tracks)

    while pending():
        step = ev.backfill(idx, tracks, frames, su.odom[last], cfg, g, limit=5.0)
        assert step > 0
        spent += step
        # breadth first: no track holds an older keyframe while another lacks a newer one
        for k in range(len(frames) - 1):
            older, newer = frames[k].key, frames[k + 1].key
            if any(older in t.ev for t in tracks):
                assert all(newer in t.ev or ev.dropped(t, frames, 0.0, g) for t in tracks)
    mean_true, n_true = ev.evidence(true_t, frames)
    mean_off, _ = ev.evidence(off_t, frames)
    assert n_true == len(frames)
    assert mean_true < 0.45, mean_true
    assert mean_off > mean_true + g.drive_margin
    assert ev.median(true_t, frames) <= g.drive_max_cost
    # a second pass has nothing left to score for the complete track
    assert ev.backfill(idx, [true_t], frames, su.odom[last], cfg, g, 100.0) == 0.0
    # the poses it was judged at follow the tour: within 0.3 m of the truth on every keyframe
    for f in frames:
        i = int(np.argmin(np.linalg.norm(su.odom[:, :2] - f.odom[:2], axis=1)))
        assert np.hypot(*(true_t.ev_pose[f.key][:2] - su.truth[i][:2])) < 0.3


def test_evidence_margin_compares_the_same_keyframes_of_distinct_alternatives() -> None:
    g = GlobalConfig(evidence_drop_frames=3)
    frames = [_frame(k, 0.3 * k) for k in range(6)]
    best = _track(np.array([0.0, 0.0, 0.0]))
    best.ev = {k: 0.3 for k in range(6)}
    same = _track(np.array([0.1, 0.0, 0.0]))  # not distinct from best: ignored
    same.ev = {k: 0.1 for k in range(6)}
    far = _track(np.array([5.0, 0.0, 0.0]))
    far.ev = {k: 0.6 for k in range(3, 6)}  # scored on the 3 newest only
    assert abs(ev.evidence_margin(best, [best, same, far], frames, g) - 0.3) < 1e-12
    young = _track(np.array([0.0, 5.0, 0.0]))
    young.ev = {5: 0.9}  # not judged on enough keyframes yet: the margin is unknown
    assert ev.evidence_margin(best, [best, far, young], frames, g) == float("-inf")
    assert ev.evidence_margin(best, [best], frames, g) == float("inf")
    assert (
        ev.leader([best, far, young], frames, g.model_copy(update={"evidence_min_frames": 5}))
        is best
    )
    assert ev.leader([best], frames, g.model_copy(update={"evidence_min_frames": 7})) is None


def test_prune_keeps_a_judged_track_before_unjudged_newcomers() -> None:
    """A search delivers ten newcomers with better single-scan costs than the track that has
    explained the whole window; the old track stays, the newcomers are kept apart until
    judged, and tracks that explain nearly nothing or are clearly worse go."""
    g = GlobalConfig(evidence_drop=0.3, evidence_junk=0.95, evidence_drop_frames=3)
    frames = [_frame(k, 0.3 * k) for k in range(6)]
    old = _track(np.array([0.0, 0.0, 0.0]), cost=0.6)
    old.ev = {k: 0.45 for k in range(6)}
    worse = _track(np.array([3.0, 0.0, 0.0]), cost=0.3)
    worse.ev = {k: 0.8 for k in range(6)}  # 0.35 worse than old
    junk = _track(np.array([6.0, 0.0, 0.0]), cost=0.3)
    junk.ev = {5: 1.0, 4: 1.0, 3: 0.97}
    fresh = [_track(np.array([10.0 + k, 0.0, 0.0]), cost=0.2) for k in range(10)]
    kept = ev.prune([old, worse, junk, *fresh], frames, keep=8, g=g)
    assert old in kept
    assert worse not in kept and junk not in kept
    assert sum(t in kept for t in fresh) == 8
    assert kept == sorted(kept, key=lambda t: (t.hyp.cost, -t.age))
    # one per pose: a newcomer on the old track's pose is not kept beside it
    twin = _track(np.array([0.05, 0.0, 0.0]), cost=0.1)
    assert twin not in ev.prune([old, twin], frames, keep=8, g=g)


def test_prune_keeps_the_copy_of_a_place_that_explains_its_keyframes_better() -> None:
    """Two tracks at one place: an old one, slid a little, whose back-scored keyframes are
    poor, and a fresh one a search found at the same place, scored better on the keyframes
    both have. The fresh one stays (the slid one would make the place lose the drive to an
    alias); a fresh copy only slightly better, or judged on too few keyframes, does not
    replace the judged track."""
    g = GlobalConfig(evidence_drop=0.3, evidence_junk=0.95, evidence_drop_frames=3)
    frames = [_frame(k, 0.3 * k) for k in range(8)]
    slid = _track(np.array([0.0, 0.0, 0.0]), cost=0.6)
    slid.ev = {k: 0.7 for k in range(8)}
    alias = _track(np.array([8.0, 0.0, np.pi]), cost=0.45)
    alias.ev = {k: 0.5 for k in range(8)}
    fresh = _track(np.array([0.2, 0.0, 0.05]), cost=0.3)
    fresh.ev = {k: 0.3 for k in range(5, 8)}
    kept = ev.prune([slid, alias, fresh], frames, keep=8, g=g)
    assert fresh in kept and slid not in kept and alias in kept
    close = _track(np.array([0.2, 0.0, 0.05]), cost=0.3)
    close.ev = {k: 0.6 for k in range(5, 8)}  # better by 0.1 < evidence_drop / 2
    kept = ev.prune([slid, alias, close], frames, keep=8, g=g)
    assert slid in kept and close not in kept
    early = _track(np.array([0.2, 0.0, 0.05]), cost=0.3)
    early.ev = {7: 0.2, 6: 0.2}  # two keyframes: not judged yet
    kept = ev.prune([slid, alias, early], frames, keep=8, g=g)
    assert slid in kept and early not in kept


def test_prune_keeps_the_best_fit_to_the_scans_whatever_its_drive() -> None:
    """Nine fully judged tracks and one room to keep eight: the one that fits the scans at
    hand best (the robot started where the map explains little, so its early keyframes are
    poor) is kept although eight others have a better mean over the drive; without it, the
    decision would rank the runner-up first. The mean still orders the rest."""
    g = GlobalConfig(evidence_drop=0.3, evidence_junk=0.95, evidence_drop_frames=3)
    frames = [_frame(k, 0.3 * k) for k in range(10)]
    others = []
    for k in range(8):
        t = _track(np.array([5.0 * (k + 1), 0.0, 0.0]), cost=0.3 + 0.01 * k)
        t.ev = {f: 0.35 + 0.01 * k for f in range(10)}
        others.append(t)
    true = _track(np.array([0.0, 0.0, 0.0]), cost=0.11)
    true.ev = {f: (0.75 if f < 5 else 0.15) for f in range(10)}  # mean 0.45: ninth
    kept = ev.prune([*others, true], frames, keep=8, g=g)
    assert len(kept) == 8 and true in kept
    assert kept[0] is true  # ordered by decision cost
    assert others[-1] not in kept  # the worst mean over the drive made room
    # a track both worst on the drive and not the best fit is still let go
    true.hyp.cost = 0.5
    assert true not in ev.prune([*others, true], frames, keep=8, g=g)


def test_a_single_scan_winner_is_beaten_by_an_alternative_that_explains_the_drive_better() -> None:
    """A single-scan winner and a distinct alternative scored on the same keyframes: the
    winner is beaten while the alternative's mean over them is lower; not when it is higher,
    nor by a copy at the winner's own place, nor by an alternative judged on fewer than
    ``evidence_drop_frames`` of the winner's keyframes."""
    g = GlobalConfig(evidence_drop_frames=3)
    frames = [_frame(k, 0.3 * k) for k in range(6)]
    best = _track(np.array([0.0, 0.0, 0.0]), cost=0.37)
    best.ev = {k: 0.52 for k in range(6)}
    alias = _track(np.array([5.4, 0.0, 0.0]), cost=0.41)
    for theirs, want in ((0.46, True), (0.51, True), (0.53, False), (0.70, False)):
        alias.ev = {k: theirs for k in range(6)}
        assert ev.beaten(best, [best, alias], frames, g) is want, theirs
    copy = _track(np.array([0.1, 0.0, 0.02]), cost=0.3)
    copy.ev = {k: 0.30 for k in range(6)}
    assert not ev.beaten(best, [best, copy], frames, g)
    alias.ev = {4: 0.30, 5: 0.30}  # two keyframes: not judged yet
    assert not ev.beaten(best, [best, alias], frames, g)
    alias.ev = {k: 0.30 for k in range(2, 6)}  # four of the winner's six: judged
    assert ev.beaten(best, [best, alias], frames, g)


def test_a_short_return_counts_by_how_far_in_front_of_the_predicted_wall_it_lies() -> None:
    """``GlobalConfig.evidence_short_scale`` (floor plans: 1 m): with the flat credit a
    return 0.5 m in front of the predicted wall (furniture along the wall of its room) and
    one 4 m in front of it (a pose that puts the walls far behind the returns) count the
    same; graded, the first counts exp(-0.5) of a short return, the second exp(-4)."""
    g = GlobalConfig.for_kind("schematic")
    assert g.evidence_short_scale == 1.0
    r = np.full(10, 2.0)
    near, far = np.full(10, 2.5), np.full(10, 6.0)
    tol = 0.2
    flat = [ps._beam_fractions(r, pred, tol, g) for pred in (near, far)]
    assert flat[0] == flat[1] == (0.0, 0.0, 1.0)
    graded = [ps._beam_fractions(r, p, tol, g, short_scale=1.0) for p in (near, far)]
    assert graded[0][2] == pytest.approx(np.exp(-0.5))
    assert graded[1][2] == pytest.approx(np.exp(-4.0))
    # hits, violations and beams with nothing predicted are counted as before
    mixed = ps._beam_fractions(
        np.array([5.0, 9.0, 3.0, 1.0]), np.array([5.1, 5.0, np.nan, 2.0]), tol, g, short_scale=1.0
    )
    assert mixed == pytest.approx((0.25, 0.25, np.exp(-1.0) / 4))


def test_window_polish_pins_the_pose_on_the_keyframes_of_the_drive(office_window: Callable) -> None:
    """``GlobalConfig.window_polish``: a winner 0.25 m and 3 degrees off is polished on the
    points of the window's keyframes at once, each placed by the odometry, and lands within
    5 cm and 1.5 degrees of the true pose (office floor plan, the tour's scans 270-300)."""
    last = 300
    su, _cfg, g, idx, frames = office_window(270, last)
    truth = su.truth[last]
    for off in ([0.25, 0.0, 0.05], [0.0, -0.2, -0.05], [-0.15, 0.15, 0.0]):
        start = compose(truth, np.array(off))
        got = ev.window_polish(idx, start, frames, su.odom[last], g)
        assert np.hypot(*(got[:2] - truth[:2])) < 0.05, (off, got, truth)
        assert abs(wrap_angle(float(got[2] - truth[2]))) < np.deg2rad(1.5), (off, got, truth)


def test_a_track_found_again_at_a_better_pose_takes_it_and_is_judged_again(
    office_window: Callable,
) -> None:
    """``GlobalConfig.refound_margin`` (opt-in, at 0.1): a kept track whose keyframe
    scores were taken at a pose the distance field's polish left off (here 0.3 m along the
    heading, its newest keyframe costing 0.6) takes the pose a later search found it at when
    that pose explains the newest keyframe 0.1 better, and its keyframe scores are dropped
    (``backfill`` redoes them); a search pose that explains less, or one within 5 cm and 1
    degree, changes nothing; at 0 nothing is checked (office floor plan, scans 270-300)."""
    last = 300
    su, cfg, g0, idx, frames = office_window(270, last)
    g = g0.model_copy(update={"refound_margin": 0.1})
    truth = su.truth[last]
    odom = su.odom[last]
    kf = frames[-1]
    off = compose(truth, np.array([0.3, 0.0, 0.0]))

    biased = _track(off)
    biased.ev[kf.key], biased.ev_pose[kf.key], biased.ev_odom[kf.key] = 0.6, off, kf.odom
    spent = ev.adopt_refound(idx, [(biased, truth.copy())], frames, odom, cfg, g, limit=100.0)
    assert spent > 0.0
    assert np.allclose(biased.pose, truth)
    assert biased.ev == {} and biased.ev_pose == {} and biased.ev_odom == {}

    right = _track(truth)
    ev.backfill(idx, [right], frames, odom, cfg, g, limit=1e9)
    scores = dict(right.ev)
    assert scores[kf.key] < 0.2
    ev.adopt_refound(idx, [(right, off)], frames, odom, cfg, g, limit=100.0)
    assert np.allclose(right.pose, truth) and right.ev == scores

    near = compose(truth, np.array([0.03, 0.0, 0.01]))
    assert ev.adopt_refound(idx, [(right, near)], frames, odom, cfg, g, limit=100.0) == 0.0
    assert np.allclose(right.pose, truth)

    off_g = g.model_copy(update={"refound_margin": 0.0})
    kept = _track(off)
    kept.ev[kf.key] = 0.6
    assert ev.adopt_refound(idx, [(kept, truth.copy())], frames, odom, cfg, off_g, 100.0) == 0.0
    assert np.allclose(kept.pose, off)
