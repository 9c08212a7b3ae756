"""Evidence over a drive for the budgeted multi-hypothesis search (global localisation with
odometry): every kept hypothesis is judged on the same scans of the last metres driven,
including the scans taken before a search found it.

Why. A search runs on the scan at hand, so a hypothesis it finds is good *now*; a place along
a corridor with a repeating pattern of doors, or the twin of a room, can be as good now as the
true place while the drive so far tells them apart. Re-scoring only from the scan a hypothesis
appeared on (the rule before this module: the last 10 re-scored scans) compared an old true
hypothesis with a young alias on the alias' terms; on the tuning log fr079 (schematised map)
a true hypothesis that had explained 40 scans lost its lead to an alias 4.4 m along the
corridor that fitted the last 10 scans better, and was pruned. With odometry the hypothesis'
pose implies where the robot stood on every earlier scan, so it can be scored there
(*back-scored*): 16 keyframes over the last 4.9 m gave the true place a mean cost of 0.39 and
the alias 0.55 (a margin of 0.16 per keyframe), where the last scans ranked the alias first.

What.

* :class:`Keyframe` — a scan kept while searching, when the robot has moved
  ``GlobalConfig.evidence_spacing`` or turned ``evidence_turn`` since the last one: its beams
  (the verification's subsample), a subsample of its points (for the polish) and its odometry
  pose. The window holds the keyframes within ``evidence_span`` metres of travel of the newest
  (at most ``evidence_frames``).
* :func:`backfill` — scores each track on the window's keyframes it has no score for, newest
  first: its pose there is the pose at the next newer keyframe (or its current pose) moved
  back by the odometry between them, polished on the distance field with that pose as the
  motion prior (as the re-scoring does, so odometry drift over the window is absorbed a
  keyframe at a time), and verified beam by beam (the cost of
  :func:`service.core.sensor.pose_scoring.verify`, clipped at ``evidence_clip``). Work is counted
  in reference ms and bounded per scan. A track whose evidence is already clearly worse than
  the best complete one (``evidence_drop``) is not scored further.
* :func:`evidence` / :func:`evidence_margin` — a track's mean cost over the window and how
  much better the best track explains the window than every distinct alternative, on the
  same keyframes.

Units: metres, radians; poses ``[x, y, theta]`` in the map frame, odometry poses in the
odometry frame.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from service.core.pose import compose, invert, transform_points
from service.core.reloc.global_config import GlobalConfig
from service.core.reloc.global_search import WORK_MS, _distinct, _near, beams_ms, polish_ms
from service.core.reloc.hypotheses import Track
from service.core.reloc.view_index import ViewIndex
from service.core.sensor.pose_scoring import (
    _beam_cost,
    _beam_fractions,
    _polish,
    _predict,
    _subsample,
)
from service.core.tracking.localizer import ShapeConfig
from service.core.types import wrap_angle

#: Polish stages (step m, step rad) of a track's first keyframe: +-0.43 m / +-10 degrees.
_WIDE = ((0.15, 0.06), (0.05, 0.02), (0.015, 0.006))


@dataclass(eq=False)
class Keyframe:
    """A scan kept as evidence: ``key`` its serial number; ``ranges`` / ``angles`` the
    verification's beams (valid returns only); ``points`` robot-frame return points for the
    polish; ``odom`` the odometry pose; ``travel`` the search's odometry travel (m) there."""

    key: int
    ranges: np.ndarray
    angles: np.ndarray
    points: np.ndarray
    odom: np.ndarray
    travel: float


def make_keyframe(
    key: int,
    ranges: np.ndarray,
    angles: np.ndarray,
    odom: np.ndarray,
    travel: float,
    gconfig: GlobalConfig,
) -> Keyframe:
    """A :class:`Keyframe` of one scan (``ranges`` metres, NaN = no return; ``angles`` radians
    in the robot frame; ``odom`` its odometry pose)."""
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    ok = np.nonzero(np.isfinite(r))[0]
    sel = _subsample(ok, gconfig.verify_beams)
    rr, aa = r[sel].copy(), a[sel].copy()
    pts = np.column_stack([rr * np.cos(aa), rr * np.sin(aa)])
    return Keyframe(
        key=key,
        ranges=rr,
        angles=aa,
        points=_subsample(pts, gconfig.support_points).copy(),
        odom=np.asarray(odom, dtype=np.float64).copy(),
        travel=float(travel),
    )


def keyframe_due(frames: list[Keyframe], odom: np.ndarray, travel: float, g: GlobalConfig) -> bool:
    """Whether a scan at odometry pose ``odom`` and search travel ``travel`` becomes a
    keyframe: the first one, or ``evidence_spacing`` metres driven or ``evidence_turn``
    radians turned since the last one."""
    if not frames:
        return True
    last = frames[-1]
    if travel - last.travel >= g.evidence_spacing:
        return True
    return abs(float(wrap_angle(float(odom[2]) - float(last.odom[2])))) >= g.evidence_turn


def window(frames: list[Keyframe], g: GlobalConfig) -> list[Keyframe]:
    """The keyframes within ``evidence_span`` metres of travel of the newest, at most
    ``evidence_frames`` (oldest first)."""
    if not frames:
        return []
    newest = frames[-1].travel
    out = [f for f in frames if newest - f.travel <= g.evidence_span]
    return out[-g.evidence_frames :]


def pair_ms(index: ViewIndex, g: GlobalConfig) -> float:
    """Work (reference ms) of scoring one track on one keyframe: a one-pose polish, and the
    beams (a verification without its feature check)."""
    return WORK_MS["polish_call"] + polish_ms(g.support_points) + beams_ms(index, g, g.verify_beams)


def frame_cost(
    index: ViewIndex, pose: np.ndarray, kf: Keyframe, config: ShapeConfig, g: GlobalConfig
) -> float:
    """:func:`service.core.sensor.pose_scoring.verify`'s cost of ``pose`` on keyframe ``kf``'s
    beams, clipped at ``evidence_clip`` (one bad keyframe, e.g. a person in front of the
    laser, must not outweigh the rest of the drive), a short return graded by how far in
    front of the predicted wall it lies (``GlobalConfig.evidence_short_scale``)."""
    if kf.ranges.size == 0:
        return g.evidence_clip
    tol = config.support_tolerance
    pred, landed = _predict(index, pose, kf.ranges, kf.angles, tol, config.view_max_range, g)
    hit, viol, short = _beam_fractions(
        kf.ranges, pred, tol, g, landed, short_scale=g.evidence_short_scale
    )
    cost = _beam_cost(hit, viol, short, g) + g.cost_floor
    return float(min(cost, g.evidence_clip))


def _narrow_cost(
    index: ViewIndex, start: np.ndarray, kf: Keyframe, config: ShapeConfig, g: GlobalConfig
) -> tuple[np.ndarray, float]:
    """A pose placed on keyframe ``kf`` (``start``), polished on the distance field with
    ``start`` as the motion prior (``rescore_prior``, as the re-scoring does), and its
    :func:`frame_cost` there."""
    narrow, _ = _polish(index, start[None, :], kf.points, g.fine_scale, prior=g.rescore_prior)
    return narrow[0], frame_cost(index, narrow[0], kf, config, g)


def window_polish(
    index: ViewIndex,
    pose: np.ndarray,
    frames: list[Keyframe],
    odom_now: np.ndarray,
    g: GlobalConfig,
) -> np.ndarray:
    """``pose`` (the robot's now) polished on the distance field with the points of every
    keyframe of ``frames`` at once, each placed by the odometry between it and now
    (``odom_now``): a window that spans metres and turns pins a pose that one scan leaves
    free along a corridor. Stages as a track's first keyframe's (+-0.3 m / +-7 degrees,
    then finer), the field score's scale ``fine_scale``."""
    inv = invert(np.asarray(odom_now, dtype=np.float64))
    pts = np.vstack([transform_points(compose(inv, kf.odom), kf.points) for kf in frames])
    start = np.asarray(pose, dtype=np.float64)[None, :]
    out, _ = _polish(index, start, pts, g.fine_scale, _WIDE)
    return out[0]


def adopt_refound(
    index: ViewIndex,
    refound: list[tuple[Track, np.ndarray]],
    frames: list[Keyframe],
    odom_now: np.ndarray,
    config: ShapeConfig,
    g: GlobalConfig,
    limit: float,
) -> float:
    """A kept track that a finished search found again (``refound``: the track and the
    search's pose, moved to now) takes the search's pose when that differs from its own by
    more than ``refound_offset`` / ``refound_turn`` and, placed on the newest keyframe the
    track was scored on as :func:`backfill` places it, costs ``refound_margin`` less there;
    the track's keyframe scores are then dropped, so :func:`backfill` redoes them from the
    new pose. The re-scoring only polishes a track within +-0.13 m of where the odometry
    moved it, while the search refines its seeds (the kept poses among them) with the
    wider point-to-line fit: a track induced 0.18 m off is otherwise judged off for the whole
    drive. Tracks are checked in ``refound``'s order (the search's, best first) while the
    work stays within ``limit`` reference ms (at least one is checked). Returns the work
    spent."""
    if g.refound_margin <= 0.0 or not frames:
        return 0.0
    spent = 0.0
    inv = invert(np.asarray(odom_now, dtype=np.float64))
    for t, pose in refound:
        d = np.asarray(pose, dtype=np.float64) - t.pose
        if np.hypot(d[0], d[1]) <= g.refound_offset and abs(wrap_angle(d[2])) <= g.refound_turn:
            continue
        scored = [f for f in frames if f.key in t.ev]
        if not scored:
            continue
        if spent > 0.0 and spent + pair_ms(index, g) > limit:
            break
        kf = scored[-1]
        _, cost = _narrow_cost(index, compose(pose, compose(inv, kf.odom)), kf, config, g)
        spent += pair_ms(index, g)
        if cost < t.ev[kf.key] - g.refound_margin:
            t.pose = np.asarray(pose, dtype=np.float64).copy()
            t.ev.clear()
            t.ev_pose.clear()
            t.ev_odom.clear()
    return spent


def median(track: Track, frames: list[Keyframe]) -> float:
    """A track's median cost over the keyframes of ``frames`` it has been scored on."""
    costs = [track.ev[f.key] for f in frames if f.key in track.ev]
    return float(np.median(costs)) if costs else float("inf")


def evidence(track: Track, frames: list[Keyframe]) -> tuple[float, int]:
    """A track's mean cost over ``frames`` it has been scored on, and how many those are
    (``(inf, 0)`` for none)."""
    costs = [track.ev[f.key] for f in frames if f.key in track.ev]
    if not costs:
        return float("inf"), 0
    return float(np.mean(costs)), len(costs)


def dropped(track: Track, frames: list[Keyframe], best: float, g: GlobalConfig) -> bool:
    """Whether ``track`` has been judged on enough keyframes (``evidence_drop_frames``) to
    be let go: worse than the ``best`` fully scored track's mean by ``evidence_drop``, or
    explaining nearly nothing (a mean of at least ``evidence_junk``)."""
    mean, n = evidence(track, frames)
    if n < g.evidence_drop_frames:
        return False
    return mean > best + g.evidence_drop or mean >= g.evidence_junk


def _rank(track: Track, frames: list[Keyframe]) -> tuple[int, float]:
    """Order of tracks still being judged: by their evidence so far, those with none after
    them by their cost."""
    mean, n = evidence(track, frames)
    return (0, mean) if n else (1, track.hyp.cost)


def complete(track: Track, frames: list[Keyframe]) -> bool:
    """Whether ``track`` has a score on every keyframe of ``frames``."""
    return all(f.key in track.ev for f in frames)


def _start_pose(track: Track, kf: Keyframe, odom_now: np.ndarray) -> np.ndarray:
    """Where ``track`` puts the robot at keyframe ``kf``: from its polished pose at the
    nearest newer keyframe it has one for, else from its current pose, moved back by the
    odometry in between."""
    newer = [k for k in track.ev_pose if k > kf.key]
    if newer:
        k = min(newer)
        base, base_odom = track.ev_pose[k], track.ev_odom[k]
    else:
        base, base_odom = track.pose, odom_now
    return compose(base, compose(invert(base_odom), kf.odom))


def backfill(
    index: ViewIndex,
    tracks: list[Track],
    frames: list[Keyframe],
    odom_now: np.ndarray,
    config: ShapeConfig,
    g: GlobalConfig,
    limit: float,
) -> float:
    """Score tracks on the keyframes of ``frames`` (the window) they have no score for,
    newest keyframe first, within ``limit`` reference ms (at least one keyframe of one track
    when anything is missing, so the work always progresses). Breadth first: the newest
    keyframe for every track (in order of their evidence so far, tracks with none by their
    cost), then the next older one, and so on; a track whose mean is worse by
    ``evidence_drop`` than the best complete track's after ``evidence_drop_frames`` keyframes
    is skipped (the caller prunes it). Scores older than the window are forgotten. Returns
    the work spent."""
    keys = {f.key for f in frames}
    for t in tracks:
        for k in [k for k in t.ev if k not in keys]:
            del t.ev[k]
            t.ev_pose.pop(k, None)
            t.ev_odom.pop(k, None)
    if not frames:
        return 0.0
    best = min(
        (evidence(t, frames)[0] for t in tracks if complete(t, frames)), default=float("inf")
    )
    each = pair_ms(index, g)
    spent = 0.0
    ranked = sorted(tracks, key=lambda t: _rank(t, frames))
    # breadth first, newest keyframe first: every track gets its recent keyframes before any
    # gets old ones, so a clearly worse newcomer is dropped after evidence_drop_frames
    for kf in reversed(frames):
        for t in ranked:
            if kf.key in t.ev:
                continue
            if dropped(t, frames, best, g):
                continue
            if spent >= limit:
                return spent
            start = _start_pose(t, kf, odom_now)
            pose, cost = _narrow_cost(index, start, kf, config, g)
            if not t.ev:
                # a track's first keyframe: also a wider polish without a prior, and the pose
                # as given; the one the beams explain best is kept. A hypothesis some degrees
                # off then converges before it is judged (tuning building 16: a twin 0.2 m /
                # 10 degrees from the true pose, back-scored with the narrow polish only,
                # looked 0.3 worse than a mirrored alias and was dropped), while a pose
                # already right is not pulled off by furniture on a floor plan (the
                # distance field's score and the beams disagree there)
                wide, _ = _polish(index, start[None, :], kf.points, g.fine_scale, _WIDE)
                for alt in (wide[0], start):
                    c = frame_cost(index, alt, kf, config, g)
                    if c < cost:
                        pose, cost = alt, c
                spent += 0.5 * polish_ms(len(kf.points)) + 2 * pair_ms(index, g)
            t.ev[kf.key] = cost
            t.ev_pose[kf.key] = pose.copy()
            t.ev_odom[kf.key] = kf.odom
            spent += each
    return spent


def _gaps(
    best: Track, tracks: list[Track], frames: list[Keyframe], g: GlobalConfig
) -> Iterator[tuple[float, int]]:
    """For each distinct alternative to ``best``: its mean cost minus ``best``'s over the
    keyframes of ``frames`` both were scored on, and how many those are."""
    for t in tracks:
        if t is best or not _distinct(t.pose, best.pose, g):
            continue
        mine, theirs, n = _common_means(best, t, frames)
        yield theirs - mine, n


def evidence_margin(
    best: Track, tracks: list[Track], frames: list[Keyframe], g: GlobalConfig
) -> float:
    """How much better ``best`` explains ``frames`` than any distinct alternative: the
    smallest difference of mean costs over the keyframes both were scored on (``inf`` with
    no alternative; ``-inf`` if an alternative has fewer than ``evidence_drop_frames`` of
    them scored: it is not known yet; :func:`backfill` scores every track's newest keyframes
    first)."""
    need = min(g.evidence_drop_frames, len(frames))
    out = float("inf")
    for gap, n in _gaps(best, tracks, frames, g):
        if n < need:
            return float("-inf")
        out = min(out, gap)
    return out


def recent_margin(
    best: Track, tracks: list[Track], frames: list[Keyframe], g: GlobalConfig
) -> float:
    """The evidence rule's second way (``GlobalConfig.drive_recent_frames`` = k): how much
    better ``best`` explains the newest k keyframes of ``frames`` than any distinct
    alternative, each scored on all k (else ``-inf``); also ``-inf`` if an alternative
    explains the window's older keyframes (those both were scored on) better than ``best`` by
    more than ``drive_recent_tie``: the newest keyframes may only settle what the older ones
    left tied, not overrule them (tuning building 1, start 13: a place 15 m off and turned
    180 degrees led the newest 8 keyframes by 0.24, the true place had led the 5 before by
    about 0.37, and the window's mean was a tie)."""
    k = g.drive_recent_frames
    if k <= 0 or len(frames) < k:
        return float("-inf")
    older = _gaps(best, tracks, frames[:-k], g)
    if any(n and gap < -g.drive_recent_tie for gap, n in older):
        return float("-inf")
    out = float("inf")
    for gap, n in _gaps(best, tracks, frames[-k:], g):
        if n < k:
            return float("-inf")
        out = min(out, gap)
    return out


def overturned(best: Track, tracks: list[Track], frames: list[Keyframe], g: GlobalConfig) -> bool:
    """Whether the drive now names a distinct alternative instead of ``best`` by the evidence
    rule's second way (``GlobalConfig.probation_reversal``): the alternative explains the
    newest ``drive_recent_frames`` keyframes (both scored on all of them) better than
    ``best`` by ``drive_recent_margin``, and the keyframes of the whole window that both
    were scored on at least as well."""
    k = g.drive_recent_frames
    if k <= 0 or len(frames) < k:
        return False
    newest = frames[-k:]
    for t in tracks:
        if t is best or not _distinct(t.pose, best.pose, g):
            continue
        mine, theirs, n = _common_means(best, t, newest)
        if n < k or theirs > mine - g.drive_recent_margin:
            continue
        mine_all, theirs_all, _n = _common_means(best, t, frames)
        if theirs_all <= mine_all:
            return True
    return False


def beaten(
    best: Track,
    tracks: list[Track],
    frames: list[Keyframe],
    g: GlobalConfig,
    margin: float = 0.0,
) -> bool:
    """Whether a distinct alternative explains the drive better than ``best``, or not worse
    by ``margin``: its mean cost over the keyframes both were scored on, at least
    ``evidence_drop_frames`` of them (or all of ``frames`` if fewer), is lower than
    ``best``'s + ``margin``."""
    need = min(g.evidence_drop_frames, len(frames))
    return need > 0 and any(n >= need and gap < margin for gap, n in _gaps(best, tracks, frames, g))


def _better_twin(young: Track, old: Track, frames: list[Keyframe], g: GlobalConfig) -> bool:
    """Whether ``young`` stands at ``old``'s place (:func:`_near`) and explains the
    keyframes both were scored on (at least ``evidence_drop_frames``) better by
    ``evidence_drop`` / 2."""
    if not _near(young.pose, old.pose):
        return False
    mine, theirs, n = _common_means(young, old, frames)
    return n >= g.evidence_drop_frames and mine < theirs - 0.5 * g.evidence_drop


def _common_means(a: Track, b: Track, frames: list[Keyframe]) -> tuple[float, float, int]:
    """The mean costs of ``a`` and of ``b`` over the keyframes of ``frames`` both were
    scored on, and how many those are (``nan`` means for none)."""
    common = [f.key for f in frames if f.key in a.ev and f.key in b.ev]
    if not common:
        return float("nan"), float("nan"), 0
    return (
        float(np.mean([a.ev[k] for k in common])),
        float(np.mean([b.ev[k] for k in common])),
        len(common),
    )


def leader(tracks: list[Track], frames: list[Keyframe], g: GlobalConfig) -> Track | None:
    """The track with the lowest mean cost over the window among those scored on every
    keyframe of it, once the window holds ``evidence_min_frames`` keyframes (``None``
    before, or when no track is complete)."""
    if len(frames) < g.evidence_min_frames:
        return None
    full = [t for t in tracks if complete(t, frames)]
    if not full:
        return None
    return min(full, key=lambda t: evidence(t, frames)[0])


def prune(tracks: list[Track], frames: list[Keyframe], keep: int, g: GlobalConfig) -> list[Track]:
    """The tracks to keep, by the drive's evidence: a track clearly worse than the best fully
    scored one (``evidence_drop`` after ``evidence_drop_frames`` keyframes) goes; of the rest
    at most ``keep`` fully scored ones (best evidence first) and ``keep`` still being scored
    (best evidence so far, or best cost), one per pose. A young hypothesis thus never pushes
    out an old one before it has been judged on the same drive. Returns them ordered by
    decision cost (as :func:`service.core.reloc.hypotheses.prune`)."""
    full = [t for t in tracks if frames and complete(t, frames)]
    best = min((evidence(t, frames)[0] for t in full), default=float("inf"))
    live = [t for t in tracks if not dropped(t, frames, best, g)]
    done = sorted((t for t in live if t in full), key=lambda t: evidence(t, frames)[0])

    pending = sorted((t for t in live if t not in full), key=lambda t: _rank(t, frames))
    # two tracks at one place are one hypothesis; the one that explains their common
    # keyframes better stays, even if it is younger (tuning building 5, start 42: a true
    # track slid 0.25 m, back-scored 0.69, shadowed a fresh one at 0.05 m scoring 0.30 on
    # the same keyframes, and a mirrored alias at 0.50 then beat the slid one)
    done = [t for t in done if not any(_better_twin(p, t, frames, g) for p in pending)]
    if done:
        # the best fit to the scans at hand is kept whatever its drive: the decision ranks the
        # kept tracks by it, and a robot that started where the map explains little (clutter,
        # unmapped furniture) has its true place worst on the early keyframes (tuning log
        # intel, start 8708, floor plan: the true place, cost 0.11 against 0.24, keyframes
        # 0.72-0.81 where every place scored poorly, came ninth by the drive's mean and was
        # pruned; the runner-up by cost, 7.2 m off, was then fixed)
        now = min(done, key=lambda t: t.hyp.cost)
        done = [now] + [t for t in done if t is not now]
    out: list[Track] = []
    for group in (done, pending):
        taken = 0
        for t in group:
            if taken >= keep:
                break
            if any(_near(t.pose, o.pose) for o in out):
                continue
            out.append(t)
            taken += 1
    return sorted(out, key=lambda t: (t.hyp.cost, -t.age))
